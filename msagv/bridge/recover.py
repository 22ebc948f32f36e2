"""``msagv recover``: a recording cut short (a killed process, a full disk) made whole.

A killed writer leaves an MCAP file without its summary and footer (and possibly a chunk
cut in the middle), which the standard readers refuse (``mcap``'s ``make_reader`` needs the
footer; ``rosbags`` and ``ros2 bag`` also need the bag's ``metadata.yaml``).
:func:`repair_mcap` reads such a file record by record with the ``mcap`` library's
streaming reader up to the cut and writes every complete record again (header, schemas,
channels, messages with their times and sequence numbers, metadata) into a complete MCAP
file, which then replaces it; what the cut chunk held (at most the recorder's flush interval,
0.5 s) is lost. :func:`recover_recording` does that for every file of a recording (its
rotated parts and its ROS 2 bag, :mod:`bridge.ros_bag`) and writes the bag's
``metadata.yaml`` anew. A complete file is left as it is.
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from .recording import RecordingError, part_path
from .ros_bag import bag_path, scan_file, write_metadata


@dataclass
class Repaired:
    """What :func:`repair_mcap` found: ``complete`` (nothing to do) or repaired, the
    messages kept, by topic."""

    path: str
    complete: bool
    messages: int = 0
    by_topic: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"path": self.path, "complete": self.complete, "messages": self.messages,
                "by_topic": dict(self.by_topic)}


def is_complete(path: Path) -> bool:
    """True when the standard reader reads the file: a footer, a summary, every message."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            if reader.get_summary() is None:
                return False
            for _ in reader.iter_messages():
                pass
        return True
    except Exception:
        return False


def _count(path: Path) -> Counter:
    from mcap.reader import make_reader

    n: Counter = Counter()
    with open(path, "rb") as f:
        for _, channel, _ in make_reader(f).iter_messages():
            n[channel.topic] += 1
    return n


def repair_mcap(path: str | Path) -> Repaired:
    """Make ``path`` a complete MCAP file (see the module docstring). Raises
    :class:`RecordingError` for a file that is not MCAP at all, or whose recovered copy
    cannot be written (nothing is left behind then)."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such file")
    with open(p, "rb") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise RecordingError(f"{p}: not an MCAP file")
    if is_complete(p):
        n = _count(p)
        return Repaired(str(p), True, sum(n.values()), dict(n))
    tmp = p.with_name(p.name + ".recovering")
    try:
        counts = _rewrite(p, tmp)
    except OSError as e:  # a full disk, a quota, a file-size limit: nothing left behind
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"{p}: cannot write the recovered copy beside it "
                             f"({e.strerror or e}); the recording is unchanged: free some "
                             f"space and run msagv recover again") from None
    os.replace(tmp, p)
    return Repaired(str(p), False, sum(counts.values()), dict(counts))


def _rewrite(p: Path, tmp: Path) -> Counter:
    """Every complete record of ``p`` up to its cut, written as a complete MCAP file to
    ``tmp``; the messages kept, by topic. A write that fails raises OSError."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import Writer

    counts: Counter = Counter()
    with open(p, "rb") as src, open(tmp, "wb") as dst:
        w = None
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        topics: dict[int, str] = {}
        reader = StreamReader(src, skip_magic=False, record_size_limit=1 << 31)
        it = iter(reader.records)
        while True:
            try:
                r = next(it)
            except StopIteration:
                break
            except (McapError, ValueError, KeyError, EOFError, Exception):
                break  # the cut (reading): everything before it is kept
            if isinstance(r, Header):
                w = Writer(dst)
                w.start(profile=r.profile, library=r.library)
            elif w is None:
                break
            elif isinstance(r, Schema):
                if r.id not in schemas:
                    schemas[r.id] = w.register_schema(name=r.name, encoding=r.encoding,
                                                      data=r.data)
            elif isinstance(r, Channel):
                if r.id not in channels:
                    channels[r.id] = w.register_channel(
                        topic=r.topic, message_encoding=r.message_encoding,
                        schema_id=schemas.get(r.schema_id, 0), metadata=dict(r.metadata))
                    topics[r.id] = r.topic
            elif isinstance(r, Message):
                cid = channels.get(r.channel_id)
                if cid is not None:
                    w.add_message(channel_id=cid, log_time=r.log_time,
                                  publish_time=r.publish_time, data=r.data, sequence=r.sequence)
                    counts[topics[r.channel_id]] += 1
            elif isinstance(r, Metadata):
                w.add_metadata(r.name, dict(r.metadata))
        if w is None:
            dst.close()
            tmp.unlink()
            raise RecordingError(f"{p}: no MCAP header (nothing to recover)")
        w.finish()
    return counts


def recording_files(path: str | Path) -> tuple[list[Path], Path | None, list[Path]]:
    """``(parts, bag, bag_files)`` of a recording: its file and rotated parts, its ROS 2
    bag directory (None if there is none) and the bag's storage files in order."""
    p = Path(path)
    parts = [p]
    n = 1
    while part_path(p, n).is_file():
        parts.append(part_path(p, n))
        n += 1
    bag = bag_path(p)
    if not bag.is_dir():
        return parts, None, []
    files = sorted(bag.glob(f"{bag.name}_*.mcap"),
                   key=lambda q: int(q.stem.rsplit("_", 1)[-1])
                   if q.stem.rsplit("_", 1)[-1].isdigit() else -1)
    return parts, bag, files


def recover_recording(path: str | Path) -> dict:
    """Repair every file of a recording and write its bag's ``metadata.yaml``. Returns
    ``{"files": [Repaired dicts], "bag": {"path", "messages", "topics"} | None}``."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such file")
    parts, bag, bag_files = recording_files(p)
    out = {"files": [repair_mcap(q).to_dict() for q in parts + bag_files], "bag": None}
    if bag is not None:
        meta = write_metadata(bag, [scan_file(q) for q in bag_files])
        info = meta["rosbag2_bagfile_information"]
        out["bag"] = {"path": str(bag), "messages": info["message_count"],
                      "topics": len(info["topics_with_message_count"])}
    return out

"""The ROS 2 channels of a recording: a rosbag2 bag (MCAP storage) beside it.

``--record run.mcap`` writes the project's own recording (``run.mcap``, msgpack channels,
:mod:`bridge.recording`) and, beside it, the same run as ROS 2 messages in rosbag2's layout:
the directory ``run_ros2/`` holding ``metadata.yaml`` and ``run_ros2_0.mcap`` (then
``run_ros2_1.mcap``, ... when the recording rotates). The MCAP file has the profile
``ros2``, one ``ros2msg`` schema per type (the definition with its dependencies, from
rosbags' typestore), one ``cdr`` channel per topic with rosbag2's ``offered_qos_profiles``
channel metadata, and the process's header as the metadata ``msagv.header``; so ``ros2 bag
info``, ``rosbags`` and the ``mcap`` reader with ``mcap-ros2-support``'s decoders open it,
and Foxglove draws it. The topics and types are :mod:`bridge.ros_msgs`' (docs/ROS2.md).

:class:`RosBag` runs in a child process of the recording process (:class:`BagProcess`), fed by
the recorder's writer thread with the msgpack payloads it writes
(states, commands, references) and the controller's predicted paths; it decodes them with
:mod:`bridge.messages` and writes the ROS 2 messages with the payload's record time as their
log time (stamps: the vehicle time). ``metadata.yaml`` is written when the child's input
ends (the recording closed, or its process died) and by ``msagv recover``
(:mod:`bridge.recover`) after both were killed.
"""

from __future__ import annotations

import functools
import io
import logging
import os
from pathlib import Path
from typing import Mapping

from msagv.plant.signals import CONTROL_PERIOD

from . import ros_msgs as R

log = logging.getLogger("msagv.recording")

BAG_SUFFIX = "_ros2"
PROFILE = "ros2"
ROSBAG2_VERSION = 9  # rosbag2's metadata version (Jazzy, Kilted)
META_HEADER = "msagv.header"


def bag_path(recording: str | Path) -> Path:
    """The bag directory of a recording: ``run.mcap`` -> ``run_ros2``."""
    p = Path(recording)
    return p.with_name(p.stem + BAG_SUFFIX)


def bag_file(bag: str | Path, n: int) -> Path:
    """The n-th storage file of a bag (rosbag2's naming: ``DIR/DIR_n.mcap``)."""
    b = Path(bag)
    return b / f"{b.name}_{n}.mcap"


# ---- QoS --------------------------------------------------------------------------------------
def qos_profile(topic: str):
    """The QoS a topic is offered with (docs/ROS2.md): reliable, volatile, keep-last 10;
    ``tf`` keep-last 100; the plan keep-last 1 and transient-local (a late subscriber gets
    it, as Nav2's latched topics)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    depth = {R.TF: 100, R.PLAN: 1}.get(topic, 10)
    durability = QosDurability.TRANSIENT_LOCAL if topic == R.PLAN else QosDurability.VOLATILE
    inf = QosTime(9223372036, 854775807)
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, durability, inf, inf,
               QosLiveliness.AUTOMATIC, inf, False)


@functools.lru_cache(maxsize=None)
def qos_yaml(topic: str) -> str:
    """rosbag2's ``offered_qos_profiles`` text (version 9) of a topic."""
    from rosbags.rosbag2.metadata import dump_qos_v9
    from ruamel.yaml import YAML

    out = io.StringIO()
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    yaml.dump(dump_qos_v9([qos_profile(topic)]), out)
    return out.getvalue().strip()


def _yaml_text(obj) -> str:
    from ruamel.yaml import YAML

    out = io.StringIO()
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    yaml.dump(obj, out)
    return out.getvalue()


def bag_metadata(files: list[dict]) -> dict:
    """rosbag2's ``metadata.yaml`` content of a bag in MCAP storage. ``files``: per storage
    file ``{"path", "start", "end", "topics": {topic: (type, count, qos_yaml)}}`` (times in
    ns; topics absolute)."""
    from rosbags.rosbag2.metadata import parse_qos, dump_qos_v9

    topics: dict[str, list] = {}
    for f in files:
        for name, (typ, n, qos) in f["topics"].items():
            if name in topics:
                topics[name][1] += n
            else:
                topics[name] = [typ, n, qos]
    counts = [sum(n for _, n, _ in f["topics"].values()) for f in files]
    starts = [f["start"] for f, n in zip(files, counts) if n]
    ends = [f["end"] for f, n in zip(files, counts) if n]
    start = min(starts) if starts else 0
    end = max(ends) if ends else 0
    return {"rosbag2_bagfile_information": {
        "version": ROSBAG2_VERSION, "storage_identifier": "mcap",
        "relative_file_paths": [Path(f["path"]).name for f in files],
        "duration": {"nanoseconds": max(0, end - start)},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(counts),
        "topics_with_message_count": [
            {"topic_metadata": {"name": name, "type": typ, "serialization_format": "cdr",
                                "offered_qos_profiles": dump_qos_v9(parse_qos(qos)),
                                "type_description_hash": R.type_hash(typ)},
             "message_count": n}
            for name, (typ, n, qos) in topics.items()],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": Path(f["path"]).name,
                   "starting_time": {"nanoseconds_since_epoch": f["start"] if n else 0},
                   "duration": {"nanoseconds": max(0, f["end"] - f["start"]) if n else 0},
                   "message_count": n} for f, n in zip(files, counts)],
        "custom_data": None, "ros_distro": "kilted"}}


def write_metadata(bag: Path, files: list[dict]) -> dict:
    """Write ``metadata.yaml`` (atomically); returns its content."""
    meta = bag_metadata(files)
    tmp = bag / "metadata.yaml.tmp"
    tmp.write_text(_yaml_text(meta))
    os.replace(tmp, bag / "metadata.yaml")
    return meta


def scan_file(path: Path) -> dict:
    """A storage file's entry for :func:`bag_metadata`, read from a complete MCAP file."""
    from mcap.reader import make_reader

    topics: dict[str, list] = {}
    start, end = None, None
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            e = topics.setdefault(channel.topic, [schema.name if schema else "", 0,
                                                  channel.metadata.get("offered_qos_profiles", "")])
            e[1] += 1
            start = message.log_time if start is None else min(start, message.log_time)
            end = message.log_time if end is None else max(end, message.log_time)
    return {"path": str(path), "start": start or 0, "end": end or 0,
            "topics": {k: tuple(v) for k, v in topics.items()}}


# ---- writing ----------------------------------------------------------------------------------
class RosBag(R.RunChannels):
    """The bag of one recording (see the module docstring), written by one thread (the
    child process of :class:`BagProcess`). ``header``: the recording's header (``vehicle``, ``period``,
    ``reference``, ...); ``chunk_size``, ``max_bytes``, ``keep`` as the recorder's."""

    def __init__(self, bag: str | Path, header: Mapping, chunk_size: int = 1 << 20,
                 max_bytes: int | None = None, keep: int = 0, library: str = "msagv"):
        from msagv.plant.vehicle import vehicle_from_dict

        self.path = Path(bag)
        self.header = dict(header)
        super().__init__(vehicle_from_dict(self.header["vehicle"]),
                         float(self.header.get("period") or CONTROL_PERIOD), self.header.get("reference"))
        self._chunk = chunk_size
        self._max_bytes = max_bytes
        self._keep = keep
        self._library = library
        self._part = 0
        self._files: list[dict] = []  # closed parts' entries for metadata.yaml
        self.messages = 0
        self._prepare_dir()
        self._open()

    def _prepare_dir(self) -> None:
        p = self.path
        if p.exists() and not p.is_dir():
            raise OSError(f"{p} exists and is not a directory")
        p.mkdir(parents=True, exist_ok=True)
        # a previous recording of the same name: its files go, as the recording's own file
        # is overwritten
        for q in list(p.glob(f"{p.name}_*.mcap")) + [p / "metadata.yaml"]:
            if q.is_file():
                q.unlink()

    def _open(self) -> None:
        from mcap.writer import Writer

        fp = bag_file(self.path, self._part)
        self._f = open(fp, "wb")
        self._w = Writer(self._f, chunk_size=self._chunk)
        self._w.start(profile=PROFILE, library=self._library)
        import json

        self._w.add_metadata(META_HEADER, {k: json.dumps(v, default=str)
                                           for k, v in self.header.items()})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self._cur = {"path": str(fp), "start": None, "end": None, "topics": {}}

    def _channel(self, topic: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            typ = R.TYPES[topic]
            sid = self._schemas.get(typ)
            if sid is None:
                sid = self._w.register_schema(name=typ, encoding="ros2msg",
                                              data=R.msgdef(typ).encode())
                self._schemas[typ] = sid
            cid = self._w.register_channel(topic="/" + topic, message_encoding="cdr",
                                           schema_id=sid,
                                           metadata={"offered_qos_profiles": qos_yaml(topic)})
            self._channels[topic] = cid
        return cid

    def write(self, topic: str, msg, ts: float) -> None:
        """One typestore message on ``topic`` (relative name) at record time ``ts`` [s]."""
        data = R.encode(msg, R.TYPES[topic])
        cid = self._channel(topic)
        n = self._seq.get(cid, 0)
        self._seq[cid] = n + 1
        t = int(ts * 1e9)
        self._w.add_message(channel_id=cid, log_time=t, publish_time=t, data=data, sequence=n)
        c = self._cur
        c["start"] = t if c["start"] is None else min(c["start"], t)
        c["end"] = t if c["end"] is None else max(c["end"], t)
        e = c["topics"].get("/" + topic)
        if e is None:
            e = c["topics"]["/" + topic] = [R.TYPES[topic], 0, qos_yaml(topic)]
        e[1] += 1
        self.messages += 1

    # ---- files ---------------------------------------------------------------------------
    def flush(self) -> None:
        self._w.flush()
        if self._max_bytes is not None and self._f.tell() >= self._max_bytes:
            self._rotate()

    def _close_part(self) -> None:
        self._w.finish()
        self._f.close()
        c = dict(self._cur)
        c["start"], c["end"] = c["start"] or 0, c["end"] or 0
        c["topics"] = {k: tuple(v) for k, v in c["topics"].items()}
        self._files.append(c)

    def _rotate(self) -> None:
        self._close_part()
        self._part += 1
        if self._keep and len(self._files) >= self._keep:
            old = self._files.pop(0)
            try:
                os.unlink(old["path"])
            except OSError as e:
                log.warning("recording: cannot delete the old bag file %s: %s", old["path"], e)
        self._open()

    def close(self) -> dict:
        """Finish the storage file and write ``metadata.yaml``; returns its content."""
        self._close_part()
        return write_metadata(self.path, self._files)

    def abandon(self) -> None:
        """After a write error: close the file as it is (``msagv recover`` repairs it)."""
        try:
            self._f.close()
        except Exception:
            pass


# ---- the bag writer as a process of its own ----------------------------------------------------
class BagProcess:
    """The :class:`RosBag` of a recording in a child process (``python -m
    msagv.bridge.ros_bag``), fed the recorder's records through a pipe (msgpack-framed):
    the CDR encoding never competes with the control loop for the interpreter (in the
    recording process it cost the real-time demo 10-16 missed periods of 2000). The child
    is in a session of its own (a Ctrl-C at the terminal does not cut its file) and
    finishes the bag - footer, ``metadata.yaml`` - when its input ends: at :meth:`close`,
    or when the recording process dies (a SIGKILL included). Called only from the
    recorder's writer thread."""

    def __init__(self, bag: str | Path, header: Mapping, chunk_size: int = 1 << 20,
                 max_bytes: int | None = None, keep: int = 0, library: str = "msagv"):
        import json
        import subprocess
        import sys

        import msgpack

        self.path = Path(bag)
        self.messages = 0
        self.sent = 0  # records fed to the child
        self._pack = msgpack.Packer(use_bin_type=True)
        self._p = subprocess.Popen([sys.executable, "-m", "msagv.bridge.ros_bag"],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                   start_new_session=True)
        self._send(["open", str(self.path), json.loads(json.dumps(dict(header), default=str)),
                    chunk_size, max_bytes, keep, library])

    def _send(self, rec) -> None:
        self._p.stdin.write(self._pack.pack(rec))

    def record(self, key: str, data: bytes, ts: float) -> None:
        self._send(["rec", key, bytes(data), float(ts)])
        self.sent += 1

    def predicted(self, t0: float, dt: float, poses, ts: float) -> None:
        self._send(["pred", t0, dt, poses, ts])

    def flush(self) -> None:
        self._send(["flush"])
        self._p.stdin.flush()

    def close(self, timeout: float = 60.0) -> dict:
        """End the input; the child finishes the bag. Returns its account (``messages``,
        ``error``) and sets :attr:`messages`."""
        import json
        import subprocess

        try:
            out, _ = self._p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self._p.kill()
            self._p.wait(5)
            raise RuntimeError(f"the ROS 2 bag writer did not finish within {timeout:g} s")
        lines = [ln for ln in out.decode(errors="replace").splitlines() if ln.startswith("{")]
        res = json.loads(lines[-1]) if lines else {"messages": 0, "error": "no account"}
        self.messages = int(res.get("messages", 0))
        if res.get("error"):
            raise RuntimeError(res["error"])
        return res

    def detach(self) -> dict:
        """End the input without waiting: the child, in a session of its own, finishes the
        bag after this process has gone (a run stopped by a signal ends within a second,
        docs/PROTOCOL.md "Stopping"). :attr:`messages` is then the count fed to it."""
        self.abandon()
        self.messages = self.sent
        return {"messages": self.sent, "finishing": True}

    def abandon(self) -> None:
        """Stop feeding it (it finishes what it got)."""
        try:
            self._p.stdin.close()
        except Exception:
            pass


def main() -> int:
    """The child of :class:`BagProcess`: records from stdin until it ends, then the bag is
    finished and ``{"messages", "error"}`` printed."""
    import json
    import signal
    import sys

    import msgpack

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.nice(5)  # below the control loops of the recording processes
    except OSError:
        pass
    bag, error = None, None
    for rec in msgpack.Unpacker(sys.stdin.buffer, raw=False, max_buffer_size=64 << 20):
        if error is not None:
            continue  # drained, so the recording process never blocks on a full pipe
        try:
            op = rec[0]
            if op == "open":
                _, path, header, chunk, max_bytes, keep, library = rec
                bag = RosBag(path, header, chunk_size=chunk, max_bytes=max_bytes, keep=keep,
                             library=library)
            elif op == "rec":
                bag.record(rec[1], rec[2], rec[3])
            elif op == "pred":
                bag.predicted(*rec[1:])
            elif op == "flush":
                bag.flush()
        except Exception as e:  # noqa: BLE001 - reported at the end
            error = f"{type(e).__name__}: {e}"
            if bag is not None:
                bag.abandon()
    if bag is not None and error is None:
        try:
            bag.close()
        except Exception as e:  # noqa: BLE001
            error = f"{type(e).__name__}: {e}"
    try:
        print(json.dumps({"messages": bag.messages if bag is not None else 0, "error": error}),
              flush=True)
    except BrokenPipeError:
        # the recording process detached (RosBagWriter.detach: a run stopped by a signal)
        # and is gone: nobody reads the account; the bag is finished all the same
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""msagv recover when the recovered copy cannot be written (issue 30 item 5): a full disk
is stood in for by the operating system's file-size limit (RLIMIT_FSIZE: every write past
it fails with EFBIG, as a full disk fails with ENOSPC). Nothing is left behind, the
recording is unchanged, the error is one line; with the limit lifted the same command
recovers it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

LIMITED = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
from msagv.cli import main
sys.exit(main(["recover", {path!r}]))
"""


def _cut_recording(path: Path, messages: int = 4000) -> None:
    """An MCAP file written by the mcap library and cut before its summary and footer (as a
    killed writer leaves it)."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f, chunk_size=16 * 1024)
        w.start(profile="", library="test")
        s = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        c = w.register_channel(topic="msagv/agv0/state", message_encoding="json", schema_id=s)
        for k in range(messages):
            w.add_message(channel_id=c, log_time=k * 10_000_000, publish_time=k * 10_000_000,
                          data=b'{"seq": %d, "pad": "%s"}' % (k, b"x" * 64), sequence=k)
        w.finish()
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.8)])


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE is POSIX")
def test_recover_on_a_full_disk_leaves_nothing_and_says_so(tmp_path):
    rec = tmp_path / "run.mcap"
    _cut_recording(rec)
    before = rec.read_bytes()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    limit = len(before) // 4  # the copy cannot be written whole
    r = subprocess.run([sys.executable, "-c", LIMITED.format(limit=limit, path=str(rec))],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert r.returncode != 0
    assert "cannot write the recovered copy" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]  # no .recovering left
    assert rec.read_bytes() == before
    # space freed: the same command recovers it, and the standard reader reads every
    # message up to the cut
    ok = subprocess.run([sys.executable, "-m", "msagv", "recover", str(rec), "--json"],
                        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert ok.returncode == 0, ok.stderr
    from mcap.reader import make_reader

    with open(rec, "rb") as f:
        seqs = [m.sequence for _, _, m in make_reader(f).iter_messages()]
    assert seqs == list(range(len(seqs))) and 1000 < len(seqs) < 4000

"""The Rerun view (issue 14 item 3): what is logged, read back from the .rrd file (entity
paths, the sim_time timeline, the body's pose, each wheel at its steering angle coloured
by its wear power), from a closed loop, a recording and a running plant; and the served
web viewer in headless Chromium, whose screenshot must show the vehicle."""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import subprocess
import tempfile
import time

import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="rerun-sdk (the 'viewer' extra) is not installed")

from msagv.bridge import messages as M  # noqa: E402
from msagv.bridge.recording import Recorder  # noqa: E402
from msagv.controller.reference import make_case  # noqa: E402
from msagv.experiments.viewer import BODY_COLOR, RunView, Tee, ViewSink, wheel_colour  # noqa: E402
from helpers import ep, free_port, msagv  # noqa: E402
from msagv.plant import Plant, default_vehicle, n_axle_vehicle  # noqa: E402

WHEELS = ["11", "12", "21", "22"]


def read_rrd(path) -> dict[str, list[dict]]:
    """entity path -> rows ``{"sim_time": s, component: value, ...}`` (non-static ones
    in time order; static rows without sim_time), read with rerun's own reader."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for ch in RrdReader(str(path)).stream().to_chunks():
        import pyarrow as pa

        rb = ch.to_record_batch()
        cols = {}
        for i, f in enumerate(rb.schema):
            if f.name == "sim_time":  # a duration [ns]
                cols[f.name] = rb.column(i).cast(pa.int64()).to_pylist()
            elif ":" in f.name:  # Archetype:component
                cols[f.name] = rb.column(i).to_pylist()
        for i in range(rb.num_rows):
            row = {}
            for name, vals in cols.items():
                if name == "sim_time":
                    row["sim_time"] = None if vals[i] is None else vals[i] / 1e9
                else:
                    row[name.split(":", 1)[1]] = vals[i]
            out.setdefault(ch.entity_path, []).append(row)
    for rows in out.values():
        rows.sort(key=lambda r: -1.0 if r.get("sim_time") is None else r["sim_time"])
    return out


def _states(vehicle, n, seed=0):
    """States of a slalom with slipping wheels (every wheel wears, differently)."""
    p = Plant(vehicle, initial={"vx": 4.0})
    rng = np.random.default_rng(seed)
    sign = np.where(vehicle.wheel_x >= 0, 1.0, -1.0)
    out = []
    for k in range(n):
        st = p.state_message()
        st["t"] = round(k * 0.01, 10)
        out.append(st)
        w = 4.2 / vehicle.wheel_radius * (1 + 0.08 * rng.standard_normal(vehicle.n_wheels))
        p.set_inputs(np.maximum(w, 0), 0.3 * math.cos(k * 0.05) * sign)
        p.do_step(p.t, 0.01)
    return out


def _unpack_colour(c) -> tuple[int, int, int]:
    c = int(c[0] if isinstance(c, list) else c)
    return (c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255


def test_the_logged_entities_follow_the_states(tmp_path):
    v = default_vehicle()
    ref = make_case("curve", 15.0)[0]
    states = _states(v, 40)
    path = tmp_path / "v.rrd"
    view = RunView(v, ref, save=path)
    for st in states:
        view.log_state(st)
    view.close()
    got = read_rrd(path)
    for e in ["/vehicle/body", "/world/reference", "/world/path", "/errors/e_x_cm",
              "/errors/e_y_cm", "/errors/e_lat_cm", "/errors/e_phi_deg", "/wear/power/total"] + \
            [f"/vehicle/wheel/{w}" for w in WHEELS] + [f"/wear/power/{w}" for w in WHEELS]:
        assert e in got, (e, sorted(got))
    body = got["/vehicle/body"]
    assert [r["sim_time"] for r in body] == pytest.approx([s["t"] for s in states])
    for r, st in zip(body, states):
        assert r["centers"][0][:2] == pytest.approx([st["x"], st["y"]], abs=1e-4)
        assert r["rotation_axis_angles"][0]["angle"] == pytest.approx(st["phi"], abs=1e-5)
        assert _unpack_colour(r["colors"]) == BODY_COLOR
    # each wheel at its position in the body and at its steering angle phi + delta_ij
    for k, w in enumerate(WHEELS):
        rows = got[f"/vehicle/wheel/{w}"]
        assert len(rows) == len(states)
        st, r = states[-1], rows[-1]
        c, s = math.cos(st["phi"]), math.sin(st["phi"])
        want = [st["x"] + c * v.wheel_x[k] - s * v.wheel_y[k],
                st["y"] + s * v.wheel_x[k] + c * v.wheel_y[k]]
        assert r["centers"][0][:2] == pytest.approx(want, abs=1e-4)
        assert r["rotation_axis_angles"][0]["angle"] == pytest.approx(st["phi"] + st["delta"][k],
                                                                      abs=1e-5)
    # the wear power of each wheel: the change of its wear work over the period [kW]
    a, b = states[-2], states[-1]
    dt = b["t"] - a["t"]
    p = [sum(b[q][k] - a[q][k] for q in ("W_s_ij", "W_alpha_ij", "W_t_ij")) / dt / 1000.0
         for k in range(4)]
    for k, w in enumerate(WHEELS):
        assert got[f"/wear/power/{w}"][-1]["scalars"][0] == pytest.approx(p[k], rel=1e-5)
    # ... and the wheels' colours rank as their powers (the hottest is the reddest)
    reds = [_unpack_colour(got[f"/vehicle/wheel/{w}"][-1]["colors"])[0] for w in WHEELS]
    assert np.argsort(reds).tolist() == np.argsort(p).tolist() or len(set(reds)) < 4
    assert max(reds) > min(reds)
    tot = sum(b[q] - a[q] for q in ("W_s", "W_alpha", "W_t")) / dt / 1000.0
    assert got["/wear/power/total"][-1]["scalars"][0] == pytest.approx(tot, rel=1e-5)
    # the errors against the reference at t
    r = ref.sample(b["t"])
    assert got["/errors/e_y_cm"][-1]["scalars"][0] == pytest.approx(100 * (b["y"] - r[1]), abs=1e-3)
    # the driven path: every state's position, in order
    path_pts = got["/world/path"][-1]["strips"][0]
    assert len(path_pts) == len(states)
    assert path_pts[-1][:2] == pytest.approx([b["x"], b["y"]], abs=1e-4)


def test_wheel_colours_go_from_green_to_red():
    assert wheel_colour(0.0, 1.0) == [60, 180, 75]
    assert wheel_colour(2.0, 1.0) == [220, 30, 40]
    lo, mid = wheel_colour(0.2, 1.0), wheel_colour(0.6, 1.0)
    assert lo[0] < mid[0] and lo[1] > mid[1]


def test_a_view_without_a_sink_or_with_a_bad_file_is_refused(tmp_path):
    from msagv.experiments.viewer import ViewerError

    with pytest.raises(ViewerError, match="somewhere"):
        RunView(default_vehicle())
    with pytest.raises(ViewerError, match=r"\.rrd"):
        RunView(default_vehicle(), save=tmp_path / "x.png")


def test_the_plant_sink_queues_and_reads_the_per_wheel_wear_from_the_plant(tmp_path):
    """A plant that does not send W_s_ij (an old controller): the sink takes them from the
    plant object; the recorder beside it gets every message."""
    v = n_axle_vehicle(3)
    p = Plant(v, initial={"vx": 3.0})
    path = tmp_path / "p.rrd"
    view = RunView(v, None, save=path)
    rec = Recorder(tmp_path / "p.mcap", {"role": "plant", "vehicle": v.to_dict()})
    tee = Tee(rec, ViewSink(view, p))
    for k in range(20):
        st = p.state_message()
        st["t"] = k * 0.01
        tee.message("tx", "msagv/a/state", M.encode_state(k, st, wheel_wear=False))
        tee.message("rx", "msagv/a/cmd", b"junk", why="not_msgpack")
        p.set_inputs([3.3 / v.wheel_radius] * 6, [0.2] * 6)
        p.do_step(p.t, 0.01)
    stats = tee.close({"steps": 20})
    assert stats["records"] == 41 and stats["rejected"] == 20  # the recorder's counters
    got = read_rrd(path)
    assert len(got["/vehicle/body"]) == 20 and "/vehicle/wheel/32" in got
    assert len(got["/wear/power/32"]) == 19 and got["/wear/power/32"][-1]["scalars"][0] > 0


@pytest.mark.timeout(300)
def test_msagv_run_and_view_write_the_same_entities(tmp_path):
    rrd = tmp_path / "run.rrd"
    out = subprocess.run(msagv("run", "--duration", 0.5, "--view-save", rrd, "--json", "-q"),
                         capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    got = read_rrd(rrd)
    assert len(got["/vehicle/body"]) == doc["metrics"]["steps"] + 1  # and the final state
    assert set(WHEELS) <= {e.rsplit("/", 1)[1] for e in got if e.startswith("/vehicle/wheel/")}
    # a recording in the viewer: msagv view FILE --no-serve --view-save
    rec = tmp_path / "r.mcap"
    r = Recorder(rec, {"role": "plant", "vehicle": default_vehicle().to_dict(),
                       "reference": make_case("curve", 15.0)[0].to_message(), "period": 0.01})
    states = _states(default_vehicle(), 30)
    for k, st in enumerate(states):
        r.message("tx", "msagv/agv0/state", M.encode_state(k, st))
    r.close({})
    out = subprocess.run(msagv("view", rec, "--no-serve", "--view-save", tmp_path / "r.rrd"),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    got = read_rrd(tmp_path / "r.rrd")
    assert [b["centers"][0][0] for b in got["/vehicle/body"]] == pytest.approx(
        [s["x"] for s in states], abs=1e-4)
    # bad input: one line, exit 2
    for args, msg in ((["view", tmp_path / "nope.mcap", "--no-serve", "--view-save",
                        tmp_path / "x.rrd"], "no such file"),
                      (["view", rec, "--no-serve"], "--view-save"),
                      (["run", "--view-save", tmp_path / "x.png"], ".rrd")):
        out = subprocess.run(msagv(*args), capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and msg in out.stderr, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr


# ---- the web viewer in headless Chromium ----------------------------------------------------
def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def screenshot(url: str, wait_s: float, size=(1280, 800), until=None, every_s: float = 3.0):
    """PNG bytes of ``url`` in headless Chromium, driven over the DevTools protocol on a
    pipe (no extra package): taken every ``every_s`` until ``until(png)`` is true or
    ``wait_s`` has passed (the web viewer compiles its wasm for a few seconds)."""
    r3, w3 = os.pipe()  # Chromium reads commands on fd 3 ...
    r4, w4 = os.pipe()  # ... and writes replies on fd 4
    udd = tempfile.mkdtemp(prefix="msagv-chromium-")
    args = [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
            "--no-first-run", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", f"--user-data-dir={udd}", f"--window-size={size[0]},{size[1]}",
            "--remote-debugging-pipe", "about:blank"]

    def fds():
        os.dup2(r3, 3)
        os.dup2(w4, 4)

    p = subprocess.Popen(args, preexec_fn=fds, pass_fds=(3, 4), stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    os.close(r3)
    os.close(w4)
    wf, rf = os.fdopen(w3, "wb", buffering=0), os.fdopen(r4, "rb", buffering=0)
    state = {"buf": b"", "id": 0}

    def call(method, params=None, session=None):
        state["id"] += 1
        mid = state["id"]
        msg = {"id": mid, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        wf.write(json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in state["buf"]:
                chunk = rf.read(1 << 16)
                if not chunk:
                    raise RuntimeError("chromium closed its DevTools pipe")
                state["buf"] += chunk
            line, state["buf"] = state["buf"].split(b"\0", 1)
            m = json.loads(line)
            if m.get("id") == mid:
                if "error" in m:
                    raise RuntimeError(m["error"])
                return m["result"]

    try:
        tid = call("Target.createTarget", {"url": url})["targetId"]
        sid = call("Target.attachToTarget", {"targetId": tid, "flatten": True})["sessionId"]
        call("Emulation.setDeviceMetricsOverride", {"width": size[0], "height": size[1],
                                                    "deviceScaleFactor": 1, "mobile": False}, sid)
        t0 = time.monotonic()
        while True:
            time.sleep(every_s)
            png = base64.b64decode(call("Page.captureScreenshot", {"format": "png"}, sid)["data"])
            if until is None or until(png) or time.monotonic() - t0 > wait_s:
                return png
    finally:
        p.kill()
        p.wait()
        shutil.rmtree(udd, ignore_errors=True)


def vehicle_pixels(png: bytes) -> tuple[int, int]:
    """Pixels of the body's colour and of a wheel's (green to red; within shading) inside
    the 3D view (the left 55 %, without the top bar and the time panel)."""
    import io

    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    h, w, _ = a.shape
    a = a[int(0.07 * h):int(0.92 * h), :int(0.55 * w)]
    body = int((np.abs(a - np.array(BODY_COLOR)).max(axis=2) < 45).sum())
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    wheel = int((((g > r + 30) & (g > b + 30)) | ((r > g + 40) & (r > b + 40))).sum())
    return body, wheel


def _shows_vehicle(png: bytes) -> bool:
    body, wheel = vehicle_pixels(png)
    return body > 300 and wheel > 30


@pytest.mark.timeout(300)
def test_the_web_viewer_in_headless_chromium_shows_the_vehicle(tmp_path, procs):
    if _chromium() is None:
        pytest.skip("headless Chromium is not installed (Debian: apt-get install -y chromium; "
                    "make test installs it when it can)")
    rec = tmp_path / "r.mcap"
    r = Recorder(rec, {"role": "plant", "vehicle": default_vehicle().to_dict(),
                       "reference": make_case("curve", 15.0)[0].to_message(), "period": 0.01})
    for k, st in enumerate(_states(default_vehicle(), 150)):
        r.message("tx", "msagv/agv0/state", M.encode_state(k, st))
    r.close({})
    port = free_port()
    while port + 1 > 65534:
        port = free_port()
    procs.start("view", msagv("view", rec, "--view-port", port))
    t0 = time.monotonic()
    while "serving the view" not in procs.err("view"):
        assert procs.p["view"].poll() is None, procs.err("view")
        assert time.monotonic() - t0 < 120, procs.err("view")
        time.sleep(0.2)
    url = next(ln.split(" at ", 1)[1].split(" (", 1)[0] for ln in procs.err("view").splitlines()
               if "serving the view at" in ln)
    assert url.startswith(f"http://127.0.0.1:{port}/")
    png = screenshot(url, 90, until=_shows_vehicle)
    (tmp_path / "viewer.png").write_bytes(png)
    n, nw = vehicle_pixels(png)
    assert _shows_vehicle(png), (f"no vehicle in the screenshot ({n} body-coloured, {nw} "
                                 f"wheel-coloured pixels): {tmp_path / 'viewer.png'}")
    procs.p["view"].terminate()
    assert procs.wait("view", 30) == 0
    print(f"\nweb viewer: {n} body-coloured, {nw} wheel-coloured pixels; screenshot "
          f"{tmp_path / 'viewer.png'}")

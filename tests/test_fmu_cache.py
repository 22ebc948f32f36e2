"""A second instantiation of the FMU, in a new process and from a fresh unpack (as fmpy
does it), loads the plant's compiled kernels instead of compiling them again (FMU.md,
"numba inside the FMU"). Checked by numba's own cache counters, not by timing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import warnings

SCRIPT = textwrap.dedent("""
    import json, sys
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave
    fmu = sys.argv[1]
    md = read_model_description(fmu)
    unzip = extract(fmu)  # a new temporary directory every time
    f = FMU2Slave(guid=md.guid, unzipDirectory=unzip,
                  modelIdentifier=md.coSimulation.modelIdentifier, instanceName="p")
    f.instantiate()
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    f.doStep(0.0, 0.01)
    hits = misses = 0
    where = set()
    for name, mod in list(sys.modules.items()):
        if not name.startswith("msagv_plant_"):
            continue
        where.add(getattr(mod, "__file__", "") or "")
        for obj in vars(mod).values():
            stats = getattr(obj, "stats", None)
            if stats is not None and hasattr(stats, "cache_hits"):
                hits += sum(stats.cache_hits.values())
                misses += sum(stats.cache_misses.values())
    f.terminate(); f.freeInstance()
    print(json.dumps({"hits": int(hits), "misses": int(misses), "unzip": str(unzip),
                      "where": sorted(str(w) for w in where)}))
""")


# glibc's abort on a corrupted heap, as an fmpy host of a pythonfmu FMU can meet it at exit
# (pythonfmu issue #228, open upstream; FMU.md, "numba inside the FMU")
EXIT_ABORT = "corrupted double-linked list"


def _instantiate(fmu, env) -> dict:
    """The script's result, and ``aborted_at_exit``: whether the host then aborted so."""
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(fmu)], env=env, capture_output=True,
                       text=True, timeout=300)
    lines = r.stdout.strip().splitlines()
    if (r.returncode == -signal.SIGABRT and EXIT_ABORT in r.stderr and lines
            and lines[-1].startswith("{")):
        # the run was done and its result printed (after terminate and freeInstance): the
        # host's exit aborted, which the slave makes rare but cannot prevent (1 CI run of
        # many). Said, not hidden; anything else that ends the host is a failure.
        warnings.warn(f"the fmpy host aborted at its exit ({EXIT_ABORT}) after a complete "
                      "run: pythonfmu issue #228")
    else:
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return dict(json.loads(lines[-1]), aborted_at_exit=r.returncode != 0)


def test_a_second_instantiation_does_not_compile(paper_fmu, tmp_path):
    cache = tmp_path / "cache"
    env = dict(os.environ, MSAGV_FMU_CACHE=str(cache))
    env.pop("NUMBA_CACHE_DIR", None)
    first = _instantiate(paper_fmu, env)
    assert first["misses"] > 0  # compiled (nothing cached yet in this cache directory)
    # later instantiations, each from its own fresh unpack, load every kernel and exit
    # cleanly (_instantiate checks the exit code: loading cached kernels in an fmpy host
    # had made scipy's libgfortran abort the exit in 30-50 % of runs, see slave.py; one
    # abort after a complete run is the rare upstream one, two of four the old rate)
    aborts = int(first["aborted_at_exit"])
    for _ in range(3):
        later = _instantiate(paper_fmu, env)
        assert later["unzip"] != first["unzip"]
        assert later["misses"] == 0 and later["hits"] > 0
        aborts += later["aborted_at_exit"]
    assert aborts <= 1, aborts
    # the kept copy, named by the build's hash, is what was imported
    (copy,) = [p for p in cache.iterdir() if p.name.startswith("msagv_plant_")]
    assert all(w.startswith(str(copy)) for w in later["where"] if w)

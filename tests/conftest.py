"""Fixtures shared by the test modules (helpers that are not fixtures: helpers.py)."""

from __future__ import annotations

import pytest

import helpers


@pytest.fixture(scope="session")
def paper_vehicle():
    """The paper's 2-axle, 12 t vehicle (built in)."""
    from msagv.plant import default_vehicle

    return default_vehicle()


@pytest.fixture
def three_axle_file(tmp_path):
    """:data:`helpers.THREE_AXLE_TOML` written to a file."""
    p = tmp_path / "three.toml"
    p.write_text(helpers.THREE_AXLE_TOML)
    return p


@pytest.fixture
def procs(tmp_path):
    """The processes a test starts (:class:`helpers.Procs`), always stopped at its end."""
    p = helpers.Procs(tmp_path)
    try:
        yield p
    finally:
        p.stop_all()


@pytest.fixture
def port():
    """A free TCP port on loopback."""
    return helpers.free_port()


@pytest.fixture(scope="session")
def paper_fmu(tmp_path_factory):
    """The plant FMU of the paper's vehicle, built once for the session."""
    from msagv.fmu_build.build import build_fmu

    return build_fmu(tmp_path_factory.mktemp("paper_fmu") / "plant.fmu")


# ---- two workers (make test: pytest -n 2 --dist loadscope) --------------------------------
# The suite runs on both cores of the CI machine. The tests of these modules start real
# processes that keep a period (plants at 100 Hz, controllers, ROS 2 nodes, a browser) or
# count what crosses a loopback bus: they run one after another on one worker, never beside
# each other; the in-process tests (numerics, kernels, files) share the other core.
# test_cli_ux is not one of them: its processes are one-shot commands (msagv --help, an
# offline msagv run stopped by Ctrl-C), none with a period or a bus; as one, its 68 s (of
# 1265 s) lengthened the processes unit, the suite's longest, while the other worker sat
# idle for 142 s at the end (a clean clone's make test at load 3-12).
PROCESS_MODULES = frozenset({
    "test_foxglove", "test_handover", "test_ownership",
    "test_processes", "test_protocol_doc", "test_recording", "test_ros2_nodes",
    "test_ros2_plant_lifecycle", "test_ros2_plant_services", "test_ros2_sim", "test_ros2_three_ways", "test_ros_recording",
    "test_security", "test_viewer",
})


@pytest.fixture(scope="session")
def warm_kernels():
    """The default controller's and the plant's kernels in numba's on-disk cache, compiled
    once (``msagv run`` for a few periods) before the first test that starts processes. On
    a clean clone a controller process compiles them first: over a minute on a loaded
    2-core machine (66 s measured), longer than a plant waits for its controller by default
    (60 s); from the cache it starts in seconds."""
    r = helpers.run_msagv("run", "--duration", "0.05", "-q", timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]


@pytest.fixture(autouse=True)
def _warm_before_processes(request):
    if request.node.module.__name__ in PROCESS_MODULES:
        request.getfixturevalue("warm_kernels")


def _scope(nodeid: str) -> str:
    """A test's unit of scheduling: the process modules' tests are one, any other module's
    tests another (a module's fixtures, such as test_experiments' reduced Case 1, are built
    once: with a test per unit both workers built them, 77 s and 24 s measured)."""
    path = nodeid.split("::", 1)[0]
    module = path.rsplit("/", 1)[-1].removesuffix(".py")
    return "processes" if module in PROCESS_MODULES else path


# The modules that take longest, longest first (module totals of --durations=0 on a clean
# clone, i.e. on a cold numba cache). xdist hands units out by their number of tests, so a
# long module of few tests came last and the other worker sat idle while it ran (62 s for
# test_determinism, one test); longest first leaves the short ones for the end. The
# processes unit, the longest, goes first. test_determinism then goes to the other worker:
# it compiles into a cache of its own, so it overlaps warm_kernels' compile (the shared
# cache) instead of compiling the same kernels beside it, as the first in-process kernel
# tests did.
LONGEST_FIRST = (
    "processes", "test_determinism", "test_rollout_simd", "test_study", "test_experiments",
    "test_offset_free", "test_cli_ux", "test_tire_life", "test_nmpc", "test_ipopt",
    "test_no_nonsense", "test_controller", "test_calibrate",
)


def _unit_rank(scope: str) -> int:
    """A unit's place in :data:`LONGEST_FIRST` (the others after it, in the order xdist
    queued them: ``min`` keeps the first of equals)."""
    name = scope.rsplit("/", 1)[-1].removesuffix(".py")
    return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)


@pytest.hookimpl(optionalhook=True)  # (a run with -p no:xdist does not know the hook)
def pytest_xdist_make_scheduler(config, log):
    """xdist's loadscope scheduling over :func:`_scope` (xdist's own grouping mark,
    ``xdist_group``, does not take with pytest 9.2: it renames a node id pytest no longer
    reads)."""
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ProcessesApart(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _scope(nodeid)

        def _assign_work_unit(self, node) -> None:
            # the next unit by _unit_rank, not xdist's (most tests first)
            self.workqueue.move_to_end(min(self.workqueue, key=_unit_rank), last=False)
            super()._assign_work_unit(node)

    return ProcessesApart(config, log)

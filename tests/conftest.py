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

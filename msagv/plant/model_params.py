"""The parameters a prediction model owns, each model's declared once here.

A prediction model of the controller (:mod:`msagv.controller.models`) that needs values the
vehicle does not otherwise have (DH's Dugoff tires: their stiffnesses and friction) declares
them as one :class:`ModelParams`: its table in the vehicle file (``[tire.<section>]``), each
parameter's name, unit, description, check, default and the ``--adapt`` factor that scales
it. Everything else reads the declaration: the vehicle file's parser and writer
(:mod:`plant.vehicle`, ``experiments.calibrate``), ``msagv vehicle``, the FMU's parameter
variables (``fmu_build.variables``), the packing for the prediction kernels (the model's
values after the shared vector ``P``: :meth:`ModelParams.offset`), the online adaptation.

The declarations live in the plant package, not beside the model classes, because the
vehicle file is read by the plant, which the FMU bundles alone (it cannot import the
controller). This module imports nothing (the FMU bundles ``plant/`` under another name).
"""

from __future__ import annotations

from dataclasses import dataclass

ADAPT_FACTORS = ("c_lat", "c_lon", "f")  # controller.adaptation.NAMES


@dataclass(frozen=True)
class Param:
    """One parameter of a model: ``name`` (its key in the section), ``unit`` (FMI unit or
    None when dimensionless), ``doc`` (one line), ``positive`` (must be > 0; otherwise any
    finite number), ``default`` (None: the key is required), ``adapt`` (the ``--adapt``
    factor, one of :data:`ADAPT_FACTORS`, that multiplies it; None: not adapted)."""

    name: str
    unit: str | None
    doc: str
    positive: bool = True
    default: float | None = None
    adapt: str | None = None

    def __post_init__(self):
        if self.adapt is not None and self.adapt not in ADAPT_FACTORS:
            raise ValueError(f"Param {self.name}: adapt must be one of {ADAPT_FACTORS}, "
                             f"got {self.adapt!r}")


@dataclass(frozen=True)
class ModelParams:
    """The parameters of one prediction model: the vehicle file's ``[tire.<section>]``
    table and the values the kernels read at ``P[N_PARAMS + offset(name)]``."""

    section: str
    params: tuple[Param, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def offset(self, name: str) -> int:
        """Where ``name`` is in the model's values (0-based), as the kernels index it
        after the shared ``P`` (``plant.layout.N_PARAMS + offset``)."""
        return self.names.index(name)


@dataclass(frozen=True)
class ParamValues:
    """A vehicle's values of one :class:`ModelParams` (in its declared order)."""

    spec: ModelParams
    values: tuple[float, ...]

    def __getitem__(self, name: str) -> float:
        return self.values[self.spec.offset(name)]

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.spec.names, self.values))


DUGOFF = ModelParams("dugoff", (
    Param("C_s", "N", "Dugoff longitudinal stiffness", adapt="c_lon"),
    Param("C_alpha", "N/rad", "Dugoff cornering stiffness", adapt="c_lat"),
    Param("mu", None, "Dugoff friction coefficient", adapt="f"),
))  # Dugoff tire coefficients, for the DH baseline (Du et al. 2024)

#: every model's parameters, by section name, in the vehicle file's order
SECTIONS: dict[str, ModelParams] = {s.section: s for s in (DUGOFF,)}

"""The tire-wear-aware SA-MPC: prediction models, cost, annealer, references, metrics.

Imports only the plant's model code (tire, wear, parameters), never its stepping loop,
and nothing of transport: ``MPC.step(state, reference) -> Command`` runs the same
in-process, over Zenoh and against an FMU.
"""

from .metrics import compute_metrics, omega_index
from .models import MPCSettings, make_model
from .interface import Command, Controller, ControllerError
from .mpc import MPC
from .reference import Reference, SpeedProfile, case1_curve, case2_line, from_csv, make_case

__all__ = ["MPC", "Controller", "Command", "ControllerError", "MPCSettings", "make_model", "Reference",
           "SpeedProfile", "case1_curve", "case2_line", "from_csv", "make_case",
           "compute_metrics", "omega_index"]

"""jaxflex: flexible-joint robots with LuGre friction in pure JAX.

Workflows, for a notebook (``jaxflex.api``; each returns a result of numbers with ``.plot()``
and ``.save(path)``): ``identify_log``, ``discover_effects``, ``validate_model``,
``certify_gains``, ``tune_gains``, ``sweep_spread``. Their names carry an object because
``jaxflex.identify``, ``jaxflex.discover``, ``jaxflex.validate``, ``jaxflex.tune`` and
``jaxflex.sweep`` are the workflow packages themselves: a function bound to a package's name
would be replaced by the package as soon as anything imports it. They load on first use, so
``import jaxflex`` stays as quick as the physics. Shipped logs: ``jaxflex.data``.

Physics (pure functions and ``eqx.Module``s): ``friction`` (LuGre), ``plant``, ``effects``,
``observer``, ``controller`` (cascade control), ``trajectory``, ``sensing``, ``estimator``
(Kalman velocity estimation for coarse encoders); ``simulate`` closes the loop. ``presets`` holds the paper's tables and every named preset.
Importing jaxflex changes no global JAX setting: turn on float64 yourself with
``jax.config.update("jax_enable_x64", True)`` for identification and certificates.
"""

import importlib
from typing import Any

from jaxflex.controller import CascadeController, CascadeGains
from jaxflex.estimator import KalmanEstimator, KalmanTuning
from jaxflex.friction import LuGre
from jaxflex.params import Params, load_params, save_params
from jaxflex.plant import DiagonalInertia, FlexibleJointPlant, PlanarTwoLink, PlantState
from jaxflex.presets import (
    paper_gains,
    paper_lugre,
    paper_params,
    paper_plant,
    paper_sensing,
    sensing_preset,
    trajectory_preset,
    two_link_plant,
)
from jaxflex.sensing import AbstractSensing, Sensing, StraightThrough
from jaxflex.simulate import simulate_continuous, simulate_sampled
from jaxflex.trajectory import Multisine, RestToRest, Sinusoid, Trajectory

#: Names of ``jaxflex.api`` served from the top level on first use.
API_NAMES: tuple[str, ...] = (
    "Certification", "Discovery", "Identification", "Sweep", "Tuning", "Validation",
    "certify_gains", "discover_effects", "identify_log", "sweep_spread", "tune_gains",
    "validate_model",
)
__all__ = [
    "AbstractSensing", "KalmanEstimator", "KalmanTuning", "StraightThrough", "sensing_preset", "trajectory_preset",
    "CascadeController", "CascadeGains", "DiagonalInertia", "FlexibleJointPlant", "LuGre",
    "Multisine", "Params", "PlanarTwoLink", "PlantState", "RestToRest", "Sensing", "Sinusoid",
    "Trajectory", "load_params", "paper_gains", "paper_lugre", "paper_params", "paper_plant",
    "paper_sensing", "save_params", "simulate_continuous", "simulate_sampled", "two_link_plant",
    *API_NAMES,
]
__version__ = "0.1.0"

#: Subpackages reachable as attributes without their own import (``jaxflex.data.load_emps``).
LAZY_MODULES: tuple[str, ...] = ("api", "data", "discover", "identify", "plots", "sweep")


def __getattr__(name: str) -> Any:
    """The top-level workflows and subpackages, imported on first access.

    **Arguments:**

    - `name`: the attribute asked for.

    **Returns:**

    The function, result class or subpackage.

    **Raises:**

    ``AttributeError`` for a name jaxflex does not have.
    """
    if name in API_NAMES:
        from jaxflex import api

        return getattr(api, name)
    if name in LAZY_MODULES:
        return importlib.import_module(f"jaxflex.{name}")
    raise AttributeError(f"module 'jaxflex' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *API_NAMES, *LAZY_MODULES})

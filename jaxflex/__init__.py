"""jaxflex: flexible-joint robots with LuGre friction in pure JAX.

Workflows, for a notebook (``jaxflex.app.api``; each returns a result of numbers with ``.plot()``
and ``.save(path)``): ``identify_log``, ``discover_effects``, ``validate_model``,
``certify_gains``, ``tune_gains``, ``sweep_spread``. Their names carry an object because
``jaxflex.identify``, ``jaxflex.discover``, ``jaxflex.validate``, ``jaxflex.tune`` and
``jaxflex.sweep`` are the workflow packages themselves: a function bound to a package's name
would be replaced by the package as soon as anything imports it. They load on first use, so
``import jaxflex`` stays as quick as the physics. Shipped logs: ``jaxflex.data``.

The package's folders are its layers, each importing only from those before it
(``docs/architecture.md``): ``runtime`` (compile-time machinery), ``core`` (the physics, pure
functions and ``eqx.Module``s: ``friction`` (LuGre), ``effects``, ``plant``, ``observer``,
``controller``, ``trajectory``, ``sensing``, ``estimator``, ``certificate``), ``sim`` (the
integration step and the closed loop), ``io`` (logs, parameter files, ``presets``: the
paper's tables and every named preset), ``fit`` (the fitting engine), the workflows
(``identify``, ``discover``, ``validate``, ``loop``, ``tune``, ``sweep``, ``export``) and
``app`` (notebook verbs, command line, plots, reports, the hardware loop). The names modules
had before the layers (``jaxflex.params``, ``jaxflex.friction``, ...) still import, as the
same module objects (``jaxflex._aliases``).
Importing jaxflex changes no global JAX setting: turn on float64 yourself with
``jax.config.update("jax_enable_x64", True)`` for identification and certificates.
"""

import importlib
from typing import Any

from jaxflex._aliases import MOVED as _MOVED
from jaxflex._aliases import install as _install_aliases
from jaxflex.core.controller import CascadeController, CascadeGains
from jaxflex.core.estimator import KalmanEstimator, KalmanTuning
from jaxflex.core.friction import LuGre
from jaxflex.core.plant import DiagonalInertia, FlexibleJointPlant, PlanarTwoLink, PlantState
from jaxflex.core.sensing import AbstractSensing, Sensing, StraightThrough
from jaxflex.core.trajectory import Multisine, RestToRest, Sinusoid, Trajectory
from jaxflex.io.params import Params, load_params, save_params
from jaxflex.io.presets import (
    paper_gains,
    paper_lugre,
    paper_params,
    paper_plant,
    paper_sensing,
    sensing_preset,
    trajectory_preset,
    two_link_plant,
)
from jaxflex.sim.simulate import simulate_continuous, simulate_sampled

_install_aliases()  # the module names from before the layers (``jaxflex._aliases``)

#: Names of ``jaxflex.app.api`` served from the top level on first use.
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

#: Subpackages reachable as attributes without their own import (``jaxflex.data.load_emps``);
#: a module's name from before the layers (``jaxflex.presets``) is reachable the same way.
LAZY_MODULES: tuple[str, ...] = ("app", "data", "discover", "identify", "sweep")


def __getattr__(name: str) -> Any:
    """The top-level workflows, subpackages and old module names, imported on first access.

    **Arguments:**

    - `name`: the attribute asked for.

    **Returns:**

    The function, result class or module.

    **Raises:**

    ``AttributeError`` for a name jaxflex does not have.
    """
    if name in API_NAMES:
        from jaxflex.app import api

        return getattr(api, name)
    if name in LAZY_MODULES or f"jaxflex.{name}" in _MOVED:
        return importlib.import_module(f"jaxflex.{name}")
    raise AttributeError(f"module 'jaxflex' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *API_NAMES, *LAZY_MODULES})

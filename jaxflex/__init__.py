"""jaxflex: flexible-joint robots with LuGre friction in pure JAX.

Physics (pure functions and ``eqx.Module``s): ``friction`` (LuGre), ``plant``, ``effects``,
``observer``, ``controller`` (cascade control), ``trajectory``, ``sensing``, ``estimator``
(Kalman velocity estimation for coarse encoders); ``simulate`` closes the loop. ``presets`` holds the paper's tables and every named preset.
Importing jaxflex changes no global JAX setting: turn on float64 yourself with
``jax.config.update("jax_enable_x64", True)`` for identification and certificates.
"""

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

__all__ = [
    "AbstractSensing", "KalmanEstimator", "KalmanTuning", "StraightThrough", "sensing_preset", "trajectory_preset",
    "CascadeController", "CascadeGains", "DiagonalInertia", "FlexibleJointPlant", "LuGre",
    "Multisine", "Params", "PlanarTwoLink", "PlantState", "RestToRest", "Sensing", "Sinusoid",
    "Trajectory", "load_params", "paper_gains", "paper_lugre", "paper_params", "paper_plant",
    "paper_sensing", "save_params", "simulate_continuous", "simulate_sampled", "two_link_plant",
]
__version__ = "0.1.0"

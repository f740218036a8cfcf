"""Identification from logs (docs/spec.md section 5; paper section 5, eq. 34-39).

Public API (a workflow on the fitting engine ``jaxflex.fit``):

- ``start_from_data(log, model)``, ``suggest_model(log, link_side)``: a full start and the
  model kind from the log and its declared link side (linear least squares on the inverse
  dynamics);
- ``identify_rotor(log, init=None, free=None) -> RotorResult``: the rotor kind by equation
  error on the torque from the measured motion; ``refit_per_log``: its per-log sensor
  nuisances on another log;
- ``identify(log, init=None, free=None, model=..., segment_length=...) -> IdentResult``: joint
  output-error fit by gradient through the simulator (optimistix Levenberg-Marquardt,
  multiple shooting, constraints by reparametrisation, standard errors, identifiability
  warnings);
- ``make_problem`` / ``Problem.residuals``: the same residual for other solvers;
- ``simulate_log``: replay a log's torque through a parameter set;
- ``two_step``, ``static_map_experiment``, ``fit_static_map``: the paper's procedure;
- ``static_map_from_log``: friction against velocity from a log by inverse dynamics (the
  start ``identify`` takes for Fc, Fs, vs, sigma2, joint by joint:
  ``start_from_static_map``);
- ``synthetic_log``, ``excitation_torque``: simulated identification experiments;
- ``ParamSpace``, ``get_value``, ``set_values``, ``Problem``, ``covariance``: from the
  fitting engine ``jaxflex.fit``, re-exported for convenience.
"""

from jaxflex.fit import ParamSpace, Problem, covariance, get_value, set_values
from jaxflex.identify.core import DECREMENT_TOL, GEODESIC, identify, simulate_log
from jaxflex.identify.discretisation import (
    BIAS_TOL,
    MAX_SUBSTEPS,
    OUTPUT_TOL,
    choose_substeps,
    refine_fit,
)
from jaxflex.identify.problem import (
    DEFAULT_FREE,
    choose_segment_length,
    default_free,
    make_problem,
    noise_cost,
)
from jaxflex.identify.result import IdentificationWarning, IdentResult, finish
from jaxflex.identify.experiments import (
    TwoStepResult,
    excitation_torque,
    perturb,
    static_map_experiment,
    synthetic_log,
    two_step,
)
from jaxflex.identify.start import DataStart, StartError, start_from_data, suggest_model
from jaxflex.identify.torque import RotorResult, identify_rotor, refit_per_log
from jaxflex.identify.verdict import model_verdict
from jaxflex.identify.static import (
    STATIC_NAMES,
    StaticMap,
    fit_static_map,
    start_from_static_map,
    static_map_from_log,
)
from jaxflex.sim.step import MODEL_KINDS, replay, rigid_step, rigid_vector_field

__all__ = [
    "BIAS_TOL", "DECREMENT_TOL", "DEFAULT_FREE", "GEODESIC", "MAX_SUBSTEPS", "MODEL_KINDS",
    "OUTPUT_TOL", "choose_segment_length", "choose_substeps", "refine_fit", "STATIC_NAMES", "IdentResult", "IdentificationWarning",
    "ParamSpace", "Problem", "StaticMap", "TwoStepResult", "covariance", "excitation_torque",
    "finish", "fit_static_map", "get_value", "identify", "make_problem", "noise_cost", "perturb", "replay",
    "rigid_step", "rigid_vector_field", "set_values", "simulate_log", "static_map_experiment",
    "start_from_static_map", "static_map_from_log",
    "synthetic_log", "two_step", "DataStart", "StartError", "start_from_data", "suggest_model",
    "RotorResult", "identify_rotor", "refit_per_log",
    "model_verdict", "default_free",
]

"""The fitting engine: one least-squares problem over log segments (multiple shooting), one
constraint vocabulary, one solver path (optimistix Levenberg-Marquardt), one covariance.

``jaxflex.identify``, ``jaxflex.discover`` (and any validation) are thin workflows on it:

- ``ParamSpace``: free parameters and their reparametrisation (``space``);
- ``savgol``, ``noise_level``: Savitzky-Golay and the noise of a logged angle (``signal``);
- ``Segments``, ``make_segments``: the log cut into segments (``segments``); ``Problem``:
  their replay and residuals (``problem``);
- ``least_squares``, ``cost``, ``Solution``: the step loop and its stops (``solve``), built
  from a Levenberg-Marquardt descent and trust region (``levenberg_marquardt``) over structured
  normal-equation solves (``normal``);
- ``covariance`` and the robust covariances (``uncertainty``); ``simulated_outputs``,
  ``residuals``, ``gap`` (``replay``); ``discretisation_bias`` (``discretisation``);
- ``segment_slots``, ``slot_rows``, ``on_slot_rows`` (``segments``), ``Padding``: the buckets
  of segment counts a problem is compiled for, so that logs of other lengths reuse the
  programs.
"""

from jaxflex.fit.problem import BLOWN_RESIDUAL, Problem, dynamic_substeps
from jaxflex.fit.segments import (
    Segments,
    make_segments,
    on_slot_rows,
    output_columns,
    pack_state,
    segment_slots,
    slot_rows,
    unpack_state,
)
from jaxflex.fit.discretisation import (
    SCHEME_ORDER,
    ReplayError,
    discretisation_bias,
    integration_error,
    observed_order,
    refined,
    replay_error,
    step_doubling_error,
)
from jaxflex.fit.padding import Padding
from jaxflex.fit.replay import gap, residuals, simulated_outputs
from jaxflex.fit.signal import noise_level, savgol, savgol_coeffs, white_noise_std
from jaxflex.fit.solve import (
    CostBound,
    Solution,
    cost,
    least_squares,
    problem_residuals,
    residual_cost,
    trace_solver,
)
from jaxflex.fit.uncertainty import (
    cluster_robust_covariance,
    covariance,
    induced_point,
    induced_shift,
    remaining_step,
    segment_robust_covariance,
)
from jaxflex.fit.space import (
    NOMINAL_CONSTRAINTS,
    ParamSpace,
    constraint_of,
    get_value,
    is_fitted,
    params_of_plant,
    relative,
    set_values,
)

__all__ = [
    "BLOWN_RESIDUAL", "CostBound", "NOMINAL_CONSTRAINTS", "Padding", "ParamSpace", "Problem",
    "Segments", "Solution", "on_slot_rows", "segment_slots", "slot_rows",
    "constraint_of", "cost", "dynamic_substeps", "covariance", "cluster_robust_covariance",
    "segment_robust_covariance", "discretisation_bias", "gap", "induced_point", "induced_shift",
    "remaining_step", "ReplayError", "replay_error", "SCHEME_ORDER",
    "integration_error", "observed_order", "refined", "step_doubling_error", "get_value",
    "is_fitted", "least_squares",
    "make_segments", "noise_level", "output_columns", "pack_state", "params_of_plant",
    "problem_residuals", "residual_cost", "residuals", "simulated_outputs", "trace_solver",
    "relative", "savgol", "savgol_coeffs", "set_values", "unpack_state", "white_noise_std",
]

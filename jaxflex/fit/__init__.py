"""The fitting engine: one least-squares problem over log segments (multiple shooting), one
constraint vocabulary, one solver path (optimistix Levenberg-Marquardt), one covariance.

``jaxflex.identify``, ``jaxflex.discover`` (and any validation) are thin workflows on it:

- ``ParamSpace``: free parameters and their reparametrisation (``space``);
- ``Segments``, ``make_segments``, ``Problem``: data and residuals (``problem``);
- ``least_squares``, ``covariance``, ``cost``: solve and judge (``solve``);
- ``segment_slots``, ``slot_rows``, ``on_slot_rows``, ``Padding``: the buckets of segment
  counts a problem is compiled for, so that logs of other lengths reuse the programs.
"""

from jaxflex.fit.problem import (
    BLOWN_RESIDUAL,
    Problem,
    Segments,
    dynamic_substeps,
    make_segments,
    noise_level,
    output_columns,
    pack_state,
    savgol,
    savgol_coeffs,
    on_slot_rows,
    segment_slots,
    slot_rows,
    unpack_state,
    white_noise_std,
)
from jaxflex.fit.solve import (
    CostBound,
    Padding,
    Solution,
    cost,
    covariance,
    cluster_robust_covariance,
    segment_robust_covariance,
    discretisation_bias,
    induced_shift,
    integration_error,
    remaining_step,
    refined,
    step_doubling_error,
    gap,
    least_squares,
    problem_residuals,
    residuals,
    simulated_outputs,
    trace_solver,
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
    "segment_robust_covariance", "discretisation_bias", "gap", "induced_shift", "remaining_step",
    "integration_error", "refined", "step_doubling_error", "get_value", "is_fitted", "least_squares",
    "make_segments", "noise_level", "output_columns", "pack_state", "params_of_plant",
    "problem_residuals", "residuals", "simulated_outputs", "trace_solver",
    "relative", "savgol", "savgol_coeffs", "set_values", "unpack_state", "white_noise_std",
]

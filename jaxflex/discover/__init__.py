"""Discrepancy discovery: where do model and log disagree, which named effect is missing, and
how much does adding it close the gap (docs/spec.md section 8). A workflow on the fitting
engine ``jaxflex.fit``; it defines no solver, replay, reparametrisation or log reader.

Workflow (``discover``), for one joint:

1. Split the log in time: the first ``train_frac`` for fitting, the rest held out. Cut both in
   short segments (``segment`` seconds), each replayed open loop under the logged torque from
   its own start state (``jaxflex.fit.Problem`` with ``free_starts=True`` and no continuity
   weight). This is how a closed-loop log of an integrating plant can be replayed honestly:
   one long open-loop replay drifts without bound, short segments do not. The start states
   (q1, q1', q2, q2', z) are unknowns fitted from each segment's samples, first guessed from
   the log (angles, Savitzky-Golay velocities, and the bristle load that balances the link's
   inverse dynamics, ``bristle_entries``; z is fitted within the friction's capacity,
   ``Problem.bounded_z``, since a segment that starts in stick or just after a reversal
   carries a partial load that the steady state of its velocity cannot): a start *estimated*
   from noisy, quantised angles is off by far more than the noise (velocity errors grow
   linearly over the segment, z and the rotor velocity are not measured), and a refit from
   such starts bends the parameters to absorb the error and buries small effects.
2. Refit the nominal model (I, J, K, Fc, Fs, sigma2; vs, sigma0, sigma1 kept, they are poorly
   identifiable from positions, docs/spec.md section 9) and the training start states with
   the engine's Levenberg-Marquardt (the structured multiple-shooting solve), so that a
   parameter mismatch is not taken for missing physics.
3. Gap metric (``Problem.gap``): normalised RMS error of the simulated q1 and q2 over the
   held-out segments, relative to the measured motion within each segment. 0 is perfect, 1 is
   as bad as predicting no motion. The held-out segments' start states are fitted with the
   parameters fixed (``fit_starts``): no parameter sees the held-out data, and every model
   gets the same freedom there.
4. Localise: inverse-dynamics torque residuals (``FlexibleJointPlant.torque_residuals``) on the
   link and rotor sides, binned against link velocity (with sign), position, spring deflection,
   deflection rate and rotor velocity, their spectra, and the worst time windows, next to a
   noise floor from encoder quantisation plus measured angle noise.
5. Screen every candidate effect (``screen``: a few Levenberg-Marquardt steps on the training
   segments from the current fit, then the Gauss-Newton decrement, the further drop of the
   training residual a full step would bring: from the current optimum with a candidate that
   starts at no effect, the score test) and fit fully only the shortlist (``shortlist``: those
   whose predicted residual could make them significant and that come near the best of them,
   and the best in any case); a candidate the screen leaves out is reported with its screen
   values and marked ``screened_out``, with no held-out gap. Fit each shortlisted candidate
   (nominal parameters refitted with it) and score it: held-out gap,
   BIC on the training residual, and an F-test on the training residual sums of squares with an
   effective sample count (the residuals of a simulated trajectory are strongly correlated; the
   count is divided by their integrated autocorrelation time). A candidate is significant when
   the F-test p-value is below ``alpha``, its BIC is lower and it lowers the held-out gap by at
   least ``min_gain``. Among significant candidates within ``parsimony`` of the lowest held-out
   gap, the one with the fewest parameters is added (``select``); when significant rivals come
   within ``contest`` (3x) of its held-out gap, they and it are polished first (``settle``)
   and the pick is made again (``contest``: a fit of a few dozen steps can stop several times
   above its optimum); the search repeats until nothing is significant; an effect whose
   polished refit does not lower the held-out gap is dropped, and so is one that is no
   longer significant at its polished optimum against the base refitted from there without
   it (``without_effect``; a candidate's fit can lift the shared parameters out of a local
   minimum of the base and then let the effect go): the better base is kept and the round
   repeated once on it (``MAX_REBASE``). Every round records the Akaike and Schwarz weights
   of "none" and each candidate.
6. Gap floor (``gap_floor``): the held-out gap a correct model reaches on this log, by a
   parametric bootstrap through the workflow's own held-out steps (noise, quantisation,
   fitted starts, replay). The answer is the first effect added, or ``indistinguishable`` when
   candidates of its size explain the log as well within its noise (``tied``: not told apart
   by both the Akaike difference and a paired held-out test per segment, first on the pooled
   residual, then each encoder at its own noise level, ``break_tie``; all are reported in
   the evidence, none is guessed); else ``none`` when the gap is
   within ``unexplained_factor`` x the floor (+3 bootstrap sd), ``unexplained`` when it stays
   above: something is missing that the library does not describe, and the localisation says
   where to look. ``unexplained`` too when effects were added but the gap stays above and
   they close less than ``explained_min`` (3/4) of its excess over the floor
   (``explained_fraction``): a partial explanation, listed in ``effects``, not the answer.

The nominal model comes as the kind its file describes (``DiscoverConfig.model``,
``nominal_for_model``: a flexible joint as it is, a rigid model as two halves joined by a
stiff spring, a rotor subsystem with its link side from a rigid fit of the log); a candidate
the file's declared axis says cannot act is not tried (``cannot_act``). The file's own
effects are set aside and tried as candidates; where the model without them cannot be refit
on the log (a parameter runs away, or its replay is worse than no motion), they stay in the
base, fitted with it, their families not candidates (``DiscoverResult.kept``). The report carries
every round's tie (``effect_ties``) and the final model's residual analysis as MATLAB's
``resid`` gives it (``residual_analysis``); a numerical failure of a fit is a
``SolverFailure`` naming the fit, not a bad input.

All candidates share one compiled model: the plant holds every candidate effect, wrapped in
``jaxflex.core.effects.Gated`` (gate 0 or 1), and the engine's parameter mask says which are fitted;
both are data, so the solver compiles once per log shape. The gates are run-time branches
(``lax.cond``, one per hook for all candidates together: ``jaxflex.core.effects.effect_torque``),
so an inactive candidate costs no arithmetic per substep. A family's higher order is not a
candidate: its workspace (the candidates and that order, ``Workspaces``) is built only once
the order below is in the model, so that the rounds' programs and Jacobians carry no order a
run does not reach. Every fit ends at the engine's
statistical stop measured against its own residual variance (``relative_stop``), and the base
each round compares with is settled (``settle``).

Independent fits run side by side on the cores (``jaxflex.runtime.ahead.side_by_side``): the
candidates' starts, screens and full fits, the polish of a contest or a tie, the two held-out
start fits and the floor's draws. The answers do not depend on the number of workers.

The modules, bottom up: ``candidates`` (``Model``, the gated ``Workspace`` and the run's
``Workspaces``, ``CandidateFit``),
``fitting`` (fits, held-out starts, the gap floor), ``localisation`` (residual signatures and
the candidates' first guesses), ``ranking`` (select, contest, ties, evidence weights),
``config`` (``DiscoverConfig``, the nominal model's kind), ``screening`` (screen, shortlist,
scores), ``result`` (``DiscoverResult``, the answer) and ``workflow`` (``discover``,
``discover_joints``).
"""

from jaxflex.discover.candidates import (
    bristle_entries,
    CandidateFit,
    fitted_count,
    fitted_names,
    Model,
    NOMINAL_FIT,
    STEP_FLOOR,
    typical_effect,
    within_capacity,
    Workspace,
    workspace,
    Workspaces,
)
from jaxflex.discover.fitting import (
    DECREMENT,
    finer,
    fit_model,
    FIT_SOLVER,
    fit_starts,
    gap_floor,
    held_out_mse,
    held_out_starts,
    held_out_traces,
    made_ahead,
    PINNED,
    PINNED_FC,
    progress_stop,
    relative_stop,
    released,
    residual_analysis,
    segment_errors,
    settle,
    STALL,
    STALL_WINDOW,
    start_residuals,
    trace_fit,
    with_held_out,
    without_effect,
)
from jaxflex.discover.localisation import (
    Localisation,
    localise,
    start_effect,
    welch,
)
from jaxflex.discover.ranking import (
    autocorrelation_time,
    break_tie,
    contest,
    effective_count,
    evidence_weights,
    output_evidence,
    output_residuals,
    paired_p_value,
    representative,
    revisit_tie,
    select,
    settle_side_by_side,
    tie_by_output,
    tied,
)
from jaxflex.discover.config import (
    AXES,
    cannot_act,
    declared_axes,
    DISCOVER_MODELS,
    DiscoverConfig,
    model_kind_of,
    nominal_for_model,
    RIGID_MODE_STEP,
    SolverFailure,
    spring_mode,
    STABLE_MODE_STEP,
)
from jaxflex.discover.screening import (
    candidate_error,
    candidate_score,
    fit_candidate,
    fit_record,
    score,
    screen,
    screened_out,
    shortlist,
    training_evidence,
    unresolved,
)
from jaxflex.discover.result import (
    DiscoverResult,
    effect_ties,
    explained_fraction,
    final_answer,
    unexplained_limit,
)
from jaxflex.discover.workflow import (
    discover,
    discover_joints,
    MAX_REBASE,
)

__all__ = [
    "autocorrelation_time", "AXES", "break_tie", "bristle_entries", "candidate_error",
    "candidate_score", "CandidateFit", "cannot_act", "contest", "declared_axes", "DECREMENT",
    "discover", "discover_joints", "DISCOVER_MODELS", "DiscoverConfig", "DiscoverResult",
    "effect_ties", "effective_count", "evidence_weights", "explained_fraction", "final_answer",
    "finer", "fit_candidate", "fit_model", "fit_record", "FIT_SOLVER", "fit_starts",
    "fitted_count", "fitted_names", "gap_floor", "held_out_mse", "held_out_starts",
    "held_out_traces", "Localisation", "localise", "made_ahead",
    "MAX_REBASE", "Model", "model_kind_of", "NOMINAL_FIT", "nominal_for_model",
    "output_evidence", "output_residuals", "paired_p_value", "PINNED", "PINNED_FC",
    "progress_stop", "relative_stop", "released", "representative", "residual_analysis",
    "revisit_tie", "RIGID_MODE_STEP", "score", "screen", "screened_out", "segment_errors",
    "select", "settle", "settle_side_by_side", "shortlist", "SolverFailure", "spring_mode",
    "STABLE_MODE_STEP", "STALL", "STALL_WINDOW", "start_effect", "start_residuals",
    "STEP_FLOOR", "tie_by_output", "tied", "trace_fit",
    "training_evidence", "typical_effect", "unexplained_limit", "unresolved", "welch",
    "with_held_out", "within_capacity", "without_effect", "Workspace", "workspace",
    "Workspaces",
]

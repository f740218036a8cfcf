"""The settings of a discovery run (``DiscoverConfig``) and its nominal model: the kind of
model a parameter file describes and how it is replayed (``nominal_for_model``), the axes it
declares and the candidates they rule out (``cannot_act``), and ``SolverFailure``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from jaxflex.io.errors import ConfigError
from jaxflex.core.effects import EFFECTS
from jaxflex.io.logs import Log
from jaxflex.io.params import Params


#: The model kinds ``discover`` takes a parameter file as (``DiscoverConfig.model``, the
#: command line's ``--model``); each is replayed as the flexible joint the workflow fits
#: (``nominal_for_model``).
DISCOVER_MODELS: tuple[str, ...] = ("flexible", "rigid", "rotor")

#: A rigid model is replayed as two halves of its inertia joined by a spring whose internal
#: mode is at RIGID_MODE_STEP / h [rad/s], h the replay's step: far above a loop's bandwidth,
#: well inside RK4's stability limit (600 rad/s at 1 ms, as ``studies/discover_emps.py``).
RIGID_MODE_STEP: float = 0.6

#: RK4 is stable for an undamped mode of frequency omega while omega h < 2 sqrt(2) (its
#: stability region on the imaginary axis); discover refuses a nominal model whose spring
#: mode is past STABLE_MODE_STEP of that.
STABLE_MODE_STEP: float = 0.9 * 2.0 * math.sqrt(2.0)


#: What a parameter file may declare of its axis (top-level ``axis``: one value, or one per
#: joint; docs/spec.md section 7). The effects that then cannot act say so themselves
#: (``AbstractEffect.cannot_act_on``): about a vertical rotation axis gravity has no moment,
#: and on a prismatic axis no angle for its sine.
AXES: tuple[str, ...] = ("horizontal", "vertical", "prismatic")


def declared_axes(params: Params) -> list[str] | None:
    """The axis kind of each joint that ``params`` declares (top-level ``axis``: one of
    ``AXES``, or a list of them, one per joint), or None when it declares none.

    **Arguments:**

    - `params`: the parameter file's contents.

    **Returns:**

    One name of ``AXES`` per joint, or None.

    **Raises:**

    `jaxflex.io.params.ParamsError` for a value not in ``AXES`` or a list of the wrong
    length."""
    from jaxflex.io.params import ParamsError

    a = params.extra.get("axis")
    if a is None:
        return None
    values = [a] * params.n if isinstance(a, str) else a
    if not isinstance(values, list) or len(values) != params.n or not all(
            isinstance(v, str) and v in AXES for v in values):
        raise ParamsError(f"axis: expected one of {sorted(AXES)} or a list of {params.n} of "
                          f"them, got {a!r}")
    return list(values)


def cannot_act(params: Params) -> dict[str, str]:
    """The effects that cannot act on a one-joint ``params``'s axis as it declares it
    (``declared_axes``; each effect's ``cannot_act_on``), each with the reason in words;
    empty when it declares nothing."""
    axes = declared_axes(params)
    if not axes:
        return {}
    return {name: f"the parameter file declares the axis {axes[0]!r}: {name} cannot act"
            for name, cls in EFFECTS.items() if axes[0] in cls.cannot_act_on}


class SolverFailure(RuntimeError):
    """A fit inside discovery failed numerically (a non-converging eigen-decomposition, a
    floating point error): not a bad input, the message names the fit (``stage``)."""

    def __init__(self, stage: str, error: BaseException | str):
        self.stage = stage
        self.error = error
        what = error if isinstance(error, str) else f"{type(error).__name__}: {error}"
        super().__init__(f"discover: solver failure in {stage}: {what}")


def spring_mode(params: Params) -> float:
    """The fastest undamped internal mode of the joint(s) [rad/s]: omega = sqrt(K (1/I + 1/J))
    (the two inertias of eq. 3 joined by the spring K; section 1 of docs/spec.md)."""
    I, J, K = (np.asarray(params.plant[k], float) for k in ("I", "J", "K"))
    return float(np.max(np.sqrt(K * (1.0 / I + 1.0 / J))))


def model_kind_of(params: Params) -> str | None:
    """The model kind an identification file was fitted with (``identification.start.kind``;
    in files that carry no verdict, ``identification.model`` as a name), or None when the
    file says none."""
    ident = params.extra.get("identification")
    if not isinstance(ident, dict):
        return None
    start = ident.get("start")
    for k in (start.get("kind") if isinstance(start, dict) else None, ident.get("model")):
        if isinstance(k, str):
            return k
    return None


def nominal_for_model(params: Params, model: str, log: Log,
                      step: float) -> tuple[Params, Log, str]:
    """The flexible joint that ``discover`` replays for a parameter file of model ``model``.

    - "flexible": the file as it is.
    - "rigid" (Jx q1'' = u - F, eq. 37, Jx = I + J): two halves of Jx joined by a spring with
      its internal mode at ``RIGID_MODE_STEP`` / ``step`` [rad/s], friction on the link side;
      a log without q2 reads q2 = q1 (one encoder on a stiff axis).
    - "rotor" (the rotor subsystem: J, K and the motor side; the link side not identified):
      J and K from the file, the link inertia I = Jt - J (at least Jt / 10) and a LuGre
      friction on the link from the rigid least-squares fit of the log's own motor encoder
      (``jaxflex.validate.rigid_torque_fit``: Fc, Fs = 1.2 Fc, vs = 0.05 rad/s, sigma0 =
      Fc / 1e-4 rad, sigma1 = 0, sigma2 = Fv), as ``studies/discover_kuka.py``.

    **Arguments:**

    - `params`: the nominal parameters (one joint).
    - `model`: one of ``DISCOVER_MODELS``.
    - `log`: the one-joint log discovery runs on.
    - `step`: the replay's integration step [s] (sample period / substeps).

    **Returns:**

    The parameters to replay, the log (q2 filled for a rigid model), and a one-line note of
    what was done ("" for "flexible").

    **Raises:**

    `ValueError` for an unknown model, or a rotor model on a log without torque."""
    if model not in DISCOVER_MODELS:
        raise ValueError(f"discover: model must be one of {DISCOVER_MODELS}, got {model!r}")
    d = params.to_dict()
    if model == "rigid":
        Jx = float(np.ravel(params.plant["I"])[0]) + float(np.ravel(params.plant["J"])[0])
        half = Jx / 2.0
        omega = RIGID_MODE_STEP / step
        d["plant"] = {**d["plant"], "I": half, "J": half, "K": omega**2 * half / 2.0}
        if log.q2 is None:
            log = dataclasses.replace(log, q2=log.q1)
        note = (f"rigid model: inertia {Jx:.4g} as two halves joined by K {omega**2 * half / 2:.4g}"
                f" (internal mode {omega:.0f} rad/s)")
        return Params.from_dict(d), log, note
    if model == "rotor":
        from jaxflex.validate import rigid_torque_fit

        rigid = rigid_torque_fit(log)
        J = float(np.ravel(params.plant["J"])[0])
        Fc, Fv = abs(rigid["Fc"]), abs(rigid["Fv"])
        I = max(rigid["Jt"] - J, 0.1 * abs(rigid["Jt"]))
        if not (math.isfinite(I) and I > 0 and Fc > 0):
            raise ValueError(f"discover: the rigid fit of the log gives no usable link side "
                             f"(Jt {rigid['Jt']:.4g}, Fc {rigid['Fc']:.4g}) for the rotor model")
        d["plant"] = {**d["plant"], "I": I}
        d["friction"] = {"Fc": Fc, "Fs": 1.2 * Fc, "vs": 0.05, "sigma0": Fc / 1e-4,
                         "sigma1": 0.0, "sigma2": max(Fv, 1e-9)}
        note = (f"rotor model: J, K from the file; link I {I:.4g}, Fc {Fc:.4g}, sigma2 "
                f"{Fv:.4g} from the log's rigid fit")
        return Params.from_dict(d), log, note
    return params, log, ""


@dataclasses.dataclass
class DiscoverConfig:
    """Settings of ``discover``: segment length [s], training fraction, LM steps, substeps per
    sample, significance level, minimal relative held-out gain, max number of effects added,
    the candidate names (default: all registered effects), the parsimony margin, the
    factor over the gap floor above which a remaining gap counts as unexplained, the
    Akaike difference below which, and the held-out paired test's p-value above which, two
    equally sized candidates are not told apart (``tied``); and the screen of each round
    (``screen``, ``shortlist``): LM steps per candidate (0: no screen, every candidate is
    fitted fully), the share of the best predicted drop a candidate must explain to be
    fitted, and how many of the best predicted are fitted in any case; the factor of the
    winner's held-out gap within which significant rivals are polished before the pick
    (``contest``; at most 1: never); and the share of the held-out gap's excess over the
    floor that the effects added must close for the answer to name them when the final gap
    stays unexplained (``explained_min``, ``explained_fraction``; 0: always name them); the
    kind of model the nominal parameters describe (``model``, one of ``DISCOVER_MODELS``:
    ``nominal_for_model``); the highest order of an effect family discovery fits
    (``max_order``; 1: each family's simplest member only, ``jaxflex.discover.orders``)."""

    segment: float = 0.3
    train_frac: float = 0.7
    max_steps: int = 30
    substeps: int = 1
    alpha: float = 1e-3
    min_gain: float = 0.15
    max_effects: int = 3
    candidates: Sequence[str] | None = None
    parsimony: float = 0.1
    unexplained_factor: float = 2.0
    decisive: float = 10.0
    tie_alpha: float = 0.05
    screen_steps: int = 3
    screen_keep: float = 0.5
    screen_least: int = 1
    contest: float = 3.0
    explained_min: float = 0.75
    model: str = "flexible"
    max_order: int = 3

    def __post_init__(self) -> None:
        """Refuse a setting outside its range (``ConfigError`` naming it)."""
        ranges = {  # setting -> (lowest, highest, lowest excluded)
            "segment": (0.0, math.inf, True), "train_frac": (0.1, 0.9, False),
            "max_steps": (1, math.inf, False), "substeps": (1, 16, False),
            "alpha": (0.0, 1.0, True), "min_gain": (0.0, math.inf, False),
            "max_effects": (0, math.inf, False), "parsimony": (0.0, math.inf, False),
            "unexplained_factor": (1.0, math.inf, False), "decisive": (0.0, math.inf, False),
            "tie_alpha": (0.0, 1.0, True), "screen_steps": (0, math.inf, False),
            "screen_keep": (0.0, 1.0, False), "screen_least": (0, math.inf, False),
            "contest": (0.0, math.inf, False), "explained_min": (0.0, 1.0, False),
            "max_order": (1, math.inf, False),
        }
        for name, (lo, hi, open_lo) in ranges.items():
            v = getattr(self, name)
            integral = isinstance(lo, int) and not isinstance(v, bool)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            ok = ok and (v > lo if open_lo else v >= lo) and v <= hi
            if integral and ok and int(v) != v:
                ok = False
            if not ok:
                left = "(" if open_lo else "["
                raise ConfigError(name, f"must be {'an integer ' if integral else ''}in "
                                        f"{left}{lo:g}, {hi:g}], got {v!r}")
        if self.model not in DISCOVER_MODELS:
            raise ConfigError("model", f"must be one of {DISCOVER_MODELS}, got {self.model!r}")

"""A full start for identification from the log alone: the model kind the log's encoders
suggest, and every parameter from linear least squares on the inverse dynamics (IDIM-LS, the
EMPS benchmark's own reference method: the equations of motion are linear in the inertia,
stiffness and the Coulomb and viscous friction, evaluated on filtered derivatives of the
measured angles).

For each joint (docs/spec.md section 1, one joint of eq. 3 with M = I, a constant):

    rigid (eq. 37):  tau = Jx q1'' + sigma2 q1' + Fc sign(q1') - offset
    flexible:        tau = J q2'' + K (q2 - q1) - offset          (rotor line)
                     K (q2 - q1) = I q1'' + sigma2 q1' + Fc sign(q1')   (link line)
    rotor:           tau = J q2'' + K (q2 - q1) + Fm tanh(q2'/w) + b q2' + K s q1 - offset

(``offset`` is the ``torque_offset`` effect's: the plant receives tau + offset). The rotor
kind's line carries the effects it needs on a real two-encoder log (``ROTOR_EFFECTS``):
motor friction with a width w = ``ROTOR_FRICTION_WIDTH`` (a sign in effect), the link
encoder's scale error s (``encoder_scale``) and the torque offset. Its velocity coefficient
b is the motor's viscous friction less K times the link encoder's time skew (``encoder_skew``:
the two are collinear, q1' ~ q2'); the start gives it to the friction where it is positive
and to the skew where it is negative.

The model kind (``suggest_model``) follows the encoders and what the log's owner declares of
the link side (``LINK_SIDES``): one encoder is rigid; two encoders are flexible, or rotor
where the link side belongs to a multi-axis arm that one joint's model cannot describe. The
parameters the inverse dynamics cannot see (Fs, vs, sigma0, sigma1: the Stribeck hump and the
bristles act at speeds and displacements below what filtered derivatives resolve) get
scale-aware defaults: Fs = 1.2 Fc, vs 5% of the largest speed, a pre-sliding displacement
Fc / sigma0 of 1e-3 of the travel, and bristle damping sigma1 = 0.04 sqrt(sigma0 Jx) (the
paper's link: 0.1 N m s/rad).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from jaxflex.core.effects.library import EncoderScale
from jaxflex.fit import noise_level
from jaxflex.fit.inverse import linear_fit, measured_motion, rigid_regressors
from jaxflex.io.logs import Log
from jaxflex.io.params import Params

#: Savitzky-Golay window [samples] of the derivatives the inverse dynamics use.
WINDOW: int = 31
#: Samples moving slower than this share of the 99th-percentile speed are left out of the
#: friction regressions (sign(q') is ill-defined near rest).
MIN_SPEED_SHARE: float = 0.02
#: A torque offset is kept in the start when its t-statistic exceeds this.
OFFSET_T: float = 5.0
#: Motor-friction width w [rad/s] of the rotor kind, tanh(q2'/w): a sign in effect. At
#: standstill a drive holds torque and the sign of the encoder's creep velocity carries its
#: direction; a width above the velocity noise loses that (on the KUKA KR300 axes a width of
#: 0.01 rad/s lost to the rigid model, ``studies/kuka_flexible.py``).
ROTOR_FRICTION_WIDTH: float = 1e-4
#: The effects of the rotor kind's start (module docstring): what a real two-encoder log
#: needs beside the spring and the rotor inertia.
ROTOR_EFFECTS: tuple[str, ...] = ("motor_friction", "torque_offset", "encoder_skew",
                                  "encoder_scale")
#: What a log's owner may declare of each joint's link side (a parameter file's top-level
#: ``link_side``, ``identify --link-side``, a shipped data set's ``NamedData.link_side``):
#: "single", the link side is the one joint a single-joint model describes (the same as no
#: declaration); "coupled", it belongs to a multi-axis arm whose other axes, gravity and
#: counterbalance act on it, which a single-joint model cannot describe.
LINK_SIDES: tuple[str, ...] = ("single", "coupled")


class StartError(ValueError):
    """The log does not determine a start (too little motion, a non-physical estimate)."""


@dataclasses.dataclass(frozen=True)
class DataStart:
    """A start from the log's inverse dynamics.

    Attributes:
        params: the start parameter set (plant, friction, and a ``torque_offset`` effect where
            the log shows one).
        model: the model kind it was computed for.
        fits: per joint, the least-squares estimates with their standard errors and the
            regression's relative residual (``{"Jx": (value, stderr), ...}``).
    """

    params: Params
    model: str
    fits: list[dict[str, Any]]

    def summary(self) -> str:
        """One line per joint: the inverse-dynamics estimates."""
        rows = []
        for j, f in enumerate(self.fits):
            vals = ", ".join(f"{k} {v[0]:.4g} +- {v[1]:.2g}" for k, v in f.items()
                             if isinstance(v, tuple))
            rows.append(f"joint {j}: {vals}")
        return "\n".join(rows)


def link_sides(value: str | list[str] | None, n: int, where: str = "link_side"
               ) -> list[str] | None:
    """Each joint's declared link side (``LINK_SIDES``) from one value or a list of ``n``.

    Arguments:
        value: "single", "coupled", a list of them (one per joint), or None (no
            declaration).
        n: the number of joints.
        where: what the value came from, for the error.

    Returns:
        One name of ``LINK_SIDES`` per joint, or None.

    Raises:
        ValueError: a value not in ``LINK_SIDES`` or a list of the wrong length.
    """
    if value is None:
        return None
    values = [value] * n if isinstance(value, str) else value
    if not isinstance(values, list) or len(values) != n or not all(
            isinstance(v, str) and v in LINK_SIDES for v in values):
        raise ValueError(f"{where}: expected one of {list(LINK_SIDES)} or a list of {n} of "
                         f"them, got {value!r}")
    return list(values)


def suggest_model(log: Log, link_side: list[str] | None = None) -> tuple[str, str]:
    """The model kind a log's encoders and its declared link side support.

    Arguments:
        log: the log (docs/spec.md section 6).
        link_side: each joint's declared link side (``LINK_SIDES``, ``link_sides``), or None
            (none declared: "single").

    Returns:
        ``(kind, why)``: "rigid" when the log has no q2 or its q2 equals q1 within the
        encoders' resolution (one encoder mapped to both columns); with two encoders
        "rotor" where a joint's link side is declared "coupled" (a multi-axis arm: the link
        motion is taken from the measurement, and the spring's deflection carries whatever
        the link side does), else "flexible".
    """
    if log.q2 is None:
        return "rigid", "the log has no rotor angle q2"
    q1, q2 = np.asarray(log.q1, float), np.asarray(log.q2, float)
    d = np.max(np.abs(q2 - q1), axis=0)
    step = max(noise_level(q1[:, j])["step"] for j in range(log.n))
    if np.all(d <= 2 * step):
        return "rigid", (f"q2 equals q1 within {float(np.max(d)):.3g} (the encoder's step "
                         f"{step:.3g}): one encoder mapped to both columns")
    if link_side is not None and "coupled" in link_side:
        which = [j for j, s in enumerate(link_side) if s == "coupled"]
        joints = "the link side" if log.n == 1 else f"joint(s) {which}'s link side"
        return "rotor", (f"two encoders, and {joints} is declared coupled (part of a "
                         "multi-axis arm that a single-joint model cannot describe): the "
                         "rotor subsystem, driven by the measured link motion")
    return "flexible", "the log has distinct link and rotor angles"


def check_model(log: Log, model: str, link_side: list[str] | None = None) -> tuple[str, str]:
    """The model kind ``identify`` fits to ``log``: ``model``, or the suggested one for
    "auto".

    Arguments:
        log: the log.
        model: "auto" or one of ``jaxflex.sim.step.MODEL_KINDS``.
        link_side: each joint's declared link side (``suggest_model``), or None.

    Returns:
        ``(kind, why)``.

    Raises:
        ValueError: a two-encoder model (flexible, rotor, link) asked of a log with one
            encoder, naming ``--model rigid``.
    """
    suggested, why = suggest_model(log, link_side)
    if model == "auto":
        return suggested, why
    if model in ("flexible", "rotor", "link") and suggested == "rigid":
        raise ValueError(f"the {model} model needs two encoders, but {why}; use the rigid "
                         "model (--model rigid)")
    return model, "as given"


def _joint(log: Log, j: int, model: str) -> dict[str, Any]:
    """The inverse-dynamics estimates of joint ``j`` (module docstring)."""
    w = min(WINDOW, (log.N // 2) * 2 - 1)
    if w < 7:
        raise StartError(f"joint {j}: {log.N} samples are too few for inverse dynamics")
    m = measured_motion(log.joint(j), w, kind="rigid" if model == "rigid" else "flexible",
                        smooth=True)
    tau, q1, v1, a1 = m.tau[:, 0], log.q1[:, j], m.v1[:, 0], m.a1[:, 0]
    top = float(np.quantile(np.abs(v1), 0.99))
    if not top > 0:
        raise StartError(f"joint {j}: the link does not move")
    moving = np.abs(v1) > MIN_SPEED_SHARE * top
    edge = np.zeros_like(moving)
    edge[w:-w] = True  # the filter's ends are one-sided
    sel = moving & edge
    if sel.sum() < 20:
        raise StartError(f"joint {j}: too few moving samples for inverse dynamics")
    sgn = np.sign(v1)
    one = np.ones_like(q1)
    out: dict[str, Any] = {}
    if model == "rigid":
        x, se, rel = tuple(linear_fit(rigid_regressors(v1, a1)[sel], tau[sel]))
        out.update(Jx=(float(x[0]), float(se[0])), sigma2=(float(x[1]), float(se[1])),
                   Fc=(float(x[2]), float(se[2])), offset=(float(-x[3]), float(se[3])))
    else:
        q1s, q2s, v2, a2 = m.q1[:, 0], m.q2[:, 0], m.v2[:, 0], m.a2[:, 0]
        d = q2s - q1s
        if model == "rotor":
            # the rotor line with its effects (module docstring) on every interior sample
            A = np.column_stack([a2, d, np.tanh(v2 / ROTOR_FRICTION_WIDTH), v2, q1s, one])
            x, se, rel_r = tuple(linear_fit(A[edge], tau[edge]))
            J, K, Fm, b, Ks, c = x
            out.update(J=(float(J), float(se[0])), K=(float(K), float(se[1])),
                       Fm=(float(Fm), float(se[2])), b=(float(b), float(se[3])),
                       scale=(float(-Ks / K), float(se[4] / abs(K))),
                       offset=(float(-c), float(se[5])))
            spring = K * (d + (Ks / K) * q1s)
        else:
            # rotor line on every interior sample (no friction there)
            A = np.column_stack([a2, d, one])[edge]
            x, se, rel_r = tuple(linear_fit(A, tau[edge]))
            J, K, c = x
            out.update(J=(float(J), float(se[0])), K=(float(K), float(se[1])),
                       offset=(float(-c), float(se[2])))
            spring = K * d
        # link line with the rotor line's spring torque
        A = np.column_stack([a1, v1, sgn])[sel]
        y, sy, rel = tuple(linear_fit(A, spring[sel]))
        out.update(I=(float(y[0]), float(sy[0])), sigma2=(float(y[1]), float(sy[1])),
                   Fc=(float(y[2]), float(sy[2])))
        out["rotor_residual"] = rel_r
        out["Jx"] = (float(y[0] + J), float(math.hypot(sy[0], se[0])))
    out["relative_residual"] = rel
    out["speed"] = top
    out["travel"] = float(np.ptp(q1))
    return out


def _check(fit: dict[str, Any], j: int, model: str) -> None:
    """Refuse a non-physical estimate, naming the likely cause."""
    # the rotor kind takes the link motion from the log: its link line describes nothing
    names = {"rigid": ("Jx",), "rotor": ("J", "K")}.get(model, ("J", "K", "I"))
    for k in names:
        v = fit[k][0]
        if not v > 0:
            raise StartError(
                f"joint {j}: the inverse dynamics give {k} = {v:.4g} <= 0; the torque's sign "
                "may be flipped against the angles, the angles may not be the torque's axis, "
                + ("or the log may be of a rigid axis (use --model rigid)" if model != "rigid"
                   else "or the log may be too short"))


def start_from_data(log: Log, model: str = "flexible") -> DataStart:
    """A full parameter set for ``log`` from its inverse dynamics (module docstring).

    Arguments:
        log: the log, with columns tau, q1 (and q2 for the two-encoder models).
        model: "rigid", "flexible" (also the "link" subsystem's start) or "rotor".

    Returns:
        A ``DataStart``: I, J [kg m^2], K [N m/rad], the six LuGre parameters (docs/spec.md
        section 2; Fc and sigma2 estimated, the others by the defaults of the module
        docstring) and, where the log shows one (t-statistic above ``OFFSET_T``), a
        ``torque_offset`` effect [N m]. For "rotor": the ``ROTOR_EFFECTS`` (motor friction
        Fm [N m] and bm [N m s/rad] at width ``ROTOR_FRICTION_WIDTH``, the torque offset
        [N m], the encoder skew [s] and scale [rad/rad], the encoder offset 0: collinear
        with the torque offset); I and the LuGre parameters, which that kind does not use
        (the link motion is measured), are the link line's estimates where positive, else
        I = J.

    Raises:
        StartError: (a ``ValueError``) when the log lacks a column the model needs, moves
            too little, or the estimates are not physical (a flipped torque sign, a rigid
            axis under the flexible model).
    """
    kind = model if model in ("rigid", "rotor") else "flexible"
    if log.tau is None or log.q1 is None:
        raise StartError("a start from the data needs columns tau and q1")
    if kind != "rigid" and log.q2 is None:
        raise StartError(f"the {kind} model's start needs the rotor angle q2 (or use "
                         "--model rigid)")
    fits = []
    for j in range(log.n):
        f = _joint(log, j, kind)
        _check(f, j, kind)
        fits.append(f)
    plant: dict[str, list[float]] = {"I": [], "J": [], "K": []}
    fr: dict[str, list[float]] = {k: [] for k in ("Fc", "Fs", "vs", "sigma0", "sigma1",
                                                  "sigma2")}
    offsets = []
    rotor: dict[str, list[float]] = {k: [] for k in ("Fm", "bm", "skew", "scale")}
    for f in fits:
        Jx = f["Jx"][0]
        if kind == "rigid":
            I, J, K = Jx * 0.999, Jx * 1e-3, 1e6 * Jx
        else:
            I, J, K = f["I"][0], f["J"][0], f["K"][0]
        if kind == "rotor":
            I = I if I > 0 else J
            Jx = I + J
            # b = bm - K skew (module docstring): friction where positive, skew where not
            b, tau_std = f["b"][0], float(np.std(np.asarray(log.tau, float)))
            floor = 1e-6 * tau_std / max(f["speed"], 1e-12)
            rotor["Fm"].append(max(f["Fm"][0], 1e-6 * tau_std))
            rotor["bm"].append(max(b, floor))
            rotor["skew"].append(max(-b, 0.0) / K)
            lim = 0.99 * EncoderScale.LIMIT
            rotor["scale"].append(float(np.clip(f["scale"][0], -lim, lim)))
        Fc = max(f["Fc"][0], 1e-6 * max(abs(f["Fc"][0]), 1.0))
        sigma2 = max(f["sigma2"][0], 1e-9)
        z = 1e-3 * max(f["travel"], 1e-9)
        sigma0 = Fc / z
        plant["I"].append(I)
        plant["J"].append(J)
        plant["K"].append(K)
        fr["Fc"].append(Fc)
        fr["Fs"].append(1.2 * Fc)
        fr["vs"].append(0.05 * f["speed"])
        fr["sigma0"].append(sigma0)
        fr["sigma1"].append(0.04 * math.sqrt(sigma0 * max(Jx, 1e-300)))
        fr["sigma2"].append(sigma2)
        off, se = f["offset"]
        offsets.append(off if abs(off) > OFFSET_T * se or kind == "rotor" else 0.0)
    effects: dict[str, dict[str, list[float]]] = {}
    if kind == "rotor":
        n = log.n
        effects["motor_friction"] = {"Fm": rotor["Fm"], "bm": rotor["bm"],
                                     "width": [ROTOR_FRICTION_WIDTH] * n}
        effects["encoder_skew"] = {"skew": rotor["skew"], "offset": [0.0] * n}
        effects["encoder_scale"] = {"scale": rotor["scale"]}
    if any(o != 0.0 for o in offsets):
        effects["torque_offset"] = {"offset": offsets}
    params = Params.from_dict({"plant": plant, "friction": fr, "effects": effects})
    return DataStart(params=params, model=kind, fits=fits)

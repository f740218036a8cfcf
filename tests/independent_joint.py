"""An independent simulator of a flexible joint with LuGre friction, in plain numpy (fixed-step
RK4 of its own, not jaxflex's step): logs for the discovery tests made another way than
``jaxflex.identify.datagen``, with effects in forms of their own (a ripple's harmonics, a Stribeck
term on the rotor, a second-order current loop, a spring polynomial, LuGre levels that differ
by direction).

The joint (docs/spec.md section 1, one joint): I q1'' = K (q2 - q1) - F + link(q1, q1'),
J q2'' = a - K (q2 - q1) + rotor(q2, q2'), LuGre F (eq. 4-7); a PD loop on the rotor angle
toward a slow large swing plus a multisine, sampled at dt with a zero-order hold, saturated at
2 N m; optionally a spring torque beyond K (q2 - q1) and LuGre levels that differ by direction;
the applied torque a is the command u, or u through the second-order lag
a'' = wn^2 (u - a) - 2 zeta wn a'. The log holds the command u and the angles quantised to a
2^16-count link encoder (the rotor 50x finer) with half a count of white noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from jaxflex.io.logs import Log

#: The true joint: the paper's parameters (``jaxflex.io.presets.paper_params``) off by a few
#: percent, so that discovery's nominal refit has work to do.
TRUE = {"I": 0.074, "J": 0.0052, "K": 6.5, "Fc": 0.10, "Fs": 0.16, "vs": 0.05,
        "sigma0": 100.0, "sigma1": 0.1, "sigma2": 0.21}


def harmonics(terms: list[tuple[float, float, float]]) -> Callable[[float], float]:
    """sum A sin(N q + phi) [N m] over ``terms`` (A [N m], N [1/rad], phi [rad])."""
    def f(q: float) -> float:
        return sum(A * math.sin(N * q + phi) for A, N, phi in terms)
    return f


def simulate(t_final: float = 10.0, *, seed: int = 0, dt: float = 1e-3, substeps: int = 10,
             link_ripple: Callable[[float], float] | None = None,
             rotor_friction: Callable[[float], float] | None = None,
             lag: tuple[float, float] | None = None, swing: float = 1.2,
             spring: Callable[[float], float] | None = None,
             asymmetry: tuple[float, float] = (0.0, 0.0)) -> Log:
    """A closed-loop log of the joint of the module docstring.

    **Arguments:**

    - `t_final`: duration [s]; `dt`: sample period [s]; `substeps`: RK4 steps per sample.
    - `seed`: the multisine's phases and the encoder noise.
    - `link_ripple`: a torque [N m] added to the link equation as a function of q1 [rad].
    - `rotor_friction`: a torque [N m] added to the rotor equation as a function of q2' [rad/s].
    - `lag`: (wn [rad/s], zeta [-]) of a second-order lag from command to applied torque.
    - `swing`: amplitude [rad] of the slow 0.1 Hz swing of the reference.
    - `spring`: a torque [N m] added to the spring torque K (q2 - q1) as a function of the
      deflection q2 - q1 [rad].
    - `asymmetry`: (dFc, dFs) [N m]: LuGre's Coulomb and static levels are Fc + dFc and
      Fs + dFs while the link moves forward, Fc - dFc and Fs - dFs backward (inside g(v) of
      eq. 6, not as an added torque).

    **Returns:**

    A one-joint ``Log`` (t, tau, q1, q2)."""
    rng = np.random.default_rng(seed)
    p = TRUE
    freqs = np.array([0.7, 1.3, 2.1, 3.4])
    phases = rng.uniform(-math.pi, math.pi, freqs.size)

    def ref(t: float) -> float:
        return swing * math.sin(2 * math.pi * 0.1 * t) + 0.04 * float(
            np.sum(np.sin(2 * math.pi * freqs * t + phases)))

    def g(v: float) -> float:
        s = 1.0 if v >= 0.0 else -1.0
        Fc, Fs = p["Fc"] + s * asymmetry[0], p["Fs"] + s * asymmetry[1]
        return Fc + (Fs - Fc) * math.exp(-((v / p["vs"]) ** 2))

    def rhs(x: np.ndarray, u: float) -> np.ndarray:
        q1, v1, q2, v2, z, a, da = x
        applied = u if lag is None else a
        zdot = v1 - p["sigma0"] * abs(v1) * z / g(v1)
        F = p["sigma0"] * z + p["sigma1"] * zdot + p["sigma2"] * v1
        Ts = p["K"] * (q2 - q1) + (spring(q2 - q1) if spring else 0.0)
        acc1 = (Ts - F + (link_ripple(q1) if link_ripple else 0.0)) / p["I"]
        acc2 = (applied - Ts + (rotor_friction(v2) if rotor_friction else 0.0)) / p["J"]
        if lag is None:
            return np.array([v1, acc1, v2, acc2, zdot, 0.0, 0.0])
        wn, zeta = lag
        return np.array([v1, acc1, v2, acc2, zdot, da, wn**2 * (u - a) - 2 * zeta * wn * da])

    n = int(round(t_final / dt))
    h = dt / substeps
    x = np.zeros(7)
    res = 2 * math.pi / 2**16
    t = np.arange(n) * dt
    out = np.zeros((n, 3))
    kp, kd, tc = 8.0, 0.4, 0.005
    v2_est, q2_prev = 0.0, 0.0
    for i in range(n):
        q1m = round((x[0] + 0.5 * res * rng.standard_normal()) / res) * res
        q2m = round((x[2] + 0.5 * res / 50 * rng.standard_normal()) / (res / 50)) * (res / 50)
        v2_est += (dt / (tc + dt)) * ((q2m - q2_prev) / dt - v2_est) if i else 0.0
        q2_prev = q2m
        u = min(max(kp * (ref(t[i]) - q2m) - kd * v2_est, -2.0), 2.0)
        out[i] = (u, q1m, q2m)
        for _ in range(substeps):
            k1 = rhs(x, u)
            k2 = rhs(x + 0.5 * h * k1, u)
            k3 = rhs(x + 0.5 * h * k2, u)
            k4 = rhs(x + h * k3, u)
            x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return Log.from_arrays(t=t, tau=out[:, :1], q1=out[:, 1:2], q2=out[:, 2:3],
                           source="tests/independent_joint.py")

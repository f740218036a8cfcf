"""Where model and log disagree: inverse-dynamics torque residuals binned against the
quantities an effect depends on, their spectra and worst windows (``localise``), and the first
guesses of candidate effects drawn from those residuals (``start_effect``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import numpy as np

from jaxflex.discover.candidates import Model
from jaxflex.core.effects import AbstractEffect, EFFECTS
from jaxflex.fit import noise_level, savgol, savgol_coeffs
from jaxflex.fit.inverse import measured_motion, torque_residuals
from jaxflex.io.logs import Log
from jaxflex.io.params import Params


# ---------------------------------------------------------------------------- localisation


def _bin(x: np.ndarray, y: np.ndarray, bins: int = 15) -> dict[str, list[float]]:
    lo, hi = np.quantile(x, [0.01, 0.99])
    edges = np.linspace(lo, hi, bins + 1)
    k = np.clip(np.digitize(x, edges) - 1, 0, bins - 1)
    mean, se, centre = [], [], []
    for b in range(bins):
        m = k == b
        if m.sum() < 5:
            continue
        centre.append(float(0.5 * (edges[b] + edges[b + 1])))
        mean.append(float(y[m].mean()))
        se.append(float(y[m].std() / math.sqrt(m.sum())))
    return {"x": centre, "mean": mean, "se": se}


@dataclasses.dataclass
class Localisation:
    """Where the nominal model's inverse-dynamics residuals lie (module docstring, step 4):
    ``summary`` (JSON-ready: RMS residuals and noise floors [N m], side, signatures, spectra,
    worst windows) and ``series`` (per-sample arrays for plots and effect starts)."""

    summary: dict[str, Any]
    series: dict[str, np.ndarray]


def welch(x: np.ndarray, dt: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """Welch's power spectral density of ``x`` sampled every ``dt`` [s]: frequencies [Hz] and
    one-sided density [units^2 / Hz], from periodic-Hann-windowed segments of ``nperseg``
    samples overlapping by half, each less its mean, averaged (scipy's ``signal.welch``
    defaults, to which a test holds it; written here because importing ``scipy.signal``
    costs every command 0.55 s, ``jaxflex.fit.savgol_coeffs``)."""
    x = np.asarray(x, float)
    nperseg = min(int(nperseg), x.size)
    step = nperseg - nperseg // 2
    segs = np.lib.stride_tricks.sliding_window_view(x, nperseg)[::step]
    win = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(nperseg) / nperseg)
    spec = np.abs(np.fft.rfft((segs - segs.mean(axis=1, keepdims=True)) * win, axis=1)) ** 2
    spec *= dt / np.sum(win**2)
    spec[:, 1:nperseg // 2 + (nperseg % 2)] *= 2.0  # one-sided: all but DC (and Nyquist)
    return np.fft.rfftfreq(nperseg, dt), spec.mean(axis=0)


def localise(log: Log, params: Params, window: int = 41) -> Localisation:
    """Inverse-dynamics torque residuals [N m] of the nominal model on the link and rotor sides
    (``FlexibleJointPlant.torque_residuals`` with z at its steady state, so F = F_ss of
    eq. 35) from Savitzky-Golay derivatives; binned against link velocity (and its sign),
    position, deflection, deflection rate and rotor velocity; their spectra; the worst 1 s
    windows; and the noise floor (encoder quantisation and measured noise propagated through
    the same differentiation)."""
    dt = log.dt
    plant = params.to_plant(with_effects=False)
    q1s, q2s = log.q1[:, 0], log.q2[:, 0]
    motion = measured_motion(log.joint(0), window, smooth=True)
    motion = eqx.tree_at(lambda m: m.tau, motion, savgol(motion.tau, dt, 0, window))
    r_link, r_rot = (r[:, 0] for r in torque_residuals(plant, motion))
    q1, q2, v1, v2 = (a[:, 0] for a in (motion.q1, motion.q2, motion.v1, motion.v2))
    K, I, J = (float(np.ravel(a)[0]) for a in (plant.K, plant.links.I, plant.J))
    d, dd = q2 - q1, v2 - v1
    nf1, nf2 = noise_level(q1s), noise_level(q2s)
    c2 = savgol_coeffs(window, 3, deriv=2, delta=dt)
    c0 = savgol_coeffs(window, 3, deriv=0)
    g2, g0 = float(np.sqrt(np.sum(c2**2))), float(np.sqrt(np.sum(c0**2)))
    floor_link = math.sqrt((I * g2 * nf1["total_std"]) ** 2 + (K * g0 * nf2["total_std"]) ** 2)
    floor_rot = math.sqrt((J * g2 * nf2["total_std"]) ** 2 + (K * g0 * nf1["total_std"]) ** 2)
    fr, P1 = welch(r_link, dt, min(4096, len(r_link)))
    _, P2 = welch(r_rot, dt, min(4096, len(r_rot)))
    w = int(round(1.0 / dt))
    win = [
        (float(log.t[i * w]), float(np.sqrt(np.mean(r_link[i * w:(i + 1) * w] ** 2))),
         float(np.sqrt(np.mean(r_rot[i * w:(i + 1) * w] ** 2))))
        for i in range(len(r_link) // w)
    ]
    worst = sorted(win, key=lambda x: -(x[1] ** 2 + x[2] ** 2))[:3]
    moving = np.abs(v1) > 0.02
    mean_if = lambda m: float(r_link[m].mean()) if np.any(m) else 0.0
    summary = {
        "r_link_rms": float(np.sqrt(np.mean(r_link**2))),
        "r_rotor_rms": float(np.sqrt(np.mean(r_rot**2))),
        "noise_floor_link": floor_link, "noise_floor_rotor": floor_rot,
        "side": "link" if np.mean(r_link**2) > np.mean(r_rot**2) else "rotor",
        "mean_link_moving_pos": mean_if(moving & (v1 > 0)),
        "mean_link_moving_neg": mean_if(moving & (v1 < 0)),
        "mean_rotor": float(r_rot.mean()),
        "encoder_q1": nf1, "encoder_q2": nf2,
        "worst_windows": [{"t0": a, "link_rms": b, "rotor_rms": c} for a, b, c in worst],
        "signatures": {
            "link velocity": _bin(v1, r_link), "position": _bin(q1, r_link),
            "deflection": _bin(d, r_link), "deflection rate": _bin(dd, r_link),
            "rotor velocity": _bin(v2, r_rot),
            "link velocity (rotor side)": _bin(v1, r_rot), "deflection (rotor side)": _bin(d, r_rot),
        },
        "spectrum": {"f": fr.tolist(), "link": P1.tolist(), "rotor": P2.tolist()},
    }
    series = {"t": log.t, "r_link": r_link, "r_rotor": r_rot, "q1": q1, "v1": v1, "d": d,
              "dd": dd, "v2": v2, "q2": q2}
    return Localisation(summary=summary, series=series)


def _cleared(series: dict[str, np.ndarray], rotor: bool, vs: float | None,
             angle: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The angle [rad], the torque residual [N m] cleared of what a refit of the nominal model
    absorbs anyway, and the orthonormal basis Q of what was cleared, for a linear start
    (``_ResidualStart.ripple_fits``): the link's (q1, r_link) or the rotor's (q2,
    r_rotor). Cleared: the velocity, a Coulomb term, the deflection, the acceleration, given
    the model's ``vs`` [rad/s] the Stribeck term, a constant and, with ``angle``, the angle (a
    ripple is not a trend; a gravity is nearly one over a small travel). The link's residual
    holds the friction at its steady state (``localise``), which a link at rest does not
    follow: only its sliding samples are kept (a drive's point-to-point moves with dwells on
    the MuJoCo rig, a cogging of N = 45 1/rad: all samples gave N = 58.2, sliding ones
    45.0)."""
    q, r = (series["q2"], series["r_rotor"]) if rotor else (series["q1"], series["r_link"])
    v = series["v2"] if rotor else series["v1"]
    columns = [np.ones_like(q), v, np.tanh(v / 0.01), series["d"], np.gradient(v, series["t"])]
    if angle:
        columns.append(q)
    if vs is not None:  # a static friction off: the Stribeck term at the model's vs [rad/s]
        columns.append(np.tanh(v / 0.01) * np.exp(-((v / vs) ** 2)))
    if not rotor:
        sliding = np.abs(v) > 2.0 * (vs if vs is not None else 0.05)
        if np.mean(sliding) > 0.1:
            q, r = q[sliding], r[sliding]
            columns = [c[sliding] for c in columns]
    Q, _ = np.linalg.qr(np.column_stack(columns))
    return q, r - Q @ (Q.T @ r), Q


class _ResidualStart:
    """The ``jaxflex.core.effects.ResidualStart`` of one model in one round: its localisation's
    residual ``series``, the Stribeck velocity ``vs`` [rad/s] of its friction (None: no
    Stribeck column), its ``params`` and the replay's step ``h`` [s]; each side's cleared
    residual is computed once."""

    def __init__(self, series: dict[str, np.ndarray], vs: float | None,
                 params: Params | None = None, h: float = float("nan")) -> None:
        self._series, self._vs, self._params, self._h = series, vs, params, h
        self._cache: dict[tuple[str, bool], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    @property
    def h(self) -> float:
        return self._h

    def nominal(self, name: str) -> np.ndarray:
        if self._params is None:
            raise ValueError(f"no nominal parameters to read {name!r} from")
        sec = self._params.plant if name in self._params.plant else self._params.friction
        return np.asarray(sec[name], float)

    def _side(self, side: str, trend: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if side not in ("link", "rotor"):
            raise ValueError(f"side must be 'link' or 'rotor', got {side!r}")
        if (side, trend) not in self._cache:
            self._cache[side, trend] = _cleared(self._series, side == "rotor", self._vs,
                                                angle=trend)
        return self._cache[side, trend]

    def angle(self, side: str) -> np.ndarray:
        return self._side(side, True)[0]

    def ripple_fits(self, side: str, grid: np.ndarray, step: float,
                    trend: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q, r, Q = self._side(side, trend)
        return _grid_fits(q, r, Q, grid, step)

    def column_fits(self, side: str, columns: Any) -> tuple[float, np.ndarray]:
        if side not in ("link", "rotor"):
            raise ValueError(f"side must be 'link' or 'rotor', got {side!r}")
        s = self._series
        q, v = (s["q2"], s["v2"]) if side == "rotor" else (s["q1"], s["v1"])
        return self._fit(side, lambda m: columns(q[m], v[m]))

    def deflection(self) -> np.ndarray:
        return self._series["d"]

    def deflection_fits(self, columns: Any) -> tuple[float, np.ndarray]:
        s = self._series
        return self._fit("link", lambda m: columns(s["d"][m], s["dd"][m]))

    def _fit(self, side: str, columns: Any) -> tuple[float, np.ndarray]:
        """The fit of ``column_fits``: ``columns(mask)`` gives the columns on the samples the
        boolean ``mask`` keeps (the link's sliding samples, every rotor sample)."""
        s = self._series
        v, r = (s["v2"], s["r_rotor"]) if side == "rotor" else (s["v1"], s["r_link"])
        keep = np.ones(v.size, bool)
        if side == "link":  # the sliding samples only, as ``_cleared``
            sliding = np.abs(v) > 2.0 * (self._vs if self._vs is not None else 0.05)
            if np.mean(sliding) > 0.1:
                keep = sliding
        nuisance = np.column_stack([np.ones(v.size), s["d"], np.gradient(v, s["t"])])[keep]
        r = r[keep]
        X = np.asarray(columns(keep), float).reshape(r.size, -1)
        Q, _ = np.linalg.qr(nuisance)
        Xc, rc = X - Q @ (Q.T @ X), r - Q @ (Q.T @ r)
        c, _, rank, _ = np.linalg.lstsq(Xc, rc, rcond=None)
        if rank < X.shape[1] or not np.all(np.isfinite(c)):
            return -1.0, np.zeros(X.shape[1])
        return float(np.sum((Xc @ c) ** 2)), c


def _cogging_start(series: dict[str, np.ndarray], name: str = "cogging",
                   vs: float | None = None) -> AbstractEffect:
    """The start ``Cogging`` ("cogging") or ``MotorCogging`` ("motor_cogging") draws from a
    localisation's ``series`` with the model's Stribeck velocity ``vs`` [rad/s]."""
    return EFFECTS[name].start_from_residual(_ResidualStart(series, vs))


def _gravity_start(series: dict[str, np.ndarray], vs: float | None = None) -> AbstractEffect:
    """The start ``Gravity`` draws from a localisation's ``series`` with the model's Stribeck
    velocity ``vs`` [rad/s]."""
    return EFFECTS["gravity"].start_from_residual(_ResidualStart(series, vs))


def _grid_fits(q: np.ndarray, r: np.ndarray, Q: np.ndarray, grid: np.ndarray,
               step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every spatial frequency of the evenly spaced ``grid`` (spacing ``step``, 1/rad) the
    least-squares fit of r ~ a_s sin(N q) + a_c cos(N q), both columns cleared of the span of
    the orthonormal ``Q`` (r is cleared already): (explained ||X c||^2, -1 where the fit cannot
    be solved; a_s; a_c)."""
    turn = np.exp(1j * step * q)
    n = q.size
    out = []
    for k in range(0, grid.size, 64):  # 64 frequencies at a time, each a 2-column fit
        Ns = grid[k:k + 64]
        # E = exp(i N q), a row per N of the chunk, by repeated turns (cheaper than a sine
        # and a cosine each); its real part is the cosine column C, its imaginary part S
        E = np.empty((Ns.size, n), complex)
        E[0] = np.exp(1j * Ns[0] * q)
        for j in range(1, Ns.size):
            np.multiply(E[j - 1], turn, out=E[j])
        # the Gram entries of the columns cleared of the nuisance span, without clearing
        # them: ||P x||^2 = ||x||^2 - ||Q^T x||^2 (Q orthonormal), the plain ones from the
        # double angle (sum sin^2 = (n - Re z2) / 2, sum sin cos = Im z2 / 2, z2 = sum E^2):
        # complex products instead of a sine and a cosine block each (faster, the same fits
        # to rounding)
        z2 = np.einsum("ji,ji->j", E, E)
        W = E @ Q  # Q^T C + i Q^T S, (m, p)
        ss = 0.5 * (n - z2.real) - np.einsum("ij,ij->i", W.imag, W.imag)
        cc = 0.5 * (n + z2.real) - np.einsum("ij,ij->i", W.real, W.real)
        sc = 0.5 * z2.imag - np.einsum("ij,ij->i", W.imag, W.real)
        b = E @ r  # C^T r + i S^T r
        bs, bc = b.imag, b.real
        det = ss * cc - sc * sc
        ok = det > 1e-12 * np.maximum(ss * cc, 1e-300)  # a fit that can be solved
        det = np.where(ok, det, 1.0)
        a_s, a_c = (cc * bs - sc * bc) / det, (ss * bc - sc * bs) / det
        out.append((np.where(ok, a_s * bs + a_c * bc, -1.0), a_s, a_c))
    return tuple(np.concatenate([o[i] for o in out]) for i in range(3))  # type: ignore[return-value]


def start_effect(name: str, model: Model, series: dict[str, np.ndarray],
                 h: float) -> AbstractEffect:
    """First guess of candidate ``name`` added to ``model``: the effect class's own
    (``AbstractEffect.start_from_residual``) from the model's residual ``series``, its
    Stribeck velocity and the integration step ``h`` [s]."""
    vs = float(np.ravel(model.params.friction["vs"])[0])
    return EFFECTS[name].start_from_residual(_ResidualStart(series, vs, model.params, h))


def residual_start(log: Log, model: Model, h: float) -> _ResidualStart:
    """The ``jaxflex.core.effects.ResidualStart`` of ``model`` on ``log``: the torque residuals
    of its nominal parameters (``localise``), its Stribeck velocity and the integration step
    ``h`` [s] (what ``AbstractEffect.from_lower`` reads)."""
    vs = float(np.ravel(model.params.friction["vs"])[0])
    return _ResidualStart(localise(log, model.params).series, vs, model.params, h)

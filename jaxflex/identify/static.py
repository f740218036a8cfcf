"""The static friction map (eq. 35) as a fit of the engine, and its data: from constant-velocity
runs (``experiments.static_map_experiment``) or from any log with both encoders, by inverse
dynamics (``static_map_from_log``), which gives identification a start for Fc, Fs, vs, sigma2
that does not depend on the user's guess (``start_from_static_map``, each joint from its own
inverse dynamics)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np

from jaxflex.fit import (ParamSpace, covariance, get_value, least_squares, slot_rows)
from jaxflex.core.friction import LuGre
from jaxflex.fit.inverse import measured_motion, torque_residuals
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.plant import DiagonalInertia, FlexibleJointPlant
from jaxflex.core.validation import to_device

STATIC_NAMES: tuple[str, ...] = ("Fc", "Fs", "vs", "sigma2")


@dataclasses.dataclass(frozen=True)
class StaticMap:
    """Constant-velocity friction data (eq. 35): v [rad/s] and F [N m], shape (m,) each."""

    v: np.ndarray
    F: np.ndarray


class StaticMapProblem(eqx.Module):
    """The curve fit of eq. 35 as a problem of the fitting engine: residuals
    ``w (F_ss(v; theta) - F)`` [N m] over the static-map data, parameters in ``space``;
    ``w`` (m,) is 1 for a data point and 0 for padding (``fit_static_map`` pads the points to
    the slots of their count, ``slot_rows``, so maps of other sizes share the compiled
    solver)."""

    space: ParamSpace
    v: jax.Array
    F: jax.Array
    w: jax.Array

    def split(self, y: dict[str, jax.Array]) -> tuple[dict[str, jax.Array], None]:
        """(theta, no start states)."""
        return y, None

    def residuals(self, y: dict[str, jax.Array], args: object = None) -> jax.Array:
        """F_ss(v) - F of the friction of ``space.plant(y)`` (eq. 35) [N m]."""
        fr = self.space.plant(y).friction
        return self.w * (jax.vmap(lambda vi: fr.steady_state(vi[None])[0])(self.v) - self.F)

    @property
    def n_out(self) -> int:
        """Number of data residuals (the padding after them left out)."""
        return int(np.count_nonzero(np.asarray(self.w)))


def fit_static_map(
    data: StaticMap, init: dict[str, float], *, rtol: float = 1e-12, atol: float = 1e-12,
) -> dict[str, tuple[float, float]]:
    """Fit Fc, Fs, vs, sigma2 of one joint to static-map data by eq. 35 (``LuGre.steady_state``)
    with the fitting engine (its constraints: Fc, vs, sigma2 positive, Fs >= Fc; its solver;
    its covariance). ``init`` holds starting values for the four names. Returns name ->
    (value [N m, rad/s or N m s/rad], standard error)."""
    v, F = np.asarray(data.v, float), np.asarray(data.F, float)
    if v.shape != F.shape or v.ndim != 1 or v.size < 5:
        raise ValueError(f"fit_static_map: need >= 5 (v, F) pairs of equal length, got "
                         f"{v.shape} and {F.shape}")
    pick = slot_rows(v.size)  # the bucket's slots: padding by copies, weight 0
    w = (np.arange(pick.size) < v.size).astype(float)
    missing = [k for k in STATIC_NAMES if k not in init]
    if missing:
        raise ValueError(f"fit_static_map: missing starting value(s) {missing}")
    # A unit plant holds the friction: eq. 35 does not involve I, J, K, sigma0, sigma1.
    lugre = LuGre(Fc=init["Fc"], Fs=max(init["Fs"], 1.001 * init["Fc"]), vs=init["vs"],
                  sigma0=1.0, sigma1=0.0, sigma2=max(init["sigma2"], 1e-9))
    holder = FlexibleJointPlant(links=DiagonalInertia(I=1.0), J=1.0, K=1.0, friction=lugre)
    space = ParamSpace.build(holder, STATIC_NAMES)
    prob = StaticMapProblem(space=space, v=to_device(v[pick]), F=to_device(F[pick]),
                            w=to_device(w))
    sol = least_squares(prob, space.theta0(), fn=_static_residuals, rtol=rtol, atol=atol,
                        max_steps=500, small=True)
    phys = space.physical_values(sol.y)
    se = covariance(prob, sol.y, solution=sol)["stderr"]
    return {k: (float(phys[k][0]), float(se[k][0])) for k in STATIC_NAMES}


def _static_residuals(y: dict[str, jax.Array], prob: StaticMapProblem) -> jax.Array:
    return prob.residuals(y)




def static_map_from_log(
    log: Log, plant: FlexibleJointPlant, *, joint: int = 0, window: int = 31, bins: int = 40,
    min_speed: float | None = None,
) -> StaticMap:
    """Friction against link velocity from a log with both encoders, by inverse dynamics:
    F = K (q2 - q1) + effects - M q1'' - C q1' - G (``FlexibleJointPlant.torque_residuals`` of
    the frictionless plant, Savitzky-Golay derivatives over ``window`` samples), binned by
    velocity (median per bin, ``bins`` bins per direction, log-spaced above ``min_speed``
    [rad/s], default 2% of the largest speed). Raises ``ValueError`` if the log lacks q2 or
    has too few moving samples in either direction."""
    if log.q2 is None or log.tau is None:
        raise ValueError("static map from a log: needs columns tau, q1 and q2")
    bare = eqx.tree_at(lambda p: p.friction, plant, None, is_leaf=lambda x: x is None)
    motion = measured_motion(log, window, smooth=True)
    F = -torque_residuals(bare, motion)[0][:, joint]
    v = motion.v1[:, joint]
    top = float(np.quantile(np.abs(v), 0.99))
    lo = 0.02 * top if min_speed is None else min_speed
    vs_out, F_out = [], []
    for sign in (-1.0, 1.0):
        sel = sign * v > lo
        if sel.sum() < 4 * bins:
            raise ValueError(f"static map from a log: too few samples moving "
                             f"{'forward' if sign > 0 else 'backward'} above {lo:.3g} rad/s")
        edges = np.geomspace(lo, top, bins + 1)
        k = np.digitize(sign * v[sel], edges) - 1
        for b in range(bins):
            m = k == b
            if m.sum() >= 5:
                vs_out.append(sign * float(np.median(sign * v[sel][m])))
                F_out.append(float(np.median(F[sel][m])))
    return StaticMap(v=np.asarray(vs_out), F=np.asarray(F_out))


def start_from_static_map(
    log: Log, init: Params, free: Sequence[str] = STATIC_NAMES,
) -> dict[str, np.ndarray] | None:
    """Start values of the static friction parameters among ``free`` (Fc, Fs [N m], vs
    [rad/s], sigma2 [N m s/rad]) from the log's own static map (eq. 35), joint by joint:
    name -> (n,) values, each joint's from the friction its own inverse dynamics shows
    (``static_map_from_log(..., joint=j)``, fitted by ``fit_static_map``) where that joint's
    map determines them (relative standard error below 30%), else the joint's value in
    ``init``. None when no joint's map gives one (no q2, too
    little motion, a failed or non-physical fit)."""
    names = [k for k in STATIC_NAMES if k in free]
    if not names or log.q2 is None:
        return None
    plant = init.to_plant()
    out = {k: np.array(get_value(init, k), float) for k in names}
    found = False
    for j in range(log.n):
        vals = _start_of_joint(log, init, plant, names, j)
        if vals is None:
            continue
        found = True
        for k, v in vals.items():
            out[k][j] = v
    if not found:
        return None
    if "Fs" in out and "Fc" not in out:  # keep Fs >= Fc against the user's Fc
        out["Fs"] = np.maximum(out["Fs"], 1.001 * np.asarray(get_value(init, "Fc"), float))
    return out


def _start_of_joint(log: Log, init: Params, plant: FlexibleJointPlant, names: Sequence[str],
                    j: int) -> dict[str, float] | None:
    """``start_from_static_map`` of joint ``j``: name -> value, or None where its map fixes
    nothing."""
    try:
        data = static_map_from_log(log, plant, joint=j)
        fit = fit_static_map(data, {k: float(init.friction[k][j]) for k in STATIC_NAMES})
    except (ValueError, FloatingPointError):
        return None
    top = float(np.max(np.abs(data.F)))
    # keep a value only where the map determines it (relative standard error below 30%; a
    # Stribeck peak below the slowest velocity seen is an extrapolation)
    vals = {k: v for k, (v, se) in fit.items()
            if math.isfinite(v) and v > 0 and se < 0.3 * v and not (k == "Fs" and v > top)}
    if "Fc" not in vals or "sigma2" not in vals:  # the map does not even fix the Coulomb level
        return None
    out = {k: vals[k] for k in names if k in vals}
    if "Fs" in names and "Fs" not in out and float(init.friction["Fs"][j]) < vals["Fc"]:
        out["Fs"] = 1.05 * vals["Fc"]
    return out

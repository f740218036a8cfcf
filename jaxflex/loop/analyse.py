"""Closed-loop analysis by automatic differentiation: the one-sample map of the sampled-data loop,
its Jacobian, eigenvalues at rest and Floquet (monodromy) multipliers over a period.

The sampled-data loop of ``jaxflex.sim.simulate.simulate_sampled`` is a discrete map over one
controller period dt,

    xi_{k+1} = Phi(t_k, xi_k),   xi = (plant state (q1, q1', q2, q2', z [, aux]),
                                       controller state (observer z_hat, filters))

made of the sensing (encoders, velocity filters), the controller (eq. 9-22), the DAC and the
plant step (eq. 3-5, Strang-split RK4). ``jax.jacfwd`` of Phi gives A_k = dPhi/dxi. At an
equilibrium (a reference at rest) the eigenvalues mu of A are the closed-loop poles in the z
plane; s = log(mu) / dt gives each mode's frequency |Im s| / 2 pi [Hz] and damping ratio
-Re s / |s|. Along a T-periodic reference the monodromy matrix A_{N-1} ... A_0 (N = T / dt)
gives the Floquet multipliers of the periodic orbit, with the same reading (Floquet exponents
log(mu) / T).

Quantisers are taken as the identity (their derivative is zero almost everywhere, which
would cut every feedback path; quantisation acts as exogenous noise, as in
``jaxflex.core.sensing.StraightThrough``), so Phi is smooth away from |q1'| = 0; the filters of
the sensing path (velocity by filtered differentiation, or the Kalman filter of
``jaxflex.core.estimator`` with its estimate in the controller state) are part of Phi. The participation of state i in mode j is
|w_ij v_ij| / sum_i |w_ij v_ij| with v_j, w_j the right and left eigenvectors (Perez-Arriaga,
Verghese and Schweppe 1982).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from jaxflex.core.controller import CascadeController
from jaxflex.core.plant import FlexibleJointPlant, PlantState
from jaxflex.core.sensing import AbstractSensing, Sensing
from jaxflex.sim.simulate import controller_sample, init_controller, loop_estimator
from jaxflex.sim.step import plant_step
from jaxflex.runtime.tracecache import persistent_jit


def state_names(plant: FlexibleJointPlant, controller: CascadeController,
                sensing: AbstractSensing | None = None) -> list[str]:
    """Names of the entries of the flat closed-loop state xi, in ``ravel_pytree`` order
    (plant fields then controller-state fields, each per joint; with a Kalman-filter
    ``sensing`` the filter's estimate as ``ctrl.estimator.*``)."""
    x = plant.init_state(q1=jnp.zeros(plant.n))
    est = None if sensing is None else loop_estimator(controller, sensing)
    c = init_controller(controller, est, 0.0, x.q1, x.q2, x.dq1, x.dq2)
    names: list[str] = []
    for prefix, tree in (("plant", x), ("ctrl", c)):
        for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
            field = ".".join(str(getattr(p, "name", getattr(p, "idx", p))) for p in path)
            size = int(np.size(leaf))
            names += [f"{prefix}.{field}" + (f"[{i}]" if size > 1 else "") for i in range(size)]
    return names


class ClosedLoopMap(eqx.Module):
    """The one-sample map Phi of the sampled-data closed loop (module docstring).

    ``sensing`` decides whether the controller receives exact velocities, differentiates
    the angles or gets the Kalman filter's estimates (the filter's gain designed for the
    sensing's quantisers and DAC, its estimate part of xi); its quantisers and DAC are left
    out (the map is their small-signal model). ``substeps`` plant substeps per sample as in
    ``simulate_sampled``.
    """

    plant: FlexibleJointPlant
    controller: CascadeController
    sensing: AbstractSensing
    substeps: int = eqx.field(static=True, default=10)

    def initial(self, x0: PlantState | None = None) -> tuple[Float[Array, " d"], Callable]:
        """Flat closed-loop state at t = 0 (plant at ``x0``, default rest at q1d(0); the
        controller as ``simulate_sampled`` starts it) and the function unflattening it."""
        if x0 is None:
            x0 = self.plant.init_state(q1=self.controller.trajectory.position(jnp.asarray(0.0)))
        est = loop_estimator(self.controller, self.sensing)
        c0 = init_controller(self.controller, est, 0.0, x0.q1, x0.q2, x0.dq1, x0.dq2)
        return ravel_pytree((x0, c0))

    def step(self, t: Float[Array, ""], xi: Float[Array, " d"], unravel: Callable
             ) -> Float[Array, " d"]:
        """xi_{k+1} = Phi(t_k, xi_k) over one period dt [s] (noise-free)."""
        x, c = unravel(xi)
        # the quantisers as the identity (module docstring); the velocity path kept
        s = Sensing(velocity=self.sensing.velocity)
        zero = jnp.zeros_like(x.q1)
        q1m = s.measure(x.q1, s.q1_resolution, zero)
        q2m = s.measure(x.q2, s.q2_resolution, zero)
        # the filter is designed for the real sensing's noise; only its quantisers are dropped
        est = loop_estimator(self.controller, self.sensing)
        c_new, _, tau = controller_sample(self.controller, s, est, c, t, q1m, q2m, x.dq1, x.dq2)
        x_new = plant_step(self.plant, x, tau, self.controller.dt, self.substeps)
        return ravel_pytree((x_new, c_new))[0]


@dataclasses.dataclass(frozen=True)
class Modes:
    """Modes of a discrete closed-loop map over the period ``period`` [s].

    multipliers: complex eigenvalues mu (|mu| < 1: decaying), sorted by decreasing |mu|;
    frequency [Hz] |Im log(mu)| / (2 pi period); damping: -Re s / |s| with s = log(mu) /
    period (1 for a real pole inside the unit circle, < 0 growing); time_constant [s]
    -1 / Re s (inf for |mu| = 1); participation (d, modes): share of each state in each mode.
    Multipliers of magnitude below ``1e-12`` (states that a sample overwrites, e.g. the last
    angle a filter keeps) get frequency 0 and damping 1.
    """

    period: float
    multipliers: np.ndarray
    frequency: np.ndarray
    damping: np.ndarray
    time_constant: np.ndarray
    participation: np.ndarray
    names: list[str]

    def dominant(self, k: int = 6) -> list[dict[str, Any]]:
        """The ``k`` slowest-decaying modes as JSON-ready dicts, each with its three states of
        largest participation."""
        out = []
        seen = set()
        for j in range(len(self.multipliers)):
            mu = self.multipliers[j]
            key = (round(abs(mu), 9), round(abs(mu.imag), 9))
            if key in seen:  # the conjugate of a pair already listed
                continue
            seen.add(key)
            top = np.argsort(-self.participation[:, j])[:3]
            out.append({
                "multiplier": [float(mu.real), float(mu.imag)],
                "abs": float(abs(mu)),
                "frequency_hz": float(self.frequency[j]),
                "damping": float(self.damping[j]),
                "time_constant_s": float(self.time_constant[j]),
                "states": {self.names[i]: float(self.participation[i, j]) for i in top},
            })
            if len(out) == k:
                break
        return out


def modes(A: np.ndarray, period: float, names: list[str]) -> Modes:
    """Eigen-decomposition of the discrete map Jacobian (or monodromy matrix) ``A`` over
    ``period`` [s] into multipliers, frequencies [Hz], damping ratios, time constants [s] and
    participation factors (module docstring)."""
    A = np.asarray(A, float)
    mu, W, V = scipy.linalg.eig(A, left=True, right=True)
    order = np.argsort(-np.abs(mu))
    mu, V, W = mu[order], V[:, order], W[:, order]
    # defective or repeated multipliers (states a sample overwrites) make V singular; the
    # left/right pairs of scipy stay usable, normalised per mode
    p = np.abs(W.conj() * V)
    p = p / np.maximum(p.sum(axis=0, keepdims=True), 1e-300)
    tiny = np.abs(mu) < 1e-12
    s = np.log(np.where(tiny, 1.0, mu).astype(complex)) / period
    freq = np.where(tiny, 0.0, np.abs(s.imag) / (2 * np.pi))
    with np.errstate(divide="ignore", invalid="ignore"):
        damp = np.where(tiny, 1.0, -s.real / np.abs(s))
        tc = np.where(tiny, 0.0, np.where(s.real < 0, -1.0 / s.real, np.inf))
    return Modes(float(period), mu, freq, np.nan_to_num(damp, nan=1.0), tc, p, names)


def _jac_step(m: ClosedLoopMap, unravel: Callable):
    return jax.jacfwd(lambda xi, t: m.step(t, xi, unravel))


def jacobian_at(m: ClosedLoopMap, t: float, xi: Float[Array, " d"], unravel: Callable
                ) -> Float[Array, "d d"]:
    """dPhi/dxi at time ``t`` [s] and state ``xi`` (forward-mode autodiff). ``unravel`` is
    ``m.initial()``'s (the layout of xi); the compiled Jacobian is cached per map structure,
    so repeated calls (other gains, plants, times or states of the same shapes) do not
    recompile."""
    del unravel  # rebuilt inside the compiled function from m, which fixes the same layout
    return _jacobian_compiled(m, jnp.asarray(t, xi.dtype), xi)


@persistent_jit
def _jacobian_compiled(m: ClosedLoopMap, t: Array, xi: Array) -> Array:
    _, unravel = m.initial()
    return _jac_step(m, unravel)(xi, t)


def rest_modes(m: ClosedLoopMap, t: float = 0.0, settle: float = 0.0) -> tuple[Modes, np.ndarray]:
    """Modes of the loop linearised about rest: ``m.controller.trajectory`` should be at rest
    near ``t`` [s] (e.g. a zero-amplitude sinusoid). With ``settle`` > 0 the loop is first run
    ``settle`` seconds from rest at t (equilibrium found by simulation). Returns the modes
    and the Jacobian A."""
    xi, unravel = m.initial()
    dt = m.controller.dt
    if settle > 0:
        f = jax.jit(lambda xi_: jax.lax.fori_loop(
            0, int(round(settle / dt)), lambda k, v: m.step(jnp.asarray(t, v.dtype), v, unravel),
            xi_))
        xi = f(xi)
    A = np.asarray(jacobian_at(m, t, xi, unravel))
    names = state_names(m.plant, m.controller, m.sensing)
    return modes(A, dt, names), A


def monodromy(m: ClosedLoopMap, period: float, *, settle_periods: int = 3
              ) -> tuple[Modes, np.ndarray, dict[str, np.ndarray]]:
    """Floquet analysis along a ``period``-periodic reference [s]: run the loop
    ``settle_periods`` periods from rest (onto the periodic orbit), then multiply the
    one-sample Jacobians A_k over one more period (monodromy matrix). Returns the modes (of
    the monodromy matrix, ``period`` as their time base), the matrix and the last period's
    trajectory (t, link error e1 [rad])."""
    dt = m.controller.dt
    N = int(round(period / dt))
    xi, unravel = m.initial()
    jac = _jac_step(m, unravel)
    names = state_names(m.plant, m.controller, m.sensing)
    traj = m.controller.trajectory

    @jax.jit
    def run(xi0):
        def settle(v, k):
            return m.step(k * dt, v, unravel), None

        v, _ = jax.lax.scan(settle, xi0, jnp.arange(settle_periods * N, dtype=xi0.dtype))

        def body(carry, k):
            v, P = carry
            t = (settle_periods * N + k) * dt
            A = jac(v, t)
            x, _ = unravel(v)
            e = x.q1 - traj.position(t)
            return (m.step(t, v, unravel), A @ P), e

        (v, P), e = jax.lax.scan(body, (v, jnp.eye(v.shape[0], dtype=v.dtype)),
                                 jnp.arange(N, dtype=xi0.dtype))
        return P, e

    P, e = run(xi)
    P = np.asarray(P)
    t = (settle_periods * N + np.arange(N)) * dt
    return modes(P, period, names), P, {"t": t, "e1": np.asarray(e)}


def rest_map(plant: FlexibleJointPlant, gains: Any, *, model: FlexibleJointPlant | None = None,
             sensing: AbstractSensing | None = None, q2d_method: str = "model",
             compensation: bool = True, dt: float = 1e-3, tau_max: float = 2.0,
             substeps: int = 10) -> ClosedLoopMap:
    """The one-sample map of the cascade loop around ``plant`` held at rest (a reference of
    0 rad): the controller on ``model`` (default the plant) with ``gains``, ``sensing``
    (default ideal), q2d method, compensation, period ``dt`` [s], torque limit [N m]."""
    from jaxflex.core.trajectory import Sinusoid

    zero = jnp.zeros(plant.n)
    ctrl = CascadeController(model=plant if model is None else model, gains=gains,
                             trajectory=Sinusoid(amplitude=zero, frequency=zero + 1.0),
                             compensation=compensation, q2d_method=q2d_method, dt=dt,
                             tau_max=tau_max)
    return ClosedLoopMap(plant, ctrl, Sensing() if sensing is None else sensing, substeps)


def rest_jacobian(m: ClosedLoopMap) -> Float[Array, "d d"]:
    """dPhi/dxi of ``m`` at its initial state and t = 0 (a reference at rest), traceable in
    ``m``'s arrays (gains, plant), so one compilation serves every gain set (wrap in
    ``eqx.filter_jit``)."""
    xi, unravel = m.initial()
    return jax.jacfwd(lambda v: m.step(jnp.asarray(0.0, v.dtype), v, unravel))(xi)


def rest_damping(m: ClosedLoopMap) -> Float[Array, ""]:
    """The smallest damping ratio of the loop's modes at rest, -Re s / |s| with s = log(mu)/dt
    over the multipliers mu of ``rest_jacobian`` (multipliers at exactly 1 of conserved
    quantities and those below 1e-9, states a sample overwrites, left out; a growing mode
    gives a negative value). Differentiable almost everywhere (jax's eigenvalue derivative),
    so gains can be pushed toward damped modes by gradient."""
    mu = jnp.linalg.eigvals(rest_jacobian(m))
    live = (jnp.abs(mu - 1.0) > 1e-9) & (jnp.abs(mu) > 1e-9)
    safe = jnp.where(live, mu, 0.5 + 0.0j)
    s = jnp.log(safe) / m.controller.dt
    zeta = -s.real / jnp.abs(s)
    return jnp.min(jnp.where(live, zeta, 1.0))


def default_map(plant: FlexibleJointPlant, controller: CascadeController,
                sensing: AbstractSensing | None = None, substeps: int = 10) -> ClosedLoopMap:
    """A ``ClosedLoopMap`` with ideal sensing unless ``sensing`` is given."""
    return ClosedLoopMap(plant, controller, Sensing() if sensing is None else sensing, substeps)


def spectral_radius(A: np.ndarray) -> float:
    """Spectral radius of a one-sample (or monodromy) map's Jacobian ``A`` without the
    multipliers at exactly 1 of conserved quantities (the observer state when compensation is
    off, the pre-sliding z - q1 at rest): > 1 means a growing mode."""
    mu = np.linalg.eigvals(A)
    live = np.abs(mu - 1.0) > 1e-9
    return float(np.max(np.abs(mu[live]))) if live.any() else 0.0


@dataclasses.dataclass(frozen=True)
class RestModes:
    """The loop linearised at rest: ``spectral_radius`` of its one-sample map (multipliers
    at exactly 1, conserved quantities, left out; per sample), ``stable`` (that radius < 1)
    and ``modes``, the slowest (``Modes.dominant``: multiplier, |mu|, frequency [Hz],
    damping ratio, time constant [s], the states taking part)."""

    spectral_radius: float
    stable: bool
    modes: list[dict[str, Any]]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the fields by name."""
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class FloquetModes:
    """The loop along a periodic reference of period ``period_s`` [s]: ``spectral_radius``
    of the monodromy matrix (per period), ``stable``, the slowest ``modes`` (as
    ``RestModes``) and the RMS link error over the last period ``rms_error_last_period``
    [rad]."""

    period_s: float
    spectral_radius: float
    stable: bool
    modes: list[dict[str, Any]]
    rms_error_last_period: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the fields by name."""
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class LoopAnalysis:
    """Result of ``analyse_loop``: the configuration (``q2d_method``, ``compensation``), the
    modes at rest and, where asked for, the Floquet multipliers (else None)."""

    q2d_method: str
    compensation: bool
    rest: RestModes
    floquet: FloquetModes | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: ``q2d_method``, ``compensation``, ``rest`` and, where computed,
        ``floquet``."""
        out = dataclasses.asdict(self)
        if self.floquet is None:
            del out["floquet"]
        return out


def analyse_loop(plant: FlexibleJointPlant, gains: Any, *, q2d_method: str = "model",
                 compensation: bool = True, sensing: AbstractSensing | None = None,
                 floquet: bool = False, n_modes: int = 6, dt: float = 1e-3,
                 tau_max: float = 2.0, period_reference: Any = None) -> LoopAnalysis:
    """Modes of the paper's loop (controller on ``plant`` as its own model, ``gains``) at
    rest (a reference held at 0 rad) and, with ``floquet``, Floquet multipliers along
    ``period_reference`` (default the paper's 0.5 Hz sinusoid, period 2 s): per case the
    spectral radius, whether it is below 1 and the ``n_modes`` slowest modes
    (``LoopAnalysis``). ``dt`` [s] the controller period, ``tau_max`` [N m] its torque limit.
    """
    from jaxflex.core.trajectory import Sinusoid

    def ctrl(traj):
        return CascadeController(model=plant, gains=gains, trajectory=traj,
                                 compensation=compensation, q2d_method=q2d_method, dt=dt,
                                 tau_max=tau_max)

    rest = rest_map(plant, gains, sensing=sensing, q2d_method=q2d_method,
                    compensation=compensation, dt=dt, tau_max=tau_max)
    M, A = rest_modes(rest)
    r = spectral_radius(A)
    at_rest = RestModes(spectral_radius=r, stable=bool(r < 1.0), modes=M.dominant(n_modes))
    along = None
    if floquet:
        traj = period_reference
        if traj is None:
            zero = jnp.zeros(plant.n)
            traj = Sinusoid(amplitude=zero + 0.05, frequency=zero + 0.5)
        period = float(1.0 / np.max(np.asarray(traj.frequency)))
        MF, P, tr = monodromy(ClosedLoopMap(plant, ctrl(traj), rest.sensing), period)
        rf = spectral_radius(P)
        along = FloquetModes(period_s=period, spectral_radius=rf, stable=bool(rf < 1.0),
                             modes=MF.dominant(n_modes),
                             rms_error_last_period=float(np.sqrt(np.mean(tr["e1"] ** 2))))
    return LoopAnalysis(q2d_method=q2d_method, compensation=compensation, rest=at_rest,
                        floquet=along)

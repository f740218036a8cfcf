"""The least-squares problem of jaxflex: replay of log segments through a model (multiple
shooting), used by identification, discovery and validation alike.

The log is cut into S segments of L samples. Each segment starts from a state (q1, q1', [q2,
q2'], z) and is replayed under the logged torque (zero-order hold) by ``jaxflex.sim.step.replay``;
the effects' internal states are first brought into line with the W torque samples before the
segment (``jaxflex.sim.step.warm_effects``). Two ways to start a segment:

- ``free_starts=True`` (identification, discovery): the start states are unknowns beside the
  parameters; residuals are the weighted output errors and the continuity defects
  ``w_def (x_end(segment s) - x0(segment s+1))`` (discovery sets ``w_def`` to zero: independent
  segments). With one segment this is single shooting.
- ``free_starts=False`` (validation): each segment starts from the state measured at
  its start (angles from the log, velocities by Savitzky-Golay differentiation, z at the
  steady state of the current friction model for that velocity); only output errors.

Short segments keep an integrating plant, and closed-loop logs whose torque was computed from
the real position, from drifting, and make the problem far less nonconvex.

``Problem.residuals`` carries a custom JVP that uses the block sparsity of multiple shooting
(segment s depends on theta and its own start state only): a Jacobian costs k + n_state*n
tangents per segment, vmapped over segments, whatever the number of segments.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from jaxflex.core.effects import link_input, link_measurement
from jaxflex.fit.readings import quantised_residual, quantised_slope
from jaxflex.fit.segments import Segments, pack_state, segment_rows, slot_rows, unpack_state
from jaxflex.fit.space import ParamSpace
from jaxflex.sim.step import MODEL_KINDS, replay, warm_effects
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.validation import to_device

#: Value given to a residual that is not finite (a trial that blew up is then rejected by
#: the solver's cost comparison instead of propagating NaN).
BLOWN_RESIDUAL = 1e8
#: Most substeps a segment replay unrolls (``Problem._segment``).
UNROLL_SUBSTEPS = 4


def dynamic_substeps(n: int) -> Array:
    """``n`` integrator substeps per sample as a ``Problem.substeps`` that the compiled
    programs take as an argument (a 0-d int32 array, a traced loop count): problems that
    differ only in their substeps then share every compiled program. Per substep on a CPU
    the loop costs what the compiled-in count does from 8 substeps on, and 1.4-2x at 1-4."""
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"fit: substeps must be an integer >= 1, got {n!r}")
    return jnp.asarray(int(n), dtype=jnp.int32)


class Problem(eqx.Module):
    """One least-squares problem: parameter space, data segments, model structure, weights.

    Unknowns ``y``: ``(theta, x0s)`` with free starts, else ``theta`` (dict name -> (n,)).
    ``w_y`` scales output residuals, one value or one per output column (channel-major:
    ``outputs`` in order, n joints each; 1 / noise level for identification, 1 / motion for
    discovery); ``w_def`` (n_state,) or per joint (n_state, n) scales continuity defects.
    ``steady_z``: with free starts, each segment's start z is set at the steady state of its
    start velocity (as with estimated starts) instead of being fitted; its entry in the start
    vector is then unused (the bristle state relaxes within milliseconds of sliding and is
    otherwise poorly determined, so a fitted z wanders to unphysical values). ``bounded_z``:
    with free starts, each segment's start z is fitted within the friction's capacity instead:
    the start vector's z entry [rad] clipped to +-g(q1') / sigma0 (the bounds are the steady
    states of sliding): a segment that starts in stick carries any bristle load up to
    breakaway, which the steady state (only 0 or +-g / sigma0 at rest) cannot, and z stays
    physical (an entry past the capacity, poorly determined while sliding, stops moving
    instead of wandering; the load is absolute, so a fitted Fs moves only the bound, not
    every load with it). Otherwise, with free starts, the first segment's start z (the one
    start no continuity defect ties to a replay) is held within the bristle's invariant bound
    (``LuGre.z_bound``): a state beyond it is one no motion reaches, and a fit left free
    there uses it as an impulse at the log's start (a load many times the friction's
    largest) that the integrator cannot follow. Its entry in the start vector is the load's
    share of that bound, folded into [-1, 1] (``_folded``; ``y0`` gives the data's estimate
    so): a fitted Fs or sigma0 moves the bound and the load with it, and a step past the
    bound is reflected back, where a clipped entry would stop moving. ``jac_columns``:
    with a parameter mask, the most fitted theta entries any mask will have; the structured
    Jacobian then takes only that many tangents (the fitted directions) instead of all of
    theta. ``substeps``: integrator substeps per sample, a Python int (a compiled program per
    value; up to ``UNROLL_SUBSTEPS`` unrolled) or a 0-d integer array (``dynamic_substeps``:
    a traced loop count, so that every level of a coarse-to-fine refinement shares one
    compiled program); ``n_substeps`` reads it as an int on the host.
    ``rolled_stages``: the Jacobian blocks (``segment_jacobians``) replay with the RK4 stages
    as a loop (``jaxflex.sim.step.rk4``'s ``rolled``: the same to rounding, one copy of the
    vector field instead of four per substep): a smaller program, faster to compile and load;
    ``identify``'s and ``discover``'s problems use it (on CPU their solves also run faster
    with it); off by default.
    ``quantum``, ``read_noise``: the readings' model per output column, in the weighted units
    of ``w_y``: the encoder's count and the white noise before its rounding; the output
    residual is then ``quantised_residual`` (the reading's exact likelihood) instead of the
    Gaussian one. None (the default): Gaussian.
    """

    space: ParamSpace
    segs: Segments
    w_y: Array
    w_def: Array
    dt: float = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    substeps: int | Array
    outputs: tuple[str, ...] = eqx.field(static=True)
    free_starts: bool = eqx.field(static=True, default=True)
    steady_z: bool = eqx.field(static=True, default=False)
    bounded_z: bool = eqx.field(static=True, default=False)
    structured: bool = eqx.field(static=True, default=True)
    jac_columns: int | None = eqx.field(static=True, default=None)
    rolled_stages: bool = eqx.field(static=True, default=False)
    quantum: Array | None = None
    read_noise: Array | None = None

    def __check_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"fit: model must be one of {MODEL_KINDS}, got {self.kind!r}")
        if not isinstance(self.substeps, jax.core.Tracer) and not (
                np.ndim(self.substeps) == 0 and np.issubdtype(np.asarray(self.substeps).dtype,
                                                               np.integer)
                and int(self.substeps) >= 1):
            raise ValueError(f"fit: substeps must be an integer >= 1, got {self.substeps!r}")

    @property
    def n_substeps(self) -> int:
        """Integrator substeps per sample as a Python int (host side)."""
        return int(self.substeps)

    def split(self, y: Any) -> tuple[dict[str, Array], Array]:
        """(theta, segment start vectors (S, n_state, n)) of the unknowns ``y``."""
        if self.free_starts:
            return y
        return y, self.segs.x0

    def y0(self, theta: dict[str, Array] | None = None) -> Any:
        """Starting unknowns: ``theta`` (default: the space's base values) and, with free
        starts, the data's start states."""
        theta = self.space.theta0() if theta is None else theta
        if not self.free_starts:
            return theta
        if self.bounded_z or self.steady_z:
            return theta, self.segs.x0
        return theta, _first_start_as_share(self.space, theta, self.segs.x0)

    def _segment(self, th: dict[str, Array], v0: Array, tau: Array, tau_pre: Array,
                 rolled: bool = False, first: Array | bool = False):
        plant = self.space.plant(th)
        n = plant.n
        aux = tuple(e.aux_init(n) for e in plant.effects) if plant.effects else None
        x0 = unpack_state(self.kind, v0, aux)
        fr = plant.lugre
        if fr is not None:
            if self.free_starts and self.bounded_z:
                cap = fr.g(x0.dq1) / fr.sigma0  # the friction's capacity [rad]
                x0 = eqx.tree_at(lambda s: s.z, x0, jnp.clip(x0.z, -cap, cap))
            elif self.steady_z or not self.free_starts:
                x0 = eqx.tree_at(lambda s: s.z, x0, fr.z_steady(x0.dq1))
            else:  # the first start, which no defect ties to a replay: a state a motion reaches
                cap = fr.z_bound()
                x0 = eqx.tree_at(lambda s: s.z, x0,
                                 jnp.where(first, cap * _folded(x0.z), x0.z))
        reads_link = self.kind in ("flexible", "link") and "q1" in self.outputs
        if reads_link and not self.free_starts:
            # a measured start is the encoder's reading: start from the link angle behind it
            # (the effects' input maps, ``link_input``; the start's velocity is kept)
            q1_start, _ = link_input(plant.effects, x0.q1, x0.dq1, 0.0)  # no q1'' at a start
            x0 = eqx.tree_at(lambda s: s.q1, x0, q1_start)
        x0 = warm_effects(plant, x0, tau_pre, self.dt)
        # segments and Jacobian columns run batched: unrolled substeps are faster there, up to
        # UNROLL_SUBSTEPS (past it XLA's compile time and run time on a CPU grow steeply)
        static = isinstance(self.substeps, int)
        xs, x_end = replay(self.kind, plant, x0, tau, self.dt, self.substeps,
                           unroll=static and self.substeps <= UNROLL_SUBSTEPS, rolled=rolled)

        def column(o):  # the link output as its encoder reads it (``link_measured``)
            if o == "q1" and reads_link:
                return link_measurement(plant.effects, xs.q1, xs.dq1)
            return getattr(xs, o)

        ys = jnp.concatenate([column(o) for o in self.outputs], axis=-1)
        return ys, pack_state(self.kind, x_end)

    def simulate(self, y: Any) -> tuple[Array, Array]:
        """Simulated outputs (S, L, n_out) [rad] and segment end states (S, n_state, n)
        (``replay_segments``: the replay traced once for the residual and every other use)."""
        out, _, (n_state, n) = self._replay_flat(y)
        n_y = self.segs.y_meas.shape[1] * self.segs.y_meas.shape[2]
        return (out[:, :n_y].reshape(self.segs.y_meas.shape),
                out[:, n_y:].reshape(out.shape[0], n_state, n))

    def replay(self, y: Any) -> dict[str, Array]:
        """One replay at ``y`` and what is read from it: ``outputs`` (``simulate``'s, (S, L,
        n_out) [rad]), ``residuals`` (``residuals``' values) and ``gap`` (``gap``), so that one
        compiled program serves all three (``jaxflex.fit.simulated_outputs``, ``residuals``,
        ``gap``)."""
        out, v0s, dims = self._replay_flat(y)
        n_y = self.segs.y_meas.shape[1] * self.segs.y_meas.shape[2]
        ys = out[:, :n_y].reshape(self.segs.y_meas.shape)
        return {"outputs": ys,
                "residuals": _guard(self._assemble(out, v0s, self.segs.y_meas, dims)),
                "gap": self._gap_of(ys)}

    def _replay_flat(self, y: Any) -> tuple[Array, Array, tuple[int, int]]:
        """``replay_segments`` at ``y``: the flat replays (S, outputs + end state), the flat
        start states (S, n_state * n) and (n_state, n)."""
        theta, x0s = self.split(y)
        S, n_state, n = x0s.shape
        v0s = x0s.reshape(S, n_state * n)
        out = replay_segments(self, ravel_pytree(theta)[0], v0s, theta_spec(theta),
                              (n_state, n))
        return out, v0s, (n_state, n)

    def output_slope(self, out: Array) -> Array | None:
        """d r / d e of the output residuals at replays ``out`` (None: 1, Gaussian)."""
        if self.quantum is None:
            return None
        e = self._output_error(out, self.segs.y_meas)
        return quantised_slope(e / self.read_noise,
                               self.quantum / self.read_noise) / self.read_noise

    def _output_error(self, out: Array, y_ref: Any) -> Array:
        """Weighted output errors ``w_y (outputs - y_ref)`` (S, L, n_out) of replays ``out``."""
        n_y = self.segs.y_meas.shape[1] * self.segs.y_meas.shape[2]
        return self.w_y * (out[:, :n_y].reshape(self.segs.y_meas.shape) - y_ref)

    def _assemble(self, out: Array, nxt: Array, y_ref: Any, dims: tuple[int, int],
                  slope: Array | None = None) -> Array:
        """The residual vector from flat segment replays ``out`` (S, outputs + end state) and
        flat start states ``nxt`` (S, n_state * n; ``dims`` = (n_state, n)): weighted output
        errors against ``y_ref``, then (free starts) the continuity defects; padding slots
        give zeros."""
        n_y = self.segs.y_meas.shape[1] * self.segs.y_meas.shape[2]
        n_state, n = dims
        act = self.segs.active
        e = self._output_error(out, y_ref)
        if slope is not None:  # a linearisation: the output residual's own slope
            r = slope * e
        elif self.quantum is not None:
            r = quantised_residual(e / self.read_noise, self.quantum / self.read_noise)
        else:
            r = e
        if act is not None:  # padding slots: no residual (``padded``)
            r = jnp.where(act[:, None, None], r, 0.0)
        parts = [r.reshape(-1)]
        if self.free_starts:
            w_def = jnp.broadcast_to(self.w_def.reshape(n_state, -1), (n_state, n)).reshape(-1)
            de = (out[:-1, n_y:] - nxt[1:]) * w_def
            if act is not None:  # no defect into a padding slot
                de = jnp.where(act[1:, None], de, 0.0)
            parts.append(de.reshape(-1))
        return jnp.concatenate(parts)

    def residuals(self, y: Any, args: Any = None) -> Array:
        """Weighted output residuals and (with free starts) continuity defects, flattened.

        Non-finite entries are replaced by ``BLOWN_RESIDUAL``. With ``structured`` (the
        default) a custom JVP uses the multiple-shooting sparsity (module docstring); values
        and derivatives equal plain autodiff (a test checks this). The segment replays and
        their Jacobian blocks are module-level compiled functions (``replay_segments``,
        ``segment_jacobians``), so that the solver's several traces of the residual (start,
        trial point, linearisation) trace the replay once each instead of every time."""
        theta, x0s = self.split(y)
        th_flat, _ = ravel_pytree(theta)
        spec = theta_spec(theta)
        S, n_state, n = x0s.shape
        free = self.free_starts
        # The problem's arrays go in as an argument (no closed-over tracers); their tangents
        # are ignored (the data are not differentiated).
        dyn, static = eqx.partition(self, eqx.is_array)

        def primal(th, v0s, d):
            prob = eqx.combine(d, static)
            out = replay_segments(prob, th, v0s, spec, (n_state, n))
            return _guard(prob._assemble(out, v0s, prob.segs.y_meas, (n_state, n)))

        args_ = (th_flat, x0s.reshape(S, n_state * n), dyn)
        if not self.structured:
            return primal(*args_)
        res = jax.custom_jvp(primal)

        @res.defjvp
        def res_jvp(primals, tangents):
            th, v0s, d = primals
            dth, dv0s, _ = tangents
            prob = eqx.combine(d, static)
            out, jac_th, jac_v, basis = segment_jacobians(prob, th, v0s, spec, (n_state, n))
            dout = jnp.einsum("smc,c->sm", jac_th, basis.T @ dth)
            if free:
                dout = dout + jnp.einsum("smd,sd->sm", jac_v, dv0s)
            r = _guard(prob._assemble(out, v0s, prob.segs.y_meas, (n_state, n)))
            dr = prob._assemble(dout, dv0s, 0.0, (n_state, n), prob.output_slope(out))
            return r, jnp.where(r == BLOWN_RESIDUAL, 0.0, dr)

        return res(*args_)

    def residual_blocks(self, y: Any) -> tuple[Array, dict[str, Array]]:
        """The residual (``residuals``' values) and its Jacobian as the blocks of a free-start
        multiple-shooting problem, straight from ``segment_jacobians``: ``Jt`` (S, my + d, k)
        every segment's rows (its outputs, then its continuity defect; ``segment_rows``)
        against theta, ``Jx`` (S, my + d, d) against its own start, ``Jn`` (S, d, d) its
        defect against the next start (d = n_state n). The same numbers as linearising
        ``residuals`` and probing it with k + 2 d directions (``shooting_blocks``; a test
        checks this), without tracing a linearisation or the probes, so the solver's
        program traces and compiles faster. Rows of a
        blown residual (``BLOWN_RESIDUAL``) get zero derivatives, as in ``residuals``.
        Needs free starts (``ValueError`` otherwise)."""
        if not self.free_starts:
            raise ValueError("fit: residual blocks need free segment starts")
        theta, x0s = y
        S, n_state, n = x0s.shape
        dims = (n_state, n)
        d = n_state * n
        v0s = x0s.reshape(S, d)
        th = ravel_pytree(theta)[0]
        out, jac_th, jac_v, basis = segment_jacobians(self, th, v0s, theta_spec(theta), dims)
        r = _guard(self._assemble(out, v0s, self.segs.y_meas, dims))
        # the weight of every row, in the per-segment layout (``segment_rows``): the
        # residual's own weights and masks, read off ``_assemble`` at unit outputs
        w_rows = segment_rows(self._assemble(jnp.ones_like(out), jnp.zeros_like(v0s), 0.0,
                                             dims, self.output_slope(out)), S, d)
        w_rows = jnp.where(segment_rows(r, S, d) == BLOWN_RESIDUAL, 0.0, w_rows)
        my = w_rows.shape[1] - d
        Jt = w_rows[:, :, None] * (jac_th @ basis.T)
        Jx = w_rows[:, :, None] * jac_v
        Jn = -w_rows[:, my:, None] * jnp.eye(d, dtype=r.dtype)
        return r, {"Jt": Jt, "Jx": Jx, "Jn": Jn}

    @property
    def n_out(self) -> int:
        """Number of output residuals (the rows of every segment slot; ``Padding`` keeps
        padded problems inside the engine, so a caller's problem counts its data only)."""
        return int(np.prod(self.segs.y_meas.shape))

    def padded(self, slots: int) -> Problem:
        """The same problem in ``slots`` >= S segment slots (``segment_slots``; equal counts
        too, so that every count of a bucket has one program): the S data segments, then
        copies of the last marked inactive (``Segments.active``), whose output residuals and
        continuity defects are zero. Its residual is the original's with zero rows inserted
        (``jaxflex.fit.Padding.rows_back`` takes them out), so its least-squares solution,
        cost and normal equations are the original's; the copies keep every replay finite.
        The arrays are gathered on the host (no eager device program per shape). Raises
        ``ValueError`` for fewer slots than segments or a problem already padded."""
        S = self.segs.count
        if self.segs.active is not None:
            raise ValueError("fit: the problem is already padded")
        if slots < S:
            raise ValueError(f"fit: {slots} slots cannot hold {S} segments")
        idx = slot_rows(S, slots)
        grow = lambda a: to_device(np.asarray(a)[idx])  # noqa: E731
        segs = Segments(tau=grow(self.segs.tau), y_meas=grow(self.segs.y_meas),
                        tau_pre=grow(self.segs.tau_pre), x0=grow(self.segs.x0),
                        t0=grow(self.segs.t0), active=to_device(np.arange(slots) < S))
        return eqx.tree_at(lambda p: p.segs, self, segs)

    def gap(self, y: Any) -> Array:
        """Normalised RMS output error: sqrt(sum (y_sim - y_meas)^2 / sum (y_meas -
        y_meas[segment start])^2); 0 is perfect, 1 as bad as predicting no motion (padding
        slots left out)."""
        return self._gap_of(self.simulate(y)[0])

    def _gap_of(self, ys: Array) -> Array:
        m = self.segs.y_meas
        e, ref = (ys - m) ** 2, (m - m[:, :1]) ** 2
        if self.segs.active is not None:
            e, ref = (jnp.where(self.segs.active[:, None, None], a, 0.0) for a in (e, ref))
        return jnp.sqrt(jnp.sum(e) / jnp.sum(ref))


def _guard(r: Array) -> Array:
    """A non-finite residual entry becomes ``BLOWN_RESIDUAL``."""
    return jnp.where(jnp.isfinite(r), r, BLOWN_RESIDUAL)


def theta_spec(theta: dict[str, Array]) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """The structure of engine coordinates ``theta`` (names and shapes), hashable: what
    ``replay_segments`` needs to unflatten them."""
    return tuple((k, tuple(jnp.shape(v))) for k, v in sorted(theta.items()))


@persistent_jit(fast_compile=True)
def _first_start_as_share(space: ParamSpace, theta: dict[str, Array], x0s: Array) -> Array:
    """Start states (S, n_state, n) with the first segment's z entry as its share of the
    bristle's bound at ``theta`` (``Problem``), as one program (op by op, the plant's build
    and its bound compiled a dozen small programs: a second of a first identification)."""
    fr = space.plant(theta).lugre
    return x0s if fr is None else x0s.at[0, -1].divide(fr.z_bound())


def _folded(s: Array) -> Array:
    """A share ``s`` folded into [-1, 1]: s itself there, reflected at +-1 beyond (a triangle
    wave of period 4, slope +-1 everywhere): a step past the bound comes back inside, where a
    clip would hold the entry with no slope."""
    return 1.0 - jnp.abs(jnp.mod(s + 1.0, 4.0) - 2.0)


def _first_slot(S: int) -> Array:
    """(S,) bool: the slot of the log's first segment (``Problem``'s bound on its start z)."""
    return jnp.arange(S) == 0


def _segment_flat(prob: Problem, spec: tuple, dims: tuple[int, int], th: Array, v0: Array,
                  tau: Array, tau_pre: Array, first: Array, rolled: bool = False) -> Array:
    """One segment's outputs and end state, flattened, from flat coordinates ``th``
    (``first``: the log's first segment, ``Problem``'s bound on its start z; ``rolled``: the
    integrator's RK4 stages as a loop, ``jaxflex.sim.step.rk4``)."""
    unravel = ravel_pytree({k: jnp.zeros(shape, th.dtype) for k, shape in spec})[1]
    ys, x_end = prob._segment(unravel(th), v0.reshape(dims), tau, tau_pre, rolled, first)
    return jnp.concatenate([ys.reshape(-1), x_end.reshape(-1)])


@persistent_jit
def replay_segments(prob: Problem, th: Array, v0s: Array, spec: tuple,
                    dims: tuple[int, int]) -> Array:
    """Every segment of ``prob`` replayed from flat coordinates ``th`` and flat start states
    ``v0s`` (S, n_state * n): (S, outputs + end state) [rad, rad/s], flattened per segment.
    ``spec``: ``theta_spec`` of the coordinates; ``dims``: (n_state, n)."""
    return jax.vmap(lambda v, u, p, f: _segment_flat(prob, spec, dims, th, v, u, p, f))(
        v0s, prob.segs.tau, prob.segs.tau_pre, _first_slot(v0s.shape[0]))


@persistent_jit
def segment_jacobians(prob: Problem, th: Array, v0s: Array, spec: tuple,
                      dims: tuple[int, int]) -> tuple[Array, Array, Array, Array]:
    """``replay_segments`` and its Jacobian blocks in one forward pass per segment, with P
    tangents for the fitted coordinates (``jac_columns`` of them with a mask, else all) and,
    with free starts, the segment's own n_state * n start entries: (outputs (S, m), d/dtheta
    (S, m, P), d/dstart (S, m, n_state n), basis (k, P): the unit vectors of the P fitted
    coordinates among the k). With ``prob.rolled_stages`` the replay inside takes its RK4
    stages as a loop (``Problem``)."""
    k = th.shape[0]
    if prob.jac_columns is None:
        basis = jnp.eye(k, dtype=th.dtype)
    else:  # unit vectors of the fitted entries (masked ones have zero derivative)
        fitted = ravel_pytree({nm: jnp.broadcast_to(prob.space.mask[nm], (m,))
                               for nm, m in zip(prob.space.names, prob.space.sizes)})[0]
        idx = jnp.nonzero(fitted, size=prob.jac_columns, fill_value=k)[0]
        basis = jax.nn.one_hot(idx, k + 1, dtype=th.dtype)[:, :k].T
    P = basis.shape[1]
    free = prob.free_starts

    def seg_and_jac(v0, tau, tau_pre, first):
        # one forward pass with P (+ n_state*n) tangents: the fitted theta directions (and
        # the segment's own start state)
        f = lambda t_, v_: _segment_flat(prob, spec, dims, t_, v_, tau, tau_pre,  # noqa: E731
                                         first, rolled=prob.rolled_stages)
        d = v0.shape[0]
        t_th = basis.T if not free else jnp.concatenate([basis.T, jnp.zeros((d, k), th.dtype)])
        t_v = jnp.zeros((P, d), v0.dtype) if not free else jnp.concatenate(
            [jnp.zeros((P, d), v0.dtype), jnp.eye(d, dtype=v0.dtype)])
        out, cols = jax.vmap(lambda a, b: jax.jvp(f, (th, v0), (a, b)),
                             out_axes=(None, 1))(t_th, t_v)
        return out, cols[:, :P], cols[:, P:]

    out, jac_th, jac_v = jax.vmap(seg_and_jac)(v0s, prob.segs.tau, prob.segs.tau_pre,
                                               _first_slot(v0s.shape[0]))
    return out, jac_th, jac_v, basis

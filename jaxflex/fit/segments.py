"""The log cut into segments for multiple shooting (``jaxflex.fit.problem``): the data pieces
(``Segments``, ``make_segments``), the buckets of segment counts a program is compiled for
(``segment_slots``, ``slot_rows``, ``on_slot_rows``), the measured channels fitted and the
layout of a segment's start vector (``pack_state``, ``unpack_state``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxflex.core.friction import LuGre
from jaxflex.core.state import PlantState
from jaxflex.core.validation import to_device
from jaxflex.fit.signal import savgol
from jaxflex.io.logs import Log
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.sim.step import ModelKind


class Segments(eqx.Module):
    """Pieces of a log for multiple shooting.

    tau (S, L, n) logged torque [N m]; y_meas (S, L, n_out) measured outputs [rad];
    tau_pre (S, W, n) the torque before each start (the first sample repeated before the log
    starts); x0 (S, n_state, n) start states estimated from the data; t0 (S,) start times [s].
    ``active`` (S,) bool, or None (every segment is data): which slots hold data; the others
    are inert padding (``Problem.padded``: copies of the last segment whose residuals and
    continuity defects are zero), so that logs of other lengths share one compiled program.
    """

    tau: Array
    y_meas: Array
    tau_pre: Array
    x0: Array
    t0: Array
    active: Array | None = None

    @property
    def count(self) -> int:
        """Number of segment slots S (the data segments and any padding after them)."""
        return int(self.tau.shape[0])

    @property
    def length(self) -> int:
        """Samples per segment L."""
        return int(self.tau.shape[1])


def segment_slots(count: int) -> int:
    """The number of segment slots a problem of ``count`` segments is compiled for
    (``Problem.padded``), so that logs of other lengths share the solver's compiled programs:
    1 and 2 as they are, then 4 and 8, then m 2^e with m in 5..8 (10, 12, 14, 16, 20, 24,
    ...). A new compilation costs about a thousand steps of a small problem, so small counts
    share coarse slots (at most 3 inert segments); from 9 segments on, the padding costs at
    most a quarter more segment replays (about a tenth on average)."""
    if count <= 2:
        return int(count)
    if count <= 8:
        return 4 if count <= 4 else 8
    e = (count - 1).bit_length() - 3        # 8 * 2^(e-1) < count <= 8 * 2^e
    m = -(-count // (1 << e))               # ceil(count / 2^e), in 5..8
    return int(m << e)


def slot_rows(count: int, slots: int | None = None) -> np.ndarray:
    """Row indices 0..count-1 filling ``slots`` (default ``segment_slots(count)``) slots, the
    last repeated: a per-log array indexed with them and cut back to ``count`` rows after a
    compiled call keeps that call's shape within the bucket (``Problem.padded``,
    ``on_slot_rows``)."""
    slots = segment_slots(count) if slots is None else slots
    return np.minimum(np.arange(slots), count - 1)


def on_slot_rows(fn: Callable[..., Any], *rows: Any) -> Any:
    """``fn(*rows)`` for a ``fn`` that works row by row (a vmap over the leading axis, or a
    compiled program of one): the rows (n each) padded to the slots of n (``slot_rows``) and
    moved to the device, every output cut back to n rows on the host (numpy), so that logs of
    other lengths share ``fn``'s program. The one way jaxflex evaluates a JAX function on
    per-log rows (start z, static-map inverse dynamics, discover's start loads, capacity clip
    and localisation)."""
    n = np.shape(rows[0])[0]
    pick = slot_rows(n)
    out = fn(*(to_device(np.asarray(a)[pick]) for a in rows))
    return jax.tree_util.tree_map(lambda o: np.asarray(o)[:n], out)


@persistent_jit(fast_compile=True)
def _steady_z(friction: LuGre, v: Array) -> Array:
    """``friction.z_steady`` row by row, (rows, n) [rad] from velocities (rows, n) [rad/s],
    as one program (evaluated op by op, its ten operations compiled one by one took 0.6 s
    of a first ``jaxflex identify``)."""
    return jax.vmap(friction.z_steady)(v)


def segment_rows(v: Array, S: int, d: int) -> Array:
    """Residual rows (..., m) of a free-start multiple-shooting problem regrouped per segment,
    (..., S, my + d): segment s's outputs, then its continuity defect (zero for the last)."""
    lead = v.shape[:-1]
    my = (v.shape[-1] - (S - 1) * d) // S
    out = v[..., : S * my].reshape(*lead, S, my)
    de = v[..., S * my:].reshape(*lead, S - 1, d)
    de = jnp.concatenate([de, jnp.zeros((*lead, 1, d), v.dtype)], axis=-2)
    return jnp.concatenate([out, de], axis=-1)


def output_columns(log: Log, kind: ModelKind, outputs: Sequence[str] | None) -> tuple[str, ...]:
    """The measured position channels fitted: default ("q1", "q2") for the flexible model when
    the log has q2, else ("q1",); raises ``ValueError`` for a channel the log lacks."""
    if outputs is None and kind == "rotor":  # the rotor subsystem predicts the motor angle
        outputs = ("q2",)
    if outputs is None and kind == "link":  # the link subsystem predicts the link angle
        outputs = ("q1",)
    if outputs is None:
        outputs = ("q1", "q2") if (kind == "flexible" and log.q2 is not None) else ("q1",)
    outputs = tuple(outputs)
    for o in outputs:
        if o not in ("q1", "q2") or getattr(log, o) is None:
            raise ValueError(f"fit: output '{o}' is not a position column of this log")
    return outputs


def make_segments(
    log: Log, *, kind: ModelKind = "flexible", outputs: Sequence[str] = ("q1", "q2"),
    start: int = 0, stop: int | None = None, length: int | None = None, warmup: int = 30,
    window: int = 31, friction: LuGre | None = None,
) -> Segments:
    """Non-overlapping segments of ``length`` samples within samples [start, stop) of a log
    (a tail shorter than one segment is dropped; ``length`` None: one segment). For the
    "rotor" kind ``tau`` holds (S, L, 4, n): the torque and the measured link angle, velocity
    and acceleration (``jaxflex.sim.step.ROTOR_INPUTS``); for the "link" kind (S, L, 3, n): the
    measured rotor angle, velocity and acceleration (``jaxflex.sim.step.LINK_INPUTS``).

    Start states: angles from the log, velocities by Savitzky-Golay differentiation over
    ``window`` samples, z the steady bristle deflection of ``friction`` at that velocity
    (``LuGre.z_steady``; zeros if None).
    """
    if log.tau is None or log.q1 is None:
        raise ValueError("fit: the log needs columns tau and q1")
    stop = log.N if stop is None else stop
    L = stop - start if length is None else int(length)
    if not 2 <= L <= stop - start:
        raise ValueError(f"fit: segment length must be in [2, {stop - start}] samples, got {L}")
    starts = np.arange(start, stop - L + 1, L)
    dt = log.dt
    idx = starts[:, None] + np.arange(L)[None, :]
    pre = np.clip(starts[:, None] + np.arange(-warmup, 0)[None, :], 0, None)
    q1 = log.q1
    q2 = log.q2 if log.q2 is not None else log.q1
    v1 = savgol(q1, dt, 1, window)
    v2 = savgol(q2, dt, 1, window)
    if friction is None:
        z0 = np.zeros_like(v1[starts])
    else:  # one compiled program on the bucket's slots: none per segment count
        z0 = on_slot_rows(lambda v: _steady_z(friction, v), v1[starts])
    if kind == "rigid":
        x0 = np.stack([q1[starts], v1[starts], z0], axis=1)
    else:
        x0 = np.stack([q1[starts], v1[starts], q2[starts], v2[starts], z0], axis=1)
    y = np.concatenate([getattr(log, o) for o in outputs], axis=-1)
    u = log.tau
    if kind == "rotor":  # input (N, 4, n): tau and the measured link motion
        if log.q2 is None:
            raise ValueError("fit: the rotor model needs the motor angle q2 in the log")
        u = np.stack([log.tau, q1, v1, savgol(q1, dt, 2, window)], axis=1)
    if kind == "link":  # input (N, 3, n): the measured rotor motion
        if log.q2 is None:
            raise ValueError("fit: the link model needs the motor angle q2 in the log")
        u = np.stack([q2, v2, savgol(q2, dt, 2, window)], axis=1)
    return Segments(
        tau=to_device(u[idx]), y_meas=to_device(y[idx]), tau_pre=to_device(log.tau[pre]),
        x0=to_device(x0), t0=to_device(log.t[starts]),
    )


def pack_state(kind: ModelKind, x: PlantState) -> Array:
    """Segment start vector (q1, dq1, [q2, dq2], z), shape (n_state, n); aux dropped."""
    if kind == "rigid":
        return jnp.stack([x.q1, x.dq1, x.z])
    return jnp.stack([x.q1, x.dq1, x.q2, x.dq2, x.z])


def unpack_state(kind: ModelKind, v: Array, aux: Any = None) -> PlantState:
    """Inverse of ``pack_state``."""
    if kind == "rigid":
        q1, dq1, z = v
        return PlantState(q1=q1, dq1=dq1, q2=q1, dq2=dq1, z=z, aux=aux)
    q1, dq1, q2, dq2, z = v
    return PlantState(q1=q1, dq1=dq1, q2=q2, dq2=dq2, z=z, aux=aux)

"""Inverse dynamics from a log: the measured motion's derivatives, the torques a model needs
to follow that motion, and the linear-in-parameters regressions built on them.

Every workflow that reads a model's equation error off a log goes through this module:
identification's start from the data, the static friction map, discovery's localisation of
the residual, the rigid baseline of validation and the arm's regressor. Derivatives are
Savitzky-Golay (``savgol``) over one window of samples.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxtyping import Array

from jaxflex.core.effects import link_input
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.state import PlantState
from jaxflex.fit.segments import on_slot_rows
from jaxflex.fit.signal import savgol
from jaxflex.io.logs import Log
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.sim.step import MODEL_KINDS

#: Regressors of the rigid model ``tau = Jt q'' + Fv q' + Fc sign(q') + offset`` (eq. 37
#: with Coulomb and viscous friction and a constant), in ``rigid_regressors``' column order.
RIGID_TERMS: tuple[str, ...] = ("Jt", "Fv", "Fc", "offset")


class Motion(eqx.Module):
    """A log's motion for inverse dynamics: link (1) and rotor (2) angles [rad], velocities
    [rad/s] and accelerations [rad/s^2], and the torque [N m], each (N, n). A rigid model's
    motion has the motor encoder's samples on both sides."""

    q1: Array
    v1: Array
    a1: Array
    q2: Array
    v2: Array
    a2: Array
    tau: Array

    def columns(self) -> tuple[Array, ...]:
        """The arrays in the order of the fields: q1, v1, a1, q2, v2, a2, tau."""
        return (self.q1, self.v1, self.a1, self.q2, self.v2, self.a2, self.tau)


def measured_motion(log: Log, window: int = 31, *, kind: str = "flexible",
                    smooth: bool = False) -> Motion:
    """The ``Motion`` of ``log`` under the model ``kind`` (``MODEL_KINDS``): velocities and
    accelerations by Savitzky-Golay differentiation over ``window`` samples (``savgol``);
    the torque as logged; the angles as logged, or smoothed by the same filter when
    ``smooth`` (the motion the derivatives describe). The rigid kind takes both sides from
    the link column q1. Raises ``ValueError`` for an unknown kind,
    a log without torque, or a two-sided kind on a log without q2."""
    if kind not in MODEL_KINDS:
        raise ValueError(f"inverse dynamics: model must be one of {MODEL_KINDS}, got {kind!r}")
    if log.tau is None:
        raise ValueError("inverse dynamics: the log has no torque column")
    if kind != "rigid" and log.q2 is None:
        raise ValueError(f"inverse dynamics: the {kind} model needs the motor angle q2 in "
                         "the log")
    dt = log.dt

    def side(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        angle = savgol(q, dt, 0, window) if smooth else np.asarray(q, float)
        return angle, savgol(q, dt, 1, window), savgol(q, dt, 2, window)

    link = side(log.q1)
    rotor = link if kind == "rigid" else side(log.q2)
    return Motion(*link, *rotor, np.asarray(log.tau, float))


def model_residuals(plant: FlexibleJointPlant, kind: str, motion: Motion,
                    z: Array | None = None) -> tuple[Array, Array]:
    """Link and rotor torque residuals [N m], (N, n) each, of ``plant`` at the measured
    ``motion`` (``FlexibleJointPlant.torque_residuals``, eq. 2-3): what the model lacks to
    follow it. The friction's bristle deflection is ``z`` (N, n) [rad] where given, else at
    its steady state (F = F_ss, eq. 35); the effects' states are at theirs; the rotor kind
    reads the link motion through the effects' link maps (``link_input``). A plant without friction leaves the friction the motion needs in the
    link line. Traceable in the plant; ``torque_residuals`` runs it on a log."""
    def one(a1, v1, ac1, a2, v2, ac2, tau, z):
        if kind == "rotor":
            a1, v1 = link_input(plant.effects, a1, v1, ac1)
        if z is None:
            z = (plant.lugre.z_steady(v1) if plant.friction is not None
                 else jnp.zeros_like(v1))
        aux = tuple(e.aux_steady(tau) for e in plant.effects) if plant.effects else None
        x = PlantState(q1=a1, dq1=v1, q2=a2, dq2=v2, z=z, aux=aux)
        return plant.torque_residuals(x, ac1, ac2, tau)

    return jax.vmap(one)(*(jnp.asarray(c) for c in motion.columns()), z)


@persistent_jit(fast_compile=True)
def _residual_rows(plant: FlexibleJointPlant, kind: str, *cols: Array
                   ) -> tuple[Array, Array]:
    return model_residuals(plant, kind, Motion(*cols))


def torque_residuals(plant: FlexibleJointPlant, motion: Motion,
                     kind: str = "flexible") -> tuple[np.ndarray, np.ndarray]:
    """``model_residuals`` of ``plant`` on a log's ``motion``, as arrays (N, n) [N m]: one
    compiled program per bucket of log lengths (``on_slot_rows``)."""
    cols = [np.asarray(c, float).reshape(len(c), -1) for c in motion.columns()]
    link, rotor = on_slot_rows(functools.partial(_residual_rows, plant, kind), *cols)
    return np.asarray(link), np.asarray(rotor)


def rigid_regressors(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Columns of the rigid model (``RIGID_TERMS``) at velocities ``v`` [rad/s] and
    accelerations ``a`` [rad/s^2] of shape S: an array S + (4,) of ``a, v, sign(v), 1``."""
    v = np.asarray(v, float)
    return np.stack([np.asarray(a, float), v, np.sign(v), np.ones_like(v)], axis=-1)


class LinearFit(NamedTuple):
    """A least-squares fit ``b ~ A x``: coefficients ``x``, their standard errors ``se`` (a
    white residual assumed; inf where ``A`` is rank deficient) and the relative residual
    ``rel`` = ||b - A x|| / ||b||."""

    x: np.ndarray
    se: np.ndarray
    rel: float


def linear_fit(A: np.ndarray, b: np.ndarray) -> LinearFit:
    """Least squares of ``b`` (N,) on the columns of ``A`` (N, p) with standard errors from
    the residual's variance (``LinearFit``)."""
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ x
    dof = max(A.shape[0] - A.shape[1], 1)
    s2 = float(r @ r) / dof
    try:
        se = np.sqrt(np.maximum(np.diag(s2 * np.linalg.inv(A.T @ A)), 0.0))
    except np.linalg.LinAlgError:
        se = np.full(x.shape, np.inf)
    return LinearFit(x, se, math.sqrt(float(r @ r) / max(float(b @ b), 1e-300)))

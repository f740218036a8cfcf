"""Flexible-joint robot plant (docs/spec.md section 1; paper eq. 3, 8, 40).

    M(q1) q1'' + C(q1, q1') q1' + G(q1) + F = K (q2 - q1)      link side, LuGre friction F
    J q2''     + K (q2 - q1)                  = tau             rotor side (link-referred)

The rigid-link part is an ``AbstractLinkDynamics`` (mass matrix and potential energy); C and G are
derived from them by automatic differentiation (Christoffel symbols and the gradient of the
potential), so a new arm needs only M(q) and U(q). The plant is composed of links, joint
inertia J, stiffness K, optional LuGre friction and optional effects (``jaxflex.core.effects``).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.effects import (AbstractEffect, applied_torque, effect_torque,
                                  spring_state_torque, uses_hook)
from jaxflex.core.friction import LuGre
from jaxflex.core.state import PlantState
from jaxflex.core.validation import as_param, check_positive


class AbstractLinkDynamics(eqx.Module):
    """Rigid-link dynamics: mass matrix M(q) [kg m^2] and potential energy U(q) [J].

    ``constraints`` names each field a fit may free (as ``"links.<field>"``, docs/spec.md
    section 5) with its constraint in the vocabulary of ``jaxflex.fit.space``; a field not
    listed (a length, gravity) is geometry, never fitted. ``base_parameters`` gives the
    combinations of the fields that M, C and G depend on (the identifiable ones).
    """

    constraints: ClassVar[dict[str, str]] = {}

    @property
    @abc.abstractmethod
    def n(self) -> int:
        """Number of links."""

    @abc.abstractmethod
    def mass_matrix(self, q: Float[Array, " n"]) -> Float[Array, "n n"]:
        """M(q) [kg m^2]."""

    def solve_mass(self, q: Float[Array, " n"], rhs: Float[Array, " n"]) -> Float[Array, " n"]:
        """M(q)^-1 rhs (accelerations [rad/s^2] from torques [N m])."""
        return jnp.linalg.solve(self.mass_matrix(q), rhs)

    def potential(self, q: Float[Array, " n"]) -> Float[Array, ""]:
        """Potential energy U(q) [J]; zero for a horizontal arm."""
        return jnp.zeros((), dtype=q.dtype)

    def coriolis(self, q: Array, dq: Array, v: Array) -> Float[Array, " n"]:
        """C(q, dq) v [N m] with C from the Christoffel symbols of M (so M' - 2C is skew).

        C v = 1/2 (dM[dq] v + dM[v] dq - grad_q(dq^T M(q) v)), every term a contraction of
        the one derivative T_ijk = dM_ij/dq_k (a single forward pass over the n directions).
        """
        T = jax.jacfwd(self.mass_matrix)(q)
        return 0.5 * (jnp.einsum("ijk,j,k->i", T, v, dq) + jnp.einsum("ijk,j,k->i", T, dq, v)
                      - jnp.einsum("jki,j,k->i", T, dq, v))

    def gravity(self, q: Float[Array, " n"]) -> Float[Array, " n"]:
        """G(q) = dU/dq [N m]."""
        return jax.grad(self.potential)(q)

    def base_parameters(self) -> dict[str, Array]:
        """The base parameters: the fewest combinations of the fields that determine M, C
        and G (dict name -> value, SI units). Fields outside every combination, and
        combinations beyond their number, no log can determine. Default: the fitted fields
        themselves (each determines the dynamics on its own)."""
        return {k: getattr(self, k) for k in self.constraints}

    def base_definitions(self) -> dict[str, str]:
        """Each base parameter's definition in words (name -> expression of the fields)."""
        return {k: k for k in self.constraints}


class DiagonalInertia(AbstractLinkDynamics):
    """Decoupled links with constant inertia, M = diag(I), C = G = 0 (paper eq. 40).

    I [kg m^2] per joint, > 0.
    """

    constraints: ClassVar[dict[str, str]] = {"I": "positive"}
    I: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_positive("plant", I=self.I)

    @property
    def n(self) -> int:
        return int(self.I.shape[-1])

    def mass_matrix(self, q: Array) -> Array:
        return jnp.diag(self.I)

    def solve_mass(self, q: Array, rhs: Array) -> Array:
        # a batched LU of a 1x1 matrix costs far more than a division (vmapped sweeps)
        return rhs / self.I

    def coriolis(self, q: Array, dq: Array, v: Array) -> Array:
        return jnp.zeros_like(v)

    def gravity(self, q: Array) -> Array:
        return jnp.zeros_like(q)


class PlanarTwoLink(AbstractLinkDynamics):
    """Two-link planar arm (revolute-revolute), optionally in a vertical plane with gravity.

    m1, m2 [kg] link masses; l1 [m] length of link 1; lc1, lc2 [m] centre-of-mass distances;
    I1, I2 [kg m^2] link inertias about their centres of mass; g [m/s^2] gravity (0 for a
    horizontal arm). q = (absolute angle of link 1 from the horizontal, relative angle of link 2).

    The masses and inertias are fitted (``constraints``: positive); the lengths l1, lc1, lc2
    and g are geometry. M, C and G depend on the fields only through the base parameters
    (``base_parameters``), three for a horizontal arm and four with gravity.
    """

    constraints: ClassVar[dict[str, str]] = {
        "m1": "positive", "m2": "positive", "lc1": "positive", "lc2": "positive",
        "I1": "positive", "I2": "positive",
    }
    m1: Array = eqx.field(converter=jnp.asarray)
    m2: Array = eqx.field(converter=jnp.asarray)
    l1: Array = eqx.field(converter=jnp.asarray)
    lc1: Array = eqx.field(converter=jnp.asarray)
    lc2: Array = eqx.field(converter=jnp.asarray)
    I1: Array = eqx.field(converter=jnp.asarray)
    I2: Array = eqx.field(converter=jnp.asarray)
    g: Array = eqx.field(converter=jnp.asarray, default=9.81)

    def __check_init__(self) -> None:
        check_positive(
            "PlanarTwoLink", m1=self.m1, m2=self.m2, l1=self.l1, lc1=self.lc1, lc2=self.lc2,
            I1=self.I1, I2=self.I2,
        )

    @property
    def n(self) -> int:
        return 2

    def mass_matrix(self, q: Array) -> Array:
        c2 = jnp.cos(q[1])
        m11 = self.I1 + self.I2 + self.m1 * self.lc1**2 + self.m2 * (
            self.l1**2 + self.lc2**2 + 2 * self.l1 * self.lc2 * c2
        )
        m12 = self.I2 + self.m2 * (self.lc2**2 + self.l1 * self.lc2 * c2)
        m22 = self.I2 + self.m2 * self.lc2**2
        return jnp.stack([jnp.stack([m11, m12]), jnp.stack([m12, m22])])

    def potential(self, q: Array) -> Array:
        y1 = self.lc1 * jnp.sin(q[0])
        y2 = self.l1 * jnp.sin(q[0]) + self.lc2 * jnp.sin(q[0] + q[1])
        return self.g * (self.m1 * y1 + self.m2 * y2)

    def base_parameters(self) -> dict[str, Array]:
        """The base parameters of the arm (paper eq. 3's M, C, G written in them):

            a1 = I1 + m1 lc1^2 + m2 l1^2   [kg m^2]   link 1 about joint 1, link 2 as a point
            a2 = I2 + m2 lc2^2             [kg m^2]   link 2 about joint 2
            a3 = m2 l1 lc2                 [kg m^2]   the coupling
            a4 = m1 lc1 + m2 l1            [kg m]     first moment about joint 1 (g != 0 only)

        M = [[a1 + a2 + 2 a3 c2, a2 + a3 c2], [a2 + a3 c2, a2]], C from the Christoffel
        symbols with h = a3 s2, G = g [a4 c1 + (a3 / l1) c12, (a3 / l1) c12]: with l1 known,
        m2 lc2 = a3 / l1 is no further parameter. M > 0 at every q iff a2 > 0 and
        a1 a2 > a3^2. A horizontal arm (g = 0) has no a4."""
        out = {
            "a1": self.I1 + self.m1 * self.lc1**2 + self.m2 * self.l1**2,
            "a2": self.I2 + self.m2 * self.lc2**2,
            "a3": self.m2 * self.l1 * self.lc2,
        }
        if _nonzero(self.g):
            out["a4"] = self.m1 * self.lc1 + self.m2 * self.l1
        return out

    def base_definitions(self) -> dict[str, str]:
        """The expression of each base parameter (``base_parameters``)."""
        out = {"a1": "I1 + m1 lc1^2 + m2 l1^2", "a2": "I2 + m2 lc2^2", "a3": "m2 l1 lc2"}
        if _nonzero(self.g):
            out["a4"] = "m1 lc1 + m2 l1"
        return out


def _nonzero(x: ArrayLike) -> bool:
    """Whether a concrete structural value (gravity) is not zero; a traced one counts as
    nonzero (the combinations then include the gravity terms)."""
    if isinstance(x, jax.core.Tracer):
        return True
    return bool(jnp.any(jnp.asarray(x) != 0))


#: The least level a direction-dependent shift leaves the link friction: this share of the
#: LuGre's own g(v) (a fit may try a shift larger than the level; g must stay positive for
#: eq. 5's bristle to relax).
LEVEL_FLOOR: float = 0.05


class LevelledLuGre(LuGre):
    """The plant's LuGre (eq. 4-6) with its level shifted by direction by the plant's effects
    (``AbstractEffect.friction_level``): g(v) + sign(v) Delta(v), at least ``LEVEL_FLOOR``
    g(v). Everything that reads the level (the bristle's rate, its exact step, the steady
    state, the capacity) reads this one; the parameters are the LuGre's."""

    effects: tuple[AbstractEffect, ...] = ()

    def g(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """The level [N m] for the direction of ``v`` [rad/s] (eq. 6 shifted)."""
        base = super().g(v)
        shift = effect_torque(self.effects, "friction_level", v, self)
        return jnp.maximum(base + jnp.sign(v) * shift, LEVEL_FLOOR * base)


class FlexibleJointPlant(eqx.Module):
    """Flexible-joint robot: links + elastic joints + rotors + LuGre friction + effects.

    J [kg m^2] rotor inertias (link-referred), K [N m/rad] joint stiffnesses, both (n,).
    ``friction=None`` gives a frictionless plant. ``effects`` is a tuple of ``AbstractEffect``s.
    """

    links: AbstractLinkDynamics
    J: Float[Array, " n"] = eqx.field(converter=as_param)
    K: Float[Array, " n"] = eqx.field(converter=as_param)
    friction: LuGre | None = None
    effects: tuple[AbstractEffect, ...] = ()

    def __check_init__(self) -> None:
        check_positive("plant", J=self.J, K=self.K)
        n = self.links.n
        for name in ("J", "K"):
            if getattr(self, name).shape != (n,):
                raise ValueError(
                    f"plant: {name} must have shape ({n},) to match {n} link(s), "
                    f"got {getattr(self, name).shape}"
                )
        if self.friction is not None and self.friction.Fc.shape != (n,):
            raise ValueError(
                f"plant: friction parameters must have shape ({n},), got {self.friction.Fc.shape}"
            )

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.links.n

    def with_effects(self, *effects: AbstractEffect) -> FlexibleJointPlant:
        """A copy with ``effects`` appended (the discrepancy workflow's way to augment)."""
        return eqx.tree_at(lambda p: p.effects, self, tuple(self.effects) + tuple(effects))

    def init_state(
        self, q1: ArrayLike = 0.0, dq1: ArrayLike = 0.0, q2: ArrayLike | None = None,
        dq2: ArrayLike | None = None, z: ArrayLike = 0.0,
    ) -> PlantState:
        """A state with the given values broadcast to (n,); q2 defaults to q1 (spring at rest)."""
        dtype = jnp.result_type(float)
        full = lambda v: jnp.broadcast_to(jnp.asarray(v, dtype), (self.n,))
        q1a = full(q1)
        aux = tuple(e.aux_init(self.n) for e in self.effects) if self.effects else None
        return PlantState(
            q1=q1a, dq1=full(dq1), q2=q1a if q2 is None else full(q2),
            dq2=full(dq1) if dq2 is None else full(dq2), z=full(z), aux=aux,
        )

    @property
    def lugre(self) -> LuGre | None:
        """The link's friction model: ``friction`` itself, or, where an effect shifts its
        level by direction (``friction_level``), the ``LevelledLuGre`` of both; None without
        friction."""
        if self.friction is None or not uses_hook(self.effects, "friction_level"):
            return self.friction
        fr = self.friction
        return LevelledLuGre(Fc=fr.Fc, Fs=fr.Fs, vs=fr.vs, sigma0=fr.sigma0, sigma1=fr.sigma1,
                             sigma2=fr.sigma2, effects=tuple(self.effects))

    def friction_torque(self, x: PlantState) -> Float[Array, " n"]:
        """LuGre friction F(q1', z) [N m] (eq. 4, with the effects' level shifts: ``lugre``);
        zero without friction."""
        if self.friction is None:
            return jnp.zeros_like(x.dq1)
        return self.lugre.force(x.dq1, x.z)

    def spring_torque(self, x: PlantState) -> Float[Array, " n"]:
        """Elastic joint torque K (q2 - q1) plus effects' spring terms [N m] (eq. 3), those of
        their internal states (a hysteresis) included."""
        d, dd = x.q2 - x.q1, x.dq2 - x.dq1
        Ts = self.K * d + effect_torque(self.effects, "spring_torque", d, dd)
        extra = spring_state_torque(self.effects, x.aux, d, dd)
        return Ts if extra is None else Ts + extra

    def applied_torque(self, x: PlantState, tau: Array) -> Float[Array, " n"]:
        """Motor torque reaching the rotor after input-path effects [N m]."""
        return applied_torque(self.effects, tau, x.aux or ())

    def accelerations(self, x: PlantState, tau: Array) -> tuple[Array, Array]:
        """(q1'', q2'') [rad/s^2] from eq. 3 with friction and effects."""
        Ts = self.spring_torque(x)
        link_rhs = (
            Ts - self.links.coriolis(x.q1, x.dq1, x.dq1) - self.links.gravity(x.q1)
            - self.friction_torque(x) + effect_torque(self.effects, "link_torque", x)
        )
        ddq1 = self.links.solve_mass(x.q1, link_rhs)
        rotor_rhs = (
            self.applied_torque(x, tau) - Ts + effect_torque(self.effects, "rotor_torque", x)
        )
        return ddq1, rotor_rhs / self.J

    def torque_residuals(
        self, x: PlantState, ddq1: Float[Array, " n"], ddq2: Float[Array, " n"],
        tau: Float[Array, " n"],
    ) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """Inverse dynamics: what eq. 3 leaves unexplained at a measured motion [N m].

            r_link  = M q1'' + C q1' + G + F - T_s - sum link_torque
            r_rotor = J q2'' + T_s - tau_a - sum rotor_torque

        with the friction F of the state ``x`` (pass z at its steady state ``z_steady(q1')``
        for F_ss of eq. 35) and effect states in ``x.aux``. Both are zero for a motion the
        model explains; a torque the model lacks appears with its own sign (a missing link
        torque T_e gives r_link = T_e). The one inverse-dynamics function of jaxflex (used by
        the discrepancy localisation and the torque-prediction error)."""
        Ts = self.spring_torque(x)
        r_link = (
            self.links.mass_matrix(x.q1) @ ddq1 + self.links.coriolis(x.q1, x.dq1, x.dq1)
            + self.links.gravity(x.q1) + self.friction_torque(x) - Ts
            - effect_torque(self.effects, "link_torque", x)
        )
        r_rotor = (
            self.J * ddq2 + Ts - self.applied_torque(x, tau)
            - effect_torque(self.effects, "rotor_torque", x)
        )
        return r_link, r_rotor

    def vector_field(self, x: PlantState, tau: Float[Array, " n"]) -> PlantState:
        """Time derivative of the state under motor torque ``tau`` [N m] (eq. 3-5)."""
        ddq1, ddq2 = self.accelerations(x, tau)
        dz = jnp.zeros_like(x.z) if self.friction is None else self.lugre.z_dot(x.dq1, x.z)
        daux = (
            None if x.aux is None
            else tuple(e.aux_rhs(a, tau, x) for e, a in zip(self.effects, x.aux))
        )
        return PlantState(q1=x.dq1, dq1=ddq1, q2=x.dq2, dq2=ddq2, z=dz, aux=daux)

    def energy(self, x: PlantState) -> Float[Array, ""]:
        """Mechanical energy [J]: link and rotor kinetic, spring and link potential.

        Effects' spring terms are not included (their potential is effect-specific).
        """
        kin = 0.5 * x.dq1 @ self.links.mass_matrix(x.q1) @ x.dq1 + 0.5 * jnp.sum(self.J * x.dq2**2)
        spring = 0.5 * jnp.sum(self.K * (x.q2 - x.q1) ** 2)
        return kin + spring + self.links.potential(x.q1)

    def bristle_energy(self, x: PlantState) -> Float[Array, ""]:
        """LuGre storage function sigma0 z^2 / 2 [J] (passivity of the map v -> F)."""
        if self.friction is None:
            return jnp.zeros(())
        return 0.5 * jnp.sum(self.friction.sigma0 * x.z**2)

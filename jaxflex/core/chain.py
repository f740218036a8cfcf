"""A serial chain of rigid links from its Denavit-Hartenberg parameters: M(q), C(q, q') q', G(q)
for the link side of the flexible-joint arm (paper eq. 2-3; docs/spec.md section 1).

Kinematics in the *standard* Denavit-Hartenberg convention (Denavit & Hartenberg 1955, as in
Spong, Hutchinson & Vidyasagar and Corke's Robotics Toolbox ``Link``): the transform from frame
i-1 to frame i is

    A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i),

with theta_i = q_i + offset_i for a revolute joint ("R") and d_i = q_i + offset_i for a
prismatic one ("P"). Joint i moves about / along z_{i-1}; frame i sits at the distal end of
link i, and link i's inertial parameters are expressed in frame i.

Dynamics as a Lagrangian by automatic differentiation: the kinetic energy
T = 1/2 q'^T M(q) q' comes from the geometric Jacobians of the link frames (no symbolic
expansion), the potential V(q) = -sum_i g . (m_i o_i + R_i h_i) from the frame positions;
C(q, q') v follows from the Christoffel symbols of M (``jax.jvp`` of M,
``AbstractLinkDynamics.coriolis``, so M' - 2C is skew, which the cascade law's proof uses) and
G = dV/dq from ``jax.grad``. Everything is a pure function of array leaves, so ``jit``, ``vmap``
and ``grad`` pass through q, the kinematics and the inertial parameters.

Why not MuJoCo MJX or jaxsim: the cascade law (eq. 13) and the certificate need M, C and G
themselves (not only forward dynamics), an identification needs the inverse dynamics to be
*linear* in the inertial parameters (the regressor of ``jaxflex.core.inertial``), and arms of up to
six or seven joints make the O(n^3) Jacobian form cheap. A Lagrangian of about a hundred lines
gives all three with no compiled dependency; MJX builds its model from an MJCF file on the
host, so differentiating through inertias means rebuilding device arrays of its model, and it
is not a core dependency of jaxflex.

Inertial parameters of link i, the ten *standard* (linear) parameters about the origin of
frame i, in frame i (``INERTIAL_NAMES``):

    phi_i = (m, m cx, m cy, m cz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz)

with m [kg] the mass, c [m] the centre of mass, and I_o [kg m^2] = I_c + m (|c|^2 1 - c c^T)
the inertia tensor about the frame origin, whose matrix entries are listed (Ixy is the (x, y)
entry of the tensor, not its negation). M, C and G are linear in phi (the regressor form).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.plant import AbstractLinkDynamics
from jaxflex.core.validation import as_param

#: Names of a link's ten standard inertial parameters, in the order of ``SerialChain.phi``.
INERTIAL_NAMES: tuple[str, ...] = (
    "m", "mx", "my", "mz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz",
)
#: Gravity's acceleration [m/s^2] in a base frame whose z axis points up.
GRAVITY_DOWN: tuple[float, float, float] = (0.0, 0.0, -9.81)


def skew(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """The cross-product matrix S(v) (S(v) w = v x w)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                      jnp.stack([-y, x, o], -1)], -2)


def inertia_matrix(I6: Float[Array, "... 6"]) -> Float[Array, "... 3 3"]:
    """The symmetric 3x3 tensor from its entries (Ixx, Ixy, Ixz, Iyy, Iyz, Izz) [kg m^2]."""
    xx, xy, xz, yy, yz, zz = (I6[..., k] for k in range(6))
    return jnp.stack([jnp.stack([xx, xy, xz], -1), jnp.stack([xy, yy, yz], -1),
                      jnp.stack([xz, yz, zz], -1)], -2)


def inertia_entries(I: Float[Array, "... 3 3"]) -> Float[Array, "... 6"]:
    """(Ixx, Ixy, Ixz, Iyy, Iyz, Izz) of a 3x3 tensor (its upper triangle)."""
    return jnp.stack([I[..., 0, 0], I[..., 0, 1], I[..., 0, 2], I[..., 1, 1], I[..., 1, 2],
                      I[..., 2, 2]], -1)


def is_inertia_tensor(I: ArrayLike) -> bool:
    """Whether ``I`` [kg m^2] (..., 3, 3) holds symmetric positive semi-definite tensors (to
    rounding: eigenvalues of the symmetric part above -1e-12 of the largest entry, at least
    1 kg m^2)."""
    I = np.asarray(I, float)
    sym = (I + np.swapaxes(I, -1, -2)) / 2
    return bool(np.all(np.linalg.eigvalsh(sym) >= -1e-12 * np.max(np.abs(I), initial=1.0)))


def standard_parameters(mass: ArrayLike, com: ArrayLike, inertia: ArrayLike
                        ) -> Float[Array, "n 10"]:
    """The standard parameters phi (module docstring) of links given their mass m [kg] (n,),
    centre of mass c [m] (n, 3) and inertia tensor about the centre of mass I_c [kg m^2]
    (n, 3, 3), each in its link's frame (parallel-axis theorem to the frame origin)."""
    m = jnp.asarray(mass, jnp.result_type(float))
    c = jnp.asarray(com, m.dtype)
    Ic = jnp.asarray(inertia, m.dtype)
    eye = jnp.eye(3, dtype=m.dtype)
    Io = Ic + m[:, None, None] * (jnp.sum(c * c, -1)[:, None, None] * eye
                                  - c[:, :, None] * c[:, None, :])
    return jnp.concatenate([m[:, None], m[:, None] * c, inertia_entries(Io)], -1)


def _dh_transform(theta: Array, d: Array, a: Array, alpha: Array) -> Array:
    """A_i = Rz(theta) Tz(d) Tx(a) Rx(alpha) as a 4x4 homogeneous transform."""
    ct, st, ca, sa = jnp.cos(theta), jnp.sin(theta), jnp.cos(alpha), jnp.sin(alpha)
    z, o = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.stack([
        jnp.stack([ct, -st * ca, st * sa, a * ct]),
        jnp.stack([st, ct * ca, -ct * sa, a * st]),
        jnp.stack([z, sa, ca, d]),
        jnp.stack([z, z, z, o]),
    ])


class AbstractChain(AbstractLinkDynamics):
    """An open chain of n rigid links, revolute or prismatic joints, described by where its
    frames and joint axes are (``frames``, ``joint_axes``): the dynamics (M from the frames'
    geometric Jacobians, V from their positions, C and G by differentiation, module docstring)
    are the same for every description of the kinematics (standard DH: ``SerialChain``; a
    URDF's joint origins and axes: ``jaxflex.core.urdf.UrdfChain``).

    phi: (n, 10) standard inertial parameters (``INERTIAL_NAMES``), link i's in its own
    frame (frame i of ``frames``). g [m/s^2]: gravity's acceleration vector in the base frame
    (frame 0). joints: one letter per joint, "R" or "P" (static). Each description declares
    the three fields itself (an abstract field here would fix their order before its own)."""

    @abc.abstractmethod
    def frames(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n1 3 3"], Float[Array, "n1 3"]]:
        """Orientations R_i and origins o_i [m] of frames 0..n in the base frame (frame i:
        link i's, in which its ``phi`` is given; frame 0: the base)."""

    @abc.abstractmethod
    def joint_axes(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
        """Each joint's unit axis z_j and a point p_j [m] on it, in the base frame: joint j
        turns the links beyond it about (or moves them along) z_j through p_j."""

    @property
    def n(self) -> int:
        return len(self.joints)

    @property
    def revolute(self) -> Array:
        """1.0 for revolute joints, 0.0 for prismatic, (n,)."""
        return jnp.asarray([j == "R" for j in self.joints], self.phi.dtype)

    @property
    def mass(self) -> Float[Array, " n"]:
        """Link masses m [kg]."""
        return self.phi[:, 0]

    @property
    def com(self) -> Float[Array, "n 3"]:
        """Centres of mass c [m] in each link's frame."""
        return self.phi[:, 1:4] / self.phi[:, :1]

    @property
    def inertia_origin(self) -> Float[Array, "n 3 3"]:
        """Inertia tensors I_o [kg m^2] about each link frame's origin."""
        return inertia_matrix(self.phi[:, 4:])

    @property
    def inertia_com(self) -> Float[Array, "n 3 3"]:
        """Inertia tensors I_c [kg m^2] about each link's centre of mass."""
        c, m = self.com, self.mass
        eye = jnp.eye(3, dtype=m.dtype)
        return self.inertia_origin - m[:, None, None] * (
            jnp.sum(c * c, -1)[:, None, None] * eye - c[:, :, None] * c[:, None, :])

    def with_phi(self, phi: Float[Array, "n 10"]) -> AbstractChain:
        """A copy with other standard inertial parameters (same kinematics)."""
        return eqx.tree_at(lambda s: s.phi, self, jnp.asarray(phi, self.phi.dtype))

    # ----- kinematics and dynamics -------------------------------------------------------

    def axis_kinds(self, q: ArrayLike) -> list[str]:
        """What gravity can do on each joint at the pose ``q`` [rad or m], in the words a
        parameter file declares (``jaxflex.discover.config.AXES``): "prismatic" for a
        prismatic joint, "vertical" for a revolute joint whose axis is parallel to gravity
        (no gravity moment about it, whatever the pose of the joints beyond it), else
        "horizontal" (gravity can act)."""
        z = np.asarray(self.joint_axes(jnp.asarray(q, self.g.dtype))[0])
        g = np.asarray(self.g, float)
        g_dir = g / max(float(np.linalg.norm(g)), 1e-300)
        rev = np.asarray(self.revolute) > 0.5
        return ["prismatic" if not rev[i] else
                "vertical" if abs(float(z[i] @ g_dir)) >= 1.0 - 1e-6 else "horizontal"
                for i in range(self.n)]

    def jacobians(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n 3 n"],
                                                        Float[Array, "n 3 n"]]:
        """Geometric Jacobians (Jo, Jw) of the origins and angular velocities of frames
        1..n: v_o_i = Jo[i] q', omega_i = Jw[i] q' (base frame; [m/rad] or 1)."""
        _, o = self.frames(q)
        z, p = self.joint_axes(q)                          # (n, 3) each
        rev = self.revolute
        lever = o[1:, None, :] - p[None, :, :]             # o_i - p_j, (n_i, n_j, 3)
        lin = rev[None, :, None] * jnp.cross(z[None], lever) + (1 - rev)[None, :, None] * z[None]
        mask = jnp.tril(jnp.ones((self.n, self.n), q.dtype))[:, :, None]
        Jo = jnp.swapaxes(mask * lin, 1, 2)
        Jw = jnp.swapaxes(mask * (rev[:, None] * z)[None], 1, 2)
        return Jo, Jw

    def mass_matrix(self, q: Float[Array, " n"]) -> Float[Array, "n n"]:
        """M(q) [kg m^2, kg m, kg]: sum over links of their kinetic-energy quadratic forms

            M_i = m Jo^T Jo + Jw^T R I_o R^T Jw - (Jo^T S(R h) Jw + (Jo^T S(R h) Jw)^T)

        with h = m c (T_i = 1/2 m |v_o|^2 + v_o . (omega x R h) + 1/2 omega^T R I_o R^T omega).
        """
        R, _ = self.frames(q)
        R = R[1:]
        Jo, Jw = self.jacobians(q)
        m, h, Io = self.phi[:, 0], self.phi[:, 1:4], self.inertia_origin
        Iw = R @ Io @ jnp.swapaxes(R, 1, 2)
        Sh = skew(jnp.einsum("iab,ib->ia", R, h))
        lin = jnp.einsum("i,iaj,iak->jk", m, Jo, Jo)
        rot = jnp.einsum("iaj,iab,ibk->jk", Jw, Iw, Jw)
        cross = jnp.einsum("iaj,iab,ibk->jk", Jo, Sh, Jw)
        return lin + rot - cross - cross.T

    def kinetic_energy(self, q: Float[Array, " n"], dq: Float[Array, " n"]) -> Float[Array, ""]:
        """T = 1/2 q'^T M(q) q' [J]."""
        return 0.5 * dq @ self.mass_matrix(q) @ dq

    def potential(self, q: Float[Array, " n"]) -> Float[Array, ""]:
        """V(q) = -sum_i g . (m_i o_i + R_i h_i) [J] (zero at the base origin)."""
        R, o = self.frames(q)
        m, h = self.phi[:, 0], self.phi[:, 1:4]
        pos = m[:, None] * o[1:] + jnp.einsum("iab,ib->ia", R[1:], h)
        return -jnp.sum(pos @ self.g)

    def inverse_dynamics(self, q: Float[Array, " n"], dq: Float[Array, " n"],
                         ddq: Float[Array, " n"]) -> Float[Array, " n"]:
        """M(q) q'' + C(q, q') q' + G(q) [N m or N]: the joint torques of the rigid chain
        (the left side of the link line of eq. 3 without friction); linear in ``phi``."""
        return self.mass_matrix(q) @ ddq + self.coriolis(q, dq, dq) + self.gravity(q)

    def com_positions(self, q: Float[Array, " n"]) -> Float[Array, "n 3"]:
        """Centres of mass [m] of the links in the base frame."""
        R, o = self.frames(q)
        return o[1:] + jnp.einsum("iab,ib->ia", R[1:], self.com)




class SerialChain(AbstractChain):
    """An open chain of n rigid links, revolute or prismatic joints, standard DH (module
    docstring); a ``FlexibleJointPlant``'s ``links``.

    a [m], d [m], alpha [rad], offset [rad for "R", m for "P"]: DH parameters, each (n,);
    the joint variable adds to theta (revolute) or d (prismatic). phi: (n, 10) standard
    inertial parameters (``INERTIAL_NAMES``; build them from mass, centre of mass and
    inertia with ``from_dh``). g [m/s^2]: gravity's acceleration vector in the base
    frame (frame 0), e.g. (0, 0, -9.81) for a base whose z points up. joints: one letter per
    joint, "R" or "P" (static).
    """

    a: Float[Array, " n"] = eqx.field(converter=as_param)
    d: Float[Array, " n"] = eqx.field(converter=as_param)
    alpha: Float[Array, " n"] = eqx.field(converter=as_param)
    offset: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, "n 10"] = eqx.field(converter=lambda x: jnp.asarray(x, jnp.result_type(float)))
    g: Float[Array, " 3"] = eqx.field(converter=lambda x: jnp.asarray(x, jnp.result_type(float)))
    joints: str = eqx.field(static=True, default="")

    def __check_init__(self) -> None:
        n = len(self.joints)
        if n == 0 or set(self.joints) - {"R", "P"}:
            raise ValueError(f"SerialChain: joints must be a non-empty string of 'R' "
                             f"(revolute) and 'P' (prismatic), got {self.joints!r}")
        for name in ("a", "d", "alpha", "offset"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"SerialChain: {name} must have shape ({n},) for joints "
                                 f"{self.joints!r}, got {getattr(self, name).shape}")
        if self.phi.shape != (n, 10):
            raise ValueError(f"SerialChain: phi must have shape ({n}, 10) (INERTIAL_NAMES "
                             f"per link), got {self.phi.shape}")
        if self.g.shape != (3,):
            raise ValueError(f"SerialChain: g must be gravity's acceleration, a 3-vector "
                             f"[m/s^2] in the base frame, got shape {self.g.shape}")

    @classmethod
    def from_dh(
        cls, a: ArrayLike, d: ArrayLike, alpha: ArrayLike, mass: ArrayLike, com: ArrayLike,
        inertia: ArrayLike, gravity: ArrayLike = GRAVITY_DOWN, joints: str | None = None,
        offset: ArrayLike | None = None,
    ) -> SerialChain:
        """A chain from DH parameters and each link's mass, centre of mass and inertia.

        **Arguments:**

        - ``a``, ``d`` [m], ``alpha`` [rad]: standard DH parameters, (n,) each.
        - ``mass`` [kg] (n,); ``com`` [m] (n, 3): centre of mass of link i in frame i;
          ``inertia`` [kg m^2] (n, 3, 3): inertia tensor of link i about its centre of mass,
          in frame i's orientation. Differentiable: ``jax.grad`` through them reaches M, C, G.
        - ``gravity`` [m/s^2]: gravity's acceleration in the base frame.
        - ``joints``: "R"/"P" per joint (default all revolute).
        - ``offset``: joint zero offsets [rad or m] (default 0).

        **Returns:** the ``SerialChain``.

        **Raises:** ``ValueError`` for shapes that disagree.
        """
        a = as_param(a)
        n = a.shape[0]
        joints = "R" * n if joints is None else joints
        offset = jnp.zeros(n) if offset is None else offset
        mass = as_param(mass)
        com, inertia = jnp.asarray(com), jnp.asarray(inertia)
        if mass.shape != (n,) or com.shape != (n, 3) or inertia.shape != (n, 3, 3):
            raise ValueError(f"SerialChain.from_dh: need mass (n,), com (n, 3), inertia "
                             f"(n, 3, 3) for n = {n}, got {mass.shape}, {com.shape}, "
                             f"{inertia.shape}")
        return cls(a=a, d=d, alpha=alpha, offset=offset,
                   phi=standard_parameters(mass, com, inertia), g=gravity, joints=joints)

    # ----- kinematics ------------------------------------------------------------------------

    def frames(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n1 3 3"], Float[Array, "n1 3"]]:
        """Orientations R_i and origins o_i [m] of frames 0..n in the base frame (frame i at
        the distal end of link i, DH)."""
        rev = self.revolute
        theta = (self.offset + q) * rev        # a prismatic joint's theta is 0
        dd = self.d + (self.offset + q) * (1.0 - rev)
        T = jnp.eye(4, dtype=q.dtype)
        Ts = [T]
        for i in range(self.n):
            T = T @ _dh_transform(theta[i], dd[i], self.a[i], self.alpha[i])
            Ts.append(T)
        Ts = jnp.stack(Ts)
        return Ts[:, :3, :3], Ts[:, :3, 3]

    def joint_axes(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
        """Joint j's axis is frame j-1's z axis, through frame j-1's origin (DH)."""
        R, o = self.frames(q)
        return R[:-1, :, 2], o[:-1]


class LockedJoints(AbstractLinkDynamics):
    """A chain with some joints held at fixed positions: the free joints' link dynamics.

    With the held joints at rest (q_h' = q_h'' = 0) the Lagrangian of the free joints has
    M_ff(q_f; q_h) (the free rows and columns of the chain's M) and V(q_f; q_h), so C and G
    follow from them as for any ``AbstractLinkDynamics``. ``chain``: the full chain;
    ``free``: indices of the free joints (static); ``q_held``: positions of all joints
    (n_full,) [rad or m], of which the held ones are used.

    A held joint that moves (a wrist following its own trajectory) adds M_fh q_h'' and
    velocity terms to the free joints' torques; evaluate ``chain.inverse_dynamics`` on the
    full motion for those.
    """

    chain: AbstractChain
    q_held: Float[Array, " n_full"] = eqx.field(converter=as_param)
    free: tuple[int, ...] = eqx.field(static=True, default=())

    def __check_init__(self) -> None:
        if not self.free or len(set(self.free)) != len(self.free) or not all(
                0 <= i < self.chain.n for i in self.free):
            raise ValueError(f"LockedJoints: free must be distinct joint indices in "
                             f"0..{self.chain.n - 1}, got {self.free}")
        if self.q_held.shape != (self.chain.n,):
            raise ValueError(f"LockedJoints: q_held must have shape ({self.chain.n},), got "
                             f"{self.q_held.shape}")

    @property
    def n(self) -> int:
        return len(self.free)

    def full(self, q: Float[Array, " n"]) -> Float[Array, " n_full"]:
        """All joint positions: ``q`` in the free joints, ``q_held`` elsewhere."""
        return self.q_held.astype(q.dtype).at[jnp.asarray(self.free)].set(q)

    def mass_matrix(self, q: Float[Array, " n"]) -> Float[Array, "n n"]:
        idx = jnp.asarray(self.free)
        return self.chain.mass_matrix(self.full(q))[idx][:, idx]

    def potential(self, q: Float[Array, " n"]) -> Float[Array, ""]:
        return self.chain.potential(self.full(q))

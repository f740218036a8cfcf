"""A serial chain from a URDF file (the Unified Robot Description Format of ROS): its joints'
origins and axes and its links' inertial elements, as the link side of a flexible-joint arm
(``UrdfChain``, an ``jaxflex.core.chain.AbstractChain``: M, C, G as for a DH chain).

What is read (``read_urdf``): the ``<link>`` elements' ``<inertial>`` (``origin`` xyz [m] and
rpy [rad], ``mass`` [kg], ``inertia`` [kg m^2] about the centre of mass in the origin's
axes) and the ``<joint>`` elements' ``type``, ``parent``, ``child``, ``origin`` and ``axis``.
Geometry, limits, dynamics tags and transmissions are not read. The chain is the path of
joints from the root link (the one link that is no joint's child) to a leaf whose path holds
every moving joint:

- a ``revolute`` or ``continuous`` joint is a revolute joint ("R"), a ``prismatic`` one a
  prismatic joint ("P");
- a ``fixed`` joint welds its child to its parent: the child's inertia (and everything welded
  to it, branches included) joins the parent link's, and its origin joins the next joint's;
- the root link and what is welded to it do not move and are left out;
- a branch off the path that holds a moving joint, a ``floating`` or ``planar`` joint and a
  ``mimic`` joint are refused (``UrdfError`` naming them): their motion is not the chain's.

Frames, as URDF defines them: joint j's frame is its parent link's frame moved by its
``origin`` (the rotation R = Rz(yaw) Ry(pitch) Rx(roll)); the joint turns (or slides) its
child about (along) ``axis`` in that frame through its origin, and the child link's frame is
the joint's frame after that motion. Link j's inertial parameters ``phi`` are given in that
frame. Gravity is not part of a URDF: it is the reader's argument, in the root link's frame
(default (0, 0, -9.81) m/s^2, z up, as ROS and MuJoCo take it).
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.chain import (
    GRAVITY_DOWN,
    AbstractChain,
    inertia_entries,
    inertia_matrix,
    is_inertia_tensor,
    skew,
    standard_parameters,
)

#: The URDF joint types of a chain's joints, by the letter ``AbstractChain.joints`` uses.
MOVING_TYPES: dict[str, str] = {"revolute": "R", "continuous": "R", "prismatic": "P"}


class UrdfError(ValueError):
    """A URDF that is malformed or that does not describe a serial chain (module docstring)."""


def rpy_matrix(rpy: ArrayLike) -> np.ndarray:
    """URDF's rotation of an origin's ``rpy`` (roll, pitch, yaw) [rad]: Rz(yaw) Ry(pitch)
    Rx(roll), fixed axes."""
    r, p, y = (float(v) for v in np.asarray(rpy, float))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), \
        math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def moved_phi(phi: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """A body's ten standard inertial parameters (``jaxflex.core.chain.INERTIAL_NAMES``)
    given in a frame B, expressed in a frame A where B has orientation ``R`` and origin ``p``
    [m]: m, h' = R h + m p, I_o' = R I_o R^T + m (|p|^2 1 - p p^T) + (p . R h) 2 1 -
    (p (R h)^T + (R h) p^T). Standard parameters of bodies in one frame add."""
    m, h = phi[0], phi[1:4]
    Io = np.asarray(inertia_matrix(np.asarray(phi[4:])))
    Rh = R @ h
    eye = np.eye(3)
    I = (R @ Io @ R.T + m * (p @ p * eye - np.outer(p, p))
         + 2.0 * (p @ Rh) * eye - np.outer(p, Rh) - np.outer(Rh, p))
    return np.concatenate([[m], Rh + m * p, np.asarray(inertia_entries(I))])


def _as_float(x: ArrayLike) -> Array:
    """An array in the default float type (float64 where x64 is on)."""
    return jnp.asarray(x, jnp.result_type(float))


class UrdfChain(AbstractChain):
    """A serial chain in URDF's description (module docstring); a ``FlexibleJointPlant``'s
    ``links``.

    origin: (n, 4, 4) homogeneous transform from joint j's parent link frame to joint j's
    frame (fixed joints before it folded in); axis: (n, 3) joint j's unit axis in its frame;
    phi: (n, 10) standard inertial parameters of link j (and what is welded to it) in its
    frame; g [m/s^2]: gravity's acceleration in the root link's frame; joints: "R"/"P" per
    joint (static); names: the URDF's joint names (static)."""

    origin: Float[Array, "n 4 4"] = eqx.field(converter=_as_float)
    axis: Float[Array, "n 3"] = eqx.field(converter=_as_float)
    phi: Float[Array, "n 10"] = eqx.field(converter=_as_float)
    g: Float[Array, " 3"] = eqx.field(converter=_as_float)
    joints: str = eqx.field(static=True, default="")
    names: tuple[str, ...] = eqx.field(static=True, default=())

    def __check_init__(self) -> None:
        n = len(self.joints)
        if n == 0 or set(self.joints) - {"R", "P"}:
            raise ValueError(f"UrdfChain: joints must be a non-empty string of 'R' and 'P', "
                             f"got {self.joints!r}")
        shapes = {"origin": (n, 4, 4), "axis": (n, 3), "phi": (n, 10), "g": (3,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"UrdfChain: {name} must have shape {shape} for joints "
                                 f"{self.joints!r}, got {getattr(self, name).shape}")

    def _walk(self, q: Float[Array, " n"]) -> tuple[Array, Array, Array, Array]:
        """(orientations and origins of frames 0..n in the root's frame, the joints' axes,
        the joints' origins) at the joint positions ``q``: rotations and translations kept
        apart (no homogeneous products), a joint's turn by Rodrigues' formula
        cos q 1 + sin q S(a) + (1 - cos q) a a^T."""
        R, p = jnp.eye(3, dtype=q.dtype), jnp.zeros(3, q.dtype)
        Rs, ps, axes, points = [R], [p], [], []
        for j, kind in enumerate(self.joints):
            a = self.axis[j]
            p = p + R @ self.origin[j, :3, 3]
            R = R @ self.origin[j, :3, :3]
            axes.append(R @ a)
            points.append(p)
            if kind == "R":
                c, s = jnp.cos(q[j]), jnp.sin(q[j])
                turn = c * jnp.eye(3, dtype=q.dtype) + s * skew(a) + (1.0 - c) * jnp.outer(a, a)
                R = R @ turn
            else:
                p = p + axes[-1] * q[j]
            Rs.append(R)
            ps.append(p)
        return jnp.stack(Rs), jnp.stack(ps), jnp.stack(axes), jnp.stack(points)

    def frames(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n1 3 3"], Float[Array, "n1 3"]]:
        R, p, _, _ = self._walk(q)
        return R, p

    def joint_axes(self, q: Float[Array, " n"]) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
        _, _, axes, points = self._walk(q)
        return axes, points


@dataclass
class _Joint:
    name: str
    kind: str
    parent: str
    child: str
    T: np.ndarray
    axis: np.ndarray


def _floats(text: str | None, n: int, where: str, default: Sequence[float]) -> np.ndarray:
    if text is None:
        return np.asarray(default, float)
    try:
        v = np.asarray([float(t) for t in text.split()], float)
    except ValueError:
        raise UrdfError(f"URDF {where}: expected {n} numbers, got {text!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UrdfError(f"URDF {where}: expected {n} finite numbers, got {text!r}")
    return v


def _transform(elem: ET.Element | None, where: str) -> np.ndarray:
    """The 4x4 transform of an ``<origin xyz rpy>`` element (identity when absent)."""
    T = np.eye(4)
    if elem is not None:
        T[:3, :3] = rpy_matrix(_floats(elem.get("rpy"), 3, f"{where} origin rpy", (0, 0, 0)))
        T[:3, 3] = _floats(elem.get("xyz"), 3, f"{where} origin xyz", (0, 0, 0))
    return T


def _link_phi(link: ET.Element) -> np.ndarray:
    """A ``<link>``'s standard inertial parameters in its own frame (zero without
    ``<inertial>``)."""
    name = link.get("name")
    inertial = link.find("inertial")
    if inertial is None:
        return np.zeros(10)
    where = f"link {name!r} inertial"
    mass_el = inertial.find("mass")
    mass = _floats(None if mass_el is None else mass_el.get("value"), 1, f"{where} mass",
                   (0.0,))[0]
    if mass < 0:
        raise UrdfError(f"URDF {where}: mass must be >= 0 kg, got {mass}")
    el = inertial.find("inertia")
    keys = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    vals = [0.0] * 6 if el is None else [
        _floats(el.get(k), 1, f"{where} inertia {k}", (0.0,))[0] for k in keys]
    Ic = np.asarray(inertia_matrix(np.asarray(vals)))  # URDF's keys in the entries' order
    if not is_inertia_tensor(Ic):
        raise UrdfError(f"URDF {where}: the inertia tensor is not positive semi-definite")
    T = _transform(inertial.find("origin"), where)
    R = T[:3, :3]
    phi = np.asarray(standard_parameters(np.array([mass]), T[None, :3, 3],
                                         (R @ Ic @ R.T)[None]))[0]
    return phi


def _parse(source: str | os.PathLike) -> ET.Element:
    """The ``<robot>`` element of a URDF given as a path or as the XML text itself."""
    text = os.fspath(source)
    try:
        if text.lstrip().startswith("<"):
            root = ET.fromstring(text)
        else:
            if not os.path.isfile(text):
                raise UrdfError(f"URDF file not found: {text}")
            root = ET.parse(text).getroot()
    except ET.ParseError as e:
        raise UrdfError(f"URDF is not well-formed XML: {e}") from None
    if root.tag != "robot":
        raise UrdfError(f"URDF: the root element must be <robot>, got <{root.tag}>")
    return root


def read_urdf(source: str | os.PathLike, *, gravity: ArrayLike = GRAVITY_DOWN) -> UrdfChain:
    """The serial chain of a URDF (module docstring): its moving joints, root first.

    **Arguments:**

    - ``source``: a URDF file's path, or its XML text.
    - ``gravity`` [m/s^2]: gravity's acceleration in the root link's frame.

    **Returns:** a ``UrdfChain`` whose joints are the URDF's moving joints, root first.

    **Raises:** ``UrdfError`` for a missing file, malformed XML, a missing or repeated name,
    a joint type or element it does not take, moving joints that are not on one path.
    """
    robot = _parse(source)
    links = {}
    for link in robot.findall("link"):
        name = link.get("name")
        if not name:
            raise UrdfError("URDF: a <link> without a name")
        if name in links:
            raise UrdfError(f"URDF: link {name!r} is defined twice")
        links[name] = _link_phi(link)
    joints: dict[str, _Joint] = {}
    for el in robot.findall("joint"):
        name, kind = el.get("name"), el.get("type")
        parent, child = el.find("parent"), el.find("child")
        if not name or parent is None or child is None:
            raise UrdfError(f"URDF: joint {name!r} needs a name, a <parent> and a <child>")
        if kind not in (*MOVING_TYPES, "fixed"):
            raise UrdfError(f"URDF joint {name!r}: type {kind!r} is not a serial chain's "
                            f"(one of {[*MOVING_TYPES, 'fixed']})")
        if el.find("mimic") is not None:
            raise UrdfError(f"URDF joint {name!r}: a mimic joint is not a chain's own joint")
        axis = _floats(el.find("axis").get("xyz") if el.find("axis") is not None else None,
                       3, f"joint {name!r} axis", (1.0, 0.0, 0.0))
        if kind != "fixed":
            norm = float(np.linalg.norm(axis))
            if norm == 0.0:
                raise UrdfError(f"URDF joint {name!r}: the axis is zero")
            axis = axis / norm
        j = _Joint(name, kind, parent.get("link", ""), child.get("link", ""),
                   _transform(el.find("origin"), f"joint {name!r}"), axis)
        for end in (j.parent, j.child):
            if end not in links:
                raise UrdfError(f"URDF joint {name!r}: link {end!r} is not defined")
        joints[name] = j
    return _chain(links, list(joints.values()), gravity)


def _chain(links: dict[str, np.ndarray], joints: list[_Joint], gravity: ArrayLike
           ) -> UrdfChain:
    """The chain of parsed links and joints (``read_urdf``)."""
    children: dict[str, list[_Joint]] = {name: [] for name in links}
    parent_of: dict[str, _Joint] = {}
    for j in joints:
        if j.child in parent_of:
            raise UrdfError(f"URDF: link {j.child!r} is the child of two joints")
        parent_of[j.child] = j
        children[j.parent].append(j)
    roots = [name for name in links if name not in parent_of]
    if len(roots) != 1:
        raise UrdfError(f"URDF: a chain needs one root link (no joint's child), got {roots}")

    def moving_below(link: str) -> list[str]:
        out = []
        for j in children[link]:
            out += ([j.name] if j.kind != "fixed" else []) + moving_below(j.child)
        return out

    # a leaf whose path holds every moving joint (the rest of the tree is welded on)
    moving = set(moving_below(roots[0]))
    ends = [name for name in links if not children[name] and moving <= {
        parent_of[a].name for a in _ancestors(name, parent_of)}]
    if not ends:
        raise UrdfError(f"URDF: the moving joints {sorted(moving)} do not lie on one path "
                        f"from the root {roots[0]!r}: not a serial chain")
    tip = ends[0]
    path = [parent_of[a] for a in reversed(_ancestors(tip, parent_of))]
    on_path = {j.name for j in path}

    def welded(link: str, T: np.ndarray) -> np.ndarray:
        """The inertia of ``link`` and all welded to it off the path (only fixed joints
        leave the path: it holds every moving one), in the frame where ``link``'s frame has
        pose ``T``."""
        phi = moved_phi(links[link], T[:3, :3], T[:3, 3])
        for j in children[link]:
            if j.name in on_path:
                continue
            phi = phi + welded(j.child, T @ j.T)
        return phi

    origins, axes, phis, kinds, names = [], [], [], [], []
    pending = np.eye(4)  # fixed joints since the last moving one
    for j in path:
        if j.kind == "fixed":
            pending = pending @ j.T
            if phis:  # welded to the last moving link: its inertia, in that link's frame
                phis[-1] = phis[-1] + welded(j.child, pending)
            continue
        origins.append(pending @ j.T)
        axes.append(j.axis)
        phis.append(welded(j.child, np.eye(4)))
        kinds.append(MOVING_TYPES[j.kind])
        names.append(j.name)
        pending = np.eye(4)
    if not kinds:
        raise UrdfError(f"URDF: no moving joint between the root {roots[0]!r} and {tip!r}")
    return UrdfChain(origin=np.stack(origins), axis=np.stack(axes), phi=np.stack(phis),
                     g=gravity, joints="".join(kinds), names=tuple(names))


def _ancestors(link: str, parent_of: dict[str, _Joint]) -> list[str]:
    """The links from ``link`` up to (not including) the root, ``link`` first."""
    out = []
    while link in parent_of:
        out.append(link)
        link = parent_of[link].parent
    return out

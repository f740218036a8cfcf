"""The arms a parameter file's ``links`` section can name beside the planar two-link
(``jaxflex.io.params.LINK_TYPES``): the shipped KUKA KR300's kinematic and inertial tables, and
the builders of a chain given by its DH table (``dh_links``) or by a URDF (``urdf_links``).

The KUKA KR300 R2500 ultra (Quantec), axes 1-3 flexible, the wrist held. Source: the
rigid-body model of the arm in the public repository its measured data come from (GitHub
``JonasWeigand/Robot_Identification``, MIT licence, file
``robot_model/model_KUKA_Quantec_Ultra_KR300.m``: standard DH parameters, link masses,
centres of mass, inertia tensors about the centre of mass, rotor inertias and gear ratios,
written for Corke's Robotics Toolbox; the 200 kg payload of ``MASTER_create_symbolic_robot.m``
lumped into link 6); ``jaxflex/data/SOURCE.md``. The angle convention, the base frame and what
G leaves out: ``jaxflex.data.kr300``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from jaxflex.core.chain import GRAVITY_DOWN, LockedJoints, SerialChain, is_inertia_tensor
from jaxflex.core.urdf import UrdfChain, read_urdf

#: Standard DH parameters of axes 1-6: a [m], d [m], alpha [rad].
KR300_A: tuple[float, ...] = (0.350, 1.150, 0.041, 0.0, 0.0, 0.0)
KR300_D: tuple[float, ...] = (-0.675, -0.189, 0.189, -1.0, 0.0, -0.240)
KR300_ALPHA: tuple[float, ...] = (math.pi / 2, 0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, math.pi)
#: Joint offsets [rad] from the recorded angles to the DH angles (module docstring).
KR300_OFFSET: tuple[float, ...] = (0.0, -math.pi / 2, math.pi, 0.0, 0.0, 0.0)
#: Link masses [kg] without payload (link 6: the flange, 17.78 kg at z = -50 mm).
KR300_MASS: tuple[float, ...] = (395.40, 339.12, 105.21, 35.80, 31.46, 17.78)
#: Centres of mass [m] in the link frames (link 6 without payload).
KR300_COM: tuple[tuple[float, float, float], ...] = (
    (-0.353, 0.174, -0.004), (-0.709, -0.001, 0.023), (-0.018, -0.018, -0.076),
    (0.0, 0.236, 0.001), (0.0, -0.080, -0.009), (0.0, 0.0, -0.050),
)
#: Inertia about the centre of mass [kg m^2], entries (Ixx, Iyy, Izz, Ixy, Iyz, Ixz) as the
#: source lists them (tensor entries); link 6 is a point mass there.
KR300_INERTIA: tuple[tuple[float, ...], ...] = tuple(tuple(v * 1e-6 for v in row) for row in (
    (16733765, 29799119, 32814954, -1703664, 129384, 4404062),
    (7507819, 88886691, 88673761, 430046, 173157, -4396607),
    (10783798, 10186135, 1943179, 118474, -606384, -101950),
    (425035, 217993, 428465, -4, -11353, -27),
    (283826, 229562, 258266, -4, -19521, -120),
    (0, 0, 0, 0, 0, 0),
))
#: Gear ratios u and rotor inertias J_m [kg m^2] (motor side) of axes 1-6.
KR300_GEAR: tuple[float, ...] = (1798 / 7, 1872 / 7, 757 / 3, 221.0, 5032 / 21, 206793 / 1340)
KR300_JM: tuple[float, ...] = (0.00923, 0.0118, 0.0118, 0.00173, 0.00173, 0.00173)
#: Payload [kg] of the authors' model and its distance [m] along link 6's z axis.
KR300_PAYLOAD: float = 200.0
KR300_PAYLOAD_Z: float = 0.100
#: Gravity's acceleration [m/s^2] in the DH base frame (z down).
KR300_GRAVITY: tuple[float, float, float] = (0.0, 0.0, 9.81)


def _tensor(e: tuple[float, ...]) -> np.ndarray:
    xx, yy, zz, xy, yz, xz = e
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def kuka_kr300_chain(payload: float = KR300_PAYLOAD) -> SerialChain:
    """The six-axis rigid chain of the KR300 R2500 ultra in the recorded angle convention.

    **Arguments:** ``payload`` [kg] (>= 0), a point mass 0.1 m along link 6's z axis (the
    authors' model; 200 kg there).

    **Returns:** a ``SerialChain`` (standard DH, base z down, gravity (0, 0, 9.81) m/s^2).
    """
    if not payload >= 0:
        raise ValueError(f"kuka_kr300_chain: payload must be >= 0 kg, got {payload}")
    mass = np.array(KR300_MASS)
    com = np.array(KR300_COM)
    m6 = mass[5] + payload
    com[5, 2] = (mass[5] * com[5, 2] + payload * KR300_PAYLOAD_Z) / m6
    mass[5] = m6
    inertia = np.stack([_tensor(e) for e in KR300_INERTIA])
    return SerialChain.from_dh(a=KR300_A, d=KR300_D, alpha=KR300_ALPHA, mass=mass, com=com,
                               inertia=inertia, gravity=KR300_GRAVITY, offset=KR300_OFFSET)


def kuka_kr300_arm(q_wrist: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   payload: float = KR300_PAYLOAD) -> LockedJoints:
    """Axes 1-3 of the KR300 with the wrist (axes 4-6) held at ``q_wrist`` [rad] (recorded
    convention): the link dynamics of the three flexible joints."""
    q_held = np.concatenate([np.zeros(3), np.asarray(q_wrist, float)])
    return LockedJoints(chain=kuka_kr300_chain(payload), q_held=q_held, free=(0, 1, 2))


def kuka_kr300_links(payload: float, q4: float, q5: float, q6: float) -> LockedJoints:
    """The links a parameter file names ``{"type": "kuka_kr300", "payload": ..., "q4": ...,
    "q5": ..., "q6": ...}`` (``jaxflex.io.params.LINK_TYPES``): ``kuka_kr300_arm`` with the
    payload [kg] and the wrist held at q4, q5, q6 [rad] (recorded convention)."""
    return kuka_kr300_arm((q4, q5, q6), payload)


def dh_links(a: list[float], d: list[float], alpha: list[float], mass: list[float],
             com: list[list[float]], inertia: list[list[list[float]]],
             offset: list[float] | None = None, joints: str | None = None,
             gravity: Sequence[float] = GRAVITY_DOWN) -> SerialChain:
    """The links a parameter file names ``{"type": "dh", ...}``: a chain of any length from
    its standard DH table (``SerialChain.from_dh``): ``a``, ``d`` [m], ``alpha`` [rad],
    ``offset`` [rad or m] (default 0) per joint, ``joints`` ("R"/"P" per joint, default all
    revolute), each link's ``mass`` [kg], ``com`` [m] (n x 3, in its DH frame) and
    ``inertia`` [kg m^2] (n x 3 x 3, about its centre of mass), and ``gravity`` [m/s^2] in
    the base frame (default (0, 0, -9.81)).

    **Raises:** ``ValueError`` for lengths or shapes that disagree, a non-positive mass or an
    inertia that is not positive semi-definite."""
    m = np.asarray(mass, float)
    Ic = np.asarray(inertia, float)
    if m.ndim != 1 or np.any(m <= 0):
        raise ValueError(f"dh links: mass must be a list of positive masses [kg], got {mass}")
    if Ic.shape != (m.size, 3, 3) or not is_inertia_tensor(Ic):
        raise ValueError("dh links: inertia must be one symmetric positive semi-definite "
                         f"3 x 3 tensor [kg m^2] per link, got shape {Ic.shape}")
    return SerialChain.from_dh(a=a, d=d, alpha=alpha, mass=m, com=com, inertia=Ic,
                               gravity=gravity, joints=joints, offset=offset)


def urdf_links(path: str, gravity: Sequence[float] = GRAVITY_DOWN) -> UrdfChain:
    """The links a parameter file names ``{"type": "urdf", "path": ..., "gravity": ...}``:
    the chain of the URDF at ``path`` (``jaxflex.core.urdf.read_urdf``; a relative path is
    taken from the parameter file's folder), gravity [m/s^2] in its root link's frame
    (default (0, 0, -9.81))."""
    return read_urdf(path, gravity=gravity)

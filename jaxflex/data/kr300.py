"""The KUKA KR300 R2500 ultra (Quantec) as a shipped model: kinematics and nominal inertias of
its six links, axes 1-3 as flexible joints, the measured wrist motion.

Source: the rigid-body model of the arm in the public repository the measured data come from
(GitHub ``JonasWeigand/Robot_Identification``, MIT licence, file
``robot_model/model_KUKA_Quantec_Ultra_KR300.m``: standard DH parameters, link masses,
centres of mass, inertia tensors about the centre of mass, rotor inertias and gear ratios,
written for Corke's Robotics Toolbox; the 200 kg payload of ``MASTER_create_symbolic_robot.m``
lumped into link 6). See ``SOURCE.md`` beside this file. ``tests/test_kr300.py`` checks
M(q) and G(q) against values of the authors' generated model.

Angle convention: the recorded angles (``load_kuka``'s q1, q2; ``load_kuka_wrist``). The
authors' dynamics adds (0, -pi/2, pi/2, 0, 0, 0) to them and their axis 3 has a DH offset of
pi/2, so the chain's offsets are (0, -pi/2, pi, 0, 0, 0). The DH base frame has its z axis
pointing *down* (the authors' base transform is a rotation of pi about x), so gravity is
(0, 0, +9.81) m/s^2 in it and axis 1 is vertical: G_1 = 0.

Not in G: the hydraulic weight counterbalance of axis 2 (a gas spring; the authors model it
separately, ``hydraulic_counterbalance``), friction, and the rotor inertias (the rotor side of
eq. 3: ``kuka_kr300_plant``'s J).
"""

from __future__ import annotations

import math
from pathlib import Path
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np

from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.data import DATA_DIR, KUKA_TRAJECTORIES, check_choice
from jaxflex.io.arms import (  # noqa: F401 - the arm's tables, here with its data
    KR300_A,
    KR300_ALPHA,
    KR300_COM,
    KR300_D,
    KR300_GEAR,
    KR300_GRAVITY,
    KR300_INERTIA,
    KR300_JM,
    KR300_MASS,
    KR300_OFFSET,
    KR300_PAYLOAD,
    KR300_PAYLOAD_Z,
    kuka_kr300_arm,
    kuka_kr300_chain,
    kuka_kr300_links,
)

#: The wrist (axes 4-6), recorded without link-side encoders.
WRIST_AXES: tuple[int, ...] = (4, 5, 6)


def kuka_kr300_plant(q_wrist: tuple[float, float, float] = (0.0, 0.0, 0.0),
                     payload: float = KR300_PAYLOAD, friction=None) -> FlexibleJointPlant:
    """Axes 1-3 as a flexible-joint arm (eq. 3): ``kuka_kr300_arm`` links, rotor inertias
    J = u^2 J_m [kg m^2] referred to the link, and the nominal joint stiffnesses K [N m/rad]
    of the recording's feed-forward (``c_rad_ff``, SOURCE.md); ``friction``: a ``LuGre`` for
    the three axes or None."""
    J = np.array(KR300_GEAR[:3]) ** 2 * np.array(KR300_JM[:3])
    K = np.load(DATA_DIR / "kuka_kr300_traj_A.npz")["c_rad_ff"].astype(float)
    return FlexibleJointPlant(links=kuka_kr300_arm(q_wrist, payload), J=J, K=K,
                              friction=friction)


#: Sliding friction per axis 1-3, link-referred: the motor friction level Fm [N m] and viscous
#: coefficient bm [N m s/rad] that ``jaxflex.identify.torque.identify_rotor`` fits on
#: trajectory A of each axis (``studies/kuka_control.py``, ``sliding_friction``; standard
#: errors 56, 177, 86 N m and 216, 747, 381 N m s/rad), to five digits.
KR300_FM: tuple[float, float, float] = (413.75, 504.07, 459.20)
KR300_BM: tuple[float, float, float] = (1752.4, 1517.8, 226.48)
#: The LuGre quantities the recordings do not determine (assumed): Fs / Fc, the Stribeck
#: speed vs [rad/s], the presliding range Fc / sigma0 [rad] and the bristles' damping ratio
#: against the link inertia M_ii at the pose.
KR300_FS_OVER_FC: float = 1.2
KR300_VS: float = 0.01
KR300_PRESLIDING: float = 1e-4
KR300_BRISTLE_DAMPING: float = 0.05
#: The cascade's gain rule on the arm, one for every joint: L1, L2 [1/s]; KD1 = KD2 = K / L2
#: so that L2^2 KD1 KD2 = K^2 dominates the K^2 / 4 coupling of N2's e1-e2 block (eq. 31);
#: Ke = KE_SIGMA0 / sigma0; kv [s/rad].
KR300_L1: float = 10.0
KR300_L2: float = 30.0
KR300_KE_SIGMA0: float = 0.1
KR300_KV: float = 200.0
#: The arm's controller section: the paper's rest-to-rest task (every axis the same move),
#: a torque limit twice the recordings' largest link-referred torque (5.1e3 N m, axis 2 of
#: trajectory B), exact angles and dirty-derivative velocities.
KR300_CONTROLLER: Mapping[str, Any] = MappingProxyType({
    "trajectory": "polynomial", "tau_max": 1e4, "sensing": {"velocity": "filtered"}})


def kuka_kr300_params(pose: tuple[float, float, float] = (0.0, -0.1, -0.4),
                      payload: float = KR300_PAYLOAD,
                      controller: Mapping[str, Any] | None = KR300_CONTROLLER) -> dict[str, Any]:
    """Axes 1-3 of the KR300 as one coupled flexible-joint arm under the cascade controller,
    as a parameter file (docs/spec.md section 7).

    **Arguments:**

    - ``pose`` [rad]: the link angles of axes 1-3 at which the bristles' damping is set
      (sigma1 = 2 zeta sqrt(sigma0 M_ii), eq. 4-6; the wrist held at zero).
    - ``payload`` [kg]: at the flange (``kuka_kr300_chain``).
    - ``controller``: the ``controller`` section (``jaxflex.io.params.ControllerConfig``
      entries; default ``KR300_CONTROLLER``); None: none (the defaults of
      ``jaxflex.io.presets.DEFAULT_CONTROLLER``, the paper's rig).

    **Returns:**

    The mapping: ``plant`` (J, K of ``kuka_kr300_plant``), ``links`` (type ``kuka_kr300``),
    ``friction`` (LuGre per axis: Fc = ``KR300_FM``, sigma2 = ``KR300_BM`` and the assumed
    rest), ``gains`` (the ``KR300_L1`` ... rule), and ``controller`` where given.
    """
    import jax

    plant = kuka_kr300_plant(payload=payload)
    with jax.enable_x64(True):
        M = np.diag(np.asarray(plant.links.mass_matrix(np.asarray(pose, float))))
    K = np.asarray(plant.K, float)
    Fc = np.asarray(KR300_FM)
    sigma0 = Fc / KR300_PRESLIDING
    p = {
        "plant": {"J": np.asarray(plant.J, float).tolist(), "K": K.tolist()},
        "links": {"type": "kuka_kr300", "payload": float(payload), "q4": 0.0, "q5": 0.0,
                  "q6": 0.0},
        "friction": {"Fc": Fc.tolist(), "Fs": (KR300_FS_OVER_FC * Fc).tolist(),
                     "vs": [KR300_VS] * 3, "sigma0": sigma0.tolist(),
                     "sigma1": (2 * KR300_BRISTLE_DAMPING * np.sqrt(sigma0 * M)).tolist(),
                     "sigma2": list(KR300_BM)},
        "gains": {"Ke": (KR300_KE_SIGMA0 / sigma0).tolist(), "KD1": (K / KR300_L2).tolist(),
                  "KD2": (K / KR300_L2).tolist(), "kv": [KR300_KV] * 3,
                  "L1": [KR300_L1] * 3, "L2": [KR300_L2] * 3},
    }
    if controller is not None:
        p["controller"] = {k: (dict(v) if isinstance(v, dict) else v)
                           for k, v in controller.items()}
    return p


def hydraulic_counterbalance(q2: np.ndarray) -> np.ndarray:
    """Torque [N m] of the gas-spring weight counterbalance on axis 2 at the recorded angle
    ``q2`` [rad], to add to G_2 (the authors' model of a bladder accumulator: isothermal real
    gas, 0.159 kg of nitrogen at 328 K, anchor points 0.8 m and 0.2 m from axis 2)."""
    D, k = 0.8, 0.2
    area = math.pi * (0.055**2 - 0.030**2) / 4
    delta = np.asarray(q2) - math.pi / 2 + math.radians(95.0)
    dl = np.sqrt(D**2 + k**2 - 2 * D * k * np.cos(delta)) - (D - k)
    lever = np.sin(delta) * D * k / (dl + D - k)
    pressure = 1.01 * 296.8 * 328.0 * 2 * 0.0795 / (2 * 0.00048 - dl * area)
    return lever * pressure * area


def _wrist_file(trajectory: str) -> Path:
    return DATA_DIR / f"kuka_kr300_wrist_{trajectory}.npz"


def load_kuka_wrist(trajectory: str) -> dict[str, np.ndarray]:
    """The measured wrist motion of a KUKA trajectory: t [s] (L,); q [rad] (L, 3) motor
    angles of axes 4-6 referred to the link (no link encoders there); tau [N m] (L, 3)
    motor torques referred to the link (u tau_m); q_ref [rad] (L, 3) references."""
    check_choice("trajectory", trajectory, KUKA_TRAJECTORIES)
    z = np.load(_wrist_file(trajectory))
    t = np.load(DATA_DIR / f"kuka_kr300_traj_{trajectory}.npz")["time_cont"]
    return {"t": t, "q": np.deg2rad(z["act_pos_mot_deg"]).T,
            "tau": (z["u"][:, None] * z["act_torque_abs_nm"]).T,
            "q_ref": np.deg2rad(z["ref_pos_deg"]).T}


def reduce_kuka_wrist(src_dir: str | Path, out_dir: str | Path = DATA_DIR) -> list[Path]:
    """Write ``kuka_kr300_wrist_{A,B,C}.npz`` from the original ``.mat`` files in ``src_dir``
    (``jaxflex.data.KUKA_SOURCE_FILES`` names, or the repository's ``data.mat`` per folder):
    rows 3-5 (axes 4-6) of ``act_pos_mot_deg``, ``act_torque_abs_nm``, ``ref_pos_deg`` and
    entries 3-5 of ``para.u``, ``para.J_mr``, bit-identical, with the source's sha256."""
    import hashlib

    import scipy.io

    from jaxflex.data import KUKA_SOURCE_FILES

    out = []
    for traj, name in KUKA_SOURCE_FILES.items():
        src = Path(src_dir) / name
        raw = src.read_bytes()
        mat = scipy.io.loadmat(src, squeeze_me=True, struct_as_record=False)
        rec, para = mat["rec"], mat["para"]
        path = Path(out_dir) / f"kuka_kr300_wrist_{traj}.npz"
        np.savez_compressed(
            path, act_pos_mot_deg=rec.act_pos_mot_deg[3:6], act_torque_abs_nm=
            rec.act_torque_abs_nm[3:6], ref_pos_deg=rec.ref_pos_deg[3:6],
            u=np.asarray(para.u)[3:6], J_mr=np.asarray(para.J_mr)[3:6],
            source_sha256=hashlib.sha256(raw).hexdigest())
        out.append(path)
    return out

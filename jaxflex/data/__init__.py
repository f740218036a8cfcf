"""Measured data shipped with jaxflex: the EMPS benchmark and the KUKA KR300 flexible joints.

Two real data sets, installed with the package (see ``SOURCE.md`` beside this file for their
origin, citation and licence):

- **EMPS** (``load_emps``): the Electro-Mechanical Positioning System benchmark (Janot, Gautier,
  Brunot 2019), a rigid prismatic axis (ball screw) in closed loop, 1 kHz, 24.84 s. Shipped
  byte-identical to the benchmark's ``DATA_EMPS.mat`` (estimation) and
  ``DATA_EMPS_PULSES.mat`` (validation, with force pulses).
- **KUKA KR300 R2500 ultra** (``load_kuka``): axes 1-3 of an industrial robot with a motor-side
  and a link-side (secondary) encoder, 4 ms samples, 10 s per trajectory; trajectory A for
  identification, B and C for validation (Weigand et al., MIT licence). Shipped reduced to the
  variables a flexible-joint identification uses (``reduce_kuka`` made the files; every kept
  value is bit-identical to the original).

Loaders return a ``jaxflex.io.logs.Log`` (docs/spec.md section 6: SI units, link-referred);
``emps_record`` and ``kuka_record`` give the data sets' other variables (gains, references,
pulses, gear ratios). Host-only numpy/scipy code; nothing here imports JAX. The KR300's
rigid-body model (kinematics, nominal inertias, the flexible axes 1-3 as a plant, the measured
wrist motion) is ``jaxflex.data.kr300``, which does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.io.logs import Log

DATA_DIR: Path = Path(__file__).resolve().parent

EMPS_NAMES: tuple[str, ...] = ("DATA_EMPS", "DATA_EMPS_PULSES")
KUKA_TRAJECTORIES: tuple[str, ...] = ("A", "B", "C")
KUKA_AXES: tuple[int, ...] = (1, 2, 3)

# Original file names in the source data folder (SOURCE.md of the KUKA set).
KUKA_SOURCE_FILES: dict[str, str] = {
    "A": "traj_A_ident_2020-10-21.mat",
    "B": "traj_B_valid_2020-10-21.mat",
    "C": "traj_C_valid_2020-10-21.mat",
}
# Signals kept by reduce_kuka: ``rec.<name>`` rows 0..2 (axes 1-3), (3, N) float64 as stored.
KUKA_SIGNALS: tuple[str, ...] = (
    "act_pos_se_deg", "act_pos_mot_deg", "act_torque_abs_nm", "ref_pos_deg",
)
# Per-axis constants kept from the file's ``para`` struct, entries 0..2 (axes 1-3), dtype as stored.
KUKA_PARA: tuple[str, ...] = ("u", "k_T", "J_mr", "c_rad_ff", "q_back")


def _kuka_file(trajectory: str) -> Path:
    return DATA_DIR / f"kuka_kr300_traj_{trajectory}.npz"


def check_choice(what: str, value: Any, choices: Sequence[Any]) -> None:
    """Raise ``ValueError`` naming ``what`` and the valid ``choices`` when ``value`` is not
    one of them."""
    if value not in choices:
        raise ValueError(f"unknown {what} {value!r}; choices: {list(choices)}")


def available() -> dict[str, dict[str, Any]]:
    """The shipped data sets: for each, its loader, the valid arguments, sample period, units
    and files (paths inside the installed package)."""
    return {
        "emps": {
            "loader": "load_emps(name)",
            "names": EMPS_NAMES,
            "roles": {"DATA_EMPS": "estimation", "DATA_EMPS_PULSES": "validation (force pulses)"},
            "dt": 1e-3,
            "joints": 1,
            "units": "prismatic: q1, q2, q1d in m; tau in N (= gtau * vir)",
            "files": [str(DATA_DIR / f"{n}.mat") for n in EMPS_NAMES],
            "citation": "A. Janot, M. Gautier, M. Brunot, 'Data Set and Reference Models of "
                        "EMPS', Nonlinear System Identification Benchmarks workshop, 2019",
        },
        "kuka_kr300": {
            "loader": "load_kuka(trajectory, axis)",
            "trajectories": KUKA_TRAJECTORIES,
            "roles": {"A": "identification", "B": "validation", "C": "validation"},
            "axes": KUKA_AXES,
            "dt": 4e-3,
            "joints": "1 per axis (or several with axis=(1, 2, 3))",
            "units": "q1 link encoder, q2 motor encoder / gear ratio, q1d reference, in rad; "
                     "tau = gear ratio * motor torque in N m (link side)",
            "files": [str(_kuka_file(k)) for k in KUKA_TRAJECTORIES],
            "citation": "J. Weigand, J. Ulmen, A. Janot, M. Ruskowski, GitHub "
                        "JonasWeigand/Robot_Identification (MIT licence), recordings of "
                        "2020-10-21",
        },
    }


# --------------------------------------------------------------------------------------- EMPS


@dataclasses.dataclass(frozen=True)
class EmpsRecord:
    """The EMPS benchmark variables of one file, as stored (column vectors flattened to (N,)).

    t [s]; qm [m] measured position (motor encoder expressed on the load side); qg [m] position
    reference; vir [V] drive input voltage (the controller output); gtau [N/V] drive gain, so
    that the motor force is ``gtau * vir`` [N]; kp [1/s] and kv [V/(m/s)] the P position /
    P velocity cascade gains (``vir = kp kv (qg - qm) - kv qm'``, saturated at 10 V);
    pulses: the ``pulses_N`` signal of DATA_EMPS_PULSES (values 0 or 5, stored as uint8; the
    benchmark documentation says newtons, but the force in the data jumps by about 5 V * gtau at
    each pulse edge, i.e. the pulses act on vir in volts), None for DATA_EMPS.
    """

    name: str
    t: np.ndarray
    qm: np.ndarray
    qg: np.ndarray
    vir: np.ndarray
    gtau: float
    kp: float
    kv: float
    pulses: np.ndarray | None

    @property
    def dt(self) -> float:
        """Sample period [s] (1 ms)."""
        return float((self.t[-1] - self.t[0]) / (self.t.shape[0] - 1))

    @property
    def force(self) -> np.ndarray:
        """Motor force gtau * vir [N], as the benchmark defines it."""
        return self.gtau * self.vir


def emps_record(name: str = "DATA_EMPS") -> EmpsRecord:
    """All variables of an EMPS file (``"DATA_EMPS"`` or ``"DATA_EMPS_PULSES"``).

    Raises ``ValueError`` naming the choices for an unknown name.
    """
    import scipy.io

    check_choice("EMPS data set", name, EMPS_NAMES)
    d = scipy.io.loadmat(DATA_DIR / f"{name}.mat")
    col = {k: np.asarray(d[k], dtype=float).reshape(-1) for k in ("t", "qm", "qg", "vir")}
    pulses = d.get("pulses_N")
    return EmpsRecord(
        name=name, **col,
        gtau=float(np.asarray(d["gtau"]).item()), kp=float(np.asarray(d["kp"]).item()),
        kv=float(np.asarray(d["kv"]).item()),
        pulses=None if pulses is None else np.asarray(pulses, dtype=float).reshape(-1),
    )


def load_emps(name: str = "DATA_EMPS") -> Log:
    """An EMPS benchmark file as a one-joint ``Log`` (24841 samples at 1 kHz).

    EMPS is a **prismatic**, rigid axis with a single encoder, so the log's "angles" are
    positions in metres and its torque is a force in newtons (docs/spec.md section 6 otherwise
    speaks of rad and N m): ``t`` [s]; ``q1 = q2 = qm`` [m] (rigid: link and rotor coincide);
    ``tau = gtau * vir`` [N], the benchmark's definition of the motor force; ``q1d = qg`` [m],
    the position reference. The data come from closed loop (the P/P cascade in
    ``emps_record``), so simulate them with that controller, not open loop.

    ``name``: ``"DATA_EMPS"`` (estimation set) or ``"DATA_EMPS_PULSES"`` (validation set).
    Raises ``ValueError`` naming the choices for an unknown name.
    """
    r = emps_record(name)
    return Log.from_arrays(t=r.t, tau=r.force, q1=r.qm, q2=r.qm, q1d=r.qg,
                           source=f"jaxflex.data:{name}")


@dataclasses.dataclass(frozen=True)
class EmpsRigidModel:
    """A rigid model of the EMPS axis in the benchmark's form (SI, load side):

        force = M q'' + Fv q' + Fc sign(q') + offset        [N]

    M [kg] moving mass; Fv [N s/m] viscous friction; Fc [N] Coulomb friction; offset [N]
    force offset in the benchmark's sign (jaxflex's ``torque_offset`` effect, which adds to
    the applied force, holds -offset).
    """

    M: float
    Fv: float
    Fc: float
    offset: float

    def params_dict(self, *, Fs: float | None = None, vs: float = 0.01, sigma0: float = 1e6,
                    sigma1: float = 0.0, J: float = 1e-3, K: float = 1e6,
                    offset: bool = True) -> dict[str, Any]:
        """The model as the sections of a rigid jaxflex parameter file (docs/spec.md
        section 7), for ``Params.from_dict``: the rigid identification's M = I + J split as
        I = M - J, LuGre friction with Fc and sigma2 = Fv.

        **Arguments:**

        - ``Fs``: static friction [N] (None: Fc, no Stribeck hump).
        - ``vs``: Stribeck velocity [m/s].
        - ``sigma0``, ``sigma1``: bristle stiffness [N/m] and damping [N s/m].
        - ``J``: the rotor's share of M [kg]; ``K``: the spring joining the two [N/m].
        - ``offset``: whether the ``torque_offset`` effect (-offset [N]) is included.

        **Returns:**

        ``{"plant", "friction"}`` and, with ``offset``, ``"effects"``.
        """
        d: dict[str, Any] = {
            "plant": {"I": self.M - J, "J": J, "K": K},
            "friction": {"Fc": self.Fc, "Fs": self.Fc if Fs is None else Fs, "vs": vs,
                         "sigma0": sigma0, "sigma1": sigma1, "sigma2": self.Fv},
        }
        if offset:
            d["effects"] = {"torque_offset": {"offset": [-self.offset]}}
        return d


EMPS_IDIM_LS: EmpsRigidModel = EmpsRigidModel(M=95.1089, Fv=203.5034, Fc=20.3935,
                                              offset=-3.1648)
"""The EMPS benchmark's published reference model, identified on DATA_EMPS by the inverse
dynamic model and ordinary least squares (IDIM-LS): A. Janot, M. Gautier, M. Brunot, "Data
Set and Reference Models of EMPS", 2019 Workshop on Nonlinear System Identification
Benchmarks, Eindhoven (SOURCE.md beside this file)."""


# --------------------------------------------------------------------------------------- KUKA


@dataclasses.dataclass(frozen=True)
class KukaRecord:
    """The kept variables of one KUKA KR300 recording (axes 1-3), as in the original file.

    time_cont [s] (N,): ``rec.time_cont``, 0 ... 10 s at 4 ms (stored values carry float32
    rounding, e.g. 0.0039999999 s). Signals (3, N), row i = axis i+1, float64, all from ``rec``:
    act_pos_se_deg [deg] link-side (secondary) encoder; act_pos_mot_deg [deg] motor encoder
    already divided by the gear ratio (link-referred); act_torque_abs_nm [N m] measured motor
    torque, motor side; ref_pos_deg [deg] executed position reference. Constants (3,), from
    ``para`` (nominal values at recording time): u gear ratio [-]; k_T torque constant [N m/A];
    J_mr motor inertia [kg m^2]; c_rad_ff joint stiffness [N m/rad, link side, nominal];
    q_back backlash [rad]. traj_name: the authors' trajectory name; source_sha256: digest of
    the original ``.mat``.
    """

    trajectory: str
    time_cont: np.ndarray
    act_pos_se_deg: np.ndarray
    act_pos_mot_deg: np.ndarray
    act_torque_abs_nm: np.ndarray
    ref_pos_deg: np.ndarray
    u: np.ndarray
    k_T: np.ndarray
    J_mr: np.ndarray
    c_rad_ff: np.ndarray
    q_back: np.ndarray
    traj_name: str
    source_sha256: str

    @property
    def dt(self) -> float:
        """Sample period [s] (4 ms)."""
        t = self.time_cont
        return float((t[-1] - t[0]) / (t.shape[0] - 1))


def kuka_record(trajectory: str = "A") -> KukaRecord:
    """The shipped variables of a KUKA recording (``"A"`` identification, ``"B"``, ``"C"``
    validation). Raises ``ValueError`` naming the choices for an unknown trajectory."""
    check_choice("KUKA trajectory", trajectory, KUKA_TRAJECTORIES)
    with np.load(_kuka_file(trajectory), allow_pickle=False) as z:
        kw = {k: z[k] for k in z.files}
    kw["traj_name"] = str(kw["traj_name"])
    kw["source_sha256"] = str(kw["source_sha256"])
    return KukaRecord(trajectory=trajectory, **kw)


def load_kuka(trajectory: str = "A", axis: int | Sequence[int] = 1) -> Log:
    """One or several axes of a KUKA KR300 recording as a ``Log`` (2501 samples at 4 ms).

    Columns (docs/spec.md section 6, link-referred, radians), for axis i (1, 2 or 3):

    - ``t`` [s] = ``rec.time_cont``;
    - ``q1`` [rad] = deg2rad(``rec.act_pos_se_deg[i-1]``), the link-side secondary encoder;
    - ``q2`` [rad] = deg2rad(``rec.act_pos_mot_deg[i-1]``), the motor encoder, which the
      recording already stores divided by the gear ratio (link-referred), so no gear factor
      or sign is applied;
    - ``tau`` [N m] = ``para.u[i-1] * rec.act_torque_abs_nm[i-1]``, the measured motor torque
      times the gear ratio u = [1798/7, 1872/7, 757/3] (about 257, 267, 252), i.e. the motor
      torque referred to the link side with a lossless gear (no efficiency factor is known);
    - ``q1d`` [rad] = deg2rad(``rec.ref_pos_deg[i-1]``), the executed reference.

    Signs: none changed. In this convention the deflection q2 - q1 correlates positively with
    tau, and a rigid fit tau ~ Jt q2'' + Fv q2' + Fc sign(q2') + c gives positive Jt, Fv, Fc
    on every axis. Gravity (axes 2 and 3, with a hydraulic counterbalance on axis 2) and the
    coupling between axes are not removed: they are in tau. The two encoders are not
    synchronised perfectly (about 3 ms of skew, an offset that changes between recordings).

    ``axis``: 1, 2 or 3, or a sequence of them for an n-joint log (columns (N, n) in the given
    order). Raises ``ValueError`` naming the choices for an unknown trajectory or axis.
    """
    check_choice("KUKA trajectory", trajectory, KUKA_TRAJECTORIES)
    axes = [axis] if isinstance(axis, (int, np.integer)) else list(axis)
    if not axes:
        raise ValueError(f"no KUKA axis given; choices: {list(KUKA_AXES)}")
    for a in axes:
        check_choice("KUKA axis", a, KUKA_AXES)
    r = kuka_record(trajectory)
    rows = [int(a) - 1 for a in axes]

    def col(x: np.ndarray, scale: np.ndarray | float = 1.0) -> np.ndarray:
        out = (x[rows] * np.reshape(scale, (-1, 1))).T  # (axis, time) -> (N, n)
        return out[:, 0] if isinstance(axis, (int, np.integer)) else out

    return Log.from_arrays(
        t=r.time_cont,
        q1=col(np.deg2rad(r.act_pos_se_deg)),
        q2=col(np.deg2rad(r.act_pos_mot_deg)),
        tau=col(r.act_torque_abs_nm, np.asarray(r.u, dtype=float)[rows]),
        q1d=col(np.deg2rad(r.ref_pos_deg)),
        source=f"jaxflex.data:kuka_kr300 trajectory {trajectory} axis {axis}",
    )


def reduce_kuka(src_dir: str | os.PathLike, out_dir: str | os.PathLike) -> dict[str, Path]:
    """Make the shipped KUKA files from the original recordings (re-runnable).

    Reads ``traj_{A,B,C}_*_2020-10-21.mat`` from ``src_dir`` (the files of
    JonasWeigand/Robot_Identification, renamed as in SOURCE.md) and writes
    ``kuka_kr300_traj_{A,B,C}.npz`` (``np.savez_compressed``) into ``out_dir``, keeping, with
    every value bit-identical and in its original dtype: ``rec.time_cont``; rows 0-2 (axes
    1-3, the axes with a link-side encoder) of ``rec.act_pos_se_deg``, ``rec.act_pos_mot_deg``,
    ``rec.act_torque_abs_nm``, ``rec.ref_pos_deg``; entries 0-2 of ``para.u``, ``para.k_T``,
    ``para.J_mr``, ``para.c_rad_ff``, ``para.q_back``; ``traj_name``; and the sha256 of the
    source file. All 2501 samples are kept. Returns {trajectory: written path}.
    """
    import scipy.io

    src_dir, out_dir = Path(src_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    for traj, fname in KUKA_SOURCE_FILES.items():
        src = src_dir / fname
        if not src.exists():
            raise FileNotFoundError(f"KUKA recording not found: {src}")
        d = scipy.io.loadmat(src, squeeze_me=True, struct_as_record=False)
        rec, para = d["rec"], d["para"]
        arrays: dict[str, np.ndarray] = {"time_cont": np.asarray(rec.time_cont)}
        for k in KUKA_SIGNALS:
            arrays[k] = np.ascontiguousarray(np.asarray(getattr(rec, k))[:3])
        for k in KUKA_PARA:
            arrays[k] = np.asarray(getattr(para, k))[:3]
        arrays["traj_name"] = np.asarray(str(d["traj_name"]))
        arrays["source_sha256"] = np.asarray(hashlib.sha256(src.read_bytes()).hexdigest())
        out = out_dir / _kuka_file(traj).name
        np.savez_compressed(out, **arrays)
        written[traj] = out
    return written


__all__ = [
    "DATA_DIR", "EMPS_IDIM_LS", "EMPS_NAMES", "KUKA_AXES", "KUKA_TRAJECTORIES", "EmpsRecord",
    "EmpsRigidModel", "KukaRecord",
    "available", "emps_record", "kuka_record", "load_emps", "load_kuka", "reduce_kuka",
]


#: The prefix that names a shipped data set on the command line (``jaxflex:emps/DATA_EMPS``).
NAMED_PREFIX: str = "jaxflex:"


@dataclasses.dataclass(frozen=True)
class NamedData:
    """A shipped data set named on the command line.

    Attributes:
        log: the log (docs/spec.md section 6).
        loop_controller: the controller that ran while it was recorded, as a parameter
            file's ``loop_controller`` section (EMPS: its P/P cascade), or None.
        name: the name as given.
        axis: what gravity can do on each joint, as a parameter file declares it
            (``jaxflex.discover.config.AXES``: EMPS's prismatic axis; the KUKA axes from the
            arm's kinematics, ``jaxflex.core.chain.SerialChain.axis_kinds``), or None.
        link_side: what a single-joint model can describe of each joint's link side, as a
            parameter file declares it (``jaxflex.identify.start.LINK_SIDES``): EMPS's
            "single" (one prismatic axis); every KUKA axis "coupled" (one axis of a six-axis
            arm: the other axes, gravity and axis 2's hydraulic counterbalance act on its
            link), or None.
    """

    log: Log
    loop_controller: dict[str, Any] | None
    name: str
    axis: list[str] | None = None
    link_side: list[str] | None = None


def _kuka_axis_kinds(trajectory: str, axes: Sequence[int]) -> list[str]:
    """What gravity can do on the KUKA ``axes`` (1-3) at the first sample of ``trajectory``,
    from the arm's kinematics (``jaxflex.data.kr300``)."""
    from jaxflex.data.kr300 import kuka_kr300_chain

    q = np.zeros(6)
    q[:3] = np.asarray(load_kuka(trajectory, KUKA_AXES).q1, float)[0]
    kinds = kuka_kr300_chain().axis_kinds(q)
    return [kinds[a - 1] for a in axes]


def is_named(spec: str) -> bool:
    """Whether ``spec`` names a shipped data set (``jaxflex:...``) rather than a file."""
    return str(spec).startswith(NAMED_PREFIX)


def load_named(spec: str) -> NamedData:
    """A shipped data set by name: ``jaxflex:emps/DATA_EMPS``,
    ``jaxflex:emps/DATA_EMPS_PULSES``, ``jaxflex:kuka/A`` (axes 1-3 of trajectory A, also B,
    C) or ``jaxflex:kuka/A/2`` (one axis).

    Arguments:
        spec: the name.

    Returns:
        A ``NamedData`` (the log and, for EMPS, its declared loop controller).

    Raises:
        ValueError: an unknown set, file, trajectory or axis, listing the valid names.
    """
    known = ([f"{NAMED_PREFIX}emps/{n}" for n in EMPS_NAMES]
             + [f"{NAMED_PREFIX}kuka/{t}[/<axis 1-3>]" for t in KUKA_TRAJECTORIES])
    if not is_named(spec):
        raise ValueError(f"not a shipped data set name: {spec!r}; known: {known}")
    parts = spec[len(NAMED_PREFIX):].strip("/").split("/")
    try:
        if parts[0] == "emps" and len(parts) == 2 and parts[1] in EMPS_NAMES:
            rec = emps_record(parts[1])
            loop = {"type": "pp_cascade", "kp": float(rec.kp), "kv": float(rec.kv),
                    "gtau": float(rec.gtau), "vmax": 10.0}
            return NamedData(log=load_emps(parts[1]), loop_controller=loop, name=spec,
                             axis=["prismatic"], link_side=["single"])
        if parts[0] == "kuka" and len(parts) in (2, 3) and parts[1] in KUKA_TRAJECTORIES:
            axis = KUKA_AXES if len(parts) == 2 else int(parts[2])
            axes = [axis] if isinstance(axis, int) else list(axis)
            return NamedData(log=load_kuka(parts[1], axis), loop_controller=None, name=spec,
                             axis=_kuka_axis_kinds(parts[1], axes),
                             link_side=["coupled"] * len(axes))
    except ValueError:
        pass
    raise ValueError(f"unknown shipped data set {spec!r}; known: {known}")

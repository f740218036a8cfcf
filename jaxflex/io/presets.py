"""The paper's tables and every named preset, in one place.

- The paper's link-1 values: Table 1 (plant), Table 2 with the correction in docs/spec.md (Appendix B) (LuGre),
  Table 3 (gains), and the modules and ``Params`` built from them (``paper_plant``,
  ``paper_lugre``, ``paper_gains``, ``paper_params``); a 2-link arm (``two_link_plant``).
- Sensing presets (``SENSING_PRESETS``, ``sensing_preset``): ``"rig"`` (16-bit encoders,
  filtered velocities, 12-bit DAC), ``"ideal"`` (exact) and ``"paper"`` (0.72 deg encoder).
- Reference tasks (``TRAJECTORIES``, ``trajectory_preset``): the paper's sinusoid (Fig.
  9-11), rest-to-rest polynomial (Fig. 12-14) and faster motion (Fig. 15).
- The controller configuration used where a parameter file records none
  (``DEFAULT_CONTROLLER``) and its resolution against a file (``controller_config``).

Every command-line choice list and every workflow takes its names from here. This module
sits above the physics modules and ``params`` (it builds their objects); none of them
imports it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from jaxflex.core.controller import CascadeGains
from jaxflex.core.friction import LuGre
from jaxflex.io.params import ControllerConfig, Params, ParamsError, build_plant
from jaxflex.core.plant import FlexibleJointPlant, PlanarTwoLink
from jaxflex.core.sensing import Sensing
from jaxflex.core.trajectory import RestToRest, Sinusoid, Trajectory

# ----- the paper's tables (link 1) ------------------------------------------------------------

PAPER_PLANT: Mapping[str, float] = MappingProxyType({"I": 0.07, "J": 0.005, "K": 6.77})
"""Table 1: link inertia I [kg m^2], link-referred rotor inertia J [kg m^2], joint
stiffness K [N m/rad]."""

PAPER_FRICTION: Mapping[str, float] = MappingProxyType(
    {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1, "sigma2": 0.2})
"""Table 2 with the correction in docs/spec.md (Appendix B): Fc, Fs [N m], vs [rad/s], sigma0 [N m/rad], sigma1,
sigma2 [N m s/rad]."""

PAPER_GAINS: Mapping[str, float] = MappingProxyType(
    {"Ke": 0.001, "KD1": 1.0, "KD2": 1.0, "kv": 2.0, "L1": 200.0, "L2": 6.0})
"""Table 3: Ke [rad/(N m)], KD1, KD2 [N m s/rad], kv [s/rad], L1, L2 [1/s]."""


def paper_lugre() -> LuGre:
    """Link-1 LuGre parameters of the paper (Table 2 with the correction in docs/spec.md (Appendix B))."""
    return LuGre.from_dict(PAPER_FRICTION)


def paper_plant(friction: bool = True) -> FlexibleJointPlant:
    """The paper's single horizontal link (Table 1; LuGre of Table 2 unless ``friction`` is
    False)."""
    return build_plant(PAPER_PLANT, PAPER_FRICTION if friction else None)


def paper_gains() -> CascadeGains:
    """Table 3 gains for link 1."""
    return CascadeGains(**PAPER_GAINS)


def paper_params() -> Params:
    """The paper's link-1 parameters (Tables 1-3, the corrected Table 2 of docs/spec.md) as ``Params``."""
    return Params.from_dict({"plant": dict(PAPER_PLANT), "friction": dict(PAPER_FRICTION),
                             "gains": dict(PAPER_GAINS)})


def two_link_plant(gravity: float = 9.81, friction: bool = True) -> FlexibleJointPlant:
    """A 2-link planar arm with elastic joints and LuGre friction on both links.

    Link 1 is sized so that its inertia about the joint is close to the paper's prototype;
    link 2 is lighter. With ``gravity`` [m/s^2] > 0 the arm moves in a vertical plane.
    """
    links = PlanarTwoLink(
        m1=0.6, m2=0.35, l1=0.3, lc1=0.15, lc2=0.12, I1=0.0045, I2=0.002, g=gravity
    )
    lugre = (
        LuGre(Fc=[0.11, 0.06], Fs=[0.15, 0.08], vs=[0.05, 0.05], sigma0=[100.0, 80.0],
              sigma1=[0.1, 0.08], sigma2=[0.2, 0.1])
        if friction else None
    )
    return FlexibleJointPlant(links=links, J=[0.005, 0.003], K=[6.77, 5.0], friction=lugre)


# ----- sensing presets ------------------------------------------------------------------------

def rig_sensing(bits: int = 16, dac_range: float = 2.0, dac_bits: int = 12) -> Sensing:
    """A rig with ``bits``-bit encoders on link and rotor (the rotor's behind a 1:50 gear, so
    its step is 1/50 of the link's when referred to the link), filtered-derivative
    velocities, and a ``dac_bits``-bit DAC over +-dac_range [N m] (0 bits: no DAC).

    The paper's 0.72 deg link encoder (``paper_sensing``) makes the paper's loop (L1 = 200)
    chatter at the torque limit: one count moves q2d by about L1 KD1 0.0126 / K = 0.37 rad.
    """
    res = 2 * math.pi / 2**bits
    return Sensing(q1_resolution=res, q2_resolution=res / 50.0, velocity="filtered",
                   dac_bits=dac_bits, dac_range=dac_range)


def paper_sensing() -> Sensing:
    """The paper's rig (section 6.3): 0.72 deg link encoder, velocities by filtered
    differentiation, 12-bit DAC over +-2 N m. The rotor encoder is not stated; we take 0.72 deg
    before a 1:50 gear (0.0144 deg link-referred)."""
    deg = math.pi / 180.0
    return Sensing(
        q1_resolution=0.72 * deg, q2_resolution=0.72 * deg / 50.0, velocity="filtered",
        dac_bits=12, dac_range=2.0,
    )


_SENSING: Mapping[str, tuple[Callable[[], Sensing], str]] = MappingProxyType({
    "rig": (rig_sensing, "16-bit encoders, filtered velocities, 12-bit DAC over +-2 N m"),
    "ideal": (Sensing, "exact angles and velocities, no DAC"),
    "paper": (paper_sensing, "the paper's 0.72 deg link encoder, filtered velocities, "
                             "12-bit DAC"),
})
SENSING_PRESETS: tuple[str, ...] = tuple(_SENSING)
SENSING_DESCRIPTIONS: Mapping[str, str] = MappingProxyType({k: v[1] for k, v in _SENSING.items()})


def sensing_preset(name: str) -> Sensing:
    """The sensing preset ``name`` (one of ``SENSING_PRESETS``); raises ``ValueError``
    naming the choices."""
    if name not in _SENSING:
        raise ValueError(f"unknown sensing preset {name!r}; choices: {list(SENSING_PRESETS)}")
    return _SENSING[name][0]()


VELOCITY_ESTIMATORS: tuple[str, ...] = ("filtered", "kalman")

REPRODUCE_LEAK: float = 0.2
"""The observer leakage [rad/s] ``jaxflex reproduce`` adds to the paper's gains by default
(``CascadeGains.leak``; 0 is the paper's observer): the smallest value of the grid of
``studies/observer_leak.py`` at which every mode of the loop linearised at rest has a damping
ratio of at least 0.05 under the ideal, rig and paper sensings (with the Kalman filter)."""


def with_estimator(sensing: Sensing, estimator: str | None) -> Sensing:
    """``sensing`` with its velocity source replaced by ``estimator`` ("filtered": the dirty
    derivative; "kalman": the steady-state Kalman filter of ``jaxflex.core.estimator``, default
    tuning; None: unchanged). A sensing with exact velocities is returned as it is."""
    if estimator is None or sensing.velocity == "exact":
        return sensing
    if estimator not in VELOCITY_ESTIMATORS:
        raise ValueError(f"unknown velocity estimator {estimator!r}; choices: "
                         f"{list(VELOCITY_ESTIMATORS)}")
    return Sensing(q1_resolution=sensing.q1_resolution, q2_resolution=sensing.q2_resolution,
                   q1_noise=sensing.q1_noise, q2_noise=sensing.q2_noise, velocity=estimator,
                   dac_bits=sensing.dac_bits, dac_range=sensing.dac_range,
                   kalman=sensing.kalman if estimator == "kalman" else None)


def sensing_of(entry: str | Mapping[str, Any]) -> Sensing:
    """A sensing from a preset name or a mapping of ``Sensing`` fields (SI units), as a
    spread file or a parameter file's ``controller.sensing`` gives it."""
    return sensing_preset(entry) if isinstance(entry, str) else Sensing(**entry)


def sensing_fields(sensing: Sensing) -> dict[str, Any]:
    """The fields of ``sensing`` as a parameter file's ``controller.sensing`` records them
    (the inverse of ``sensing_of`` for a mapping; plain numbers, SI units).

    **Arguments:**

    - ``sensing``: a ``Sensing``.

    **Returns:**

    A mapping of its fields (``kalman`` only where the Kalman filter is selected).
    """
    import numpy as np

    def num(v: Any) -> float | list[float]:
        a = np.asarray(v, dtype=float)
        return float(a) if a.ndim == 0 else [float(x) for x in a.reshape(-1)]

    out: dict[str, Any] = {k: num(getattr(sensing, k)) for k in (
        "q1_resolution", "q2_resolution", "q1_noise", "q2_noise")}
    out.update(velocity=sensing.velocity, dac_bits=int(sensing.dac_bits),
               dac_range=num(sensing.dac_range))
    if sensing.velocity == "kalman":
        k = sensing.kalman
        out["kalman"] = ({} if k is None else
                         {"disturbance_rate": num(k.disturbance_rate),
                          "torque_noise": num(k.torque_noise),
                          "angle_floor": num(k.angle_floor), "angles": bool(k.angles)})
    return out


# ----- reference tasks ------------------------------------------------------------------------

def paper_sinusoid() -> Sinusoid:
    """The paper's sinusoidal task (Fig. 9-11): 0.05 rad amplitude, 0.5 Hz, 10 s.

    The paper prints neither amplitude nor frequency; the amplitude is read off Fig. 9-10,
    the frequency is our choice (five periods in the 10 s plot window).
    """
    return Sinusoid(amplitude=0.05, frequency=0.5)


def paper_polynomial() -> RestToRest:
    """The paper's polynomial task (Fig. 12-14): rest-to-rest moves between -0.07 and 0.07 rad."""
    return RestToRest(
        waypoints=[0.0, 0.07, -0.07, 0.07, -0.07, 0.0],
        durations=[1.5, 2.0, 2.0, 2.0, 1.5],
        t0=0.5,
    )


def paper_fast() -> RestToRest:
    """A faster motion (Fig. 15): 0.5 rad moves in 0.6 s, about 2 rad/s peak link speed."""
    return RestToRest(
        waypoints=[0.0, 0.5, -0.5, 0.5, 0.0],
        durations=[0.6, 0.9, 0.9, 0.6],
        t0=0.5,
    )


_TRAJECTORIES: Mapping[str, tuple[Callable[[], Trajectory], str]] = MappingProxyType({
    "sinusoid": (paper_sinusoid, "Fig. 9-11: sinusoid, 0.05 rad, 0.5 Hz"),
    "polynomial": (paper_polynomial, "Fig. 12-14: rest-to-rest polynomial, +-0.07 rad"),
    "fast": (paper_fast, "Fig. 15: faster motion, +-0.5 rad moves in 0.6-0.9 s"),
})
TRAJECTORIES: tuple[str, ...] = tuple(_TRAJECTORIES)
TRAJECTORY_DESCRIPTIONS: Mapping[str, str] = MappingProxyType(
    {k: v[1] for k, v in _TRAJECTORIES.items()})


def trajectory_preset(name: str) -> Trajectory:
    """The one-joint reference task ``name`` (one of ``TRAJECTORIES``); raises
    ``ValueError`` naming the choices."""
    if name not in _TRAJECTORIES:
        raise ValueError(f"unknown trajectory {name!r}; choices: {list(TRAJECTORIES)}")
    return _TRAJECTORIES[name][0]()


# ----- controller configuration ---------------------------------------------------------------

DEFAULT_CONTROLLER = ControllerConfig(
    q2d_method="model", dt=1e-3, tau_max=2.0, compensation=True, sensing="rig",
    trajectory="sinusoid",
)
"""The configuration where a parameter file records none: 1 kHz, the rig's +-2 N m DAC
range as torque limit, q2d derivatives along the model, compensation on, rig sensing, the
paper's sinusoid."""


def controller_config(params: Params | None, given: Mapping[str, Any] | None = None,
                      flags: Mapping[str, str] | None = None,
                      source: str = "the parameter file") -> ControllerConfig:
    """The controller configuration to use: ``params.controller`` (if recorded), then the
    ``given`` entries (field name -> value, ``None``: not given) where it records nothing,
    then ``DEFAULT_CONTROLLER``. Every entry is then set.

    Raises ``ParamsError`` when a given entry contradicts a recorded one (see
    ``ControllerConfig.resolve``; ``flags`` names the options in the message), and
    ``ValueError`` naming the choices for an unknown sensing preset or trajectory.
    """
    recorded = (params.controller if params is not None else None) or ControllerConfig()
    cfg = recorded.resolve(given or {}, flags, source).with_defaults(DEFAULT_CONTROLLER)
    names = (cfg.trajectory,) if isinstance(cfg.trajectory, str) else cfg.trajectory
    for name in names:
        if name not in _TRAJECTORIES:
            raise ParamsError(f"controller.trajectory: unknown trajectory {name!r}; choices: "
                              f"{list(TRAJECTORIES)}")
    if isinstance(cfg.sensing, str) and cfg.sensing not in _SENSING:
        raise ParamsError(f"controller.sensing: unknown sensing preset {cfg.sensing!r}; "
                          f"choices: {list(SENSING_PRESETS)}")
    return cfg

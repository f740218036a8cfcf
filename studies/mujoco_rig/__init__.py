"""A flexible-joint rig simulated by MuJoCo, not by jaxflex: logs for testing jaxflex on data
it did not make.

The rig is the paper's single link (docs/spec.md section 1) built as a MuJoCo model: a rotor
body and a link body on one horizontal (or, with gravity, vertical-plane) hinge axis, coupled
by a fixed tendon ``q2 - q1`` whose stiffness is the joint spring. What MuJoCo itself computes
(its integrator ``implicitfast`` at 0.01 ms, its own implementations):

- the spring and the joint damping (tendon stiffness and damping; a backlash is the tendon's
  dead band, a sharp one, where jaxflex's is smooth);
- the viscous part of the link's LuGre friction (joint damping);
- gravity (a link whose centre of mass is off the axis);
- motor friction (the rotor's ``frictionloss``, a constraint, and ``damping``), not
  jaxflex's tanh-smoothed Coulomb term;
- an actuator lag (a ``filterexact`` actuator).

What this module adds as applied forces, written here, not taken from jaxflex: the LuGre
bristle force (its state advanced exactly for the velocity frozen over a physics step),
a direction-dependent Coulomb level (and, for ``asymmetric_friction_2``, a static level of its
own) inside the LuGre curve, cogging on either side (with a second harmonic for
``cogging_2``), a cubic spring term (and a fifth-power one for ``hardening_spring_2``), a
Stribeck excess on the rotor beside MuJoCo's Coulomb constraint (``motor_friction_2``), a
second-order current loop on the command (``actuator_lag_2``), and disturbances outside
jaxflex's effect library (a vibration of the base, a stiffness that ripples with position). A time delay is the exact transport delay
of the sampled command (a buffer at the physics step, not a Pade approximant); an encoder
skew is the link channel read late by a separate recorder, interpolated from the physics
steps.

The experiment is not jaxflex's either: an industrial drive's P/PI cascade on the motor
encoder with velocity feedforward (``loop="drive"``) following point-to-point moves with
dwells or a logarithmic chirp, or open-loop torque (alternating pulses, or a chirp). The
encoders, the DAC and the noise are this module's own. A log has the columns t, tau (the
commanded torque as the DAC wrote it), q1, q2 and q1d (the reference; zero open loop), at
1 kHz.

``simulate_rig(effects, seed)`` returns the log and the truth. MuJoCo (``pip install
mujoco``, or jaxflex's ``test`` extra) is needed; jaxflex itself does not depend on it.
A folder, not a ``studies/*.py`` file, so that the test that runs every study skips it; the
scripts import it as ``mujoco_rig`` (``python studies/X.py`` puts ``studies/`` on the path).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from scipy.signal import lfilter

from jaxflex.core.effects import EFFECTS
from jaxflex.identify.datagen import draw_effect
from jaxflex.io.logs import Log
from jaxflex.io.presets import paper_params

LOOPS: tuple[str, ...] = ("drive", "open_loop")
EXCITATIONS: tuple[str, ...] = ("moves", "chirp")
DISTURBANCES: tuple[str, ...] = ("vibration", "stiffness_ripple")
def draw_rig_effect(name: str, rng: np.random.Generator, scale: float = 1.0) -> dict[str, float]:
    """The parameters of effect ``name`` on the rig: an order-1 effect's moderate magnitudes
    times ``scale`` (``jaxflex.identify.datagen.draw_effect``, the generator's draws); a
    family's order 2 (``cogging_2``, ``hardening_spring_2``, ``asymmetric_friction_2``,
    ``motor_friction_2``, ``actuator_lag_2``) its order 1's draw plus the terms of order 2,
    sized here so that the order-1 term alone leaves a clear part of them: a second harmonic
    of 40-70% of the fundamental, a fifth-power spring term equal to 50-100% of the cubic
    one at a deflection of 0.05 rad, a static level shifted 0.02-0.04 N m further than the
    Coulomb level, a Stribeck excess of 70-120% of the rotor's Coulomb level below 0.05-0.15
    rad/s, a current loop with 1 / natural frequency 2-4 ms and damping 0.4-0.7. The keys are the
    jaxflex class's parameters."""
    if name not in EFFECTS or EFFECTS[name].order == 1:
        return draw_effect(name, rng, scale)  # an unknown name: its error
    if name not in HIGHER_DRAWS:
        raise ValueError(f"the rig has no draw for {name!r}; its orders 2: {sorted(HIGHER_DRAWS)}")
    kw = draw_effect(EFFECTS[name].family_name(), rng, scale)
    return {**kw, **HIGHER_DRAWS[name](kw, rng)}


#: The terms of each order 2 the rig draws, from its order 1's draw (``draw_rig_effect``).
HIGHER_DRAWS: dict[str, Any] = {
    "cogging_2": lambda kw, rng: {"A2": kw["A"] * rng.uniform(0.4, 0.7),
                                  "phi2": rng.uniform(-math.pi, math.pi)},
    "hardening_spring_2": lambda kw, rng: {"K5": kw["K3"] * rng.uniform(0.5, 1.0) / 0.05**2},
    "asymmetric_friction_2": lambda kw, rng: {
        "dS": kw["dF"] + math.copysign(rng.uniform(0.02, 0.04), kw["dF"])},
    "motor_friction_2": lambda kw, rng: {"Fsm": kw["Fm"] * rng.uniform(0.7, 1.2),
                                         "vsm": rng.uniform(0.05, 0.15)},
    "actuator_lag_2": lambda kw, rng: {"T": rng.uniform(2e-3, 4e-3),
                                       "zeta": rng.uniform(0.4, 0.7)},
}


def _family(eff: dict[str, dict[str, float]], name: str) -> dict[str, float] | None:
    """The parameters of whichever order of family ``name`` the rig holds (None: none)."""
    return next((kw for k, kw in eff.items() if EFFECTS[k].family_name() == name), None)


@dataclasses.dataclass
class RigLog:
    """A log of the MuJoCo rig (``jaxflex.io.logs.Log``) and its truth: hidden effects with
    their parameters, the true plant, the experiment and the sensing."""

    log: Log
    effects: list[str]
    truth: dict[str, Any]


def rig_xml(plant: dict[str, float], fr: dict[str, float], eff: dict[str, dict[str, float]],
            physics_dt: float) -> str:
    """The MJCF of the rig: link and rotor bodies on the hinge axis y, the spring tendon, the
    motor actuator. ``plant``: I, J [kg m^2], K [N m/rad]; ``fr``: the link's LuGre parameters
    (only sigma2 [N m s/rad] enters the model, the rest is applied by ``simulate_rig``)."""
    I, J, K = plant["I"], plant["J"], plant["K"]
    g = eff.get("gravity")
    if g:
        # mass m at distance l from the axis, hanging at q1 = q0:
        # gravity torque = -m g l sin(q1 - q0); inertia about the axis stays I
        length = 0.1
        m = g["mgl"] / (9.81 * length)
        pos = f"{length * math.sin(g['q0']):.12g} 0 {-length * math.cos(g['q0']):.12g}"
        ic = I - m * length**2
        link_inertial = f'<inertial pos="{pos}" mass="{m:.12g}" diaginertia="{ic:.12g} {ic:.12g} {ic:.12g}"/>'
        gravity = "0 0 -9.81"
    else:
        link_inertial = f'<inertial pos="0 0 0" mass="1" diaginertia="{I:.12g} {I:.12g} {I:.12g}"/>'
        gravity = "0 0 0"
    mf = _family(eff, "motor_friction") or {"Fm": 0.0, "bm": 0.0}
    rotor_friction = (f'frictionloss="{mf["Fm"]:.12g}" damping="{mf["bm"]:.12g}" '
                      f'solreffriction="{4 * physics_dt:.6g} 1"')
    b = eff.get("backlash", {}).get("b", 0.0)
    D = eff.get("joint_damping", {}).get("D", 0.0)
    lag = eff.get("actuator_lag")  # order 2 is this module's own filter (simulate_rig)
    dyn = f'dyntype="filterexact" dynprm="{lag["T"]:.12g}"' if lag else 'dyntype="none"'
    return f"""
<mujoco model="flexible_joint_rig">
  <option timestep="{physics_dt:.6g}" integrator="implicitfast" gravity="{gravity}"/>
  <worldbody>
    <body name="link">
      <joint name="link" type="hinge" axis="0 1 0" damping="{fr['sigma2']:.12g}"/>
      {link_inertial}
    </body>
    <body name="rotor">
      <joint name="rotor" type="hinge" axis="0 1 0" {rotor_friction}/>
      <inertial pos="0 0 0" mass="1" diaginertia="{J:.12g} {J:.12g} {J:.12g}"/>
    </body>
  </worldbody>
  <tendon>
    <fixed name="spring" stiffness="{K:.12g}" damping="{D:.12g}" springlength="{-b:.12g} {b:.12g}">
      <joint joint="rotor" coef="1"/>
      <joint joint="link" coef="-1"/>
    </fixed>
  </tendon>
  <actuator>
    <general name="motor" joint="rotor" gainprm="1" biastype="none" {dyn}/>
  </actuator>
</mujoco>"""


def _moves(rng: np.random.Generator, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-point moves with dwells: trapezoidal velocity (peak 0.4-1.0 rad/s,
    acceleration 4-8 rad/s^2) between targets in +-0.35 rad, dwells of 0.1-0.6 s. Returns
    position [rad] and velocity [rad/s] on the time grid t [s]."""
    r, v = np.zeros_like(t), np.zeros_like(t)
    t0, x0 = 0.2, 0.0
    while t0 < t[-1]:
        x1 = rng.uniform(-0.35, 0.35)
        vmax, acc = rng.uniform(0.4, 1.0), rng.uniform(4.0, 8.0)
        dist = abs(x1 - x0)
        ta = min(vmax / acc, math.sqrt(dist / acc))  # accelerating phase
        vp = acc * ta
        tc = max(dist - acc * ta**2, 0.0) / vp if vp > 0 else 0.0  # cruise
        T = 2 * ta + tc
        s = np.sign(x1 - x0)
        m = (t >= t0) & (t < t0 + T)
        tau = t[m] - t0
        vel = np.where(tau < ta, acc * tau, np.where(tau < ta + tc, vp, vp - acc * (tau - ta - tc)))
        pos = np.where(tau < ta, 0.5 * acc * tau**2,
                       np.where(tau < ta + tc, 0.5 * acc * ta**2 + vp * (tau - ta),
                                dist - 0.5 * acc * np.maximum(T - tau, 0.0) ** 2))
        r[m], v[m] = x0 + s * pos, s * vel
        t_end = t0 + T
        x0 = x1
        dwell = rng.uniform(0.1, 0.6)
        r[(t >= t_end) & (t < t_end + dwell)] = x0
        t0 = t_end + dwell
        r[t >= t0] = x0
    return r, v


def _chirp(rng: np.random.Generator, t: np.ndarray, f0: float, f1: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """A unit logarithmic chirp from f0 to f1 [Hz] over the time grid t [s] and its time
    derivative [1/s], with a random phase."""
    T = t[-1] + (t[1] - t[0])
    k = (f1 / f0) ** (1.0 / T)
    phase = 2 * math.pi * f0 * (k**t - 1.0) / math.log(k) + rng.uniform(-math.pi, math.pi)
    return np.sin(phase), np.cos(phase) * 2 * math.pi * f0 * k**t


def _pulses(rng: np.random.Generator, t: np.ndarray, level: float) -> np.ndarray:
    """Open-loop torque [N m]: pulses of alternating sign, 1.2-2.2 x ``level`` high,
    30-150 ms long, 50-300 ms apart, edges smoothed by a 10 ms first-order filter."""
    u = np.zeros_like(t)
    t0, sign = 0.2, rng.choice([-1.0, 1.0])
    while t0 < t[-1]:
        w = rng.uniform(0.03, 0.15)
        u[(t >= t0) & (t < t0 + w)] = sign * level * rng.uniform(1.2, 2.2)
        t0 += w + rng.uniform(0.05, 0.3)
        sign = -sign
    a = math.exp(-(t[1] - t[0]) / 0.01)
    return lfilter([1.0 - a], [1.0, -a], u)


def simulate_rig(
    effects: tuple[str, ...] | list[str] = (),
    seed: int = 0,
    *,
    t_final: float = 12.0,
    loop: str = "drive",
    excitation: str = "moves",
    disturbance: str | None = None,
    scale: float = 1.0,
    mismatch: float = 0.1,
    dt: float = 1e-3,
    physics_dt: float = 1e-5,
) -> RigLog:
    """Run one identification experiment on the MuJoCo rig with ``effects`` hidden.

    seed: every draw (plant mismatch, magnitudes, excitation, noise); loop (``LOOPS``),
    excitation (``EXCITATIONS``), disturbance (``DISTURBANCES`` or None: outside jaxflex's
    library); scale: multiplies the effect magnitudes; mismatch: relative std of the true
    plant against the paper's parameters (I, J, K, Fc, Fs, sigma2); dt: the controller's and
    the log's sample period [s]; physics_dt: MuJoCo's step [s] (dt a multiple of it).
    Raises ``RuntimeError`` if the run leaves +-50 rad (a loop that went unstable)."""
    import mujoco

    if loop not in LOOPS or excitation not in EXCITATIONS:
        raise ValueError(f"loop must be one of {LOOPS} and excitation one of {EXCITATIONS}; "
                         f"got {loop!r}, {excitation!r}")
    if disturbance is not None and disturbance not in DISTURBANCES:
        raise ValueError(f"disturbance must be one of {DISTURBANCES} or None, got {disturbance!r}")
    sub = int(round(dt / physics_dt))
    if abs(sub * physics_dt - dt) > 1e-12 * dt or sub < 1:
        raise ValueError(f"dt {dt} must be a whole multiple of physics_dt {physics_dt}")
    rng = np.random.default_rng(seed)
    nominal = paper_params()
    plant = {k: float(v[0]) * math.exp(mismatch * rng.standard_normal()) if k in ("I", "J", "K")
             else float(v[0]) for k, v in nominal.plant.items()}
    fr = {k: float(v[0]) for k, v in nominal.friction.items()}
    for k in ("Fc", "Fs", "sigma2"):
        fr[k] *= math.exp(mismatch * rng.standard_normal())
    fr["Fs"] = max(fr["Fs"], 1.05 * fr["Fc"])
    # the magnitudes of jaxflex's generator (each class's ``moderate`` x scale, the same draws)
    eff = {name: draw_rig_effect(name, rng, scale) for name in effects}
    if "backlash" in eff:
        eff["backlash"]["K"] = plant["K"]
    dist: dict[str, float] = {}
    if disturbance == "vibration":  # the base shakes: a torque at one frequency on the link
        dist = {"A": rng.uniform(0.02, 0.04), "f": rng.uniform(5.0, 12.0),
                "phi": rng.uniform(-math.pi, math.pi)}
    elif disturbance == "stiffness_ripple":  # a spring stiffer at some link angles than others
        dist = {"e": rng.uniform(0.15, 0.3), "N": rng.uniform(8.0, 15.0),
                "phi": rng.uniform(-math.pi, math.pi)}

    model = mujoco.MjModel.from_xml_string(rig_xml(plant, fr, eff, physics_dt))
    data = mujoco.MjData(model)
    LINK, ROTOR = 0, 1

    n = int(round(t_final / dt))
    t = np.arange(n) * dt
    # the experiment
    if loop == "drive":
        if excitation == "moves":
            ref, dref = _moves(rng, t)
        else:
            c, dc = _chirp(rng, t, 0.2, 2.0)
            amp = rng.uniform(0.12, 0.18)
            ref, dref = amp * c, amp * dc
        u_ol = None
    else:
        ref = dref = np.zeros(n)
        level = fr["Fs"]
        if excitation == "moves":
            u_ol = _pulses(rng, t, level)
        else:
            u_ol = 1.6 * level * _chirp(rng, t, 0.2, 5.0)[0]

    # sensing: a link encoder of 2^17 counts, a motor encoder of 4096 counts behind a 1:100
    # gear (reflected to the link: 409600 counts), 0.3 counts of white noise, a 16-bit DAC
    # over +-3 N m, a torque limit of 2 N m
    res1, res2 = 2 * math.pi / 2**17, 2 * math.pi / 409600
    dac = 6.0 / 2**16
    tau_max = 2.0

    def read(x: float, res: float) -> float:
        return res * round((x + 0.3 * res * rng.standard_normal()) / res)

    # drive gains: P position loop [1/s], PI velocity loop [N m s/rad, 1/s], velocity from the
    # motor encoder's backward difference through a 2 ms first-order filter
    kp, kv, ki, vtc = 25.0, 0.5, 15.0, 0.002
    av = math.exp(-dt / vtc)
    v_est, q2_prev, integ = 0.0, 0.0, 0.0

    # the physics
    delay = eff.get("time_delay", {}).get("T", 0.0)
    lag_steps = delay / physics_dt  # transport delay of the command, in physics steps
    offset = eff.get("torque_offset", {}).get("offset", 0.0)
    cog = _family(eff, "cogging")
    mcog = eff.get("motor_cogging")
    spring = _family(eff, "hardening_spring") or {}
    K3, K5 = spring.get("K3", 0.0), spring.get("K5", 0.0)
    asym = _family(eff, "asymmetric_friction") or {}
    dF = asym.get("dF", 0.0)
    dS = asym.get("dS", dF)
    stribeck = eff.get("motor_friction_2")
    loop2 = eff.get("actuator_lag_2")
    a2, da2 = 0.0, 0.0  # the current loop's output and its rate
    s0, s1, Fc, Fs, vs = fr["sigma0"], fr["sigma1"], fr["Fc"], fr["Fs"], fr["vs"]
    K = plant["K"]
    hist_len = int(math.ceil(lag_steps)) + 2
    cmd_hist = np.zeros(hist_len)  # commanded torque at the last physics steps, newest last
    skew = eff.get("encoder_skew")
    q1_fine = np.zeros(n * sub + 1)  # the link angle at every physics step (for the skew)
    z = 0.0
    tau_log, q1_log, q2_log = np.zeros(n), np.zeros(n), np.zeros(n)
    cmd = 0.0
    for k in range(n):
        # sample: read the encoders, compute and write the command (held for one period)
        q1m, q2m = read(data.qpos[LINK], res1), read(data.qpos[ROTOR], res2)
        if u_ol is None:
            v_raw = (q2m - q2_prev) / dt if k > 0 else 0.0
            v_est = av * v_est + (1 - av) * v_raw
            v_ref = kp * (ref[k] - q2m) + dref[k]
            e = v_ref - v_est
            u = kv * e + integ
            if abs(u) < tau_max:  # anti-windup: integrate only while unsaturated
                integ += kv * ki * e * dt
            cmd = float(np.clip(u, -tau_max, tau_max))
        else:
            cmd = float(np.clip(u_ol[k], -tau_max, tau_max))
        cmd = dac * round(cmd / dac)
        q2_prev = q2m
        tau_log[k], q1_log[k], q2_log[k] = cmd, q1m, q2m
        for j in range(sub):
            cmd_hist[:-1] = cmd_hist[1:]
            cmd_hist[-1] = cmd
            if delay > 0:  # the command that was current `delay` ago (linear between steps)
                i = hist_len - 1 - lag_steps
                i0 = int(math.floor(i))
                applied = cmd_hist[i0] + (i - i0) * (cmd_hist[min(i0 + 1, hist_len - 1)] - cmd_hist[i0])
            else:
                applied = cmd
            if loop2:  # T^2 a'' + 2 zeta T a' + a = command, semi-implicit at the physics step
                T2, z2 = loop2["T"], loop2["zeta"]
                da2 += physics_dt * (applied - a2 - 2 * z2 * T2 * da2) / T2**2
                a2 += physics_dt * da2
                applied = a2
            data.ctrl[0] = applied + offset
            q1, q2 = data.qpos[LINK], data.qpos[ROTOR]
            v1 = data.qvel[LINK]
            # LuGre bristles (docs/spec.md eq. 4-6), a direction-dependent Coulomb level
            e1 = math.exp(-(v1 / vs) ** 2)
            g = Fc + (Fs - Fc) * e1 + ((dF + (dS - dF) * e1) * math.copysign(1.0, v1)
                                       if v1 != 0 else 0.0)
            a = s0 * abs(v1) / g
            zdot = v1 - a * z
            f_link = -(s0 * z + s1 * zdot)
            if a * physics_dt > 1e-12:  # exact for v1 frozen over the step
                zs = v1 / a
                z = zs + (z - zs) * math.exp(-a * physics_dt)
            else:
                z += v1 * physics_dt
            f_rotor = 0.0
            d = q2 - q1
            spring_extra = K3 * d**3 + K5 * d**5
            if disturbance == "stiffness_ripple":
                spring_extra += dist["e"] * K * math.sin(dist["N"] * q1 + dist["phi"]) * d
            f_link += spring_extra
            f_rotor -= spring_extra
            if cog:
                f_link += cog["A"] * math.sin(cog["N"] * q1 + cog["phi"])
                if "A2" in cog:
                    f_link += cog["A2"] * math.sin(2 * cog["N"] * q1 + cog["phi2"])
            if stribeck:  # beside MuJoCo's Coulomb constraint: the excess, smoothed at 2 mrad/s
                v2 = data.qvel[ROTOR]
                f_rotor -= (stribeck["Fsm"] * math.exp(-(v2 / stribeck["vsm"]) ** 2)
                            * math.tanh(v2 / 0.002))
            if mcog:
                f_rotor += mcog["A"] * math.sin(mcog["N"] * q2 + mcog["phi"])
            if disturbance == "vibration":
                tt = k * dt + j * physics_dt
                f_link += dist["A"] * math.sin(2 * math.pi * dist["f"] * tt + dist["phi"])
            data.qfrc_applied[LINK] = f_link
            data.qfrc_applied[ROTOR] = f_rotor
            mujoco.mj_step(model, data)
            q1_fine[k * sub + j + 1] = data.qpos[LINK]
        if not (abs(data.qpos[LINK]) < 50.0 and abs(data.qpos[ROTOR]) < 50.0):
            raise RuntimeError(f"simulate_rig: the run left +-50 rad at t = {k * dt:.3f} s "
                               f"(effects={list(effects)}, seed={seed}, loop={loop})")
    if skew:
        # a separate recorder reads the link encoder skew late and offset low
        tf = np.arange(n * sub + 1) * physics_dt
        late = np.interp(t - skew["skew"], tf, q1_fine)
        q1_log = np.array([read(x, res1) for x in late - skew["offset"]])
    log = Log.from_arrays(t=t, tau=tau_log, q1=q1_log, q2=q2_log, q1d=ref,
                          source=f"mujoco_rig(effects={list(effects)}, seed={seed}, {loop}, "
                                 f"{excitation})")
    truth = {"effects": eff, "plant": {"plant": {k: [v] for k, v in plant.items()},
                                       "friction": {k: [v] for k, v in fr.items()}},
             "seed": seed, "loop": loop, "excitation": excitation, "disturbance": disturbance,
             "disturbance_params": dist, "scale": scale, "mismatch": mismatch,
             "physics_dt": physics_dt, "simulator": f"MuJoCo {mujoco.__version__}",
             "saturation_fraction": float(np.mean(np.abs(tau_log) >= tau_max - dac))}
    return RigLog(log=log, effects=list(effects), truth=truth)

"""Synthetic identification logs with hidden effects (for testing the discrepancy workflow).

A case is a closed-loop identification experiment on the paper's link (docs/spec.md section 1-3): the
paper's cascade controller (its nominal model = the paper's parameters, gentler gains
``IDENT_GAINS``) tracks a randomised
Schroeder multisine around a true plant that differs from the nominal one by (a) a random
parameter mismatch of I, J, K, Fc, Fs, sigma2 (so that a refit is needed) and (b) zero, one or
two hidden effects from docs/spec.md section 8 with randomised magnitudes. Sensing: encoders with
``bits`` counts per revolution on the link and 50x finer on the rotor (a 1:50 gear), white
angle noise, filtered velocities, 12-bit DAC over +-2 N m. The log holds the applied (DAC)
torque, the sensed angles and the reference, at 1 kHz (docs/spec.md section 6 columns t,tau,q1,q2,q1d).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.core.controller import (
    AbstractTrackingLaw, CascadeController, CascadeGains, ControllerState, LawOutput,
    dirty_derivative, pd_torque,
)
from jaxflex.core.effects import EFFECTS, AbstractEffect
from jaxflex.identify.experiments import synthetic_log
from jaxflex.io.logs import Log
from jaxflex.io.presets import paper_params
from jaxflex.core.sensing import Sensing
from jaxflex.sim.simulate import simulate_sampled
from jaxflex.core.plant import FlexibleJointPlant, PlantState
from jaxflex.core.trajectory import Multisine, Trajectory
from jaxflex.core.validation import as_param, requires_float64

#: Gentler gains than Table 3 for the identification experiment: with L1 = 200 1/s the loop
#: chatters at the 2 N m limit on a 0.15 rad multisine (nearly every sample saturated).
IDENT_GAINS = CascadeGains(Ke=0.001, KD1=0.5, KD2=0.5, kv=2.0, L1=15.0, L2=6.0)

_simulate = eqx.filter_jit(simulate_sampled)



LOOPS: tuple[str, ...] = ("cascade", "pd_rotor", "open_loop")
"""Experiment loops of ``generate_log``: the paper's cascade (its nominal model, compensation
on), a PD on the rotor angle (no model, no compensation, a different set of signatures), or
open-loop torque (no feedback at all)."""
EXCITATIONS: tuple[str, ...] = ("multisine", "multisine_ramp")
"""References (or, open loop, torques): a Schroeder multisine, or the same plus a slow large
swing (a 0.03 Hz tone: slow ramps through the friction regimes)."""
DISTURBANCES: tuple[str, ...] = ("friction_bump",)
"""Disturbances outside the effect library (the discrepancy workflow should answer
"unexplained"): a friction patch localised in position."""


class FrictionBump(AbstractEffect):
    """A friction patch at one place of the link's travel (a dent, a dirty spot on a bearing
    race): link_torque = -B exp(-((q1 - qb) / w)^2) tanh(q1' / 0.01) [N m]. Not in the library
    (not registered): a disturbance the workflow should call unexplained."""

    name: ClassVar[str] = "friction_bump"
    where: ClassVar[str] = "link torque"
    candidate: ClassVar[bool] = False
    B: Float[Array, " n"] = eqx.field(converter=as_param)
    qb: Float[Array, " n"] = eqx.field(converter=as_param)
    w: Float[Array, " n"] = eqx.field(converter=as_param)

    @classmethod
    def typical(cls, n: int) -> FrictionBump:
        return cls(B=jnp.full(n, 0.08), qb=jnp.zeros(n), w=jnp.full(n, 0.02))

    def link_torque(self, x: PlantState) -> Float[Array, " n"]:
        return -self.B * jnp.exp(-jnp.square((x.q1 - self.qb) / self.w)) * jnp.tanh(x.dq1 / 0.01)


class RotorPD(AbstractTrackingLaw):
    """A PD loop on the rotor angle toward the link reference (sampled, dirty-derivative
    velocity): tau = kp (q1d - q2) - kd q2' [N m], saturated at tau_max
    (``jaxflex.core.controller.pd_torque``, ``dirty_derivative``); an
    ``AbstractTrackingLaw``."""

    model: FlexibleJointPlant
    trajectory: Trajectory
    kp: Array = eqx.field(converter=as_param, default=8.0)
    kd: Array = eqx.field(converter=as_param, default=0.4)
    dt: float = eqx.field(static=True, default=1e-3)
    tau_max: Array = eqx.field(converter=as_param, default=2.0)
    velocity_tc: float = eqx.field(static=True, default=0.005)

    def init(self, t0, q1, q2, dq1=None, dq2=None) -> ControllerState:
        return ControllerState.at_rest(q1, q2, dq2)

    def step(self, state: ControllerState, t, q1, q2, dq1=None, dq2=None):
        if dq2 is None:
            dq2 = dirty_derivative(state.dq2, q2, state.q2_prev, self.velocity_tc, self.dt)
        ref = self.trajectory.position(jnp.asarray(t, q1.dtype))
        tau = pd_torque(self.kp, self.kd, self.tau_max, ref, q2, dq2)
        new = dataclasses.replace(state, q1_prev=q1, q2_prev=q2, dq2=dq2)
        return new, LawOutput.of_torque(tau, q2d=ref, e1=q1 - ref)


@dataclasses.dataclass
class GeneratedLog:
    """A generated ``Log`` (columns t, tau, q1, q2, q1d; write it with
    ``jaxflex.io.logs.save_log``) plus the truth: hidden effect names and parameters, the true
    plant parameters, and the generator settings."""

    log: Log
    effects: list[str]
    truth: dict[str, Any]


def draw_effect(name: str, rng: np.random.Generator, scale: float = 1.0) -> dict[str, Any]:
    """Keyword arguments of an effect ``name`` with moderate magnitudes times ``scale``
    (``AbstractEffect.draw``, from the class's ``moderate`` ranges; a parameter tied to the
    plant, backlash's K, is left None, to be set from the true plant)."""
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {sorted(EFFECTS)}")
    return EFFECTS[name].draw(rng, scale)


@requires_float64
def generate_log(
    effects: tuple[str, ...] | list[str] = (),
    seed: int = 0,
    *,
    t_final: float = 20.0,
    dt: float = 1e-3,
    bits: int = 16,
    noise_counts: float = 0.5,
    mismatch: float = 0.1,
    scale: float = 1.0,
    rms: float = 0.15,
    substeps: int = 10,
    loop: str = "cascade",
    excitation: str = "multisine",
    disturbance: str | None = None,
) -> GeneratedLog:
    """Simulate one identification experiment with ``effects`` hidden in the true plant.

    seed: PRNG seed for magnitudes, mismatch, excitation and noise; bits: encoder counts per
    revolution = 2^bits on the link (rotor 50x finer); noise_counts: white angle noise std in
    encoder steps; mismatch: relative std of the true-vs-nominal parameter mismatch; scale:
    multiplies the effect magnitudes; rms [rad]: excitation RMS; loop (``LOOPS``),
    excitation (``EXCITATIONS``) and disturbance (``DISTURBANCES`` or None): the experiment
    beyond the workflow's own assumptions (open loop: a torque multisine of RMS 0.15 N m
    about the breakaway level instead of a reference; the log's q1d is then zero).
    Computed in float64 whatever the global JAX setting (``requires_float64``): in float32
    the simulated time is no longer uniformly sampled past 16 s (its spacing is then 2e-6 s,
    2e-3 of a 1 ms sample) and the log is refused.
    """
    if loop not in LOOPS:
        raise ValueError(f"generate_log: loop must be one of {LOOPS}, got {loop!r}")
    if excitation not in EXCITATIONS:
        raise ValueError(f"generate_log: excitation must be one of {EXCITATIONS}, got {excitation!r}")
    if disturbance is not None and disturbance not in DISTURBANCES:
        raise ValueError(f"generate_log: disturbance must be one of {DISTURBANCES} or None, "
                         f"got {disturbance!r}")
    for name in effects:
        if name not in EFFECTS:
            raise ValueError(f"generate_log: unknown effect {name!r}; known: {sorted(EFFECTS)}")
    rng = np.random.default_rng(seed)
    nominal = paper_params()
    true = paper_params()
    for sec, names in (("plant", ("I", "J", "K")), ("friction", ("Fc", "Fs", "sigma2"))):
        for k in names:
            getattr(true, sec)[k] = [
                v * math.exp(mismatch * rng.standard_normal()) for v in getattr(true, sec)[k]
            ]
    true.friction["Fs"] = [max(fs, fc * 1.05) for fs, fc in zip(true.friction["Fs"], true.friction["Fc"])]
    effect_kw: dict[str, dict[str, Any]] = {}
    for name in effects:
        kw = draw_effect(name, rng, scale)
        for p, c in EFFECTS[name].constraints.items():
            if c.startswith("tied:"):  # on the true plant's own parameter (backlash's K)
                kw[p] = true.plant[c.removeprefix("tied:")][0]
        effect_kw[name] = kw
    extra = []
    if disturbance == "friction_bump":
        dist_kw = {"B": float(rng.uniform(0.06, 0.12)), "qb": float(rng.uniform(-0.05, 0.05)),
                   "w": float(rng.uniform(0.01, 0.03))}
        extra.append(FrictionBump(**dist_kw))
    plant = true.to_plant(with_effects=False).with_effects(
        *(EFFECTS[k](**kw) for k, kw in effect_kw.items() if not EFFECTS[k].recording),
        *extra
    )
    count = 6  # fixed so that every case shares one compiled simulation
    f_max = rng.uniform(1.0, 2.0)
    base = Multisine.schroeder(rms=rms * rng.uniform(0.8, 1.2), f_min=0.1, f_max=f_max, count=count)
    amps, freqs, phases = base.amplitudes, base.frequencies, base.phases + rng.uniform(-0.5, 0.5, count)
    if excitation == "multisine_ramp":  # a slow large swing through the friction regimes
        amps = jnp.concatenate([amps, jnp.asarray([2.0 * rms])])
        freqs = jnp.concatenate([freqs, jnp.asarray([0.03])])
        phases = jnp.concatenate([phases, jnp.asarray([rng.uniform(-math.pi, math.pi)])])
    traj = Multisine(amplitudes=amps, frequencies=freqs, phases=phases)
    res = 2 * math.pi / 2**bits
    sensing = Sensing(
        q1_resolution=res, q2_resolution=res / 50.0, q1_noise=noise_counts * res,
        q2_noise=noise_counts * res / 50.0, velocity="filtered", dac_bits=12, dac_range=2.0,
    )
    if loop == "open_loop":
        # torque about the breakaway level: the same multisine shape, scaled to N m
        ts = jnp.arange(int(round(t_final / dt))) * dt
        shape = jax.vmap(traj.position)(ts)
        tau_ol = np.asarray(shape / rms * 1.6 * float(true.friction["Fs"][0]))
        log, xs = synthetic_log(plant, tau_ol, dt=dt, substeps=substeps, sensing=sensing,
                                key=jax.random.PRNGKey(seed))
        if not np.all(np.isfinite(log.q1)) or float(np.max(np.abs(log.q1))) > 50.0:
            raise RuntimeError(f"generate_log: open-loop run ran away (effects={effects}, seed={seed})")
        # the columns a rig logs (no exact velocity)
        log = dataclasses.replace(
            log, v=None, source=f"generate_log(effects={list(effects)}, seed={seed}, open_loop)")
        truth = _truth(effect_kw, true, seed, bits, noise_counts, mismatch, scale, 0.0, loop,
                       excitation, disturbance, extra)
        return GeneratedLog(log=log, effects=list(effects), truth=truth)
    if loop == "pd_rotor":
        controller = RotorPD(model=nominal.to_plant(), trajectory=traj, dt=dt)
    else:
        controller = CascadeController(
            model=nominal.to_plant(), gains=IDENT_GAINS, trajectory=traj, compensation=True,
            q2d_method="model", dt=dt, tau_max=2.0,
        )
    r = _simulate(plant, controller, t_final, sensing=sensing, key=jax.random.PRNGKey(seed),
                  substeps=substeps)
    if bool(r.metrics.diverged):
        raise RuntimeError(f"generate_log: closed loop diverged (effects={effects}, seed={seed})")
    truth = _truth(effect_kw, true, seed, bits, noise_counts, mismatch, scale,
                   float(jnp.ravel(r.metrics.saturation_fraction)[0]), loop, excitation,
                   disturbance, extra)
    q1_log = np.asarray(r.q1_meas)
    recorded = [k for k in effect_kw if EFFECTS[k].recording]
    if recorded:
        q1_log = _recorded_link(np.asarray(r.t), np.asarray(r.q1), sensing,
                                {k: effect_kw[k] for k in recorded}, rng)
    log = Log.from_arrays(t=np.asarray(r.t), tau=np.asarray(r.tau), q1=q1_log,
                          q2=np.asarray(r.q2_meas), q1d=np.asarray(r.q1d),
                          source=f"generate_log(effects={list(effects)}, seed={seed})")
    return GeneratedLog(log=log, effects=list(effects), truth=truth)


def _recorded_link(t: np.ndarray, q1: np.ndarray, sensing: Sensing,
                   effects: dict[str, dict[str, Any]], rng: np.random.Generator) -> np.ndarray:
    """The link channel [rad] (N, n) of a recorder with the ``recording`` effects ``effects``
    (name: keyword arguments, applied in order, ``AbstractEffect.recorded_link``) on the true
    link angle ``q1`` (N, n) sampled at ``t`` [s], with its own white noise and quantisation
    (``sensing``'s link encoder). The loop's controller still reads the true encoder, as on a
    rig where the link encoder is logged by a separate recorder (KUKA KR300)."""
    late = q1
    for name, kw in effects.items():
        late = EFFECTS[name].recorded_link(t, late, kw)
    noise = float(np.ravel(sensing.q1_noise)[0]) * rng.standard_normal(late.shape)
    return np.asarray(sensing.measure(jnp.asarray(late), sensing.q1_resolution,
                                      jnp.asarray(noise)))


def _truth(effect_kw, true, seed, bits, noise_counts, mismatch, scale, saturation, loop,
           excitation, disturbance, extra) -> dict[str, Any]:
    return {
        "effects": {k: {p: float(np.ravel(v)[0]) for p, v in kw.items()} for k, kw in effect_kw.items()},
        "plant": true.to_dict(), "seed": seed, "bits": bits, "noise_counts": noise_counts,
        "mismatch": mismatch, "scale": scale, "saturation_fraction": saturation, "loop": loop,
        "excitation": excitation, "disturbance": disturbance,
        "disturbance_params": {k: float(np.ravel(v)[0]) for e in extra
                               for k, v in e.params().items()} if extra else {},
    }

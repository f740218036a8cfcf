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
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.controller import CascadeController, CascadeGains
from jaxflex.effects import EFFECTS
from jaxflex.logs import Log
from jaxflex.presets import paper_params
from jaxflex.sensing import Sensing
from jaxflex.simulate import simulate_sampled
from jaxflex.trajectory import Multisine

#: Moderate magnitude ranges per effect (uniform draws; a sign is drawn for signed ones).
MODERATE: dict[str, dict[str, tuple[float, float]]] = {
    "asymmetric_friction": {"dF": (0.03, 0.06)},
    "gravity": {"mgl": (0.3, 0.6)},
    "cogging": {"A": (0.03, 0.06)},
    "motor_cogging": {"A": (0.02, 0.04)},
    "backlash": {"b": (0.004, 0.01)},
    "hardening_spring": {"K3": (300.0, 800.0)},
    "joint_damping": {"D": (0.02, 0.05)},
    "motor_friction": {"Fm": (0.02, 0.04), "bm": (0.01, 0.03)},
    "actuator_lag": {"T": (0.002, 0.004)},
    "torque_offset": {"offset": (0.03, 0.06)},
    "time_delay": {"T": (0.002, 0.004)},
}
#: Gentler gains than Table 3 for the identification experiment: with L1 = 200 1/s the loop
#: chatters at the 2 N m limit on a 0.15 rad multisine (measured: 99% of samples saturated).
IDENT_GAINS = CascadeGains(Ke=0.001, KD1=0.5, KD2=0.5, kv=2.0, L1=15.0, L2=6.0)

_simulate = eqx.filter_jit(simulate_sampled)

_SIGNED = {("asymmetric_friction", "dF"), ("torque_offset", "offset")}


@dataclasses.dataclass
class GeneratedLog:
    """A generated ``Log`` (columns t, tau, q1, q2, q1d; write it with
    ``jaxflex.logs.save_log``) plus the truth: hidden effect names and parameters, the true
    plant parameters, and the generator settings."""

    log: Log
    effects: list[str]
    truth: dict[str, Any]


def draw_effect(name: str, rng: np.random.Generator, scale: float = 1.0) -> dict[str, Any]:
    """Keyword arguments of an effect ``name`` with magnitudes drawn from ``MODERATE`` times
    ``scale`` (backlash's K is left None, to be set to the true plant's K)."""
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {sorted(EFFECTS)}")
    kw: dict[str, Any] = {}
    for p, (lo, hi) in MODERATE[name].items():
        v = scale * rng.uniform(lo, hi)
        if (name, p) in _SIGNED:
            v *= rng.choice([-1.0, 1.0])
        kw[p] = v
    if name == "cogging":
        kw["N"] = float(rng.choice([20.0, 30.0, 45.0]))
        kw["phi"] = rng.uniform(-math.pi, math.pi)
    if name == "motor_cogging":
        kw["N"] = float(rng.choice([60.0, 90.0, 150.0]))
        kw["phi"] = rng.uniform(-math.pi, math.pi)
    if name == "backlash":
        kw["K"] = None  # filled with the true plant's K by generate_log
    if name == "gravity":
        kw["q0"] = rng.uniform(-0.2, 0.2)
    return kw


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
) -> GeneratedLog:
    """Simulate one identification experiment with ``effects`` hidden in the true plant.

    seed: PRNG seed for magnitudes, mismatch, excitation and noise; bits: encoder counts per
    revolution = 2^bits on the link (rotor 50x finer); noise_counts: white angle noise std in
    encoder steps; mismatch: relative std of the true-vs-nominal parameter mismatch; scale:
    multiplies the effect magnitudes; rms [rad]: excitation RMS.
    """
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
        if name == "backlash":
            kw["K"] = true.plant["K"][0]
        effect_kw[name] = kw
    plant = true.to_plant(with_effects=False).with_effects(
        *(EFFECTS[k](**kw) for k, kw in effect_kw.items())
    )
    count = 6  # fixed so that every case shares one compiled simulation
    f_max = rng.uniform(1.0, 2.0)
    base = Multisine.schroeder(rms=rms * rng.uniform(0.8, 1.2), f_min=0.1, f_max=f_max, count=count)
    traj = Multisine(
        amplitudes=base.amplitudes, frequencies=base.frequencies,
        phases=base.phases + rng.uniform(-0.5, 0.5, count),
    )
    res = 2 * math.pi / 2**bits
    sensing = Sensing(
        q1_resolution=res, q2_resolution=res / 50.0, q1_noise=noise_counts * res,
        q2_noise=noise_counts * res / 50.0, velocity="filtered", dac_bits=12, dac_range=2.0,
    )
    controller = CascadeController(
        model=nominal.to_plant(), gains=IDENT_GAINS, trajectory=traj, compensation=True,
        q2d_method="model", dt=dt, tau_max=2.0,
    )
    r = _simulate(plant, controller, t_final, sensing=sensing, key=jax.random.PRNGKey(seed),
                  substeps=substeps)
    if bool(r.metrics.diverged):
        raise RuntimeError(f"generate_log: closed loop diverged (effects={effects}, seed={seed})")
    truth = {
        "effects": {k: {p: float(np.ravel(v)[0]) for p, v in kw.items()} for k, kw in effect_kw.items()},
        "plant": true.to_dict(),
        "seed": seed, "bits": bits, "noise_counts": noise_counts, "mismatch": mismatch,
        "scale": scale, "saturation_fraction": float(jnp.ravel(r.metrics.saturation_fraction)[0]),
    }
    log = Log.from_arrays(t=np.asarray(r.t), tau=np.asarray(r.tau), q1=np.asarray(r.q1_meas),
                          q2=np.asarray(r.q2_meas), q1d=np.asarray(r.q1d),
                          source=f"generate_log(effects={list(effects)}, seed={seed})")
    return GeneratedLog(log=log, effects=list(effects), truth=truth)

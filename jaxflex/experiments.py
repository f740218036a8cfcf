"""The paper's experiment section (section 6.5, Fig. 9-15) re-run in simulation.

Each experiment closes the sampled-data loop (1 kHz, zero-order hold) around the paper's plant
(Table 1, LuGre with SPEC's corrected Table 2) with the paper's gains (Table 3), with and
without friction compensation, and reports RMS and max link tracking error [rad] and torque RMS
[N m]. ``run_paper_experiments`` is what ``jaxflex reproduce`` and ``studies/reproduce_paper.py``
call; it writes figures and ``results.json``.

Sensing: the paper's 0.72 deg link encoder is coarse against its 0.05 rad motion; with the
paper's L1 = 200 1/s a quantisation step of the link angle moves the rotor set point by
L1 KD1 step / K ~ 0.4 rad, and the loop chatters at the DAC limits (measured in the q2d study).
The default here is therefore a rig with 16-bit encoders on both sides, filtered
differentiation for the velocities, a 12-bit DAC over +-2 N m and a 2 N m torque limit;
``sensing="ideal"`` uses exact measurements and ``sensing="paper"`` the 0.72 deg encoder.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from jaxflex.controller import CascadeController, CascadeGains
from jaxflex.params import Params, paper_params
from jaxflex.plant import FlexibleJointPlant
from jaxflex.simulate import Sensing, SimResult, paper_sensing, simulate_sampled, tracking_summary
from jaxflex.trajectory import Trajectory, paper_fast, paper_polynomial, paper_sinusoid

SENSING_CHOICES: tuple[str, ...] = ("rig", "ideal", "paper")


def rig_sensing(bits: int = 16, dac_range: float = 2.0) -> Sensing:
    """A rig with ``bits``-bit encoders on link and rotor (rotor behind a 1:50 gear), filtered
    velocities, 12-bit DAC over +-dac_range [N m]."""
    res = 2 * math.pi / 2**bits
    return Sensing(q1_resolution=res, q2_resolution=res / 50.0, velocity="filtered",
                   dac_bits=12, dac_range=dac_range)


def sensing_by_name(name: str) -> Sensing:
    """'rig' (default), 'ideal' (exact angles and velocities) or 'paper' (0.72 deg encoder)."""
    if name == "rig":
        return rig_sensing()
    if name == "ideal":
        return Sensing()
    if name == "paper":
        return paper_sensing()
    raise ValueError(f"sensing must be one of {SENSING_CHOICES}, got {name!r}")


PAPER_TASKS: dict[str, tuple[Callable[[], Trajectory], str]] = {
    "sinusoid": (paper_sinusoid, "Fig. 9-11: sinusoid, 0.05 rad, 0.5 Hz"),
    "polynomial": (paper_polynomial, "Fig. 12-14: rest-to-rest polynomial, +-0.07 rad"),
    "fast": (paper_fast, "Fig. 15: faster motion, +-0.5 rad moves in 0.6-0.9 s"),
}


def run_closed_loop(
    plant: FlexibleJointPlant, gains: CascadeGains, traj: Trajectory, *, compensation: bool,
    q2d_method: str = "model", sensing: Sensing | None = None, t_final: float = 10.0,
    tau_max: float = 2.0, dt: float = 1e-3, seed: int = 0, **controller_kw: Any,
) -> SimResult:
    """One sampled-data closed loop of the paper's controller around ``plant`` (the controller
    uses the same plant as its nominal model)."""
    c = CascadeController(
        model=plant, gains=gains, trajectory=traj, compensation=compensation,
        q2d_method=q2d_method, dt=dt, tau_max=tau_max, **controller_kw,
    )
    sim = eqx.filter_jit(lambda p, c, s, k: simulate_sampled(p, c, t_final, sensing=s, key=k))
    return sim(plant, c, sensing, jax.random.PRNGKey(seed))


def _summary(r: SimResult) -> dict[str, Any]:
    s = tracking_summary(r.e1, r.tau)
    s["diverged"] = bool(r.metrics.diverged)
    s["saturation_fraction"] = float(np.asarray(r.metrics.saturation_fraction).max())
    return s


def run_paper_experiments(
    out: str | Path, *, params: Params | None = None, sensing: str = "rig",
    q2d_method: str = "model", t_final: float = 10.0, compare_q2d: bool = True,
    tasks: list[str] | None = None, progress: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Run the paper's experiments and write figures and ``results.json`` to ``out``.

    Returns the results dict: per experiment, ``rms_error`` / ``max_error`` [rad] and
    ``tau_rms`` [N m], each with ``with_compensation`` and ``without_compensation``.
    With ``compare_q2d`` it also compares the three q2d-derivative options (SPEC section 3).
    ``tasks`` selects experiments by name (default: all of ``PAPER_TASKS``).
    """
    from jaxflex.plots.tracking import plot_q2d_comparison, plot_torque_friction, plot_tracking

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    params = paper_params() if params is None else params
    plant, gains = params.to_plant(), params.to_gains()
    sens = sensing_by_name(sensing)
    say = progress or (lambda s: None)
    results: dict[str, Any] = {
        "config": {
            "params": params.to_dict(), "sensing": sensing, "q2d_method": q2d_method,
            "dt": 1e-3, "t_final": t_final, "tau_max": 2.0,
        },
        "experiments": {},
    }
    t_start = time.perf_counter()
    unknown = set(tasks or ()) - set(PAPER_TASKS)
    if unknown:
        raise ValueError(f"unknown experiment(s) {sorted(unknown)}; known: {sorted(PAPER_TASKS)}")
    for name, (make, title) in PAPER_TASKS.items():
        if tasks is not None and name not in tasks:
            continue
        traj = make()
        runs = {}
        for comp in (False, True):
            key = "with_compensation" if comp else "without_compensation"
            say(f"[reproduce] {name}: {key.replace('_', ' ')} ...")
            runs[key] = run_closed_loop(plant, gains, traj, compensation=comp,
                                        q2d_method=q2d_method, sensing=sens, t_final=t_final)
        summ = {k: _summary(r) for k, r in runs.items()}
        figs = plot_tracking(runs, title, out / f"{name}_tracking.png")
        entry: dict[str, Any] = {"title": title, "figures": figs}
        for metric in ("rms_error", "max_error", "tau_rms", "diverged", "saturation_fraction"):
            entry[metric] = {k: summ[k][metric] for k in summ}
        if name == "sinusoid":
            entry["figures"] += plot_torque_friction(runs["with_compensation"], out / "sinusoid_torque_friction.png")
        results["experiments"][name] = entry
    if compare_q2d:
        say("[reproduce] q2d-derivative options ...")
        results["q2d_comparison"] = compare_q2d_methods(plant, gains, t_final=t_final)
        plot_q2d_comparison(results["q2d_comparison"], out / "q2d_comparison.png")
    results["wall_time_s"] = time.perf_counter() - t_start
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


def compare_q2d_methods(
    plant: FlexibleJointPlant, gains: CascadeGains, *, t_final: float = 10.0,
    sensings: tuple[str, ...] = ("ideal", "rig", "paper"),
    derivative_tcs: tuple[float, ...] = (0.002, 0.02),
) -> dict[str, Any]:
    """Tracking on the paper's sinusoid, with and without compensation, for each q2d option
    ('model', 'filtered' at each derivative filter time constant [s], 'reference') under each
    sensing. Returns nested dicts of RMS/max error [rad], torque RMS [N m] and divergence."""
    traj = paper_sinusoid()
    table: dict[str, Any] = {}
    variants = [("model", {}), ("reference", {})] + [
        (f"filtered_tc{tc * 1e3:g}ms", {"derivative_tc": tc}) for tc in derivative_tcs
    ]
    for sname in sensings:
        sens = sensing_by_name(sname)
        for label, kw in variants:
            method = label.split("_")[0]
            for comp in (False, True):
                r = run_closed_loop(plant, gains, traj, compensation=comp, q2d_method=method,
                                    sensing=sens, t_final=t_final, **kw)
                key = "with_compensation" if comp else "without_compensation"
                table.setdefault(sname, {}).setdefault(label, {})[key] = _summary(r)
    return table

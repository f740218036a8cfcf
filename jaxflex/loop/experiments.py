"""The paper's experiment section (section 6.5, Fig. 9-15) re-run in simulation.

Each experiment closes the sampled-data loop (1 kHz, zero-order hold) around the paper's plant
(Table 1, LuGre with the corrected Table 2 of docs/spec.md) with the paper's gains (Table 3), with and
without friction compensation, and reports RMS and max link tracking error [rad] and torque RMS
[N m]. ``run_paper_experiments`` returns the runs and numbers (``PaperExperiments``);
``jaxflex reproduce`` and ``studies/reproduce_paper.py`` write its figures and
``results.json`` with ``jaxflex.app.reports.write_paper_experiments``.

Sensing: the default is the paper's own rig (``sensing="paper"``: 0.72 deg link encoder, a
12-bit DAC over +-2 N m, a 2 N m torque limit) with the velocities from the model-based Kalman
filter (``estimator="kalman"``, ``jaxflex.core.estimator``), which ``studies/estimator_sensing.py``
selects: with the dirty derivative of the paper's text, the 0.72 deg steps make compensation
*worse* (the loop chatters at the torque limit), with the Kalman filter compensation lowers
the RMS error in every experiment. ``sensing="rig"`` (16-bit encoders) and ``"ideal"``
(exact) remain options; ``estimator="filtered"`` gives the dirty derivative.

Observer: by default the paper's gains with an observer leakage of
``jaxflex.io.presets.REPRODUCE_LEAK`` rad/s (``CascadeGains.leak``, ``studies/observer_leak.py``).
The paper's observer (leak 0) has no leakage at rest and, with the pre-sliding spring of the
friction, a growing ~3-4 Hz mode that saturates into a limit cycle; with the leakage the loop
at rest is stable. The compensated runs of the paper's observer are re-run beside the
default ones (``paper_observer`` in the results) so both are shown; and the paper's own
controller, its observer without leakage fed by the dirty derivative of its text
(``paper_own_observer``), is run and plotted too. Every figure title names the velocity
source and the observer it shows (``configuration_label``).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.core.controller import CascadeController, CascadeGains
from jaxflex.io.params import Params
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.io.presets import (
    SENSING_PRESETS,
    TRAJECTORIES,
    TRAJECTORY_DESCRIPTIONS,
    REPRODUCE_LEAK,
    paper_params,
    paper_sinusoid,
    sensing_fields,
    sensing_preset,
    trajectory_preset,
    with_estimator,
)
from jaxflex.core.sensing import AbstractSensing
from jaxflex.sim.simulate import SimResult, simulate_sampled, tracking_summary
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.trajectory import Trajectory
from jaxflex.io.progress import Progress, silent

COMPENSATION_KEYS: tuple[str, ...] = ("without_compensation", "with_compensation")
METRICS: tuple[str, ...] = ("rms_error", "max_error", "tau_rms", "diverged", "saturation_fraction",
                            "friction_error_rms")


def run_closed_loop(
    plant: FlexibleJointPlant, gains: CascadeGains, traj: Trajectory, *, compensation: bool,
    q2d_method: str = "model", sensing: AbstractSensing | None = None, t_final: float = 10.0,
    tau_max: float = 2.0, dt: float = 1e-3, seed: int = 0, **controller_kw: Any,
) -> SimResult:
    """One sampled-data closed loop of the paper's controller around ``plant`` (the controller
    uses the same plant as its nominal model)."""
    c = CascadeController(
        model=plant, gains=gains, trajectory=traj, compensation=compensation,
        q2d_method=q2d_method, dt=dt, tau_max=tau_max, **controller_kw,
    )
    return _closed_loop(plant, c, sensing, jax.random.PRNGKey(seed), float(t_final))


@persistent_jit
def _closed_loop(plant: FlexibleJointPlant, controller: CascadeController,
                 sensing: AbstractSensing | None, key: jax.Array, t_final: float) -> SimResult:
    """``simulate_sampled`` compiled once per structure (and kept across runs when the
    command's trace cache is on)."""
    return simulate_sampled(plant, controller, t_final, sensing=sensing, key=key)


def run_summary(r: SimResult) -> dict[str, Any]:
    """``METRICS`` of a saved run: RMS and max link error [rad], torque RMS [N m], whether it
    was lost, the fraction of samples at the torque limit and the RMS of F_hat - F [N m]."""
    s = tracking_summary(r.e1, r.tau)
    s["diverged"] = bool(r.metrics.diverged)
    s["saturation_fraction"] = float(np.asarray(r.metrics.saturation_fraction).max())
    # RMS of F_hat - F [N m] (without compensation F_hat = 0: the friction's own RMS)
    s["friction_error_rms"] = float(np.sqrt(np.mean((np.asarray(r.F_hat) - np.asarray(r.F)) ** 2)))
    return s


def configuration_label(velocity: str, leak: list[float], compensation: bool = True) -> str:
    """A figure's second title line: where the controller's velocities come from and which
    observer it runs.

    **Arguments:**

    - ``velocity``: the sensing's velocity source ("exact", "filtered", "kalman").
    - ``leak`` [rad/s]: the observer leakage per joint (0: the paper's observer).
    - ``compensation``: whether the runs shown compensate friction at all.

    **Returns:**

    E.g. "Kalman-filter velocities; observer with leak 0.2 rad/s".
    """
    vel = {"exact": "exact velocities", "filtered": "dirty-derivative velocities (the paper's)",
           "kalman": "Kalman-filter velocities"}.get(velocity, f"{velocity} velocities")
    if any(x > 0 for x in leak):
        vals = sorted(set(leak))
        obs = f"observer with leak {vals[0] if len(vals) == 1 else vals} rad/s"
    else:
        obs = "the paper's observer (no leak)"
    if not compensation:
        obs += " (runs without compensation have none)"
    return f"{vel}; {obs}"


@dataclasses.dataclass
class PaperExperiment:
    """One of the paper's experiments: its trajectory name and figure title, the saved runs
    keyed by ``COMPENSATION_KEYS`` and their summaries (``METRICS``: RMS and max link error
    [rad], torque RMS [N m], divergence, saturation fraction)."""

    name: str
    title: str
    runs: dict[str, SimResult]
    summaries: dict[str, dict[str, Any]]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the title and each metric by compensation key."""
        out: dict[str, Any] = {"title": self.title}
        for metric in METRICS:
            out[metric] = {k: self.summaries[k][metric] for k in self.summaries}
        return out


@dataclasses.dataclass
class PaperExperiments:
    """Result of ``run_paper_experiments``: the configuration, the experiments by trajectory
    name, the q2d-option comparison (None if not run), the wall time [s], the loop at rest
    (``rest_oscillation``), when the observer has leakage the paper's observer (leak 0)
    re-run with compensation (its summaries per experiment and its loop at rest), and the
    paper's own controller (leak 0, dirty-derivative velocities; None where the
    configuration is that already or the velocities are exact): the compensated run of each
    experiment (``paper_own_runs``) and its summaries (``paper_own_observer``)."""

    config: dict[str, Any]
    experiments: dict[str, PaperExperiment]
    q2d_comparison: dict[str, Any] | None
    wall_time_s: float
    rest: dict[str, Any] | None = None
    paper_observer: dict[str, Any] | None = None
    paper_own_observer: dict[str, Any] | None = None
    paper_own_runs: dict[str, SimResult] | None = None

    def params(self) -> Params:
        """The configuration run, as a parameter file: the parameters with the observer leak
        in ``gains`` and a ``controller`` section recording the sensing (its fields, with the
        velocity source used), q2d method, dt, torque limit, compensation and the tasks, so
        that ``jaxflex export --params`` writes the controller these experiments ran."""
        c = self.config
        d = dict(c["params"])
        d.pop("certificate", None)  # certified for other gains (the leak is added here)
        d["gains"] = {**d["gains"], "leak": list(c["observer_leak"])}
        d["controller"] = {
            "q2d_method": c["q2d_method"], "dt": c["dt"], "tau_max": c["tau_max"],
            "compensation": True, "sensing": c["sensing_fields"],
            "trajectory": list(self.experiments) or list(TRAJECTORIES)}
        return Params.from_dict(d)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready results (``results.json`` without the figure names)."""
        out: dict[str, Any] = {
            "config": self.config,
            "experiments": {k: e.to_dict() for k, e in self.experiments.items()},
        }
        if self.q2d_comparison is not None:
            out["q2d_comparison"] = self.q2d_comparison
        if self.rest is not None:
            out["rest"] = self.rest
        if self.paper_observer is not None:
            out["paper_observer"] = self.paper_observer
        if self.paper_own_observer is not None:
            out["paper_own_observer"] = self.paper_own_observer
        out["wall_time_s"] = self.wall_time_s
        return out


def run_paper_experiments(
    *, params: Params | None = None, sensing: str = "paper", estimator: str | None = "kalman",
    q2d_method: str = "model", leak: float | None = None,
    t_final: float = 10.0, compare_q2d: bool = True, tasks: list[str] | None = None,
    progress: Progress | None = None,
) -> PaperExperiments:
    """Run the paper's experiments (``tasks``: trajectory names, default all of
    ``jaxflex.io.presets.TRAJECTORIES``) with and without compensation under the sensing preset
    ``sensing`` with its velocities from ``estimator`` ("kalman", "filtered", or None for the
    preset's own; ignored where the preset has exact velocities), ``t_final`` [s] per run; with ``compare_q2d`` also compare the three
    q2d-derivative options (docs/spec.md section 3). ``leak`` [rad/s]: the observer leakage
    (``CascadeGains.leak``); None takes the parameter file's, or ``REPRODUCE_LEAK`` for the
    paper's parameters (whose file records none); 0 is the paper's observer. With leak > 0 the
    compensated runs and the loop at rest are repeated with the paper's observer
    (``PaperExperiments.paper_observer``). ``progress`` (``jaxflex.io.progress.Progress``)
    gets a line as each run starts; None: silent. Writes nothing (see
    ``jaxflex.app.reports.write_paper_experiments``).
    """
    if leak is not None and not (np.isfinite(leak) and leak >= 0):
        raise ValueError(f"leak must be a finite number >= 0 rad/s, got {leak}")
    own = params is None
    params = paper_params() if params is None else params
    plant, gains = params.to_plant(), params.to_gains()
    if leak is None and own:
        leak = REPRODUCE_LEAK
    if leak is not None:
        gains = eqx.tree_at(lambda g: g.leak, gains,
                            jnp.full(gains.n, float(leak), gains.Ke.dtype))
    leak_used = [float(x) for x in np.broadcast_to(np.asarray(gains.leak), (gains.n,))]
    sens = with_estimator(sensing_preset(sensing), estimator)
    say = lambda s: (progress or silent)(0, None, s)
    config = {
        "params": params.to_dict(), "sensing": sensing, "estimator": sens.velocity,
        "q2d_method": q2d_method, "observer_leak": leak_used,
        "dt": 1e-3, "t_final": t_final, "tau_max": 2.0,
    }
    config["label"] = configuration_label(sens.velocity, leak_used)
    config["sensing_fields"] = sensing_fields(sens)
    t_start = time.perf_counter()
    unknown = set(tasks or ()) - set(TRAJECTORIES)
    if unknown:
        raise ValueError(f"unknown experiment(s) {sorted(unknown)}; known: {list(TRAJECTORIES)}")
    experiments: dict[str, PaperExperiment] = {}
    for name in TRAJECTORIES:
        if tasks is not None and name not in tasks:
            continue
        traj = trajectory_preset(name)
        runs = {}
        for key in COMPENSATION_KEYS:
            say(f"[reproduce] {name}: {key.replace('_', ' ')} ...")
            runs[key] = run_closed_loop(plant, gains, traj,
                                        compensation=key == "with_compensation",
                                        q2d_method=q2d_method, sensing=sens, t_final=t_final)
        experiments[name] = PaperExperiment(
            name=name, title=f"{TRAJECTORY_DESCRIPTIONS[name]}\n{config['label']}", runs=runs,
            summaries={k: run_summary(r) for k, r in runs.items()})
    say("[reproduce] the loop at rest ...")
    rest = rest_oscillation(plant, gains, sensing=sens, q2d_method=q2d_method)
    paper_obs = None
    if any(x > 0 for x in leak_used):
        say("[reproduce] the paper's observer (no leakage), with compensation ...")
        paper_gains = eqx.tree_at(lambda g: g.leak, gains, jnp.zeros_like(gains.Ke))
        paper_obs = {"observer_leak": [0.0] * gains.n, "experiments": {}}
        for name in experiments:
            r = run_closed_loop(plant, paper_gains, trajectory_preset(name), compensation=True,
                                q2d_method=q2d_method, sensing=sens, t_final=t_final)
            paper_obs["experiments"][name] = {"with_compensation": run_summary(r)}
        paper_obs["rest"] = rest_oscillation(plant, paper_gains, sensing=sens,
                                             q2d_method=q2d_method, keys=("with_compensation",))
    own_sens = with_estimator(sensing_preset(sensing), "filtered")
    own_runs = own = None
    if own_sens.velocity == "filtered" and (any(x > 0 for x in leak_used)
                                            or sens.velocity != "filtered"):
        say("[reproduce] the paper's own controller (no leakage, dirty derivative), with "
            "compensation ...")
        own_gains = eqx.tree_at(lambda g: g.leak, gains, jnp.zeros_like(gains.Ke))
        own_runs = {name: run_closed_loop(plant, own_gains, trajectory_preset(name),
                                          compensation=True, q2d_method=q2d_method,
                                          sensing=own_sens, t_final=t_final)
                    for name in experiments}
        own = {"velocity": "filtered", "observer_leak": [0.0] * gains.n,
               "label": configuration_label("filtered", [0.0] * gains.n),
               "experiments": {name: {"with_compensation": run_summary(r)}
                               for name, r in own_runs.items()}}
    q2d = None
    if compare_q2d:
        say("[reproduce] q2d-derivative options ...")
        q2d = compare_q2d_methods(plant, gains, t_final=t_final)
    return PaperExperiments(config=config, experiments=experiments, q2d_comparison=q2d,
                            wall_time_s=time.perf_counter() - t_start, rest=rest,
                            paper_observer=paper_obs, paper_own_observer=own,
                            paper_own_runs=own_runs)


def rest_oscillation(
    plant: FlexibleJointPlant, gains: CascadeGains, *, sensing: AbstractSensing,
    q2d_method: str = "model", t_final: float = 6.0, tail: float = 3.0, hold: float = 0.003,
    keys: tuple[str, ...] = COMPENSATION_KEYS,
) -> dict[str, Any]:
    """Does the loop oscillate at rest, and why? Per compensation setting: the link error of
    the loop held at a reference of ``hold`` rad for ``t_final`` s (by default between two
    counts of the paper's link encoder, so that its quantisation excites the loop), its RMS over the last ``tail`` s [rad] and the frequency [Hz]
    and amplitude [rad] of its spectral peak there; and the modes of the loop linearised at
    rest (``jaxflex.loop.analyse.analyse_loop``: spectral radius, the slowest modes with frequency,
    damping and the states taking part), which say whether an oscillation is a growing mode
    of the design (radius > 1) or forced by quantisation. ``keys``: the compensation settings
    to run (``COMPENSATION_KEYS`` or a subset)."""
    from jaxflex.loop.analyse import analyse_loop
    from jaxflex.core.trajectory import Multisine

    rest_ref = Multisine(amplitudes=np.zeros((1, plant.n)), frequencies=np.ones((1, plant.n)),
                         phases=np.zeros((1, plant.n)), offset=np.full(plant.n, hold))
    out: dict[str, Any] = {"t_final": t_final, "tail": tail, "hold": hold}
    for key in keys:
        comp = key == "with_compensation"
        r = run_closed_loop(plant, gains, rest_ref, compensation=comp, q2d_method=q2d_method,
                            sensing=sensing, t_final=t_final)
        e = np.asarray(r.e1)[:, 0]
        dt = float(np.asarray(r.t)[1] - np.asarray(r.t)[0])
        last = e[-int(round(tail / dt)):]
        spec = np.abs(np.fft.rfft(last - last.mean())) * 2 / len(last)
        f = np.fft.rfftfreq(len(last), dt)
        k = int(np.argmax(spec[1:]) + 1)
        modes = analyse_loop(plant, gains, q2d_method=q2d_method, compensation=comp,
                             sensing=sensing, n_modes=3).rest
        out[key] = {"rms_error_tail": float(np.sqrt(np.mean(last**2))),
                    "peak_hz": float(f[k]), "peak_amplitude": float(spec[k]),
                    **modes.to_dict()}
    return out


def compare_q2d_methods(
    plant: FlexibleJointPlant, gains: CascadeGains, *, t_final: float = 10.0,
    sensings: tuple[str, ...] = SENSING_PRESETS,
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
        sens = sensing_preset(sname)
        for label, kw in variants:
            method = label.split("_")[0]
            for comp in (False, True):
                r = run_closed_loop(plant, gains, traj, compensation=comp, q2d_method=method,
                                    sensing=sens, t_final=t_final, **kw)
                key = "with_compensation" if comp else "without_compensation"
                table.setdefault(sname, {}).setdefault(label, {})[key] = run_summary(r)
    return table

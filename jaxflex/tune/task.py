"""What gains are tuned for (``TuneTask``: references, sensing, limits, cost weights) and
its simulated cost (``tracking_cost``) and runs (``simulate_task``, ``max_link_speed``)."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxflex.core.controller import CascadeController, CascadeGains
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.io.presets import rig_sensing
from jaxflex.core.sensing import AbstractSensing
from jaxflex.sim.simulate import SimResult, simulate_sampled
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.trajectory import Trajectory


def reference_speed(trajectories: Sequence[Trajectory], t_final: float, dt: float) -> float:
    """Fastest reference link speed max |q1d'| [rad/s] of ``trajectories`` over [0, t_final] s,
    sampled every ``dt`` s."""
    ts = jnp.linspace(0.0, t_final, int(t_final / dt) + 1)
    return max(float(jnp.max(jnp.abs(tr.sample(ts, order=1)[:, 1]))) for tr in trajectories)


def certify_speed(trajectories: Sequence[Trajectory], t_final: float, dt: float,
                  velocity_factor: float) -> float:
    """Speed [rad/s] up to which gains for these references must be certified:
    ``velocity_factor`` x the fastest reference speed (at least 1e-3 rad/s)."""
    return velocity_factor * max(reference_speed(trajectories, t_final, dt), 1e-3)


@dataclasses.dataclass(frozen=True)
class TuneTask:
    """What the gains are tuned for.

    trajectories: references (each for the plant's n joints); t_final [s] per run; sensing;
    tau_max [N m] controller torque limit; q2d_method "model" or "filtered" ("reference"
    diverges with the paper's gains); dt [s] sample period; substeps plant steps per sample;
    seed of the measurement noise (common random numbers for all candidates); torque_weight
    [rad^2/(N m)^2] weight of the mean squared torque in the cost (default 1e-6 prices 1 N m
    RMS like 1 mrad RMS error; with 0 the search drifts to gains that chatter at the torque
    limit); velocity_factor: the
    certificate must hold up to velocity_factor x the fastest reference speed;
    min_rest_damping: if set, every mode of the closed loop linearised at rest (plant,
    observer, controller, velocity estimator: ``jaxflex.loop.analyse.rest_damping``) must have at
    least this damping ratio, so that no oscillation persists at rest (None: not required).
    """

    trajectories: tuple[Trajectory, ...]
    t_final: float = 2.0
    sensing: AbstractSensing = dataclasses.field(default_factory=rig_sensing)
    tau_max: float = 2.0
    q2d_method: str = "model"
    dt: float = 1e-3
    substeps: int = 10
    seed: int = 0
    torque_weight: float = 1e-6
    velocity_factor: float = 1.5
    min_rest_damping: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.trajectories, Trajectory):
            object.__setattr__(self, "trajectories", (self.trajectories,))
        object.__setattr__(self, "trajectories", tuple(self.trajectories))
        if not self.trajectories:
            raise ValueError("TuneTask: needs at least one trajectory")
        if not self.t_final > 0:
            raise ValueError(f"TuneTask: t_final must be > 0 s, got {self.t_final}")
        if not self.tau_max > 0:
            raise ValueError(f"TuneTask: tau_max must be > 0 N m, got {self.tau_max}")
        if self.q2d_method not in ("model", "filtered", "reference"):
            raise ValueError(f"TuneTask: unknown q2d_method {self.q2d_method!r}")
        if self.torque_weight < 0:
            raise ValueError(f"TuneTask: torque_weight must be >= 0, got {self.torque_weight}")
        if not self.velocity_factor >= 1:
            raise ValueError(
                f"TuneTask: velocity_factor must be >= 1, got {self.velocity_factor}")
        if self.min_rest_damping is not None and not -1 < self.min_rest_damping < 1:
            raise ValueError("TuneTask: min_rest_damping must be in (-1, 1) (a damping ratio), "
                             f"got {self.min_rest_damping}")

    def settings(self) -> tuple:
        """The static (hashable) settings of the cost, for caching compiled functions."""
        return (self.t_final, self.tau_max, self.q2d_method, self.dt, self.substeps, self.seed,
                self.torque_weight)

    @classmethod
    def from_settings(cls, trajectories, sensing, settings: tuple) -> "TuneTask":
        """Inverse of ``settings`` (velocity_factor, which the cost does not use, at default)."""
        t_final, tau_max, q2d, dt, substeps, seed, tw = settings
        return cls(tuple(trajectories), t_final, sensing, tau_max, q2d, dt, substeps, seed, tw)

    def reference_speed(self) -> float:
        """Fastest reference link speed max |q1d'| [rad/s] over the task's trajectories."""
        return reference_speed(self.trajectories, self.t_final, self.dt)

    def certify_speed(self) -> float:
        """Speed [rad/s] up to which tuned gains must be certified."""
        return certify_speed(self.trajectories, self.t_final, self.dt, self.velocity_factor)

    def controller(self, model: FlexibleJointPlant, gains: CascadeGains,
                   trajectory: Trajectory) -> CascadeController:
        """The cascade controller of this task for ``gains``."""
        return CascadeController(model=model, gains=gains, trajectory=trajectory,
                                 q2d_method=self.q2d_method, dt=self.dt, tau_max=self.tau_max)


def tracking_cost(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask,
                  model: FlexibleJointPlant | None = None,
                  sensing: AbstractSensing | None = None) -> tuple[Float[Array, ""], dict[str, Array]]:
    """Cost [rad^2] of ``gains`` on ``task``: mean over trajectories and joints of the squared
    RMS link error plus torque_weight x mean squared RMS torque; +inf when a run diverged.

    ``plant`` is the true plant, ``model`` the controller's (default: the plant). Pure; jit and
    grad friendly. Returns (cost, {"rms_error", "tau_rms", "saturation", "diverged"}).
    """
    model = plant if model is None else model
    sensing = task.sensing if sensing is None else sensing
    key = jax.random.PRNGKey(task.seed)
    mets = [
        simulate_sampled(plant, task.controller(model, gains, tr), task.t_final,
                         substeps=task.substeps, sensing=sensing, key=key, save=False,
                         unroll_substeps=False).metrics  # a gradient runs through it
        for tr in task.trajectories
    ]
    rms = jnp.stack([m.rms_error for m in mets])
    tau = jnp.stack([m.tau_rms for m in mets])
    diverged = jnp.any(jnp.stack([m.diverged for m in mets]))
    cost = jnp.mean(rms**2) + task.torque_weight * jnp.mean(tau**2)
    ok = jnp.isfinite(cost) & ~diverged
    cost = jnp.where(ok, cost, jnp.inf)
    aux = {"rms_error": rms, "tau_rms": tau,
           "saturation": jnp.stack([m.saturation_fraction for m in mets]), "diverged": diverged}
    return cost, aux


def simulate_task(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask,
                  model: FlexibleJointPlant | None = None) -> list[SimResult]:
    """Saved closed-loop runs of ``gains`` on each trajectory of ``task`` (for reports)."""
    model = plant if model is None else model
    key = jax.random.PRNGKey(task.seed)
    return [_simulate_saved(plant, task.controller(model, gains, tr), task.t_final,
                            task.substeps, task.sensing, key)
            for tr in task.trajectories]


@persistent_jit
def _simulate_saved(plant, controller, t_final, substeps, sensing, key):
    return simulate_sampled(plant, controller, t_final, substeps=substeps, sensing=sensing,
                            key=key)


def max_link_speed(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask,
                   model: FlexibleJointPlant | None = None) -> float:
    """Fastest link speed max |q1'| [rad/s] reached on the task (inf if a run diverged)."""
    runs = simulate_task(plant, gains, task, model)
    if any(bool(r.metrics.diverged) for r in runs):
        return float("inf")
    return max(float(jnp.max(jnp.abs(r.dq1))) for r in runs)

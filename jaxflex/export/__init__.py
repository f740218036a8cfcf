"""Export the certified controller to standalone Python (numpy) or C99.

The single source of truth is the JAX controller as the sampled-data loop runs it
(``SampledController``: ``jaxflex.core.controller.CascadeController`` with its configuration's
velocity source -- the dirty derivative, or the Kalman filter of ``jaxflex.core.estimator`` with
its state and the DAC it predicts through -- observer leak, q2d method, torque limit, n
joints). Its ``init`` and ``step`` are traced once with ``jax.make_jaxpr``
(``tracing.trace``) and the jaxprs are translated by one translator with two dialects
(``jaxflex.export.translate``): straight-line Python (``pygen.generate_source``) and C99
(``cgen.generate_c``; ``native`` compiles and loads it through ctypes). A change to the JAX
controller changes both exports. Both also take the reference from the rig at each step
(q1d and its first four derivatives) besides following the recorded trajectory.

``rig_controller`` builds the controller a parameter file's ``controller`` section
certifies and refuses, naming the entry, what the export cannot run (``ExportError``).
``check_parity`` closes the sampled-data loop in JAX under the configuration's own sensing
(``simulate_sampled``: quantised, noisy encoders, DAC), feeds the sensed angles to the
exported controller and to the JAX controller compiled without XLA's fusion (each primitive
its own kernel, the arithmetic of ``jax.disable_jit``), each carrying its own state, and
returns the largest torque differences, also against the jitted loop.
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.export.atoms import UnsupportedPrimitive
from jaxflex.export.program import (
    REFERENCE_ROWS,
    ExportError,
    SampledController,
    check_exportable,
    describe,
    describe_sensing,
    parity_sensing,
    rig_controller,
    sampled_controller,
)
from jaxflex.export.pygen import generate_source
from jaxflex.export.tracing import Traced, trace

__all__ = [
    "ExportError", "PARITY_RELATIVE", "ParityResult", "REFERENCE_ROWS", "SampledController",
    "Traced", "UnsupportedPrimitive", "broadcast_trajectory", "build_controller", "check_exportable",
    "check_parity", "describe", "describe_sensing", "export_controller", "generate_source",
    "load_module", "parity_ok", "parity_sensing", "parity_tolerance", "rig_controller",
    "sampled_controller", "trace",
]


def build_controller(
    params: Any = None,
    trajectory: Any = None,
    *,
    q2d_method: str | None = None,
    dt: float | None = None,
    tau_max: float | None = None,
    compensation: bool | None = None,
    **controller_kw: Any,
):
    """A ``CascadeController`` from a parameter set (``Params``, a docs/spec.md section 7 mapping, a
    path, or None for the paper's) and a trajectory (a name of
    ``jaxflex.io.presets.TRAJECTORIES`` or a ``Trajectory``).

    The configuration -- ``q2d_method``, sample period ``dt`` [s], torque limit ``tau_max``
    [N m], ``compensation`` and the trajectory name -- is what the parameter file's
    ``controller`` section records (the configuration its gains were tuned for); an argument
    left at None takes the recorded value, or ``jaxflex.io.presets.DEFAULT_CONTROLLER``'s where
    nothing is recorded (1 kHz, the rig's 2 N m, "model", compensation on, the sinusoid). An
    argument that contradicts the section raises ``ParamsError``. The model ignores the
    file's effects (as the controller does); n-joint trajectories are broadcast from the
    one-joint tasks.
    """
    import jax.numpy as jnp

    from jaxflex.core.controller import CascadeController
    from jaxflex.io.params import Params, load_params
    from jaxflex.io.presets import controller_config, paper_params, trajectory_preset
    from jaxflex.core.trajectory import Trajectory

    if params is None:
        params = paper_params()
    elif isinstance(params, (str, os.PathLike)):
        params = load_params(params)
    elif isinstance(params, dict):
        params = Params.from_dict(params)
    if trajectory is not None and not isinstance(trajectory, (str, Trajectory)):
        raise ValueError("trajectory must be a trajectory name or a Trajectory")
    cfg = controller_config(params, {
        "q2d_method": q2d_method, "dt": dt, "tau_max": tau_max, "compensation": compensation,
        "trajectory": trajectory if isinstance(trajectory, str) else None,
    })
    traj = trajectory_preset(cfg.trajectory_name) if not isinstance(trajectory, Trajectory) \
        else trajectory
    n = params.n
    q = traj.position(jnp.asarray(0.0))
    if q.shape[-1] != n:
        if q.shape[-1] != 1:
            raise ValueError(f"trajectory is for {q.shape[-1]} joints, parameters for {n}")
        traj = broadcast_trajectory(traj, n)
    return CascadeController(
        model=params.to_plant(with_effects=False), gains=params.to_gains(), trajectory=traj,
        compensation=cfg.compensation, q2d_method=cfg.q2d_method, dt=cfg.dt,
        tau_max=cfg.tau_max, **controller_kw,
    )


def broadcast_trajectory(traj: Any, n: int) -> Any:
    """A one-joint reference task for n joints (every joint the same motion).

    **Arguments:**

    - ``traj``: a one-joint ``Sinusoid`` or ``RestToRest``.
    - ``n``: joints.

    **Returns:**

    The trajectory with every array leaf of shape (n,) (waypoints (k, n)).

    **Raises:**

    ``ValueError`` for another trajectory type.
    """
    import jax

    from jaxflex.core.trajectory import RestToRest, Sinusoid

    if isinstance(traj, Sinusoid):
        return jax.tree_util.tree_map(lambda a: a * np.ones(n), traj)
    if isinstance(traj, RestToRest):
        w = traj.waypoints if traj.waypoints.ndim == 2 else traj.waypoints[:, None]
        return RestToRest(waypoints=w * np.ones((1, n)), durations=traj.durations, t0=traj.t0)
    raise ValueError(f"cannot broadcast a one-joint {type(traj).__name__} to {n} joints")


def load_module(source_or_path: str | os.PathLike, name: str = "jaxflex_exported_controller") -> types.ModuleType:
    """Import an exported controller from a file path or from its source text."""
    if isinstance(source_or_path, os.PathLike) or (
        isinstance(source_or_path, str) and "\n" not in source_or_path
    ):
        path = Path(source_or_path)
        if not path.exists():
            raise FileNotFoundError(f"controller file not found: {path}")
        spec = importlib.util.spec_from_file_location(name, path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    mod = types.ModuleType(name)
    mod.__file__ = f"<{name}>"
    exec(compile(source_or_path, mod.__file__, "exec"), mod.__dict__)
    return mod


def export_controller(controller: Any, path: str | os.PathLike, description: str = "",
                      traced: Traced | None = None) -> str:
    """Write the Python export of ``controller`` to ``path`` (atomically).

    **Arguments:**

    - ``controller``: a ``SampledController`` (``rig_controller``) or a ``CascadeController``.
    - ``path``: the ``.py`` file to write.
    - ``description``: the module docstring's first line.
    - ``traced``: the programs already traced (``trace``).

    **Returns:**

    The source.
    """
    src = generate_source(controller, description=description, traced=traced)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(src)
    os.replace(tmp, path)
    return src


@dataclass
class ParityResult:
    """Exported vs JAX torques over one closed-loop run.

    ``max_abs_diff`` [N m]: largest |tau_export - tau_jax| of the commanded torques, against
    the jitted closed loop (``tau_jax``: its torques, or where the sensing has a DAC, the
    commands of the jitted controller replayed on the loop's angles, which the DAC turns
    into the loop's torques). ``applied_diff`` [N m]: largest difference of the torques
    after the DAC against the loop's. At the ``worst`` samples (largest differences) the
    JAX step is also evaluated op by op (``jax.disable_jit``) from the JAX controller's
    state: ``eager_diff`` is the largest |exported - JAX op by op| there (the export's own
    error) and ``jit_floor`` the largest |JAX op by op - JAX jitted| (what XLA's compilation
    -- fusion, its own exp/expm1 -- changes, amplified by the law's sensitivity).
    ``jit_drift`` [N m]: the largest difference of the JAX controller against itself over
    the run, compiled once as one loop and once batched (``vmap``, as sweeps run it): what
    XLA's choices (fused multiply-adds, order of sums) change, carried by the filter and
    observer states from sample to sample, the floor of any re-implementation.
    ``unfused_diff`` [N m]: largest |tau_export - tau_unfused| over the whole run, where
    ``tau_unfused`` is the JAX controller replayed on the same sensed angles, compiled with
    XLA's fusion pass off (``UNFUSED``: every primitive its own kernel, no fused
    multiply-adds across primitives -- the arithmetic of ``jax.disable_jit``), each side
    carrying its own state: the program as written, the export's reference. Also the torque
    series (N, n), the measured angles fed to both, the run's RMS tracking error [rad] and
    what was run (``config``).
    """

    max_abs_diff: float
    eager_diff: float
    jit_floor: float
    worst: np.ndarray
    tau_jax: np.ndarray
    tau_export: np.ndarray
    q1_meas: np.ndarray
    q2_meas: np.ndarray
    rms_error: float
    applied_diff: float = 0.0
    jit_drift: float = 0.0
    config: str = ""
    unfused_diff: float = math.inf
    tau_unfused: np.ndarray | None = None

    def __str__(self) -> str:
        return (f"parity over {self.tau_jax.shape[0]} samples ({self.config}): largest "
                f"|tau_export - tau_jax unfused| = {self.unfused_diff:.3e} N m; "
                f"|tau_export - tau_jax jitted| = {self.max_abs_diff:.3e} N m (after the DAC "
                f"{self.applied_diff:.3e} N m); at the {self.worst.size} worst samples "
                f"exported vs JAX op-by-op {self.eager_diff:.3e} N m, JAX op-by-op vs JAX jit "
                f"{self.jit_floor:.3e} N m; JAX against itself batched {self.jit_drift:.3e} "
                f"N m (tau range {np.min(self.tau_jax):.3f} .. "
                f"{np.max(self.tau_jax):.3f} N m; RMS tracking error {self.rms_error:.3e} rad)")


def check_parity(
    controller: Any, module: Any = None, *, t_final: float = 10.0,
    plant: Any = None, sensing: Any = None, seed: int = 0, n_worst: int = 10,
    reference: bool = False,
) -> ParityResult:
    """Run the closed loop in JAX, then the exported controller on its sensed angles.

    **Arguments:**

    - ``controller``: a ``SampledController`` (run under its own sensing) or a
      ``CascadeController`` (run under ``sensing``, default ``parity_sensing``).
    - ``module``: the exported controller (a Python module from ``load_module``, or a C
      library from ``jaxflex.export.native.load_c``); None: the Python export, generated.
    - ``t_final`` [s]: length of the run; ``plant``: the true plant (default the
      controller's model); ``seed``: the encoders' noise; ``n_worst``: samples evaluated op
      by op.
    - ``reference``: give the exported controller the reference at each sample (its
      ``ref`` input: q1d and four derivatives, as the loop hands them to the JAX controller)
      instead of letting it evaluate the recorded one.

    **Returns:**

    A ``ParityResult`` (docs/spec.md section 7.1: ``unfused_diff`` within
    ``parity_tolerance``, 1e-12 N m or 1e-14 of the largest torque, in float64).

    **Raises:**

    ``ValueError`` when a ``SampledController`` is given a ``sensing`` (its own is run);
    ``ExportError`` for a configuration the export cannot run.
    """
    import jax

    if isinstance(controller, SampledController) and sensing is not None:
        raise ValueError("check_parity: a SampledController runs under its own sensing; build "
                         "it for another one with rig_controller(..., sensing=...)")
    with jax.enable_x64(True):
        sc = sampled_controller(controller, sensing)
        if module is None:
            module = load_module(generate_source(sc))
        plant = sc.controller.model if plant is None else plant
        r = _closed_loop(plant, sc.controller, sc.sensing, jax.random.PRNGKey(seed),
                         float(t_final))
        q1m, q2m, ts = np.asarray(r.q1_meas), np.asarray(r.q2_meas), np.asarray(r.t)
        rms = float(np.sqrt(np.mean(np.asarray(r.e1) ** 2)))
        refs = np.asarray(_reference_samples(sc.controller.trajectory, ts))
        states, tau_cmd = _replay(sc, ts, q1m, q2m, refs if reference else None)
        _, tau_batched = _replay(sc, ts, q1m, q2m, refs if reference else None, batch=2)
        _, tau_unfused = _replay(sc, ts, q1m, q2m, refs if reference else None, unfused=True)
        jit_drift = float(np.max(np.abs(tau_batched - tau_cmd)))
        tau_loop = np.asarray(r.tau)
        tau_jax = tau_loop if not sc.sensing.dac_bits else tau_cmd
    ctrl = module.Controller()
    ctrl.reset()
    n = tau_jax.shape[1]
    tau_np = np.empty_like(tau_jax)
    for k in range(ts.shape[0]):
        ref = refs[k] if reference else None
        if n == 1:
            tau_np[k, 0] = ctrl.step(float(ts[k]), float(q1m[k, 0]), float(q2m[k, 0]), ref=ref)
        else:
            tau_np[k] = ctrl.step(ts[k], q1m[k], q2m[k], ref=ref)
    with jax.enable_x64(True):
        applied = np.asarray(sc.sensing.dac(jax.numpy.asarray(tau_np)))
    per = np.max(np.abs(tau_np - tau_jax), axis=1)
    finite = np.all(np.isfinite(tau_jax))
    diff = float(np.max(per)) if finite else math.inf
    unfused_diff = (float(np.max(np.abs(tau_np - tau_unfused)))
                    if np.all(np.isfinite(tau_unfused)) else math.inf)
    applied_diff = float(np.max(np.abs(applied - tau_loop))) if finite else math.inf
    worst = np.argsort(per)[::-1][:n_worst]
    eager_diff = floor = 0.0
    names = getattr(module, "STATE_NAMES", None)
    if names is not None and len(names) != len(states):
        # an export of another configuration (another state): no step from JAX's state
        worst, eager_diff, floor = worst[:0], math.inf, math.inf
    with jax.enable_x64(True), jax.disable_jit():
        st_def = jax.tree_util.tree_structure(sc.init(0.0, q1m[0], q2m[0]))
        for k in worst:
            st = jax.tree_util.tree_unflatten(st_def, [np.asarray(x[k]) for x in states])
            S = tuple(float(v) for x in states for v in np.ravel(x[k]))
            qs = [*map(float, q1m[k]), *map(float, q2m[k])]
            if reference:
                _, out = sc.with_reference(refs[k], ts[k]).step(st, ts[k], q1m[k], q2m[k])
                _, tau_x = ctrl._step_ref(S, float(ts[k]), *qs, *map(float, refs[k].ravel()))
            else:
                _, out = sc.step(st, ts[k], q1m[k], q2m[k])
                _, tau_x = ctrl._step(S, float(ts[k]), *qs)
            tau_e = np.asarray(out.tau)
            eager_diff = max(eager_diff, float(np.max(np.abs(np.asarray(tau_x) - tau_e))))
            floor = max(floor, float(np.max(np.abs(tau_e - tau_jax[k]))))
    config = (f"{describe(sc)}; under {describe_sensing(sc.sensing)}"
              + ("; reference given at each sample" if reference else ""))
    return ParityResult(diff, eager_diff, floor, worst, tau_jax, tau_np, q1m, q2m, rms,
                        applied_diff, jit_drift, config, unfused_diff, tau_unfused)


PARITY_RELATIVE: float = 1e-14
"""Parity's tolerance relative to the run's largest torque, where that exceeds the absolute
1e-12 N m (docs/spec.md section 7.1): about 45 units in the last place. Above 100 N m, 1e-12
N m is within a few units in the last place of the torque, which an export agrees to only
where it rounds bit for bit as XLA does; a coupled arm's linear solve (LAPACK's LU in JAX,
written-out elimination in the export) and XLA's shape-dependent order of sums in a dot do
not."""


def parity_tolerance(result: ParityResult, tol: float = 1e-12,
                     rel: float = PARITY_RELATIVE) -> float:
    """The torque difference [N m] parity allows on a run.

    **Arguments:**

    - ``result``: a ``check_parity`` result.
    - ``tol`` [N m]: the absolute tolerance (docs/spec.md: 1e-12).
    - ``rel``: the tolerance relative to the run's largest |tau| (``PARITY_RELATIVE``).

    **Returns:**

    ``max(tol, rel * max |tau_jax|)``; ``tol`` where the loop's torques are not finite.
    """
    tau = np.abs(result.tau_jax)
    return max(tol, rel * float(np.max(tau))) if np.all(np.isfinite(tau)) else tol


def parity_ok(result: ParityResult, tol: float = 1e-12, floor_factor: float = 4.0,
              rel: float = PARITY_RELATIVE) -> bool:
    """The check's verdict.

    **Arguments:**

    - ``result``: a ``check_parity`` result.
    - ``tol`` [N m]: the absolute parity tolerance (docs/spec.md: 1e-12).
    - ``floor_factor``: how far above XLA's own floor the difference may be.
    - ``rel``: the tolerance relative to the largest torque where that is larger
      (``parity_tolerance``).

    **Returns:**

    True when the export equals the un-fused JAX controller to the tolerance over the run
    (``unfused_diff``) and the jitted one to the tolerance, or within ``floor_factor`` times
    what XLA's compilation itself changes (``jit_floor`` at the worst samples, ``jit_drift``
    over the run).
    """
    d = result.max_abs_diff
    floor = max(result.jit_floor, result.jit_drift)
    tol = parity_tolerance(result, tol, rel)
    return bool(result.unfused_diff <= tol and (d <= tol or d <= floor_factor * floor))


def _closed_loop(plant: Any, controller: Any, sensing: Any, key: Any, t_final: float):
    """The jitted sampled-data loop of the parity run (compiled once per configuration),
    from rest at q1d(0) with the springs holding the links' weight (q2 = q1 + K^-1 G(q1),
    eq. 3 at rest; q2 = q1 without gravity)."""
    return _jitted()["loop"](plant, controller, sensing, key, t_final)


def _rest(plant: Any, q1: Any) -> Any:
    """The plant at rest at link angles q1 [rad], the springs holding G(q1)."""
    return plant.init_state(q1=q1, q2=q1 + plant.links.gravity(q1) / plant.K)


def _reference_samples(trajectory: Any, ts: np.ndarray) -> Any:
    """q1d and its first four derivatives at every sample time, (N, 5, n)."""
    return _jitted()["refs"](trajectory, ts)


def _replay(sc: SampledController, ts: np.ndarray, q1m: np.ndarray, q2m: np.ndarray,
            refs: np.ndarray | None = None, batch: int = 0, unfused: bool = False):
    """The JAX controller alone (init + step in a ``lax.scan``) on recorded angles (and, if
    given, the reference at each sample): the state leaves before each sample and the
    commanded torques. ``batch`` > 0: the same run ``batch`` times under ``vmap`` (another
    compilation of the same program; the first copy is returned). ``unfused``: compiled
    with ``UNFUSED``."""
    fns = _jitted()
    if unfused:
        states, taus = fns["replay_unfused"](sc, ts, q1m, q2m, refs)
        return [np.asarray(x) for x in states], np.asarray(taus)
    if batch:
        tile = lambda a: None if a is None else np.stack([a] * batch)
        fn = fns["replay_batched"] if refs is None else fns["replay_batched_ref"]
        states, taus = fn(sc, ts, tile(q1m), tile(q2m), tile(refs))
        return [np.asarray(x[0]) for x in states], np.asarray(taus[0])
    states, taus = fns["replay"](sc, ts, q1m, q2m, refs)
    return [np.asarray(x) for x in states], np.asarray(taus)


_JITTED: dict[str, Any] = {}

UNFUSED: dict[str, str] = {"xla_disable_hlo_passes": "fusion"}
"""XLA options of the un-fused reference: without the fusion pass every primitive is its own
kernel (a single-op loop), so LLVM has no multiply feeding an add in one kernel to contract
into a fused multiply-add, and the compiled program rounds as ``jax.disable_jit`` evaluates
it, primitive by primitive (XLA's own dot, exp, sin; at a sample, equal bit for bit)."""


def _jitted() -> dict[str, Any]:
    """The parity run's compiled functions, made once (JAX is imported on first use)."""
    if _JITTED:
        return _JITTED
    import equinox as eqx
    import jax

    from jaxflex.sim.simulate import REFERENCE_ORDER, simulate_sampled

    def replay(c, ts, q1m, q2m, refs):
        at = (lambda t, R: c) if refs is None else (lambda t, R: c.with_reference(R, t))
        st0 = at(ts[0], None if refs is None else refs[0]).init(ts[0], q1m[0], q2m[0])

        def body(st, inp):
            t, q1, q2, R = inp
            new, out = at(t, R).step(st, t, q1, q2)
            return new, (jax.tree_util.tree_leaves(st), out.tau)

        rs = ts if refs is None else refs  # a placeholder when no reference is given
        return jax.lax.scan(body, st0, (ts, q1m, q2m, rs))[1]

    _JITTED.update(
        loop=eqx.filter_jit(lambda p, c, s, k, T: simulate_sampled(
            p, c, T, sensing=s, key=k,
            x0=_rest(p, c.trajectory.position(jax.numpy.zeros((), float))))),
        refs=eqx.filter_jit(lambda tr, ts: jax.vmap(
            lambda t: tr.derivatives(t, order=REFERENCE_ORDER))(ts)),
        replay=eqx.filter_jit(replay),
        replay_unfused=eqx.filter_jit(replay, compiler_options=UNFUSED),
        replay_batched=eqx.filter_jit(eqx.filter_vmap(replay, in_axes=(None, None, 0, 0, None))),
        replay_batched_ref=eqx.filter_jit(eqx.filter_vmap(replay, in_axes=(None, None, 0, 0, 0))),
    )
    return _JITTED


def main_check(argv: list[str] | None = None) -> int:  # pragma: no cover - convenience
    """``python -m jaxflex.export``: export the paper's controller and print the parity."""
    c = build_controller()
    print(check_parity(c))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main_check())

"""Batched Monte Carlo runs: sample, build, simulate under ``vmap``, reduce per chunk.

Sample i is drawn from ``fold_in(PRNGKey(seed), i)``, so a sample's parameters and noise do not
depend on the chunk size, the number of devices or the number of processes: sharded,
unsharded and multi-process runs of the same spread give the same numbers.

Memory: one chunk of ``chunk_size`` samples is simulated at a time; per chunk only the link
error at the band grid (``band_dt``) lives on the device, and it is folded into fixed-size
histograms before the next chunk (``jaxflex.sweep.summary.Accumulator``). Nothing is stored
per controller sample. Per sample only its parameters and five metrics are kept (and only when
``keep_samples``), so peak memory does not grow with the number of samples.

Scale-out: each chunk is laid out over the local devices with a ``NamedSharding`` on a 1-D
``Mesh`` (axis ``"batch"``). On a CPU JAX has one device unless told otherwise, so a sweep
would use one core: ``use_all_cores`` (called by the ``jaxflex`` command before JAX starts)
exposes every core as a host device; with ``jax.distributed`` initialised, process p runs the chunks
c = p, p + P, ... on its own devices and the accumulators are combined with
``multihost_utils.process_allgather`` at the end (the same code runs on one process).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import math
import os
import re
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxflex.core.controller import CascadeController
from jaxflex.io.params import build_plant
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.io.presets import trajectory_preset
from jaxflex.core.sensing import Sensing
from jaxflex.sim.simulate import simulate_sampled
from jaxflex.io.progress import Bar, Progress, silent
from jaxflex.sweep.spec import SweepSpec
from jaxflex.sweep.summary import Accumulator, SweepResult, band_bins


_HOST_FLAG = "--xla_force_host_platform_device_count"


def use_all_cores(n: int | None = None) -> int:
    """Expose ``n`` CPU cores (default: every core this process may run on) to JAX as ``n``
    host devices, so that ``run_sweep`` (which shards each chunk over ``jax.local_devices()``)
    runs on all of them. Call it right after ``import jax``, before any JAX computation:

        import jax
        from jaxflex.sweep.engine import use_all_cores
        use_all_cores()

    A device count already chosen (``XLA_FLAGS`` holding ``--xla_force_host_platform_device_
    count``, or ``jax_num_cpu_devices`` set) is kept. Once JAX's backends have started the
    count can no longer change; the call then changes nothing. Only the CPU platform is
    affected (a GPU keeps its own devices). Returns the number of host devices JAX will use
    (or uses).

    Raises ``ValueError`` if ``n < 1``.
    """
    if n is not None and n < 1:
        raise ValueError(f"use_all_cores: n must be >= 1, got {n}")
    m = re.search(_HOST_FLAG + r"=(\d+)", os.environ.get("XLA_FLAGS", ""))
    if m:
        return int(m.group(1))
    current = int(jax.config.jax_num_cpu_devices)
    if current > 0:
        return current
    want = n if n is not None else _usable_cores()
    try:
        jax.config.update("jax_num_cpu_devices", want)
    except RuntimeError:  # backends already started: the count is fixed
        return len(jax.devices("cpu"))
    return want


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def sample_parameters(spec: SweepSpec, index: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(theta, noise_key) of sample ``index``: theta (d,) in ``spec.labels`` order.

    A draw with Fs < Fc breaks the LuGre constraint Fs >= Fc (docs/spec.md section 2): its Fc
    and Fs columns are redrawn (rejection sampling, up to ``_MAX_REDRAWS`` times), so the
    sweep samples the spread conditioned on Fs >= Fc; the other columns keep their first draw.
    ``SweepSpec.fs_below_fc_possible`` says whether this can happen, and a spread where Fs is
    always below Fc is refused when it is read.
    """
    key = jax.random.fold_in(jax.random.PRNGKey(spec.seed), index)
    k_theta, k_noise = jax.random.split(key)
    if not spec.columns:
        return jnp.zeros((0,), jnp.result_type(float)), k_noise

    def draw(k):
        keys = jax.random.split(k, len(spec.columns))
        post = None if spec.posterior is None else spec.posterior.sample(
            jax.random.fold_in(k, _POSTERIOR_STREAM))
        return jnp.stack([post[int(c.dist.a)] if c.dist.kind == "posterior" else c.dist.sample(kk)
                          for c, kk in zip(spec.columns, keys)])

    theta = draw(k_theta)
    pairs = spec.fs_fc_pairs() if spec.fs_below_fc_possible() else []
    if pairs:
        redo = jnp.asarray([i for p in pairs for i in (p[0], p[2]) if i >= 0])

        def violated(th):
            bad = jnp.asarray(False)
            for i_fc, fc0, i_fs, fs0 in pairs:
                fc = th[i_fc] if i_fc >= 0 else fc0
                fs = th[i_fs] if i_fs >= 0 else fs0
                bad = bad | (fs < fc)
            return bad

        def body(carry):
            th, i = carry
            new = draw(jax.random.fold_in(k_theta, i + 1))
            return th.at[redo].set(new[redo]), i + 1

        theta, _ = jax.lax.while_loop(
            lambda c: violated(c[0]) & (c[1] < _MAX_REDRAWS), body, (theta, jnp.asarray(0)))
    return theta, k_noise


_POSTERIOR_STREAM = 2**20  # the identification's posterior draws from its own key stream
_MAX_REDRAWS = 100  # a spread with P(Fs >= Fc) of 1e-2 leaves 1 sample in e^100 unresolved


def build_models(
    spec: SweepSpec, theta: jax.Array
) -> tuple[FlexibleJointPlant, CascadeController, Sensing, jax.Array]:
    """True plant, controller (nominal model and gains) and sensing of one sample.

    ``sample_parameters`` redraws pairs with Fs < Fc; should one remain after its redraws
    (LuGre needs Fs >= Fc, docs/spec.md section 2), Fs is raised to Fc and the returned
    ``fs_raised`` (bool) says so; the summary counts these samples (``fs_raised_to_fc``).
    Traceable in ``theta`` (the modules' value checks skip traced values).
    """
    n = spec.n
    nom = spec.nominal
    vals: dict[str, dict[str, jax.Array]] = {
        "plant": {k: jnp.asarray(v, float) for k, v in nom.plant.items()},
        "friction": {k: jnp.asarray(v, float) for k, v in nom.friction.items()},
        "sensing": {k: jnp.full((n,), spec.sensing[k]) for k in
                    ("q1_noise", "q2_noise", "q1_resolution", "q2_resolution")},
        "limits": {"tau_max": jnp.full((n,), spec.tau_max)},
        "effects": {},
    }
    eff: dict[str, dict[str, Any]] = {
        k: {p: jnp.broadcast_to(jnp.asarray(v, float), (n,)) for p, v in kw.items()}
        for k, kw in spec.effects.items()
    }
    for i, c in enumerate(spec.columns):
        parts = c.name.split(".")
        if parts[0] == "effects":
            cur = eff[parts[1]].get(parts[2], jnp.zeros((n,)))
            eff[parts[1]][parts[2]] = cur.at[c.joint].set(theta[i])
        else:
            vals[parts[0]][parts[1]] = vals[parts[0]][parts[1]].at[c.joint].set(theta[i])
    fr = vals["friction"]
    fs_raised = jnp.any(fr["Fs"] < fr["Fc"])
    fr["Fs"] = jnp.maximum(fr["Fs"], fr["Fc"])
    plant = build_plant(vals["plant"], fr, eff)
    model = nom.to_plant(with_effects=False)
    ctrl = CascadeController(
        model=model, gains=nom.to_gains(), trajectory=trajectory_preset(spec.trajectory),
        compensation=spec.compensation, q2d_method=spec.q2d_method, dt=spec.dt,
        tau_max=vals["limits"]["tau_max"],
    )
    s = vals["sensing"]
    sensing = Sensing(
        q1_resolution=s["q1_resolution"], q2_resolution=s["q2_resolution"],
        q1_noise=s["q1_noise"], q2_noise=s["q2_noise"], velocity=spec.sensing["velocity"],
        dac_bits=spec.sensing["dac_bits"], dac_range=spec.sensing["dac_range"],
    )
    return plant, ctrl, sensing, fs_raised


def is_noisy(spec: SweepSpec) -> bool:
    """Whether the sensors of some sample add noise (then each sample's noise key is used)."""
    return any(c.name in ("sensing.q1_noise", "sensing.q2_noise") for c in spec.columns) or (
        spec.sensing["q1_noise"] > 0 or spec.sensing["q2_noise"] > 0)


def sample_models(spec: SweepSpec, index: jax.Array) -> tuple[
        jax.Array, FlexibleJointPlant, CascadeController, Sensing, jax.Array, jax.Array]:
    """Everything sample ``index`` runs with: (theta, true plant, controller, sensing, noise
    key, fs_raised), from ``sample_parameters`` and ``build_models``; vmap over ``index`` for
    a batch of plants (``jaxflex.tune.robust`` tunes over one)."""
    theta, k_noise = sample_parameters(spec, index)
    plant, ctrl, sensing, fs_raised = build_models(spec, theta)
    return theta, plant, ctrl, sensing, k_noise, fs_raised


#: samples per trip of a batched closed loop's time loop on a GPU (``loop_unrolls``). One H100,
#: 1000 x 10 s at 3 substeps, float64, controller steps/s (compilation): 1 per trip 4.24e7
#: (7.5 s), 2: 5.8e7 (9.6 s), 4: 6.8e7 (13.5 s), 8: 7.2e7 (21 s); 1e5 samples 2.08e9 at 1,
#: 2.78e9 at 8. Below ~1e7 samples the compilation outweighs the gain on a first run, hence 1;
#: set it before the first sweep of a process to trade compilation for throughput.
GPU_SCAN_UNROLL = 1


def loop_unrolls(controller: CascadeController) -> tuple[bool, int]:
    """How a batched (vmapped) closed loop with ``controller`` lays out its loops:
    ``(unroll_substeps, unroll)`` for ``simulate_sampled``, decided by JAX's default backend.

    On a CPU: the substep loop unrolled for "filtered" q2d derivatives, rolled for "model"
    and "reference", one sample per trip of the time loop. Unrolled substeps fuse across
    substeps, but XLA:CPU then copies the control law into every substep kernel that reads
    the torque; the rolled loop takes the law once. The law is cheap with filtered q2d
    derivatives and a jvp tower with "model"/"reference" (1000 x 10 s, float64, two host
    devices, controller steps/s, unrolled against rolled: "model" 0.94e7 vs 1.2e7 at 3
    substeps, 3.4e6 vs 4.7e6 at 10; "filtered" 1.7e7 vs 1.46e7 at 3, 6.4e6 vs 5.5e6 at 10).

    On a GPU every trip of a loop waits for the host to read the loop's condition, so the
    substeps are unrolled and ``GPU_SCAN_UNROLL`` samples run per trip of the time loop
    (``studies/bench_sweep.py --gpu``). The same numbers either way, to rounding."""
    if jax.default_backend() != "cpu":
        return True, GPU_SCAN_UNROLL
    return controller.q2d_method == "filtered", 1


def simulate_sample(spec: SweepSpec, index: jax.Array) -> dict[str, jax.Array]:
    """Closed loop of one sample: parameters, metrics (worst joint) and the band-grid error.

    Keys: theta (d,); rms_error, max_error [rad]; tau_rms [N m]; saturation_fraction;
    diverged; fs_raised; e1_band (T, n) [rad] link error every ``band_dt`` s.
    """
    theta, plant, ctrl, sensing, k_noise, fs_raised = sample_models(spec, index)
    r = simulate_sampled(
        plant, ctrl, spec.t_final, substeps=spec.substeps, sensing=sensing,
        key=k_noise if is_noisy(spec) else None, save=True,
        **dict(zip(("unroll_substeps", "unroll"), loop_unrolls(ctrl))),
    )
    # only metrics and e1 are used below: jit's dead-code elimination drops the other
    # saved trajectories, so save=True costs one (N, n) array per sample of the chunk.
    m = r.metrics
    return {
        "theta": theta, "rms_error": jnp.max(m.rms_error), "max_error": jnp.max(m.max_error),
        "tau_rms": jnp.max(m.tau_rms), "saturation_fraction": jnp.max(m.saturation_fraction),
        "diverged": m.diverged, "fs_raised": fs_raised, "e1_band": r.e1[:: spec.band_stride],
    }


_CHUNK_FNS: dict[str, Callable] = {}


def make_chunk_fn(spec: SweepSpec, float32: bool = False) -> Callable[[jax.Array, jax.Array], dict[str, jax.Array]]:
    """A jitted function (indices (B,), valid (B,)) -> per-sample results and the chunk's
    band histogram (n, T, nbins) over valid, non-diverged samples.

    Cached per spec content (and x64 mode), so repeated sweeps of one spread compile once.
    """
    key = spec.cache_key() + str(float32)
    if key not in _CHUNK_FNS:
        _CHUNK_FNS[key] = _make_chunk_fn(spec)
    return _CHUNK_FNS[key]


def _make_chunk_fn(spec: SweepSpec) -> Callable[[jax.Array, jax.Array], dict[str, jax.Array]]:
    edges = band_bins()

    def chunk(idx: jax.Array, valid: jax.Array) -> dict[str, jax.Array]:
        out = jax.vmap(lambda i: simulate_sample(spec, i))(idx)
        e = out.pop("e1_band")  # (B, T, n)
        _B, T, n = e.shape
        w = (valid & ~out["diverged"]).astype(jnp.int32)
        b = jnp.clip(jnp.searchsorted(edges, jnp.arcsinh(e / _BAND_SCALE)) - 1, 0, edges.size - 2)
        flat = (jnp.arange(n)[None, None, :] * T + jnp.arange(T)[None, :, None]) * (edges.size - 1) + b
        hist = jnp.zeros(n * T * (edges.size - 1), jnp.int32).at[flat.reshape(-1)].add(
            jnp.broadcast_to(w[:, None, None], flat.shape).reshape(-1)
        )
        out["band_hist"] = hist.reshape(n, T, edges.size - 1)
        return out

    return jax.jit(chunk)


_BAND_SCALE = 1e-6  # [rad]; band histograms are uniform in asinh(e1 / _BAND_SCALE)


@dataclasses.dataclass
class SweepCheckpoint:
    """The state of a sweep after some chunks: ``run`` identifies the run (spec, sample
    count, chunk size, precision, kept summaries) so that a resume continues the same one;
    ``done`` lists the chunk numbers folded into ``acc``."""

    run: str
    done: list[int]
    acc: Accumulator


def _swallowed(frame: Any) -> bool:
    """Whether an exception raised in ``frame`` would be swallowed by Python: the frame or one
    it was called from is a garbage-collector callback (``gc.callbacks``, e.g. JAX's
    ``_xla_gc_callback``) or a ``__del__``, where CPython prints "Exception ignored in ..."
    with a traceback and goes on."""
    codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


@contextlib.contextmanager
def _deferred_interrupts():
    """SIGINT/SIGTERM raise ``KeyboardInterrupt`` except inside ``state["critical"]``
    sections (folding a chunk in, checkpointing), where they only set ``state["stop"]``, so
    an interrupt never leaves a half-added chunk; likewise where Python would swallow the
    exception (``_swallowed``: a signal that arrived during a garbage-collector callback
    printed a traceback there, and the sweep stopped at the next chunk all the same)."""
    state = {"stop": False, "critical": False}
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handler(signum, frame):
        state["stop"] = True
        if not state["critical"] and not _swallowed(frame):
            raise KeyboardInterrupt

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield state
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def run_sweep(
    spec: SweepSpec,
    *,
    samples: int | None = None,
    chunk_size: int = 256,
    shard: bool = True,
    keep_samples: bool = True,
    n_worst: int = 10,
    progress: Progress | bool = True,
    float32: bool = False,
    resume: SweepCheckpoint | None = None,
    on_chunk: Callable[[SweepCheckpoint], None] | None = None,
) -> SweepResult | None:
    """Run the Monte Carlo sweep of ``spec`` and return its summary.

    ``samples`` overrides ``spec.samples``; ``chunk_size`` samples run together (rounded up
    to a multiple of the local device count when ``shard``); ``keep_samples`` keeps each
    sample's parameters and metrics (a few dozen bytes per sample; needed for Spearman
    sensitivities and the CSV); ``n_worst`` worst cases are kept with their parameters.
    ``float32`` runs the loop in single precision (faster on CPU/GPU; see the benchmark
    for its accuracy). With ``jax.distributed`` initialised, each process runs its share of
    the chunks and every process returns the combined result.

    Interrupts (single process): Ctrl-C or SIGTERM stop the sweep between chunks; the result
    then summarises the chunks done, with ``summary["partial"] = True`` (``None`` if no chunk
    was done). ``on_chunk`` gets a ``SweepCheckpoint`` after each chunk (the CLI saves it);
    ``resume`` continues from one (refused if it belongs to another run). ``progress``
    (``jaxflex.io.progress.Progress``) gets each chunk done of this process's chunks; True:
    a tqdm bar, False: silent.
    """
    n_samples = spec.samples if samples is None else int(samples)
    if n_samples < 1:
        raise ValueError(f"run_sweep: samples must be >= 1, got {n_samples}")
    if chunk_size < 1:
        raise ValueError(f"run_sweep: chunk_size must be >= 1, got {chunk_size}")
    devices = jax.local_devices()
    nd = len(devices) if shard else 1
    chunk_size = int(math.ceil(min(chunk_size, n_samples) / nd) * nd)
    n_chunks = math.ceil(n_samples / chunk_size)
    pid, nproc = jax.process_index(), jax.process_count()
    mine = list(range(pid, n_chunks, nproc))
    sharding = NamedSharding(Mesh(np.array(devices[:nd]), ("batch",)), PartitionSpec("batch")) if shard else None

    run_id = json.dumps({"spec": spec.to_dict(), "samples": n_samples, "chunk_size": chunk_size,
                         "float32": float32, "keep_samples": keep_samples, "n_worst": n_worst},
                        sort_keys=True, default=str)
    if resume is not None:
        if nproc > 1:
            raise ValueError("run_sweep: resume is for single-process sweeps")
        if resume.run != run_id:
            raise ValueError("run_sweep: the checkpoint belongs to another sweep (spread, "
                             "samples, chunk size, precision or kept summaries differ)")
        acc, done = resume.acc, list(resume.done)
    else:
        acc, done = Accumulator(spec, keep_samples=keep_samples, n_worst=n_worst), []
    todo = [c for c in mine if c not in set(done)]
    count0 = acc.count
    ctx = jax.enable_x64(False) if float32 else contextlib.nullcontext()
    t0, c0 = time.perf_counter(), time.process_time()
    t_compile = 0.0
    interrupted = False
    stops = _deferred_interrupts() if nproc == 1 else contextlib.nullcontext({"stop": False, "critical": False})
    with ctx, stops as state:
        bar = None
        report: Progress = progress if callable(progress) else silent
        try:
            fn = make_chunk_fn(spec, float32)
            if progress is True:
                bar = report = Bar(f"sweep[{pid}/{nproc}]" if nproc > 1 else "sweep",
                                   unit="chunk", initial=len(mine) - len(todo))
            for k, c in enumerate(todo):
                idx = np.arange(c * chunk_size, (c + 1) * chunk_size)
                valid = idx < n_samples
                idx = np.where(valid, idx, 0).astype(np.uint32)
                a_idx, a_valid = jnp.asarray(idx), jnp.asarray(valid)
                if sharding is not None:
                    a_idx, a_valid = jax.device_put(a_idx, sharding), jax.device_put(a_valid, sharding)
                out = jax.device_get(fn(a_idx, a_valid))
                if k == 0:
                    t_compile = time.perf_counter() - t0
                state["critical"] = True
                acc.add(idx[valid], {k2: (v if k2 == "band_hist" else v[valid]) for k2, v in out.items()})
                done.append(c)
                if on_chunk is not None:
                    on_chunk(SweepCheckpoint(run_id, list(done), acc))
                state["critical"] = False
                report(len(mine) - len(todo) + k + 1, len(mine), "")
                if state["stop"]:
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            if nproc > 1:
                raise
            interrupted = True
        finally:
            if bar is not None:
                bar.close()
    if nproc > 1:
        acc = acc.allgather()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if acc.count == 0:
        return None
    res = acc.result()
    res.summary["partial"] = interrupted
    res.summary["chunks_done"] = len(done)
    res.summary["chunks"] = n_chunks
    # controller steps run in this call (a resumed run counts only its own chunks)
    steps = (acc.count - count0 if nproc == 1 else n_samples) * round(spec.t_final / spec.dt)
    res.timing = {
        "wall_s": wall, "cpu_s": cpu, "first_chunk_s": t_compile, "chunk_size": chunk_size, "chunks": n_chunks,
        "devices": nd, "processes": nproc, "controller_steps": steps,
        "steps_per_s": steps / wall if nproc == 1 else None,
        "steps_per_cpu_s": steps / cpu if nproc == 1 else None, "float32": float32,
    }
    return res


def nominal_run(spec: SweepSpec) -> dict[str, np.ndarray]:
    """The nominal closed loop (each sampled quantity at its nominal value, or at its
    distribution's centre where it has none; no noise): t [s], e1 (N, n) [rad]."""
    theta = jnp.asarray([c.nominal_or_center for c in spec.columns], float)
    plant, ctrl, sensing, _ = build_models(spec, theta)
    r = eqx.filter_jit(lambda p, c, s: simulate_sampled(p, c, spec.t_final, substeps=spec.substeps, sensing=s))(
        plant, ctrl, sensing
    )
    return {"t": np.asarray(r.t), "e1": np.asarray(r.e1), "rms_error": float(np.max(np.asarray(r.metrics.rms_error)))}

"""Fixed-period hardware loop around an exported controller, with rig protections.

The loop (``run_loop``) reads encoders, computes the torque, protects it and writes it, once
per period (default 1 kHz), on a fixed time grid: it sleeps until shortly before each
deadline and busy-waits the rest (``time.perf_counter``). Protections a rig needs:

- torque limit: the command is clipped to +-``tau_limit`` [N m];
- guard: non-finite or out-of-range angles (|q| > ``q_limit`` rad) or a non-finite torque
  command zero torque and stop the loop (``stop_on_fault``) or skip the sample;
- watchdog: a sample whose torque is written after its deadline is a miss; the loop stops after
  ``max_consecutive_misses`` misses in a row;
- clean stop: whatever happens (end of run, fault, exception, SIGINT/SIGTERM) zero torque is
  written in a ``finally`` before the I/O is closed.

The log has the docs/spec.md section 6 columns (t, tau, q1, q2, and q1d when the controller has a
reference), written as CSV, so it feeds ``identify`` and ``discover`` directly.

``SimulatedRig`` is an ``RigIO`` whose plant (``jaxflex.sim.step.plant_step``, jitted) runs in
a separate process and advances by one period per written torque (lock-step in plant time),
so that the loop is exercised as it would be on hardware.

This module needs only numpy and the standard library at import time; JAX is imported by the
simulated rig's child process only.
"""

from __future__ import annotations

import abc
import dataclasses
import math
import multiprocessing.connection as mp_connection
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

import numpy as np

from jaxflex.io.logs import Log, save_log


class RigIO(abc.ABC):
    """Encoder and motor-driver interface of a rig with ``n`` joints."""

    n: int = 1

    @abc.abstractmethod
    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Link and rotor angles (q1, q2) [rad], each of shape (n,)."""

    @abc.abstractmethod
    def write(self, tau: np.ndarray) -> None:
        """Command the motor torques tau [N m], shape (n,)."""

    def close(self) -> None:
        """Release the hardware (called after the final zero-torque write)."""
        return None


class ControllerLike(Protocol):
    """What the loop needs from a controller (an exported ``Controller``)."""

    def reset(self) -> None: ...

    def step(self, t: float, q1: Any, q2: Any) -> Any: ...


@dataclass
class LoopConfig:
    """Loop settings: ``rate`` [Hz]; ``duration`` [s]; ``tau_limit`` [N m]; ``q_limit`` [rad]
    (guard on |q1|, |q2|); ``max_consecutive_misses`` (watchdog); ``realtime`` False runs
    without waiting (lock-step: timing does not affect the result); ``busy_wait`` [s] spent
    spinning before each deadline instead of sleeping; ``stop_on_fault``: stop at the first
    guard trip (else command zero for that sample and continue)."""

    rate: float = 1000.0
    duration: float = 5.0
    tau_limit: float = 2.0
    q_limit: float = 10.0
    max_consecutive_misses: int = 10
    realtime: bool = True
    busy_wait: float = 2e-4
    stop_on_fault: bool = True

    def __post_init__(self) -> None:
        if not (self.rate > 0 and math.isfinite(self.rate)):
            raise ValueError(f"LoopConfig: rate must be > 0 Hz, got {self.rate}")
        if not self.duration > 0:
            raise ValueError(f"LoopConfig: duration must be > 0 s, got {self.duration}")
        if not self.tau_limit > 0:
            raise ValueError(f"LoopConfig: tau_limit must be > 0 N m, got {self.tau_limit}")
        if not self.q_limit > 0:
            raise ValueError(f"LoopConfig: q_limit must be > 0 rad, got {self.q_limit}")
        if self.max_consecutive_misses < 1:
            raise ValueError("LoopConfig: max_consecutive_misses must be >= 1")

    @property
    def period(self) -> float:
        """Sample period [s]."""
        return 1.0 / self.rate


@dataclass
class LoopResult:
    """What happened: the log columns (t (N,), tau, q1, q2, q1d (N, n); q1d None without a
    reference), per-sample compute time [s] (controller step), lateness of each sample's
    start after its scheduled time [s], the deadline misses, guard trips, why it stopped, and
    the log written (None: no log asked for, or fewer than 2 samples)."""

    t: np.ndarray
    tau: np.ndarray
    q1: np.ndarray
    q2: np.ndarray
    q1d: np.ndarray | None
    compute_time: np.ndarray
    lateness: np.ndarray
    misses: int
    max_consecutive_misses: int
    faults: list[str] = field(default_factory=list)
    stop_reason: str = "completed"
    log_path: str | None = None

    @property
    def samples(self) -> int:
        """Number of samples run."""
        return int(self.t.shape[0])

    def timing_summary(self) -> dict[str, float]:
        """Median, 99th percentile and max of compute time and start lateness [us]."""
        def stats(a):
            if a.size == 0:
                return {"median_us": math.nan, "p99_us": math.nan, "max_us": math.nan}
            return {"median_us": float(np.median(a) * 1e6),
                    "p99_us": float(np.percentile(a, 99) * 1e6), "max_us": float(np.max(a) * 1e6)}
        return {"compute": stats(self.compute_time), "lateness": stats(self.lateness),
                "misses": self.misses, "samples": self.samples}


def _sleep_until(deadline: float, busy: float) -> None:
    """Sleep until ``busy`` seconds before ``deadline`` (perf_counter), then spin."""
    remaining = deadline - time.perf_counter() - busy
    if remaining > 0:
        time.sleep(remaining)
    while time.perf_counter() < deadline:
        pass


def run_loop(
    io: RigIO, controller: ControllerLike, config: LoopConfig | None = None,
    log_path: str | os.PathLike | None = None, reference: np.ndarray | None = None,
) -> LoopResult:
    """Run ``controller`` around ``io`` at ``config.rate`` for ``config.duration`` seconds.

    Sample k is scheduled at t_k = k / rate after the start; the controller gets t_k (the
    nominal sample time, as in the simulation) and the angles read at that sample.
    ``reference`` (samples, rows, n): the rig's reference at each sample (q1d and its
    derivatives, as an exported controller's ``step(..., ref=...)`` takes them), given to
    the controller instead of its recorded trajectory and logged as q1d; None: the
    controller follows its own.

    Raises ``ValueError`` (before the loop starts) for a ``reference`` of the wrong shape.

    Every way out ends at zero torque and returns a result whose log (if ``log_path``) is
    written: completion, a guard trip (NaN or out-of-range angle, non-finite torque), the
    watchdog (overrun), SIGINT/SIGTERM (Ctrl-C; stops after the current sample), a
    controller that raises, or a rig that fails (e.g. its process died); ``stop_reason``
    says which. Exceptions are reported there, not raised.
    """
    cfg = LoopConfig() if config is None else config
    n = int(getattr(io, "n", 1))
    N = int(round(cfg.duration * cfg.rate))
    period = cfg.period
    ref = getattr(controller, "reference", None)
    if reference is not None:
        reference = np.asarray(reference, dtype=float)
        if reference.ndim != 3 or reference.shape[0] < N or reference.shape[2] != n:
            raise ValueError(f"run_loop: reference must be (samples >= {N}, rows, {n}), got "
                             f"shape {reference.shape}")
        ref = lambda t: reference[int(round(t / period)), 0]  # noqa: E731 - the log's q1d
    T = np.full(N, np.nan)
    TAU = np.zeros((N, n))
    Q1 = np.zeros((N, n))
    Q2 = np.zeros((N, n))
    Q1D = np.zeros((N, n)) if ref is not None else None
    comp = np.zeros(N)
    late = np.zeros(N)
    zero = np.zeros(n)
    stop = {"reason": None}
    faults: list[str] = []
    misses = consec = worst = 0

    def on_signal(signum, frame):
        stop["reason"] = f"signal {signal.Signals(signum).name}"

    old = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, on_signal)
    k = -1
    try:
        controller.reset()
        io.read()  # warm the I/O path (reads have no side effect) before the clock starts
        t_start = time.perf_counter()
        for k in range(N):
            if stop["reason"] is not None:
                break
            t_k = k * period
            if cfg.realtime:
                _sleep_until(t_start + t_k, cfg.busy_wait)
            if cfg.realtime:
                late[k] = time.perf_counter() - (t_start + t_k)
            try:
                q1, q2 = io.read()
            except Exception as e:
                stop["reason"] = f"rig: reading the encoders failed at sample {k}: {_describe(e)}"
                break
            q1 = np.asarray(q1, float).reshape(n)
            q2 = np.asarray(q2, float).reshape(n)
            fault = None
            tau = zero
            if not (np.all(np.isfinite(q1)) and np.all(np.isfinite(q2))):
                fault = f"sample {k}: non-finite angle (q1={q1.tolist()}, q2={q2.tolist()})"
            elif np.any(np.abs(q1) > cfg.q_limit) or np.any(np.abs(q2) > cfg.q_limit):
                fault = f"sample {k}: angle beyond +-{cfg.q_limit} rad (q1={q1.tolist()}, q2={q2.tolist()})"
            else:
                c0 = time.perf_counter()
                try:
                    kw = {} if reference is None else {"ref": reference[k]}
                    u = (controller.step(t_k, float(q1[0]), float(q2[0]), **kw) if n == 1
                         else controller.step(t_k, q1, q2, **kw))
                    u = np.asarray(u, float).reshape(n)
                except Exception as e:
                    stop["reason"] = f"controller: step raised at sample {k}: {_describe(e)}"
                    break
                comp[k] = time.perf_counter() - c0
                if not np.all(np.isfinite(u)):
                    fault = f"sample {k}: non-finite torque command {u.tolist()}"
                else:
                    tau = np.clip(u, -cfg.tau_limit, cfg.tau_limit)
            try:
                io.write(tau)
            except Exception as e:
                stop["reason"] = f"rig: writing the torque failed at sample {k}: {_describe(e)}"
                break
            done = time.perf_counter()
            T[k], TAU[k], Q1[k], Q2[k] = t_k, tau, q1, q2
            if Q1D is not None:
                Q1D[k] = np.asarray(ref(t_k), float).reshape(n)
            if fault is not None:
                faults.append(fault)
                if cfg.stop_on_fault:
                    stop["reason"] = f"guard: {fault}"
                    break
            if cfg.realtime and done > t_start + t_k + period:
                misses += 1
                consec += 1
                worst = max(worst, consec)
                if consec >= cfg.max_consecutive_misses:
                    stop["reason"] = (f"watchdog: {consec} consecutive deadline misses "
                                      f"(period {period * 1e6:.0f} us)")
                    break
            else:
                consec = 0
    except Exception as e:  # reset() or the warm-up read
        stop["reason"] = f"error before the first sample: {_describe(e)}"
    finally:
        # a second Ctrl-C while stopping must not skip the zero torque or the log
        for s in old:
            signal.signal(s, on_signal)
        try:
            io.write(zero)
        except Exception as e:
            faults.append(f"zero torque could not be written: {_describe(e)}")
        try:
            io.close()
        except Exception as e:
            faults.append(f"closing the rig failed: {_describe(e)}")
        for s, h in old.items():
            signal.signal(s, h)
    m = int(np.sum(np.isfinite(T)))  # samples are filled in order
    res = LoopResult(
        t=T[:m], tau=TAU[:m], q1=Q1[:m], q2=Q2[:m], q1d=None if Q1D is None else Q1D[:m],
        compute_time=comp[:m], lateness=late[:m], misses=misses, max_consecutive_misses=worst,
        faults=faults, stop_reason=stop["reason"] or "completed",
    )
    # a log holds finite samples only (docs/spec.md section 6): it ends before the first
    # sample with a non-finite angle (that sample is in ``faults``)
    finite = np.all(np.isfinite(res.q1), axis=1) & np.all(np.isfinite(res.q2), axis=1)
    m_log = int(np.argmin(finite)) if not finite.all() else m
    if log_path is not None and m_log >= 2:
        sl = slice(0, m_log)
        try:
            save_log(Log.from_arrays(t=res.t[sl], tau=res.tau[sl], q1=res.q1[sl], q2=res.q2[sl],
                                     q1d=None if res.q1d is None else res.q1d[sl],
                                     source="run-loop"), log_path)
            res.log_path = str(log_path)
            if m_log < m:
                res.faults.append(f"log ends at sample {m_log - 1}, before the non-finite angle")
        except (OSError, ValueError) as e:
            res.faults.append(f"log not written: {_describe(e)}")
    return res


def _describe(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


# ----- simulated rig ---------------------------------------------------------------------------


def _rig_main(read_fd: int, write_fd: int) -> None:
    """Entry of the rig's child process (started with ``python -c``, so that no user script is
    re-imported, unlike multiprocessing's spawn)."""
    # Ctrl-C in a terminal reaches the whole process group: the loop (the parent) stops the
    # plant itself after its zero-torque write, so the plant ignores SIGINT/SIGTERM; a parent
    # that dies closes the pipes, and the plant then exits quietly.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    conn_in = mp_connection.Connection(read_fd, writable=False)
    conn_out = mp_connection.Connection(write_fd, readable=False)
    try:
        params, dt, substeps, q1_0, resolution = conn_in.recv()
        _rig_process(_Duplex(conn_in, conn_out), params, dt, substeps, q1_0, resolution)
    except (EOFError, OSError):
        pass


class _Duplex:
    """A send/recv/poll pair over two one-way pipes."""

    def __init__(self, rx: Any, tx: Any):
        self.rx, self.tx = rx, tx

    def send(self, obj: Any) -> None:
        self.tx.send(obj)

    def recv(self) -> Any:
        return self.rx.recv()

    def poll(self, timeout: float) -> bool:
        return self.rx.poll(timeout)

    def close(self) -> None:
        self.rx.close()
        self.tx.close()


def _rig_process(conn: Any, params: dict, dt: float, substeps: int, q1_0: Sequence[float],
                 resolution: tuple[float, float]) -> None:
    """Child process: the plant of ``params`` (with its effects) stepped by jitted
    ``plant_step`` once per written torque."""
    try:
        import jax

        jax.config.update("jax_enable_x64", True)
        import jax.numpy as jnp

        from jaxflex.io.params import Params
        from jaxflex.sim.step import plant_step

        plant = Params.from_dict(params).to_plant()
        x0 = plant.init_state(q1=jnp.asarray(q1_0, float))
        leaves0, treedef = jax.tree_util.tree_flatten(x0)

        def advance(flat, tau):
            x = jax.tree_util.tree_unflatten(treedef, list(flat))
            return jax.tree_util.tree_leaves(plant_step(plant, x, tau, dt, substeps))

        # ahead-of-time compiled: no tracing or cache lookup per call
        step = jax.jit(advance).lower(leaves0, jnp.zeros(plant.n)).compile()
        flat = [np.asarray(a) for a in leaves0]
        jax.block_until_ready(step(flat, np.zeros(plant.n)))  # first execution is slow
        r1, r2 = resolution
        names = [f.name for f in dataclasses.fields(x0)]
        i_q1, i_q2 = names.index("q1"), names.index("q2")

        def quant(q, r):
            return np.round(q / r) * r if r > 0 else q

        conn.send(("ready", plant.n))
    except Exception as e:  # pragma: no cover - reported to the parent
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    while True:
        msg = conn.recv()
        kind = msg[0]
        if kind == "read":
            conn.send((quant(np.asarray(flat[i_q1]), r1), quant(np.asarray(flat[i_q2]), r2)))
        elif kind == "write":
            flat = step(flat, np.asarray(msg[1], float))
        elif kind == "state":
            x = jax.tree_util.tree_unflatten(treedef, list(flat))
            conn.send({k: np.asarray(getattr(x, k)) for k in ("q1", "dq1", "q2", "dq2", "z")})
        elif kind == "close":
            conn.send("closed")
            break


class SimulatedRig(RigIO):
    """A simulated rig: the plant (``params``, docs/spec.md section 7, effects included) runs in a
    separate process and advances by ``dt`` [s] (``substeps`` integrator steps) each time a
    torque is written; ``read`` returns its angles quantised to ``resolution`` = (q1, q2)
    encoder steps [rad] (0: exact). Starts at rest at ``q1_0`` [rad]. Use as a context
    manager or call ``close``."""

    def __init__(self, params: Any, dt: float = 1e-3, *, substeps: int = 10,
                 q1_0: Sequence[float] | float = 0.0, resolution: tuple[float, float] = (0.0, 0.0),
                 start_timeout: float = 120.0):
        d = params.to_dict() if hasattr(params, "to_dict") else dict(params)
        n = len(np.atleast_1d(d["plant"]["I"]))
        self.n = n
        self.dt = float(dt)
        q1_0 = [float(v) for v in np.broadcast_to(np.asarray(q1_0, float), (n,))]
        # a fresh interpreter (never fork a process that runs JAX threads; no re-import of
        # the user's script as multiprocessing's spawn would do)
        down_r, down_w = os.pipe()
        up_r, up_w = os.pipe()
        code = "import sys; from jaxflex.app.hardware import _rig_main; _rig_main(int(sys.argv[1]), int(sys.argv[2]))"
        self._proc = subprocess.Popen([sys.executable, "-c", code, str(down_r), str(up_w)],
                                      pass_fds=(down_r, up_w))
        os.close(down_r)
        os.close(up_w)
        self._conn = _Duplex(mp_connection.Connection(up_r, writable=False),
                             mp_connection.Connection(down_w, readable=False))
        self._conn.send((d, self.dt, int(substeps), q1_0, tuple(resolution)))
        if not self._conn.poll(start_timeout):
            self._proc.kill()
            raise RuntimeError(f"SimulatedRig: plant process did not start within {start_timeout} s")
        try:
            msg = self._conn.recv()
        except EOFError:
            msg = ("error", f"exited with status {self._proc.wait(5)}")
        if msg[0] != "ready":
            self._proc.kill()
            raise RuntimeError(f"SimulatedRig: plant process failed: {msg[1]}")
        self._closed = False

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        self._conn.send(("read",))
        return self._conn.recv()

    def write(self, tau: np.ndarray) -> None:
        self._conn.send(("write", np.asarray(tau, float).reshape(self.n)))

    def plant_state(self) -> dict[str, np.ndarray]:
        """The plant's true state (q1, dq1, q2, dq2, z)."""
        self._conn.send(("state",))
        return self._conn.recv()

    def close(self) -> None:
        """Stop the plant process (a later ``close`` does nothing)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._conn.send(("close",))
            self._conn.poll(5.0) and self._conn.recv()
        except (BrokenPipeError, EOFError, OSError):
            pass
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._conn.close()

    def __enter__(self) -> "SimulatedRig":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

"""Does the exported controller's friction compensation help on a plant jaxflex did not simulate?

The exported numpy controller of ``reproduce``'s default configuration (the paper's gains,
the steady-state Kalman velocity estimator, the observer leak) runs in closed loop with a
flexible joint with LuGre friction written here from the paper's equations (eq. 3-6: link
I q1'' = K (q2 - q1) - F, rotor J q2'' = tau - K (q2 - q1), F = sigma0 z + sigma1 z' +
sigma2 q1', z' = q1' - sigma0 |q1'| / g(q1') z with the plain |.|, integrated by classical
fourth-order Runge-Kutta in plain Python floats, none of jaxflex's integrator or plant code),
sensed through the paper's 0.72 degree link encoder (and its rotor encoder behind the 1:50
gear) and driven through a 12-bit DAC over +-2 N m. For each of the paper's three
experiments (sinusoid, rest-to-rest polynomial, fast motion) the RMS tracking error
e1 = q1 - q1d of the compensated controller (friction observer on) is compared with the
uncompensated one (observer off; the same Kalman sensing and gains).

One export per configuration serves the three experiments: the rig gives the controller
the reference (q1d and four derivatives) at each sample. Writes results.json (and
tracking.png when matplotlib is installed) to --out. Usage: ``python
studies/export_independent_plant.py [--out DIR] [--duration S] [--substeps N] [--small]``
(``--small``: 2 s per run).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

EXPERIMENTS: tuple[str, ...] = ("sinusoid", "polynomial", "fast")


class LuGreJoint:
    """The paper's one-joint flexible plant with LuGre friction, integrated by RK4.

    **Arguments:**

    - ``I``, ``J`` [kg m^2], ``K`` [N m/rad]: link and rotor inertia, joint stiffness.
    - ``Fc``, ``Fs`` [N m], ``vs`` [rad/s], ``sigma0`` [N m/rad], ``sigma1`` [N m s/rad],
      ``sigma2`` [N m s/rad]: LuGre parameters (eq. 4-6).
    - ``substeps``: RK4 steps per controller sample.
    """

    def __init__(self, I: float, J: float, K: float, Fc: float, Fs: float, vs: float,
                 sigma0: float, sigma1: float, sigma2: float, substeps: int = 10):
        self.I, self.J, self.K = I, J, K
        self.Fc, self.Fs, self.vs = Fc, Fs, vs
        self.s0, self.s1, self.s2 = sigma0, sigma1, sigma2
        self.substeps = substeps

    def rhs(self, x: tuple[float, ...], tau: float) -> tuple[float, ...]:
        """Time derivative of (q1, dq1, q2, dq2, z) under motor torque ``tau`` [N m]."""
        q1, v, q2, w, z = x
        g = self.Fc + (self.Fs - self.Fc) * math.exp(-(v / self.vs) ** 2)
        dz = v - self.s0 * abs(v) / g * z
        F = self.s0 * z + self.s1 * dz + self.s2 * v
        spring = self.K * (q2 - q1)
        return v, (spring - F) / self.I, w, (tau - spring) / self.J, dz

    def advance(self, x: tuple[float, ...], tau: float, dt: float) -> tuple[float, ...]:
        """The state after ``dt`` [s] of constant torque ``tau`` (zero-order hold)."""
        h = dt / self.substeps
        for _ in range(self.substeps):
            k1 = self.rhs(x, tau)
            k2 = self.rhs(tuple(a + 0.5 * h * b for a, b in zip(x, k1)), tau)
            k3 = self.rhs(tuple(a + 0.5 * h * b for a, b in zip(x, k2)), tau)
            k4 = self.rhs(tuple(a + h * b for a, b in zip(x, k3)), tau)
            x = tuple(a + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
                      for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4))
        return x


def quantise(x: float, step: float) -> float:
    """``x`` rounded to the nearest multiple of ``step`` (an encoder or DAC)."""
    return round(x / step) * step


def run(ctrl, plant: LuGreJoint, refs: np.ndarray, dt: float, enc1: float, enc2: float,
        dac_bits: int, dac_range: float) -> dict:
    """One closed-loop run of an exported controller on the independent plant.

    **Arguments:**

    - ``ctrl``: an exported controller (``Controller()`` of a generated module).
    - ``plant``: the plant.
    - ``refs``: (N, 5) reference q1d and its four derivatives at each sample.
    - ``dt`` [s]: sample period; ``enc1``, ``enc2`` [rad]: link and (link-referred) rotor
      encoder steps; ``dac_bits``, ``dac_range`` [N m]: the DAC.

    **Returns:**

    ``rms_error`` and ``max_error`` [rad] of e1 = q1 - q1d, ``saturated`` (fraction of
    samples at the DAC's limit), and the series ``e1`` and ``tau`` (lists).
    """
    lsb = 2.0 * dac_range / 2**dac_bits
    q0 = float(refs[0, 0])
    x = (q0, 0.0, q0, 0.0, 0.0)
    ctrl.reset()
    e1, taus = [], []
    for k in range(refs.shape[0]):
        t = k * dt
        e1.append(x[0] - float(refs[k, 0]))
        tau = ctrl.step(t, quantise(x[0], enc1), quantise(x[2], enc2), ref=refs[k][:, None])
        tau = min(max(quantise(tau, lsb), -dac_range), dac_range)
        taus.append(tau)
        x = plant.advance(x, tau, dt)
        if not all(math.isfinite(v) for v in x):
            raise FloatingPointError(f"the independent plant diverged at t = {t:.3f} s")
    e = np.asarray(e1)
    return {"rms_error": float(np.sqrt(np.mean(e**2))), "max_error": float(np.max(np.abs(e))),
            "saturated": float(np.mean(np.abs(np.asarray(taus)) >= dac_range)),
            "e1": e.tolist(), "tau": taus}


def main(argv: list[str] | None = None) -> dict:
    """Run the study; writes results.json (and tracking.png) to --out; returns the results."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/export_independent_plant")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per run (default 10)")
    ap.add_argument("--substeps", type=int, default=10, help="RK4 steps per sample")
    ap.add_argument("--small", action="store_true", help="2 s per run (a quick check)")
    args = ap.parse_args(argv)
    if args.small:
        args.duration = min(args.duration, 2.0)

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxflex.export import generate_source, load_module, rig_controller
    from jaxflex.io.presets import (
        REPRODUCE_LEAK,
        paper_params,
        paper_sensing,
        trajectory_preset,
        with_estimator,
    )
    from jaxflex.sim.simulate import REFERENCE_ORDER

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    p = paper_params().to_dict()
    p["gains"]["leak"] = [REPRODUCE_LEAK]
    sensing = paper_sensing()
    kalman = with_estimator(sensing, "kalman")
    t_start = time.perf_counter()
    modules = {name: load_module(generate_source(
        rig_controller(p, sensing=kalman, compensation=on)))
        for name, on in (("compensated", True), ("uncompensated", False))}
    setup_s = time.perf_counter() - t_start
    pl, fr = p["plant"], p["friction"]
    plant = LuGreJoint(pl["I"][0], pl["J"][0], pl["K"][0], *(fr[k][0] for k in (
        "Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")), substeps=args.substeps)
    dt = float(modules["compensated"].DT)
    n = int(round(args.duration / dt))
    ts = np.arange(n) * dt
    enc1, enc2 = float(np.ravel(sensing.q1_resolution)[0]), float(np.ravel(sensing.q2_resolution)[0])
    dac_range = float(np.ravel(sensing.dac_range)[0])
    results: dict = {
        "question": __doc__.splitlines()[0], "duration_s": args.duration, "dt_s": dt,
        "substeps": args.substeps, "link_encoder_rad": enc1, "rotor_encoder_rad": enc2,
        "dac_bits": int(sensing.dac_bits), "dac_range_Nm": dac_range,
        "controllers": {k: m.CONFIG for k, m in modules.items()},
        "setup_s": setup_s, "experiments": {},
    }
    series = {}
    for exp in EXPERIMENTS:
        traj = trajectory_preset(exp)
        refs = np.asarray(jax.jit(jax.vmap(
            lambda t: traj.derivatives(t, order=REFERENCE_ORDER)))(ts))[:, :, 0]
        row = {}
        for name, mod in modules.items():
            t0 = time.perf_counter()
            r = run(mod.Controller(), plant, refs, dt, enc1, enc2, int(sensing.dac_bits),
                    dac_range)
            series[(exp, name)] = r.pop("e1")
            r.pop("tau")
            r["run_s"] = time.perf_counter() - t0
            row[name] = r
        row["ratio_compensated_to_uncompensated"] = (
            row["compensated"]["rms_error"] / row["uncompensated"]["rms_error"])
        row["compensation_wins"] = row["compensated"]["rms_error"] < row["uncompensated"]["rms_error"]
        results["experiments"][exp] = row
        print(f"{exp:10s} RMS e1 compensated {row['compensated']['rms_error']:.3e} rad, "
              f"uncompensated {row['uncompensated']['rms_error']:.3e} rad "
              f"(ratio {row['ratio_compensated_to_uncompensated']:.3f})", flush=True)
    results["compensation_wins_all"] = all(r["compensation_wins"]
                                           for r in results["experiments"].values())
    (out / "results.json").write_text(json.dumps(results, indent=2))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - the figure is optional
        return results
    fig, axes = plt.subplots(len(EXPERIMENTS), 1, figsize=(8, 8), sharex=True)
    for ax, exp in zip(axes, EXPERIMENTS):
        for name in modules:
            ax.plot(ts, 1e3 * np.asarray(series[(exp, name)]), lw=0.8, label=name)
        ax.set_ylabel(f"{exp}\ne1 [mrad]")
    axes[0].legend(loc="upper right")
    axes[0].set_title("Exported controller on an independent LuGre plant "
                      f"({describe_short(modules)}; 0.72 deg encoder, 12-bit DAC)", fontsize=9)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(out / "tracking.png", dpi=120)
    plt.close(fig)
    return results


def describe_short(modules: dict) -> str:
    """The velocity source and observer of the compensated export, for the figure's title."""
    return modules["compensated"].CONFIG.split(";")[0]


if __name__ == "__main__":
    main()

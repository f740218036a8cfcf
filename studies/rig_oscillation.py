"""Question: where does the ~3.6 Hz oscillation of the compensated loop come from:
the observer's Ke sigma0 s1 term acting as integral action, the model-based q2d' and q2d''
(docs/spec.md section 3, correction 2), or a defect?

Method: the Jacobian of the one-sample closed-loop map (``jaxflex.loop.analyse``) at rest for each
q2d method with and without compensation, and with exact or filtered velocities; the modes'
frequency, damping and participating states; the rest modes as the observer gain Ke, the link
damping KD1 and the rotor slope L2 vary; Floquet multipliers along the paper's sinusoid; and,
to tie the linear picture to the simulation, the spectral peak of the link error of the loop
started slightly off rest (nonlinear limit cycle) against the unstable mode's frequency.

Writes ``rest_modes.json`` (all numbers) and figures to --out (default out/rig_oscillation).
``--small`` runs a reduced grid.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/rig_oscillation")
    ap.add_argument("--small", action="store_true", help="reduced grid (smoke test)")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxflex.loop.analyse import analyse_loop
    from jaxflex.core.controller import CascadeController, CascadeGains
    from jaxflex.io.presets import PAPER_GAINS, paper_plant, sensing_preset
    from jaxflex.sim.simulate import simulate_sampled
    from jaxflex.core.trajectory import Sinusoid

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plant = paper_plant()
    doc: dict = {"question": __doc__.split("\n\n")[0]}

    def gains(**kw):
        return CascadeGains(**{**PAPER_GAINS, **kw})

    def top(res):
        """The slowest oscillatory mode (or the slowest mode) at rest."""
        ms = [m for m in res.rest.modes if m["abs"] < 1 - 1e-9 or m["abs"] > 1 + 1e-9]
        osc = [m for m in ms if m["frequency_hz"] > 0.05]
        return (osc or ms)[0]

    # 1. every q2d method x compensation x velocity path, at rest
    grid = {}
    for method in ("model", "filtered", "reference"):
        for vel in ("ideal", "rig"):
            for comp in (True, False):
                res = analyse_loop(plant, gains(), q2d_method=method, compensation=comp,
                                   sensing=sensing_preset(vel))
                key = f"{method}/{'exact' if vel == 'ideal' else 'filtered'}_velocity/" + (
                    "with_compensation" if comp else "without_compensation")
                grid[key] = {"spectral_radius": res.rest.spectral_radius,
                             "stable": res.rest.stable, "slowest_oscillatory": top(res),
                             "modes": res.rest.modes}
                print(f"{key:<60} radius {res.rest.spectral_radius:.5f} "
                      f"f {top(res)['frequency_hz']:.2f} Hz zeta {top(res)['damping']:.3f}")
    doc["rest_modes"] = grid

    # 2. gain sweeps (model method, exact velocities, compensation on)
    sweeps = {"Ke": [1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3],
              "KD1": [0.5, 1.0, 2.0, 4.0, 8.0, 16.0],
              "L2": [3.0, 6.0, 12.0, 25.0, 50.0, 100.0]}
    if args.small:
        sweeps = {k: v[::2] for k, v in sweeps.items()}
    doc["gain_sweeps"] = {}
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.5))
    for ax, (name, values) in zip(axs, sweeps.items()):
        rows = []
        for method in ("model", "filtered"):
            rad, freq = [], []
            for v in values:
                res = analyse_loop(plant, gains(**{name: v}), q2d_method=method)
                m = top(res)
                rad.append(res.rest.spectral_radius)
                freq.append(m["frequency_hz"])
                rows.append({"q2d_method": method, name: v, "spectral_radius": rad[-1],
                             "frequency_hz": m["frequency_hz"], "damping": m["damping"]})
            ax.semilogx(values, (np.array(rad) - 1) * 1e3, "o-", label=f"q2d {method}")
        ax.axhline(0, color="k", lw=0.8)
        ax.axvline(PAPER_GAINS[name], color="gray", ls=":", label="Table 3")
        ax.set_xlabel(name)
        ax.set_ylabel("(spectral radius - 1) x 1e3 per sample")
        ax.legend(fontsize=7)
        doc["gain_sweeps"][name] = rows
    fig.suptitle("rest modes with compensation, exact velocities: > 0 means unstable")
    fig.tight_layout()
    fig.savefig(out / "gain_sweeps.png", dpi=120)
    plt.close(fig)

    # 3. Floquet multipliers along the sinusoid
    doc["floquet"] = {}
    for method in ("model", "filtered"):
        for comp in (True, False):
            res = analyse_loop(plant, gains(), q2d_method=method, compensation=comp,
                               floquet=True)
            doc["floquet"][f"{method}/{'with' if comp else 'without'}_compensation"] = \
                res.floquet.to_dict()

    # 4. nonlinear check: the loop at rest, started 1 mrad off, spectral peak of e1
    T = 4.0 if args.small else 10.0
    doc["limit_cycle"] = {}
    fig, ax = plt.subplots(2, 1, figsize=(8, 6))
    for method in ("model", "filtered"):
        for comp in (True, False):
            c = CascadeController(model=plant, gains=gains(), compensation=comp,
                                  q2d_method=method, tau_max=2.0,
                                  trajectory=Sinusoid(amplitude=0.0, frequency=1.0))
            x0 = plant.init_state(q1=jnp.array([1e-3]))
            r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, T, x0=x0))(plant, c)
            e = np.asarray(r.e1[:, 0])
            tail = e[len(e) // 2:]
            spec = np.abs(np.fft.rfft(tail - tail.mean()))
            f = np.fft.rfftfreq(len(tail), 1e-3)
            peak = float(f[1:][np.argmax(spec[1:])])
            key = f"{method}/{'with' if comp else 'without'}_compensation"
            doc["limit_cycle"][key] = {
                "peak_hz": peak, "amplitude_rad": float(0.5 * np.ptp(tail)),
                "F_hat_peak": float(np.max(np.abs(np.asarray(r.F_hat[:, 0])))),
                "F_peak": float(np.max(np.abs(np.asarray(r.F[:, 0])))),
            }
            print(key, doc["limit_cycle"][key])
            ax[0].plot(np.asarray(r.t), e, lw=0.8, label=key)
            ax[1].semilogy(f[1:], spec[1:] + 1e-12, lw=0.8, label=key)
    ax[0].set_xlabel("t (s)")
    ax[0].set_ylabel("e1 (rad), reference at rest")
    ax[1].set_xlim(0, 20)
    ax[1].set_xlabel("frequency (Hz), second half")
    ax[1].set_ylabel("|FFT e1|")
    ax[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rest_limit_cycle.png", dpi=120)
    plt.close(fig)

    lin = grid["model/exact_velocity/with_compensation"]["slowest_oscillatory"]
    doc["explanation"] = (
        "With the model-based q2d' and q2d'' and compensation on, the loop linearised at rest "
        f"has a growing mode at {lin['frequency_hz']:.2f} Hz (|mu| = {lin['abs']:.5f} per "
        "sample, damping ratio "
        f"{lin['damping']:.3f}) in which the plant's bristle state z, the observer's z_hat and "
        "the link take part; without compensation the same loop is stable, and with the "
        "filtered q2d derivatives and compensation it is stable too. At rest Psi_hat(0) = 0, "
        "so the observer integrates q1' - Ke sigma0 s1 without leak: F_hat - F is sigma0 "
        "Ke sigma0 times the integral of s1 (integral action on the tracking error), and the "
        "model-based q1'' estimate (K (q2 - q1) - F_hat) / I carries this error into q2d' with "
        "the gain (I L1 + KD1) / K ~ 2 of docs/spec.md section 3, a path that the Lyapunov "
        "proof (which uses the true q2d') does not have. The mode is removed by a smaller Ke, "
        "a larger KD1 or a faster rotor loop (L2), see gain_sweeps. Away from rest the "
        "LuGre dissipation sigma0 Psi (|v| / g) damps it, which bounds the oscillation to "
        "a limit cycle (its frequency is below the linear one: limit_cycle.peak_hz). A "
        "property of the paper's Table 3 gains with the model-based q2d derivatives, not a "
        "coding defect.")
    (out / "rest_modes.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(doc["explanation"])


if __name__ == "__main__":
    main()

"""Study: does the paper's cascade controller with friction compensation (eq. 9-22) hold on
the KUKA KR300's axes 1-3 as one coupled flexible-joint arm, with gains certified by the N2
condition for n joints (eq. 29-31)?

Plant (simulation): ``jaxflex.data.kr300.kuka_kr300_plant``, the three flexible joints of the
arm from its kinematics and shipped inertias (the wrist held at zero, the 200 kg payload of
the authors' model), rotor inertias J = u^2 J_m and the recording's nominal stiffnesses K
(``c_rad_ff``); gravity from the kinematics. Friction per joint: a LuGre model (eq. 4-6)
whose sliding levels come from the recordings, the rest stated assumptions:

- Fc and sigma2: the motor friction Fm and viscous bm that ``jaxflex identify`` fits on
  trajectory A of each axis (the rotor kind, ``jaxflex.identify.torque.identify_rotor``,
  equation error on the measured torque);
- assumed: Fs = 1.2 Fc, vs = 0.01 rad/s, a presliding range Fc / sigma0 of 1e-4 rad, and
  sigma1 giving the bristles a damping ratio of 0.05 against the link inertia M_ii at the
  start pose.

Gains (one rule, every joint; ``jaxflex.data.kr300``'s ``KR300_L1`` ..., which
``kuka_kr300_params`` also uses): L1 = 10 /s, L2 = 30 /s, KD1 = KD2 = K / L2 (so that
L2^2 KD1 KD2 = K^2 dominates the K^2 / 4 coupling of N2's e1-e2 block), Ke = 0.1 / sigma0,
kv = 200 s/rad. N2 is evaluated for every joint over the speeds 0 to 1.3x the fastest link
speed of trajectory A (``jaxflex.core.certificate.certify``).

Task: a rest-to-rest move of (0.4, 0.25, -0.4) rad from the pose (0, -0.1, -0.4) rad and back
(3 s each), the arm starting at rest with the springs holding its weight; the controller at
1 kHz with the nominal model equal to the plant, exact angle and velocity readings. Closed
loop with and without the friction compensation (``compensation=False``: F_hat = 0).

Writes ``DIR/results.json`` (the friction per joint and where each number comes from, the
gains, the certificate, the tracking errors with and without compensation, timings) and
``DIR/kuka_control.png`` (link error per joint, both runs). Usage:
``python studies/kuka_control.py --out DIR [--small]`` (``--small``: 1 s moves).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import jax

from jaxflex.data.kr300 import (
    KR300_BRISTLE_DAMPING as BRISTLE_DAMPING,
    KR300_FS_OVER_FC as FS_OVER_FC,
    KR300_KE_SIGMA0 as KE_SIGMA0,
    KR300_KV as KV,
    KR300_L1 as L1,
    KR300_L2 as L2,
    KR300_PRESLIDING as PRESLIDING,
    KR300_VS as VS,
)

#: Task: start pose, move [rad], segment duration [s]; controller period [s]; substeps.
POSE: tuple[float, float, float] = (0.0, -0.1, -0.4)
MOVE: tuple[float, float, float] = (0.4, 0.25, -0.4)
SEGMENT_S: float = 3.0
DT: float = 1e-3
SUBSTEPS: int = 4


def sliding_friction() -> dict[str, Any]:
    """Fm, bm per axis [N m, N m s/rad] from ``identify_rotor`` on trajectory A, with their
    standard errors and whether each fit converged."""
    import numpy as np

    from jaxflex.data import load_named
    from jaxflex.identify.torque import identify_rotor

    out: dict[str, Any] = {"Fm": [], "bm": [], "Fm_stderr": [], "bm_stderr": [],
                           "converged": []}
    for axis in (1, 2, 3):
        res = identify_rotor(load_named(f"jaxflex:kuka/A/{axis}").log)
        eff = res.params.effects["motor_friction"]
        se = res.params.extra["stderr"]
        out["Fm"].append(float(np.ravel(eff["Fm"])[0]))
        out["bm"].append(float(np.ravel(eff["bm"])[0]))
        out["Fm_stderr"].append(float(np.ravel(se["motor_friction.Fm"])[0]))
        out["bm_stderr"].append(float(np.ravel(se["motor_friction.bm"])[0]))
        out["converged"].append(bool(res.converged))
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the study; returns and writes the results (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder (must exist)")
    ap.add_argument("--small", action="store_true", help="1 s moves instead of 3 s (a quick check)")
    args = ap.parse_args(argv)
    if not args.out.is_dir():
        raise SystemExit(f"kuka_control: output folder {args.out} does not exist")
    segment_s = 1.0 if args.small else SEGMENT_S
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    from jaxflex.core.certificate import certify
    from jaxflex.core.controller import CascadeController, CascadeGains
    from jaxflex.data import load_named
    from jaxflex.data.kr300 import kuka_kr300_plant
    from jaxflex.core.friction import LuGre
    from jaxflex.sim.simulate import simulate_sampled
    from jaxflex.core.trajectory import RestToRest

    sliding = sliding_friction()
    nominal = kuka_kr300_plant()
    q0 = jnp.asarray(POSE)
    M = np.diag(np.asarray(nominal.links.mass_matrix(q0)))
    Fc = np.asarray(sliding["Fm"])
    sigma0 = Fc / PRESLIDING
    lugre = LuGre(Fc=Fc, Fs=FS_OVER_FC * Fc, vs=np.full(3, VS), sigma0=sigma0,
                  sigma1=2 * BRISTLE_DAMPING * np.sqrt(sigma0 * M),
                  sigma2=np.asarray(sliding["bm"]))
    plant = eqx.tree_at(lambda p: p.friction, nominal, lugre, is_leaf=lambda v: v is None)
    K = np.asarray(plant.K)
    gains = CascadeGains(Ke=KE_SIGMA0 / sigma0, KD1=K / L2, KD2=K / L2, kv=np.full(3, KV),
                         L1=np.full(3, L1), L2=np.full(3, L2))
    log_a = load_named("jaxflex:kuka/A").log
    v_task = float(np.max(np.abs(np.diff(log_a.q1, axis=0))) / log_a.dt)
    cert = certify(plant, gains, vmax=1.3 * v_task)

    traj = RestToRest(waypoints=[q0, q0 + jnp.asarray(MOVE), q0],
                      durations=[segment_s, segment_s], t0=0.5)
    x0 = plant.init_state(q1=q0, q2=q0 + plant.links.gravity(q0) / plant.K)
    t_final = 2 * segment_s + 1.0
    run = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, t_final, x0=x0,
                                                       substeps=SUBSTEPS))
    loops: dict[str, Any] = {}
    series = {}
    for name, comp in (("compensated", True), ("uncompensated", False)):
        ctrl = CascadeController(model=plant, gains=gains, trajectory=traj, compensation=comp,
                                 dt=DT)
        t0 = time.perf_counter()
        first = run(plant, ctrl)
        jax.block_until_ready(first.e1)
        t_first = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = run(plant, ctrl)
        jax.block_until_ready(r.e1)
        e1 = np.asarray(r.e1)
        series[name] = (np.asarray(r.t), e1)
        loops[name] = {"diverged": bool(r.metrics.diverged),
                       "max_abs_e1_rad": np.abs(e1).max(0).tolist(),
                       "rms_e1_rad": np.asarray(r.metrics.rms_error).tolist(),
                       "first_call_s": t_first, "warm_s": time.perf_counter() - t0}
        print(f"{name}: max |e1| {np.abs(e1).max(0)} rad, rms {loops[name]['rms_e1_rad']}")
    results = {
        "friction": {"from_recordings": sliding,
                     "lugre": {k: np.asarray(getattr(lugre, k)).tolist()
                               for k in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")},
                     "assumed": {"Fs_over_Fc": FS_OVER_FC, "vs": VS, "presliding_rad": PRESLIDING,
                                 "bristle_damping_ratio": BRISTLE_DAMPING}},
        "plant": {"J": np.asarray(plant.J).tolist(), "K": K.tolist(), "M_diag_at_pose": M.tolist()},
        "gains": {k: np.asarray(getattr(gains, k)).tolist()
                  for k in ("Ke", "KD1", "KD2", "kv", "L1", "L2")},
        "certificate": {"vmax": 1.3 * v_task, "v_task_A": v_task,
                        "certified_up_to": cert.certified_up_to, "certified": cert.certified,
                        "lambda_min_min": float(np.min(cert.lambda_min))},
        "task": {"pose": POSE, "move": MOVE, "segment_s": segment_s, "dt": DT,
                 "substeps": SUBSTEPS},
        "loops": loops,
    }
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(3, 1, figsize=(7, 6), sharex=True)
    for j in range(3):
        for name, (t, e1) in series.items():
            axs[j].plot(t, 1e3 * e1[:, j], lw=0.8, label=name)
        axs[j].set_ylabel(f"e1 axis {j + 1} [mrad]")
    axs[0].legend()
    axs[-1].set_xlabel("t [s]")
    axs[0].set_title(f"KR300 axes 1-3, cascade law; N2 certified up to "
                     f"{cert.certified_up_to:.2g} rad/s")
    fig.tight_layout()
    fig.savefig(args.out / "kuka_control.png", dpi=120)
    plt.close(fig)
    return results


if __name__ == "__main__":
    main()

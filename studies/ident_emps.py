"""Study: how well does gradient identification through the simulator do on real measured data?

Question: identified on the EMPS benchmark's estimation set (``DATA_EMPS.mat``, a real
prismatic drive in closed loop, nobody here produced it), how close do the closed-loop
simulation errors of a rigid mass with friction come to the benchmark's published reference
numbers (IDIM-LS), on the estimation set and on the validation set with force pulses
(``DATA_EMPS_PULSES.mat``)?

Model: the EMPS is rigid and prismatic, so the rigid model of ``jaxflex.identify`` (eq. 37,
Jx = I + J) is used with SI units on the load side (m, N, kg): LuGre friction (Fc, Fs, vs,
sigma2 free; stiff bristles sigma0, sigma1 fixed, so the model is Coulomb + Stribeck +
viscous) plus a ``torque_offset`` effect. Identification: multiple shooting on the measured
position with the measured force ``gtau*vir`` as input (``identify``, Levenberg-Marquardt).
Validation: the benchmark's closed loop (SOURCE.md): P position / P velocity cascade with the
0.5/0.5 FIR velocity estimate and the 10 V saturation, driven by the reference ``qg``;
relative errors 100 ||y - y_hat|| / ||y|| of position, velocity, acceleration and force after
dropping 49 samples, velocity and acceleration of the measured position by central
differences after a 4th-order 100 Hz Butterworth filtfilt (as the benchmark does).

Note on sign: the benchmark writes force = M qdd + Fv qd + Fc sign(qd) + offset; our
``torque_offset`` adds to the applied force, so ``offset_benchmark = -torque_offset.offset``.
The injection point of ``pulses_N`` is in a Simulink file that is not available; the
validation is run with the pulses ignored and with them added to the force [N], and both are
reported.

Usage: ``python studies/ident_emps.py [--data DIR] [--out DIR] [--small]``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

PUBLISHED = {
    "params": {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648},
    "DATA_EMPS": {"position": 0.013752, "velocity": 0.22911, "acceleration": 8.6036,
                  "force": 5.848},
    "DATA_EMPS_PULSES": {"position": 0.0080248, "velocity": 0.47888, "acceleration": 19.8152,
                         "force": 8.9409},
}
MAPPING = {"t": "t", "tau": "gtau*vir", "q1": "qm", "q2": "qm", "q1d": "qg"}
J_FIXED = 1e-3  # kg; the rigid model identifies Jx = I + J, J is a fixed small share


def default_data_dir() -> Path:
    """The EMPS files shipped with jaxflex (``jaxflex/data``)."""
    import jaxflex.data

    return Path(jaxflex.data.__file__).parent


def closed_loop(plant, qg, dt, gains, pulses=None, substeps=2):
    """The benchmark's closed loop (SOURCE.md) around the rigid model; returns (q, force)."""
    import jax
    import jax.numpy as jnp

    from jaxflex.step import rigid_step

    kp, kv, gtau = gains
    pulses = jnp.zeros_like(qg) if pulses is None else jnp.asarray(pulses, float)
    x0 = plant.init_state(q1=qg[0])

    def body(carry, inp):
        x, qm_prev, qf_prev = carry
        r, d = inp
        qm = x.q1[0]
        qf = 0.5 * qm + 0.5 * qm_prev
        qd = (qf - qf_prev) / dt
        vir = jnp.clip(kp * kv * (r - qm) - kv * qd, -10.0, 10.0)
        force = gtau * vir
        x = rigid_step(plant, x, jnp.atleast_1d(force + d), dt, substeps)
        return (x, qm, qf), (qm, force)

    q0 = jnp.asarray(qg[0], float)
    _, (q, f) = jax.lax.scan(body, (x0, q0, q0), (jnp.asarray(qg, float), pulses))
    return np.asarray(q), np.asarray(f)


def measured_derivatives(q, dt):
    """Velocity and acceleration of the measured position: 4th-order 100 Hz Butterworth
    filtfilt, then central differences (the benchmark's processing)."""
    from scipy.signal import butter, filtfilt

    b, a = butter(4, 100.0 / (0.5 / dt))
    qf = filtfilt(b, a, q)
    v = np.gradient(qf, dt)
    return qf, v, np.gradient(v, dt)


def rel_err(y, yh, drop=49):
    """100 ||y - y_hat|| / ||y|| [%] after dropping ``drop`` samples."""
    y, yh = y[drop:], yh[drop:]
    return float(100 * np.linalg.norm(y - yh) / np.linalg.norm(y))


def validate(params, path, dt_gains, substeps, pulses_mode):
    """Closed-loop simulation errors [%] on one data file."""
    import jax.numpy as jnp
    import scipy.io

    raw = scipy.io.loadmat(path)
    qm, qg = raw["qm"].ravel(), raw["qg"].ravel()
    force_meas = float(raw["gtau"].ravel()[0]) * raw["vir"].ravel()
    dt = float(np.mean(np.diff(raw["t"].ravel())))
    gains = tuple(float(raw[k].ravel()[0]) for k in ("kp", "kv", "gtau"))
    pulses = None
    if pulses_mode == "force" and "pulses_N" in raw:
        pulses = raw["pulses_N"].ravel().astype(float)
    q_sim, f_sim = closed_loop(params.to_plant(), jnp.asarray(qg), dt, gains,
                               None if pulses is None else jnp.asarray(pulses), substeps)
    _, v_meas, a_meas = measured_derivatives(qm, dt)
    v_sim = np.gradient(q_sim, dt)
    a_sim = np.gradient(v_sim, dt)
    return {"position": rel_err(qm, q_sim), "velocity": rel_err(v_meas, v_sim),
            "acceleration": rel_err(a_meas, a_sim), "force": rel_err(force_meas, f_sim)}, (
        raw["t"].ravel(), qm, q_sim, force_meas, f_sim)


def initial_params():
    """A deliberately rough start: mass 60 kg, Coulomb 10 N, viscous 100 N s/m, no offset."""
    from jaxflex.params import Params

    return Params.from_dict({
        "plant": {"I": 60.0, "J": J_FIXED, "K": 1e6},
        "friction": {"Fc": 10.0, "Fs": 12.0, "vs": 0.02, "sigma0": 1e6, "sigma1": 2e3,
                     "sigma2": 100.0},
        "effects": {"torque_offset": {"offset": [0.0]}},
    })


def main(argv=None) -> dict:
    """Run the study; returns the results dict (also written to ``results.json``)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxflex.identify import IdentificationWarning, identify
    from jaxflex.logs import load_log
    from jaxflex.params import save_params
    from jaxflex.plots.identify import plot_fit, plot_validation

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(default_data_dir()), help="folder with the EMPS .mat")
    ap.add_argument("--out", default="out/ident_emps")
    ap.add_argument("--small", action="store_true", help="fit on the first 5 s only")
    ap.add_argument("--segment", type=int, default=1000)
    ap.add_argument("--substeps", type=int, default=2)
    args = ap.parse_args(argv)
    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    est, val = data / "DATA_EMPS.mat", data / "DATA_EMPS_PULSES.mat"
    for f in (est, val):
        if not f.exists():
            raise FileNotFoundError(f"EMPS data file not found: {f} (pass --data DIR)")
    log = load_log(est, MAPPING)
    if args.small:
        log = log.slice(0, 5000)
    free = ["I", "Fc", "Fs", "vs", "sigma2", "torque_offset.offset"]
    print(f"[emps] identifying {free} from {log.N} samples, segments of {args.segment}")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        res = identify(log, initial_params(), free, model="rigid",
                       segment_length=min(args.segment, log.N), substeps=args.substeps,
                       max_steps=100, progress=10, rtol=1e-8, atol=1e-8)
    wall = time.perf_counter() - t0
    print(res.table())
    save_params(res.params, out / "emps_params.json")
    plot_fit(res, out / "emps_fit.png")
    p = res.params
    ours = {"M": p.plant["I"][0] + p.plant["J"][0], "Fv": p.friction["sigma2"][0],
            "Fc": p.friction["Fc"][0], "Fs": p.friction["Fs"][0], "vs": p.friction["vs"][0],
            "offset": -p.effects["torque_offset"]["offset"][0]}
    se = {"M": res.stderr["I"][0], "Fv": res.stderr["sigma2"][0], "Fc": res.stderr["Fc"][0],
          "Fs": res.stderr["Fs"][0], "vs": res.stderr["vs"][0],
          "offset": res.stderr["torque_offset.offset"][0]}
    results = {"identified": ours, "stderr": se, "published_params": PUBLISHED["params"],
               "identify_wall_s": wall, "steps": res.steps, "rms_residual_m": res.rms,
               "warnings": res.warnings, "validation": {}}
    for name, path in (("DATA_EMPS", est), ("DATA_EMPS_PULSES", val)):
        modes = ("none",) if name == "DATA_EMPS" else ("none", "force")
        for mode in modes:
            errs, (t, qm, qs, fm, fs) = validate(p, path, None, args.substeps, mode)
            key = name if mode == "none" else f"{name} (pulses added to force)"
            results["validation"][key] = {"ours": errs, "published": PUBLISHED[name]}
            plot_validation(t, {"position (m)": (qm, qs), "force (N)": (fm, fs)},
                            out / f"validation_{name}_{mode}.png",
                            title=f"{name}: closed-loop simulation, pulses: {mode}")
    lines = ["| data | quantity | ours (%) | published IDIM-LS (%) |", "|---|---|---|---|"]
    for key, v in results["validation"].items():
        for q in ("position", "velocity", "acceleration", "force"):
            lines.append(f"| {key} | {q} | {v['ours'][q]:.4g} | {v['published'][q]:.4g} |")
    lines += ["", "| parameter | ours | stderr | published |", "|---|---|---|---|"]
    for k in ("M", "Fv", "Fc", "offset"):
        lines.append(f"| {k} | {ours[k]:.4f} | {se[k]:.3g} | {PUBLISHED['params'][k]:.4f} |")
    lines.append(f"| Fs | {ours['Fs']:.4f} | {se['Fs']:.3g} | (Coulomb model) |")
    lines.append(f"| vs | {ours['vs']:.4g} | {se['vs']:.3g} | (Coulomb model) |")
    table = "\n".join(lines)
    print(table)
    (out / "table.md").write_text(table + "\n")
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


if __name__ == "__main__":
    main()

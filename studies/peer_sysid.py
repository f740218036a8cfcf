"""Peer benchmark: MuJoCo's own system identification against jaxflex's, on each other's logs.

Question: on an open-loop log of a rigid hinge with friction (a torque multisine, an encoder's
quantisation; true inertia, viscous and Coulomb friction known), started from the same start
40-50% off, how long do ``mujoco.sysid`` (Levenberg-Marquardt on finite-difference Jacobians
of MuJoCo rollouts of the true MJCF, its three physical parameters free, with its default
scaling and with ``x_scale="jac"``) and ``jaxflex.identify`` (the rigid model eq. 37 with
LuGre friction eq. 4-6, multiple shooting, forward-mode Jacobians through its own integrator;
a first, cold call with compilation and a second, warm one in the same process) take, how
close do they come to the true physical quantities the two models share (inertia Jx = I + J,
viscous sigma2 = MuJoCo's joint ``damping``, Coulomb Fc = MuJoCo's ``frictionloss``; LuGre's
sigma0, sigma1, Fs, vs have no MuJoCo counterpart and are only reported), do the standard
errors each reports cover its true error, and does each say it succeeded? Two logs of the
same experiment: ``mujoco_log``, made by MuJoCo with the very MJCF sysid fits (sysid's home
game: jaxflex's error there includes the mismatch of friction model and integrator), and
``jaxflex_log``, made by jaxflex's rigid model with a near-Coulomb LuGre (jaxflex's home
game: sysid's MuJoCo hinge then fits a model that is not the data's).

Writes ``DIR/results.json`` (versions, settings, BLAS threads, load, per log and method:
times, iterations, errors, standard errors, success flags, the ratio table) and
``DIR/peer_sysid.png``.

Usage: ``python studies/peer_sysid.py --out DIR [--small]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchkit  # noqa: E402

BLAS = benchkit.limit_blas_threads(1)

import argparse  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

#: The true hinge: link inertia I and rotor armature J [kg m^2] (Jx = I + J, eq. 37), joint
#: damping [N m s/rad] and frictionloss [N m] (the paper's sigma2 and Fc, docs/spec.md).
TRUTH: dict[str, float] = {"I": 0.07, "J": 0.005, "damping": 0.2, "frictionloss": 0.11}
#: The common start: each free physical quantity this factor off its truth.
START_FACTORS: dict[str, float] = {"I": 1.4, "damping": 0.6, "frictionloss": 1.5}
#: MuJoCo's physics step [s] (5 per 1 kHz log sample) and the encoder (counts per turn).
PHYSICS_DT: float = 2e-4
LOG_DT: float = 1e-3
COUNTS: int = 2**16
#: The shared quantities: name here -> (MuJoCo parameter, jaxflex parameter).
COMMON: dict[str, tuple[str, str]] = {"Jx": ("inertia", "Jx"), "viscous": ("damping", "sigma2"),
                                      "coulomb": ("frictionloss", "Fc")}

XML = """<mujoco model="rigid_hinge">
  <option timestep="{h}" integrator="implicitfast" gravity="0 0 0"/>
  <worldbody>
    <body name="link">
      <joint name="hinge" type="hinge" axis="0 1 0" armature="{J}" damping="{damping}"
             frictionloss="{frictionloss}" solreffriction="{sr} 1"/>
      <inertial pos="0 0 0" mass="1" diaginertia="{I} {I} {I}"/>
    </body>
  </worldbody>
  <actuator><motor name="motor" joint="hinge"/></actuator>
  <sensor><jointpos name="q" joint="hinge"/></sensor>
</mujoco>"""


def mjcf(p: dict[str, float]) -> str:
    """The MJCF of the hinge with parameters ``p`` (``TRUTH``'s keys)."""
    return XML.format(h=PHYSICS_DT, sr=4 * PHYSICS_DT, **{k: f"{v:.12g}" for k, v in p.items()})


def multisine(t: np.ndarray, rng: np.random.Generator, peak: float = 0.6) -> np.ndarray:
    """Torque [N m]: 12 sines 0.2-4 Hz with random phases, scaled to ``peak``."""
    f = np.linspace(0.2, 4.0, 12)
    ph = rng.uniform(0, 2 * np.pi, f.size)
    u = np.sin(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]).sum(0)
    return peak * u / np.max(np.abs(u))


def quantise(q: np.ndarray) -> np.ndarray:
    """The encoder: ``COUNTS`` per turn, no noise [rad]."""
    res = 2 * np.pi / COUNTS
    return res * np.round(q / res)


def mujoco_log(t_final: float, seed: int):
    """Simulate the true hinge in MuJoCo (``mujoco.rollout``) under the multisine held over
    each 1 ms sample and quantise the angle. Returns the jaxflex ``Log``."""
    import mujoco
    import mujoco.rollout as rollout

    from jaxflex.io.logs import Log

    model = mujoco.MjModel.from_xml_string(mjcf(TRUTH))
    data = mujoco.MjData(model)
    sub = int(round(LOG_DT / PHYSICS_DT))
    t = np.arange(int(round(t_final / LOG_DT))) * LOG_DT
    tau = multisine(t, np.random.default_rng(seed))
    x0 = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(model, data, x0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    _, sens = rollout.rollout(model, data, x0, np.repeat(tau, sub)[:, None])
    q = np.concatenate([[0.0], sens[0, sub - 1::sub, 0][:-1]])  # q(t_k): before tau[k] acts
    qm = quantise(q)
    return Log.from_arrays(t=t, tau=tau, q1=qm, q2=qm,
                           source=f"MuJoCo {mujoco.__version__} rigid hinge, seed {seed}")


#: The jaxflex-made log's LuGre (near-Coulomb: no Stribeck hump, stiff bristles) with
#: TRUTH's inertia, viscous and Coulomb levels, so that MuJoCo's hinge can represent it.
JAXFLEX_FRICTION: dict[str, float] = {"Fc": TRUTH["frictionloss"], "Fs": TRUTH["frictionloss"],
                                      "vs": 0.05, "sigma0": 1e4, "sigma1": 1.0,
                                      "sigma2": TRUTH["damping"]}


def jaxflex_log(t_final: float, seed: int):
    """The same experiment replayed through jaxflex's rigid model (eq. 37, ``synthetic_log``,
    4 RK4 substeps per sample) with ``JAXFLEX_FRICTION``, quantised alike."""
    from jaxflex.identify import synthetic_log
    from jaxflex.io.logs import Log
    from jaxflex.io.params import Params

    t = np.arange(int(round(t_final / LOG_DT))) * LOG_DT
    tau = multisine(t, np.random.default_rng(seed))
    p = Params.from_dict({"plant": {"I": TRUTH["I"], "J": TRUTH["J"], "K": 1e3},
                          "friction": JAXFLEX_FRICTION})
    log, _ = synthetic_log(p.to_plant(), tau[:, None], dt=LOG_DT, model="rigid")
    qm = quantise(np.asarray(log.q1)[:, 0])
    return Log.from_arrays(t=t, tau=tau, q1=qm, q2=qm, source=f"jaxflex rigid LuGre, seed {seed}")


def sysid_inputs(log) -> dict[str, Any]:
    """What sysid takes from a log: the initial state (rest at the first angle), the torque
    held over each sample at MuJoCo's step (so that sysid's linear resampling is exact) and
    the angle series (its first sample, the initial state, left out)."""
    import mujoco
    from mujoco import sysid

    model = mujoco.MjModel.from_xml_string(mjcf(TRUTH))
    data = mujoco.MjData(model)
    t, tau, q = np.asarray(log.t), np.asarray(log.tau)[:, 0], np.asarray(log.q1)[:, 0]
    data.qpos[0] = q[0]
    sub = int(round(LOG_DT / PHYSICS_DT))
    x0 = sysid.create_initial_state(model, data.qpos, data.qvel, data.act)
    return {"x0": x0,
            "control": sysid.TimeSeries(np.arange(t.size * sub) * PHYSICS_DT,
                                        np.repeat(tau, sub)[:, None]),
            "sensor": sysid.TimeSeries.from_names(t[1:], q[1:, None], model)}


def run_sysid(d: dict[str, Any], start: dict[str, float], x_scale: Any,
              max_iters: int) -> dict[str, Any]:
    """``mujoco.sysid.optimize`` (backend "mujoco") from ``start`` on the true MJCF with the
    link inertia, damping and frictionloss free (armature fixed at its truth, as jaxflex's J),
    bounds start/5 .. start*5; 95% intervals by ``sysid.calculate_intervals``."""
    import mujoco
    from mujoco import sysid
    from scipy.special import stdtrit

    spec = mujoco.MjSpec.from_string(mjcf(TRUTH))

    def set_inertia(s, p):
        s.body("link").inertia = [p.value[0]] * 3

    def set_damping(s, p):
        s.joint("hinge").damping = [p.value[0], 0.0, 0.0]  # MuJoCo 4: [linear, higher orders]

    def set_frictionloss(s, p):
        s.joint("hinge").frictionloss = p.value[0]

    params = sysid.ParameterDict()
    mods = {"inertia": set_inertia, "damping": set_damping, "frictionloss": set_frictionloss}
    for name, mod in mods.items():
        v = start["I" if name == "inertia" else name]
        params.add(sysid.Parameter(name, nominal=v, min_value=v / 5, max_value=v * 5,
                                   modifier=mod))
    ms = sysid.ModelSequences("hinge", spec, "multisine", d["x0"], d["control"], d["sensor"])
    residual_fn = sysid.build_residual_fn(models_sequences=[ms])
    out = io.StringIO()
    kw = {} if x_scale is None else {"x_scale": x_scale}
    t0 = time.perf_counter()
    opt, res = sysid.optimize(params, residual_fn, optimizer="mujoco", verbose=False,
                              max_iters=max_iters, output=out, **kw)
    wall = time.perf_counter() - t0
    text = out.getvalue()
    m = re.search(r"Terminated after (\d+) iterations: ([^y]*?)\s+y: ([0-9.eE+-]+), "
                  r"Residual evals: (\d+)", text)
    status = m.group(2).strip() if m else "unknown"
    x = opt.as_vector()
    r = np.concatenate(residual_fn(x, opt)[0])
    dof = r.size - x.size
    _, half = sysid.calculate_intervals([r], res.jac)
    se = half / stdtrit(dof, 0.975)
    J = np.asarray(res.jac)
    se_gn = np.sqrt(np.diag(float(r @ r) / dof * np.linalg.pinv(J.T @ J)))
    names = list(mods)
    return {"x_scale": x_scale, "wall_s": wall, "iterations": int(m.group(1)) if m else None,
            "residual_evals": int(m.group(4)) if m else None, "status": status,
            "success": status in ("norm(dx) < tol.", "norm(gradient) < tol."),
            "final_objective": float(m.group(3)) if m else None,
            "values": dict(zip(names, map(float, x))), "stderr": dict(zip(names, map(float, se))),
            "ci95_half": dict(zip(names, map(float, half))),
            "stderr_gn": dict(zip(names, map(float, se_gn)))}


#: The LuGre-only parameters' start: ``JAXFLEX_FRICTION`` this factor off (MuJoCo's log has
#: no truth for them; its frictionloss is nearest to that near-Coulomb LuGre).
LUGRE_START_FACTORS: dict[str, float] = {"sigma0": 0.6, "sigma1": 1.5, "vs": 1.4}


def jaxflex_start(start: dict[str, float]):
    """The jaxflex rigid start: I, sigma2, Fc from the common start; J at its truth; Fs just
    above Fc; vs, sigma0, sigma1 ``LUGRE_START_FACTORS`` off ``JAXFLEX_FRICTION``."""
    from jaxflex.io.params import Params

    fr = {k: JAXFLEX_FRICTION[k] * LUGRE_START_FACTORS.get(k, 1.0) for k in JAXFLEX_FRICTION}
    fr.update(Fc=start["frictionloss"], Fs=1.05 * start["frictionloss"], sigma2=start["damping"])
    return Params.from_dict({"plant": {"I": start["I"], "J": TRUTH["J"], "K": 1e3},
                             "friction": fr})


def run_jaxflex(log, init, same_start: bool) -> dict[str, Any]:
    """``jaxflex.identify`` (rigid, default free set: six LuGre parameters and I) twice in this
    process: cold (with compilation) then warm. ``same_start``: only the given start
    (no static-map or inverse-dynamics starts); else identify's own extra starts too."""
    import jax

    from jaxflex.identify import DEFAULT_FREE, identify

    # the six LuGre parameters and the inertia I (J is fixed in both tools)
    kw = dict(model="rigid", free=[*DEFAULT_FREE, "I"], static_start=not same_start,
              data_start=not same_start)
    walls, r = [], None
    for _ in range(2):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = identify(log, init, **kw)
        jax.block_until_ready(r.solution)
        walls.append(time.perf_counter() - t0)
    p = r.params
    val = {k: float(np.asarray(p.friction[k])[0]) for k in p.friction}
    val["I"] = float(np.asarray(p.plant["I"])[0])
    val["Jx"] = val["I"] + TRUTH["J"]
    se = {k: float(v[0]) for k, v in r.stderr.items()}
    se["Jx"] = se.get("I", math.nan)
    return {"cold_s": walls[0], "warm_s": walls[1], "compile_estimate_s": walls[0] - walls[1],
            "steps": int(r.steps), "success": bool(r.converged), "model_verdict": r.model,
            "reason": r.reason, "cost": float(r.cost), "noise_cost": float(r.noise_cost),
            "values": val, "stderr": se, "unidentifiable": list(r.unidentifiable),
            "attempts": len(r.attempts), "settings": kw}


def compare(values: dict[str, float], stderr: dict[str, float], which: int) -> dict[str, Any]:
    """Relative errors of the shared quantities against the truth (the same on both logs)
    and |error| / stderr."""
    truth = {"Jx": TRUTH["I"] + TRUTH["J"], "viscous": TRUTH["damping"],
             "coulomb": TRUTH["frictionloss"]}
    out = {}
    for q, names in COMMON.items():
        n = names[which]
        v = values[n] + (TRUTH["J"] if n == "inertia" else 0.0)
        e = v - truth[q]
        s = stderr.get(n, math.nan)
        out[q] = {"value": v, "true": truth[q], "rel_error": e / truth[q], "stderr": s,
                  "error_over_stderr": abs(e) / s if s and s > 0 else math.nan}
    out["max_abs_rel_error"] = max(abs(out[q]["rel_error"]) for q in COMMON)
    return out


def run_log(log, max_iters: int, own_starts: bool) -> dict[str, Any]:
    """Both tools on one log from the common start: sysid with default and "jac" scaling,
    jaxflex from that start alone (and, with ``own_starts``, with its own extra starts); the
    ratio table jaxflex time / sysid time where jaxflex's worst shared error is at most
    sysid's (equal or better parameter error), else null with both errors."""
    start = {k: TRUTH[k] * START_FACTORS[k] for k in START_FACTORS}
    d = sysid_inputs(log)
    methods: dict[str, Any] = {}
    for label, xs in (("sysid_default", None), ("sysid_xscale_jac", "jac")):
        r = run_sysid(d, start, xs, max_iters)
        r["compare"] = compare(r["values"], r["stderr"], 0)
        methods[label] = r
        print(f"  {label}: {r['wall_s']:.2f} s, {r['iterations']} it, {r['status']}, "
              f"max rel err {r['compare']['max_abs_rel_error']:.2e}", flush=True)
    init = jaxflex_start(start)
    for label, same in (("jaxflex_same_start", True), ("jaxflex_own_starts", False)):
        if not same and not own_starts:
            continue
        r = run_jaxflex(log, init, same)
        r["compare"] = compare(r["values"], r["stderr"], 1)
        methods[label] = r
        print(f"  {label}: cold {r['cold_s']:.2f} s, warm {r['warm_s']:.2f} s, {r['steps']} "
              f"steps, converged {r['success']}, max rel err "
              f"{r['compare']['max_abs_rel_error']:.2e}", flush=True)
    ratios = []
    for jl in [k for k in methods if k.startswith("jaxflex")]:
        for sl in [k for k in methods if k.startswith("sysid")]:
            j, s = methods[jl], methods[sl]
            ej, es = j["compare"]["max_abs_rel_error"], s["compare"]["max_abs_rel_error"]
            ok = ej <= es
            ratios.append({"jaxflex": jl, "sysid": sl, "jaxflex_err": ej, "sysid_err": es,
                           "equal_or_better": ok,
                           "warm_ratio": j["warm_s"] / s["wall_s"] if ok else None,
                           "cold_ratio": j["cold_s"] / s["wall_s"] if ok else None,
                           "warm_ratio_any_error": j["warm_s"] / s["wall_s"]})
    return {"start": start, "methods": methods, "ratios": ratios}


def print_ratios(name: str, ratios: list[dict[str, Any]]) -> None:
    """The ratio table of one log."""
    print(f"\n{name}: {'jaxflex':20s} {'sysid':17s} {'err jf':>9s} {'err sysid':>9s} "
          f"{'warm/sysid':>10s} {'cold/sysid':>10s} {'warm/sysid any err':>18s}")
    f = (lambda v: f"{v:10.2f}" if v is not None else f"{'n/a':>10s}")
    for r in ratios:
        print(f"{name}: {r['jaxflex']:20s} {r['sysid']:17s} {r['jaxflex_err']:9.2e} "
              f"{r['sysid_err']:9.2e} {f(r['warm_ratio'])} {f(r['cold_ratio'])} "
              f"{r['warm_ratio_any_error']:18.2f}")


def main(argv: list[str] | None = None) -> dict:
    """Run the study; returns the results dict (also written to ``results.json``)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--small", action="store_true",
                    help="3 s logs, 30 sysid iterations")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--own-starts", action="store_true",
                    help="also time jaxflex with its own extra starts (static map, data)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import jax

    jax.config.update("jax_enable_x64", True)
    import mujoco

    import jaxflex

    t_final = 3.0 if args.small else 15.0
    max_iters = 30 if args.small else 100
    load = [list(np.round(benchkit.machine_state()["load_avg"], 2))]
    logs = {}
    for name, make in (("mujoco_log", mujoco_log), ("jaxflex_log", jaxflex_log)):
        log = make(t_final, args.seed)
        q = np.asarray(log.q1)[:, 0]
        print(f"{name}: {log.source}", flush=True)
        logs[name] = {"source": log.source, "q_range_rad": float(np.ptp(q)),
                      "v_max_rad_s": float(np.max(np.abs(np.diff(q))) / LOG_DT),
                      **run_log(log, max_iters, own_starts=args.own_starts)}
        load.append(list(np.round(benchkit.machine_state()["load_avg"], 2)))
    for name, r in logs.items():
        print_ratios(name, r["ratios"])

    results = {
        "question": __doc__.split("\n\n")[1],
        "versions": {"mujoco": mujoco.__version__, "jaxflex": getattr(jaxflex, "__version__", "?"),
                     "jax": jax.__version__, "numpy": np.__version__},
        "blas": BLAS, "load_avg_per_stage": load, "cpu_count": benchkit.machine_state()["cpu_count"],
        "experiment": {"t_final_s": t_final, "dt_s": LOG_DT, "encoder_counts_per_turn": COUNTS,
                       "excitation": "open-loop multisine 0.2-4 Hz, 12 sines, peak 0.6 N m, "
                                     "held over each sample", "seed": args.seed,
                       "mujoco_log": f"mujoco.rollout of the true MJCF, implicitfast, "
                                     f"step {PHYSICS_DT} s, frictionloss with solreffriction "
                                     f"{4 * PHYSICS_DT} s",
                       "jaxflex_log": {"model": "rigid (eq. 37), 4 RK4 substeps",
                                       "friction": JAXFLEX_FRICTION}},
        "truth": TRUTH, "start_factors": START_FACTORS,
        "settings": {
            "sysid": {"optimizer": "mujoco (mujoco.minimize.least_squares)",
                      "max_iters": max_iters, "free": ["inertia", "damping", "frictionloss"],
                      "bounds": "start/5 .. start*5", "model": "the MJCF that made mujoco_log "
                      "(with its step and friction constraint)", "residual": "jointpos, "
                      "sysid's defaults (normalised by the measured signal's norm)",
                      "intervals": "sysid.calculate_intervals, 95%; stderr = half-width / "
                                   "t(0.975, dof); stderr_gn: sqrt(diag(s2 (J'J)^-1))",
                      "timing": "one run each (no compilation)"},
            "jaxflex": {"model": "rigid (eq. 37) + LuGre (eq. 4-6)", "identify": "defaults "
                        "(substeps auto, segment_length auto, max_steps 200)",
                        "start": "I, sigma2, Fc as sysid's; J true; Fs = 1.05 Fc; vs, "
                                 "sigma0, sigma1 LUGRE_START_FACTORS off JAXFLEX_FRICTION",
                        "lugre_start_factors": LUGRE_START_FACTORS,
                        "stderr": "IdentResult.stderr (segment-robust where available)",
                        "timing": "cold: first call on the log (compilation included; "
                                  "jaxflex_log runs after mujoco_log in the same process, so "
                                  "its cold call may reuse programs compiled for the first "
                                  "log); warm: the same call again; no trace cache on disk"}},
        "common_quantities": {"note": "MuJoCo's damping and frictionloss (a soft constraint) "
                              "against LuGre's sigma2 and Fc; Jx = I + J with J fixed at its "
                              "truth in both. LuGre's sigma0, sigma1, Fs, vs have no MuJoCo "
                              "counterpart (reported under values, not compared)",
                              "map": COMMON},
        "logs": logs,
    }
    (out / "results.json").write_text(json.dumps(results, indent=1, default=str))
    try:
        figure(logs, out / "peer_sysid.png")
    except Exception as e:  # a figure is optional; the numbers are the result
        print(f"no figure: {e}")
    return results


def figure(logs: dict[str, Any], path: Path) -> None:
    """Relative error of each shared quantity per method and log, with +-1 reported stderr."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(logs), figsize=(5 * len(logs), 3.5), squeeze=False)
    for ax, (name, lg) in zip(axes[0], logs.items()):
        ms = lg["methods"]
        for i, (label, m) in enumerate(ms.items()):
            c = m["compare"]
            x = np.arange(len(COMMON)) + 0.15 * (i - (len(ms) - 1) / 2)
            y = [100 * c[q]["rel_error"] for q in COMMON]
            e = [100 * c[q]["stderr"] / c[q]["true"] for q in COMMON]
            ax.errorbar(x, y, yerr=e, fmt="o", capsize=3, label=label)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xticks(range(len(COMMON)), list(COMMON))
        ax.set_title(name)
        ax.set_ylabel("error vs truth [%] (bars: reported stderr)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()

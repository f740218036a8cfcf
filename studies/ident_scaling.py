"""Study: how does identification scale with the log length, and does it converge on logs of
the lengths a lab records?

Logs: closed-loop identification experiments of ``jaxflex.identify.datagen.generate_log`` (the cascade
controller tracking a random multisine around a plant 10% off the nominal one), a fine 20-bit
encoder with half a count of white noise, 1 kHz, of 3, 10, 20 and 60 s. Start: the six LuGre
parameters 50% off the truth (x1.5 or x0.5). Segments of 300 samples, 2 substeps.

Measured, per log length, in one process (compilation timed apart):
- one Levenberg-Marquardt step (Jacobian + damped normal equations) with the dense solve
  (Jacobian materialised, m x p) and with the structured multiple-shooting solve
  (block-tridiagonal + Schur complement), each warm, min and median of ``--repeat`` runs;
- ``identify`` end to end (first call, including compilation, and a second, warm call):
  converged or not, steps, the largest relative parameter error.
Writes ``results.json`` and ``scaling.png`` (step time against log length) to ``--out``.
BLAS threads and the machine load are recorded; this is a shared 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np


def _timed(fn, repeat):
    out, times = None, []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, {"min": min(times), "median": float(np.median(times)), "all": times}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/ident_scaling")
    ap.add_argument("--lengths", default="3,10,20,60", help="log lengths [s]")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dense-max", type=float, default=20.0,
                    help="longest log [s] for which the dense solve is timed (memory, time)")
    ap.add_argument("--small", action="store_true", help="3 s and 6 s logs, one repeat")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import lineax as lx

    from jaxflex.identify.datagen import generate_log
    from jaxflex.fit.normal import dense_newton_step, shooting_newton_step
    from jaxflex.identify import DEFAULT_FREE, IdentificationWarning, identify, make_problem, perturb
    from jaxflex.io.params import Params

    lengths = [3.0, 6.0] if a.small else [float(s) for s in a.lengths.split(",")]
    repeat = 1 if a.small else a.repeat
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    @eqx.filter_jit
    def one_step(prob, y, structured):
        r, lin = jax.linearize(prob.residuals, y)
        jac = lx.FunctionLinearOperator(lin, jax.eval_shape(lambda: y))
        solve = shooting_newton_step if structured else dense_newton_step
        return solve(jac, r, jnp.asarray(1e-3), "identity")

    rows = []
    for T in lengths:
        g = generate_log((), seed=7, t_final=T, bits=20, noise_counts=0.5)
        truth = Params.from_dict(g.truth["plant"])
        init = perturb(truth, DEFAULT_FREE, (1.5, 1.5, 0.5, 1.5, 0.5, 1.5))
        prob, y0 = make_problem(g.log, init, DEFAULT_FREE, segment_length=300, substeps=2)
        row = {"log_s": T, "samples": g.log.N, "segments": prob.segs.count,
               "unknowns": int(sum(np.size(v) for v in jax.tree_util.tree_leaves(y0))),
               "residuals": int(prob.residuals(y0).size)}
        for name, structured in (("shooting", True), ("dense", False)):
            if not structured and T > a.dense_max:
                continue
            t = time.perf_counter()
            jax.block_until_ready(one_step(prob, y0, structured))
            compile_s = time.perf_counter() - t
            _, tm = _timed(lambda s=structured: jax.block_until_ready(one_step(prob, y0, s)),
                           repeat)
            row[f"step_{name}"] = tm | {"first_call_s": compile_s}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IdentificationWarning)
            for which in ("first", "warm"):
                t = time.perf_counter()
                r = identify(g.log, init, DEFAULT_FREE, segment_length=300, substeps=2,
                             max_steps=100)
                row[f"identify_{which}_s"] = time.perf_counter() - t
        err = {k: abs(r.params.friction[k][0] / truth.friction[k][0] - 1) for k in DEFAULT_FREE}
        row.update({"converged": r.converged, "reason": r.reason, "steps": r.steps,
                    "max_rel_error": max(err.values()), "rel_errors": err,
                    "unidentified": r.unidentifiable})
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "rel_errors"}, default=str),
              flush=True)
    try:
        from threadpoolctl import threadpool_info

        blas = [{k: i.get(k) for k in ("internal_api", "num_threads")} for i in threadpool_info()]
    except ImportError:
        blas = "threadpoolctl not installed"
    res = {"rows": rows, "load_average": os.getloadavg(), "cpus": os.cpu_count(),
           "blas": blas, "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "note": "step times warm (compilation in first_call_s); identify_first_s includes "
                   "compilation, identify_warm_s reuses it in the same process"}
    if len(rows) >= 2:
        Ts = np.array([r["log_s"] for r in rows])
        st = np.array([r["step_shooting"]["min"] for r in rows])
        res["shooting_step_growth_exponent"] = float(np.polyfit(np.log(Ts), np.log(st), 1)[0])
        dn = [(r["log_s"], r["step_dense"]["min"]) for r in rows if "step_dense" in r]
        if len(dn) >= 2:
            x, y = np.array(dn).T
            res["dense_step_growth_exponent"] = float(np.polyfit(np.log(x), np.log(y), 1)[0])
    (out / "results.json").write_text(json.dumps(res, indent=2, default=str) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, mark in (("shooting", "o-"), ("dense", "s--")):
        pts = [(r["log_s"], r[f"step_{name}"]["min"]) for r in rows if f"step_{name}" in r]
        if pts:
            x, y = np.array(pts).T
            ax.loglog(x, 1e3 * y, mark, label=f"{name} solve")
    ax.set_xlabel("log length [s] (1 kHz)")
    ax.set_ylabel("one LM step, warm [ms]")
    ax.set_title("Identification step time against log length")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=110)
    plt.close(fig)
    return res


if __name__ == "__main__":
    main()

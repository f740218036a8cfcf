"""Benchmark: is gradient identification through the JAX simulator faster than scipy?

Question: on the same least-squares residual (``Problem.residuals``: multiple-shooting output
error of a synthetic flexible-joint log, all six LuGre parameters free plus the segment start
states) and the same starting point, in the same process, how long do optimistix
Levenberg-Marquardt (forward-mode Jacobian through the ``lax.scan`` simulator, jitted) and
``scipy.optimize.least_squares`` (finite-difference Jacobian, residual jitted, method "trf")
take to converge, and to what final cost?

Reported: wall time of each (JAX both with and without its one-off compilation), final cost
0.5 ||r||^2, steps and residual evaluations, and the speed ratio scipy / JAX.

Usage: ``python studies/ident_bench_scipy.py [--out DIR] [--small]``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> dict:
    """Run the benchmark; returns the results dict (also written to ``results.json``)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import optimistix as optx
    import scipy.optimize
    from jax.flatten_util import ravel_pytree

    from jaxflex.identify import (
        DEFAULT_FREE,
        excitation_torque,
        make_problem,
        perturb,
        synthetic_log,
    )
    from jaxflex.params import paper_params

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/ident_bench_scipy")
    ap.add_argument("--small", action="store_true", help="1 s log, 4 segments")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_final, L = (1.0, 250) if args.small else (2.0, 250)

    truth = paper_params()
    log, _ = synthetic_log(truth.to_plant(), excitation_torque(t_final=t_final,
                                                              periods=(1.5, 0.7)), substeps=2)
    init = perturb(truth, DEFAULT_FREE, (1.3, 0.85, 1.3, 0.8, 1.3, 0.8))
    prob, y0 = make_problem(log, init, DEFAULT_FREE, segment_length=L, substeps=2)
    flat0, unravel = ravel_pytree(y0)
    tol = 1e-10

    @eqx.filter_jit
    def solve(prob, y0):
        solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
        return optx.least_squares(prob.residuals, solver, y0, max_steps=500, throw=False)

    t = time.perf_counter()
    sol = jax.block_until_ready(solve(prob, y0))
    jax_first = time.perf_counter() - t
    t = time.perf_counter()
    sol = jax.block_until_ready(solve(prob, y0))
    jax_warm = time.perf_counter() - t
    r = np.asarray(prob.residuals(sol.value))
    jax_cost = 0.5 * float(r @ r)

    res_jit = jax.jit(lambda f: prob.residuals(unravel(f)))
    fun = lambda f: np.asarray(res_jit(jax.numpy.asarray(f)))
    fun(np.asarray(flat0))  # compile outside the timing
    t = time.perf_counter()
    ls = scipy.optimize.least_squares(fun, np.asarray(flat0), jac="2-point", method="trf",
                                      xtol=tol, ftol=tol, gtol=tol, max_nfev=20000)
    sp_wall = time.perf_counter() - t
    sp_cost = float(ls.cost)

    phys = lambda flat: {k: float(v[0]) for k, v in
                         prob.space.physical(unravel(jax.numpy.asarray(flat))[0]).items()}
    rel = lambda d: {k: d[k] / truth.friction[k][0] - 1 for k in d}
    results = {
        "unknowns": int(flat0.size), "residuals": int(r.size), "log_s": t_final,
        "jax": {"wall_s_with_compile": jax_first, "wall_s": jax_warm, "cost": jax_cost,
                "steps": int(sol.stats["num_steps"]), "result": str(sol.result),
                "rel_error": rel(phys(ravel_pytree(sol.value)[0]))},
        "scipy": {"wall_s": sp_wall, "cost": sp_cost, "nfev": int(ls.nfev),
                  "njev": int(ls.njev or 0), "status": int(ls.status),
                  "rel_error": rel(phys(ls.x))},
    }
    results["speed_ratio_warm"] = sp_wall / jax_warm
    results["speed_ratio_with_compile"] = sp_wall / jax_first
    results["cost_ratio_jax_over_scipy"] = jax_cost / sp_cost if sp_cost > 0 else float("nan")
    print(json.dumps(results, indent=2))
    print(f"scipy/JAX time ratio: {results['speed_ratio_warm']:.1f}x (JAX warm), "
          f"{results['speed_ratio_with_compile']:.1f}x (JAX incl. compile); final cost "
          f"JAX {jax_cost:.3e} vs scipy {sp_cost:.3e}")
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


if __name__ == "__main__":
    main()

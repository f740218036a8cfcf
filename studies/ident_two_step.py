"""Study: does the paper's two-step identification (section 5) recover the LuGre parameters?

Question: with realistic sensing (16-bit link encoder, 12-bit DAC, encoder noise), how close
do (1) the static-map fit of Fc, Fs, vs, sigma2 (eq. 35) to constant-velocity runs and (2) the
fit of sigma0, sigma1 on the rigid model Jx x'' = u - F (eq. 37-39) to an open-loop
stick-slip run of the *flexible* plant come to the true values, compared with the joint fit of
all six on the flexible model from the same stick-slip log?

Writes ``static_map.png``, ``two_step_fit.png``, ``joint_fit.png`` and ``results.json``.
Usage: ``python studies/ident_two_step.py [--out DIR] [--small]``.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings
from pathlib import Path

import numpy as np


def main(argv=None) -> dict:
    """Run the study; returns the results dict (also written to ``results.json``)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxflex.core.friction import LUGRE_NAMES
    from jaxflex.identify import (
        DEFAULT_FREE,
        IdentificationWarning,
        excitation_torque,
        identify,
        perturb,
        static_map_experiment,
        synthetic_log,
        two_step,
    )
    from jaxflex.io.presets import paper_params
    from jaxflex.app.plots import save_figure
    from jaxflex.app.plots.identify import plot_fit, plot_static_map
    from jaxflex.core.sensing import Sensing

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/ident_two_step")
    ap.add_argument("--small", action="store_true", help="short runs, no joint fit")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    truth = paper_params()
    plant = truth.to_plant()
    m = 5 if args.small else 10
    v = np.concatenate([-np.geomspace(0.005, 1.5, m), np.geomspace(0.005, 1.5, m)])
    res = 2 * math.pi / 2**16
    static = static_map_experiment(
        plant, v, sensing=Sensing(q1_resolution=res, q1_noise=2e-5, dac_bits=12, dac_range=2.0),
        run_time=4.0, substeps=2, key=jax.random.PRNGKey(0),
    )
    sens = Sensing(q1_resolution=res, q2_resolution=res / 50, q1_noise=2e-5, q2_noise=1e-6)
    t_final = 1.0 if args.small else 3.0
    log, _ = synthetic_log(plant, excitation_torque(t_final=t_final, periods=(1.5, 0.7)),
                           substeps=2, sensing=sens, key=jax.random.PRNGKey(1))
    init = perturb(truth, DEFAULT_FREE, (2.0, 0.6, 2.0, 0.5, 2.0, 0.5))
    steps = 20 if args.small else 100
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        ts = two_step(static, log, init, segment_length=250, substeps=2, max_steps=steps)
    lg = ts.params.to_lugre()
    save_figure(plot_static_map(
        static.v, static.F, lambda x: np.asarray(lg.steady_state(jnp.asarray(x))),
        true_curve=lambda x: np.asarray(truth.to_lugre().steady_state(jnp.asarray(x)))),
        out / "static_map.png")
    save_figure(plot_fit(ts.dynamic), out / "two_step_fit.png")
    rel = lambda p: {k: p.friction[k][0] / truth.friction[k][0] - 1 for k in LUGRE_NAMES}
    results = {
        "truth": truth.friction,
        "two_step": {"params": ts.params.friction, "rel_error": rel(ts.params),
                     "stderr": ts.params.extra["stderr"], "wall_s": ts.wall_s},
    }
    if not args.small:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IdentificationWarning)
            jf = identify(log, init, DEFAULT_FREE, segment_length=300, substeps=2,
                          max_steps=100)
        save_figure(plot_fit(jf), out / "joint_fit.png")
        results["joint"] = {"params": jf.params.friction, "rel_error": rel(jf.params),
                            "stderr": jf.stderr, "wall_s": jf.wall_s, "warnings": jf.warnings}
    print(json.dumps(results, indent=2))
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


if __name__ == "__main__":
    main()

"""Question: does the paper's cascade controller with LuGre friction compensation track better
than without it, on the paper's sinusoid (Fig. 9-11), polynomial (Fig. 12-14) and faster
motion (Fig. 15), and which of the three ways to get q2d' and q2d'' works?

Writes PNG figures and results.json (RMS and max link error in rad, torque RMS in N m) to
--out (default out/reproduce_paper). Same code path as ``jaxflex reproduce``: the paper's gains
with the observer leakage of ``jaxflex.io.presets.REPRODUCE_LEAK`` by default, the paper's own
observer re-run beside it (``paper_observer``; ``studies/observer_leak.py``).
"""

from __future__ import annotations

import argparse

import jax

from jaxflex.io.presets import SENSING_PRESETS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/reproduce_paper")
    ap.add_argument("--small", action="store_true", help="2 s runs (smoke test)")
    ap.add_argument("--sensing", default="paper", choices=SENSING_PRESETS)
    ap.add_argument("--estimator", default="kalman", choices=("filtered", "kalman"))
    ap.add_argument("--leak", type=float, default=None,
                    help="observer leakage [rad/s] (default: presets.REPRODUCE_LEAK; 0: the "
                    "paper's observer)")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    from jaxflex.io.progress import Printer
    from jaxflex.loop.experiments import run_paper_experiments
    from jaxflex.app.reports import write_paper_experiments

    results = run_paper_experiments(sensing=args.sensing, estimator=args.estimator, leak=args.leak,
                                    t_final=2.0 if args.small else 10.0, progress=Printer())
    write_paper_experiments(results, args.out)


if __name__ == "__main__":
    main()

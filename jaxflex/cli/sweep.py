"""``jaxflex sweep SPREAD.json``: Monte Carlo robustness sweep from a spread file.

Writes ``summary.json`` (quantiles, worst cases with their parameters, sensitivities, error
bands, timing), the figures, and with ``--keep-samples`` (the default) ``samples.csv`` of each
sample's parameters and metrics. Multi-process: start the same command in every process with
``--coordinator HOST:PORT --num-processes P --process-id i``; process 0 writes the files.
"""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``sweep`` subcommand."""
    p = subparsers.add_parser(
        "sweep", help="Monte Carlo robustness sweep (vmap, chunks, sharding, jax.distributed)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("spread", help="spread file (JSON; see jaxflex.sweep.spec)")
    p.add_argument("--out", default="out/sweep", help="output folder (default out/sweep)")
    p.add_argument("--samples", type=int, help="number of samples (overrides the file)")
    p.add_argument("--seed", type=int, help="random seed (overrides the file)")
    p.add_argument("--t-final", type=float, help="horizon per sample [s] (overrides the file)")
    p.add_argument("--chunk-size", type=int, default=256, help="samples per chunk (default 256)")
    p.add_argument("--no-compensation", action="store_true", help="run with F_hat = 0")
    p.add_argument("--no-shard", action="store_true", help="do not shard chunks over devices")
    p.add_argument("--no-samples", action="store_true", help="keep only fixed-size summaries")
    p.add_argument("--float32", action="store_true", help="single-precision loop (faster)")
    p.add_argument("--worst", type=int, default=10, help="worst cases to keep (default 10)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--coordinator", help="jax.distributed coordinator HOST:PORT")
    p.add_argument("--num-processes", type=int, default=1)
    p.add_argument("--process-id", type=int, default=0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the sweep and write its files; returns the exit status."""
    import json
    from pathlib import Path

    import jax
    import numpy as np

    from jaxflex.sweep import load_spread, nominal_run, run_sweep

    spec = load_spread(args.spread)  # validate before starting any process group
    if args.coordinator:
        jax.distributed.initialize(
            coordinator_address=args.coordinator, num_processes=args.num_processes,
            process_id=args.process_id,
        )
    changes = {}
    if args.samples is not None:
        changes["samples"] = args.samples
    if args.seed is not None:
        changes["seed"] = args.seed
    if args.t_final is not None:
        if not args.t_final >= spec.dt:
            raise ValueError(f"--t-final must be >= one controller period ({spec.dt} s)")
        changes["t_final"] = args.t_final
    if args.no_compensation:
        changes["compensation"] = False
    spec = spec.with_(**changes)
    res = run_sweep(
        spec, chunk_size=args.chunk_size, shard=not args.no_shard,
        keep_samples=not args.no_samples, n_worst=args.worst, progress=not args.no_progress,
        float32=args.float32,
    )
    if jax.process_index() == 0:
        from jaxflex.plots.sweep import plot_sweep

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        figs = plot_sweep(res, out, nominal=nominal_run(spec))
        doc = res.to_json()
        doc["figures"] = figs
        (out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n")
        if res.samples is not None:
            cols = spec.labels + ["rms_error", "max_error", "tau_rms", "saturation_fraction", "diverged"]
            s = res.samples
            table = np.column_stack([s["index"], s["theta"]] + [s[c] for c in cols[len(spec.labels):]])
            np.savetxt(out / "samples.csv", table, delimiter=",", header=",".join(["index"] + cols),
                       comments="", fmt="%.17g")
        m = res.summary["metrics"]["rms_error"]
        if res.summary["fs_raised_to_fc"]:
            print(f"note: {res.summary['fs_raised_to_fc']} sample(s) drew Fs < Fc; their Fs was "
                  "raised to Fc (LuGre needs Fs >= Fc)")
        print(
            f"{res.summary['samples']} samples, {res.summary['diverged']} diverged; RMS link error "
            f"median {m['q50']:.3g} rad, 95% {m['q95']:.3g} rad; "
            f"top driver: {res.summary['sensitivity'][0]['parameter'] if res.summary['sensitivity'] else '-'}; "
            f"wrote {out}"
        )
    if args.coordinator:
        jax.distributed.shutdown()
    return 0

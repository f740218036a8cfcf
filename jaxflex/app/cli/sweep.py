"""``jaxflex sweep SPREAD.json``: Monte Carlo robustness sweep from a spread file.

Writes summary.json (quantiles, worst cases with their parameters, sensitivities, error
bands, timing), the figures, and (unless --no-samples) samples.csv of each sample's
parameters and metrics. Multi-process: start the same command in every process with
--coordinator HOST:PORT --num-processes P --process-id i; process 0 writes the files.

Ctrl-C (or SIGTERM) stops between chunks: summary.json then summarises the chunks done and
says "partial": true, and --resume continues from the checkpoint kept in the output folder
(single process). A draw with Fs < Fc is redrawn (the sweep samples the spread conditioned on
Fs >= Fc); a spread whose Fs is always below Fc is refused.
"""

from __future__ import annotations

import argparse

EXAMPLE = ("jaxflex sweep studies/spreads/sweep_paper_20pct.json --out out/sweep --samples 2000\n"
           "  (after Ctrl-C)  jaxflex sweep studies/spreads/sweep_paper_20pct.json --out out/sweep "
           "--samples 2000 --resume")
CHECKPOINT = "checkpoint.pkl"
#: The files ``sweep`` writes in its output folder: an existing one needs ``--force``.
OUTPUT_FILES = ("summary.json", "samples.csv", "error_histograms.png", "error_bands.png",
                "sensitivity.png")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``sweep`` subcommand."""
    p = subparsers.add_parser(
        "sweep", help="Monte Carlo robustness sweep (vmap, chunks, sharding, jax.distributed)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("spread", help="spread file (JSON; see jaxflex.sweep.spec)")
    p.add_argument("--out", default="out/sweep", help="output folder (default out/sweep)")
    p.add_argument("--resume", action="store_true",
                   help=f"continue an interrupted sweep from OUT/{CHECKPOINT} (same spread "
                   "and options)")
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
    p.add_argument("--num-processes", type=int, default=1,
                   help="number of jax.distributed processes")
    p.add_argument("--process-id", type=int, default=0, help="this process's number")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the sweep and write its files; returns the exit status."""
    import json
    import os
    import pickle
    import sys
    from pathlib import Path

    import jax
    import numpy as np

    from jaxflex.app.cli.outputs import OutputError, check_folder, suggest_command
    from jaxflex.io.errors import InputError
    from jaxflex.sweep import load_spread, nominal_run, run_sweep

    for flag, value, low in (("--samples", args.samples, 1), ("--chunk-size", args.chunk_size, 1),
                             ("--worst", args.worst, 0)):
        if value is not None and value < low:
            raise InputError(f"{flag} must be an integer >= {low}, got {value}")
    spec = load_spread(args.spread)  # validate before starting any process group
    # the command as given (main's argv), for the --resume hint; the spread and --out as
    # parsed when called without it
    argv = getattr(args, "argv", None) or ["sweep", args.spread, "--out", args.out]
    resume_command = suggest_command(argv, add=["--resume"], drop=["--force"])
    ckpt_path = Path(args.out) / CHECKPOINT
    if ckpt_path.exists() and not (args.resume or args.force):
        raise OutputError(f"--out {args.out}: holds an interrupted sweep ({CHECKPOINT}); "
                          f"continue it with: {_resume_command(Path(args.out), resume_command)}"
                          "; or pass --force to start again")
    out = check_folder(args.out, force=args.force, resume=args.resume, marker=OUTPUT_FILES)
    resume = None
    if args.resume:
        if args.coordinator:
            raise ValueError("--resume is for single-process sweeps")
        if not ckpt_path.is_file():
            raise OutputError(f"--resume: no checkpoint {ckpt_path} (nothing to resume; run "
                              "without --resume)")
        try:
            resume = pickle.loads(ckpt_path.read_bytes())
        except Exception as e:  # a truncated or foreign file
            raise OutputError(f"--resume: {ckpt_path} is not a readable checkpoint ({e})") from None
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
    writer = jax.process_index() == 0 and not args.coordinator

    def save_checkpoint(ck) -> None:
        out.mkdir(parents=True, exist_ok=True)
        tmp = ckpt_path.with_name(CHECKPOINT + ".tmp")
        tmp.write_bytes(pickle.dumps(ck))
        os.replace(tmp, ckpt_path)

    if spec.fs_below_fc_possible():
        print("note: the spread can draw Fs < Fc (LuGre needs Fs >= Fc); such (Fc, Fs) draws "
              "are redrawn, so the sweep samples the spread conditioned on Fs >= Fc")
    res = run_sweep(
        spec, chunk_size=args.chunk_size, shard=not args.no_shard,
        keep_samples=not args.no_samples, n_worst=args.worst, progress=not args.no_progress,
        float32=args.float32, resume=resume, on_chunk=save_checkpoint if writer else None,
    )
    if res is None:
        print("jaxflex sweep: interrupted before the first chunk finished; nothing written",
              file=sys.stderr)
        return 130
    partial = bool(res.summary.get("partial"))
    if jax.process_index() == 0:
        out.mkdir(parents=True, exist_ok=True)
        doc = res.to_json()
        doc["fs_below_fc"] = ("redrawn: sampled conditioned on Fs >= Fc"
                              if spec.fs_below_fc_possible() else "cannot occur")
        doc["figures"] = []
        if partial:
            doc["resume_command"] = resume_command
        tmp = out / "summary.json.tmp"
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
        os.replace(tmp, out / "summary.json")
        if res.samples is not None:
            cols = spec.labels + ["rms_error", "max_error", "tau_rms", "saturation_fraction", "diverged"]
            s = res.samples
            table = np.column_stack([s["index"], s["theta"]] + [s[c] for c in cols[len(spec.labels):]])
            np.savetxt(out / "samples.csv", table, delimiter=",", header=",".join(["index"] + cols),
                       comments="", fmt="%.17g")
        if partial:
            print(f"jaxflex sweep: interrupted after {res.summary['chunks_done']} of "
                  f"{res.summary['chunks']} chunks ({res.summary['samples']} samples); wrote the "
                  f"partial summary {out / 'summary.json'} (\"partial\": true, no figures); "
                  f"continue with: {resume_command}", file=sys.stderr)
            return 130
        from jaxflex.app.plots import save_figures
        from jaxflex.app.plots.sweep import plot_sweep

        figs = save_figures(plot_sweep(res, nominal=nominal_run(spec)), out, dpi=120)
        doc["figures"] = [str(out / f) for f in figs]
        (out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n")
        ckpt_path.unlink(missing_ok=True)
        m = res.summary["metrics"]["rms_error"]
        if res.summary["fs_raised_to_fc"]:
            print(f"note: {res.summary['fs_raised_to_fc']} sample(s) kept Fs < Fc after "
                  "their redraws; their Fs was raised to Fc")
        sens = res.summary["sensitivity"]
        pu = "rad"  # the sweep's plant is a revolute joint model
        top = (f"{sens[0]['parameter']} (explains {100 * sens[0]['shapley']:.3g}% of the RMS "
               "error's variance, Shapley share of the linear fit)") if sens else "-"
        print(
            f"{res.summary['samples']} samples, {res.summary['diverged']} diverged; RMS link error "
            f"median {m['q50']:.3g} {pu}, 95% {m['q95']:.3g} {pu}; top driver: {top}; wrote {out}"
        )
        for w in res.summary["sensitivity_warnings"]:
            print(f"warning: {w}", file=sys.stderr)
    if args.coordinator:
        jax.distributed.shutdown()
    return 0


def _resume_command(out, fallback: str) -> str:
    """The command that continues the interrupted sweep in ``out``: the one its partial
    summary recorded (the options it ran with), else ``fallback`` (this command line with
    ``--resume``)."""
    import json

    try:
        cmd = json.loads((out / "summary.json").read_text()).get("resume_command")
    except (OSError, ValueError, AttributeError):
        cmd = None
    return cmd if isinstance(cmd, str) and cmd else fallback

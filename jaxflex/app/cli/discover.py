"""``jaxflex discover LOG [--params NOMINAL.json] --out DIR``: discrepancy discovery.

Writes ``DIR/report.json`` (first effect added or ``none``, all effects, held-out gap before
and after, fitted effect parameters with standard errors, candidate scores, localisation),
``DIR/params.json`` (the augmented model, docs/spec.md section 7) and figures.

The parameter file's model (``--model``; default the one its identification recorded, else
flexible) says how it is replayed (``jaxflex.discover.nominal_for_model``): a rigid model as
two halves of its inertia joined by a stiff spring (a one-encoder log reads q2 = q1), a rotor
subsystem with its link side fitted rigidly on the log. An identification whose model is
limited (``identification.model.verdict`` "model-limited") is taken with a note; one whose
solver did not converge is refused unless ``--accept-unconverged`` (``load_params``). Bad
input exits with 2; a
numerical failure of a fit inside discovery with 1, naming the fit (report.json records it).
"""

from __future__ import annotations

import argparse

from jaxflex.app.cli.spans import span

EXAMPLE = "jaxflex discover log.csv --params nominal.json --out out/discover"
#: The files ``discover`` writes in its output folder (one joint; n joints add
#: ``params_joint<j>.json`` and ``joint<j>/``): an existing one needs ``--force``.
OUTPUT_FILES = ("report.json", "params.json", "params_joint0.json", "signature.png",
                "replay.png", "scores.png")

#: Exit status when a fit inside discovery fails numerically: a result that did not
#: converge (bad input exits with 2, a bug with 70).
SOLVER_FAILURE = 3


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``discover`` subcommand."""
    p = subparsers.add_parser(
        "discover", help="find the effect a model misses in a log, add it, report the gap",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("log", help="log file (docs/spec.md section 6; CSV with t,tau,q1,q2), or a "
                               "shipped data set: jaxflex:emps/DATA_EMPS, jaxflex:kuka/A/1 (one "
                               "axis; also B, C and axes 2, 3)")
    p.add_argument("--map", default=None,
                   help="column mapping for files with other variable names, e.g. "
                        "'tau=gtau*vir,q1=qm,q2=qm' (docs/spec.md section 6)")
    p.add_argument("--params", default=None, help="nominal parameter file (default: the paper's)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--candidates", default=None,
                   help="comma-separated effect names to try (default: all known)")
    p.add_argument("--segment", type=span, default=span("0.3s"),
                   help="segment length in samples (300) or seconds (0.3s) (default 0.3s)")
    p.add_argument("--train-frac", type=float, default=0.7, help="training fraction (0.7)")
    p.add_argument("--max-steps", type=int, default=30, help="LM steps per candidate (30)")
    p.add_argument("--alpha", type=float, default=1e-3, help="F-test significance level")
    p.add_argument("--min-gain", type=float, default=0.15,
                   help="minimal relative held-out gap reduction to accept an effect")
    p.add_argument("--max-effects", type=int, default=3, help="most effects to add (3)")
    p.add_argument("--max-order", type=int, default=3,
                   help="highest order of an effect family to fit (3; 1: each family's "
                        "simplest member: a ripple's fundamental, Coulomb and viscous motor "
                        "friction, a first-order lag)")
    p.add_argument("--substeps", type=int, default=1,
                   help="RK4 steps per sample in every replay (1); the lag's and the delay's "
                        "time constants are fitted from 1.5 x the step dt / substeps up, so a "
                        "delay shorter than 1.5 samples needs 2 or more (longer runs)")
    p.add_argument("--model", choices=("rigid", "flexible", "rotor"), default=None,
                   help="the model the parameter file describes: flexible joint; rigid "
                        "(replayed as two halves of its inertia joined by a stiff spring, a "
                        "one-encoder log reads q2 = q1); rotor (J, K from the file, the link "
                        "side from a rigid fit of the log). Default: the identification's "
                        "model recorded in the file, else flexible")
    p.add_argument("--no-plots", action="store_true", help="skip figures")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run discovery and write the report; returns the exit code."""
    import dataclasses
    import importlib
    import json
    import sys
    from pathlib import Path

    from jaxflex.discover import (
        DISCOVER_MODELS,
        DiscoverConfig,
        SolverFailure,
        discover,
        model_kind_of,
    )
    from jaxflex.data import is_named, load_named
    from jaxflex.core.effects import EFFECTS
    from jaxflex.runtime.ahead import Ahead
    from jaxflex.io.errors import ConfigError, InputError
    from jaxflex.io.logs import load_log, parse_mapping
    from jaxflex.io.params import load_params, save_params
    from jaxflex.io.presets import paper_params

    from jaxflex.app.cli.outputs import check_outputs, interrupts_stop, writing

    check_outputs(args.force, folders=[args.out], marker=OUTPUT_FILES)
    # a converged, model-limited identification is taken with load_params's one-line note
    nominal = load_params(args.params) if args.params else paper_params()
    model = args.model or model_kind_of(nominal) or "flexible"
    if model not in DISCOVER_MODELS:  # e.g. a link subsystem's identification
        print(f"note: the identification's model {model!r} is replayed as a flexible joint")
        model = "flexible"
    cands = [c.strip() for c in args.candidates.split(",")] if args.candidates else None
    try:  # the settings checked before the log is read; the segment in seconds once it is
        cfg = DiscoverConfig(
            segment=float(args.segment.value), train_frac=args.train_frac,
            max_steps=args.max_steps, alpha=args.alpha, min_gain=args.min_gain,
            max_effects=args.max_effects, candidates=cands, max_order=args.max_order,
            substeps=args.substeps, model=model,
        )
    except ConfigError as e:  # named as the option the user typed
        raise InputError(e.option()) from None
    joint_axes = None
    if is_named(args.log):  # a shipped data set by name, as identify takes it
        if args.map:
            raise ValueError(f"--map applies to files; {args.log} is a shipped data set")
        named = load_named(args.log)
        log = named.log
        if named.axis is not None and "axis" not in nominal.extra:
            # what gravity can do on the shipped data set's axes (its kinematics): declared
            # in the file's words, or joint by joint for one joint's file over an n-axis log
            if nominal.n == log.n:
                nominal.extra["axis"] = named.axis[0] if log.n == 1 else list(named.axis)
            else:
                joint_axes = list(named.axis)
    else:
        required = ("t", "tau", "q1") if model == "rigid" else None
        log = load_log(args.log, parse_mapping(args.map), **({"required": required}
                                                              if required else {}))
    cfg = dataclasses.replace(cfg, segment=args.segment.seconds(log.dt))
    out = Path(args.out)  # created once there is a result to write (no empty folder on Ctrl-C)
    if log.n > 1:
        return _run_joints(args, log, nominal, cfg, out, joint_axes)
    # matplotlib is imported beside the fits (0.4 s), not after them
    plots = None if args.no_plots else Ahead(
        [lambda: importlib.import_module("jaxflex.app.plots.discover")])
    try:
        with interrupts_stop() as check:  # a fit ends on Ctrl-C; the command stops too
            res = discover(log, nominal, cfg, progress=lambda d, t, m: (check(), print(m)))
    except SolverFailure as e:
        # a numerical failure of a fit, not a bad input: said so, and recorded in the folder
        with writing():
            out.mkdir(parents=True, exist_ok=True)
            (out / "report.json").write_text(json.dumps(
                {"effect": None, "failed": {"kind": "solver failure", "stage": e.stage,
                                            "message": str(e)}, "model": model}, indent=2) + "\n")
        print(f"jaxflex {e} (nothing discovered; "
              f"{out / 'report.json'} records it)", file=sys.stderr)
        return SOLVER_FAILURE
    finally:
        if plots is not None:  # no thread left behind, a failed run's included
            plots.join()
    rep = res.to_json()
    params = res.params
    params.extra = dict(params.extra)
    params.extra["discover"] = {"effects": rep["effects"], "stderr": rep["final_stderr"]}
    with writing():  # the whole result or nothing, Ctrl-C included
        out.mkdir(parents=True, exist_ok=True)
        save_params(params, out / "params.json")
        if plots is not None:
            from jaxflex.app.plots import save_figures
            from jaxflex.app.plots.discover import plot_report

            rep["figures"] = save_figures(plot_report(res), out)
        (out / "report.json").write_text(json.dumps(rep, indent=2) + "\n")
    named = (f"{rep['effect']} order {rep['order']}" if rep["order"] > 1
             or rep["effect"] in EFFECTS and EFFECTS[rep["effect"]].higher else rep["effect"])
    grown = [f"{f} order {k}" if k > 1 else e
             for e, f, k in zip(rep["effects"], rep["families"], rep["orders"])]
    print(f"effect: {named}  effects: {grown}  gap {rep['gap_before']:.4f} -> "
          f"{rep['gap_after']:.4f} (floor {rep['gap_floor']:.4f})  {rep['seconds']:.0f} s")
    added = [r for r in rep["rounds"] if r["winner"] != "none"]
    for k, r in enumerate(added):
        others = [t for t in r.get("tied", []) if t != r["winner"]]
        if others:
            print(f"effect {k + 1} ({r['winner']}) is not told apart from {', '.join(others)} "
                  "on this log: the model carries one of them (report.json effects_tied)")
    if any(len(t) > 1 for t in rep["effects_tied"]):
        print(f"answer: {rep['answer']}")
    if rep["unexplained"]:
        where = rep["localisation"].get("side", "?")
        print(f"unexplained: the held-out gap stays above {cfg.unexplained_factor:g} x the floor "
              f"and no candidate closes {'the rest of ' if rep['effects'] else ''}it: something "
              f"the effect library does not describe (residual mostly on the {where} side; see "
              "report.json 'localisation' for the velocity, position, frequency and time "
              "signatures)")
        if rep["effect"] == "unexplained" and rep["effects"]:
            print(f"partial: the effects added ({', '.join(rep['effects'])}) close "
                  f"{100 * rep['explained_fraction']:.0f}% of the held-out gap's excess over the "
                  f"floor, less than {100 * cfg.explained_min:.0f}%: they are not the answer")
    print(f"wrote {out / 'report.json'} and {out / 'params.json'}")
    return 0


def _run_joints(args: argparse.Namespace, log, nominal, cfg, out,
                joint_axes: list[str] | None = None) -> int:
    """An n-joint log: ``discover_joints``; report.json holds one report per joint (and the
    answers side by side), params_joint<j>.json each joint's final parameters."""
    import json

    from jaxflex.discover import discover_joints
    from jaxflex.io.params import save_params

    from jaxflex.app.cli.outputs import interrupts_stop, writing

    with interrupts_stop() as check:  # a fit ends on Ctrl-C; the command stops too
        results = discover_joints(log, nominal, cfg, progress=lambda d, t, m: (check(), print(m)),
                                  axes=joint_axes)
    reps = []
    with writing():  # the whole result or nothing, Ctrl-C included
        out.mkdir(parents=True, exist_ok=True)
        for j, res in enumerate(results):
            rep = res.to_json()
            params = res.params
            params.extra = {"discover": {"effects": rep["effects"], "stderr": rep["final_stderr"],
                                         "joint": j}}
            save_params(params, out / f"params_joint{j}.json")
            if not args.no_plots:
                from jaxflex.app.plots import save_figures
                from jaxflex.app.plots.discover import plot_report

                sub = out / f"joint{j}"
                sub.mkdir(exist_ok=True)
                rep["figures"] = [f"joint{j}/{f}" for f in save_figures(plot_report(res), sub)]
            reps.append({"joint": j, **rep})
        summary = {"joints": reps, "effect": [r["effect"] for r in reps],
                   "answer": [r["answer"] for r in reps],
                   "effects": [r["effects"] for r in reps],
                   "unexplained": [r["unexplained"] for r in reps]}
        (out / "report.json").write_text(json.dumps(summary, indent=2) + "\n")
    for j, rep in enumerate(reps):
        print(f"joint {j}: answer {rep['answer']}  effects {rep['effects']}  gap "
              f"{rep['gap_before']:.4f} -> {rep['gap_after']:.4f} (floor {rep['gap_floor']:.4f})")
    print(f"wrote {out / 'report.json'} and {len(reps)} params_joint<j>.json")
    return 0

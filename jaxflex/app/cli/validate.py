"""``jaxflex validate LOG... --params P [--against P0] --out DIR``: judge parameters on logs.

For each log: the open-loop segment replay gap, the torque prediction error from the measured
motion ``100 ||tau - tau_hat|| / ||tau||`` [%], and, when the parameter file declares the
controller that ran (top-level ``loop_controller`` section: the EMPS P/P cascade
``{"type": "pp_cascade", ...}``, a PD loop ``{"type": "pd", "kp": ..., "kd": ...}`` or
jaxflex's cascade ``{"type": "cascade"}``; docs/spec.md section 7) and the log has a
reference q1d, the closed-loop errors in the benchmark metric (position, velocity, torque).
``--against`` adds the same rows for a reference parameter set. Each error stands beside its
noise floor, what the log's measurement noise alone gives a perfect model
(``jaxflex.validate``). Writes ``DIR/report.json``, ``DIR/table.md`` and figures (measured
against predicted, residuals); an existing one of them needs ``--force``, and nothing is
written until every log has been validated. Each row's ``residual_analysis`` is the segment replay's residual analysis as
MATLAB's ``resid`` gives it (autocorrelation and torque cross-correlation with 99% bands,
Ljung-Box whiteness), drawn in ``DIR/<log>_<params>_residuals.png``.

A rotor-kind file (``jaxflex identify`` on a coupled axis, e.g. ``jaxflex:kuka/A/2``) is
judged by the torque it predicts from each log's measured motion. The link encoder's offset
and scale against the motor encoder are sensor nuisances that a recording sets anew (the
file's ``identification.per_log``): they are re-estimated on each log with every other
parameter held (``jaxflex.identify.torque.refit_per_log``), and the row gives the torque error
with them (``torque_pct``) and with the file's own values (``torque_pct_as_identified``).

    jaxflex identify jaxflex:kuka/A/2 --out a2.json
    jaxflex validate jaxflex:kuka/B/2 jaxflex:kuka/C/2 --params a2.json --out val2

Example (EMPS, with the pulses of the validation file injected in volts):

    jaxflex validate jaxflex/data/DATA_EMPS_PULSES.mat --params emps.json --model rigid \\
        --map 't=t,tau=gtau*vir,q1=qm,q2=qm,q1d=qg' --disturbance pulses_N --linear --out val
"""

from __future__ import annotations

import argparse
from typing import Any

from jaxflex.app.cli.spans import span


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``validate`` subcommand."""
    p = subparsers.add_parser(
        "validate", help="validate parameters on logs (replay gap, torque error, closed loop)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("logs", nargs="+", help="log files (docs/spec.md section 6)")
    p.add_argument("--params", required=True, help="parameter file to validate (JSON)")
    p.add_argument("--against", default=None, help="reference parameter file (JSON)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--map", default=None, help="column mapping or @FILE (docs/spec.md 6.4)")
    p.add_argument("--model", choices=("flexible", "rigid", "rotor", "link"), default=None,
                   help="model structure (default: the kind the file was identified as, "
                        "identification.start.kind, else flexible)")
    p.add_argument("--disturbance", default=None,
                   help="expression on the log file's variables added to the controller output "
                        "in the closed loop [V for pp_cascade, N m otherwise], e.g. pulses_N (default: none; a file without "
                        "the variable runs without it)")
    p.add_argument("--segment", type=span, default=None,
                   help="replay segment length in samples (500) or seconds (0.5s) "
                        "(default: 0.5s)")
    p.add_argument("--substeps", type=int, default=4, help="integrator substeps per sample (4)")
    p.add_argument("--linear", action="store_true",
                   help="prismatic joint: label m and N (implied by a --map that converts q1 or "
                        "q2 from :m or :mm, or tau from :N)")
    p.set_defaults(func=run)


def log_name(f: str) -> str:
    """The name a log's figures and report entries take: a file's stem, or a shipped data
    set's name with its folders ("jaxflex:kuka/B/2" -> "kuka_B_2")."""
    from pathlib import Path

    from jaxflex.data import NAMED_PREFIX, is_named

    if is_named(f):
        return f[len(NAMED_PREFIX):].strip("/").replace("/", "_")
    return Path(f).stem


def output_files(logs: list[str], against: bool) -> list[str]:
    """Every file ``validate`` writes in its output folder for these logs."""
    which = ("params", "against") if against else ("params",)
    return (["report.json", "table.md", "torque_errors.png"]
            + [f"{log_name(f)}_{w}.png" for f in logs for w in which])


def run(args: argparse.Namespace) -> int:
    """Validate and write the report; returns the exit code."""
    import json
    from pathlib import Path

    from jaxflex.app.cli.outputs import OutputError, check_outputs, writing
    from jaxflex.data import is_named, load_named
    from jaxflex.io.errors import InputError
    from jaxflex.io.logs import LogError, axis_units, evaluate, load_log, parse_mapping, read_variables
    from jaxflex.io.params import load_params
    from jaxflex.validate import loop_controller, validate

    if args.substeps < 1:
        raise InputError(f"--substeps must be an integer >= 1, got {args.substeps}")
    stems = [log_name(f) for f in args.logs]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise OutputError(f"logs: two logs share the name {dup[0]!r}; their figures would "
                          "overwrite each other in --out: rename one or validate them apart")
    check_outputs(args.force, folders=[args.out],
                  marker=output_files(args.logs, args.against is not None))
    out = Path(args.out)
    sets = {"params": load_params(args.params)}
    if args.against:
        sets["against"] = load_params(args.against)
    for p in sets.values():  # a bad loop_controller section is refused before any work
        loop_controller(p)
    if args.model is None:
        args.model = identified_kind(sets["params"])
        if args.model is None:
            args.model = "flexible"
        else:
            print(f"model {args.model} (as {args.params} was identified; --model to choose)")
    mapping = parse_mapping(args.map)
    units = axis_units(mapping, args.linear)
    logs = []
    for f in args.logs:
        if is_named(f):  # a shipped data set by name, as identify takes it
            if args.map or args.disturbance:
                raise InputError(f"--map and --disturbance read a file's variables; {f} is a "
                                 "shipped data set: give its file (jaxflex.data.available())")
            log = load_named(f).log
        else:
            log = load_log(f, mapping, required=("t", "tau", "q1"))
        d = None
        if args.disturbance:
            try:
                d = evaluate(args.disturbance, read_variables(f), f"{f}: ").reshape(-1)
            except LogError as e:  # a file without the disturbance ran without one
                if "not in the file" not in str(e):
                    raise
                print(f"note: {f} has no '{args.disturbance}'; no disturbance for it")
        logs.append((log_name(f), log, d))
    segments = {}
    for name, log, _ in logs:
        segments[name] = None if args.segment is None else args.segment.samples(log.dt)
        if segments[name] is not None and segments[name] < 2:
            raise InputError(f"--segment must be at least 2 samples, got {args.segment} "
                             f"({segments[name]} samples of {name})")
    results = []  # everything is computed before the folder is created
    for name, log, d in logs:
        for which, p in sets.items():
            p, nuisance = per_log_sensors(p, log, args.model)
            res = validate(p, log, kind=args.model, segment=segments[name],
                           substeps=args.substeps, disturbance=d)
            if nuisance is not None:
                res["per_log"] = nuisance
                res["torque_pct_as_identified"] = nuisance["torque_pct_as_identified"]
                print(f"{name} {which}: per-log sensor nuisances {nuisance['values']} "
                      f"(converged {nuisance['converged']}); torque error {res['torque_pct']:.4g}% "
                      f"({nuisance['torque_pct_as_identified']:.4g}% with the file's values)")
            results.append((name, which, res))

    from jaxflex.app.plots import save_figure
    from jaxflex.app.plots.validate import plot_table, plot_validation_log

    with writing():  # the whole result or nothing, Ctrl-C included
        out.mkdir(parents=True, exist_ok=True)
        rows = []
        report = {"model": args.model, "logs": {},
                  "units": {"position": units[0], "torque": units[1]}}
        for name, which, res in results:
            fig = save_figure(plot_validation_log(
                res["series"], units=units,
                title=f"{name}: {which} ({args.model} model); torque error "
                      f"{res['torque_pct']:.2f}% (noise alone {res['torque_noise_pct']:.2f}%), "
                      f"replay gap {res['gap']:.3f}"), out / f"{name}_{which}.png")
            row = {k: v for k, v in res.items() if k != "series"}
            row["figure"] = fig
            ra = res["residual_analysis"]
            if ra.get("channels"):
                from jaxflex.app.plots.discover import plot_residual_analysis

                resid_fig = out / f"{name}_{which}_residuals.png"
                save_figure(plot_residual_analysis(ra, f"{name}: {which} ({args.model} model), "
                                                       "residual of the segment replay"),
                            resid_fig)
                row["residual_figure"] = resid_fig.name
                white = ", ".join(f"{c} p {v['p_white']:.2g} (correlation time "
                                  f"{v['correlation_time']:.3g} samples)"
                                  for c, v in ra["channels"].items())
                print(f"{name} {which}: residual whiteness (Ljung-Box, {ra['lags']} lags): "
                      f"{white}")
            report["logs"].setdefault(name, {})[which] = row
            rows.append({"log": name, "params": which, **row})
        report["figures"] = [save_figure(plot_table(rows), out / "torque_errors.png")]
        lines = ["| log | params | replay gap | torque % | CL position % | CL velocity % | "
                 "CL torque % |", "|---|---|---|---|---|---|---|"]
        for r in rows:
            cl = r["closed_loop"] or {}
            fl = cl.get("noise_floor", {})
            f = lambda k: f"{cl[k]:.4g} ({fl[k]:.2g})" if k in cl else "-"
            lines.append(f"| {r['log']} | {r['params']} | {r['gap']:.4g} ({r['gap_noise']:.2g}) | "
                         f"{r['torque_pct']:.4g} ({r['torque_noise_pct']:.3g})"
                         + (f" [{r['torque_pct_as_identified']:.4g} with the file's sensors]"
                            if "torque_pct_as_identified" in r else "") + " | "
                         f"{f('position_pct')} | {f('velocity_pct')} | {f('torque_pct')} |")
        table = "\n".join(lines)
        (out / "table.md").write_text(table + "\n")
        (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    print(table)
    print("in parentheses, each error's noise floor: what the log's measurement noise alone "
          f"gives a perfect model (noise std of tau in {units[1]}, of q1 and q2 in {units[0]}: "
          "report.json noise_std); an error near its floor is as good as this log can tell. "
          "torque %: 100 ||tau - tau_hat|| / ||tau|| from the measured motion; CL: the declared "
          "closed loop, the benchmark metric")
    print(f"wrote {out / 'report.json'}")
    return 0


def identified_kind(params: Any) -> str | None:
    """The model kind a parameter file was identified as (``identification.start.kind``, or
    ``identification.model`` as a name), None for a file that records none."""
    ident = params.extra.get("identification")
    if not isinstance(ident, dict):
        return None
    start = ident.get("start")
    for k in (start.get("kind") if isinstance(start, dict) else None, ident.get("model")):
        if k in ("flexible", "rigid", "rotor", "link"):
            return k
    return None


def per_log_sensors(params: Any, log: Any, kind: str) -> tuple[Any, dict[str, Any] | None]:
    """For the rotor kind, ``params`` with the file's per-log sensor nuisances
    (``identification.per_log``) re-estimated on ``log`` (``refit_per_log``) and a record:
    the values, whether the fit converged and the torque error [%] with the file's own
    values; ``(params, None)`` for another kind or a file that declares none."""
    ident = params.extra.get("identification")
    names = ident.get("per_log") if isinstance(ident, dict) else None
    if kind != "rotor" or not names:
        return params, None
    from jaxflex.fit import get_value
    from jaxflex.identify.torque import refit_per_log
    from jaxflex.validate import rel_error_pct, torque_prediction

    before = rel_error_pct(log.tau, torque_prediction(params, log, kind="rotor"))
    refit, fit = refit_per_log(params, log, names)
    if fit is None:
        return params, None
    return refit, {"names": list(names), "converged": fit.converged,
                   "values": {k: [float(x) for x in get_value(refit, k)] for k in names},
                   "torque_pct_as_identified": before}

"""Report folders of the workflows (app layer): figures and a JSON of the numbers.

The workflows (``jaxflex.tune``, ``jaxflex.loop.experiments``) return typed results and write
nothing; the command line and the studies call these writers. Figures come from
``jaxflex.app.plots``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from jaxflex.loop.experiments import PaperExperiments
from jaxflex.io.params import save_params
from jaxflex.app.plots import save_figure
from jaxflex.app.plots.tracking import plot_q2d_comparison, plot_torque_friction, plot_tracking
from jaxflex.app.plots.tune import plot_history, plot_lambda_min, plot_tracking_comparison
from jaxflex.tune import TuneComparison, TuneResult, TuneTask


def write_json(doc: dict[str, Any], path: str | Path) -> None:
    """Write ``doc`` as indented JSON (with a final newline) to ``path``."""
    Path(path).write_text(json.dumps(doc, indent=2) + "\n")


def write_tune_report(result: TuneResult, task: TuneTask, comparison: TuneComparison,
                      out: str | Path) -> dict[str, Any]:
    """Write ``report.json`` and figures (lambda_min(N2) over speed [rad/s], tracking of the
    initial and tuned gains, search history) to the folder ``out``; returns the report
    (``comparison.summary`` plus the figure names)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = comparison.summary(result, task)
    report["figures"] = [
        save_figure(plot_lambda_min({k: e["certificate"] for k, e in comparison.evaluations.items()},
                                    v_task=result.v_task, margin=result.margin),
                    out / "lambda_min.png"),
        save_figure(plot_tracking_comparison(comparison.runs), out / "tracking.png"),
        save_figure(plot_history(report["search"]["starts"]), out / "history.png"),
    ]
    write_json(report, out / "report.json")
    return report


def write_paper_experiments(results: PaperExperiments, out: str | Path) -> dict[str, Any]:
    """Write the figures of the paper's experiments (tracking per experiment, torque and
    friction of the compensated sinusoid, the paper's own controller per experiment, the
    q2d comparison), ``results.json`` and ``params.json`` (the configuration run, which
    ``jaxflex export --params`` exports) to the folder ``out``; returns the results document
    (with figure names per experiment). Every title names the velocity source and the
    observer shown."""
    from jaxflex.io.presets import TRAJECTORY_DESCRIPTIONS

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = results.to_dict()
    label = results.config.get("label", "")
    for name, e in results.experiments.items():
        figs = [save_figure(plot_tracking(e.runs, e.title), out / f"{name}_tracking.png")]
        if name == "sinusoid":
            figs.append(save_figure(plot_torque_friction(e.runs["with_compensation"], config=label),
                                    out / "sinusoid_torque_friction.png"))
        doc["experiments"][name]["figures"] = figs
    if results.paper_own_runs:
        own = doc["paper_own_observer"]
        for name, r in results.paper_own_runs.items():
            own["experiments"][name]["figures"] = [save_figure(plot_tracking(
                {"with_compensation": r}, f"{TRAJECTORY_DESCRIPTIONS[name]}\n{own['label']}"),
                out / f"{name}_paper_own_observer.png")]
    save_params(results.params(), out / "params.json")
    doc["params_file"] = "params.json"
    if results.q2d_comparison is not None:
        leak = results.config.get("observer_leak", [0.0])
        obs = label.split("; ", 1)[1] if "; " in label else ""
        save_figure(plot_q2d_comparison(
            results.q2d_comparison,
            config=f"each sensing's own velocities (dirty derivative; exact for ideal); "
                   f"{obs or f'observer leak {leak}'}"), out / "q2d_comparison.png")
    write_json(doc, out / "results.json")
    return doc

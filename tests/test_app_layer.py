"""The app layer: one table of presets behind every choice list, the controller
configuration carried from a parameter file into export and run-loop, the rig's plant apart
from the controller's, and the import graph (every import points to its own layer or below,
edges at the edges, no private names across modules, nothing below ``presets`` imports it)."""

from __future__ import annotations

import argparse
import ast
import json
from pathlib import Path

import numpy as np
import pytest

from jaxflex.app.cli import build_parser, main
from jaxflex.io import presets
from jaxflex.io.params import Params, save_params
from jaxflex.io.presets import SENSING_PRESETS, TRAJECTORIES, paper_params

PKG = Path(__file__).resolve().parents[1] / "jaxflex"


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_every_cli_choice_list_is_the_presets_table():
    seen = {"trajectory": set(), "sensing": set()}
    for name, parser in _subcommands().items():
        for a in parser._actions:
            if a.dest in ("trajectory", "tasks"):
                assert tuple(a.choices) == TRAJECTORIES, (name, a.dest)
                seen["trajectory"].add(name)
            if a.dest == "sensing":
                assert tuple(a.choices) == SENSING_PRESETS, name
                seen["sensing"].add(name)
    assert {"tune", "export", "run-loop", "reproduce"} <= seen["trajectory"]
    assert {"tune", "reproduce"} <= seen["sensing"]


def test_presets_name_their_choices_and_match_the_paper_tables():
    with pytest.raises(ValueError, match=r"unknown sensing preset 'perfect'; choices: \['rig'"):
        presets.sensing_preset("perfect")
    with pytest.raises(ValueError, match=r"unknown trajectory 'zigzag'; choices: \['sinusoid'"):
        presets.trajectory_preset("zigzag")
    assert presets.sensing_preset("ideal") == presets.Sensing()
    assert presets.sensing_preset("rig").dac_bits == 12
    p = paper_params()
    assert p.plant == {k: [v] for k, v in presets.PAPER_PLANT.items()}
    assert p.gains == {k: [v] for k, v in presets.PAPER_GAINS.items()}
    assert presets.paper_lugre().to_dict() == p.friction
    assert set(presets.TRAJECTORY_DESCRIPTIONS) == set(TRAJECTORIES)


# ----- the controller section travels from the file into export and run-loop ------------------

SECTION = {"q2d_method": "filtered", "dt": 0.002, "tau_max": 1.5, "compensation": False,
           "trajectory": "polynomial"}


@pytest.fixture()
def tuned_file(tmp_path) -> Path:
    d = paper_params().to_dict()
    d["controller"] = SECTION
    path = tmp_path / "tuned.json"
    save_params(Params.from_dict(d), path)
    return path


def test_build_controller_follows_the_files_controller_section(tuned_file):
    import jax.numpy as jnp

    from jaxflex.export import build_controller
    from jaxflex.io.params import ParamsError

    c = build_controller(tuned_file)
    assert (c.q2d_method, c.dt, c.compensation) == ("filtered", 0.002, False)
    assert float(c.tau_max[0]) == 1.5
    ref = presets.paper_polynomial()
    for t in (0.0, 1.3, 4.0):
        assert float(c.trajectory.position(jnp.asarray(t))[0]) == float(ref.position(jnp.asarray(t))[0])
    with pytest.raises(ParamsError, match="contradicts controller.dt"):
        build_controller(tuned_file, dt=1e-3)
    d = build_controller()  # no section: the defaults, as before
    assert (d.q2d_method, d.dt, d.compensation, float(d.tau_max[0])) == ("model", 1e-3, True, 2.0)


def test_cli_export_reads_the_section_and_refuses_a_contradicting_flag(tuned_file, tmp_path,
                                                                       capsys):
    from jaxflex.export import load_module

    out = tmp_path / "c.py"
    assert main(["export", "--params", str(tuned_file), "--out", str(out)]) == 0
    mod = load_module(out)
    assert (mod.Q2D_METHOD, mod.DT) == ("filtered", 0.002)
    assert mod.DEFAULT_PARAMS["tau_max"][1] == [1.5]
    capsys.readouterr()
    assert main(["export", "--params", str(tuned_file), "--out", str(out), "--q2d", "model",
                 "--force"]) == 2
    err = capsys.readouterr().err
    assert "--q2d 'model' contradicts controller.q2d_method = 'filtered'" in err
    assert str(tuned_file) in err
    # a flag that agrees with the file is accepted
    assert main(["export", "--params", str(tuned_file), "--out", str(out), "--dt", "0.002",
                 "--trajectory", "polynomial", "--force"]) == 0


def _run_loop(capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["run-loop", "--duration", "0.1", "--lockstep", *argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_run_loop_refuses_mixing_exported_gains_with_a_parameter_file(tuned_file, tmp_path,
                                                                      capsys):
    ctrl = tmp_path / "c.py"
    assert main(["export", "--params", str(tuned_file), "--out", str(ctrl)]) == 0
    log = str(tmp_path / "log.csv")
    rc, _, err = _run_loop(capsys, "--log", log, "--controller", str(ctrl),
                           "--params", str(tuned_file))
    assert rc == 2 and "--rig-params" in err
    rc, _, err = _run_loop(capsys, "--log", log, "--controller", str(ctrl), "--rate", "1000")
    assert rc == 2 and "contradicts controller.dt" in err
    rc, _, err = _run_loop(capsys, "--log", log, "--params", str(tuned_file), "--tau-limit", "2")
    assert rc == 2 and "--tau-limit 2.0 contradicts controller.tau_max = 1.5" in err
    rc, _, err = _run_loop(capsys, "--log", log, "--controller", str(ctrl), "--q2d", "model")
    assert rc == 2 and "--q2d applies when exporting now" in err


def test_run_loop_uses_the_files_configuration_and_a_separate_rig_plant(tuned_file, tmp_path,
                                                                        capsys):
    d = json.loads(tuned_file.read_text())
    d["controller"]["trajectory"] = "sinusoid"  # moves from t = 0 (the polynomial rests 0.5 s)
    tuned_file.write_text(json.dumps(d))
    heavy = paper_params().to_dict()
    heavy["plant"]["I"] = [0.14]
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps(heavy))
    logs = {}
    for label, extra in (("own", []), ("heavy", ["--rig-params", str(rig)])):
        log = tmp_path / f"{label}.csv"
        rc, out, err = _run_loop(capsys, "--log", str(log), "--params", str(tuned_file), *extra)
        assert rc == 0, out + err
        doc = json.loads(out)
        assert doc["samples"] == 50 and doc["rate_hz"] == pytest.approx(500.0)
        assert doc["tau_limit"] == 1.5
        logs[label] = np.loadtxt(log, delimiter=",", skiprows=1)
    # same controller (same gains, same reference), another rig: the link moves differently
    np.testing.assert_array_equal(logs["own"][:, 4], logs["heavy"][:, 4])
    assert np.abs(logs["own"][:, 2]).max() > 1e-3
    assert not np.allclose(logs["own"][:, 2], logs["heavy"][:, 2])


# ----- the import graph ------------------------------------------------------------------------

#: The layers, bottom up (docs/architecture.md): a module imports from its own layer or the
#: layers below. Each top-level folder or module of jaxflex has its place; ``__init__`` and
#: ``_aliases`` (the package's face and its old module names) stand outside.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("runtime",), ("core",), ("sim",), ("io", "data"), ("fit",),
    ("identify", "discover", "validate", "loop", "tune", "sweep", "export"), ("app", "__main__"))
RANK = {top: i for i, tops in enumerate(LAYERS) for top in tops}
FACE = ("__init__", "_aliases")
# below ``presets``: these build nothing from presets and must not import it (the layers below
# ``io`` cannot import it at all)
BELOW_PRESETS = ("io/params", "fit/__init__", "fit/space", "fit/problem", "fit/solve",
                 "fit/normal", "fit/levenberg_marquardt", "fit/padding", "fit/uncertainty",
                 "fit/replay", "fit/discretisation", "fit/signal")


def _modules() -> dict[str, ast.Module]:
    return {str(p.relative_to(PKG)): ast.parse(p.read_text()) for p in sorted(PKG.rglob("*.py"))}


def _imports(tree: ast.Module):
    """(module name, imported names, enclosing function name or None) of every import."""
    def walk(node, fn):
        for child in ast.iter_child_nodes(node):
            f = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else fn
            if isinstance(child, ast.Import):
                for a in child.names:
                    yield a.name, (), fn
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                yield child.module, tuple(a.name for a in child.names), fn
            yield from walk(child, f)
    yield from walk(tree, None)


def _top(rel: str) -> str:
    return rel.split("/")[0].removesuffix(".py")


def _targets(mod: str, names: tuple[str, ...]) -> list[str]:
    """The jaxflex top-level folders or modules an import reaches."""
    if mod == "jaxflex":
        return list(names)
    return [mod.split(".")[1]] if mod.startswith("jaxflex.") else []


def test_every_module_has_a_layer():
    assert {_top(rel) for rel in _modules()} - set(FACE) <= set(RANK)


def test_every_import_points_to_its_own_layer_or_below():
    bad = []
    for rel, tree in _modules().items():
        if _top(rel) in FACE:
            continue
        for mod, names, _ in _imports(tree):
            for top in _targets(mod, names):
                if RANK.get(top, -1) > RANK[_top(rel)]:
                    bad.append((rel, mod))
    assert not bad


def test_no_module_outside_the_app_layer_imports_matplotlib_or_argparse():
    bad = []
    for rel, tree in _modules().items():
        if _top(rel) == "app":
            continue
        for mod, _, _ in _imports(tree):
            if mod.split(".")[0] in ("matplotlib", "argparse"):
                bad.append((rel, mod))
    assert not bad


def _loaded_by(modules: str, watched: tuple[str, ...]) -> list[str]:
    """The modules of ``watched`` that importing ``modules`` (comma-separated) in a fresh
    interpreter brings in."""
    import subprocess
    import sys

    code = (f"import sys, {modules}; "
            f"print(','.join(m for m in {watched!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    return [m for m in out.split(",") if m]


def test_commands_start_without_scipy_signal_and_stats():
    """Importing ``scipy.signal`` (which imports ``scipy.stats``) costs every command 0.55 s of
    its start on the 2-core machine; the workflows use jaxflex's Savitzky-Golay and Welch and
    scipy.special's distribution functions instead. Loading every module of the command line
    and of the workflows a command runs must not bring either in (``validate`` imports
    scipy.signal's filter only where it filters)."""
    assert _loaded_by("jaxflex.app.cli, jaxflex.identify, jaxflex.discover, jaxflex.validate, "
                      "jaxflex.tune.robust, jaxflex.tune, jaxflex.sweep, jaxflex.loop.experiments",
                      ("scipy.signal", "scipy.stats")) == []


def test_identify_starts_without_scipy_special():
    """``scipy.special`` (0.2 s of a start: it imports numpy.f2py) is imported where its
    distribution functions are used (discover, the robust tuner, a posterior's box), not by
    the modules ``jaxflex identify`` loads before its fit (a first run compiles its solver
    behind that start)."""
    assert _loaded_by("jaxflex.app.cli, jaxflex.app.cli.identify, jaxflex.identify, "
                      "jaxflex.sweep.engine, jaxflex.app.plots.identify", ("scipy.special",)) == []


def test_no_private_name_is_imported_across_modules():
    bad = []
    for rel, tree in _modules().items():
        for mod, names, _ in _imports(tree):
            for n in names:
                if mod.startswith("jaxflex") and n.startswith("_"):
                    bad.append((rel, mod, n))
    assert not bad


def test_nothing_below_presets_imports_it_and_the_sweep_takes_no_experiment():
    bad = []
    for rel, tree in _modules().items():
        stem = rel.removesuffix(".py")
        for mod, _, _ in _imports(tree):
            if stem in BELOW_PRESETS and mod == "jaxflex.io.presets":
                bad.append((rel, mod))
            if _top(rel) == "sweep" and mod == "jaxflex.loop.experiments":  # names come from presets
                bad.append((rel, mod))
    assert not bad


def test_no_import_loops_between_modules():
    mods = _modules()
    name = {rel: "jaxflex." + rel.removesuffix(".py").replace("/", ".").removesuffix(".__init__")
            for rel in mods}
    known = set(name.values())
    graph: dict[str, set[str]] = {}
    for rel, tree in mods.items():
        # module-level imports only (a lazy import inside a function runs later)
        deps = set()
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in known:
                deps.add(node.module)
                deps |= {f"{node.module}.{a.name}" for a in node.names} & known
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names} & known
        if not rel.endswith("__init__.py"):  # a package face re-exports; its arrows are not loops
            graph[name[rel]] = deps - {name[rel]}
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for d in graph.get(m, ()):
            assert state.get(d) != 1, "import loop: " + " -> ".join(path + [m, d])
            if d not in state:
                visit(d, path + [m])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [])


def test_a_long_line_is_drawn_by_the_extremes_of_each_run_of_samples():
    """``envelope`` draws at most ``max_points`` points, in time order, keeping each run's
    lowest and highest sample (a one-sample spike that even thinning would drop is drawn),
    gaps (NaN) stay gaps, and a short series is drawn whole."""
    from jaxflex.app.plots.identify import envelope

    t = np.arange(10_001) * 1e-3
    y = np.sin(t) + 1e-3 * np.random.default_rng(0).standard_normal(t.size)
    y[4_321] = 5.0  # a spike between any even thinning's points
    tt, yy = envelope(t, y, 200)
    assert tt.size <= 200 and np.all(np.diff(tt) > 0)
    assert yy.max() == 5.0 and yy.min() == y.min()
    assert np.array_equal(yy, y[np.searchsorted(t, tt)])  # samples of the series itself
    y[77] = np.nan
    assert np.isnan(envelope(t, y, 200)[1]).any()
    short = envelope(t[:150], y[:150], 200)
    assert np.array_equal(short[0], t[:150]) and np.array_equal(short[1], y[:150], equal_nan=True)

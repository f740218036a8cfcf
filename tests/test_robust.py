"""Robust tuning: risk measures, spreads from an identification, the box
certificate and the robust search on a small batch."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.certificate import (
    N2_PARAMETERS,
    ParameterBox,
    box_lambda_min,
    certify,
    certify_box,
    lambda_min,
)
from jaxflex.fit.posterior import Posterior
from jaxflex.identify import DEFAULT_FREE, excitation_torque, identify, perturb, synthetic_log
from jaxflex.io.params import load_params, save_params
from jaxflex.io.presets import paper_gains, paper_params
from jaxflex.core.sensing import Sensing
from jaxflex.tune.robust import RiskMeasure, RobustTask, spread_box, tune_robust
from jaxflex.sweep import SpreadError, parse_spread, sample_parameters


@pytest.mark.parametrize("risk", ["mean", "quantile:0.8", "cvar:0.9", "cvar:0.75"])
def test_risk_gradient_equals_finite_differences(risk):
    """The risk of a smooth map of parameters: autodiff gradient = central differences."""
    rm = RiskMeasure.parse(risk)
    A = jnp.asarray(np.random.default_rng(1).normal(size=(23, 4)))

    def f(p):
        return rm(jnp.exp(A @ p) + (A @ p) ** 2)

    p = jnp.asarray([0.1, -0.2, 0.3, 0.05])
    g = jax.grad(f)(p)
    h = 1e-6
    fd = jnp.asarray([(f(p + h * e) - f(p - h * e)) / (2 * h) for e in jnp.eye(4)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
    assert float(jnp.linalg.norm(g)) > 0


def test_risk_values_match_their_definitions():
    x = np.random.default_rng(0).random(41)
    for a in (0.5, 0.9):
        ru = min(t + np.mean(np.maximum(x - t, 0)) / (1 - a) for t in x)
        assert float(RiskMeasure("cvar", a)(jnp.asarray(x))) == pytest.approx(ru, rel=1e-12)
        assert float(RiskMeasure("quantile", a)(jnp.asarray(x))) == pytest.approx(
            np.quantile(x, a), rel=1e-12)
    assert float(RiskMeasure("mean")(jnp.asarray(x))) == pytest.approx(x.mean())
    with pytest.raises(ValueError, match="kind"):
        RiskMeasure.parse("var:0.9")
    with pytest.raises(ValueError, match="alpha"):
        RiskMeasure.parse("cvar:1.5")


def _plant_at(p, vals):
    fr = eqx.tree_at(lambda f: (f.Fc, f.Fs, f.vs, f.sigma0, f.sigma1), p.friction,
                     tuple(jnp.asarray(vals[k]) for k in ("Fc", "Fs", "vs", "sigma0", "sigma1")))
    return eqx.tree_at(lambda q: (q.K, q.friction), p, (jnp.asarray(vals["K"]), fr))


@pytest.mark.slow
def test_box_certificate_holds_at_every_sample_of_the_box():
    """A gain set certified on the box is certified at every plant drawn from it (and the
    bound is a lower bound of lambda_min at each speed), including the box's corners."""
    p = paper_params().to_plant()
    g = paper_gains()
    box = ParameterBox.of_plant(p, 0.2)
    cert = certify_box(box, g, 0.5, num=21, margin=0.0)
    assert cert.certified, cert.lambda_min.min()
    rng = np.random.default_rng(3)
    arr = box.arrays()
    corners = [{k: (box.lo[k] if (c >> i) & 1 else box.hi[k]) for i, k in enumerate(N2_PARAMETERS)}
               for c in range(0, 64, 7)]
    draws = [{k: rng.uniform(box.lo[k], box.hi[k]) for k in N2_PARAMETERS} for _ in range(30)]
    for vals in corners + draws:
        vals = dict(vals)
        vals["Fs"] = np.maximum(vals["Fs"], vals["Fc"])
        assert box.contains(vals)
        q = _plant_at(p, vals)
        c = certify(q, g, 0.5, num=21)
        assert c.certified
        for v in (0.0, 2e-3, 0.05, 0.3):
            assert float(box_lambda_min(arr, g, v)) <= float(lambda_min(q, g, v)) + 1e-12
    # a box that is too wide is not certified, and the bound at its worst corner is attained
    wide = ParameterBox.of_plant(p, 0.6)
    assert not certify_box(wide, g, 0.5, num=21).certified
    with pytest.raises(ValueError, match="lo > hi"):
        ParameterBox({**box.lo, "K": box.hi["K"] + 1}, box.hi)
    with pytest.raises(ValueError, match="sigma0"):
        ParameterBox({**box.lo, "sigma0": np.array([-1.0])}, box.hi)


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    p = paper_params()
    res = 2 * math.pi / 2**16
    sens = Sensing(q1_resolution=res, q2_resolution=res / 50, q1_noise=2e-5, q2_noise=1e-6)
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=3.0, periods=(1.5, 0.7)),
                           substeps=2, sensing=sens, key=jax.random.PRNGKey(0))
    r = identify(log, perturb(p, DEFAULT_FREE, (1.2, 0.9, 1.2, 0.8, 1.2, 0.8)), DEFAULT_FREE,
                 segment_length=300, substeps=2, max_steps=100)
    assert r.converged, r.reason
    path = tmp_path_factory.mktemp("ident") / "ident.json"
    save_params(dataclasses.replace(r.params, gains=paper_gains().to_dict()), path)
    return path


@pytest.mark.slow
def test_spread_from_identification_keeps_the_constraints(identified):
    """Every draw of an identification's posterior (widened 1000x so that the constraints
    would bind) has Fs >= Fc and every parameter > 0; correlations come from the fit."""
    params = load_params(identified)
    post = Posterior.from_params(params, inflate=1000.0)
    assert set(post.names) == set(DEFAULT_FREE)
    spec = parse_spread({"identified": {"file": str(identified), "inflate": 1000.0},
                         "uncertain": {"plant.K": {"dist": "uniform", "rel": 0.1}}})
    th = np.asarray(jax.vmap(lambda i: sample_parameters(spec, i)[0])(jnp.arange(400)))
    lab = spec.labels
    fc, fs = th[:, lab.index("friction.Fc")], th[:, lab.index("friction.Fs")]
    assert np.all(fs >= fc)
    assert np.all(th > 0)
    # wide enough that a normal in physical units would have broken positivity
    s1 = th[:, lab.index("friction.sigma1")]
    assert np.std(s1) / np.mean(s1) > 0.2
    # the box at 95% holds most draws of each parameter
    lo, hi = post.box(0.95)
    inside = (fc >= lo["Fc"][0]) & (fc <= hi["Fc"][0])
    assert inside.mean() > 0.9


@pytest.mark.slow
def test_identified_spread_errors(identified, tmp_path):
    with pytest.raises(SpreadError, match="drawn from the identification"):
        parse_spread({"identified": str(identified),
                      "uncertain": {"friction.Fc": {"dist": "uniform", "rel": 0.1}}})
    with pytest.raises(SpreadError, match="inflate"):
        parse_spread({"identified": {"file": str(identified), "inflate": "x"}})
    plain = tmp_path / "plain.json"
    save_params(paper_params(), plain)
    with pytest.raises(SpreadError, match="no identification covariance"):
        parse_spread({"identified": str(plain)})


@pytest.mark.slow
def test_spread_box_bounds_and_robust_search_small():
    """The box of a uniform spread is its support; the robust search on a tiny batch returns
    gains certified on that box and not worse in risk than its start."""
    spec = parse_spread({"nominal": "paper", "t_final": 0.2, "sensing": "rig",
                         "controller": {"tau_max": 2.0},
                         "uncertain": {"friction.*": {"dist": "uniform", "rel": 0.3},
                                       "plant.K": {"dist": "uniform", "rel": 0.15}}})
    box, how = spread_box(spec)
    assert box.lo["K"][0] == pytest.approx(6.77 * 0.85) and how["K"] == "uniform support"
    task = RobustTask(spec, RiskMeasure.parse("cvar:0.75"), plants=4)
    r = tune_robust(task, paper_gains(), iterations=2, starts=1)
    assert r.certified
    assert r.risk <= r.initial_risk * (1 + 1e-12)
    assert certify_box(box, r.gains, r.v_check, margin=r.margin).certified
    with pytest.raises(ValueError, match="plants"):
        RobustTask(spec, plants=1)


@pytest.mark.slow
def test_cli_tune_spread_writes_certified_gains_that_export_follows(tmp_path, capsys):
    """``jaxflex tune --spread``: the written file carries the controller configuration of the
    spread and the box certificate; ``export`` follows it; an impossible margin is refused
    with nothing written."""
    import json

    from jaxflex.app.cli import main
    from jaxflex.export import load_module

    spread = tmp_path / "spread.json"
    spread.write_text(json.dumps({
        "nominal": "paper", "t_final": 0.2, "sensing": "rig",
        "controller": {"tau_max": 2.0, "q2d_method": "filtered"},
        "uncertain": {"friction.*": {"dist": "uniform", "rel": 0.3},
                      "plant.K": {"dist": "uniform", "rel": 0.15}}}))
    out = tmp_path / "robust.json"
    rc = main(["tune", "--spread", str(spread), "--out", str(out), "--plants", "4",
               "--iterations", "1", "--starts", "1", "--quiet"])
    assert rc == 0
    tuned = load_params(out)
    assert tuned.controller.q2d_method == "filtered" and tuned.controller.tau_max == 2.0
    cert = tuned.extra["certificate"]
    assert cert["kind"] == "robust" and cert["certified"] and cert["risk"] == "cvar:0.9"
    assert cert["box"]["K"]["lo"][0] == pytest.approx(6.77 * 0.85)
    rep = json.loads((tmp_path / "robust_report" / "report.json").read_text())
    assert set(rep["held_out"]) == {"initial", "tuned"}
    py = tmp_path / "c.py"
    assert main(["export", "--params", str(out), "--out", str(py)]) == 0
    assert load_module(py).Q2D_METHOD == "filtered"
    capsys.readouterr()
    bad = tmp_path / "bad.json"
    assert main(["tune", "--spread", str(spread), "--out", str(bad), "--plants", "4",
                 "--iterations", "0", "--margin", "1e6", "--quiet"]) == 2
    assert "no gains found that are certified" in capsys.readouterr().err
    assert not bad.exists()
    assert main(["tune", "--spread", str(spread), "--out", str(bad), "--sensing", "ideal"]) == 2
    assert "come from the spread file" in capsys.readouterr().err


def test_a_file_whose_gains_were_edited_after_certification_is_refused(tmp_path):
    import json

    from jaxflex.io.params import ParamsError

    d = paper_params().to_dict()
    d["certificate"] = {"kind": "robust", "gains": dict(d["gains"])}
    path = tmp_path / "c.json"
    path.write_text(json.dumps(d))
    assert load_params(path).extra["certificate"]["kind"] == "robust"
    d["gains"]["KD1"] = [2.0]
    path.write_text(json.dumps(d))
    with pytest.raises(ParamsError, match="edited after"):
        load_params(path)

"""The top level a notebook uses: the workflows' names resolve without hiding the workflow
packages, and their results hold numbers, draw a Figure and save JSON beside a PNG."""

import json

import jax
import numpy as np
import pytest


def test_top_level_names_leave_the_workflow_packages_importable():
    import jaxflex
    import jaxflex.identify.core

    assert callable(jaxflex.identify_log) and callable(jaxflex.discover_effects)
    assert jaxflex.identify.core.identify is jaxflex.identify.identify
    assert hasattr(jaxflex.data, "load_emps")
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = jaxflex.nothing


def test_certification_is_numbers_with_a_figure_and_a_file(tmp_path):
    jax.config.update("jax_enable_x64", True)
    from matplotlib.figure import Figure

    import jaxflex

    cert = jaxflex.certify_gains(jaxflex.paper_plant(), jaxflex.paper_gains(), 2.0, num=21)
    assert isinstance(cert.lambda_min, np.ndarray) and cert.lambda_min.shape == (21,)
    assert 0.0 < cert.certified_up_to <= 2.0 and np.isfinite(cert.D_bar)
    assert isinstance(cert.plot(), Figure)
    written = cert.save(tmp_path / "cert.json")
    assert [p.name for p in written] == ["cert.json", "cert.png"]
    doc = json.loads((tmp_path / "cert.json").read_text())
    assert doc["certified_up_to"] == pytest.approx(cert.certified_up_to)
    assert len(doc["velocities"]) == 21


def test_certify_gains_takes_the_gains_of_a_parameter_set():
    jax.config.update("jax_enable_x64", True)
    import jaxflex

    with pytest.raises(ValueError, match="give gains"):
        jaxflex.certify_gains(jaxflex.paper_plant())
    p = jaxflex.paper_params()
    if p.gains is not None:
        assert jaxflex.certify_gains(p, vmax=1.0, num=5).velocities.shape == (5,)


@pytest.mark.slow
def test_sweep_tune_and_validate_results_draw_and_save(tmp_path):
    jax.config.update("jax_enable_x64", True)
    from matplotlib.figure import Figure

    import jaxflex
    from jaxflex.identify import excitation_torque, synthetic_log

    sweep = jaxflex.sweep_spread({"nominal": "paper", "t_final": 0.2, "samples": 8, "uncertain": {
        "plant.*": {"dist": "uniform", "rel": 0.2}}}, chunk_size=4)
    assert np.isfinite(sweep.summary["metrics"]["rms_error"]["q95"])
    assert all(isinstance(sweep.plot(w), Figure)
               for w in ("sensitivity", "error_histograms", "error_bands"))
    with pytest.raises(ValueError, match="no figure"):
        sweep.plot("nothing")

    tuning = jaxflex.tune_gains(jaxflex.paper_params(), iterations=1, starts=1)
    assert tuning.cost <= tuning.initial_cost and tuning.certified_up_to >= tuning.v_task
    assert isinstance(tuning.gains, jaxflex.CascadeGains)

    p = jaxflex.paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=2.0), substeps=2)
    validation = jaxflex.validate_model(p, log)
    assert 0.0 <= validation.gap < 1.0 and np.isfinite(validation.torque_pct)

    for name, result in (("sweep", sweep), ("tune", tuning), ("validate", validation)):
        written = result.save(tmp_path / f"{name}.json")
        assert [w.name for w in written] == [f"{name}.json", f"{name}.png"]
        assert json.loads(written[0].read_text())

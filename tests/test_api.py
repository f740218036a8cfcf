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

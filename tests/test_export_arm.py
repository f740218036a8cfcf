"""The cascade on the KUKA KR300's coupled axes 1-3 (``jaxflex.data.kr300.kuka_kr300_params``)
goes the single joint's way: a parameter file, the N2 certificate for n joints, the closed
loop, and the export whose torques equal JAX's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxflex.core.certificate import lambda_min_curve
from jaxflex.data.kr300 import KR300_CONTROLLER, kuka_kr300_params, kuka_kr300_plant
from jaxflex.io.params import Params, ParamsError, load_params, save_params


@pytest.fixture(scope="module")
def arm_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("kr300") / "kr300.json"
    save_params(Params.from_dict(kuka_kr300_params()), path)
    return path


def test_parameter_file_builds_the_shipped_arm(arm_file):
    """The file's links are the shipped arm's: same M(q), G(q), J, K as ``kuka_kr300_plant``,
    three joints, the controller section kept; a links section missing a field is refused
    by name."""
    params = load_params(arm_file)
    assert params.n == 3
    assert params.controller.tau_max == KR300_CONTROLLER["tau_max"]
    plant, ref = params.to_plant(), kuka_kr300_plant()
    q = np.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(plant.links.mass_matrix(q), ref.links.mass_matrix(q), rtol=1e-14)
    np.testing.assert_allclose(plant.links.gravity(q), ref.links.gravity(q), rtol=1e-14)
    np.testing.assert_array_equal(plant.J, ref.J)
    np.testing.assert_array_equal(plant.K, ref.K)
    bad = kuka_kr300_params()
    del bad["links"]["payload"]
    with pytest.raises(ParamsError, match="payload"):
        Params.from_dict(bad)


def test_certificate_of_the_arm_is_its_joints_certificates():
    """N2 for n joints is block-diagonal per joint up to a permutation (eq. 29-31) and free
    of M(q): the arm's lambda_min(N2) at each speed is the least of its joints' one-joint
    lambda_min, each joint certified as a single joint with its own K, friction and gains."""
    p = kuka_kr300_params()
    params = Params.from_dict(p)
    v = np.concatenate([np.linspace(0.0, 1.0, 11), np.geomspace(1e-3, 1e-2, 5)])
    arm = np.asarray(lambda_min_curve(params.to_plant(), params.to_gains(), v))
    joints = []
    for j in range(3):
        pick = lambda sec: {k: [val[j]] for k, val in sec.items()}
        one = Params.from_dict({"plant": {"I": [1.0], "J": [p["plant"]["J"][j]],
                                          "K": [p["plant"]["K"][j]]},
                                "friction": pick(p["friction"]), "gains": pick(p["gains"])})
        joints.append(np.asarray(lambda_min_curve(one.to_plant(), one.to_gains(), v)))
    # to the eigensolver's accuracy, eps times a block's norm (up to 1e17 here)
    np.testing.assert_allclose(arm, np.min(joints, axis=0), rtol=1e-8)


def test_cli_certify_the_arm(arm_file, capsys):
    """``jaxflex certify`` reads the arm's file and evaluates N2 over the speeds asked for."""
    from jaxflex.app.cli import main

    rc = main(["certify", "--params", str(arm_file), "--vmax", "1", "--num", "51", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == (0 if out["certified"] else 1)
    assert len(out["lambda_min"]) == 51 and np.all(np.isfinite(out["lambda_min"]))
    assert out["lambda_min"][0] > 0  # at rest


@pytest.mark.slow
def test_cli_export_check_of_the_arm(arm_file, tmp_path, capsys):
    """``jaxflex export --params kr300.json --out controller.py --check``: the standalone
    controller of the coupled arm (model-based q2d with M, C, G and their derivatives along
    the reference, the friction observers) closes the loop from rest with the springs holding
    the arm's weight, tracks, stays below its torque limit, and its torques equal the JAX
    controller's to the parity tolerance (docs/spec.md section 7.1)."""
    from jaxflex.app.cli import main
    from jaxflex.export import (
        check_parity,
        load_module,
        parity_ok,
        parity_tolerance,
        rig_controller,
    )

    out = tmp_path / "controller.py"
    rc = main(["export", "--params", str(arm_file), "--out", str(out), "--check",
               "--check-duration", "1.0"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "3 joint(s)" in text and "check passed" in text, text
    mod = load_module(out)
    assert mod.N_JOINTS == 3
    # the same run through the API (the compiled programs of the command are reused)
    r = check_parity(rig_controller(load_params(arm_file)), mod, t_final=1.0)
    tol = parity_tolerance(r)
    assert r.tau_jax.shape == (1000, 3)
    assert np.all(np.isfinite(r.tau_jax))
    assert 1e3 < np.max(np.abs(r.tau_jax)) < KR300_CONTROLLER["tau_max"]  # gravity, no clip
    assert r.rms_error < 1e-3, str(r)
    assert 1e-12 < tol <= 1e-14 * KR300_CONTROLLER["tau_max"]
    assert r.unfused_diff <= tol, str(r)
    assert parity_ok(r), str(r)


@pytest.mark.slow
def test_c_export_of_the_arm_equals_the_python_export(tmp_path):
    """The C99 export of the arm's controller (``jaxflex export --out controller.c``) meets
    the same parity and equals the Python export of the same traced program bit for bit."""
    from jaxflex.export import (
        check_parity,
        generate_source,
        load_module,
        parity_ok,
        parity_tolerance,
        rig_controller,
        trace,
    )
    from jaxflex.export.native import export_c, find_cc, load_c

    if find_cc() is None:
        pytest.skip("no C compiler")
    sc = rig_controller(Params.from_dict(kuka_kr300_params()))
    tr = trace(sc)
    export_c(sc, tmp_path / "controller.c", traced=tr)
    cmod = load_c(tmp_path / "controller.c")
    py = load_module(generate_source(sc, traced=tr))
    assert cmod.N_JOINTS == 3 and cmod.STATE_NAMES == py.STATE_NAMES
    r = check_parity(sc, cmod, t_final=0.5)
    assert r.unfused_diff <= parity_tolerance(r) and parity_ok(r), str(r)
    ctrl = py.Controller()
    tau_py = np.array([ctrl.step(k * 1e-3, r.q1_meas[k], r.q2_meas[k]) for k in range(500)])
    np.testing.assert_array_equal(r.tau_export, tau_py)

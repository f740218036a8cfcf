"""The N2 stability certificate (paper section 4, eq. 24-33; docs/spec.md section 4)."""

from __future__ import annotations

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sp

from jaxflex.core.certificate import (
    certify,
    d_vector,
    lambda_min,
    lambda_min_curve,
    n2_matrix,
    psi_sharp,
    ultimate_bound,
)
from jaxflex.core.controller import CascadeGains
from jaxflex.core.friction import LuGre
from jaxflex.io.params import save_params
from jaxflex.core.plant import DiagonalInertia, FlexibleJointPlant
from jaxflex.io.presets import paper_gains, paper_params, paper_plant, paper_sinusoid


def _lyapunov_derivative(n: int):
    """V' of eq. 24-26 along the closed loop (eq. 14, 17, 23), derived symbolically for n
    joints with diagonal gain/parameter matrices and a general skew matrix W = M'/2 - C.

    Returns (Vdot, rho, symbols) with z_tilde = Psi# eta substituted (eta = Psi_hat z_tilde).
    """
    def vec(name):
        return sp.Matrix(sp.symbols(f"{name}_0:{n}", real=True))

    def dg(name, positive=True):
        return sp.diag(*sp.symbols(f"{name}_0:{n}", positive=positive))

    e1, de1, e2, de2, eta, z = (vec(s) for s in ("e1", "de1", "e2", "de2", "eta", "z"))
    K, J, Ke, KD1, KD2, L1, L2 = (dg(s) for s in ("K", "J", "Ke", "KD1", "KD2", "L1", "L2"))
    M = sp.Matrix(n, n, lambda i, j: sp.Symbol(f"M_{min(i, j)}{max(i, j)}", real=True))
    W = sp.Matrix(n, n, lambda i, j: 0 if i == j else
                  (1 if i < j else -1) * sp.Symbol(f"W_{min(i, j)}{max(i, j)}", real=True))
    S0, S1 = dg("sigma0"), dg("sigma1")
    Psih, dPsi = dg("Psihat"), dg("dPsi", positive=None)
    zt = Psih.inv() * eta  # z_tilde = Psi# eta for |v| >= eps (eq. 30)

    s1 = de1 + L1 * e1
    s2 = de2 + L2 * e2
    # eq. 23: observer error dynamics
    dzt = -S0 * Psih * zt - S0 * dPsi * z + Ke * S0 * s1
    # eq. 14 with F - F_hat = sigma0 z_tilde + sigma1 z_tilde' (eq. 4, 22; sigma2 cancels):
    # M s1' = -(C + KD1) s1 - (F - F_hat) + K e2
    M_ds1_plus_C = -KD1 * s1 - (S0 * zt + S1 * dzt) + K * e2
    # eq. 17: J s2' = -KD2 s2
    J_ds2 = -KD2 * s2
    P1, P2 = 2 * L1 * KD1, 2 * L2 * KD2
    # d/dt of eq. 25-26; s1^T M s1' + 1/2 s1^T M' s1 = s1^T (M s1' + C s1) + s1^T W s1
    Vdot = (s1.T * M_ds1_plus_C + s1.T * W * s1 + zt.T * Ke.inv() * dzt
            + e1.T * P1 * de1 + s2.T * J_ds2 + e2.T * P2 * de2)[0, 0]
    rho = list(e1) + list(de1) + list(e2) + list(de2) + list(eta)
    syms = {"K": K, "Ke": Ke, "KD1": KD1, "KD2": KD2, "L1": L1, "L2": L2, "S0": S0, "S1": S1,
            "Psih": Psih, "dPsi": dPsi, "z": z, "M": M, "J": J}
    return sp.expand(Vdot), rho, syms


def _two_joint_case():
    fr = LuGre(Fc=[0.11, 0.3], Fs=[0.15, 0.4], vs=[0.05, 0.1], sigma0=[100.0, 250.0],
               sigma1=[0.1, 0.7], sigma2=[0.2, 0.05])
    plant = FlexibleJointPlant(DiagonalInertia(I=[0.07, 0.2]), J=[0.005, 0.01], K=[6.77, 20.0],
                               friction=fr)
    gains = CascadeGains(Ke=[0.001, 0.004], KD1=[1.0, 2.5], KD2=[1.0, 0.7], kv=[2.0, 5.0],
                         L1=[200.0, 30.0], L2=[6.0, 11.0])
    return plant, gains


def test_n2_matches_symbolic_lyapunov_derivative():
    """N2 and D from the code equal -1/2 Hessian and the rest of V' derived with sympy."""
    n = 2
    Vdot, rho, S = _lyapunov_derivative(n)
    hess = sp.hessian(Vdot, rho)
    assert all(sp.simplify(h.diff(r)) == 0 for h in hess for r in rho[:1])  # V' is quadratic
    N2_sym = -hess / 2
    rest = sp.expand(Vdot + (sp.Matrix(rho).T * N2_sym * sp.Matrix(rho))[0, 0])
    D_sym = sp.Matrix([sp.diff(rest, r) for r in rho])
    # the remainder is exactly linear in rho (rho^T D) and carries dPsi
    assert sp.expand(rest - (sp.Matrix(rho).T * D_sym)[0, 0]) == 0
    assert all(sp.expand(d.subs({x: 0 for x in S["dPsi"].values() if x != 0})) == 0 for d in D_sym)
    # M and the skew part W dropped out
    assert not (N2_sym.free_symbols | D_sym.free_symbols) & (S["M"].free_symbols | {
        s for s in Vdot.free_symbols if s.name.startswith("W_")})

    plant, gains = _two_joint_case()
    fr = plant.friction
    for v in ([0.3, -2.0], [0.02, 7.5]):
        v = np.asarray(v)
        # independent numbers for Psi_hat, dPsi: m(v) = 2/pi v arctan(kv v), g Stribeck
        kv = np.asarray(gains.kv)
        g = np.asarray(fr.Fc) + np.asarray(fr.Fs - fr.Fc) * np.exp(-(v / np.asarray(fr.vs)) ** 2)
        m = 2 / math.pi * v * np.arctan(kv * v)
        z = np.array([0.0011, -0.0009])
        num = {}
        for key, arr in (("K", plant.K), ("Ke", gains.Ke), ("KD1", gains.KD1), ("KD2", gains.KD2),
                         ("L1", gains.L1), ("L2", gains.L2), ("S0", fr.sigma0), ("S1", fr.sigma1),
                         ("Psih", m / g), ("dPsi", (np.abs(v) - m) / g)):
            for i in range(n):
                num[S[key][i, i]] = float(np.asarray(arr)[i])
        for i in range(n):
            num[S["z"][i]] = float(z[i])
        N2_num = np.array(N2_sym.subs(num).evalf(), dtype=float)
        D_num = np.array(D_sym.subs(num).evalf(), dtype=float).ravel()
        N2_code = np.asarray(n2_matrix(plant, gains, jnp.asarray(v)))
        D_code = np.asarray(d_vector(plant, gains, jnp.asarray(v), jnp.asarray(z)))
        np.testing.assert_allclose(N2_code, N2_num, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(D_code, D_num, rtol=1e-12, atol=1e-9)


def test_psi_sharp_below_eps_and_finite_gradient():
    plant, gains = paper_plant(), paper_gains()
    assert float(psi_sharp(plant, gains, 1e-4, eps=1e-3)[0]) == pytest.approx(1e3)
    # Above eps, Psi# = g(v)/m(v) is checked through its limits, not by restating it: at high
    # speed m(v) -> |v| and g -> Fc (Coulomb), so Psi# |v| -> Fc; just above eps, m(v) ~
    # (2/pi) kv v^2 and g ~ Fs (Stribeck plateau), so Psi# v^2 -> pi Fs / (2 kv).
    Fc, Fs, kv = 0.11, 0.15, float(gains.kv[0])
    assert float(psi_sharp(plant, gains, 1e4)[0]) * 1e4 == pytest.approx(Fc, rel=1e-4)
    assert float(psi_sharp(plant, gains, -1e4)[0]) * 1e4 == pytest.approx(Fc, rel=1e-4)
    v = 2e-3
    assert float(psi_sharp(plant, gains, v)[0]) * v**2 == pytest.approx(
        math.pi * Fs / (2 * kv), rel=2e-3)
    # it falls with speed (the reason the certificate holds only up to some speed)
    vs = np.linspace(2e-3, 50.0, 400)
    assert np.all(np.diff(np.asarray([float(psi_sharp(plant, gains, x)[0]) for x in vs])) < 0)
    grad = jax.grad(lambda s: lambda_min(plant, gains, s))(0.0)
    assert np.isfinite(grad)
    dg = jax.grad(lambda gg: lambda_min(plant, gg, 1.0))(gains)
    assert all(np.isfinite(np.asarray(getattr(dg, k))).all() for k in ("Ke", "KD1", "L2"))


def test_paper_gains_certified_over_paper_sinusoid():
    plant, gains = paper_plant(), paper_gains()
    traj = paper_sinusoid()
    ts = jnp.linspace(0.0, 10.0, 2001)
    vmax_task = float(jnp.max(jnp.abs(traj.sample(ts, order=1)[:, 1])))
    assert 0.1 < vmax_task < 1.0
    res = certify(plant, gains, 3 * vmax_task)
    assert res.certified and res.certified_up_to == pytest.approx(3 * vmax_task)
    assert np.all(res.lambda_min > 0.5)
    assert len(res.velocities) == len(res.lambda_min)


def test_certified_range_boundary_and_monotone():
    plant, gains = paper_plant(), paper_gains()
    res = certify(plant, gains, 200.0, num=201)
    assert not res.certified
    vb = res.certified_up_to
    assert 10.0 < vb < 200.0
    assert float(lambda_min(plant, gains, vb)) > 0
    assert float(lambda_min(plant, gains, vb * 1.001)) < 0
    lam = np.asarray(lambda_min_curve(plant, gains, np.linspace(0.01, 200.0, 50)))
    assert np.all(np.diff(lam) <= 1e-12)  # Psi# falls with |v|, so does lambda_min
    # a larger observer gain Ke shrinks sigma0 Psi# / Ke: certified range shrinks
    res2 = certify(plant, eqx.tree_at(lambda g: g.Ke, gains, gains.Ke * 10), 200.0, num=201)
    assert res2.certified_up_to < vb


@pytest.mark.parametrize("name,value", [("KD1", 0.0), ("KD2", 0.0), ("KD1", -1.0), ("KD2", -0.5)])
def test_zero_or_negative_damping_refused_or_uncertified(name, value):
    g = paper_gains()
    with pytest.raises(ValueError, match=name):
        CascadeGains(**{**g.to_dict(), name: [value]})
    # built around the check (e.g. inside a tracer): the certificate reports it uncertified
    bad = eqx.tree_at(lambda gg: getattr(gg, name), g, jnp.array([value]))
    res = certify(paper_plant(), bad, 5.0)
    assert not res.certified and res.certified_up_to == 0.0
    assert np.all(res.lambda_min <= 0)


def test_bad_ranges_raise():
    plant, gains = paper_plant(), paper_gains()
    for vmax in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="vmax"):
            certify(plant, gains, vmax)
    with pytest.raises(ValueError, match="margin"):
        certify(plant, gains, 5.0, margin=-1.0)
    with pytest.raises(ValueError, match="vmax"):
        ultimate_bound(plant, gains, 0.0)
    with pytest.raises(ValueError, match="friction"):
        certify(paper_plant(friction=False), gains, 5.0)


def test_ultimate_bound():
    plant, gains = paper_plant(), paper_gains()
    b = ultimate_bound(plant, gains, 1.0)
    assert b["D_bar"] > 0 and b["lambda_min"] > 0
    assert b["rho_bound"] == pytest.approx(b["D_bar"] / b["lambda_min"])
    # more link damping: larger lambda_min, D unchanged -> tighter bound
    g2 = CascadeGains(**{**gains.to_dict(), "KD1": [2.0], "KD2": [2.0]})
    assert ultimate_bound(plant, g2, 1.0)["rho_bound"] < b["rho_bound"]
    assert ultimate_bound(plant, gains, 200.0)["rho_bound"] == float("inf")


def _cli(capsys, *args):
    """Run ``jaxflex certify`` in-process; returns (exit code, stdout, stderr)."""
    from jaxflex.app.cli import main

    rc = main(["certify", *args])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_certify_json(tmp_path, capsys):
    p = tmp_path / "p.json"
    save_params(paper_params(), p)
    rc, stdout, _ = _cli(capsys, "--params", str(p), "--vmax", "200", "--num", "101", "--json")
    out = json.loads(stdout)
    assert rc == 1  # not certified over the whole grid
    assert len(out["velocities"]) == len(out["lambda_min"]) == 101
    assert 10.0 < out["certified_up_to"] < 200.0
    rc, stdout, _ = _cli(capsys, "--params", str(p), "--json")
    out = json.loads(stdout)
    assert rc == 0 and out["certified_up_to"] == pytest.approx(5.0)


def test_cli_certify_bad_input(tmp_path, capsys):
    p = tmp_path / "p.json"
    save_params(paper_params(), p)
    rc, _, err = _cli(capsys, "--params", str(p), "--vmax", "0")
    assert rc == 2 and "vmax" in err
    d = paper_params().to_dict()
    d["gains"]["KD2"] = -1.0
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    rc, _, err = _cli(capsys, "--params", str(bad))
    assert rc == 2 and "KD2" in err


def test_certify_is_float64_without_the_global_setting():
    """From Python with float64 off (the default), certify computes in float64 anyway: the
    paper's gains are certified up to 5 rad/s (float32 arithmetic would say lambda_min =
    -6.95, not certified), and the global setting is left off."""
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import jax\n"
        "from jaxflex.core.certificate import certify\n"
        "from jaxflex.io.presets import paper_gains, paper_plant\n"
        "r = certify(paper_plant(), paper_gains(), 5.0)\n"
        "print(r.certified, r.to_dict()['min_lambda_min'], r.lambda_min.dtype, "
        "jax.config.jax_enable_x64)\n"
    )
    root = Path(__file__).resolve().parents[1]
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = str(root)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       cwd=root)
    assert r.returncode == 0, r.stderr
    certified, lam, dtype, x64 = r.stdout.split()
    assert certified == "True" and dtype == "float64" and x64 == "False"
    # the float64 answer (the model's float32-rounded parameters move it by ~1e-8)
    assert float(lam) == pytest.approx(float(certify(paper_plant(), paper_gains(), 5.0)
                                             .to_dict()["min_lambda_min"]), rel=1e-6)
    assert float(lam) > 0.5


def test_lambda_min_of_a_graded_n2_holds_its_digits():
    """On the shipped KR300 arm just above eps, p55 = sigma0 Psi# / Ke is about 1e21 while
    lambda_min is about 1e5: an eigensolver on the block is wrong by up to its own size (it
    showed a failing band of speeds that does not exist). ``lambda_min`` agrees with a
    60-digit eigensolution to 1e-9, and the arm's gain rule is certified on a fine grid."""
    import mpmath

    from jaxflex.data.kr300 import kuka_kr300_params
    from jaxflex.io.params import Params

    p = Params.from_dict(kuka_kr300_params())
    plant, gains = p.to_plant(), p.to_gains()
    mpmath.mp.dps = 60
    for v in (1.05e-3, 1.2e-3, 1.4e-3):
        N = np.asarray(n2_matrix(plant, gains, v))
        exact = min(min(float(e) for e in mpmath.eigsy(mpmath.matrix(
            N[j::3, j::3].tolist()))[0]) for j in range(3))
        assert float(lambda_min(plant, gains, v)) == pytest.approx(exact, rel=1e-9)
    assert certify(plant, gains, vmax=0.05, num=2001).certified

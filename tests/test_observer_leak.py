"""The observer's leakage (``CascadeGains.leak``): the paper's observer is leak = 0
and unchanged; a leak removes the growing rest mode; files, certificate and search carry it."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.loop.analyse import rest_jacobian, rest_map, spectral_radius
from jaxflex.core.certificate import psi_sharp
from jaxflex.core.controller import CascadeGains
from jaxflex.io.params import Params, ParamsError
from jaxflex.io.presets import paper_gains, paper_params
from jaxflex.tune import gains_of


def _leaky(leak):
    g = paper_gains()
    return eqx.tree_at(lambda g: g.leak, g, jnp.full(g.n, leak))


def _radius(gains):
    m = rest_map(paper_params().to_plant(), gains)
    return spectral_radius(np.asarray(eqx.filter_jit(rest_jacobian)(m)))


def test_leak_removes_the_growing_rest_mode():
    # (float64 is on for the suite, tests/conftest.py)
    # the paper's observer integrates the error at rest: a growing mode (radius > 1)
    assert _radius(paper_gains()) > 1.001
    # with leakage every rest mode decays
    assert _radius(_leaky(0.2)) < 0.999


def test_paper_observer_is_leak_zero_and_files_keep_it_out():
    g = paper_gains()
    assert float(g.leak[0]) == 0.0
    assert "leak" not in g.to_dict()  # files of the paper's observer are unchanged
    assert g.to_vector().shape == (6,)  # not a searched gain


def test_leak_round_trips_through_files_and_the_search_coordinates():
    d = paper_params().to_dict()
    d["gains"]["leak"] = [0.2]
    p = Params.from_dict(d)
    assert p.to_gains().to_dict()["leak"] == [0.2]
    assert Params.from_dict(p.to_dict()).to_gains().to_dict() == p.to_gains().to_dict()
    theta = jnp.log(p.to_gains().to_vector())
    assert float(gains_of(theta, p.to_gains().leak).leak[0]) == pytest.approx(0.2)


@pytest.mark.parametrize("bad", [[-0.1], ["0.2"], [0.1, 0.2]])
def test_bad_leak_in_a_file_is_named(bad):
    d = paper_params().to_dict()
    d["gains"]["leak"] = bad
    with pytest.raises(ParamsError, match="gains.leak"):
        Params.from_dict(d)


def test_negative_leak_is_refused():
    with pytest.raises(ValueError, match="leak"):
        CascadeGains(**{**paper_gains().to_dict(), "leak": [-1.0]})


def test_certificate_uses_the_leaky_observer_at_rest():
    p = paper_params().to_plant()
    # paper: Psi_hat(0) = 0, eq. 30 takes 1/eps
    assert float(psi_sharp(p, paper_gains(), 0.0, eps=1e-3)[0]) == pytest.approx(1e3)
    # leak: Psi# = g(0) / leak = Fs / leak, finite, no cut-off
    assert float(psi_sharp(p, _leaky(0.2), 0.0, eps=1e-3)[0]) == pytest.approx(0.15 / 0.2)
    # away from rest the leak lowers Psi# = g / (m + leak)
    v = 0.5
    assert float(psi_sharp(p, _leaky(0.2), v)[0]) < float(psi_sharp(p, paper_gains(), v)[0])

"""Validation workflow and the rotor model kind: known answers on synthetic data."""

import jax
import numpy as np
import pytest

from jaxflex.io.logs import Log
from jaxflex.io.params import Params, ParamsError
from jaxflex.validate import (
    PPCascade,
    rel_error_pct,
    rigid_torque,
    rigid_torque_fit,
    segment_gap,
    torque_prediction,
)

jax.config.update("jax_enable_x64", True)


def _rotor_params(K=2e4, skew=0.0, off=0.0):
    return Params.from_dict({
        "plant": {"I": 1.0, "J": 2.0, "K": K},
        "friction": {"Fc": 1.0, "Fs": 1.0, "vs": 0.1, "sigma0": 1e5, "sigma1": 0.0, "sigma2": 0.0},
        "effects": {"motor_friction": {"Fm": [3.0], "bm": [5.0], "width": [0.01]},
                    "encoder_skew": {"skew": [skew], "offset": [off]}}})


def _rotor_log(p, N=1500, dt=2e-3):
    """A log whose torque obeys the rotor line of eq. 3 exactly for a smooth motion."""
    t = np.arange(N) * dt
    q1 = 0.3 * np.sin(2.0 * t) + 0.1 * np.sin(5.3 * t)
    v1 = 0.6 * np.cos(2.0 * t) + 0.53 * np.cos(5.3 * t)
    a1 = -1.2 * np.sin(2.0 * t) - 2.809 * np.sin(5.3 * t)
    d = 1e-3 * np.sin(3.1 * t)
    q2, v2, a2 = q1 + d, v1 + 3.1e-3 * np.cos(3.1 * t), a1 - 9.61e-3 * np.sin(3.1 * t)
    e, sk = p.effects["motor_friction"], p.effects["encoder_skew"]
    q1c = q1 + sk["skew"][0] * v1 + sk["offset"][0]
    tau = (p.plant["J"][0] * a2 + p.plant["K"][0] * (q2 - q1c)
           + e["Fm"][0] * np.tanh(v2 / e["width"][0]) + e["bm"][0] * v2)
    return Log.from_arrays(t=t, tau=tau, q1=q1, q2=q2)


def test_rotor_torque_prediction_is_exact_for_the_true_model():
    p = _rotor_params(skew=2e-3, off=1e-4)
    log = _rotor_log(p)
    err = rel_error_pct(log.tau[100:-100], torque_prediction(p, log, kind="rotor")[100:-100])
    assert err < 0.2  # Savitzky-Golay derivative error only
    wrong = _rotor_params(K=3e4, skew=2e-3, off=1e-4)
    assert rel_error_pct(log.tau, torque_prediction(wrong, log, kind="rotor")) > 10 * err
    no_skew = _rotor_params(skew=0.0, off=1e-4)
    assert rel_error_pct(log.tau, torque_prediction(no_skew, log, kind="rotor")) > 10 * err


def test_rotor_replay_gap_small_for_true_model_and_larger_for_wrong_one():
    p = _rotor_params()
    log = _rotor_log(p)
    g = segment_gap(p, log, kind="rotor", length=50)
    g_wrong = segment_gap(_rotor_params(K=1e4), log, kind="rotor", length=50)
    assert g < 0.05 and g_wrong > 3 * g


def test_loop_controller_section_is_checked():
    assert PPCascade.from_dict({"type": "pp_cascade", "kp": 1.0, "kv": 2.0, "gtau": 3.0}).vmax == 10
    with pytest.raises(ParamsError, match="unknown key 'kpp'"):
        PPCascade.from_dict({"type": "pp_cascade", "kpp": 1.0, "kv": 2.0, "gtau": 3.0})
    with pytest.raises(ParamsError, match="gtau is missing"):
        PPCascade.from_dict({"type": "pp_cascade", "kp": 1.0, "kv": 2.0})


def _pp_params(M=95.0, Fv=200.0, Fc=20.0, offset=3.0):
    return Params.from_dict({
        "plant": {"I": M - 1e-3, "J": 1e-3, "K": 1e6},
        "friction": {"Fc": Fc, "Fs": 26.0, "vs": 0.01, "sigma0": 1e6, "sigma1": 0.0, "sigma2": Fv},
        "effects": {"torque_offset": {"offset": [offset]}},
        "loop_controller": {"type": "pp_cascade", "kp": 160.18, "kv": 243.44, "gtau": 35.15}})


def test_closed_loop_fit_recovers_a_known_rigid_axis_and_refuses_what_it_cannot_run():
    """Closed-loop output error through the P/P cascade (the EMPS benchmark's loop): a log
    simulated by the same loop from known parameters is fitted back from 15-20% off."""
    from jaxflex.validate import closed_loop_fit, simulate_pp_cascade

    truth = _pp_params()
    from jaxflex.data import load_emps

    dt, N = 1e-3, 4000
    t = np.arange(N) * dt
    ref = load_emps("DATA_EMPS").q1d[:N, 0]  # the benchmark's rest-to-rest reference [m]
    q, tau = simulate_pp_cascade(truth, PPCascade.from_dict(truth.extra["loop_controller"]),
                                 ref, dt)
    log = Log.from_arrays(t=t, tau=tau, q1=q, q2=q, q1d=ref)
    start = _pp_params(M=80.0, Fv=240.0, Fc=16.0, offset=2.4)
    res = closed_loop_fit(start, log, ["I", "sigma2", "Fc", "torque_offset.offset"],
                          max_steps=40)
    p = res.params
    assert res.converged and res.cost < 1e-6 * res.cost_start
    assert p.plant["I"][0] == pytest.approx(truth.plant["I"][0], rel=1e-3)
    assert p.friction["sigma2"][0] == pytest.approx(200.0, rel=1e-3)
    assert p.friction["Fc"][0] == pytest.approx(20.0, rel=1e-3)
    # standard errors with the log's consecutive blocks as clusters (closed-loop errors are
    # correlated in time), finite for every fitted name
    assert res.stderr_kind.startswith("block-robust")
    assert all(np.all(np.isfinite(v)) and np.all(np.asarray(v) >= 0) for v in res.stderr.values())
    with pytest.raises(ValueError, match="declare no controller"):
        closed_loop_fit(Params.from_dict({k: v for k, v in start.to_dict().items()
                                          if k != "loop_controller"}), log, ["I"])
    with pytest.raises(ValueError, match="no reference"):
        closed_loop_fit(start, Log.from_arrays(t=t, tau=tau, q1=q, q2=q), ["I"])


# ----- declared loops: the EMPS P/P cascade, a PD loop, or jaxflex's own cascade -------------

def _declared(gen, section, scale=None):
    """The generated log's true parameters with the loop ``section`` declared; ``scale``:
    (section, name, factor) multiplies one parameter."""
    import copy

    d = copy.deepcopy(gen.truth["plant"])
    d["loop_controller"] = section
    if scale is not None:
        sec, name, f = scale
        d[sec][name] = [v * f for v in d[sec][name]]
    return Params.from_dict(d)


def test_declared_pd_loop_reproduces_a_pd_rotor_log_and_wrong_parameters_do_not():
    """A log of ``datagen.RotorPD`` (kp 8, kd 0.4, 2 N m, 5 ms dirty derivative, on q2; 16-bit
    encoders with noise, 12-bit DAC) simulated back through the declared PD with the truth:
    measured position error 0.06% (seed 1, 2 s); K or Fc 30% off: 7-21%."""
    from jaxflex.identify.datagen import generate_log
    from jaxflex.validate import PDLoop, closed_loop_errors, loop_controller

    gen = generate_log(seed=1, t_final=2.0, loop="pd_rotor")
    pd = {"type": "pd", "kp": 8.0, "kd": 0.4, "on": "q2", "tau_max": 2.0, "velocity_tc": 0.005}
    truth = _declared(gen, pd)
    assert loop_controller(truth) == PDLoop(kp=8.0, kd=0.4, tau_max=2.0, velocity_tc=0.005)
    err = closed_loop_errors(truth, gen.log, kind="flexible")
    assert err["position_pct"] < 0.3 and err["torque_pct"] < 0.5
    for wrong in (("plant", "K", 1.3), ("friction", "Fc", 1.3)):
        bad = closed_loop_errors(_declared(gen, pd, wrong), gen.log, kind="flexible")
        assert bad["position_pct"] > 10 * err["position_pct"], wrong
    # the same loop on the link angle is another controller: it does not reproduce the log
    on_q1 = closed_loop_errors(_declared(gen, {**pd, "on": "q1"}), gen.log, kind="flexible")
    assert on_q1["position_pct"] > 10 * err["position_pct"]
    # closed-loop output error through the declared PD: K from 15% off back to the truth
    # (measured: 8 steps, K within 2e-5)
    from jaxflex.validate import closed_loop_fit

    res = closed_loop_fit(_declared(gen, pd, ("plant", "K", 1.15)), gen.log, ["K"],
                          kind="flexible", max_steps=30)
    assert res.converged
    assert res.params.plant["K"][0] == pytest.approx(truth.plant["K"][0], rel=1e-3)


def test_loop_controller_sections_name_their_problem():
    from jaxflex.validate import PDLoop, loop_controller

    def declared(section):
        return loop_controller(Params.from_dict({**_rotor_params().to_dict(),
                                                 "loop_controller": section}))

    assert declared({"type": "pd", "kp": 1.0, "kd": 0.1}) == PDLoop(kp=1.0, kd=0.1)
    for section in ({"type": "pd", "kp": 1.0, "kd": 0.1, "on": "q1", "tau_max": 2.0},
                    {"type": "cascade", "tau_max": 2.0, "gains": {"Ke": 1e-3, "KD1": 0.5,
                     "KD2": 0.5, "kv": 2.0, "L1": 15.0, "L2": 6.0}, "q2d_method": "filtered"}):
        ctrl = declared(section)
        assert declared(ctrl.to_dict()) == ctrl
    with pytest.raises(ParamsError, match="unknown loop 'pid'.*'pp_cascade', 'pd', 'cascade'"):
        declared({"type": "pid", "kp": 1.0})
    with pytest.raises(ParamsError, match="unknown key 'kdd'"):
        declared({"type": "pd", "kp": 1.0, "kdd": 0.1})
    with pytest.raises(ParamsError, match="kp is missing"):
        declared({"type": "pd", "kd": 0.1})
    with pytest.raises(ParamsError, match=r"kd: expected a number > 0, got -0.1"):
        declared({"type": "pd", "kp": 1.0, "kd": -0.1})
    with pytest.raises(ParamsError, match=r"velocity_tc: expected a number >= 0"):
        declared({"type": "pd", "kp": 1.0, "kd": 0.1, "velocity_tc": -1e-3})
    with pytest.raises(ParamsError, match="on: expected \"q1\" or \"q2\""):
        declared({"type": "pd", "kp": 1.0, "kd": 0.1, "on": "q3"})
    with pytest.raises(ParamsError, match="gains: unknown key 'KD3'"):
        declared({"type": "cascade", "gains": {"KD3": 1.0}})
    with pytest.raises(ParamsError, match="q2d_method"):
        declared({"type": "cascade", "q2d_method": "guess"})


def test_sampled_reference_gives_the_derivatives_the_cascade_needs():
    """The logged q1d of a 1 kHz multisine, interpolated: derivatives 0-4 at a sample instant
    and between samples match the analytic ones (measured relative errors <= 3e-7 up to the
    3rd, <= 3e-5 for the 4th)."""
    import jax.numpy as jnp

    from jaxflex.core.trajectory import Multisine, SampledReference

    tr = Multisine.schroeder(rms=0.15, f_min=0.1, f_max=2.0, count=6)
    dt = 1e-3
    ref = SampledReference(samples=jax.vmap(tr.position)(jnp.arange(3000) * dt), dt=dt)
    ts = jnp.asarray([0.0, 0.0123, 1.5005, 2.9])
    exact, interp = np.asarray(tr.sample(ts, 4)), np.asarray(ref.sample(ts, 4))  # (4, 5, 1)
    rel = np.abs(exact - interp).max(axis=(0, 2)) / np.abs(exact).max(axis=(0, 2))
    assert np.all(rel[:4] < 1e-5) and rel[4] < 1e-3, rel


@pytest.mark.slow
def test_declared_cascade_reproduces_a_cascade_log_and_wrong_parameters_do_not():
    """A log of jaxflex's cascade (``generate_log(loop="cascade")``: IDENT_GAINS, the paper's
    parameters as the controller's nominal model, 2 N m) simulated back through the declared
    cascade with the truth. Exact sensing (no noise, 2^30 counts): measured position error
    0.001%, torque 0.05%; K 30% off: 12% position, Fc 30% off: 3.0%. With the generator's
    default 16-bit noisy encoders: 0.5% position (torque 21%: the logged torque holds the
    loop's response to encoder noise, which the simulation does not have)."""
    from jaxflex.identify.datagen import IDENT_GAINS, generate_log
    from jaxflex.io.presets import paper_params
    from jaxflex.validate import CascadeLoop, closed_loop_errors, loop_controller

    nominal = paper_params()
    section = {"type": "cascade", "gains": IDENT_GAINS.to_dict(), "tau_max": 2.0,
               "model": {"plant": nominal.plant, "friction": nominal.friction}}
    gen = generate_log(seed=1, t_final=2.0, loop="cascade", noise_counts=0.0, bits=30)
    truth = _declared(gen, section)
    assert isinstance(loop_controller(truth), CascadeLoop)
    err = closed_loop_errors(truth, gen.log, kind="flexible")
    assert err["position_pct"] < 0.01 and err["torque_pct"] < 0.3
    for wrong in (("plant", "K", 1.3), ("friction", "Fc", 1.3)):
        bad = closed_loop_errors(_declared(gen, section, wrong), gen.log, kind="flexible")
        assert bad["position_pct"] > 100 * err["position_pct"], wrong
    noisy = generate_log(seed=1, t_final=2.0, loop="cascade")
    assert closed_loop_errors(_declared(noisy, section), noisy.log,
                              kind="flexible")["position_pct"] < 1.0


def test_rigid_torque_fit_recovers_a_rigid_axis_and_names_bad_input():
    """The rigid baseline's regression: a torque that obeys tau = Jt q'' + Fv q' +
    Fc sign(q') + offset exactly for a smooth motion gives back its four coefficients, and
    ``rigid_torque`` its torque; a missing joint is refused by name."""
    dt = 2e-3
    t = np.arange(3000) * dt
    q = 0.4 * np.sin(1.3 * t) + 0.1 * np.sin(4.1 * t)
    v = 0.52 * np.cos(1.3 * t) + 0.41 * np.cos(4.1 * t)
    a = -0.676 * np.sin(1.3 * t) - 1.681 * np.sin(4.1 * t)
    true = {"Jt": 2.0e3, "Fv": 8.0e2, "Fc": 3.0e2, "offset": -50.0}
    tau = true["Jt"] * a + true["Fv"] * v + true["Fc"] * np.sign(v) + true["offset"]
    log = Log.from_arrays(t=t, tau=tau, q1=q, q2=q)
    got = rigid_torque_fit(log)
    for k, x in true.items():
        assert got[k] == pytest.approx(x, rel=2e-3, abs=0.5), (k, got)
    assert rel_error_pct(tau, rigid_torque(got, log)) < 1.0
    with pytest.raises(ValueError, match="joint 1"):
        rigid_torque_fit(log, joint=1)


def test_shipped_data_sets_get_distinct_names_in_validate():
    """`jaxflex validate jaxflex:kuka/B/2 jaxflex:kuka/C/2`: the two logs' figures take the
    data sets' names with their folders, not a shared stem "2"."""
    from jaxflex.app.cli.validate import log_name, output_files

    assert log_name("jaxflex:kuka/B/2") == "kuka_B_2"
    assert log_name("runs/run.csv") == "run"
    files = output_files(["jaxflex:kuka/B/2", "jaxflex:kuka/C/2"], against=False)
    assert "kuka_B_2_params.png" in files and "kuka_C_2_params.png" in files

"""Optional physical effects that augment a plant without forking it (STYLE: 'a plant is composed').

An effect says where it acts by overriding one or more hooks; the defaults do nothing:

- ``link_torque(x)``   torque added to the right-hand side of the link equation [N m]
- ``rotor_torque(x)``  torque added to the right-hand side of the rotor equation [N m]
- ``spring_torque(d, dd)`` extra elastic torque added to K (q2 - q1) (acts on both sides) [N m]
- ``applied_torque(tau, aux)`` maps the commanded motor torque to the applied one [N m]
- ``aux_init(n)``, ``aux_rhs(aux, tau, x)``  internal states (e.g. an actuator lag), if any
- ``link_measured(q1, dq1)`` the link encoder's reading of the link motion [rad] (a sensor
  map on the replayed link output, e.g. the ``encoder_skew``; identity by default), and
  ``link_reading(q1, dq1, ddq1)`` its inverse on a measured link motion used as an input

Plant equations with effects (docs/spec.md section 1 plus effects):

    M q1'' + C q1' + G + F = T_s + sum link_torque
    J q2''                 = tau_a - T_s + sum rotor_torque
    T_s = K (q2 - q1) + sum spring_torque,  tau_a = applied_torque(tau)

Fitting metadata: each concrete effect lists in ``constraints`` how the discrepancy workflow
reparametrises each parameter ("positive": exp, "positive>=m": m + exp (keeps a fixed-step
integrator stable), "free": identity, "fixed": not fitted, e.g. a smoothing width or a
structural frequency, "tied:K": copied from the plant's K), and ``typical(n)`` gives a small instance to start a
fit from. ``Params.to_plant`` rebuilds an effect as ``EFFECTS[name](**params)``.

Modules: ``base`` (``AbstractEffect`` and the registry), ``library`` (the named effects),
``compose`` (the hooks summed over a plant's effects, ``Gated``).

Concrete effects register themselves by their docs/spec.md section 8 name in ``EFFECTS``; the
discrepancy workflow looks them up there. Every effect's parameters are array leaves so that
``grad`` reaches them.
"""


from jaxflex.effects.base import (
    AbstractEffect,
    EFFECTS,
    candidate_effects,
    register_effect,
)
from jaxflex.effects.library import (
    ActuatorLag,
    AsymmetricFriction,
    Backlash,
    Cogging,
    EncoderScale,
    EncoderSkew,
    Gravity,
    HardeningSpring,
    JointDamping,
    MotorCogging,
    MotorFriction,
    TimeDelay,
    TorqueOffset,
)
from jaxflex.effects.compose import (
    Gated,
    REPLAY_HOOKS,
    acts_on_replay,
    applied_torque,
    effect_torque,
    link_input,
    link_measurement,
    state_in_use,
    unwrap,
)

__all__ = [
    "AbstractEffect",
    "ActuatorLag",
    "AsymmetricFriction",
    "Backlash",
    "Cogging",
    "EFFECTS",
    "EncoderScale",
    "EncoderSkew",
    "Gated",
    "Gravity",
    "HardeningSpring",
    "JointDamping",
    "MotorCogging",
    "MotorFriction",
    "REPLAY_HOOKS",
    "TimeDelay",
    "TorqueOffset",
    "acts_on_replay",
    "applied_torque",
    "candidate_effects",
    "effect_torque",
    "link_input",
    "link_measurement",
    "register_effect",
    "state_in_use",
    "unwrap",
]

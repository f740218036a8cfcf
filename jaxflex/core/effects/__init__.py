"""Optional physical effects that augment a plant without forking it (STYLE: 'a plant is composed').

An effect says where it acts by overriding one or more hooks; the defaults do nothing:

- ``link_torque(x)``   torque added to the right-hand side of the link equation [N m]
- ``rotor_torque(x)``  torque added to the right-hand side of the rotor equation [N m]
- ``spring_torque(d, dd)`` extra elastic torque added to K (q2 - q1) (acts on both sides) [N m]
- ``spring_state_torque(aux, d, dd)`` the same from the effect's internal state (a hysteresis)
- ``applied_torque(tau, aux)`` maps the commanded motor torque to the applied one [N m]
- ``aux_init(n)``, ``aux_rhs(aux, tau, x)``  internal states (e.g. an actuator lag), if any
- ``link_measured(q1, dq1)`` the link encoder's reading of the link motion [rad] (a sensor
  map on the replayed link output, e.g. the ``encoder_skew``; identity by default), and
  ``link_reading(q1, dq1, ddq1)`` its inverse on a measured link motion used as an input

Plant equations with effects (docs/spec.md section 1 plus effects):

    M q1'' + C q1' + G + F = T_s + sum link_torque
    J q2''                 = tau_a - T_s + sum rotor_torque
    T_s = K (q2 - q1) + sum spring_torque + sum spring_state_torque,  tau_a = applied_torque(tau)

Fitting metadata: each concrete effect lists in ``constraints`` how the discrepancy workflow
reparametrises each parameter ("positive": exp, "positive>=m": m + exp (keeps a fixed-step
integrator stable), "free": identity, "fixed": not fitted, e.g. a smoothing width or a
structural frequency, "tied:K": copied from the plant's K), and ``typical(n)`` gives a small instance to start a
fit from. ``Params.to_plant`` rebuilds an effect as ``EFFECTS[name](**params)``.

Discovery and synthetic-log metadata live on the class too, so that a new effect needs only
its class: ``telling`` (the quantity its residual signature shows against), ``step_bounded``
(time constants bounded by a replay's step), ``cannot_act_on`` (declared axes it cannot act
on), ``start_from_residual`` (discovery's first guess), and ``moderate`` / ``signed`` /
``draw`` / ``recording`` (how ``jaxflex.identify.datagen`` hides it in a synthetic log).

Families: an effect may be order k of a family (``family``, ``order``, ``higher``): a harmonic
series of a ripple, a rotor friction with a Stribeck term, a friction level that differs by
direction in its Coulomb and then its static part, a spring polynomial of odd powers, a lag
of order two. Order k + 1 is
its own registered class whose ``from_lower`` starts it from a fitted order k; discovery keeps
a higher order only when it pays (``family_orders``).

Modules: ``base`` (``AbstractEffect``, ``ResidualStart`` and the registry), ``library`` (the
paper's named effects), ``ripple`` (cogging on either side and its harmonic orders),
``orders`` (the higher orders of the friction, spring and lag families), ``extra`` (effects
of real joints beyond the paper's model, opt-in discovery candidates), ``compose`` (the hooks
summed over a plant's effects, ``Gated``).

Concrete effects register themselves by their docs/spec.md section 8 name in ``EFFECTS``; the
discrepancy workflow looks them up there (importing this package registers those of
``library``, ``ripple``, ``orders`` and ``extra``). Every effect's parameters are array leaves
so that ``grad`` reaches them.
"""


from jaxflex.core.effects.base import (
    AbstractEffect,
    EFFECTS,
    ResidualStart,
    STEP_FLOOR,
    candidate_effects,
    family_orders,
    register_effect,
)
from jaxflex.core.effects.library import (
    ActuatorLag,
    AsymmetricFriction,
    Backlash,
    EncoderScale,
    EncoderSkew,
    Gravity,
    HardeningSpring,
    JointDamping,
    MotorFriction,
    TimeDelay,
    TorqueOffset,
)
from jaxflex.core.effects.extra import (
    ActuatorDeadZone,
    LoadFriction,
    SpringHysteresis,
)
from jaxflex.core.effects.ripple import (
    AbstractRipple,
    Cogging,
    Cogging2,
    Cogging3,
    MotorCogging,
    MotorCogging2,
    MotorCogging3,
)
from jaxflex.core.effects.orders import (
    ActuatorLag2,
    AsymmetricFriction2,
    HardeningSpring2,
    MotorFriction2,
)
from jaxflex.core.effects.compose import (
    Gated,
    REPLAY_HOOKS,
    acts_on_replay,
    applied_torque,
    effect_torque,
    link_input,
    link_measurement,
    spring_state_torque,
    state_in_use,
    unwrap,
    uses_hook,
)

__all__ = [
    "AbstractEffect",
    "AbstractRipple",
    "ActuatorDeadZone",
    "ActuatorLag",
    "ActuatorLag2",
    "AsymmetricFriction",
    "AsymmetricFriction2",
    "Backlash",
    "Cogging",
    "Cogging2",
    "Cogging3",
    "EFFECTS",
    "EncoderScale",
    "EncoderSkew",
    "Gated",
    "Gravity",
    "HardeningSpring",
    "HardeningSpring2",
    "JointDamping",
    "LoadFriction",
    "MotorCogging",
    "MotorCogging2",
    "MotorCogging3",
    "MotorFriction",
    "MotorFriction2",
    "REPLAY_HOOKS",
    "ResidualStart",
    "SpringHysteresis",
    "STEP_FLOOR",
    "TimeDelay",
    "TorqueOffset",
    "acts_on_replay",
    "applied_torque",
    "candidate_effects",
    "effect_torque",
    "family_orders",
    "link_input",
    "link_measurement",
    "register_effect",
    "spring_state_torque",
    "state_in_use",
    "unwrap",
    "uses_hook",
]

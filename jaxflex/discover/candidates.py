"""The candidates' shared ground: a ``Model`` (nominal parameters plus named effects), the
``Workspace`` whose plant holds every candidate effect behind a gate (so every candidate shares
one compiled program), the run's workspaces by the effects they hold (``Workspaces``: a
family's next order only once its order below is in a model), the log's segments and their
first start states (``bristle_entries``), and a ``CandidateFit``, the outcome of fitting one
model.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.core.effects import STEP_FLOOR, AbstractEffect, EFFECTS, Gated
from jaxflex.fit import ParamSpace, Problem, is_fitted, make_segments, on_slot_rows
from jaxflex.fit.inverse import Motion, measured_motion, model_residuals
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.validation import to_device


#: Nominal parameters refitted with every model.
NOMINAL_FIT: tuple[str, ...] = ("I", "J", "K", "Fc", "Fs", "sigma2")


def fitted_names(name: str) -> tuple[str, ...]:
    """The parameters the fit adjusts for effect ``name``, as ``"<effect>.<param>"``."""
    return tuple(f"{name}.{k}" for k, c in EFFECTS[name].constraints.items() if is_fitted(c))


def fitted_count(name: str) -> int:
    """Number of parameters the fit adjusts for effect ``name``."""
    return len(fitted_names(name))


# --------------------------------------------------------------------------- the model


@dataclasses.dataclass
class Model:
    """A one-joint model to fit: nominal ``Params`` plus the active effects (instances, in the
    order added); ``starts`` gives start instances for inactive candidates (e.g. cogging with
    its frequency from the residual spectrum)."""

    params: Params
    effects: list[AbstractEffect]
    starts: dict[str, AbstractEffect] = dataclasses.field(default_factory=dict)

    @property
    def active(self) -> dict[str, AbstractEffect]:
        """Active effects by name."""
        return {e.name: e for e in self.effects}

    def plant(self) -> FlexibleJointPlant:
        """The plant with the active effects only (what params.json describes)."""
        return self.params.to_plant(with_effects=False).with_effects(*self.effects)


@functools.lru_cache(maxsize=2)
def _gate(on: bool) -> jax.Array:
    """A gate (``Gated``) as one strongly typed array per value, made once: a weakly typed
    one is converted at every compiled call that receives it, most of a solver step's host
    time."""
    return to_device(1.0 if on else 0.0)


class Workspace(eqx.Module):
    """The compiled shape of one universe of effects (``universe``, registered names): the
    gated universal parameter space (every effect of the universe present, gated), the
    training and held-out problems."""

    space: ParamSpace
    train: Problem
    test: Problem
    universe: tuple[str, ...] = eqx.field(static=True)

    @property
    def step(self) -> float:
        """The replay's integration step [s]: the sample period over the substeps."""
        return self.train.dt / self.train.substeps

    def for_model(self, model: Model) -> tuple[Problem, Problem, dict[str, jax.Array]]:
        """Training and held-out problems of ``model`` (gates and mask set) and its start
        coordinates.

        **Raises:** ``ValueError`` for a model with an effect outside the universe or with
        more fitted parameters than the Jacobian's columns."""
        act = model.active
        if missing := sorted(set(act) - set(self.universe)):
            raise ValueError(f"discover: the model's effects {missing} are not in the "
                             f"workspace's universe {list(self.universe)}")
        effs = []
        for name in self.universe:
            e = act.get(name) or model.starts.get(name) or typical_effect(name, self.step)
            effs.append(Gated(e, _gate(name in act)))
        base = model.params.to_plant(with_effects=False).with_effects(*effs)
        space = eqx.tree_at(lambda s: s.base, self.space, base)
        theta0 = space.theta0()
        fitted = NOMINAL_FIT + tuple(k for name in act for k in fitted_names(name))
        if len(fitted) > self.train.jac_columns:
            raise ValueError(f"discover: {len(fitted)} fitted parameters exceed the "
                             f"{self.train.jac_columns} the workspace was built for")
        space = space.with_mask(fitted, theta0)
        train = eqx.tree_at(lambda p: p.space, self.train, space)
        test = eqx.tree_at(lambda p: p.space, self.test, space)
        return train, test, theta0

    def theta_of(self, fit: CandidateFit) -> dict[str, jax.Array]:
        """``fit``'s engine coordinates in this workspace: as they are when the fit was made
        in a workspace of the same universe; from another of the run's workspaces
        (``Workspaces``), its entries kept and those of the effects only this universe holds
        (gated off in the fit's model, so the replay does not read them) at their starts."""
        if set(fit.theta) == set(self.space.names):
            return fit.theta
        _, _, theta0 = self.for_model(fit.model)
        return {k: fit.theta.get(k, v) for k, v in theta0.items()}


def replayed_outputs(log: Log) -> tuple[str, ...]:
    """The angles a replay of ``log`` is compared with: ("q1", "q2"), or ("q1",) where the
    two columns are one encoder's samples (q2 = q1: a rigid axis read once). Compared twice,
    one measurement would count every sample twice in the evidence (the effective count,
    every F-test, information criterion and tie) and a floor drawn with two independent
    noises would not be the log's."""
    q1, q2 = np.asarray(log.q1), np.asarray(log.q2)
    return ("q1",) if q2.shape == q1.shape and np.array_equal(q1, q2) else ("q1", "q2")


def workspace(log: Log, nominal: Params, universe: Sequence[str], *, segment: float,
              train_frac: float, substeps: int, max_effects: int) -> Workspace:
    """Cut ``log`` into training and held-out segments [s] and build the gated universal
    space (Jacobians over the most entries a model with ``max_effects`` effects fits: the
    last round fits the ``max_effects`` - 1 added and one candidate).
    The space bounds the Stribeck excess Fs - Fc by the largest logged torque |tau| [N m]
    (``ParamSpace.friction_cap``): a static friction the actuator could never have broken is
    not physical (identify marks one as unidentified), and a nominal refit that misses an
    effect could otherwise turn the bristles into a spring to ground (Fs far above any
    logged torque with Fc at zero), after which every candidate of the next round seems to
    gain."""
    dt = log.dt
    L = int(round(segment / dt))
    N = log.N
    split = int(train_frac * N)
    for a, b, what in ((0, split, "training"), (split, N, "held-out")):
        if (b - a) // max(L, 1) < 2:
            raise ValueError(
                f"log too short: the {what} part ({b - a} samples) needs at least 2 segments of "
                f"{L} samples ({segment} s); use a longer log or a shorter --segment"
            )
    universe = tuple(sorted(universe))
    # the most entries a model fits: the nominal ones and the largest max_effects effects
    # (``discover`` adds at most max_effects; a tie's rivals are swapped in, not added), each
    # family at the largest order the universe holds (a family's orders are swapped in, one
    # at a time)
    family: dict[str, int] = {}
    for n in universe:
        f = EFFECTS[n].family_name()
        family[f] = max(family.get(f, 0), fitted_count(n))
    sizes = sorted(family.values(), reverse=True)
    jac_columns = len(NOMINAL_FIT) + sum(sizes[:max_effects])
    h = dt / substeps
    effs = [Gated(typical_effect(n, h), to_device(0.0)) for n in universe]
    base = nominal.to_plant(with_effects=False).with_effects(*effs)
    space = ParamSpace.build(base, NOMINAL_FIT + tuple(k for n in universe for k in fitted_names(n)))
    for k in (f"{n}.{p}" for n in universe for p in EFFECTS[n].step_bounded):
        if k in space.names:  # time constants the replay's step keeps stable (STEP_FLOOR)
            space = space.with_lower_bound(k, STEP_FLOOR * h)
    top = float(np.max(np.abs(np.asarray(log.tau))))
    if not (math.isfinite(top) and top > 0):
        raise ValueError(f"discover: the log's torque column has largest |tau| = {top}: "
                         "nothing drives the motion the workflow replays")
    space = eqx.tree_at(lambda s: s.friction_cap, space, to_device(top))
    # start estimates (the solver's first guess of each segment's start state): angles and
    # Savitzky-Golay velocities from the log, the bristle load that balances the link's
    # inverse dynamics there (``bristle_entries``; the start z is bounded, Problem.bounded_z)
    plant = nominal.to_plant(with_effects=False)
    outputs = replayed_outputs(log)
    kw = dict(kind="flexible", outputs=outputs, length=L)

    def segments(a, b):
        segs = make_segments(log, start=a, stop=b, **kw)
        u = bristle_entries(log, plant, a + L * np.arange(segs.count))
        x0 = np.array(segs.x0)  # on the host: op by op, each update would compile anew
        x0[:, 4, 0] = u
        return eqx.tree_at(lambda s: s.x0, segs, to_device(x0))

    train_segs, test_segs = segments(0, split), segments(split, N)

    def problem(segs, columns):
        m = np.asarray(segs.y_meas)[..., :1]
        scale = float(np.sqrt(np.mean((m - m[:, :1]) ** 2)))
        # free starts without continuity (w_def 0): every segment's start state is fitted
        # from the segment's own samples, so no estimate error is left for the parameters to
        # absorb; the start z is fitted within the friction's capacity (bounded_z): a
        # segment that starts in stick carries a bristle load between the steady states
        return Problem(space=space, segs=segs, w_y=to_device(1.0 / scale),
                       w_def=to_device(np.zeros(5)), dt=dt, kind="flexible", substeps=substeps,
                       outputs=outputs, free_starts=True, bounded_z=True,
                       jac_columns=columns, rolled_stages=True)

    # no parameter is fitted on the held-out segments (only their starts): no theta tangents
    return Workspace(space=space, train=problem(train_segs, jac_columns),
                     test=problem(test_segs, 0),
                     universe=universe)


class Workspaces:
    """The workspaces of one discovery run, each built when first asked for (``holding``):
    the candidates' own, and, once a family's order k is in a model, one that also holds its
    order k + 1 (``jaxflex.discover.orders.grow``). Every gated effect of a universe is
    traced into each of its programs and the largest fitted families set its Jacobian's
    width (``workspace``'s ``jac_columns``), so an order that a run never reaches costs it
    nothing. A model is fitted in any workspace that holds its effects: an effect gated off
    adds nothing to a replay.

    **Arguments:**

    - `log`, `nominal`: as ``workspace``.
    - `candidates`: the registered names every workspace holds (the run's candidates).
    - `prepare`: called with each workspace once it is built (the run's compilation ahead:
      ``jaxflex.discover.fitting.trace_fit``, ``made_ahead``), or None.
    - `build`: ``workspace``'s keyword arguments (``segment``, ``train_frac``, ``substeps``,
      ``max_effects``)."""

    def __init__(self, log: Log, nominal: Params, candidates: Iterable[str], *,
                 prepare: Callable[[Workspace], None] | None = None, **build: float) -> None:
        self.log, self.nominal, self.prepare, self.build = log, nominal, prepare, build
        self.candidates = frozenset(candidates)
        self.built: list[Workspace] = []

    def holding(self, names: Iterable[str] = ()) -> Workspace:
        """The workspace that holds the candidates and the registered effects ``names``: the
        smallest built one that does, else a new one of exactly those (``workspace``).

        **Raises:** ``ValueError`` as ``workspace`` (a log too short for its segments)."""
        need = self.candidates | set(names)
        have = [ws for ws in self.built if need <= set(ws.universe)]
        if have:
            return min(have, key=lambda ws: len(ws.universe))
        ws = workspace(self.log, self.nominal, sorted(need), **self.build)  # type: ignore[arg-type]
        self.built.append(ws)
        if self.prepare is not None:
            self.prepare(ws)
        return ws


@persistent_jit(fast_compile=True)
def _bristle_residuals(plant: FlexibleJointPlant, *cols: jax.Array
                       ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(capacity g(q1') / sigma0 [rad], link residual at z = 0, at z = capacity [N m]), each
    (N, 1), at the samples ``cols`` (a ``Motion``'s columns) of ``bristle_entries`` (the
    residual is affine in z: F = sigma0 z + sigma1 z' + sigma2 q1'), in one compiled
    program."""
    motion = Motion(*cols)
    fr = plant.lugre
    cap = fr.g(motion.v1) / fr.sigma0[0]
    r_link = lambda z: model_residuals(plant, "flexible", motion, z)[0]
    return cap, r_link(jnp.zeros_like(cap)), r_link(cap)


def bristle_entries(log: Log, plant: FlexibleJointPlant, idx: np.ndarray,
                    window: int = 31, bound: float = 0.995) -> np.ndarray:
    """First guesses of the bounded start z [rad] (``Problem.bounded_z``) at samples ``idx``
    of a one-joint log: the bristle deflection at which the link's inverse dynamics
    (``FlexibleJointPlant.torque_residuals``, angles and their derivatives by Savitzky-Golay
    over ``window`` samples) leave no residual, within +-``bound`` x the friction's capacity
    g(q1') / sigma0. While
    sliding this is (near) the steady state; in stick, or just after a reversal, the load
    lies between +-capacity and has either sign, where the steady state of the velocity
    (only 0 or +-capacity at rest) puts the start in another basin of the fit (a segment
    that starts just after a reversal is then fitted to the opposite load, and replays
    several times worse than the noise)."""
    cols = [c[idx] for c in measured_motion(log.joint(0), window, smooth=True).columns()]
    # in the segment count's bucket: one program per bucket
    cap, r0, r1 = (a[:, 0] for a in on_slot_rows(
        functools.partial(_bristle_residuals, plant), *cols))
    frac = -r0 / np.where(r1 != r0, r1 - r0, 1.0)
    return cap * np.clip(frac, -bound, bound)


@dataclasses.dataclass
class CandidateFit:
    """One fitted model: the model, engine coordinates ``theta``, the fitted start states of
    the training segments ``starts`` and of the held-out segments ``test_starts`` (S,
    n_state, 1) (q1 [rad], q1' [rad/s], q2 [rad], q2' [rad/s], z [rad]), fitted physical
    ``values`` and their standard errors (name -> float), training residual sum of squares
    ``rss`` (residuals in units of the segments' RMS motion), their count ``n_res``, fitted
    parameter count ``n_par`` (start states included), training and held-out gaps, solver
    steps, whether the solver met its tolerance, and wall time [s]."""

    model: Model
    theta: dict[str, jax.Array]
    starts: jax.Array
    test_starts: jax.Array
    values: dict[str, float]
    stderr: dict[str, float]
    rss: float
    n_res: int
    n_par: int
    gap_train: float
    gap_test: float
    steps: int
    converged: bool
    seconds: float

    @property
    def y_train(self) -> tuple[dict[str, jax.Array], jax.Array]:
        """The training problem's unknowns (theta, starts)."""
        return self.theta, self.starts

    @property
    def y_test(self) -> tuple[dict[str, jax.Array], jax.Array]:
        """The held-out problem's unknowns (theta, held-out starts)."""
        return self.theta, self.test_starts


def within_capacity(x0s: jax.Array, plant: FlexibleJointPlant,
                    bound: float = 0.995) -> jax.Array:
    """Start states (S, n_state, 1) with their bounded z entries [rad] (``Problem.bounded_z``)
    brought back within ``bound`` x the friction's capacity g(q1') / sigma0 of ``plant``. An
    entry a long solver step pushed past the capacity stops moving there (the clip has no
    slope); from just inside, a further solve can bring it back when the data want a partial
    load (a second solve from the entries brought back reaches the fit the true parameters
    give). Compiled (one program per bucket of segment counts, ``on_slot_rows``, kept
    by ``jaxflex.runtime.tracecache``): run op by op it cost a dozen small compilations per shape on
    every run."""
    return to_device(on_slot_rows(lambda x: _within_capacity(x, plant, bound), x0s))


@persistent_jit(fast_compile=True)
def _within_capacity(x0s: jax.Array, plant: FlexibleJointPlant, bound: float) -> jax.Array:
    fr = plant.lugre
    cap = bound * fr.g(x0s[:, 1]) / fr.sigma0
    return x0s.at[:, 4].set(jnp.clip(x0s[:, 4], -cap, cap))


def typical_effect(name: str, h: float) -> AbstractEffect:
    """``EFFECTS[name].typical_at_step(1, h)``: the effect's typical one-joint start with its
    step-bounded time constants at twice their bound at the integration step ``h`` [s]."""
    return EFFECTS[name].typical_at_step(1, h)

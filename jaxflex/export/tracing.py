"""Trace the controller once: the programs every back end translates.

``trace`` runs ``jax.make_jaxpr`` on the functions of a ``SampledController`` for fixed
shapes (n joints): ``init`` (filters, Kalman filter and observer state at the first
sample), ``step`` (one sample: velocity source, observer, q2d derivatives, cascade law,
saturation), their variants with the reference given (``init_ref``, ``step_ref``) and the
recorded reference (``reference``, ``reference_derivatives``). Every array leaf of the
controller (model, LuGre, gains, reference, filter constants, Kalman gains, torque limit) is
a jaxpr *input*. ``translate_program`` translates one program in a dialect:
``jaxflex.export.pygen`` writes the Python module from them, where the leaves stay
parameters, ``jaxflex.export.cgen`` the C source, where they are folded.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.core.controller import CascadeController
from jaxflex.export.atoms import Program, Sym, eliminate_dead, sym_array
from jaxflex.export.dialect import PYTHON, Dialect
from jaxflex.export.program import REFERENCE_ROWS, SampledController, sampled_controller
from jaxflex.export.translate import Translator
from jaxflex.sim.simulate import REFERENCE_ORDER

# docs/spec.md section 7 entries -> controller leaf names (the model the rig's plant defaults to)
SPEC_ENTRIES: dict[str, str] = {
    "plant.I": "model.links.I", "plant.J": "model.J", "plant.K": "model.K",
    **{f"friction.{k}": f"model.friction.{k}" for k in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")},
    **{f"gains.{k}": f"gains.{k}" for k in ("Ke", "KD1", "KD2", "kv", "L1", "L2")},
}


@dataclass
class _Leaves:
    names: list[str]
    values: list[np.ndarray]
    rebuild: Callable[[list[Any]], Any]


def _leaves(controller: Any) -> _Leaves:
    dyn, static = eqx.partition(controller, eqx.is_array)
    flat, treedef = jax.tree_util.tree_flatten_with_path(dyn)
    names = [jax.tree_util.keystr(path).lstrip(".") for path, _ in flat]
    values = [np.asarray(v, dtype=np.float64) for _, v in flat]

    def rebuild(leaves):
        return eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)

    return _Leaves(names, values, rebuild)


@dataclass
class Traced:
    """The traced programs of one ``SampledController`` (shared by every back end).

    ``jaxprs``: name -> (ClosedJaxpr, signal inputs as (name, shape) pairs), for ``init``
    (t, q1, q2), ``step`` (state, t, q1, q2), ``init_ref`` and ``step_ref`` (the same with
    the reference R given), ``reference`` (t -> q1d) and ``reference_derivatives``
    (t -> R); the controller's array leaves (``names``, ``values``) come first in each.
    """

    sc: SampledController
    names: list[str]
    values: list[np.ndarray]
    state_names: list[str]
    state_sizes: list[int]
    jaxprs: dict[str, tuple[Any, list[tuple[str, tuple[int, ...]]]]]

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.sc.n

    @property
    def n_state(self) -> int:
        """Number of state values (every leaf's size)."""
        return sum(self.state_sizes)


def trace(controller: CascadeController | SampledController) -> Traced:
    """Trace the programs of a controller once, in float64, for every back end.

    **Arguments:**

    - ``controller``: a ``SampledController``, or a ``CascadeController`` (run with the
      dirty derivative and no DAC, ``jaxflex.export.sampled_controller``).

    **Returns:**

    The ``Traced`` programs.

    **Raises:**

    ``ExportError`` for a configuration the export cannot run.
    """
    with jax.enable_x64(True):
        return _trace(sampled_controller(controller))


def _trace(sc: SampledController) -> Traced:
    n = sc.n
    lv = _leaves(sc)
    f64 = jnp.float64
    leaves = [jnp.asarray(v, f64) for v in lv.values]
    zeros = jnp.zeros(n, f64)
    state0 = sc.init(0.0, zeros, zeros)
    flat, st_def = jax.tree_util.tree_flatten_with_path(state0)
    st_leaves = [x for _, x in flat]
    state_names = [jax.tree_util.keystr(path).lstrip(".") for path, _ in flat]
    k = len(leaves)

    def rebuild(args):
        return lv.rebuild(list(args[:k]))

    def state_of(args):
        return jax.tree_util.tree_unflatten(st_def, list(args[k:k + len(st_leaves)]))

    def step_fn(*args):
        t, q1, q2 = args[k + len(st_leaves):]
        new, out = rebuild(args).step(state_of(args), t, q1, q2)
        return jax.tree_util.tree_leaves(new), out.tau

    def step_ref_fn(*args):
        t, q1, q2, R = args[k + len(st_leaves):]
        new, out = rebuild(args).with_reference(R, t).step(state_of(args), t, q1, q2)
        return jax.tree_util.tree_leaves(new), out.tau

    def init_fn(*args):
        t, q1, q2 = args[k:]
        return jax.tree_util.tree_leaves(rebuild(args).init(t, q1, q2))

    def init_ref_fn(*args):
        t, q1, q2, R = args[k:]
        return jax.tree_util.tree_leaves(rebuild(args).with_reference(R, t).init(t, q1, q2))

    def ref_fn(*args):
        return rebuild(args).controller.trajectory.position(args[k])

    def ref_derivs_fn(*args):
        return rebuild(args).controller.trajectory.derivatives(args[k], order=REFERENCE_ORDER)

    S = [(f"s{i}", tuple(x.shape)) for i, x in enumerate(st_leaves)]
    tq = [("t", ()), ("q1", (n,)), ("q2", (n,))]
    r = [("r", (REFERENCE_ROWS, n))]
    specs = {
        "init": (init_fn, tq), "step": (step_fn, S + tq),
        "init_ref": (init_ref_fn, tq + r), "step_ref": (step_ref_fn, S + tq + r),
        "reference": (ref_fn, [("t", ())]), "reference_derivatives": (ref_derivs_fn, [("t", ())]),
    }
    jaxprs = {}
    for name, (fn, sig) in specs.items():
        examples = [*leaves, *[jnp.zeros(shape, f64) for _, shape in sig]]
        jaxprs[name] = (jax.make_jaxpr(fn)(*examples), sig)
    # the law's constants keep the names of the bare controller ("gains.L1"); the
    # estimator's and the DAC's are "estimator.L", "sensing.dac_range"
    names = [nm.removeprefix("controller.") for nm in lv.names]
    return Traced(sc, names, lv.values, state_names,
                  [int(np.size(x)) for x in st_leaves], jaxprs)


def _signal_syms(sig: list[tuple[str, tuple[int, ...]]]) -> list[np.ndarray]:
    out = []
    for name, shape in sig:
        if shape == ():
            out.append(np.array(Sym(name, False), dtype=object).reshape(()))
        else:
            out.append(sym_array(name, shape, False))
    return out


def _signal_args(sig: list[tuple[str, tuple[int, ...]]]) -> list[str]:
    return [name if shape == () else f"{name}_{i}"
            for name, shape in sig for i in range(int(np.prod(shape, dtype=int)))]


def translate_program(tr: Traced, name: str, param_inputs: list[np.ndarray],
                      dialect: Dialect = PYTHON) -> Program:
    """Translate one traced program of ``tr`` into ``dialect``.

    **Arguments:**

    - ``tr``: the traced programs (``trace``).
    - ``name``: which one ("init", "step", "init_ref", "step_ref", "reference",
      "reference_derivatives").
    - ``param_inputs``: the controller's leaves as atoms (``sym_array`` symbols to keep
      them parameters, ``const_array`` of their values to fold them into the code).
    - ``dialect``: the back end's spelling (``PYTHON`` or ``C99``).

    **Returns:**

    The ``Program`` (hoisted and per-sample statements, outputs).

    **Raises:**

    ``UnsupportedPrimitive`` naming a primitive the translator cannot handle.
    """
    closed, sig = tr.jaxprs[name]
    t = Translator(prefix="v", dialect=dialect)
    outs = t.run(closed.jaxpr, closed.consts, [*param_inputs, *_signal_syms(sig)])
    prog = Program(params=[], signals=_signal_args(sig),
                   outputs=[a for o in outs for a in np.asarray(o).reshape(-1)])
    prog.static_stmts, prog.dyn_stmts = t.static_stmts, t.dyn_stmts
    return prog


_PARAM = re.compile(r"\bp(\d+)_\d+\b")


def _used_params(progs: list[Program]) -> set[int]:
    """Indices of the controller leaves that any program's live code reads."""
    used: set[int] = set()
    for prog in progs:
        live = {a.name for a in prog.outputs if isinstance(a, Sym)}
        dyn = eliminate_dead(prog.dyn_stmts, live)
        live |= {u for st in dyn for u in st.uses}
        eliminate_dead(prog.static_stmts, live)
        used |= {int(m.group(1)) for name in live for m in [_PARAM.fullmatch(name)] if m}
    return used


def listed_leaves(tr: Traced, progs: list[Program] | None = None) -> list[int]:
    """Indices of the controller leaves an export lists as its constants: those its code
    reads, and the parameter file's entries (the rig's plant and friction default to them)
    even where the law does not read them.

    **Arguments:**

    - ``tr``: the traced programs.
    - ``progs``: their translations with the leaves as parameters (translated here if None).

    **Returns:**

    Sorted indices into ``tr.names``.
    """
    if progs is None:
        syms = [sym_array(f"p{i}", v.shape, True) for i, v in enumerate(tr.values)]
        progs = [translate_program(tr, name, syms) for name in tr.jaxprs]
    spec_leaves = {tr.names.index(v) for v in SPEC_ENTRIES.values() if v in tr.names}
    return sorted(_used_params(progs) | spec_leaves)

"""Trace the controller once and write the standalone Python module from its programs.

``trace`` runs ``jax.make_jaxpr`` on the functions of a ``SampledController`` for fixed
shapes (n joints): ``init`` (filters, Kalman filter and observer state at the first
sample), ``step`` (one sample: velocity source, observer, q2d derivatives, cascade law,
saturation), their variants with the reference given (``init_ref``, ``step_ref``) and the
recorded reference (``reference``, ``reference_derivatives``). Every array leaf of the
controller (model, LuGre, gains, reference, filter constants, Kalman gains, torque limit) is
a jaxpr *input*. ``generate_source`` translates the programs into Python, where the leaves
stay parameters (the module can be rebuilt with other values; the traced ones are its
defaults); ``jaxflex.export.cgen`` translates the same programs into C.
"""

from __future__ import annotations

import datetime
import math
import re
from dataclasses import dataclass
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.controller import CascadeController
from jaxflex.export.program import (
    REFERENCE_ROWS,
    SampledController,
    describe,
    sampled_controller,
)
from jaxflex.export.translate import (
    PYTHON,
    Dialect,
    Program,
    Sym,
    Translator,
    eliminate_dead,
    format_atom,
    sym_array,
)
from jaxflex.simulate import REFERENCE_ORDER

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


def _translate(fn: Callable, example_args: list[Any], arg_syms: list[np.ndarray],
               prefix: str) -> Program:
    """Trace ``fn`` (flat args) and translate its jaxpr, with ``arg_syms`` as its inputs."""
    closed = jax.make_jaxpr(fn)(*example_args)
    flat_syms = [a for a in arg_syms]
    if len(flat_syms) != len(closed.jaxpr.invars):
        raise RuntimeError("jaxflex.export: argument count mismatch while tracing")
    tr = Translator(prefix=prefix)
    outs = tr.run(closed.jaxpr, closed.consts, flat_syms)
    prog = Program(params=[], signals=[], outputs=[a for o in outs for a in o.reshape(-1)])
    prog.static_stmts, prog.dyn_stmts = tr.static_stmts, tr.dyn_stmts
    return prog


def _fn_source(prog: Program, fname: str, param_names: list[str], signal_sig: str,
               unpack: str, ret: str) -> str:
    """``_derive_<f>`` (hoisted constants) and ``_make_<f>`` (closure with the per-sample code)."""
    live: set[str] = {a.name for a in prog.outputs if isinstance(a, Sym)}
    dyn = eliminate_dead(prog.dyn_stmts, live)
    dyn_targets = {t for st in dyn for t in st.targets}
    closure = sorted(n for n in live if n not in dyn_targets and n[0] in "cp")
    live_static = set(closure)
    stat = eliminate_dead(prog.static_stmts, live_static)
    lines = [f"def _derive_{fname}({', '.join(param_names)}):"]
    lines += [f"    {', '.join(st.targets)} = {st.code}" for st in stat]
    lines.append(f"    return ({''.join(c + ', ' for c in closure)})")
    lines.append("")
    lines.append("")
    cl = ", ".join(closure)
    body = ([f"{unpack}"] if unpack else []) + _inline_single_use(dyn, ret)
    body.append(f"return {ret}")
    # fast path: Python floats and math (raises on 1/0, overflow, domain errors, even in a
    # branch that jnp.where discards); fallback: the same statements on numpy float64 scalars
    # with IEEE semantics, as XLA computes them
    lines.append(f"def _make_{fname}_ieee({cl}):")
    lines.append(f"    def _{fname}_ieee({signal_sig}):")
    lines += ["        " + b.replace("_m.", "_s.") for b in body]
    lines.append(f"    return _{fname}_ieee")
    lines.append("")
    lines.append("")
    lines.append(f"def _make_{fname}({cl}):")
    lines.append(f"    _slow = _make_{fname}_ieee(*[_np.float64(x) for x in ({cl}{',' if closure else ''})])")
    lines.append(f"    def _{fname}({signal_sig}):")
    lines.append("        try:")
    lines += ["            " + b for b in body]
    lines.append("        except (ArithmeticError, ValueError):")
    lines.append(f"            return _ieee(_slow, {signal_sig.replace('*', '')})")
    lines.append(f"    return _{fname}")
    return "\n".join(lines)


_NAME = re.compile(r"\bv\d+\b")


def _inline_single_use(dyn: list, ret: str, max_depth: int = 12) -> list[str]:
    """Statement lines with temporaries used exactly once substituted into their user
    (parenthesised, so the evaluation order and every rounding stay those of the separate
    statements; fewer stores and loads per sample). Nesting is capped at ``max_depth``."""
    counts: dict[str, int] = {}
    for st in dyn:
        for m in _NAME.findall(st.code):
            counts[m] = counts.get(m, 0) + 1
    for m in _NAME.findall(ret):
        counts[m] = counts.get(m, 0) + 2  # outputs stay named
    pending: dict[str, tuple[str, int]] = {}
    lines = []
    for st in dyn:
        depth = 0

        def sub(m):
            nonlocal depth
            name = m.group(0)
            if name in pending:
                code, d = pending.pop(name)
                depth = max(depth, d)
                return f"({code})"
            return name

        code = _NAME.sub(sub, st.code)
        if len(st.targets) == 1 and counts.get(st.targets[0], 0) == 1 and depth < max_depth:
            pending[st.targets[0]] = (code, depth + 1)
            continue
        lines.append(f"{', '.join(st.targets)} = {code}")
    if pending:  # pragma: no cover - every single-use name has a later user
        raise RuntimeError("jaxflex.export: unresolved inlined temporaries")
    return lines


def _literal(v: float) -> str:
    if math.isnan(v):
        return "_NAN"
    if math.isinf(v):
        return "_INF" if v > 0 else "-_INF"
    return repr(float(v))


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


_PY_FUNCS = ("step", "init", "reference", "step_ref", "init_ref", "reference_derivatives")


def generate_source(controller: CascadeController | SampledController, *,
                    description: str = "", traced: Traced | None = None) -> str:
    """Python source of a standalone module (numpy and the standard library only) that
    computes exactly what the controller's ``init`` / ``step`` compute.

    **Arguments:**

    - ``controller``: a ``SampledController`` (``jaxflex.export.rig_controller``), or a
      ``CascadeController`` (run with the dirty derivative, no DAC).
    - ``description``: the module docstring's first line.
    - ``traced``: the programs already traced by ``trace`` (else traced here).

    **Returns:**

    The module's source: ``class Controller`` with ``reset()``, ``step(t, q1, q2, ref=None)``
    and ``reference(t)``.

    **Raises:**

    ``UnsupportedPrimitive`` (a ``ValueError``) naming a primitive it cannot translate;
    ``ExportError`` for a configuration the export cannot run.
    """
    tr = trace(controller) if traced is None else traced
    with jax.enable_x64(True):
        return _generate(tr, description)


def _generate(tr: Traced, description: str) -> str:
    n = tr.n
    sc = tr.sc
    c = sc.controller
    param_syms = [sym_array(f"p{i}", v.shape, True) for i, v in enumerate(tr.values)]
    progs = {name: translate_program(tr, name, param_syms) for name in _PY_FUNCS}
    used = listed_leaves(tr, list(progs.values()))
    param_args = [f"p{i}_{k}" for i in used for k in range(tr.values[i].size)]
    tup = lambda xs: "(" + "".join(x + ", " for x in xs) + ")"
    one = lambda xs: xs[0] if n == 1 else tup(xs)
    q_args = [f"q1_{k}" for k in range(n)] + [f"q2_{k}" for k in range(n)]
    r_args = [f"r_{k}" for k in range(REFERENCE_ROWS * n)]
    state_args = [f"s{i}_{k}" for i, size in enumerate(tr.state_sizes) for k in range(size)]
    unpack = f"{tup(state_args)} = S"
    funcs = []
    for name in _PY_FUNCS:
        prog = progs[name]
        outs = [format_atom(a) for a in prog.outputs]
        if name in ("step", "step_ref"):
            ns = len(state_args)
            ret = f"{tup(outs[:ns])}, {one(outs[ns:])}"
            sig = ", ".join(["S", "t", *q_args, *(r_args if name == "step_ref" else [])])
            funcs.append(_fn_source(prog, name, param_args, sig, unpack, ret))
        elif name in ("init", "init_ref"):
            sig = ", ".join(["t", *q_args, *(r_args if name == "init_ref" else [])])
            funcs.append(_fn_source(prog, name, param_args, sig, "", tup(outs)))
        elif name == "reference":
            funcs.append(_fn_source(prog, name, param_args, "t", "", one(outs)))
        else:
            funcs.append(_fn_source(prog, name, param_args, "t", "", tup(outs)))
    defaults = ",\n".join(
        f"    {tr.names[i]!r}: ({tuple(tr.values[i].shape)!r}, "
        f"[{', '.join(_literal(x) for x in tr.values[i].reshape(-1))}])"
        for i in used
    )
    used_names = {tr.names[i] for i in used}
    spec_map = {k: v for k, v in SPEC_ENTRIES.items() if v in used_names}
    header = _HEADER.format(
        description=description or "Cascade controller with LuGre friction observer",
        date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        n=n, dt=repr(float(c.dt)), method=c.q2d_method, compensation=c.compensation,
        config=describe(sc), rows=REFERENCE_ROWS,
    )
    body = _BODY.format(
        n=n, dt=repr(float(c.dt)), method=c.q2d_method, velocity=sc.sensing.velocity,
        config=describe(sc), rows=REFERENCE_ROWS,
        defaults=defaults, spec_map=repr(spec_map), state_names=repr(tr.state_names),
        funcs="\n\n\n".join(funcs),
    )
    return header + body


_HEADER = '''"""{description} -- standalone export.

Generated by ``jaxflex export`` on {date} from the traced JAX definition
(``jaxflex.export.SampledController.init`` / ``.step``: the cascade law with its
configuration's velocity source); DO NOT EDIT: change the JAX controller and export again.
Imports only numpy and the Python standard library.

Joints: {n}; sample period dt = {dt} s; q2d_method = {method!r}; friction compensation: {compensation}.
Controller-side sensing: {config}.

    ctrl = Controller()                      # the exported parameters
    ctrl = Controller.from_json("P.json")    # other plant/friction/gains (docs/spec.md section 7;
                                             # not the model where the Kalman filter runs)
    ctrl = Controller(params={{"gains.L1": [150.0]}})
    ctrl.reset()
    tau = ctrl.step(t, q1, q2)               # t [s], q1, q2 [rad] -> tau [N m], recorded reference
    tau = ctrl.step(t, q1, q2, ref=R)        # the rig's reference, R ({rows}, n): q1d, q1d', ..., q1d^(4)

``step`` must be called once per sample period dt (the velocity filters, the Kalman filter
and the observer assume it). One joint: floats in, float out; n joints: arrays (n,) in,
numpy array out. The torque is the command before the DAC.
"""

'''

_BODY = '''import json as _json
import math as _m

import numpy as _np

N_JOINTS = {n}
DT = {dt}
Q2D_METHOD = {method!r}
VELOCITY = {velocity!r}
CONFIG = {config!r}
REFERENCE_ROWS = {rows}
_INF = float("inf")
_NAN = float("nan")

# name: (shape, row-major values) of every controller constant
DEFAULT_PARAMS = {{
{defaults}
}}
# docs/spec.md section 7 parameter-file entries -> names above
SPEC_MAP = {spec_map}
STATE_NAMES = {state_names}


def _sign(x):
    return 1.0 if x > 0 else (-1.0 if x < 0 else x)


class _s:
    """IEEE versions (numpy float64) of the math functions used by the generated code."""

    sin, cos, tan, asin, acos, atan = _np.sin, _np.cos, _np.tan, _np.arcsin, _np.arccos, _np.arctan
    sinh, cosh, tanh = _np.sinh, _np.cosh, _np.tanh
    asinh, acosh, atanh = _np.arcsinh, _np.arccosh, _np.arctanh
    exp, log, expm1, log1p, sqrt = _np.exp, _np.log, _np.expm1, _np.log1p, _np.sqrt
    atan2, fmod, copysign, floor, ceil = _np.arctan2, _np.fmod, _np.copysign, _np.floor, _np.ceil
    isfinite, nextafter = _np.isfinite, _np.nextafter
    erf, erfc, lgamma = _m.erf, _m.erfc, _m.lgamma


def _to_float(x):
    return tuple(_to_float(y) for y in x) if isinstance(x, tuple) else float(x)


def _ieee(fn, *args):
    """Run the IEEE variant on float64 scalars (inf/nan instead of exceptions)."""
    conv = [tuple(_np.float64(y) for y in a) if isinstance(a, tuple) else _np.float64(a)
            for a in args]
    with _np.errstate(all="ignore"):
        return _to_float(fn(*conv))


def _fma(a, b, c):
    """a * b + c rounded once (IEEE fused multiply-add, as XLA's CPU dot products compute):
    Dekker's exact two-product summed by math.fsum; by rationals outside its range."""
    p = a * b
    if a == 0 or b == 0 or not (_m.isfinite(p) and _m.isfinite(c)):
        return p + c
    if 1e-140 < abs(a) < 1e140 and 1e-140 < abs(b) < 1e140:
        t = 134217729.0 * a
        ah = t - (t - a)
        al = a - ah
        t = 134217729.0 * b
        bh = t - (t - b)
        bl = b - bh
        return _m.fsum((p, ((ah * bh - p) + ah * bl + al * bh) + al * bl, c))
    from fractions import Fraction

    r = Fraction(float(a)) * Fraction(float(b)) + Fraction(float(c))
    return float(r) if r != 0 else p + c


def _round_away(x):
    return float(_m.copysign(_m.floor(abs(x) + 0.5), x))


def _solve(n, a, b):
    """x with A x = b (A row-major), Gaussian elimination with partial pivoting."""
    A = [list(a[i * n:(i + 1) * n]) + [b[i]] for i in range(n)]
    for k in range(n):
        piv = max(range(k, n), key=lambda i: abs(A[i][k]))
        A[k], A[piv] = A[piv], A[k]
        for i in range(k + 1, n):
            f = A[i][k] / A[k][k]
            for j in range(k, n + 1):
                A[i][j] -= f * A[k][j]
    x = [0.0] * n
    for i in range(n - 1, -1, -1):
        x[i] = (A[i][n] - sum(A[i][j] * x[j] for j in range(i + 1, n))) / A[i][i]
    return tuple(x)


{funcs}


def _scalar(x, what):
    if type(x) is float:
        return x
    a = _np.asarray(x, dtype=float)
    if a.size != 1:
        raise ValueError(f"{{what}}: expected one value for a one-joint controller, got shape {{a.shape}}")
    return float(a.reshape(()))


def _vector(x, what):
    a = _np.asarray(x, dtype=float).reshape(-1)
    if a.size != N_JOINTS:
        raise ValueError(f"{{what}}: expected {{N_JOINTS}} values, got shape {{_np.shape(x)}}")
    return a.tolist()


class Controller:
    """The exported controller: ``reset()``, then ``step(t, q1, q2) -> tau`` once per DT.

    ``params`` overrides constants by name (see ``DEFAULT_PARAMS``), each a number or a list
    of row-major values of the right size.
    """

    n = N_JOINTS
    dt = DT

    def __init__(self, params=None):
        p = {{k: list(v[1]) for k, v in DEFAULT_PARAMS.items()}}
        for name, value in (params or {{}}).items():
            if name not in DEFAULT_PARAMS:
                raise ValueError(f"unknown controller parameter {{name!r}}; known: {{sorted(DEFAULT_PARAMS)}}")
            vals = [float(x) for x in _np.asarray(value, dtype=float).reshape(-1)]
            if len(vals) != len(p[name]):
                raise ValueError(f"parameter {{name}}: expected {{len(p[name])}} value(s), got {{len(vals)}}")
            if any(_m.isnan(x) for x in vals):
                raise ValueError(f"parameter {{name}}: NaN")
            p[name] = vals
        model = sorted(k for k in (params or {{}}) if k.startswith("model."))
        if VELOCITY == "kalman" and model:
            raise ValueError(f"parameters {{model}}: the Kalman filter's matrices (estimator.*) "
                             "were designed for the exported model; export again from the "
                             "parameter file instead of overriding the model")
        self.params = p
        flat = [x for k in DEFAULT_PARAMS for x in p[k]]
        self._step = _make_step(*_derive_step(*flat))
        self._init = _make_init(*_derive_init(*flat))
        self._ref = _make_reference(*_derive_reference(*flat))
        self._step_ref = _make_step_ref(*_derive_step_ref(*flat))
        self._init_ref = _make_init_ref(*_derive_init_ref(*flat))
        self._ref_derivs = _make_reference_derivatives(*_derive_reference_derivatives(*flat))
        self._state = None

    @classmethod
    def from_json(cls, path):
        """Controller with the plant, friction and gains of a docs/spec.md section 7 parameter file."""
        with open(path) as f:
            doc = _json.load(f)
        params = {{}}
        for key, name in SPEC_MAP.items():
            section, entry = key.split(".")
            if section in doc and isinstance(doc[section], dict) and entry in doc[section]:
                params[name] = doc[section][entry]
        return cls(params=params)

    def reset(self):
        """Forget the filter and observer state; the next ``step`` starts from its angles."""
        self._state = None

    @property
    def state(self):
        """Current internal state by name (None before the first step)."""
        if self._state is None:
            return None
        vals = _np.asarray(self._state, dtype=float).reshape(len(STATE_NAMES), N_JOINTS)
        return dict(zip(STATE_NAMES, vals))

    def reference(self, t):
        """Recorded reference link angle q1d(t) [rad]."""
        r = self._ref(float(t))
        return r if N_JOINTS == 1 else _np.array(r)

    def reference_derivatives(self, t):
        """Recorded reference at t [s] as ``step``'s ``ref`` takes it: (REFERENCE_ROWS, n),
        rows q1d, q1d', ..., q1d^(4) [rad/s^k]."""
        return _np.array(self._ref_derivs(float(t))).reshape(REFERENCE_ROWS, N_JOINTS)

    def step(self, t, q1, q2, ref=None):
        """Motor torque tau [N m] at time t [s] from link and rotor angles q1, q2 [rad];
        ``ref`` (REFERENCE_ROWS, n): the rig's reference at t (rows q1d, q1d', ...,
        q1d^(4) [rad/s^k]); None: the recorded one."""
        t = float(t)
        if N_JOINTS == 1:
            q = (_scalar(q1, "q1"), _scalar(q2, "q2"))
        else:
            q = _vector(q1, "q1") + _vector(q2, "q2")
        if ref is None:
            if self._state is None:
                self._state = self._init(t, *q)
            self._state, tau = self._step(self._state, t, *q)
        else:
            r = _np.asarray(ref, dtype=float)
            if r.size != REFERENCE_ROWS * N_JOINTS:
                raise ValueError(f"ref: expected ({{REFERENCE_ROWS}}, {{N_JOINTS}}) values "
                                 f"(q1d and its first {{REFERENCE_ROWS - 1}} derivatives), got "
                                 f"shape {{r.shape}}")
            r = r.reshape(-1).tolist()
            if self._state is None:
                self._state = self._init_ref(t, *q, *r)
            self._state, tau = self._step_ref(self._state, t, *q, *r)
        return tau if N_JOINTS == 1 else _np.array(tau)
'''


def function_source(fn: Callable, *example_args: Any, name: str = "f") -> str:
    """Source of a standalone Python function ``name(*flat_scalars) -> tuple`` computing
    ``fn`` (a JAX function of arrays) for the shapes of ``example_args``, through the same
    translator as the controller export. Inputs and outputs are flattened row-major; every
    input is a signal (nothing is hoisted). Used to test the translator primitive by primitive.
    """
    with jax.enable_x64(True):
        args = [jnp.asarray(a) for a in example_args]
        syms = [sym_array(f"a{i}", tuple(a.shape), False) for i, a in enumerate(args)]
        prog = _translate(fn, args, syms, "v")
    names = [f"a{i}_{k}" for i, a in enumerate(args) for k in range(int(np.size(a)))]
    outs = "(" + "".join(format_atom(a) + ", " for a in prog.outputs) + ")"
    src = _fn_source(prog, name, [], ", ".join(names), "", outs)
    prelude = _BODY.split("{funcs}")[0].split("N_JOINTS")[0]
    helpers = _BODY.split("def _sign")[1].split("{funcs}")[0]
    return (prelude + '_INF = float("inf")\n_NAN = float("nan")\n\n\ndef _sign' + helpers
            + src + f"\n\n\n{name} = _make_{name}(*_derive_{name}())\n")

"""Write the standalone Python module of a traced controller.

``generate_source`` translates the programs of ``jaxflex.export.tracing.trace`` with the
``PYTHON`` dialect into a module that imports only numpy and the standard library: each
program becomes ``_derive_<f>`` (the statements on the controller's leaves alone, run once
per parameter set) and ``_make_<f>`` (a closure with the per-sample statements, on Python
floats with a numpy float64 fallback that keeps IEEE semantics). The leaves stay parameters,
so the module can be rebuilt with other values; the traced ones are its defaults. The
module's fused multiply-add is the source of ``jaxflex.export.fma.exact_fma`` itself.
"""

from __future__ import annotations

import datetime
import inspect
import math
import re
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.core.controller import CascadeController
from jaxflex.export.atoms import Program, Sym, eliminate_dead, sym_array
from jaxflex.export.dialect import format_atom
from jaxflex.export.fma import exact_fma
from jaxflex.export.program import REFERENCE_ROWS, SampledController, describe
from jaxflex.export.tracing import (
    SPEC_ENTRIES,
    Traced,
    listed_leaves,
    trace,
    translate_program,
)
from jaxflex.export.translate import Translator

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
        prelude=_PRELUDE, helpers=_HELPERS, n=n, dt=repr(float(c.dt)), method=c.q2d_method, velocity=sc.sensing.velocity,
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

_PRELUDE = """import json as _json
import math
import math as _m

import numpy as _np
"""

# the generated module's helpers; ``exact_fma`` is the one implementation, carried as source
_HELPERS = '''def _sign(x):
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


''' + inspect.getsource(exact_fma) + '''

def _round_away(x):
    return float(_m.copysign(_m.floor(abs(x) + 0.5), x))

'''

_BODY = '''{prelude}
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


{helpers}

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
    return (_PRELUDE + '\n_INF = float("inf")\n_NAN = float("nan")\n\n\n' + _HELPERS + "\n\n"
            + src + f"\n\n\n{name} = _make_{name}(*_derive_{name}())\n")

"""Translate a traced jaxpr into straight-line code on floats (the exporter's code generator).

One translator, several back ends: a ``Dialect`` spells each operation, ``PYTHON`` (floats and
``math``) or ``C99`` (doubles and libm); the same jaxpr translated in both gives the same
operations in the same order, so the two exports round alike.

Every array value of the jaxpr is *scalarised*: it becomes a numpy object array of atoms, one
per element, where an atom is a Python constant (folded at generation time) or a ``Sym`` (a
variable name in the generated code). Structural primitives (reshape, broadcast, slice,
concatenate, transpose, pad, ...) only rearrange atoms and emit no code; elementwise
primitives emit one statement per element; reductions and ``dot_general`` emit sums of
products. For a one-joint controller this gives plain float code with ``math`` functions,
several times faster than the same code on numpy scalars (``studies/bench_export_step.py``).

Inputs are either *parameters* (controller constants that may be overridden when the exported
controller is built) or *signals* (state, time, angles). Statements whose inputs are all
parameters are hoisted into a ``derive`` function that runs once per parameter set; the rest
forms the per-sample function. Common subexpressions are shared, trivial operations (x * 1,
x + 0, operations on literals) are folded, and dead code is dropped.

Unsupported primitives raise ``UnsupportedPrimitive`` naming the primitive. The atoms,
statements and programs are defined in ``jaxflex.export.atoms``, the spellings in
``jaxflex.export.dialect``, the exact fused multiply-add in ``jaxflex.export.fma``.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from jaxflex.export.atoms import (
    Atom,
    Opaque,
    Stmt,
    Sym,
    UnsupportedPrimitive,
    const_array,
    is_const,
    map_atoms,
)
from jaxflex.export.dialect import PYTHON, Dialect
from jaxflex.export.fma import exact_fma

# Generation-time folding on literals (IEEE-identical to XLA for arithmetic).
_FOLD2: dict[str, Callable[[Any, Any], Any]] = {
    "add": lambda a, b: a + b, "add_any": lambda a, b: a + b, "sub": lambda a, b: a - b,
    "mul": lambda a, b: a * b, "max": lambda a, b: max(a, b), "min": lambda a, b: min(a, b),
    "eq": lambda a, b: a == b, "ne": lambda a, b: a != b, "lt": lambda a, b: a < b,
    "le": lambda a, b: a <= b, "gt": lambda a, b: a > b, "ge": lambda a, b: a >= b,
    "and": lambda a, b: a and b, "or": lambda a, b: a or b,
}
_FOLD1: dict[str, Callable[[Any], Any]] = {"neg": lambda a: -a, "abs": abs, "not": lambda a: not a}

_CALLS = ("pjit", "jit", "closed_call", "core_call", "remat", "checkpoint", "custom_jvp_call",
          "custom_vjp_call", "custom_vjp_call_jaxpr", "custom_lin")
_IDENTITY = ("stop_gradient", "copy", "copy_p", "optimization_barrier", "reduce_precision")


def _constant_indices(idx: np.ndarray, prim: str) -> np.ndarray:
    """The index operand of a gather or scatter as integers; refused when it depends on the
    signals (a data-dependent index has no straight-line translation here)."""
    flat = idx.reshape(-1)
    if not all(is_const(a) for a in flat):
        raise UnsupportedPrimitive(f"primitive '{prim}' with data-dependent indices")
    return np.array([int(a) for a in flat], dtype=np.int32).reshape(idx.shape)


def _is_int_dtype(aval: Any) -> bool:
    return np.issubdtype(np.dtype(aval.dtype), np.integer)


def _is_bool_dtype(aval: Any) -> bool:
    return np.dtype(aval.dtype) == np.bool_


class Translator:
    """Walks jaxprs and accumulates the statements of one ``Program``."""

    def __init__(self, prefix: str = "v", dialect: Dialect = PYTHON):
        self.prefix = prefix
        self.d = dialect
        self.count = 0
        self.cse: dict[str, Sym] = {}
        self.static_stmts: list[Stmt] = []
        self.dyn_stmts: list[Stmt] = []

    # ----- statements -------------------------------------------------------------------------

    def _new(self, static: bool) -> Sym:
        self.count += 1
        return Sym(f"{'c' if static else self.prefix}{self.count}", static)

    def emit(self, template: str, *args: Atom) -> Sym:
        """One statement computing ``template`` of atoms; shared when already computed."""
        for a in args:
            if isinstance(a, Opaque):
                raise UnsupportedPrimitive(
                    f"the exporter cannot use the {a.what} output of a primitive directly"
                )
        code = template.format(*[a.name if isinstance(a, Sym) else self.d.literal(a) for a in args])
        hit = self.cse.get(code)
        if hit is not None:
            return hit
        static = all(a.static for a in args if isinstance(a, Sym))
        s = self._new(static)
        uses = tuple(a.name for a in args if isinstance(a, Sym))
        (self.static_stmts if static else self.dyn_stmts).append(Stmt((s.name,), code, uses, static))
        self.cse[code] = s
        return s

    # ----- scalar operations with simplification ----------------------------------------------

    def unary(self, prim: str, a: Atom, *, int_out: bool = False) -> Atom:
        if is_const(a) and prim in _FOLD1:
            return _FOLD1[prim](a)
        if is_const(a) and prim in ("sin", "cos", "exp", "log", "sqrt", "atan", "tanh", "expm1",
                                     "log1p") and isinstance(a, (int, float)):
            try:
                return float(getattr(math, prim)(a))
            except (ValueError, OverflowError):
                pass
        if prim not in self.d.unary:
            raise UnsupportedPrimitive(f"primitive '{prim}' is not supported by the exporter")
        return self.emit(self.d.unary[prim], a)

    def binary(self, prim: str, a: Atom, b: Atom, *, is_int: bool = False) -> Atom:
        ca, cb = is_const(a), is_const(b)
        if prim == "div" and is_int:
            if ca and cb:
                return int(a / b)
            return self.emit(self.d.int_div, a, b)
        if ca and cb:
            if prim in _FOLD2:
                return _FOLD2[prim](a, b)
            if prim == "div" and b != 0:
                return a / b
        if prim in ("add", "add_any"):
            if ca and a == 0 and not isinstance(a, bool):
                return b
            if cb and b == 0 and not isinstance(b, bool):
                return a
        elif prim == "sub":
            if cb and b == 0:
                return a
            if ca and a == 0:
                return self.unary("neg", b)
        elif prim == "mul":
            for x, y, cx in ((a, b, ca), (b, a, cb)):
                if cx and x == 1:
                    return y
                if cx and x == -1:
                    return self.unary("neg", y)
                if cx and x == 0 and not math.isnan(float(x)):
                    return 0 if isinstance(y, int) and not isinstance(y, bool) else 0.0
        elif prim == "div":
            if cb and b == 1:
                return a
        elif prim == "pow" and cb and b == 1:
            return a
        if prim not in self.d.binary:
            raise UnsupportedPrimitive(f"primitive '{prim}' is not supported by the exporter")
        return self.emit(self.d.binary[prim], a, b)

    def integer_pow(self, a: Atom, y: int) -> Atom:
        if is_const(a):
            return float(a) ** y
        if y == 0:
            return 1.0
        if y < 0:
            return self.binary("div", 1.0, self.integer_pow(a, -y))
        # binary exponentiation by repeated products, as XLA expands integer_pow
        acc, base, k = None, a, y
        while k:
            if k & 1:
                acc = base if acc is None else self.binary("mul", acc, base)
            k >>= 1
            if k:
                base = self.binary("mul", base, base)
        return acc

    def select(self, pred: Atom, cases: Sequence[Atom]) -> Atom:
        if is_const(pred):
            return cases[int(pred)]
        if len(cases) == 2:
            if is_const(cases[0]) and is_const(cases[1]) and cases[0] == cases[1] \
                    and type(cases[0]) is type(cases[1]):
                return cases[0]
            return self.emit(self.d.select2, pred, cases[0], cases[1])
        acc = cases[-1]
        for i in range(len(cases) - 2, -1, -1):
            acc = self.emit(self.d.select_n.format(i=i), pred, cases[i], acc)
        return acc

    def fma(self, a: Atom, b: Atom, c: Atom) -> Atom:
        """a * b + c rounded once (IEEE 754 fusedMultiplyAdd)."""
        if is_const(a) and is_const(b) and is_const(c):
            return exact_fma(float(a), float(b), float(c))
        for x, y in ((a, b), (b, a)):
            if is_const(x) and x == 0 and not math.isnan(float(x)) and is_const(y):
                return self.binary("add", 0.0 * float(y), c)
            if is_const(x) and x == 1:
                return self.binary("add", y, c)
        if is_const(c) and c == 0:
            return self.binary("mul", a, b)
        return self.emit(self.d.fma, a, b, c)

    def matvec_sum(self, a: Sequence[Atom], b: Sequence[Atom]) -> Atom:
        """One row of a matrix-vector product, sum_k a_k b_k, in the order and roundings of
        XLA's CPU dot emitter: for 2 or 3 terms the first product, then fused multiply-adds
        of the others; for 4 or 5 terms the first four products summed as
        (p0 + p2) + (p1 + p3) (its four-lane vector reduced), then + p4. Longer rows are
        summed in order."""
        k = len(a)
        if k in (2, 3):
            acc = self.binary("mul", a[0], b[0])
            for x, y in zip(a[1:], b[1:]):
                acc = self.fma(x, y, acc)
            return acc
        p = [self.binary("mul", x, y) for x, y in zip(a, b)]
        if k in (4, 5):
            acc = self.binary("add", self.binary("add", p[0], p[2]),
                              self.binary("add", p[1], p[3]))
            return acc if k == 4 else self.binary("add", acc, p[4])
        return self.total(p)

    def total(self, atoms: Sequence[Atom]) -> Atom:
        acc: Atom = None
        for a in atoms:
            acc = a if acc is None else self.binary("add", acc, a)
        return 0.0 if acc is None else acc

    # ----- jaxpr walking ----------------------------------------------------------------------

    def run(self, jaxpr: Any, consts: Sequence[Any], args: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Evaluate an (open) jaxpr on object arrays of atoms; returns the outputs' arrays."""
        env: dict[Any, np.ndarray] = {}

        def read(v):
            if type(v).__name__ == "Literal":
                return const_array(v.val)
            return env[v]

        for v, c in zip(jaxpr.constvars, consts):
            env[v] = c if isinstance(c, np.ndarray) and c.dtype == object else const_array(c)
        for v, a in zip(jaxpr.invars, args):
            env[v] = a
        for eqn in jaxpr.eqns:
            ins = [read(v) for v in eqn.invars]
            outs = self.eqn(eqn, ins)
            for v, o in zip(eqn.outvars, outs):
                shape = tuple(v.aval.shape)
                if o.shape != shape:
                    o = o.reshape(shape) if o.size == int(np.prod(shape)) else o
                env[v] = o
        return [read(v) for v in jaxpr.outvars]

    def _call(self, sub: Any, ins: list[np.ndarray]) -> list[np.ndarray]:
        if hasattr(sub, "jaxpr") and hasattr(sub, "consts"):
            return self.run(sub.jaxpr, sub.consts, ins)
        return self.run(sub, [], ins)

    def eqn(self, eqn: Any, ins: list[np.ndarray]) -> list[np.ndarray]:
        prim = eqn.primitive.name
        p = eqn.params
        out_avals = [v.aval for v in eqn.outvars]
        if prim in _CALLS:
            sub = p.get("jaxpr") or p.get("call_jaxpr") or p.get("fun_jaxpr")
            if sub is None:
                raise UnsupportedPrimitive(f"primitive '{prim}' without a jaxpr parameter")
            n_in = len(sub.jaxpr.invars) if hasattr(sub, "consts") else len(sub.invars)
            return self._call(sub, ins[len(ins) - n_in:])
        if prim in _IDENTITY:
            return list(ins[: len(out_avals)])
        if prim == "scan":
            return self.scan(p, ins)
        if prim == "convert_element_type":
            return [self._convert(ins[0], eqn.invars[0].aval, out_avals[0])]
        if prim == "integer_pow":
            return [map_atoms(lambda a: self.integer_pow(a, int(p["y"])), ins[0])]
        if prim in ("select_n",):
            pred, cases = ins[0], ins[1:]
            arrs = np.broadcast_arrays(pred, *cases)
            out = np.empty(arrs[0].shape, dtype=object)
            for idx in np.ndindex(out.shape):
                out[idx] = self.select(arrs[0][idx], [c[idx] for c in arrs[1:]])
            return [out]
        if prim == "clamp":
            lo, x, hi = np.broadcast_arrays(*ins)
            out = np.empty(x.shape, dtype=object)
            for idx in np.ndindex(x.shape):
                out[idx] = self.binary("min", self.binary("max", x[idx], lo[idx]), hi[idx])
            return [out]
        if prim in self.d.unary or prim in _FOLD1:
            if prim == "sign" and _is_int_dtype(out_avals[0]):
                raise UnsupportedPrimitive("primitive 'sign' on integers is not supported")
            return [map_atoms(lambda a: self.unary(prim, a), ins[0])]
        if prim in self.d.binary:
            is_int = _is_int_dtype(out_avals[0])
            a, b = np.broadcast_arrays(ins[0], ins[1])
            out = np.empty(a.shape, dtype=object)
            for idx in np.ndindex(a.shape):
                out[idx] = self.binary(prim, a[idx], b[idx], is_int=is_int)
            return [out]
        if prim == "round":
            method = int(p.get("rounding_method", 0))
            fmt = self.d.round_even if method == 1 else self.d.round_away
            return [map_atoms(lambda a: self.emit(fmt, a), ins[0])]
        return [np.asarray(o, dtype=object) if not isinstance(o, np.ndarray) else o
                for o in self.structural(prim, p, ins, out_avals)]

    def _convert(self, x: np.ndarray, in_aval: Any, aval: Any) -> np.ndarray:
        if _is_bool_dtype(aval):
            return map_atoms(lambda a: bool(a) if is_const(a) else self.emit(self.d.to_bool, a), x)
        if _is_int_dtype(aval):
            return map_atoms(lambda a: int(a) if is_const(a) else self.emit(self.d.to_int, a), x)

        from_float = np.issubdtype(np.dtype(in_aval.dtype), np.floating)

        def to_float(a):
            if is_const(a):
                return float(a)
            if from_float or self.d.to_float is None:
                return a
            return self.emit(self.d.to_float, a)

        return map_atoms(to_float, x)

    def structural(self, prim: str, p: dict, ins: list[np.ndarray], out_avals: list) -> list:
        x = ins[0] if ins else None
        if prim == "broadcast_in_dim":
            shape, dims = tuple(p["shape"]), tuple(p["broadcast_dimensions"])
            expanded = [1] * len(shape)
            for i, d in enumerate(dims):
                expanded[d] = x.shape[i]
            return [np.broadcast_to(x.reshape(expanded), shape).copy()]
        if prim in ("reshape", "squeeze", "expand_dims"):
            return [x.reshape(tuple(out_avals[0].shape))]
        if prim == "transpose":
            return [x.transpose(tuple(p["permutation"]))]
        if prim == "rev":
            return [np.flip(x, axis=tuple(p["dimensions"]))]
        if prim == "slice":
            strides = p.get("strides") or (1,) * x.ndim
            sl = tuple(slice(s, e, st) for s, e, st in zip(p["start_indices"], p["limit_indices"], strides))
            return [x[sl]]
        if prim == "dynamic_slice":
            starts = []
            for a, size, dim in zip(ins[1:], p["slice_sizes"], x.shape):
                v = a.reshape(()).item()
                if not is_const(v):
                    raise UnsupportedPrimitive("dynamic_slice with data-dependent start indices")
                starts.append(min(max(int(v), 0), dim - size))
            sl = tuple(slice(s, s + z) for s, z in zip(starts, p["slice_sizes"]))
            return [x[sl]]
        if prim == "concatenate":
            return [np.concatenate(ins, axis=int(p["dimension"]))]
        if prim == "stack":
            return [np.stack(ins, axis=int(p["axis"]))]
        if prim == "split":
            axis = int(p["axis"])
            edges = np.cumsum(p["sizes"])[:-1]
            return list(np.split(x, edges, axis=axis))
        if prim == "iota":
            shape, dim = tuple(p["shape"]), int(p["dimension"])
            idx = np.indices(shape)[dim]
            conv = float if np.issubdtype(np.dtype(p["dtype"]), np.floating) else int
            return [const_array(np.vectorize(conv, otypes=[object])(idx))]
        if prim == "pad":
            pad_val = ins[1].reshape(()).item()
            cfg = p["padding_config"]
            out = np.full(tuple(out_avals[0].shape), None, dtype=object)
            for i in range(out.size):
                out.flat[i] = pad_val
            # place x at lo + k (interior + 1); negative lo/hi crop
            src_idx = np.indices(x.shape).reshape(x.ndim, -1).T
            for si in src_idx:
                di = [int(lo) + int(s) * (int(it) + 1) for s, (lo, _hi, it) in zip(si, cfg)]
                if all(0 <= d < n for d, n in zip(di, out.shape)):
                    out[tuple(di)] = x[tuple(si)]
            return [out]
        if prim in ("cumsum", "cumprod", "cummax", "cummin"):
            axis, reverse = int(p["axis"]), bool(p.get("reverse", False))
            op = {"cumsum": "add", "cumprod": "mul", "cummax": "max", "cummin": "min"}[prim]
            y = np.moveaxis(x, axis, -1).copy()
            for idx in np.ndindex(y.shape[:-1]):
                row = y[idx]
                order = range(row.shape[0] - 1, -1, -1) if reverse else range(row.shape[0])
                acc = None
                for k in order:
                    acc = row[k] if acc is None else self.binary(op, acc, row[k])
                    row[k] = acc
            return [np.moveaxis(y, -1, axis)]
        if prim in ("reduce_sum", "reduce_max", "reduce_min", "reduce_prod", "reduce_and",
                    "reduce_or"):
            axes = tuple(p["axes"])
            op = {"reduce_sum": "add", "reduce_max": "max", "reduce_min": "min",
                  "reduce_prod": "mul", "reduce_and": "and", "reduce_or": "or"}[prim]
            keep = [d for d in range(x.ndim) if d not in axes]
            y = x.transpose(keep + list(axes)).reshape([x.shape[d] for d in keep] + [-1])
            out = np.empty(y.shape[:-1], dtype=object)
            for idx in np.ndindex(out.shape):
                acc = None
                for a in y[idx]:
                    acc = a if acc is None else self.binary(op, acc, a)
                out[idx] = acc
            return [out]
        if prim == "dot_general":
            return [self.dot_general(ins[0], ins[1], p["dimension_numbers"])]
        if prim == "unstack":
            axis = int(p["axis"])
            return [np.take(x, i, axis=axis) for i in range(x.shape[axis])]
        if prim == "gather":
            return [self.gather(p, ins[0], ins[1], out_avals[0])]
        if prim in ("scatter", "scatter-add", "scatter_add"):
            return [self.scatter(prim, p, ins[0], ins[1], ins[2])]
        if prim == "sort" and all(is_const(a) for a in ins[0].reshape(-1)):
            return self.sort_constants(p, ins)
        if prim == "lu":
            return [np.full(tuple(a.shape), Opaque("LU factorisation"), dtype=object) for a in out_avals]
        if prim == "custom_linear_solve":
            return [self.linear_solve(p, ins)]
        raise UnsupportedPrimitive(
            f"primitive '{prim}' is not supported by the exporter; supported are elementwise "
            "arithmetic and math functions, comparisons, select_n, clamp, structural ops "
            "(reshape, broadcast, slice, concatenate, pad, transpose), reductions, dot_general, "
            "cumulative sums, jnp.linalg.solve and nested calls"
        )

    def gather(self, p: dict, x: np.ndarray, idx: np.ndarray, aval: Any) -> np.ndarray:
        """``lax.gather`` at indices known at generation time (``x[i]``, ``M[idx][:, idx]``):
        the primitive itself, run on the operand's element numbers, says which element each
        output is; an index out of bounds gives the mode's fill."""
        import jax

        ids = jax.lax.gather_p.bind(
            np.arange(1, x.size + 1, dtype=np.int32).reshape(x.shape),
            _constant_indices(idx, "gather"), **{**p, "fill_value": 0})
        fill = p.get("fill_value")
        fill = (math.nan if np.issubdtype(np.dtype(aval.dtype), np.inexact) else 0) \
            if fill is None else fill
        flat = x.reshape(-1)
        return np.vectorize(lambda i: flat[i - 1] if i > 0 else fill, otypes=[object])(
            np.asarray(ids)).reshape(tuple(aval.shape))

    def scatter(self, prim: str, p: dict, x: np.ndarray, idx: np.ndarray,
                upd: np.ndarray) -> np.ndarray:
        """``lax.scatter`` (``.at[i].set``) and ``scatter-add`` (``.at[i].add``, the transpose
        of a gather) at indices known at generation time. The primitive, run on one-hot
        updates, says where each update goes; the sums are taken in the updates' order, as
        XLA's scatter loop adds them."""
        import jax
        import jax.numpy as jnp

        kw = {k: v for k, v in p.items() if k not in ("update_jaxpr", "update_consts")}
        onehot = np.eye(upd.size, dtype=np.int32).reshape((upd.size, *upd.shape))
        where = jax.vmap(lambda u: jax.lax.scatter_add_p.bind(
            jnp.zeros(x.shape, jnp.int32), _constant_indices(idx, prim), u,
            update_jaxpr=None, update_consts=(), **kw))(onehot)
        where = np.asarray(where).reshape(upd.size, x.size)
        out = x.reshape(-1).copy()
        for j, u in enumerate(upd.reshape(-1)):
            for t in np.flatnonzero(where[j]):  # none where the mode drops the update
                out[t] = u if prim == "scatter" else self.binary("add", out[t], u)
        return out.reshape(x.shape)

    def sort_constants(self, p: dict, ins: list[np.ndarray]) -> list[np.ndarray]:
        """``lax.sort`` of operands known at generation time (e.g. a permutation of constant
        pivots)."""
        import jax

        vals = [np.vectorize(lambda a: a, otypes=[type(x.reshape(-1)[0])])(x) for x in ins]
        return [const_array(o) for o in jax.lax.sort_p.bind(*vals, **p)]

    def scan(self, p: dict, ins: list[np.ndarray]) -> list[np.ndarray]:
        """``lax.scan`` with a static length, unrolled (for short loops such as substeps)."""
        length, nc, nk = int(p["length"]), int(p["num_consts"]), int(p["num_carry"])
        if length > 1000:
            raise UnsupportedPrimitive(f"primitive 'scan' of length {length} (unrolled up to 1000)")
        consts, carry, xs = ins[:nc], list(ins[nc:nc + nk]), ins[nc + nk:]
        ys: list[list[np.ndarray]] = []
        order = range(length - 1, -1, -1) if p.get("reverse", False) else range(length)
        for i in order:
            outs = self._call(p["jaxpr"], [*consts, *carry, *[x[i] for x in xs]])
            carry, y = list(outs[:nk]), outs[nk:]
            ys.append(y)
        if p.get("reverse", False):
            ys.reverse()
        n_y = len(ys[0]) if ys else 0
        stacked = [np.stack([y[j] for y in ys]) for j in range(n_y)]
        return [*carry, *stacked]

    def dot_general(self, a: np.ndarray, b: np.ndarray, dims: Any) -> np.ndarray:
        (lc, rc), (lb, rb) = dims
        lf = [d for d in range(a.ndim) if d not in lc and d not in lb]
        rf = [d for d in range(b.ndim) if d not in rc and d not in rb]
        A = a.transpose(list(lb) + lf + list(lc))
        B = b.transpose(list(rb) + rf + list(rc))
        nb = len(lb)
        bshape = A.shape[:nb]
        out = np.empty(bshape + A.shape[nb:nb + len(lf)] + B.shape[nb:nb + len(rf)], dtype=object)
        csize = int(np.prod([a.shape[d] for d in lc])) if lc else 1
        # XLA folds unit batch dimensions away: a (1, m, k) x (1, k) product is the
        # matrix-vector product its CPU emitter orders (``matvec_sum``)
        rows = int(np.prod(A.shape[nb:nb + len(lf)], dtype=int))
        cols = int(np.prod(B.shape[nb:nb + len(rf)], dtype=int))
        matvec = int(np.prod(bshape, dtype=int)) == 1 and rows >= 2 and cols == 1
        # a product of two or three terms, other than a dot of two vectors, is the first
        # product and then fused multiply-adds in XLA's CPU emitter, batched or not (the
        # chain's 3 x 3 rotations and inertias)
        matvec = matvec or (csize in (2, 3) and rows * cols > 1)
        for bi in np.ndindex(bshape):
            Ab, Bb = A[(*bi, ...)], B[(*bi, ...)]  # arrays also where an operand is 0-d
            Ab = Ab.reshape(Ab.shape[: len(lf)] + (csize,))
            Bb = Bb.reshape(Bb.shape[: len(rf)] + (csize,))
            for i in np.ndindex(Ab.shape[:-1]):
                for j in np.ndindex(Bb.shape[:-1]):
                    if matvec:
                        out[bi + i + j] = self.matvec_sum(list(Ab[i]), list(Bb[j]))
                    else:
                        terms = [self.binary("mul", x, y) for x, y in zip(Ab[i], Bb[j])]
                        out[bi + i + j] = self.total(terms)
        return out

    def linear_solve(self, p: dict, ins: list[np.ndarray]) -> np.ndarray:
        """``jnp.linalg.solve``: read the matrix from the matvec jaxpr and solve directly."""
        cl = p["const_lengths"]
        mv = p["jaxprs"].matvec
        mvj = mv.jaxpr if hasattr(mv, "jaxpr") else mv
        ok = (len(mvj.eqns) == 1 and mvj.eqns[0].primitive.name == "dot_general"
              and tuple(map(tuple, mvj.eqns[0].params["dimension_numbers"][0])) == ((1,), (0,))
              and cl.matvec == 1 and mvj.eqns[0].invars[0] is mvj.invars[0])
        if not ok:
            raise UnsupportedPrimitive(
                "custom_linear_solve other than jnp.linalg.solve(A, b) with a 2-D A and 1-D b"
            )
        A = ins[0]
        b = ins[-1]
        n = b.shape[0]
        if A.shape != (n, n) or b.ndim != 1:
            raise UnsupportedPrimitive("custom_linear_solve: need A (n, n) and b (n,)")
        off = [A[i, j] for i in range(n) for j in range(n) if i != j]
        if all(is_const(a) and a == 0 for a in off):
            # diagonal A: LU with partial pivoting reduces to b_i / A_ii
            return np.array([self.binary("div", b[i], A[i, i]) for i in range(n)], dtype=object)
        return np.array(self.eliminate([[*A[i], b[i]] for i in range(n)]), dtype=object)

    def eliminate(self, rows: list[list[Atom]]) -> list[Atom]:
        """x with A x = b from the rows [A_i, b_i]: Gaussian elimination with partial
        pivoting, written out (a row moves up where its entry in the pivot column is larger
        in magnitude, so ties keep the upper row), then back substitution. Its factors of A
        are shared by every right-hand side (common subexpressions), as an LU is."""
        n = len(rows)
        R = [list(r) for r in rows]
        for k in range(n):
            for i in range(k + 1, n):
                up = self.binary("gt", self.unary("abs", R[i][k]), self.unary("abs", R[k][k]))
                R[k], R[i] = ([self.select(up, [x, y]) for x, y in zip(R[k], R[i])],
                              [self.select(up, [y, x]) for x, y in zip(R[k], R[i])])
            for i in range(k + 1, n):
                f = self.binary("div", R[i][k], R[k][k])
                for j in range(k + 1, n + 1):
                    R[i][j] = self.binary("sub", R[i][j], self.binary("mul", f, R[k][j]))
        x: list[Atom] = [0.0] * n
        for i in range(n - 1, -1, -1):
            acc = self.total([self.binary("mul", R[i][j], x[j]) for j in range(i + 1, n)])
            x[i] = self.binary("div", self.binary("sub", R[i][n], acc), R[i][i])
        return x

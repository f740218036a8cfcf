"""Traces kept across processes: ``persistent_jit``, ``eqx.filter_jit`` whose traced and
lowered program (StableHLO, through ``jax.export``) is stored on disk.

JAX's persistent compilation cache (``jaxflex.app.cli.enable_compilation_cache``) keeps XLA's
compiled executables, but the key of that cache is the lowered program, so every new process
still traces the Python function and lowers it before it can look there. For the engine's
solver step that is most of a second run's compile time (tracing and lowering take longer
than reading XLA's cache). The
fitting engine (``jaxflex.fit``), the paper's closed loop (``jaxflex.loop.experiments``), the
loop Jacobian (``jaxflex.loop.analyse``), the Kalman design (``jaxflex.core.estimator``), the tuner,
the robust tuner, the certificate and ``validate``'s loops compile through it. The command
line turns it on (``--no-trace-cache`` off); in a script call ``enable(folder)``. The folder
must be the user's own: its files are unpickled (as JAX's cache folder holds executables).

``persistent_jit(f)`` behaves like ``eqx.filter_jit(f)`` (array leaves of the arguments are
traced, every other leaf is static) and, once ``enable(folder)`` has been called, keeps each
traced program in ``folder`` under a key computed *without tracing* from

- the source of every module of the ``jaxflex`` package and the versions of jax, jaxlib,
  equinox, optimistix, lineax, diffrax and numpy (any change of code reads as a new key);
- JAX's configuration (``jax_enable_x64`` and the other flags, read at call time) and the
  backend;
- the function (module and qualified name) and the arguments with each array replaced by its
  shape, dtype and weak type and every static leaf written out in full
  (``canonical``): numbers by ``repr``, strings, enumerations, dataclasses and equinox
  modules field by field, functions by module and qualified name (with their closure cells
  and defaults), ``functools.partial`` by its parts, numpy arrays by their bytes.

Anything ``canonical`` cannot write out exactly (an object of an unknown class, a function
whose cells hold one) makes the call fall back to ``eqx.filter_jit`` for that key, as does a
program ``jax.export`` cannot serialise: the cache only ever skips work it can prove
identical, it never guesses. The executable itself still comes from XLA (and from its
persistent cache, keyed by the program as before). The flat program is exported for the
current platform only; a stored file that does not deserialise is ignored and rewritten.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import importlib.metadata
import os
import pickle
import sys
import tempfile
import types
import weakref
from pathlib import Path
from typing import Any, Callable

import equinox as eqx
import jax
import numpy as np

#: Packages whose versions enter every key.
_VERSIONED = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "diffrax", "numpy")
#: File name suffix of a stored program.
_SUFFIX = ".jaxflex-trace"

_folder: Path | None = None
#: The in-process tables of every ``persistent_jit`` function (key -> program or None, and
#: call signature -> key or None: ``_key``).
_TABLES: list[dict] = []


class Unkeyable(Exception):
    """An argument that ``canonical`` cannot write out exactly (the call is not cached)."""


def enable(folder: str | os.PathLike | None) -> None:
    """Keep traced programs in ``folder`` (created if missing; None turns the cache off).
    The command line calls this with its compilation-cache folder."""
    global _folder
    if folder is None:
        _folder = None
        return
    path = Path(folder)
    path.mkdir(parents=True, exist_ok=True)
    _folder = path


def forget() -> None:
    """Empty the in-process tables (as a new process starts): the next call of each function
    reads its program from the folder, or traces it."""
    for table in _TABLES:
        table.clear()


def folder() -> Path | None:
    """The folder traced programs are kept in, or None when the cache is off."""
    return _folder


@functools.lru_cache(maxsize=1)
def _environment_digest() -> str:
    """Digest of the jaxflex sources and the versions of the libraries they trace through."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]  # the jaxflex package
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    for name in _VERSIONED:
        try:
            h.update(f"{name}={importlib.metadata.version(name)}".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{name}=absent".encode())
    h.update(sys.version.encode())
    return h.hexdigest()


def _config_digest() -> str:
    """JAX's configuration values (every flag, read now) and the default backend. Remembered
    under the flags' values themselves (every persistent_jit call asks: 4 us to compare them
    against 127 us for the digest), so any change of a flag is seen at the next call; x64 is
    read apart, as ``jax.enable_x64`` sets it for the current thread only."""
    fingerprint = (tuple(jax.config.values.items()), bool(jax.config.jax_enable_x64))
    if _CONFIG_MEMO.get("fingerprint") != fingerprint:
        _CONFIG_MEMO.update(fingerprint=fingerprint, digest=_digest_of_config())
    return _CONFIG_MEMO["digest"]


#: The last configuration fingerprint seen and its digest (``_config_digest``).
_CONFIG_MEMO: dict[str, Any] = {}


def _digest_of_config() -> str:
    items = sorted((k, repr(v)) for k, v in jax.config.values.items())
    return hashlib.sha256(repr((items, bool(jax.config.jax_enable_x64),
                                jax.default_backend())).encode()).hexdigest()


def _trusted(module: str | None) -> bool:
    """Whether code from ``module`` is covered by the environment digest: the jaxflex package
    (its sources are hashed), the versioned libraries and Python's standard library. A
    function or class from anywhere else (a user's script or module, a study, a test) can
    change without the key changing, so it is never keyed."""
    top = (module or "").split(".")[0]
    return (top == "jaxflex" or top in _VERSIONED or top in ("lineax", "equinox")
            or top in sys.stdlib_module_names or top == "builtins")


def _code(code: types.CodeType) -> tuple:
    """A code object by its bytecode, names, constants (nested code recursively) and first
    line: two lambdas of one function share a qualified name, not a body."""
    consts = tuple(_code(c) if isinstance(c, types.CodeType) else (type(c).__name__, repr(c))
                   for c in code.co_consts)
    return ("code", code.co_code, code.co_names, code.co_varnames, code.co_freevars,
            code.co_firstlineno, consts)


def canonical(obj: Any, _depth: int = 0) -> Any:
    """A nested tuple of plain values that determines ``obj`` as a traced argument: arrays by
    (shape, dtype, weak type), static leaves in full. Raises ``Unkeyable`` for anything it
    cannot write out exactly, and for any function or class defined outside the code the key
    covers (``_trusted``)."""
    if _depth > 60:
        raise Unkeyable("argument nested too deeply")
    d = _depth + 1
    if isinstance(obj, (jax.Array, jax.ShapeDtypeStruct)):
        weak = bool(getattr(obj, "weak_type", False))
        return ("array", tuple(obj.shape), str(obj.dtype), weak)
    if isinstance(obj, np.ndarray):  # eqx.filter_jit traces numpy arrays too
        return ("array", tuple(obj.shape), str(obj.dtype), False)
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        return (type(obj).__name__, repr(obj))
    if isinstance(obj, np.generic):
        return ("npscalar", str(obj.dtype), obj.tobytes())
    if isinstance(obj, (tuple, list)) and type(obj) in (tuple, list):
        return (type(obj).__name__, tuple(canonical(x, d) for x in obj))
    if type(obj) is dict:
        if not all(isinstance(k, str) for k in obj):
            raise Unkeyable("dict with non-string keys")
        return ("dict", tuple((k, canonical(obj[k], d)) for k in obj))
    if type(obj) in (frozenset, set):
        return (type(obj).__name__, tuple(sorted(repr(canonical(x, d)) for x in obj)))
    if isinstance(obj, np.dtype):
        return ("dtype", str(obj))
    if isinstance(obj, type):
        if not _trusted(obj.__module__):
            raise Unkeyable(f"class {obj.__module__}.{obj.__qualname__} is outside jaxflex")
        return ("type", obj.__module__, obj.__qualname__)
    if isinstance(obj, functools.partial):
        return ("partial", canonical(obj.func, d), canonical(obj.args, d),
                canonical(obj.keywords, d))
    if isinstance(obj, types.MethodType):
        return ("method", canonical(obj.__self__, d), canonical(obj.__func__, d))
    if isinstance(obj, types.FunctionType):
        if not _trusted(obj.__module__):
            raise Unkeyable(f"function {obj.__module__}.{obj.__qualname__} is outside jaxflex")
        cells = tuple(canonical(c.cell_contents, d) for c in (obj.__closure__ or ()))
        return ("function", obj.__module__, obj.__qualname__, _code(obj.__code__), cells,
                canonical(obj.__defaults__, d), canonical(obj.__kwdefaults__, d))
    if isinstance(obj, (types.BuiltinFunctionType, np.ufunc)):
        module = getattr(obj, "__module__", None) or "builtins"
        if not _trusted(module):
            raise Unkeyable(f"builtin {obj!r} is outside jaxflex")
        return ("builtin", module, getattr(obj, "__qualname__", obj.__name__))
    cls = type(obj)
    if isinstance(obj, enum.Enum) and _trusted(cls.__module__):
        return ("enum", cls.__module__, cls.__qualname__, obj.name)
    if dataclasses.is_dataclass(obj) and _trusted(cls.__module__):  # equinox modules too
        fields = tuple((f.name, canonical(getattr(obj, f.name), d))
                       for f in dataclasses.fields(obj) if hasattr(obj, f.name))
        return ("dataclass", cls.__module__, cls.__qualname__, fields)
    wrapped = getattr(obj, "__wrapped__", None)  # jax.numpy's wrapped functions
    if (callable(obj) and wrapped is not None and hasattr(obj, "__qualname__")
            and _trusted(getattr(obj, "__module__", None))):
        return ("wrapped", obj.__module__, obj.__qualname__, canonical(wrapped, d))
    where = "outside jaxflex" if not _trusted(cls.__module__) else "of no known kind"
    raise Unkeyable(f"cannot key an argument of type {cls.__module__}.{cls.__qualname__} "
                    f"({where})")


class _Program(eqx.Module):
    """A traced program: the jitted call of the exported function and how to rebuild the
    output pytree from its flat array outputs."""

    call: Callable
    out_index: Any  # the output's array part with each leaf replaced by its flat position
    out_static: Any  # the output's non-array part


def _rebuild(program: _Program, flat: list) -> Any:
    dyn = jax.tree_util.tree_map(lambda i: flat[i], program.out_index)
    return eqx.combine(dyn, program.out_static)


#: XLA options of a program compiled for compile speed (``persistent_jit(...,
#: fast_compile=True)``): XLA CPU's older LLVM emitters instead of its fusion emitters, which
#: compile every fused kernel as a module of its own. The static map's solver loop and the
#: programs a fit runs once (replay, covariance, discretisation check, constraint maps)
#: compile faster and run slower, which is why the loops where a fit spends its time keep
#: XLA's defaults.
FAST_COMPILE_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}


def persistent_jit(fun: Callable | None = None, *, fast_compile: bool = False) -> Callable:
    """``eqx.filter_jit(fun)`` whose traced programs are kept across processes once ``enable``
    was called (module docstring); ``fun`` should be a module-level function of jaxflex.
    ``fast_compile``: for a program a run calls a few times, whose compilation costs more
    than its runs: its kept program is compiled with ``FAST_COMPILE_OPTIONS`` (a decorator
    ``@persistent_jit(fast_compile=True)``; the trace is the same as without, and is shared;
    without the trace cache, plain ``eqx.filter_jit`` with XLA's defaults serves it)."""
    if fun is None:
        return functools.partial(persistent_jit, fast_compile=fast_compile)
    options = FAST_COMPILE_OPTIONS if fast_compile else None
    plain = eqx.filter_jit(fun)
    programs: dict[str, _Program | None] = {}
    keys: dict[Any, str | None] = {}  # call signature -> key (None: not keyable), this process
    _TABLES.extend((programs, keys))
    name = f"{fun.__module__}.{fun.__qualname__}"

    def kept(args: tuple, kwargs: dict) -> tuple[_Program, list] | None:
        """The kept program of this call (loaded or traced now) and the call's leaves, or
        None when plain jit serves it (cache off, inside a trace, not keyable, not
        exportable)."""
        if _folder is None or jax.config.jax_disable_jit:
            return None
        leaves, treedef = jax.tree_util.tree_flatten((args, dict(sorted(kwargs.items()))))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return None  # inside a trace, where plain jit inlines
        # weak types are dropped at the boundary: the exported program's outputs come back
        # strongly typed, and a weak leaf would key (and trace) a second program
        leaves = [jax.lax.convert_element_type(x, x.dtype)
                  if isinstance(x, jax.Array) and x.weak_type else x for x in leaves]
        call = jax.tree_util.tree_unflatten(treedef, leaves)
        key = _key(name, call, treedef, leaves, keys)
        if key is None:
            return None
        if key not in programs:
            programs[key] = _load(key, options) or _trace_and_store(fun, call, key, options)
        program = programs[key]
        return None if program is None else (program, leaves)

    @functools.wraps(fun)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        found = kept(args, kwargs)
        if found is None:
            return plain(*args, **kwargs)
        program, leaves = found
        return _rebuild(program, program.call(*_committed([x for x in leaves
                                                            if eqx.is_array(x)])))

    def prepare(*args: Any, **kwargs: Any) -> bool:
        """Trace and keep (or load) the program of ``wrapper(*args, **kwargs)`` without
        compiling or running it: the part of a first call that holds Python's interpreter
        lock, done here so that another thread can then compile and run the call while this
        one goes on (``jaxflex.fit.trace_solver``). True when a kept program now serves the
        call; False when plain jit would (nothing done)."""
        return kept(args, kwargs) is not None

    wrapper.plain = plain  # type: ignore[attr-defined]
    wrapper.prepare = prepare  # type: ignore[attr-defined]
    return wrapper


def _signature(treedef: Any, leaves: list) -> Any:
    """A hashable stand-in for a call's ``canonical`` form within this process: the pytree
    structure (with its static fields), every array leaf by shape, dtype and weak type, every
    other leaf by type and value (floats by ``repr``, so that 0.0 and -0.0 differ); None when
    some part cannot be hashed or compared. Two calls with equal signatures have equal
    canonical forms, so the key of the first serves the second without walking the arguments
    again (``canonical`` is a large share of a call's host time). A
    function leaf compares by identity, so its closure cells are read once per process: the
    module-level functions jaxflex passes have none that change."""
    def leaf(x: Any) -> Any:
        if isinstance(x, (jax.Array, np.ndarray)):
            # the dtype object itself (hashable): str(dtype) took a third of this function
            return ("array", x.shape, x.dtype, bool(getattr(x, "weak_type", False)))
        return (type(x), repr(x) if isinstance(x, float) else x)

    try:
        sig = (treedef, tuple(leaf(x) for x in leaves), _config_digest())
        hash(sig)
        return sig if sig == sig else None  # a static part that cannot be compared
    except Exception:  # noqa: BLE001 - unhashable or uncomparable static parts: no memo
        return None


def _key(name: str, call: Any, treedef: Any, leaves: list,
         keys: dict[Any, str | None]) -> str | None:
    """The storage key of ``call`` to function ``name`` (module docstring), or None when it
    cannot be keyed (``Unkeyable``); remembered in ``keys`` under the call's ``_signature``."""
    sig = _signature(treedef, leaves)
    if sig is not None and sig in keys:
        return keys[sig]
    try:
        src = repr((_environment_digest(), _config_digest(), name, canonical(call)))
        key: str | None = hashlib.sha256(src.encode()).hexdigest()
    except Unkeyable:
        key = None
    if sig is not None:
        keys[sig] = key
    return key


#: Committed copies of uncommitted ``jax.Array`` arguments, by ``id`` with a weak reference
#: to the original (arrays are immutable; an entry goes when its original is collected).
_COMMITTED: dict[int, tuple[weakref.ref, jax.Array]] = {}


def _committed(arrays: list) -> list:
    """``arrays`` with every leaf that is not a committed ``jax.Array`` put on the default
    device: the outputs of a call are committed, and a call with an uncommitted argument
    lowers (and fetches from XLA's cache) the program once more. The leaves still to move go
    in one transfer, and a ``jax.Array``'s committed copy is remembered while it lives (a
    problem's data are passed again at every step; numpy arrays can change in place and are
    moved every time): one ``device_put`` per leaf would cost more than the call."""
    out = list(arrays)
    todo = []
    for i, x in enumerate(out):
        if isinstance(x, jax.Array):
            if x.committed:
                continue
            kept = _COMMITTED.get(id(x))
            if kept is not None and kept[0]() is x:
                out[i] = kept[1]
                continue
        todo.append(i)
    if todo:
        moved = jax.device_put([out[i] for i in todo], _device())
        for i, y in zip(todo, moved):
            x = out[i]
            if isinstance(x, jax.Array):
                _COMMITTED[id(x)] = (weakref.ref(x, functools.partial(_drop, id(x))), y)
            out[i] = y
    return out


def _drop(ident: int, _ref: weakref.ref) -> None:
    """Forget the committed copy of the collected array ``ident`` (``_committed``)."""
    kept = _COMMITTED.get(ident)
    if kept is not None and kept[0] is _ref:
        del _COMMITTED[ident]


@functools.lru_cache(maxsize=1)
def _device() -> jax.Device:
    return jax.devices()[0]


def _path(key: str) -> Path:
    assert _folder is not None
    return _folder / f"{key}{_SUFFIX}"


def _load(key: str, options: dict[str, Any] | None = None) -> _Program | None:
    """The program stored under ``key``, or None (absent or unreadable); ``options``: XLA's
    compile options for it (None: the defaults)."""
    path = _path(key)
    if not path.exists():
        return None
    try:
        blob = pickle.loads(path.read_bytes())
        exported = jax.export.deserialize(bytearray(blob["program"]))
        return _Program(call=jax.jit(exported.call, compiler_options=options),
                        out_index=blob["out_index"], out_static=blob["out_static"])
    except Exception:  # a stale or damaged file: trace again and overwrite it
        return None


def _trace_and_store(fun: Callable, call: tuple[tuple, dict], key: str,
                     options: dict[str, Any] | None = None) -> _Program | None:
    """Trace ``fun(*args, **kwargs)`` (``call``: the pair) as a flat function of the array
    leaves, export it, store it under ``key`` (atomically) and return it, to be compiled
    with XLA's ``options`` (None: the defaults); None if the program cannot be exported or
    its output's static part cannot be stored."""
    dyn, static = eqx.partition(call, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    kept: dict[str, Any] = {}

    def flat(*xs: jax.Array) -> list[jax.Array]:
        args, kwargs = eqx.combine(jax.tree_util.tree_unflatten(treedef, list(xs)), static)
        out = fun(*args, **kwargs)
        out_dyn, kept["static"] = eqx.partition(out, eqx.is_array)
        out_leaves, out_tree = jax.tree_util.tree_flatten(out_dyn)
        kept["index"] = jax.tree_util.tree_unflatten(out_tree, list(range(len(out_leaves))))
        return out_leaves

    specs = [jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=bool(getattr(x, "weak_type",
                                                                            False)))
             for x in leaves]
    try:
        exported = jax.export.export(jax.jit(flat))(*specs)
        blob = pickle.dumps({"program": bytes(exported.serialize()), "out_index": kept["index"],
                             "out_static": kept["static"]})
    except Exception:  # noqa: BLE001 - not exportable or not storable: plain jit serves it
        return None
    path = _path(key)
    try:
        with tempfile.NamedTemporaryFile(dir=path.parent, delete=False, suffix=".tmp") as f:
            f.write(blob)
        os.replace(f.name, path)
    except OSError:
        pass  # a read-only or full folder: the program still serves this process
    return _Program(call=jax.jit(exported.call, compiler_options=options),
                    out_index=kept["index"], out_static=kept["static"])

"""Write, compile and load the C export (``jaxflex.export.cgen``) through ``ctypes``.

``load_c`` compiles a ``controller.c`` written by ``jaxflex export`` into a shared library
with the system's C compiler and returns a module-like object with what ``jaxflex run-loop``
and ``jaxflex.export.check_parity`` read from a Python export: ``Controller`` (``reset``,
``step(t, q1, q2, ref=None)``, ``reference``), ``N_JOINTS``, ``DT``, ``Q2D_METHOD``,
``VELOCITY``, ``CONFIG``, ``REFERENCE_ROWS``, ``STATE_NAMES``, ``DEFAULT_PARAMS`` and
``SPEC_MAP`` (from the library's ``jaxflex_info``).
"""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.export.cgen import C_FLAGS, generate_c

__all__ = ["CController", "CModule", "compile_c", "export_c", "find_cc", "load_c"]


def find_cc() -> str | None:
    """The C compiler: ``$CC`` if set, else ``cc``, ``gcc`` or ``clang`` on the PATH; None
    if there is none."""
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def export_c(controller: Any, path: str | os.PathLike, description: str = "",
             traced: Any = None) -> tuple[str, str]:
    """Write the C export of ``controller`` to ``path`` (``.c``) and the header beside it
    (same name, ``.h``), each atomically.

    **Arguments:**

    - ``controller``: a ``SampledController`` or ``CascadeController``.
    - ``path``: the source file to write, e.g. ``controller.c``.
    - ``description``: the first line of the files' comment.
    - ``traced``: the programs already traced (``jaxflex.export.trace``).

    **Returns:**

    ``(source, header)``.
    """
    path = Path(path)
    header_path = path.with_suffix(".h")
    src, hdr = generate_c(controller, traced=traced, header_name=header_path.name,
                          description=description)
    for p, text in ((header_path, hdr), (path, src)):
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, p)
    return src, hdr


def compile_c(source: str | os.PathLike, out: str | os.PathLike | None = None,
              cc: str | None = None) -> Path:
    """Compile an exported ``controller.c`` into a shared library.

    **Arguments:**

    - ``source``: the ``.c`` file (its header beside it).
    - ``out``: the library to write (default: a temporary file).
    - ``cc``: the compiler (default ``find_cc``).

    **Returns:**

    The library's path.

    **Raises:**

    ``RuntimeError`` when there is no C compiler or the compilation fails (with the
    compiler's message).
    """
    cc = cc or find_cc()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC or install cc) to build the C export")
    source = Path(source)
    if out is None:
        fd, name = tempfile.mkstemp(suffix=".so", prefix=source.stem + "_")
        os.close(fd)
        out = name
    cmd = [cc, *C_FLAGS, "-shared", "-fPIC", "-o", str(out), str(source), "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"compiling {source} failed ({' '.join(cmd)}):\n{res.stderr}")
    return Path(out)


class CController:
    """The C controller behind the Python export's interface: ``reset()``, then
    ``step(t, q1, q2, ref=None) -> tau`` [N m] once per ``dt``, ``reference(t)``."""

    def __init__(self, lib: ctypes.CDLL, info: dict[str, Any]):
        self._lib = lib
        self.n = int(info["n_joints"])
        self.dt = float(info["dt"])
        self._rows = int(info["reference_rows"])
        self._buf = (ctypes.c_double * (lib.jaxflex_state_size() // 8))()
        self._q1 = (ctypes.c_double * self.n)()
        self._q2 = (ctypes.c_double * self.n)()
        self._tau = (ctypes.c_double * self.n)()
        self._ref = (ctypes.c_double * (self._rows * self.n))()
        self.reset()

    def reset(self) -> None:
        """Forget the state; the next ``step`` starts from its angles."""
        self._lib.jaxflex_reset(self._buf)

    def _set(self, q1: Any, q2: Any) -> None:
        a1 = np.asarray(q1, dtype=float).reshape(-1)
        a2 = np.asarray(q2, dtype=float).reshape(-1)
        if a1.size != self.n or a2.size != self.n:
            raise ValueError(f"q1, q2: expected {self.n} value(s) each, got shapes "
                             f"{np.shape(q1)} and {np.shape(q2)}")
        self._q1[:] = a1.tolist()
        self._q2[:] = a2.tolist()

    def step(self, t: float, q1: Any, q2: Any, ref: Any = None) -> Any:
        """Motor torque tau [N m] at time t [s] from angles q1, q2 [rad]; ``ref``
        (REFERENCE_ROWS, n): the rig's reference (q1d, q1d', ..., q1d^(4)), None: the
        recorded one. One joint: a float; n joints: an array (n,)."""
        self._set(q1, q2)
        if ref is None:
            self._lib.jaxflex_step(self._buf, float(t), self._q1, self._q2, self._tau)
        else:
            r = np.asarray(ref, dtype=float).reshape(-1)
            if r.size != self._rows * self.n:
                raise ValueError(f"ref: expected ({self._rows}, {self.n}) values, got shape "
                                 f"{np.shape(ref)}")
            self._ref[:] = r.tolist()
            self._lib.jaxflex_step_ref(self._buf, float(t), self._q1, self._q2, self._ref,
                                       self._tau)
        return self._tau[0] if self.n == 1 else np.array(self._tau[:])

    def _from_state(self, S: tuple[float, ...], t: float, args: tuple[float, ...], ref: bool):
        self._buf[0] = 1.0
        self._buf[1:] = list(S)
        q1, q2 = args[:self.n], args[self.n:2 * self.n]
        tau = self.step(t, q1, q2, None if not ref else args[2 * self.n:])
        return tuple(self._buf[1:]), tau

    def _step(self, S: tuple[float, ...], t: float, *q: float):
        """One step from the flat state ``S`` (as the Python export's ``_step``)."""
        return self._from_state(S, t, q, False)

    def _step_ref(self, S: tuple[float, ...], t: float, *qr: float):
        """As ``_step`` with the reference after the angles."""
        return self._from_state(S, t, qr, True)

    @property
    def state(self) -> np.ndarray | None:
        """The flat state (None before the first step)."""
        return None if self._buf[0] == 0.0 else np.array(self._buf[1:])

    def reference(self, t: float) -> Any:
        """Recorded reference link angle q1d(t) [rad]."""
        out = (ctypes.c_double * self.n)()
        self._lib.jaxflex_reference(float(t), out)
        return out[0] if self.n == 1 else np.array(out[:])

    def reference_derivatives(self, t: float) -> np.ndarray:
        """Recorded reference at t as ``step``'s ``ref`` takes it, (REFERENCE_ROWS, n)."""
        out = (ctypes.c_double * (self._rows * self.n))()
        self._lib.jaxflex_reference_derivatives(float(t), out)
        return np.array(out[:]).reshape(self._rows, self.n)


class CModule:
    """A loaded C export, read like an exported Python module (module docstring)."""

    def __init__(self, lib: ctypes.CDLL, path: Path):
        self._lib = lib
        self.__file__ = str(path)
        lib.jaxflex_state_size.restype = ctypes.c_int
        lib.jaxflex_info.restype = ctypes.c_char_p
        dp = ctypes.POINTER(ctypes.c_double)
        lib.jaxflex_step.argtypes = [ctypes.c_void_p, ctypes.c_double, dp, dp, dp]
        lib.jaxflex_step_ref.argtypes = [ctypes.c_void_p, ctypes.c_double, dp, dp, dp, dp]
        lib.jaxflex_reset.argtypes = [ctypes.c_void_p]
        lib.jaxflex_reference.argtypes = [ctypes.c_double, dp]
        lib.jaxflex_reference_derivatives.argtypes = [ctypes.c_double, dp]
        info = json.loads(lib.jaxflex_info().decode())
        self.info = info
        self.N_JOINTS = int(info["n_joints"])
        self.DT = float(info["dt"])
        self.Q2D_METHOD = info["q2d_method"]
        self.VELOCITY = info["velocity"]
        self.CONFIG = info["config"]
        self.REFERENCE_ROWS = int(info["reference_rows"])
        self.STATE_NAMES = list(info["state_names"])
        self.DEFAULT_PARAMS = {k: (tuple(v[0]), list(v[1])) for k, v in info["params"].items()}
        self.SPEC_MAP = dict(info["spec_map"])

    def Controller(self) -> CController:  # noqa: N802 - the Python export's class name
        """A fresh controller (its own state)."""
        return CController(self._lib, self.info)


def load_c(path: str | os.PathLike, cc: str | None = None) -> CModule:
    """Compile (``compile_c``) and load an exported ``controller.c``.

    **Arguments:**

    - ``path``: the ``.c`` file written by ``jaxflex export`` (its header beside it).
    - ``cc``: the compiler (default ``find_cc``).

    **Returns:**

    A ``CModule``.

    **Raises:**

    ``FileNotFoundError`` for a missing file; ``RuntimeError`` when it cannot be compiled.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"controller file not found: {path}")
    lib_path = compile_c(path, cc=cc)
    try:
        lib = ctypes.CDLL(str(lib_path))
    finally:
        os.unlink(lib_path)  # the mapping stays valid after the file is removed
    return CModule(lib, path)

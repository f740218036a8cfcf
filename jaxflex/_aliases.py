"""The module paths jaxflex had before its modules were grouped into layer folders, kept
importable: ``import jaxflex.params`` gives the module object ``jaxflex.io.params`` itself
(not a copy), so classes, ``isinstance`` and pickles are the same under either name.

``MOVED`` maps each old dotted name to its new one; a name under an old package maps under
the new package (``jaxflex.effects.library`` -> ``jaxflex.core.effects.library``). A finder
at the front of ``sys.meta_path`` answers for the old names only, and imports the new module
when the old one is first imported, so nothing here is loaded ahead of use.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
from collections.abc import Sequence
from types import CodeType, ModuleType

#: Old module name -> the module that now holds it.
MOVED: dict[str, str] = {
    # core: the physics
    "jaxflex.certificate": "jaxflex.core.certificate",
    "jaxflex.chain": "jaxflex.core.chain",
    "jaxflex.controller": "jaxflex.core.controller",
    "jaxflex.effects": "jaxflex.core.effects",
    "jaxflex.estimator": "jaxflex.core.estimator",
    "jaxflex.friction": "jaxflex.core.friction",
    "jaxflex.inertial": "jaxflex.core.inertial",
    "jaxflex.observer": "jaxflex.core.observer",
    "jaxflex.plant": "jaxflex.core.plant",
    "jaxflex.sensing": "jaxflex.core.sensing",
    "jaxflex.state": "jaxflex.core.state",
    "jaxflex.trajectory": "jaxflex.core.trajectory",
    "jaxflex.validation": "jaxflex.core.validation",
    # sim
    "jaxflex.simulate": "jaxflex.sim.simulate",
    "jaxflex.step": "jaxflex.sim.step",
    # io
    "jaxflex.errors": "jaxflex.io.errors",
    "jaxflex.logs": "jaxflex.io.logs",
    "jaxflex.params": "jaxflex.io.params",
    "jaxflex.presets": "jaxflex.io.presets",
    # runtime
    "jaxflex.fit.ahead": "jaxflex.runtime.ahead",
    "jaxflex.tracecache": "jaxflex.runtime.tracecache",
    # workflows
    "jaxflex.analyse": "jaxflex.loop.analyse",
    "jaxflex.arm_ident": "jaxflex.identify.arm",
    "jaxflex.datagen": "jaxflex.identify.datagen",
    "jaxflex.experiments": "jaxflex.loop.experiments",
    "jaxflex.robust": "jaxflex.tune.robust",
    # app
    "jaxflex.api": "jaxflex.app.api",
    "jaxflex.cli": "jaxflex.app.cli",
    "jaxflex.hardware": "jaxflex.app.hardware",
    "jaxflex.plots": "jaxflex.app.plots",
    "jaxflex.reports": "jaxflex.app.reports",
}


def new_name(name: str) -> str | None:
    """The current name of the module once called ``name``, or None if it was not moved."""
    head = name
    while "." in head:
        if head in MOVED:
            return MOVED[head] + name[len(head):]
        head = head.rpartition(".")[0]
    return None


class _Alias(importlib.abc.Loader):
    """Loads an old name as the module object of its new name (``target``, whose spec is
    ``spec``)."""

    def __init__(self, target: str, spec: importlib.machinery.ModuleSpec):
        self.target = target
        self.spec = spec

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        module = importlib.import_module(self.target)
        self.spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:
        # the import system has just set the module's __spec__ to the old name's; the module
        # keeps its own (its name, its file, what ``importlib.reload`` reloads)
        module.__spec__ = self.spec

    def get_code(self, name: str) -> CodeType | None:
        """The new module's code, for ``python -m`` under an old name."""
        return self.spec.loader.get_code(self.target)


class _Finder(importlib.abc.MetaPathFinder):
    """Finds the old names of ``MOVED`` (and the modules under them), nothing else."""

    def find_spec(self, fullname: str, path: Sequence[str] | None = None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        new = new_name(fullname) if fullname.startswith("jaxflex.") else None
        if new is None:
            return None
        real = importlib.util.find_spec(new)
        if real is None:
            return None
        return importlib.util.spec_from_loader(
            fullname, _Alias(new, real), is_package=real.submodule_search_locations is not None)


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once), ahead of the finder that would load a
    second copy of a moved module's file under its old name."""
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())

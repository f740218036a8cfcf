"""The physics modules import nothing from the runtime layer (``jaxflex.tracecache``): whether
a program's trace is kept across processes is decided by the workflows that call them."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "jaxflex"
PHYSICS = ("plant", "friction", "observer", "estimator", "certificate", "controller", "step",
           "simulate", "effects", "state", "trajectory", "sensing")


def test_no_physics_module_imports_the_runtime_layer():
    bad = []
    for name in PHYSICS:
        files = sorted((PKG / name).rglob("*.py")) if (PKG / name).is_dir() else [PKG / f"{name}.py"]
        for f in files:
            for node in ast.walk(ast.parse(f.read_text())):
                mods = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                        [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                bad += [(f.name, m) for m in mods if m.startswith("jaxflex.tracecache")]
    assert not bad

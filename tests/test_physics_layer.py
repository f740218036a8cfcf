"""The physics (``jaxflex.core``) and the integration on it (``jaxflex.sim``) import nothing
from the runtime layer (``jaxflex.runtime``): whether a program's trace is kept across
processes, or compiled ahead, is decided by the workflows that call them."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "jaxflex"
PHYSICS = ("core", "sim")


def test_no_physics_module_imports_the_runtime_layer():
    bad = []
    for layer in PHYSICS:
        for f in sorted((PKG / layer).rglob("*.py")):
            for node in ast.walk(ast.parse(f.read_text())):
                mods = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                        [f"{node.module}.{a.name}" for a in node.names]
                        if isinstance(node, ast.ImportFrom) and node.module else [])
                bad += [(str(f.relative_to(PKG)), m) for m in mods
                        if m.startswith("jaxflex.runtime.")]
    assert not bad

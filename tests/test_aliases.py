"""The module names from before the layer folders (``jaxflex._aliases.MOVED``) import as the
very module objects of their new names, so a user's script, an ``isinstance`` check and a
pickle written under an old name keep working; ``import jaxflex`` loads none of them ahead of
use."""

import importlib
import pickle
import subprocess
import sys

import pytest

from jaxflex._aliases import MOVED, new_name


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_name_is_the_new_module(old):
    module = importlib.import_module(old)
    assert module is importlib.import_module(MOVED[old])
    assert module.__name__ == module.__spec__.name == MOVED[old]


def test_names_under_an_old_package_and_from_imports_are_the_same_objects():
    import jaxflex.core.effects.library
    import jaxflex.effects.library
    import jaxflex.io.params
    import jaxflex.params as p
    from jaxflex.core.friction import LuGre as new_lugre
    from jaxflex.friction import LuGre

    assert jaxflex.effects.library is jaxflex.core.effects.library
    assert p.Params is jaxflex.io.params.Params and LuGre is new_lugre
    assert isinstance(jaxflex.io.presets.paper_params(), p.Params)
    assert pickle.loads(pickle.dumps(LuGre)) is LuGre
    assert new_name("jaxflex.logs.files") == "jaxflex.io.logs.files"
    assert new_name("jaxflex.fit.solve") is None and new_name("jaxflex.data") is None
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("jaxflex.params.nothing")


def test_import_jaxflex_loads_no_old_name_and_an_old_name_imports_alone():
    code = ("import sys, jaxflex; from jaxflex._aliases import MOVED; "
            "print(sorted(n for n in MOVED if n in sys.modules)); "
            "print('jaxflex.runtime.tracecache' in sys.modules, 'jaxflex.app' in sys.modules); "
            "import jaxflex.plant, jaxflex.presets; print(jaxflex.presets.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split("\n")
    assert out[:3] == ["[]", "False False", "jaxflex.io.presets"]
    help_ = subprocess.run([sys.executable, "-m", "jaxflex.cli", "--help"], capture_output=True,
                           text=True)
    assert help_.returncode == 0 and help_.stdout.startswith("usage: jaxflex")

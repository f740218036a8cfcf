"""The README's notebook examples run as written (identify a shipped log, discover, plot;
simulate the paper's loop) and print finite numbers."""

import contextlib
import io
import math
import re
import warnings
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


@pytest.mark.slow
def test_readme_notebook_examples_run():
    blocks = _python_blocks(README.read_text())
    assert blocks, "README has no python example"
    for block in blocks:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            exec(compile(block, str(README), "exec"), {"__name__": "readme_example"})
        printed = out.getvalue().replace("[", " ").replace("]", " ").split()
        assert printed and all(math.isfinite(float(v)) for v in printed), out.getvalue()


def test_readme_is_a_short_page():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    assert "pip install -e . && jaxflex reproduce --out out/reproduce" in text
    assert 'pip install -e ".[test]" && python -m pytest -q' in text

"""The README's notebook example runs as written and prints a finite RMS error."""

import contextlib
import io
import math
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_notebook_example_runs():
    blocks = _python_blocks(README.read_text())
    assert blocks, "README has no python example"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(blocks[0], str(README), "exec"), {"__name__": "readme_example"})
    printed = out.getvalue().strip().strip("[]").split()
    assert printed and all(math.isfinite(float(v)) for v in printed), out.getvalue()


def test_readme_is_a_short_page():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    assert "pip install -e . && jaxflex reproduce --out out/reproduce" in text
    assert 'pip install -e ".[test]" && python -m pytest -q' in text

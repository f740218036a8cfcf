"""Every study runs at a small size (slow: run with ``pytest -m slow``), so none rots."""

import subprocess
import sys
from pathlib import Path

import pytest

#: peer_sysid needs mujoco's optional sysid extra; tests/test_peer_sysid.py runs it (or skips)
STUDIES = sorted(s for s in (Path(__file__).parent.parent / "studies").glob("*.py")
                 if s.stem != "peer_sysid")


@pytest.mark.slow
@pytest.mark.parametrize("script", STUDIES, ids=[s.stem for s in STUDIES])
def test_study_runs_small(script, tmp_path):
    r = subprocess.run(
        [sys.executable, str(script), "--small", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=1800,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert list(tmp_path.rglob("*.json")), "a study writes its numbers to JSON"

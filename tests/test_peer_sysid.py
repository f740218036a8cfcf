"""The peer benchmark against MuJoCo's system identification (``studies/peer_sysid.py``) runs
at its small size and writes every number its question needs (slow: ``pytest -m slow``)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

STUDY = Path(__file__).resolve().parents[1] / "studies" / "peer_sysid.py"


def _sysid_usable() -> bool:
    """mujoco.sysid swallows a missing optional dependency (the ``mujoco[sysid]`` extra) and
    then lacks its functions."""
    try:
        from mujoco import sysid
    except ImportError:
        return False
    return hasattr(sysid, "optimize") and hasattr(sysid, "calculate_intervals")


@pytest.mark.slow
def test_peer_sysid_runs_small_and_writes_its_keys(tmp_path):
    if not _sysid_usable():
        pytest.skip("mujoco.sysid not usable (pip install 'mujoco[sysid]>=4')")
    r = subprocess.run([sys.executable, str(STUDY), "--small", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    for key in ("question", "versions", "blas", "load_avg_per_stage", "experiment", "truth",
                "settings", "common_quantities", "logs"):
        assert key in res, key
    for log in ("mujoco_log", "jaxflex_log"):
        _check_log(res["logs"][log])


def _check_log(lg):
    methods = lg["methods"]
    assert {"sysid_default", "sysid_xscale_jac", "jaxflex_same_start"} <= set(methods)
    for name, m in methods.items():
        assert isinstance(m["success"], bool), name
        for q in ("Jx", "viscous", "coulomb"):
            c = m["compare"][q]
            assert {"value", "true", "rel_error", "stderr", "error_over_stderr"} <= set(c)
    jf = methods["jaxflex_same_start"]
    assert jf["cold_s"] > 0 and jf["warm_s"] > 0 and jf["steps"] > 0
    assert methods["sysid_default"]["iterations"] is not None
    assert lg["ratios"] and "warm_ratio" in lg["ratios"][0]

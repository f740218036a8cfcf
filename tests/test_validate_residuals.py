"""``validate`` reports the segment replay's residual analysis (MATLAB's ``resid``): per
output, autocorrelation and torque cross-correlation with their bands, Ljung-Box whiteness;
the command draws it."""

import json

import numpy as np
import pytest

from jaxflex.data import EMPS_IDIM_LS
from jaxflex.io.logs import save_log
from jaxflex.io.params import Params
from jaxflex.validate import replay_residual_analysis

EMPS_RIGID = EMPS_IDIM_LS.params_dict(Fs=22.0, sigma1=100.0, offset=False)


@pytest.fixture(scope="module")
def emps_log():
    from jaxflex.data import load_emps

    return load_emps("DATA_EMPS").slice(0, 4000)


def test_replay_residual_analysis_of_a_rigid_model(emps_log):
    """One channel per output of the model (rigid: q1), every sample of the segments, 25
    lags; the torque's cross band is wider than the white band (the torque is coloured:
    Bartlett's variance grows with its autocorrelation)."""
    ra = replay_residual_analysis(Params.from_dict(EMPS_RIGID), emps_log, kind="rigid",
                                  length=500)
    assert set(ra["channels"]) == {"q1"} and ra["lags"] == 25
    c = ra["channels"]["q1"]
    assert c["n"] == 4000 and c["autocorrelation"][0] == pytest.approx(1.0)
    assert len(c["cross_correlation"]) == 51 and c["cross_band"] > c["band"] > 0
    assert 0.0 <= c["p_white"] <= 1.0 and c["correlation_time"] >= 1.0
    # short segments cap the lags at a segment's half less one
    assert replay_residual_analysis(Params.from_dict(EMPS_RIGID), emps_log, kind="rigid",
                                    length=30)["lags"] == 14


def test_validate_command_reports_and_draws_the_residual_analysis(emps_log, tmp_path, capsys):
    from jaxflex.app.cli import main

    save_log(emps_log, tmp_path / "emps.csv")
    (tmp_path / "p.json").write_text(json.dumps(EMPS_RIGID))
    code = main(["validate", str(tmp_path / "emps.csv"), "--params", str(tmp_path / "p.json"),
                 "--model", "rigid", "--out", str(tmp_path / "v")])
    assert code == 0
    assert "residual whiteness (Ljung-Box" in capsys.readouterr().out
    rep = json.loads((tmp_path / "v" / "report.json").read_text())
    row = rep["logs"]["emps"]["params"]
    assert np.isfinite(row["residual_analysis"]["channels"]["q1"]["ljung_box_q"])
    assert (tmp_path / "v" / row["residual_figure"]).exists()

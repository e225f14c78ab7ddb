"""The two seed methods side by side (:mod:`inclinometer_calib.lab.methods`): the twelve positions,
the turntable and the lab with both logs, on one simulated probe whose magnetometer sits a few
tenths of a degree off its housing — on a good stand, on a worn one, on a table that is not level."""
import copy

import numpy as np
import pytest
import report_layout

from inclinometer_calib.core import effects as fx
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site
from inclinometer_calib.lab.methods import BLIND, compare
from inclinometer_calib.io.probelog import write_csv

SITE = Site()


def scenario(tmp_path, stand_error_deg=0.0, tilt_deg=0.0, seed=4):
    """Logs of one probe (misaligned magnetometer): twelve poses (two rounds; the stand's random pose
    error ``stand_error_deg``), a turntable (12 steps; tilted ``tilt_deg``), a stand-grid validation."""
    probe = sim.build_probe(seed, ["misalignment:mag=0.004,-0.003,0.005"], noise_mag=20.0)
    rng = np.random.default_rng(seed)
    stand = copy.deepcopy(probe)
    if stand_error_deg:
        stand.whole_probe = [fx.make_effect("stand_pose_error", sigma=stand_error_deg)]
    cal = sim.run_session(stand, SITE, sim.twelve_pose_session((25.0, 25.0), duration_s=3.0), rng, rate_hz=50.0)
    tt = sim.run_turntable(probe, SITE, sim.turntable_session(12, 3.0, tilt_deg=tilt_deg), rng,
                           t0=cal.t_s[-1] + 10.0)
    val = sim.run_session(probe, SITE, sim.stand_grid_session(duration_s=2.0), rng, rate_hz=50.0,
                          t0=tt.t_s[-1] + 10.0)
    for name, log in (("cal", cal), ("tt", tt), ("val", val)):
        write_csv(tmp_path / f"{name}.csv", log)
    truth = Calibration(probe.model, site=SITE)
    return compare(tmp_path / "cal.csv", tmp_path / "tt.csv", tmp_path / "val.csv", SITE, truth)


def _by(rows):
    return {r["method"]: r for r in rows}


def test_on_a_good_stand_every_method_reaches_the_true_level():
    rows = _by(scenario_dir("good"))
    true = rows["truth"]["azimuth_rms_deg"]
    for m in ("twelve-position", "turntable", "lab, both logs"):
        assert rows[m]["azimuth_rms_deg"] <= 1.2 * true, rows
        assert rows[m]["mag_alpha_deg"] < 0.01 and rows[m]["mag_bias"] < 5.0
        assert rows[m]["blind"] == BLIND[m]


def test_a_worn_stand_hurts_the_twelve_positions_magnetometer_not_the_turntables():
    rows = _by(scenario_dir("worn", stand_error_deg=0.1))
    assert rows["turntable"]["mag_matrix_ppm"] < 0.5 * rows["twelve-position"]["mag_matrix_ppm"], rows
    assert rows["turntable"]["mag_alpha_deg"] < rows["twelve-position"]["mag_alpha_deg"]


def test_a_table_that_is_not_level_does_not_hurt_the_turntable():
    rows = _by(scenario_dir("tilted", tilt_deg=2.0))
    assert rows["turntable"]["azimuth_rms_deg"] <= 1.2 * rows["truth"]["azimuth_rms_deg"], rows
    assert rows["turntable"]["mag_alpha_deg"] < 0.01


_DIRS = {}


@pytest.fixture(autouse=True)
def _tmp(tmp_path_factory):
    _DIRS["factory"] = tmp_path_factory


def scenario_dir(name, **kw):
    return scenario(_DIRS["factory"].mktemp(name), **kw)


def test_the_lab_report_shows_the_comparison(tmp_path):
    pytest.importorskip("matplotlib")
    from inclinometer_calib.apps.cli import main

    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), "--seed", "4", "--effect", "misalignment:mag=0.004,-0.003,0.005",
                 "--turntable", "10", "--rate", "50", "--no-survey-effects", "--station-seconds", "2"]) == 0
    with report_layout.FiguresChecked() as figures:
        assert main(["lab", "report", "--cal", str(out / "cal.csv"), "--val", str(out / "val.csv"), "--site",
                     str(out / "site.yaml"), "--turntable", str(out / "turntable.csv"), "--truth",
                     str(out / "truth_coeffs.yaml"), "--max-steps", "1", "--quiet", "-o",
                     str(tmp_path / "r.html")]) == 0
    page = (tmp_path / "r.html").read_text()
    assert "Calibration methods compared" in page and "mag α error" in page
    for m in ("twelve-position", "turntable", "lab, both logs", "truth"):
        assert f"<td>{m}</td>" in page
    # read in a browser: the summary first, the widest table (the methods') on the page, no nan
    lay = report_layout.layout(tmp_path / "r.html")
    report_layout.check(lay, images=figures.figures)
    assert figures.collisions == []
    said = lay["summary"]["text"]
    assert "Calibration methods on the validation log, azimuth RMS: twelve-position" in said
    assert "(the simulator's true model:" in said

"""Acceptance test from outside: the independent simulator's probe (test/data/stranger-probe).

Default settings only.  Its noise is 2.5× our simulator's on the accelerometer, its vertical
poses give no azimuth, its logs each start at t = 0: the CLI must calibrate it to its true
parameters within the noise, correct its stand grid to the level its true coefficients give, and
``reprocess --calibrate`` on the same data as a bag must give the same coefficients and station
angles.  The live graph's part is test/nodes/test_stranger_graph.py.
"""
import json

import numpy as np
import pytest

import strangers as S
from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.io.probelog import read_csv, segment_stations
from inclinometer_calib.core.survey import evaluate, summarize

# one worker runs the whole module (scripts/test.sh: --dist loadgroup), so that its module
# fixtures, which build the data every test reads, run once, not once per worker
pytestmark = [pytest.mark.xdist_group("stranger-probe"), pytest.mark.long(10)]


def _run(capsys, argv):
    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return S.stranger_files(tmp_path_factory.mktemp("stranger"))


@pytest.fixture(scope="module")
def survey_stations():
    """The stand grid's stations (the live nodes' detector over the validation log)."""
    log, _ = read_csv(S.STRANGER_DIR / "validation.csv.gz")
    stations, problems = segment_stations(log)
    assert problems == []
    return stations


def test_every_row_is_read_though_the_vertical_poses_give_no_azimuth():
    log, rejections = read_csv(S.STRANGER_DIR / "calibration.csv.gz")
    assert rejections == [] and len(log) == 10800
    vertical = log.pose >= 9
    assert vertical.sum() == 2400 and np.all(np.isnan(log.ref[vertical, 1]))
    stations, problems = segment_stations(log)
    assert problems == [] and [s.pose for s in stations] == list(range(1, 13)) * 2


def test_the_cli_calibrates_it_to_its_true_parameters_within_the_noise(files, tmp_path, capsys):
    out = tmp_path / "c.yaml"
    code, stdout, err = _run(capsys, ["twelve-position", str(files["cal"]), "-o", str(out), "--site", str(files["site"])])
    assert code == 0, err
    assert err == ""                                   # nothing refused, nothing to warn about
    assert "closed form" in stdout and "1.0× the noise" in stdout
    cal = Calibration.load(out)
    truth, _ = S.stranger_truth()
    tol = {"acc": (3e-4, 1e-4, 1e-4), "mag": (3.0, 1e-4, 1e-4)}   # bias, scale, e: a few σ of 24 captures
    for sensor in ("acc", "mag"):
        est, true = cal.triad(sensor).parameters(), truth.triad(sensor).parameters()
        b, k, e = tol[sensor]
        for name, v in true.items():
            lim = b if name.startswith("bias") else k if name.startswith("scale") else e
            assert abs(est[name] - v) < lim, (sensor, name, est[name], v)


def test_its_stand_grid_is_corrected_to_the_level_its_true_coefficients_give(files, tmp_path, capsys,
                                                                             survey_stations):
    out = tmp_path / "c.yaml"
    assert _run(capsys, ["twelve-position", str(files["cal"]), "-o", str(out), "--site", str(files["site"])])[0] == 0
    cal = Calibration.load(out)
    truth, site = S.stranger_truth()
    g = np.array([s.g for s in survey_stations])
    b = np.array([s.b for s in survey_stations])
    ref = np.array([s.ref for s in survey_stations])
    floor = summarize(evaluate(*truth.correct(g, b), site, ref=ref))
    ours = summarize(evaluate(*cal.correct(g, b), site, ref=ref))
    raw = summarize(evaluate(g, b, site, ref=ref))
    assert ours["stations"] == floor["stations"] == 198 and ours["azimuth_stations"] == 198
    assert ours["drift_rms_deg"] < 1.5 * floor["drift_rms_deg"] and ours["drift_rms_deg"] < 0.003
    assert ours["azimuth_rms_deg"] < 1.5 * floor["azimuth_rms_deg"] and ours["azimuth_rms_deg"] < 0.03
    assert raw["azimuth_rms_deg"] > 100 * ours["azimuth_rms_deg"]
    # the CLI's own figures agree
    code, stdout, err = _run(capsys, ["correct", str(files["val"]), "--coeffs", str(out), "--json"])
    assert code == 0 and json.loads(stdout)["azimuth_rms_deg"] == pytest.approx(ours["azimuth_rms_deg"], rel=1e-9)


def test_without_its_site_the_angles_are_the_same(files, tmp_path, capsys, survey_stations):
    # no --site: the default site's g and M_d only scale the triads; the angles do not change
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    assert _run(capsys, ["twelve-position", str(files["cal"]), "-o", str(a), "--site", str(files["site"])])[0] == 0
    assert _run(capsys, ["twelve-position", str(files["cal"]), "-o", str(b)])[0] == 0
    g = np.array([s.g for s in survey_stations])
    m = np.array([s.b for s in survey_stations])
    _, site = S.stranger_truth()
    ra = evaluate(*Calibration.load(a).correct(g, m), site)
    rb = evaluate(*Calibration.load(b).correct(g, m), site)
    np.testing.assert_allclose(ra["drift_deg"], rb["drift_deg"], atol=1e-9)
    np.testing.assert_allclose(ra["azimuth_deg"], rb["azimuth_deg"], atol=0.005)   # the stand's measured north


def test_reprocess_calibrates_its_bag_to_the_same_coefficients_and_station_angles(files, tmp_path, capsys):
    cli = tmp_path / "cli.yaml"
    code, _, err = _run(capsys, ["twelve-position", str(files["both"]), "-o", str(cli), "--site", str(files["site"])])
    # the survey after the poses is left alone, silently; the pause between the two logs is said
    lines = err.splitlines()
    assert code == 0 and len(lines) == 1 and "1 gap(s) in the sample times so far" in lines[0]
    bag = tmp_path / "stranger.mcap"
    assert _run(capsys, ["bag", "from-csv", str(files["cal"]), str(files["val"]), "-o", str(bag)])[0] == 0
    code, stdout, err = _run(capsys, ["reprocess", str(bag), "--calibrate", "--site", str(files["site"]),
                                      "-o", str(tmp_path / "re.mcap"), "--coeffs-out", str(tmp_path / "re.yaml")])
    assert code == 0, err
    assert "222 stations" in stdout and "2 solve(s)" in stdout     # 24 poses + 198 survey stations
    assert Calibration.load(tmp_path / "re.yaml").id == Calibration.load(cli).id
    stations, coefs = S.stations_of_bag(tmp_path / "re.mcap")
    final = Calibration.load(cli)
    survey = [s for s in stations if s["coefficients_id"] == final.id]
    assert len(survey) == 198
    log, _ = read_csv(files["both"])
    csv_st = [s for s in segment_stations(log)[0] if not s.pose]
    res = evaluate(*final.correct(np.array([s.g for s in csv_st]), np.array([s.b for s in csv_st])), final.site)
    np.testing.assert_allclose([s["drift_deg"] for s in survey], res["drift_deg"], atol=1e-9)
    np.testing.assert_allclose([s["azimuth_deg"] for s in survey], res["azimuth_deg"], atol=1e-9)


def test_the_labs_predicted_sigma_holds_for_its_toolface_at_low_drift_too(files):
    """The stranger's grid has stations at 2° drift: the toolface error compared there is the
    gravity toolface's, whose noise is ~15× the magnetic toolface's that the stations report inside
    3°; the predicted 1σ is of the angle compared (it was 6.4× too small over the grid)."""
    from inclinometer_calib import lab
    from inclinometer_calib.lab.diagnose import field_fit
    from inclinometer_calib.lab.uncertainty import normalised_errors

    _, site = S.stranger_truth()
    data = lab.load_logs(files["cal"], files["val"])
    model = lab.LabModel.base(site)
    ne = normalised_errors(model, field_fit(model, data), data.subset(data.role == "val"))
    for angle in ("drift", "azimuth", "toolface"):
        assert 0.8 <= ne[angle]["rms"] <= 1.25, ne
        assert ne[angle]["within_2"] >= 0.9, ne

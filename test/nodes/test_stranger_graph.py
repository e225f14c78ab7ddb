"""Acceptance test from outside, live: the independent simulator's probe through the ROS 2 graph.

The stranger's calibration log (2.5× our noise, vertical poses without azimuth) followed by the
first 36 stations of its stand grid, replayed by the probe node as a bag and as a CSV, calibrated
and corrected by the live nodes with default settings (separate processes over DDS, this machine
only).  The coefficients must be those of ``twelve-position`` on the same CSV and of ``reprocess
--calibrate`` on the same bag (bit for bit when every sample arrives, within their uncertainty
when a loaded machine drops the first ones: see SAME), and the survey stations' angles the same
too.  Two runs of about
35 s each, and one more of a probe that is several strangers at once (20 s).
"""
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

import strangers as S  # noqa: E402
from inclinometer_calib.cli import main  # noqa: E402
from inclinometer_calib.coeffs import Calibration  # noqa: E402

VAL_STATIONS = 36
SPEED = 10.0
# Live, the coefficients are the CLI's bit for bit when every sample arrives (seen on a quiet
# machine: the same content hash). A loaded CI machine may lose the first samples of the
# best-effort streams, which shifts the noise estimator's blocks and can move a station boundary
# by a sample: then they agree to within their own uncertainty, which these bounds are (a few σ
# of the stranger's calibration: bias ~1e-4 m/s² and 1 nT, scale and e-terms ~1e-5).
#: how far a station whose hold gained or lost a sample or two live may be from reprocess's, degrees
SHIFTED = {"drift_deg": 2e-3, "azimuth_deg": 0.03, "toolface_deg": 0.1}
SAME = {"acc": {"bias": 3e-4, "scale": 5e-5, "e": 5e-5}, "mag": {"bias": 3.0, "scale": 1e-4, "e": 1e-4}}
# These runs check the live nodes' coefficients and stations (read from the bag); the summary's model
# loop (the lab on the recorded bag: 3-5 s of CPU per run) is test_graph.py's subject, not theirs.
NO_LOOP = ("--no-loop",)


def _same_coefficients(live, cli, factor=1.0):
    for sensor in ("acc", "mag"):
        a, b = live.triad(sensor).parameters(), cli.triad(sensor).parameters()
        for k in a:
            kind = "bias" if k.startswith("bias") else "scale" if k.startswith("scale") else "e"
            assert abs(a[k] - b[k]) <= factor * SAME[sensor][kind], (sensor, k, a[k], b[k])


@pytest.fixture(scope="module")
def offline(tmp_path_factory):
    """The files, the CLI's coefficients on the CSV and reprocess's stations on the bag."""
    d = tmp_path_factory.mktemp("stranger_live")
    files = S.stranger_files(d, val_stations=VAL_STATIONS)
    files["bag"] = d / "both.mcap"
    assert main(["bag", "from-csv", str(files["both"]), "-o", str(files["bag"])]) == 0
    assert main(["twelve-position", str(files["both"]), "-o", str(d / "cli.yaml"), "--site", str(files["site"])]) == 0
    assert main(["reprocess", str(files["bag"]), "--calibrate", "--site", str(files["site"]), "-o",
                 str(d / "re.mcap")]) == 0
    stations, _ = S.stations_of_bag(d / "re.mcap")
    return files, Calibration.load(d / "cli.yaml"), stations


def _live(offline, domain_env, tmp_path, source):
    files, cli, _ = offline
    env, _ = domain_env
    out = tmp_path / f"run_{source}"
    cmd = [sys.executable, "-m", "inclinometer_calib.launcher", "--out", str(out), "--source", source, "--input",
           str(files["bag" if source == "mcap" else "both"]), "--speed", str(SPEED), "--site", str(files["site"]),
           "--timeout", "150", *NO_LOOP]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=200)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]
    return out, proc.stdout


def _check(offline, out, log):
    _, cli, re_stations = offline
    stations, coefs = S.stations_of_bag(out / "survey.mcap")
    # the same calibration: both rounds solved, the last equal to the CLI's
    assert len(coefs) == 2, log[-4000:]
    live = Calibration.from_yaml(coefs[-1]["coefficients_yaml"])
    print(f"live coefficients {live.id}, CLI {cli.id}" + (" (the same)" if live.id == cli.id else ""))
    _same_coefficients(live, cli)
    # the same survey stations, with the same angles as reprocess on the bag
    survey = [s for s in stations if s["coefficients_id"] == live.id and s["stamp"] > 1e-6 and
              np.isfinite(s["reference_azimuth_deg"]) and s["reference_drift_deg"] < 89.5]
    offline_survey = [s for s in re_stations if s["coefficients_id"] == cli.id and np.isfinite(s["reference_azimuth_deg"])
                      and s["reference_drift_deg"] < 89.5]
    assert len(survey) == len(offline_survey) == VAL_STATIONS
    # A station of as many samples as reprocess's has its angles (1e-12 when the coefficients are
    # the same); a sample lost in a move on the best-effort streams can shift a hold's boundary by
    # a sample or two (seen under load: 288 and 290 samples for 287 and 291, azimuth 0.004° apart),
    # which moves its mean by a fraction of its noise (at 2° drift about 0.05° of toolface and
    # azimuth over ~290 samples): such stations stay few and within SHIFTED of reprocess's.
    same_n = [a["samples_averaged"] == b["samples_averaged"] for a, b in zip(survey, offline_survey)]
    shifted = [(i, a["samples_averaged"], b["samples_averaged"]) for i, (a, b, ok) in
               enumerate(zip(survey, offline_survey, same_n)) if not ok]
    print(f"stations whose hold lost or gained samples live (index, live, reprocess): {shifted}")
    assert len(shifted) <= 4 and all(abs(n1 - n2) <= 3 for _, n1, n2 in shifted), shifted
    for key in ("drift_deg", "azimuth_deg", "toolface_deg"):
        live_v = [s[key] for s, ok in zip(survey, same_n) if ok]
        np.testing.assert_allclose(live_v, [s[key] for s, ok in zip(offline_survey, same_n) if ok], atol=2e-3,
                                   err_msg=key)
        for i, _, _ in shifted:
            d = (survey[i][key] - offline_survey[i][key] + 180.0) % 360.0 - 180.0
            assert abs(d) <= SHIFTED[key], (i, key, d)
    for s in survey:        # against the stand's reference: the noise level
        assert abs(s["drift_deg"] - s["reference_drift_deg"]) < 0.01
        assert abs((s["azimuth_deg"] - s["reference_azimuth_deg"] + 180) % 360 - 180) < 0.3
    assert "[ERROR]" not in log


def test_the_live_graph_calibrates_the_strangers_bag_as_the_cli_and_reprocess_do(offline, domain_env, tmp_path):
    out, log = _live(offline, domain_env, tmp_path, "mcap")
    _check(offline, out, log)


def test_the_live_graph_calibrates_the_strangers_csv_as_the_cli_and_reprocess_do(offline, domain_env, tmp_path):
    out, log = _live(offline, domain_env, tmp_path, "csv")
    _check(offline, out, log)


def test_the_live_graph_calibrates_a_noisy_unlabelled_10_hz_probe_logged_in_tesla(domain_env, tmp_path):
    # several strangers at once: 5× our noise, 10 Hz, no pose labels or references, a CSV in tesla
    case = S.Case("live mix", noise=5.0, rate_hz=10.0, hold_s=4.0, labels=False, mag_unit="T")
    p = S.make(case, tmp_path / "case")
    assert main(["twelve-position", str(p["both"]), "-o", str(tmp_path / "cli.yaml"), "--site", str(p["site"]),
                 "--mag-unit", "T"]) == 0
    cli = Calibration.load(tmp_path / "cli.yaml")
    env, _ = domain_env
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "inclinometer_calib.launcher", "--out", str(out), "--source", "csv",
                           "--input", str(p["both"]), "--speed", "20.0", "--site", str(p["site"]),
                           "--param", "probe:mag_unit:=T", "--timeout", "120", *NO_LOOP],
                          env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout[-6000:]
    stations, coefs = S.stations_of_bag(out / "survey.mcap")
    live = Calibration.from_yaml(coefs[-1]["coefficients_yaml"])
    _same_coefficients(live, cli, factor=5.0)           # 5× the noise, 1/10 of the samples
    survey = [s for s in stations if s["coefficients_id"] == live.id and np.isfinite(s["reference_azimuth_deg"])]
    assert len(survey) == 24
    for s in survey:        # 5× our noise at 10 Hz: ~0.01° of drift noise per station
        assert abs(s["drift_deg"] - s["reference_drift_deg"]) < 0.05

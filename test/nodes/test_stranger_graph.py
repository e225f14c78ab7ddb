"""Acceptance test from outside, live: the independent simulator's probe through the ROS 2 graph.

The stranger's calibration log (2.5× our noise, vertical poses without azimuth) followed by the
first 36 stations of its stand grid, replayed by the probe node as a CSV, calibrated and corrected
by the live nodes with default settings (separate processes over DDS, this machine only).  The
replay is paced (it never outruns its readers): the coefficients are those of ``twelve-position``
on the same CSV and of ``reprocess --calibrate`` on the same data as a bag, bit for bit, and the
survey stations reprocess's.  (The same probe as a bag, with a pose cut, on one core: the
replay tests.)  One run of about 15 s, and one more of a probe that is several strangers at once.
"""
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

import strangers as S  # noqa: E402
from inclinometer_calib.apps.cli import main  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402

VAL_STATIONS = 36
SPEED = 50.0
#: how far the live coefficients of the noisy 10 Hz mix may be from the CLI's, which reads the same CSV
#: (a few σ of the stranger's calibration: bias ~1e-4 m/s² and 1 nT, scale and e-terms ~1e-5), times 5
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
    cmd = [sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--source", source, "--input",
           str(files["bag" if source == "mcap" else "both"]), "--speed", str(SPEED), "--site", str(files["site"]),
           "--timeout", "150", *NO_LOOP]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=200)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]
    return out, proc.stdout


def _check(offline, out, log):
    _, cli, re_stations = offline
    stations, coefs = S.stations_of_bag(out / "survey.mcap")
    # the same calibration: both rounds solved, the last the CLI's to the bit (the same content hash)
    assert len(coefs) == 2, log[-4000:]
    live = Calibration.from_yaml(coefs[-1]["coefficients_yaml"])
    assert live.id == cli.id, (live.id, cli.id)
    # the same stations as reprocess on the bag, every field that carries a number
    assert len(stations) == len(re_stations)
    for a, b in zip(stations, re_stations):
        for key in ("drift_deg", "azimuth_deg", "toolface_deg", "total_field_nt", "dip_deg", "samples_averaged",
                    "coefficients_id", "status", "temperature_c"):
            assert a[key] == b[key] or (a[key] != a[key] and b[key] != b[key]), (a["station_id"], key, a[key], b[key])
    survey = [s for s in stations if s["coefficients_id"] == live.id and s["stamp"] > 1e-6 and
              np.isfinite(s["reference_azimuth_deg"]) and s["reference_drift_deg"] < 89.5]
    assert len(survey) == VAL_STATIONS
    for s in survey:        # against the stand's reference: the noise level
        assert abs(s["drift_deg"] - s["reference_drift_deg"]) < 0.01
        assert abs((s["azimuth_deg"] - s["reference_azimuth_deg"] + 180) % 360 - 180) < 0.3
    assert "[ERROR]" not in log and "LOST" not in log


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
    proc = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--source", "csv",
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

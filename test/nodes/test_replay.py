"""The live graph equals reprocess: a recorded bag replayed through the graph gives reprocess's stations,
bit for bit, whatever the machine's speed (here: one core for the whole graph) — through the user's
own regression test, ``inclinometer-calib replay-test`` — and a run that loses anything says so.

The independent simulator's probe with pose 7 cut from both rounds of its calibration log, then
the first 36 stations of its stand grid: the calibration node ends the sequence when the probe
leaves the stand, solves by least squares, and the survey is corrected live as offline."""
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

import strangers as S  # noqa: E402
from inclinometer_calib.apps.cli import main  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.io.bag import read_bag  # noqa: E402
from inclinometer_calib.io.probelog import ProbeLog, read_csv, write_csv  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(24)

VAL_STATIONS = 36
CUT = 7


@pytest.fixture(scope="module")
def cut_bag(tmp_path_factory):
    """The stranger's logs, pose 7 cut from its calibration, as a bag with its probe's serial; every
    second sample (its 100 Hz as 50 Hz: the replay's claim does not need the rate, half the messages)."""
    d = tmp_path_factory.mktemp("replay")
    files = S.stranger_files(d, val_stations=VAL_STATIONS)
    log, _ = read_csv(files["both"])
    keep = (log.pose != CUT) & (np.arange(len(log.t_s)) % 2 == 0)
    write_csv(d / "cut.csv", ProbeLog(**{k: getattr(log, k)[keep] for k in ("t_s", "acc", "mag", "temp_c", "pose",
                                                                            "ref")}))
    bag = d / "cut.mcap"
    assert main(["bag", "from-csv", str(d / "cut.csv"), "-o", str(bag), "--probe-serial", "STRANGER-1"]) == 0
    return {"dir": d, "bag": bag, "site": files["site"]}


def test_the_strangers_bag_with_a_pose_cut_replayed_at_speed_50_on_one_core_gives_reprocess_stations(cut_bag,
                                                                                                   domain_env):
    """``replay-test --expect reprocess``, the whole graph on one core at --speed 50: the same
    stations, record and status as reprocess --calibrate, bit for bit; the whole survey corrected —
    the first station after the stand too (the sequence ends at the second: the first is held until
    then, and the record applies from it) — and the only raw stations are the stand's 22 captures,
    inside the span the record gives."""
    if shutil.which("taskset") is None:
        pytest.skip("taskset (util-linux) is not installed: the graph cannot be held to one core")
    env, _ = domain_env
    out = cut_bag["dir"] / "run"
    proc = subprocess.run(["taskset", "-c", "0", sys.executable, "-m", "inclinometer_calib.apps.cli", "replay-test",
                           str(cut_bag["bag"]), "--expect", "reprocess", "--calibrate", "--site", str(cut_bag["site"]),
                           "--speed", "50", "--tolerance", "1e-9", "--out", str(out), "--junit",
                           str(cut_bag["dir"] / "replay.xml"), "--timeout", "240"],
                          env=env, capture_output=True, text=True, timeout=300)
    log = proc.stdout + proc.stderr + (out / "launch.log").read_text()
    assert proc.returncode == 0, log[-8000:]
    assert "replay-test: PASS" in proc.stdout and "every station equal within 1e-09 deg" in proc.stdout
    assert 'failures="0"' in (cut_bag["dir"] / "replay.xml").read_text()
    stations, coefs = read_bag(out / "survey.mcap")[:2]
    assert len(coefs) == 1
    cal = Calibration.from_yaml(coefs[0]["coefficients_yaml"])
    assert "least squares" in cal.method
    survey = [s for s in stations if np.isfinite(s["reference_azimuth_deg"]) and s["reference_drift_deg"] < 89.5
              and s["stamp"] > stations[21]["stamp"]]
    corrected = [s for s in survey if s["coefficients_id"] == cal.id]
    assert len(corrected) == len(survey) and len(survey) >= 30
    t0, t1 = cal.diagnostics["stand"]["t_start"], cal.diagnostics["stand"]["t_end"]
    raw = [s for s in stations if not s["coefficients_id"]]
    assert len(raw) == 22 and all(t0 <= s["stamp"] - s["duration_s"] and s["stamp"] <= t1 + 1e-6 for s in raw)
    assert all(s["coefficients_id"] == cal.id for s in stations if s["stamp"] > t1)
    for s in corrected:       # the stand's reference, to the stranger's noise
        assert abs(s["drift_deg"] - s["reference_drift_deg"]) < 0.01
        assert abs((s["azimuth_deg"] - s["reference_azimuth_deg"] + 180) % 360 - 180) < 0.3
    assert "the twelve-pose sequence is over" in log and "missing pose 7: never captured" in log
    assert "samples: the probe sent" in log and "LOST" not in log


def test_a_record_of_another_probe_is_refused_every_station_says_why_and_the_run_is_not_clean(domain_env, tmp_path):
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.correct.reprocess import write_probe_bag

    env, _ = domain_env
    probe = sim.build_probe(3)
    log = sim.run_session(probe, Site(), sim.stand_grid_session(drifts=(10, 40), azimuths=(0, 120, 240),
                                                                toolfaces=(0,), duration_s=1.5),
                          np.random.default_rng(3), rate_hz=100)
    bag = tmp_path / "sn1.mcap"
    write_probe_bag(log, bag, serial="STRANGER-1")
    cal = Calibration(acc=probe.acc, mag=probe.mag, probe_id="ANOTHER-7", site=Site())
    rec = tmp_path / "other.yaml"
    cal.save(rec)
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--source", "mcap",
                           "--input", str(bag), "--coeffs", str(rec), "--no-calibration", "--speed", "50",
                           "--no-loop", "--timeout", "120"], env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 1, proc.stdout[-6000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert "uncorrected: record refused: record " in last and "probe ANOTHER-7, the data are of probe STRANGER-1" in last
    stations = read_bag(out / "survey.mcap")[0]
    assert len(stations) == 6 and all(not s["coefficients_id"] and s["uncorrected_reason"].startswith(
        "record refused") for s in stations)
    assert "uncorrected: record refused" in proc.stdout     # the summary's line


def test_an_unpaced_replay_on_one_core_accounts_for_every_sample_of_every_reader(domain_env, tmp_path):
    """The live-source case: --unpaced at 400 Hz × 100 on one core, where readers usually cannot keep
    up.  Whatever each of them loses, the verdict does not depend on the machine: the probe's end and
    every reader's final counts are in the recording; each reader's line is exact — the recorder's
    against the bag, read here with the mcap library, the nodes' against their own log — and the run
    is clean only if nothing was lost."""
    if shutil.which("taskset") is None:
        pytest.skip("taskset (util-linux) is not installed")
    from mcap.reader import make_reader
    env, _ = domain_env
    out = tmp_path / "run"
    proc = subprocess.run(["taskset", "-c", "0", sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out",
                           str(out), "--unpaced", "--speed", "100", "--rate", "400", "--stations", "3", "--no-loop",
                           "--timeout", "120"], env=env, capture_output=True, text=True, timeout=180)
    text = proc.stdout
    assert "end of the data is not in the recording" not in text and "did not take the end" not in text, text[-6000:]
    summary = text[text.index("=== run summary ==="):]
    sent = re.search(r"the probe sent (\d+) imu, (\d+) mag, (\d+) temperature.*\(not paced\)", summary)
    assert sent, summary
    sent = dict(zip(("imu", "mag", "temperature"), map(int, sent.groups())))
    with open(out / "survey.mcap", "rb") as f:
        counts = {}
        for _, channel, _ in make_reader(f).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    held = {k: counts.get(f"/probe/{k}", 0) for k in sent}
    lost = {"recorder": {k: sent[k] - held[k] for k in sent if held[k] < sent[k]}}
    for node in ("calibration", "correction"):
        said = re.search(rf"\[{node}\]: the source's end came .* never arrived here \(([^)]*)\)", text)
        lost[node] = ({k: int(v) for k, v in (item.split() for item in said.group(1).split(", "))} if said else {})
    for name, want in lost.items():
        line = next(x for x in summary.splitlines() if x.startswith(f"  {name} "))
        if want:
            assert line == f"  {name} LOST " + ", ".join(f"{v} {k}" for k, v in want.items()), (line, want)
        else:
            assert line.startswith(f"  {name} took every one"), line
    last = text.strip().splitlines()[-1]
    if any(lost.values()):
        assert proc.returncode == 1, text[-6000:]
        assert "samples lost: " in last and "an unpaced replay or a live source" in last
    else:
        assert "samples lost" not in text
"""The ROS graph as a graph: nodes as separate processes over real DDS (own ROS_DOMAIN_ID,
discovery on localhost only), started by the launcher; results checked from the recorded MCAP
with an independent reader (``mcap_ros2``; the launcher's summary uses ``rosbags``, the recorder
writes with ``inclinometer_calib.io.bag``).

1. the demo's scenario: a simulated twelve-pose calibration + well-path survey (50 Hz, at up to 30x speed), the
   probe's magnetometer bias drifting with temperature: coefficients against the simulator truth,
   survey angles against the reference attitudes; every temperature message recorded; one time
   base (the probe's /clock) for all header stamps; the model loop of the summary finds the
   temperature effect and its record brings the errors down to the true model's;
2. regression: replaying the recorded bag through probe(source:=mcap) -> correction (coefficients
   from the recorded coeffs.yaml) reproduces the recorded SurveyStation values.

Run with the environment of scripts/env.sh.  Takes about a minute.
"""
import json
import math
import re
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")
pytest.importorskip("mcap_ros2")

from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
import report_layout  # noqa: E402
from rig_clients import wits_client  # noqa: E402
from inclinometer_calib.core.frames import wrap180  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(40)

N_STATIONS = 12
SPEED = 30.0
RATE_HZ = 50.0     # the graph's mechanics do not need the probe's 100 Hz: half the messages
EFFECT = "temperature_bias:mag=2.5"    # the demo's (scripts/demo.sh)

# Recovery tolerances of the twelve-position fit at the simulator's default noise (0.002 m/s^2,
# 20 nT per sample; ~180 samples per pose): about 10x the errors seen (acc bias ~1e-4 m/s^2,
# scale/e ~1e-5; mag bias ~1 nT, scale/e ~4e-5).
TOL = {"acc": {"bias": 1e-3, "scale": 2e-4, "e": 2e-4, "C": 3e-4},
       "mag": {"bias": 10.0, "scale": 3e-4, "e": 3e-4, "C": 5e-4}}
# Survey angle tolerances (errors seen: drift max 0.002 deg, azimuth max 0.02 deg).  Uncorrected,
# the same probe is off by degrees.
DRIFT_TOL_DEG = 0.05
AZIMUTH_TOL_DEG = 0.2


def read_mcap(path, topics):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = {t: [] for t in topics}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(topics=list(topics)):
            out[channel.topic].append(msg)
    return out


def stamp(msg):
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def launch(args, env, timeout):
    cmd = [sys.executable, "-m", "inclinometer_calib.apps.launcher", *args]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    return proc, time.monotonic() - t0


@pytest.fixture(scope="module")
def sim_run(domain_env, tmp_path_factory):
    env, _ = domain_env
    out = tmp_path_factory.mktemp("graph") / "run"
    with socket.socket() as probe_port:
        probe_port.bind(("127.0.0.1", 0))
        port = probe_port.getsockname()[1]
    got, stop = [], threading.Event()
    client = threading.Thread(target=wits_client, args=(port, got, stop), daemon=True)
    client.start()
    # --reliable: lossless raw streams, so that what the correction node saw live is exactly what
    # the recorder stored, and the replay regression below is deterministic on a loaded machine
    proc, seconds = launch(["--out", str(out), "--speed", str(SPEED), "--stations", str(N_STATIONS),
                            "--seed", "11", "--reliable", "--timeout", "150", "--effect", EFFECT, "--param", f"probe:rate_hz:={RATE_HZ}",
                            "--wits-port", str(port)], env, timeout=200)
    stop.set()
    client.join(5)
    (out / "wits0_tcp.dat").write_bytes(b"".join(got))
    print(f"simulated calibration + survey through the launcher: {seconds:.1f} s")
    if proc.returncode != 0:
        pytest.fail(f"launcher exit status {proc.returncode}\n--- output ---\n{proc.stdout[-6000:]}\n"
                    f"{proc.stderr[-3000:]}")
    return out, proc, seconds


def test_a_rig_client_gets_every_survey_station_as_wits0_record_07(sim_run):
    from wits_parser import parse_wits0

    out, _, _ = sim_run
    bag = read_mcap(out / "survey.mcap", ["/survey/station"])
    surveyed = [s for s in bag["/survey/station"] if s.coefficients_id and s.status != 2]
    tcp = parse_wits0((out / "wits0_tcp.dat").read_bytes())
    assert len(tcp) == len(surveyed) >= N_STATIONS, (len(tcp), len(surveyed))
    for r, s in zip(tcp, surveyed):
        assert float(r[(7, 8)]) == pytest.approx(s.measured_depth_m, abs=0.005)
        assert float(r[(7, 13)]) == pytest.approx(s.drift_deg, abs=0.005)
        if math.isfinite(s.azimuth_deg):
            assert float(r[(7, 15)]) == pytest.approx(s.azimuth_deg, abs=0.005)
    assert [int(r[(7, 4)]) for r in tcp] == list(range(1, len(tcp) + 1))
    assert parse_wits0((out / "wits0.dat").read_bytes()) == tcp       # the file has the same records


def test_the_live_witsml_trajectory_is_the_export_of_the_recorded_run(sim_run):
    """The wits node's <out>/trajectory.xml (rewritten live after every station, inactive at the end)
    and the well, datum and wellbore documents beside it validate and are byte for byte what
    ``inclinometer-calib witsml`` makes of the recorded bag; its positions are the WITS0 records' to
    the centimetre, and it carries each station's ISCWSA covariance."""
    from wits_parser import parse_wits0

    from inclinometer_calib.rig import witsml
    from inclinometer_calib.io.bag import read_bag

    out, proc, _ = sim_run
    live = (out / "trajectory.xml").read_bytes()
    witsml.validate(live)
    stations, records, _ = read_bag(out / "survey.mcap")
    export = witsml.trajectory_document(stations, well="WELL", wellbore="WELLBORE", models=witsml.mag_models(records))
    assert export.exported >= N_STATIONS and live == export.xml
    assert [k for k, _ in export.parents] == ["well", "datum", "wellbore"]
    for kind, xml in export.parents:
        assert (out / f"trajectory.{kind}.xml").read_bytes() == xml and witsml.validate(xml) == "2.1"
    assert f"WITSML 2.1 trajectory: {out / 'trajectory.xml'}: {export.exported} stations, valid" in proc.stdout
    back = witsml.read_trajectory(live)
    records07 = parse_wits0((out / "wits0_tcp.dat").read_bytes())
    assert len(records07) >= N_STATIONS
    for r in records07:
        b = min(back, key=lambda b, md=float(r[(7, 8)]): abs(b["measured_depth_m"] - md))
        assert b["measured_depth_m"] == pytest.approx(float(r[(7, 8)]), abs=0.005 + 1e-9)
        for item, key in ((9, "tvd_m"), (18, "north_m"), (19, "east_m")):
            assert b[key] == pytest.approx(float(r[(7, item)]), abs=0.005 + 1e-9), (item, key)
        assert np.all(np.isfinite(b["position_covariance_ned_m2"])) and b["tool_error_model"] == "ISCWSA MWD Rev4"


def test_launcher_leaves_the_run_files(sim_run):
    out, proc, seconds = sim_run
    for name in ("survey.mcap", "coeffs.yaml", "truth.json", "summary.json"):
        assert (out / name).is_file(), f"{name} missing; output:\n{proc.stdout[-3000:]}"
    assert "=== run summary ===" in proc.stdout
    assert seconds < 90, f"the {SPEED:g}x run took {seconds:.0f} s"
    # every node stopped cleanly on SIGINT
    for node in ("probe", "calibration", "correction", "recorder"):
        assert f"[launch] {node} stopped (exit status 0)" in proc.stdout, node
    # the domain this test reserved is used as is; a clean run says so last
    assert "(from ROS_DOMAIN_ID, reserved by the parent process)" in proc.stdout
    assert proc.stdout.strip().splitlines()[-1] == "[launch] exit status 0: clean run"
    assert json.loads((out / "correction_state.json").read_text())["next_station_id"] == 12 + N_STATIONS


def test_the_summarys_model_loop_finds_the_effect_and_its_record_meets_the_truth(sim_run):
    out, proc, _ = sim_run
    loop = json.loads((out / "summary.json").read_text())["model_loop"]
    assert loop["lab_finding"] == "temperature_bias:mag:xyz", loop.get("lab_verdict")
    ladder = {r["model"]: r for r in loop["ladder"]}
    assert list(ladder) == ["uncorrected", "live_record", "lab_model", "simulator_truth"]
    live, lab, truth = (ladder[k]["azimuth_rms_deg"] for k in ("live_record", "lab_model", "simulator_truth"))
    assert lab <= 1.2 * truth < live, (live, lab, truth)
    assert Calibration.load(out / "lab_model.yaml").id == loop["lab_record"]
    page = (out / "report.html").read_text()
    assert page.count("src='data:image/png;base64,") == 3 and "lab_model" in page
    report = (out / "report.md").read_text()
    assert "## The model loop" in report and "temperature_bias:mag:xyz" in report


def test_the_run_report_reads_at_a_glance_in_a_browser(sim_run):
    """The demo's report.html laid out by Chromium and read back: first the lab's finding and the
    ladder in words and a table, then the full verdict; every plot drawn, nothing on top of
    anything, no nan."""
    out, _, _ = sim_run
    lay = report_layout.layout(out / "report.html")
    report_layout.check(lay, images=3)
    said = lay["summary"]["text"]
    assert "The lab finds temperature_bias:mag:xyz missing from the live record" in said, said
    ladder = r"Azimuth RMS \S+° uncorrected → \S+° live_record → \S+° lab_model → \S+° simulator_truth"
    assert re.search(ladder, said), said
    assert "With live_record the field monitor flags" in said


def test_the_recorder_has_every_temperature_message_from_the_first_on(sim_run):
    out, _, _ = sim_run
    bag = read_mcap(out / "survey.mcap", ["/probe/imu", "/probe/mag", "/probe/temperature", "/probe/reference"])
    imu, temp = bag["/probe/imu"], bag["/probe/temperature"]
    assert len(temp) == len(imu) == len(bag["/probe/mag"])  # reliable run: nothing lost, nothing missed
    assert stamp(temp[0]) == stamp(imu[0])
    truth = json.loads((out / "truth.json").read_text())
    assert len(imu) == truth["samples"]
    assert len(bag["/probe/reference"]) >= N_STATIONS


def test_one_time_base_for_all_stamps(sim_run):
    """stamp:=log: the probe publishes /clock, the other nodes run on it (use_sim_time), so their
    own stamps (status, diagnostics, coefficients) lie in the span of the sensor stamps."""
    out, _, _ = sim_run
    topics = ["/probe/imu", "/calibration/status", "/diagnostics", "/calibration/coefficients", "/clock"]
    bag = read_mcap(out / "survey.mcap", topics)
    t_imu = [stamp(m) for m in bag["/probe/imu"]]
    lo, hi = min(t_imu), max(t_imu)
    for topic in topics[1:4]:
        t = [stamp(m) for m in bag[topic]]
        assert t, topic
        assert lo <= min(t) and max(t) <= hi, (topic, min(t), max(t), lo, hi)
    clock = [m.clock.sec + 1e-9 * m.clock.nanosec for m in bag["/clock"]]
    assert clock == sorted(clock) and lo <= clock[0] and clock[-1] <= hi


def test_coefficients_match_the_simulator_truth(sim_run):
    out, _, _ = sim_run
    bag = read_mcap(out / "survey.mcap", ["/calibration/coefficients"])
    msgs = bag["/calibration/coefficients"]
    assert len(msgs) == 1, "one coefficient set expected (published once, transient local)"
    msg = msgs[0]
    cal = Calibration.from_yaml(msg.coefficients_yaml)
    assert cal.id == msg.id == Calibration.load(out / "coeffs.yaml").id
    truth = Calibration.load(out / "truth_coeffs.yaml")
    for s in ("acc", "mag"):
        est, true = cal.triad(s).parameters(), truth.triad(s).parameters()
        for k in est:
            kind = "bias" if k.startswith("bias") else "scale" if k.startswith("scale") else "e"
            assert abs(est[k] - true[k]) <= TOL[s][kind], f"{s} {k}: {est[k]:.6g} vs truth {true[k]:.6g}"
        dc = abs(cal.triad(s).correction_matrix - truth.triad(s).correction_matrix).max()
        assert dc <= TOL[s]["C"], f"{s} correction matrix off by {dc:.2e}"
    # the message's flat fields follow its own model: corrected = matrix·(raw - offset), REP-145 acc
    import numpy as np

    f_raw = np.array([0.3, -9.7, 0.8])  # some specific force reading
    c_msg = np.array(msg.accel_correction_matrix, float).reshape(3, 3)
    f_corr = c_msg @ (f_raw - np.array(msg.accel_offset, float))
    g_corr, _ = cal.correct(-f_raw, np.array([2e4, 0.0, 4e4]))
    assert np.allclose(f_corr, -g_corr, atol=1e-9)
    b_raw = np.array([2e4, 1e3, 4e4])
    b_msg = np.array(msg.mag_correction_matrix, float).reshape(3, 3) @ (b_raw - np.array(msg.mag_offset, float))
    assert np.allclose(b_msg, cal.correct(-f_raw, b_raw)[1], atol=1e-6)
    assert list(msg.poses_used) == list(range(1, 13))
    assert len(msg.accel_residuals) == 36 and msg.accel_residual_units == "m/s^2"


def test_survey_angles_within_tolerance(sim_run):
    out, _, _ = sim_run
    bag = read_mcap(out / "survey.mcap", ["/survey/station", "/calibration/coefficients"])
    cal_id = bag["/calibration/coefficients"][0].id
    stations = bag["/survey/station"]
    surveyed = [s for s in stations if math.isfinite(s.reference_drift_deg)]
    assert len(surveyed) == N_STATIONS, [s.station_id for s in stations]
    assert all(s.coefficients_id == cal_id for s in surveyed), "survey stations must be corrected"
    # the twelve calibration poses came before the coefficients: reported raw
    raw = [s for s in stations if not s.coefficients_id]
    assert len(raw) == 12
    assert [s.station_id for s in stations] == list(range(len(stations)))
    for s in surveyed:
        assert abs(s.drift_deg - s.reference_drift_deg) < DRIFT_TOL_DEG, (s.station_id, s.drift_deg)
        if s.azimuth_undefined:
            assert math.isnan(s.azimuth_deg) and s.status == 1
            continue
        assert abs(wrap180(s.azimuth_deg - s.reference_azimuth_deg)) < AZIMUTH_TOL_DEG, \
            (s.station_id, s.azimuth_deg, s.reference_azimuth_deg)
        assert s.status == 0 and not s.interference_suspected and not s.gravity_out_of_tolerance
        assert abs(s.delta_b_nt) < 300 and abs(s.delta_dip_deg) < 0.25
        assert s.samples_averaged > RATE_HZ and s.duration_s > 1.0     # over a second of the hold
        assert 24.0 < s.temperature_c < 61.0
    # the survey's depth (/probe/depth) and its trajectory by minimum curvature, tied in at the
    # surface; the twelve calibration poses have no depth
    from inclinometer_calib.correct.trajectory import minimum_curvature

    md = [s.measured_depth_m for s in surveyed]
    assert md == [500.0 + 30.0 * k for k in range(N_STATIONS)], md
    assert all(math.isnan(s.measured_depth_m) for s in raw)
    true = minimum_curvature([0.0] + md, [0.0] + [s.reference_drift_deg for s in surveyed],
                             [0.0] + [s.reference_azimuth_deg for s in surveyed])
    np.testing.assert_allclose([s.tvd_m for s in surveyed], true.tvd[1:], atol=0.1)
    np.testing.assert_allclose([s.north_m for s in surveyed], true.north[1:], atol=0.3)
    np.testing.assert_allclose([s.east_m for s in surveyed], true.east[1:], atol=0.3)
    assert all(s.dls_deg_per_30m > 0 for s in surveyed[1:])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["survey"]["stations"] == N_STATIONS
    assert summary["survey"]["drift_max_abs_deg"] < DRIFT_TOL_DEG
    assert summary["survey"]["azimuth_max_abs_deg"] < AZIMUTH_TOL_DEG
    assert summary["coeffs_yaml_matches_bag"] is True


def test_replaying_the_bag_reproduces_the_stations(sim_run, ros_env, tmp_path):
    out, _, _ = sim_run
    replay = tmp_path / "replay"
    proc, seconds = launch(["--out", str(replay), "--source", "mcap", "--input", str(out / "survey.mcap"),
                            "--coeffs", str(out / "coeffs.yaml"), "--no-calibration", "--speed", "100",
                            "--reliable", "--timeout", "120"], ros_env, timeout=180)
    print(f"bag replay through probe(source:=mcap) -> correction: {seconds:.1f} s")
    assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-2000:]
    # the recorded run's own outputs (/survey/station, /clock ...) are expected in its bag: said, not warned
    assert "/survey/station is an output of the recorded graph: not replayed" in proc.stdout
    assert "is not replayed: skipped" not in proc.stdout
    cal_id = Calibration.load(out / "coeffs.yaml").id
    recorded = [s for s in read_mcap(out / "survey.mcap", ["/survey/station"])["/survey/station"]
                if s.coefficients_id == cal_id]
    replayed = {round(stamp(s), 6): s
                for s in read_mcap(replay / "survey.mcap", ["/survey/station"])["/survey/station"]}
    assert len(recorded) == N_STATIONS
    fields = ("drift_deg", "azimuth_deg", "toolface_deg", "gravity_toolface_deg", "magnetic_toolface_deg",
              "total_gravity_mps2", "total_field_nt", "dip_deg", "delta_g_mps2", "delta_b_nt", "delta_dip_deg",
              "reference_drift_deg", "reference_azimuth_deg", "reference_toolface_deg", "duration_s")
    for s in recorded:
        r = replayed.get(round(stamp(s), 6))
        assert r is not None, f"station {s.station_id} at t={stamp(s):.3f} not reproduced"
        assert (r.station_id, r.status, r.samples_averaged, r.coefficients_id, r.toolface_type) == \
            (s.station_id, s.status, s.samples_averaged, s.coefficients_id, s.toolface_type)
        for f in fields:
            a, b = getattr(s, f), getattr(r, f)
            assert (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9 * max(1.0, abs(a)), (s.station_id, f, a, b)


def test_the_probes_serial_names_the_record_and_every_station(sim_run):
    out, _, _ = sim_run
    bag = read_mcap(out / "survey.mcap", ["/survey/station", "/calibration/coefficients", "/probe/serial"])
    assert [m.data for m in bag["/probe/serial"]] == ["SIM-11"]       # latched, recorded once
    cal = Calibration.from_yaml(bag["/calibration/coefficients"][0].coefficients_yaml)
    assert cal.probe_id == "SIM-11"
    assert {s.probe_serial for s in bag["/survey/station"]} == {"SIM-11"}

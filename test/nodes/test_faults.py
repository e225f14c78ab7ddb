"""Faults and recovery.

* in-process: a correction node with no calibration node around applies the last valid record
  on disk (``fallback_coeffs_file``), and its station ids continue across a restart
  (``state_file``);
* the launcher: a recorder, a calibration and a correction node killed at once mid-run are
  restarted (a new bag part; the two others resume from the recording): nothing is lost, the
  stations are reprocess's, the summary is built from both parts, the run exits 1 (nodes died); a
  calibration that never solves, a damaged input bag exit 1; two launchers at once get different
  domains and do not mix; an explicit domain held by another run is refused (exit 2).

(The recorder's SIGKILL test — readable up to at most the last chunk, recovered — is
``test_recorder.py::test_sigkill_loses_at_most_one_chunk``.)
"""
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

rclpy = pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

from inclinometer_calib.core.station import Station

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(36)


def _node(name, env, log_path, *params):
    args = [sys.executable, "-m", f"inclinometer_calib.nodes.{name}", "--ros-args"]
    for p in params:
        args += ["-p", p]
    log = open(log_path, "w")
    return subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)


def _wait_text(path, needle, timeout, proc=None):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        text = open(path).read()
        if needle in text:
            return text
        if proc is not None and proc.poll() is not None:
            break
        time.sleep(0.05)
    raise AssertionError(f"no {needle!r} in {path}:\n{open(path).read()[-3000:]}")


def _stop(proc, sig=signal.SIGINT):
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


# ---- the correction node's recovery state, in-process (no DDS needed) ---------------------------
class _Collect:
    """Stands in for a publisher: keeps what is published."""

    def __init__(self):
        self.msgs = []

    def publish(self, msg):
        self.msgs.append(msg)


def _survey_log(n_stations, seed=3):
    import numpy as np

    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.frames import Site

    refs = [(20.0 + 10.0 * k, 40.0 * k, 0.0) for k in range(n_stations)]
    stations = [Station.planned(sim.orientation_matrix(*r), 2.0, ref=r) for r in refs]
    return sim.run_session(sim.build_probe(seed), Site(), stations, np.random.default_rng(1), rate_hz=100.0,
                           move_s=0.5, survey=True)


def _correction_node(*params):
    from rclpy.parameter import Parameter

    from inclinometer_calib.nodes.correction import CorrectionNode

    node = CorrectionNode(parameter_overrides=[Parameter(k, value=v) for k, v in params])
    node.pub_station, node.pub_diag = _Collect(), _Collect()
    return node


def _feed(node, log):
    """Samples straight into the node's sample path, then the end-of-stream flush."""
    for t, g, m in zip(log.t_s.tolist(), log.gravity.tolist(), log.mag.tolist()):
        node.stream.feed(t, tuple(g), tuple(m))
    node.stream.close_hold()        # the open interval
    return node.pub_station.msgs


@pytest.fixture
def truth_record(tmp_path):
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.coeffs import Calibration
    from inclinometer_calib.core.frames import Site

    probe = sim.build_probe(3)
    cal = Calibration(acc=probe.acc, mag=probe.mag, probe_id="fallback", site=Site())
    path = tmp_path / "coeffs.yaml"
    cal.save(path)
    return path, cal


def test_correction_node_started_after_the_calibration_node_is_gone_applies_the_record_on_disk(
        ros, truth_record, tmp_path, capfd):
    path, cal = truth_record
    node = _correction_node(("fallback_coeffs_file", str(path)))
    ros.append(node)
    err = capfd.readouterr().err
    assert f"no record received yet; applying the last valid record on disk {path} (id {cal.id}, created " in err
    assert "[WARN]" in err.split("no record received yet")[0].splitlines()[-1]
    st = _feed(node, _survey_log(2))
    assert len(st) == 2 and all(s.coefficients_id == cal.id for s in st)  # corrected, not raw
    assert all(s.status == 0 and abs(s.drift_deg - r) < 0.1 for s, r in zip(st, (20.0, 30.0)))


def test_a_different_record_on_the_topic_replaces_the_fallback_one(ros, truth_record, capfd):
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.coeffs import Calibration
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.msg import CalibrationCoefficients
    from inclinometer_calib.nodes import common as c

    path, cal = truth_record
    same, node = (_correction_node(("fallback_coeffs_file", str(path))) for _ in range(2))
    ros.extend([same, node])
    same._on_coefficients(c.coefficients_to_msg(cal, CalibrationCoefficients))  # the same record: kept
    assert "is the fallback record already applied" in capfd.readouterr().err
    assert same.calibration.id == cal.id and same.engine.counts.records == 1   # not taken again
    other = sim.build_probe(4)
    newer = Calibration(acc=other.acc, mag=other.mag, probe_id="newer", site=Site())
    node._on_coefficients(c.coefficients_to_msg(newer, CalibrationCoefficients))
    err = capfd.readouterr().err
    line = next(x for x in err.splitlines() if "replaces the fallback record" in x)
    assert "[INFO]" in line and f"record {newer.id} received on /calibration/coefficients replaces the " \
        f"fallback record {cal.id} from disk" in line
    assert node.calibration.id == newer.id


def test_an_invalid_fallback_record_is_reported_and_not_used(ros, tmp_path, capfd):
    bad = tmp_path / "coeffs.yaml"
    bad.write_text("format: inclinometer_calib/coefficients\nformat_version: 1\nid: abc\n")
    node = _correction_node(("fallback_coeffs_file", str(bad)))
    ros.append(node)
    err = capfd.readouterr().err
    line = next(x for x in err.splitlines() if "fallback record" in x)
    assert "[ERROR]" in line and f"fallback record {bad} is not valid, not used" in line
    assert node.calibration is None
    missing = _correction_node(("fallback_coeffs_file", str(tmp_path / "none.yaml")))
    ros.append(missing)
    assert missing.calibration is None
    assert "no fallback record at" in capfd.readouterr().err


def test_station_ids_continue_across_a_restart_with_a_state_file(ros, truth_record, tmp_path, capfd):
    path, _ = truth_record
    state = tmp_path / "correction_state.json"
    first = _correction_node(("coeffs_file", str(path)), ("state_file", str(state)))
    ids = [s.station_id for s in _feed(first, _survey_log(3))]
    first.destroy_node()  # as if it had crashed: only the state file survives
    assert ids == [0, 1, 2]
    second = _correction_node(("coeffs_file", str(path)), ("state_file", str(state)))
    ros.append(second)
    assert "continuing station ids at 3" in capfd.readouterr().err
    assert [s.station_id for s in _feed(second, _survey_log(2, seed=4))] == [3, 4]
    # without a usable state file the node says so and numbers from 0
    state.write_text("{not json")
    third = _correction_node(("coeffs_file", str(path)), ("state_file", str(state)))
    ros.append(third)
    err = capfd.readouterr().err
    assert f"state file {state} is not usable" in err and "station ids start at 0" in err
    assert third.processor._next_id == 0


# ---- the launcher: a recorder and a correction node killed mid-run; a calibration that never
# solves; two runs at once; a domain held by another run; a damaged input bag -----------------
class Launch:
    """A launcher running in the background; its output lines collected as they come."""

    def __init__(self, env, *args):
        self.proc = subprocess.Popen([sys.executable, "-m", "inclinometer_calib.apps.launcher", *map(str, args)],
                                     env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines = []
        self.arrived = []     # time.monotonic() of each line's arrival
        self._th = threading.Thread(target=self._read, daemon=True)
        self._th.start()

    def _read(self):
        for line in self.proc.stdout:
            self.arrived.append(time.monotonic())
            self.lines.append(line)

    def arrival(self, pattern):
        """When the last line matching ``pattern`` arrived (monotonic s)."""
        return max(t for t, line in zip(self.arrived, self.lines) if re.search(pattern, line))

    @property
    def text(self):
        return "".join(self.lines)

    def wait_for(self, pattern, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for line in list(self.lines):
                m = re.search(pattern, line)
                if m:
                    return m
            if self.proc.poll() is not None and not self._th.is_alive():
                break
            time.sleep(0.05)
        raise AssertionError(f"no line matching {pattern!r}:\n{self.text[-6000:]}")

    def finish(self, timeout):
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.send_signal(signal.SIGINT)
            rc = self.proc.wait(30)
        self._th.join(5)
        return rc


def _free_env():
    """An isolated environment with no ROS_DOMAIN_ID: the launcher must reserve one itself."""
    from inclinometer_calib.apps.rosenv import RESERVED_BY_PARENT, isolated_env

    env = isolated_env(0)
    for key in ("ROS_DOMAIN_ID", RESERVED_BY_PARENT):
        env.pop(key, None)
    return env


def _bag_topics(path, topics):
    from mcap_ros2.reader import read_ros2_messages

    return [m for m in read_ros2_messages(str(path), topics=topics)]


def _sim_bag(path):
    """A simulated calibration and a 24-station well path as a recorded bag (ROS-free), 50 Hz."""
    import numpy as np

    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.io.probelog import ProbeLog
    from inclinometer_calib.correct.reprocess import write_probe_bag

    site = Site(total_field_nt=50500.0, dip_deg=62.0, declination_deg=1.5)
    probe = sim.build_probe(11)
    rng = np.random.default_rng(11)
    cal = sim.run_session(probe, site, sim.twelve_pose_session(duration_s=2.0), rng, rate_hz=50, move_s=1.0)
    well = sim.run_session(probe, site, sim.well_path_session(24, duration_s=2.0, seed=11), rng, rate_hz=50,
                           move_s=1.0, t0=cal.t_s[-1] + 2.0)
    log = ProbeLog.concatenate([cal, well])
    log.pose[:] = 0
    write_probe_bag(log, path, serial="SIM-11")


@pytest.fixture(scope="module")
def fault_runs(tmp_path_factory):
    """Two launchers at once, both reserving their own domain:

    A: a recorded bag (calibration + 24-station survey) replayed; right after the coefficients are
       published its recorder, its correction node and its calibration node are killed (SIGKILL),
       and a third launcher asks for A's domain;
    B: the calibration node runs but the probe has no calibration session (never solves).
    """
    pytest.importorskip("mcap_ros2")
    root = tmp_path_factory.mktemp("faults")
    bag = root / "input.mcap"
    _sim_bag(bag)
    env = _free_env()
    t0 = time.monotonic()
    # --no-loop: these runs check recovery and the summary's bag parts; the summary's model loop (the
    # lab on the recorded bag, seconds of CPU) is test_graph.py's subject
    # --speed 100: a ceiling (the replays are paced by their readers, whatever the machine); A's
    # kill follows its coefficients message, and the probe is then at most its window (10 s of the
    # log's 72 s of survey) ahead of the slowest reader: the survey is still replaying
    common = ("--timeout", 150, "--no-loop", "--speed", 100.0)
    a = Launch(env, "--out", root / "a", "--source", "mcap", "--input", bag, *common)
    b = Launch(env, "--out", root / "b", "--stations", 6, "--seed", 12,
               "--param", "probe:calibration_session:=false", "--param", "probe:rate_hz:=50.0", *common)
    try:
        a_domain = int(a.wait_for(r"^\[launch\] ROS_DOMAIN_ID=(\d+)", 30).group(1))
        refused = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", root / "c",
                                  "--domain-id", str(a_domain)], env=env, capture_output=True, text=True,
                                 timeout=60)
        pids = {n: int(a.wait_for(rf"^\[launch\] starting {n} \(pid (\d+)\)", 30).group(1))
                for n in ("recorder", "correction", "calibration")}
        a.wait_for(r"^\[calibration\].*published coefficients", 120)
        time.sleep(0.3)
        killed = time.monotonic()      # before the kills: a restart is due 6 s after each, so at least 6 s after this
        for pid in pids.values():
            os.kill(pid, signal.SIGKILL)
        rc_a, rc_b = a.finish(150), b.finish(150)
    finally:
        for run in (a, b):
            if run.proc.poll() is None:
                run.proc.kill()
    print(f"two launcher runs with faults, side by side: {time.monotonic() - t0:.1f} s")
    for name, run in (("A", a), ("B", b)):       # shown with a failure (captured output of the setup)
        print(f"---- launcher {name} ----\n{run.text}")
    restarted = {n: a.arrival(rf"^\[launch\] starting {n} \(") - killed for n in pids}
    return {"root": root, "bag": bag, "a": (rc_a, a.text), "b": (rc_b, b.text), "c": refused, "a_domain": a_domain,
            "restarted_after_s": restarted}


def test_killed_recorder_correction_and_calibration_are_restarted_and_nothing_is_lost(fault_runs):
    """The three nodes SIGKILLed at once mid-run: the recorder restarts into a new part (the probe's
    and the nodes' history give it what it missed), the calibration and correction nodes resume
    from the run's recording; every sample reaches every reader, every station is recorded once
    (no id repeated, none missing), and the run says it was not clean (nodes died)."""
    rc, text = fault_runs["a"]
    out = fault_runs["root"] / "a"
    assert rc == 1, text[-6000:]
    for name in ("recorder", "correction", "calibration"):
        assert f"[launch] {name} died unexpectedly (killed by SIGKILL)" in text
    assert "[launch] recorder died unexpectedly (killed by SIGKILL): restarting it into survey_1.mcap in 6 s, once " \
           "the graph has forgotten the process that died" in text
    # the graph on UDP over the loopback, not shared memory (launcher.loopback_profile: a node killed
    # while the probe writes to it could leave the probe's writer blocked, or its successor deaf)
    assert "[launch] the nodes talk over UDP on the loopback only, not shared memory" in text
    # each restarted once the graph forgot the dead one (its lease, 5 s: a successor matched before
    # could stay deaf)
    for name, after in fault_runs["restarted_after_s"].items():
        died, started = text.index(f"[launch] {name} died unexpectedly"), text.rindex(f"[launch] starting {name} (")
        assert died < started
        assert after >= 6.0, (name, after)
    for name in ("correction", "calibration"):
        assert re.search(rf"\[{name}\] \[WARN\].*resumed from the run's recording \(survey\.mcap", text), name
    last = text.strip().splitlines()[-1]
    assert last.startswith("[launch] exit status 1:") and "recorder died unexpectedly" in last
    assert "LOST" not in text and "lost" not in last and "missing" not in last
    summary = json.loads((out / "summary.json").read_text())
    first, second = summary["bag_parts"]
    assert first["file"] == "survey.mcap" and first["recovered_into"] == "survey.recovered.mcap"
    assert second["file"] == "survey_1.mcap"
    acc = summary["accounting"]
    assert acc["problems"] == [] and acc["stations"]["id_gaps"] == [] and acc["stations"]["conflicting_ids"] == []
    assert acc["stations"]["recorded"] == acc["stations"]["published"] == 36
    assert all("lost" not in r for r in acc["readers"].values()) and set(acc["readers"]) >= {
        "calibration", "correction", "recorder"}
    assert acc["restarts"] == {"recorder": 1, "correction": 1, "calibration": 1}
    assert summary["coefficient_messages"] == 1


def test_the_stations_of_a_run_whose_nodes_were_killed_are_reprocess_s_bit_for_bit(fault_runs, tmp_path):
    from inclinometer_calib.io.accounting import unique_stations
    from inclinometer_calib.apps.launcher import readable_parts
    from inclinometer_calib.io.bag import read_bag
    from inclinometer_calib.lab.field import FieldMonitor
    from inclinometer_calib.correct.reprocess import reprocess

    out = fault_runs["root"] / "a"
    live = []
    for part in readable_parts(str(out), print_fn=lambda *a: None):
        live += read_bag(part["read"])[0]
    live, _ = unique_stations(live)
    rep = reprocess(fault_runs["bag"], None, calibrate=True, monitor=FieldMonitor(window=30))
    assert len(live) == len(rep.stations) == 36
    for a, b in zip(live, rep.stations):
        for k in ("drift_deg", "azimuth_deg", "toolface_deg", "total_field_nt", "dip_deg", "measured_depth_m",
                  "north_m", "east_m", "tvd_m", "temperature_c"):
            assert a[k] == b[k] or (a[k] != a[k] and b[k] != b[k]), (a["station_id"], k, a[k], b[k])
        assert (a["station_id"], a["coefficients_id"], a["status"], a["model_misfit"]) == \
            (b["station_id"], b["coefficients_id"], b["status"], b["model_misfit"])


def test_a_calibration_that_never_solves_exits_1_and_two_runs_do_not_mix(fault_runs):
    rc, text = fault_runs["b"]
    out = fault_runs["root"] / "b"
    assert rc == 1, text[-6000:]
    last = text.strip().splitlines()[-1]
    assert last.startswith("[launch] exit status 1:") and "the calibration did not solve" in last
    assert "pending [" in last
    assert "calibration not solved: state " in text  # the summary line, with the node's last status
    b_domain = int(re.search(r"^\[launch\] ROS_DOMAIN_ID=(\d+)", text, flags=re.M).group(1))
    assert b_domain != fault_runs["a_domain"]
    # run A solved while B was recording: nothing of A's reached B's bag
    assert _bag_topics(out / "survey.mcap", ["/calibration/coefficients"]) == []
    assert not (out / "coeffs.yaml").exists()


def test_a_domain_held_by_another_run_is_refused(fault_runs):
    proc = fault_runs["c"]
    d = fault_runs["a_domain"]
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"ROS_DOMAIN_ID {d} is in use by another inclinometer_calib run" in proc.stderr
    assert "Give another --domain-id" in proc.stderr
    assert not (fault_runs["root"] / "c").exists()  # refused before touching anything


def test_a_damaged_input_bag_ends_the_launcher_with_status_1(ros_env, tmp_path):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu, MagneticField

    from inclinometer_calib.io import bag
    from inclinometer_calib.nodes import common as c

    src = tmp_path / "rec.mcap"
    w = bag.BagWriter(src, max_chunk_s=0.25, compression="none")
    ch_imu = w.add_topic(c.TOPIC_IMU, "sensor_msgs/msg/Imu")
    ch_mag = w.add_topic(c.TOPIC_MAG, "sensor_msgs/msg/MagneticField")
    for k in range(300):
        t = 1.0 + 0.01 * k
        mi, mm = Imu(), MagneticField()
        c.set_stamp(mi.header.stamp, t)
        mm.header.stamp = mi.header.stamp
        mi.linear_acceleration.z = -9.80665
        mm.magnetic_field.x, mm.magnetic_field.z = 35e-6, 35e-6
        w.write(ch_imu, serialize_message(mi), int(t * 1e9), int(t * 1e9))
        w.write(ch_mag, serialize_message(mm), int(t * 1e9), int(t * 1e9))
    w.close()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src.read_bytes()[:int(src.stat().st_size * 0.6)])
    proc = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", tmp_path / "run",
                           "--source", "mcap", "--input", cut, "--no-calibration", "--no-recorder",
                           "--speed", "20", "--drain", "0.5", "--timeout", "60"],
                          env=ros_env, capture_output=True, text=True, timeout=90)
    assert proc.returncode == 1, proc.stdout[-4000:]
    assert "[launch] probe finished (exit status 3): its input bag was damaged" in proc.stdout
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith("[launch] exit status 1:") and "input bag was damaged" in last

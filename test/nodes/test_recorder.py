"""The recorder node as a separate process: SIGINT finalizes, SIGKILL loses at most ~1 s.

A child publisher sends sensor_msgs/Imu at 200 Hz (best effort) and one transient-local
CalibrationCoefficients message published BEFORE the recorder starts. Skipped without rclpy.
"""
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

try:
    import rclpy  # noqa: F401
    from sensor_msgs.msg import Imu  # noqa: F401
except Exception as exc:  # ImportError or missing shared libraries
    pytest.skip(f"rclpy not importable ({exc!r}): run scripts/setup.sh and source scripts/env.sh",
                allow_module_level=True)

from mcap_ros2.reader import read_ros2_messages  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402

from inclinometer_calib.io import bag  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(13)

REPO = Path(__file__).resolve().parents[2]

PUBLISHER = textwrap.dedent("""
    import sys, rclpy
    from rclpy.node import Node
    from rclpy.qos import (QoSProfile, DurabilityPolicy, ReliabilityPolicy,
                           qos_profile_sensor_data)
    from sensor_msgs.msg import Imu
    from inclinometer_calib.msg import CalibrationCoefficients, CalibrationStatus
    rclpy.init()
    node = Node("test_publisher")
    latched = node.create_publisher(
        CalibrationCoefficients, "/calibration/coefficients",
        QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                   reliability=ReliabilityPolicy.RELIABLE))
    c = CalibrationCoefficients()
    c.id = "cal-42"
    c.probe_id = "P1"
    c.accel_offset = [0.1, 0.2, 0.3]
    c.poses_used = [1, 2, 3]
    latched.publish(c)
    status = node.create_publisher(CalibrationStatus, "/calibration/status", 10)
    imu = node.create_publisher(Imu, "/probe/imu", qos_profile_sensor_data)
    count = [0]
    def tick():
        m = Imu()
        m.header.frame_id = "probe"
        m.angular_velocity.z = float(count[0])
        count[0] += 1
        imu.publish(m)
        if count[0] % 200 == 0:
            s = CalibrationStatus(); s.state = "collecting"; status.publish(s)
    node.create_timer(1.0 / 200.0, tick)
    print("READY", flush=True)
    try:
        rclpy.spin(node)
    except BaseException:
        pass
""")


def _start_publisher(tmp_path, env, text=None):
    """A publisher process running ``text`` (default :data:`PUBLISHER`), once it says READY."""
    script = tmp_path / "publisher.py"
    script.write_text(PUBLISHER if text is None else text)
    proc = subprocess.Popen([sys.executable, str(script)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    line = proc.stdout.readline()
    if "READY" not in line:
        proc.kill()
        pytest.fail(f"publisher did not start: {line}{proc.stdout.read()}")
    return proc


def _start_recorder(tmp_path, env, output, *params):
    log = open(tmp_path / "recorder.log", "w+")
    args = [sys.executable, "-m", "inclinometer_calib.nodes.recorder", "--ros-args",
            "-p", f"output:={output}", *[x for p in params for x in ("-p", p)]]
    proc = subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT, text=True,
                            cwd=str(tmp_path))
    return proc, log


def _wait_log(log, needles, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        log.flush()
        text = Path(log.name).read_text()
        if all(n in text for n in needles):
            return text
        time.sleep(0.05)
    raise AssertionError(f"recorder log lacks {needles}:\n{Path(log.name).read_text()}")


def _stop(proc, sig=signal.SIGINT, timeout=10):
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


def test_record_sigint_finalizes_and_both_readers_decode(tmp_path, ros_env):
    pub = _start_publisher(tmp_path, ros_env)
    try:
        time.sleep(0.5)  # the latched message is published well before the recorder exists
        out = tmp_path / "survey.mcap"
        rec, log = _start_recorder(tmp_path, ros_env, out)
        try:
            _wait_log(log, ["recording /probe/imu", "recording /calibration/coefficients",
                            "recording /calibration/status"])
            time.sleep(2.0)
        finally:
            rc = _stop(rec)
        text = Path(log.name).read_text()
        assert rc == 0, text
        assert "finalized" in text and "/probe/imu:" in text
        assert "differs from the publisher" not in text  # installed hashes == live hashes
    finally:
        _stop(pub)

    rd = bag.open_bag(out)
    msgs = list(rd.messages())  # strict: raises if anything is wrong
    assert rd.finalized and rd.profile == "ros2"
    topics = rd.topics
    # every topic of the graph, the recorder's own progress (its place in the stream) among them
    assert set(topics) == {"/probe/imu", "/calibration/coefficients", "/calibration/status", "/graph/progress"}
    assert topics["/calibration/coefficients"].count == 1
    assert "durability: transient_local" in topics["/calibration/coefficients"].qos_yaml
    assert "reliability: best_effort" in topics["/probe/imu"].qos_yaml
    assert topics["/probe/imu"].type_hash == bag.type_hash("sensor_msgs/msg/Imu")
    n_imu = topics["/probe/imu"].count
    assert n_imu >= 300, n_imu  # >= 1.5 s at 200 Hz

    decoded = list(read_ros2_messages(str(out)))
    assert len(decoded) == len(msgs)
    coeff = [m for m in decoded if m.channel.topic == "/calibration/coefficients"]
    assert coeff[0].ros_msg.id == "cal-42" and list(coeff[0].ros_msg.accel_offset) == \
        [0.1, 0.2, 0.3]
    assert coeff[0].publish_time_ns < coeff[0].log_time_ns  # sent before the recorder ran
    z = [m.ros_msg.angular_velocity.z for m in decoded if m.channel.topic == "/probe/imu"]
    assert z == sorted(z)
    assert len(z) >= 0.9 * (z[-1] - z[0] + 1)  # (almost) no gaps over loopback

    with AnyReader([out]) as r:
        counts = {}
        for conn, _t, raw in r.messages():
            msg = r.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
        assert msg is not None
        assert counts["/probe/imu"] == n_imu and counts["/calibration/coefficients"] == 1


def test_sigkill_loses_at_most_one_chunk(tmp_path, ros_env):
    pub = _start_publisher(tmp_path, ros_env)
    try:
        out = tmp_path / "killed.mcap"
        rec, log = _start_recorder(tmp_path, ros_env, out, "max_chunk_s:=1.0",
                                   "topics:=[/probe/imu, /calibration/coefficients]")
        try:
            _wait_log(log, ["recording /probe/imu", "recording /calibration/coefficients"])
            time.sleep(3.3)
            killed_at = time.time_ns()
            rec.send_signal(signal.SIGKILL)
            rec.wait(timeout=10)
        finally:
            _stop(rec)
    finally:
        _stop(pub)

    with pytest.raises(bag.BagError, match="not finalized"):
        list(bag.open_bag(out).messages())
    fixed = tmp_path / "fixed.mcap"
    report = bag.recover(out, fixed)
    assert report.saved > 0
    decoded = list(read_ros2_messages(str(fixed)))
    assert len(decoded) == report.saved
    imu = [m for m in decoded if m.channel.topic == "/probe/imu"]
    assert any(m.channel.topic == "/calibration/coefficients" for m in decoded)
    assert "/calibration/status" not in {m.channel.topic for m in decoded}
    lost_s = (killed_at - imu[-1].log_time_ns) / 1e9
    print(f"SIGKILL: {report.saved} messages recovered, last IMU message "
          f"{lost_s:.3f} s before the kill")
    assert lost_s <= 1.25, lost_s  # max_chunk_s = 1.0 (+ scheduling slack)
    first_s = (imu[-1].log_time_ns - imu[0].log_time_ns) / 1e9
    assert first_s >= 1.5  # the earlier chunks are all there
    with AnyReader([fixed]) as r:
        assert sum(1 for _ in r.messages()) == report.saved


def test_refuses_existing_output_and_skips_unimportable_types(tmp_path, ros_env):
    existing = tmp_path / "exists.mcap"
    existing.write_bytes(b"precious")
    rec, log = _start_recorder(tmp_path, ros_env, existing)
    assert rec.wait(timeout=15) == 1
    assert existing.read_bytes() == b"precious"
    assert "already exists" in Path(log.name).read_text()

    # a recorder that cannot import inclinometer_calib.msg (no install tree on its path)
    env = dict(ros_env)
    env["PYTHONPATH"] = str(REPO)
    pub = _start_publisher(tmp_path, ros_env)
    try:
        out = tmp_path / "partial.mcap"
        rec, log = _start_recorder(tmp_path, env, out)
        try:
            text = _wait_log(log, ["recording /probe/imu",
                                   "not recording /calibration/coefficients"])
            time.sleep(0.5)
        finally:
            assert _stop(rec) == 0
    finally:
        _stop(pub)
    text = Path(log.name).read_text()
    assert "inclinometer_calib/msg/CalibrationCoefficients is not importable" in text
    assert "not recorded:" in text  # listed again in the shutdown summary
    assert set(bag.open_bag(out).topics) == {"/probe/imu"}


def test_type_hashes_match_rclpy(ros_env):
    """Hashes from the installed .json files == what rclpy reports for live publishers."""
    import rclpy
    from rclpy.node import Node
    from inclinometer_calib.msg import SurveyStation

    rclpy.init()
    try:
        node = Node("hash_probe")
        node.create_publisher(Imu, "/hash/imu", 1)
        node.create_publisher(SurveyStation, "/hash/station", 1)
        seen = {}
        deadline = time.monotonic() + 5
        while len(seen) < 2 and time.monotonic() < deadline:
            for topic in ("/hash/imu", "/hash/station"):
                for info in node.get_publishers_info_by_topic(topic):
                    seen[topic] = str(info.topic_type_hash)
            time.sleep(0.05)
        assert seen["/hash/imu"] == bag.type_hash("sensor_msgs/msg/Imu")
        assert seen["/hash/station"] == bag.type_hash("inclinometer_calib/msg/SurveyStation")
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_a_restarted_recorder_counts_the_stations_its_predecessors_recorded(tmp_path):
    """The run's recording is every part: a recorder restarted into survey_2.mcap counts, by id, the
    stations of survey.mcap and survey_1.mcap (the paced probe's end waits until the recording holds
    every station published; counting its own part alone it waited the whole flow.end_timeout_s)."""
    from rclpy.serialization import serialize_message

    from inclinometer_calib.msg import SurveyStation
    from inclinometer_calib.nodes.recorder import _recorded_station_ids
    from inclinometer_calib.io.topics import STATION_TYPE, TOPIC_STATION

    def part(name, ids, finalize=True):
        w = bag.BagWriter(tmp_path / name)
        cid = w.add_topic(TOPIC_STATION, STATION_TYPE, qos_profiles=[dict(bag.DEFAULT_QOS_PROFILE, depth=100)])
        for i in ids:
            w.write(cid, serialize_message(SurveyStation(station_id=i)), i * 1000, i * 1000)
        if finalize:
            w.close()
        else:
            w.flush()   # a killed recorder: its flushed chunks readable, never finalized

    part("survey.mcap", [0, 1, 2, 3])
    part("survey_1.mcap", [3, 4, 5], finalize=False)
    assert _recorded_station_ids(tmp_path / "survey_2.mcap", SurveyStation) == {0, 1, 2, 3, 4, 5}
    assert _recorded_station_ids(tmp_path / "survey_1.mcap", SurveyStation) == {0, 1, 2, 3}
    assert _recorded_station_ids(tmp_path / "survey.mcap", SurveyStation) == set()
    assert _recorded_station_ids(tmp_path / "elsewhere.mcap", SurveyStation) == set()

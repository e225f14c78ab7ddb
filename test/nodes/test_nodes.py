"""Fast node-level tests (in-process rclpy, own ROS_DOMAIN_ID): parameter validation, services,
message conventions, stream pairing, the probe publishing what it says (and waiting for every
reader it expects; covariances measured from a replayed log), timers on steady time."""
import math
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

from rclpy.exceptions import InvalidParameterValueException  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from inclinometer_calib.core.station import Station
from inclinometer_calib.calibrate import simulate as sim  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.core.frames import Site  # noqa: E402
from inclinometer_calib.nodes import common as c  # noqa: E402
from inclinometer_calib.nodes.calibration import CalibrationNode  # noqa: E402
from inclinometer_calib.nodes.correction import CorrectionNode  # noqa: E402
from inclinometer_calib.nodes.probe import ProbeNode  # noqa: E402
from inclinometer_calib.io.probelog import ProbeLog  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(15)


@pytest.fixture
def spinning(ros):
    """Start an executor thread spinning the given nodes; returns a function adding nodes."""
    ex = SingleThreadedExecutor()
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)

    def add(node):
        ros.append(node)
        ex.add_node(node)
        if not th.is_alive():
            th.start()
        return node

    yield add
    stop.set()
    th.join(2.0)
    ex.shutdown()


def _truth_calibration(seed=3):
    probe = sim.build_probe(seed)
    return Calibration(acc=probe.acc, mag=probe.mag, probe_id="t", site=Site())


# ---- parameters --------------------------------------------------------------------------
def test_bad_parameter_values_are_rejected(ros, tmp_path):
    node = CorrectionNode()
    ros.append(node)
    res = node.set_parameters([Parameter("tolerances.field_nt", value=-5.0)])[0]
    assert not res.successful and "out of range" in res.reason.lower()
    res = node.set_parameters([Parameter("coeffs_file", value=str(tmp_path / "missing.yaml"))])[0]
    assert not res.successful and "cannot use" in res.reason
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: something-else\n")
    res = node.set_parameters([Parameter("coeffs_file", value=str(bad))])[0]
    assert not res.successful and "format" in res.reason
    res = node.set_parameters([Parameter("site.dip_deg", value=10.0)])[0]
    assert not res.successful and "read-only" in res.reason
    res = node.set_parameters([Parameter("tolerances.field_nt", value=500)])[0]  # int for a double
    assert not res.successful and "type" in res.reason.lower()
    # a good value is accepted and applied
    good = tmp_path / "good.yaml"
    cal = _truth_calibration()
    cal.save(good)
    assert node.set_parameters([Parameter("coeffs_file", value=str(good))])[0].successful
    assert node.calibration.id == cal.id
    assert node.set_parameters([Parameter("tolerances.field_nt", value=500.0)])[0].successful


def test_bad_start_up_parameters_stop_the_node(ros):
    with pytest.raises(InvalidParameterValueException, match="not allowed"):
        ProbeNode(parameter_overrides=[Parameter("source", value="bogus")])
    with pytest.raises(InvalidParameterValueException, match="unknown effect"):
        ProbeNode(parameter_overrides=[Parameter("effects", value=["no_such_effect=1"])])
    with pytest.raises(InvalidParameterValueException, match="one of"):
        CalibrationNode(parameter_overrides=[Parameter("qos.reliability", value="sometimes")])
    with pytest.raises(InvalidParameterValueException):
        CalibrationNode(parameter_overrides=[Parameter("site.gravity_mps2", value=1.0)])


def test_probe_speed_can_change_while_running(ros):
    node = ProbeNode(parameter_overrides=[Parameter("survey", value="none"),
                                          Parameter("effects", value=["axial_interference=300"])])
    ros.append(node)
    assert node.effects == ["axial_interference=300"]
    assert node.set_parameters([Parameter("speed", value=20.0)])[0].successful
    assert node.speed == 20.0
    assert not node.set_parameters([Parameter("speed", value=0.0)])[0].successful
    assert not node.set_parameters([Parameter("rate_hz", value=50.0)])[0].successful  # read-only


# ---- services ----------------------------------------------------------------------------
def _call(node, client, request, timeout=10.0):
    assert client.wait_for_service(timeout_sec=timeout)
    fut = client.call_async(request)
    end = time.monotonic() + timeout
    while not fut.done() and time.monotonic() < end:
        time.sleep(0.01)
    assert fut.done(), "service call timed out"
    return fut.result()


def test_recapture_and_reset_services(spinning):
    from std_srvs.srv import Trigger

    from inclinometer_calib.msg import CalibrationStatus
    from inclinometer_calib.srv import RecapturePose

    cal_node = spinning(CalibrationNode())
    client_node = spinning(rclpy.create_node("test_client"))
    statuses = []
    client_node.create_subscription(CalibrationStatus, c.TOPIC_STATUS, statuses.append, c.reliable_qos(10))
    recapture = client_node.create_client(RecapturePose, "/calibration/recapture")
    reset = client_node.create_client(Trigger, "/calibration/reset")

    # feed two simulated poses straight into the node's sample path (no DDS needed for that)
    probe = sim.build_probe(5)
    log = sim.run_session(probe, Site(), sim.twelve_pose_session(duration_s=2.0)[:2],
                          np.random.default_rng(1), rate_hz=100.0)
    for t, g, m in zip(log.t_s, log.gravity, log.mag):
        cal_node.stream.feed(float(t), tuple(g), tuple(m))
    cal_node.stream.close_hold()
    assert cal_node.session.captured == [1, 2]

    res = _call(client_node, recapture, RecapturePose.Request(pose=13))
    assert not res.success and "out of range" in res.message
    res = _call(client_node, recapture, RecapturePose.Request(pose=2))  # Table 1 numbering
    assert res.success, res.message
    assert cal_node.session.recapture == {2}
    end = time.monotonic() + 5
    while time.monotonic() < end and not any(list(s.pending)[:2] == [2, 3] for s in statuses):
        time.sleep(0.05)
    last = statuses[-1]
    assert list(last.captured) == [1] and list(last.pending)[:2] == [2, 3] and last.total_poses == 12

    res = _call(client_node, reset, Trigger.Request())
    assert res.success
    assert cal_node.session.captured == [] and cal_node.session.state == "collecting"


# ---- conversions -------------------------------------------------------------------------
def test_coefficient_message_conventions():
    from inclinometer_calib.msg import CalibrationCoefficients

    cal = _truth_calibration()
    msg = c.coefficients_to_msg(cal, CalibrationCoefficients)
    assert Calibration.from_yaml(msg.coefficients_yaml).id == msg.id == cal.id
    rng = np.random.default_rng(0)
    g_raw, b_raw = rng.normal(0, 5, 3), rng.normal(0, 3e4, 3)
    g_c, b_c = cal.correct(g_raw, b_raw)
    f_c = np.reshape(msg.accel_correction_matrix, (3, 3)) @ (-g_raw - np.asarray(msg.accel_offset))
    assert np.allclose(f_c, -g_c, atol=1e-12)
    b_m = np.reshape(msg.mag_correction_matrix, (3, 3)) @ (b_raw - np.asarray(msg.mag_offset))
    assert np.allclose(b_m, b_c, atol=1e-6)
    names = list(msg.accel_parameter_names)
    assert msg.accel_parameter_values[names.index("bias_x")] == -cal.acc.bias[0]  # REP-145 sign
    assert msg.accel_parameter_units[names.index("bias_x")] == "m/s^2"
    # the node's per-stream correction is the same path, to the bit
    assert np.array_equal(cal.plan.correct_triad("acc", g_raw), g_c)
    assert np.array_equal(cal.plan.correct_triad("mag", b_raw), b_c)
    assert msg.site_source == cal.site_source and msg.site_dip_deg == cal.site.dip_deg


def test_stream_pairer_pairs_by_stamp_in_order():
    from inclinometer_calib.detect.streaming import StreamPairer

    p = StreamPairer(max_pending=4)
    assert p.add_imu((1, 0), "f1") is None
    assert p.add_imu((2, 0), "f2") is None
    assert p.add_mag((2, 0), "m2") == (2.0, "f2", "m2")
    assert p.add_mag((1, 0), "m1") is None and p.out_of_order == 1  # older than the last pair
    assert p.add_mag((3, 500_000_000), "m3") is None
    assert p.add_imu((3, 500_000_000), "f3") == (3.5, "f3", "m3")
    for k in range(10):
        p.add_imu((10 + k, 0), k)
    assert len(p._imu) <= 4 and p.unpaired >= 6


def test_stamp_round_trip():
    from builtin_interfaces.msg import Time

    for t in (0.0, 1.0, 12.3456789, 1e9 + 0.999999999):
        s = Time()
        c.set_stamp(s, t)
        assert 0 <= s.nanosec < 1_000_000_000
        assert math.isclose(c.stamp_to_sec(s), t, abs_tol=2e-9)


# ---- the probe's messages over DDS ---------------------------------------------------------
def test_probe_publishes_rep145_tesla_and_shared_stamps(spinning):
    from sensor_msgs.msg import Imu, MagneticField, Temperature

    got = {"imu": [], "mag": [], "temp": []}
    sub = spinning(rclpy.create_node("test_sub"))
    # reliable, and histories deeper than the script's 3 500 samples: a writer never drops a sample
    # its reader has not acknowledged, however far this process's executor falls behind (with 1 000,
    # a machine at its slowest lost 78 of them: the verdict then depended on timing)
    qos = c.sensor_qos(10000, "reliable")
    sub.create_subscription(Imu, c.TOPIC_IMU, got["imu"].append, qos)
    sub.create_subscription(MagneticField, c.TOPIC_MAG, got["mag"].append, qos)
    sub.create_subscription(Temperature, c.TOPIC_TEMPERATURE, got["temp"].append, qos)
    # pieces of 700 samples (the script is simulated piece by piece while it is published)
    probe = spinning(ProbeNode(parameter_overrides=[
        Parameter("survey", value="none"), Parameter("speed", value=10.0), Parameter("chunk_samples", value=700),
        Parameter("wait_for_subscribers", value=1), Parameter("start_delay_s", value=0.2),
        Parameter("qos.reliability", value="reliable"), Parameter("qos.depth", value=10000)]))
    # the same script simulated whole: the probe node's defaults (seed 7, its generator seed + 1)
    log = sim.run_session(sim.build_probe(7), Site(), sim.twelve_pose_session([25.0], duration_s=2.0),
                          np.random.default_rng(8), rate_hz=100.0, move_s=1.0)
    end = time.monotonic() + 30
    while not probe.done.done() and time.monotonic() < end:
        time.sleep(0.05)
    assert probe.done.done(), "probe did not finish"
    n = len(log)
    assert probe.script.n == n > 3 * 700
    end = time.monotonic() + 60          # (the wait ends when all are in: a minute only on a starved machine)
    while time.monotonic() < end and min(len(v) for v in got.values()) < n:
        time.sleep(0.05)
    assert len(got["imu"]) == n and len(got["mag"]) == n and len(got["temp"]) == n
    imu, mag, temp = got["imu"][50], got["mag"][50], got["temp"][50]
    assert (imu.header.stamp.sec, imu.header.stamp.nanosec) == (mag.header.stamp.sec, mag.header.stamp.nanosec) \
        == (temp.header.stamp.sec, temp.header.stamp.nanosec)
    assert math.isclose(c.stamp_to_sec(imu.header.stamp), log.t_s[50], abs_tol=1e-9)
    a = np.array([imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z])
    assert 9.0 < np.linalg.norm(a) < 10.6
    # every sample, across the pieces, is the whole simulation's (REP-145: a resting probe reads -g; tesla)
    acc = np.array([(m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z) for m in got["imu"]])
    field = np.array([(m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z) for m in got["mag"]])
    np.testing.assert_array_equal(acc, log.acc)
    np.testing.assert_array_equal(field, log.mag / c.NT_PER_TESLA)
    np.testing.assert_array_equal([m.temperature for m in got["temp"]], log.temp_c)
    assert all(math.isclose(c.stamp_to_sec(m.header.stamp), t, abs_tol=1e-9) for m, t in zip(got["imu"], log.t_s))
    b = np.array([mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z])
    assert 3e-5 < np.linalg.norm(b) < 7e-5  # tesla
    assert imu.orientation_covariance[0] == -1.0
    assert math.isclose(imu.linear_acceleration_covariance[0], 0.002 ** 2)
    assert math.isclose(mag.magnetic_field_covariance[4], (20e-9) ** 2)


def _whole_probe_script(n_well, rate_hz):
    """The probe node's default script (seed 7, its generator seed + 1) simulated whole."""
    probe, rng = sim.build_probe(7), np.random.default_rng(8)
    stations = sim.twelve_pose_session([25.0], duration_s=2.0)
    cal = sim.run_session(probe, Site(), stations, rng, rate_hz=rate_hz)
    well = sim.run_session(probe, Site(), sim.well_path_session(n_well, duration_s=2.0, seed=7), rng,
                           rate_hz=rate_hz, t0=cal.t_s[-1] + 1.0 / rate_hz, survey=True,
                           lead_in=(stations[-1].rotation, 2.0))
    return ProbeLog.concatenate([cal, well])


def test_probe_truth_names_the_stations_of_the_whole_script(ros, tmp_path):
    import json

    from inclinometer_calib.io.probelog import label_runs

    node = ProbeNode(parameter_overrides=[Parameter("well.n_stations", value=4), Parameter("rate_hz", value=50.0),
                                          Parameter("chunk_samples", value=300),
                                          Parameter("truth_file", value=str(tmp_path / "truth.json"))])
    ros.append(node)
    truth = json.loads((tmp_path / "truth.json").read_text())
    log = _whole_probe_script(n_well=4, rate_hz=50.0)
    want = [{"pose": int(pose), "ref": [None if not math.isfinite(x) else float(x) for x in ref],
             "t_start": float(log.t_s[i0]), "t_end": float(log.t_s[i1])} for i0, i1, pose, ref in label_runs(log)]
    assert len(want) == 16 and truth["stations"] == want and truth["samples"] == len(log)


@pytest.mark.parametrize("chunk", [1, 97, 100000])
def test_probe_pieces_announce_the_reference_and_depth_changes_of_the_whole_script(ros, chunk):
    """Across piece boundaries the probe announces the same reference changes and depth changes
    (held or running: whether the next sample has the same depth) as over the whole log."""
    node = ProbeNode(parameter_overrides=[Parameter("survey", value="well_path"),
                                          Parameter("well.n_stations", value=3), Parameter("chunk_samples", value=chunk),
                                          Parameter("rate_hz", value=50.0)])
    ros.append(node)
    refs, depths, t = list(node._ref_changes), list(node._depth_changes), list(node._t)
    while node._load_piece():
        refs += node._ref_changes
        depths += node._depth_changes
        t += node._t
    assert node._base + len(node._t) == node.script.n == len(t)
    log = _whole_probe_script(n_well=3, rate_hz=50.0)
    assert t == log.t_s.tolist()

    def changes(rows):
        out, prev = [], None
        for i, row in enumerate(rows):
            key = tuple(None if not math.isfinite(x) else x for x in row)
            if key != prev:
                out.append((i, tuple(row)))
                prev = key
        return out[1:] if out and not any(map(math.isfinite, out[0][1])) else out

    want_refs = changes(log.ref.tolist())
    assert len(want_refs) >= 5 and [(k, str(v)) for k, v in refs] == [(k, str(v)) for k, v in want_refs]
    md = changes(log.md_m[:, None].tolist())
    want_depths = [(k, v, j + 1 >= len(md) or md[j + 1][0] - k >= 2) for j, (k, v) in enumerate(md)]
    assert len(want_depths) > 3 and any(h for *_, h in want_depths) and not all(h for *_, h in want_depths)
    assert [(k, str(v), h) for k, v, h in depths] == [(k, str(v), h) for k, v, h in want_depths]


def test_probe_waits_for_temperature_and_reference_subscribers_too(spinning):
    from geometry_msgs.msg import Vector3Stamped
    from sensor_msgs.msg import Imu, MagneticField, Temperature

    probe = spinning(ProbeNode(parameter_overrides=[
        Parameter("survey", value="none"), Parameter("speed", value=10.0), Parameter("start_delay_s", value=0.0),
        Parameter("wait_for_subscribers", value=1), Parameter("wait_for_reference_subscribers", value=1)]))
    sub = spinning(rclpy.create_node("test_sub"))
    qos = c.sensor_qos(10)
    sub.create_subscription(Imu, c.TOPIC_IMU, lambda m: None, qos)
    sub.create_subscription(MagneticField, c.TOPIC_MAG, lambda m: None, qos)

    def settle(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end and probe._state == "waiting":
            time.sleep(0.05)

    settle(1.5)  # imu and mag have their reader, the temperature and reference have none yet
    assert probe._state == "waiting"
    missing = probe._missing_subscribers()
    assert missing == [f"{c.TOPIC_TEMPERATURE} (0/1)", f"{c.TOPIC_REFERENCE} (0/1)"], missing
    sub.create_subscription(Temperature, c.TOPIC_TEMPERATURE, lambda m: None, qos)
    settle(1.5)
    assert probe._state == "waiting" and probe._missing_subscribers() == [f"{c.TOPIC_REFERENCE} (0/1)"]
    sub.create_subscription(Vector3Stamped, c.TOPIC_REFERENCE, lambda m: None, c.reliable_qos(10))
    settle(5.0)
    assert probe._state != "waiting"


def test_probe_waits_for_a_recorder_of_the_stations_before_its_first_sample(spinning):
    # /survey/station is reliable but volatile: a recorder subscribing after the first station misses it
    from inclinometer_calib.msg import SurveyStation

    probe = spinning(ProbeNode(parameter_overrides=[
        Parameter("survey", value="none"), Parameter("speed", value=10.0), Parameter("start_delay_s", value=0.0),
        Parameter("wait_for_topic_subscribers", value=[f"{c.TOPIC_STATION}=1"])]))
    sub = spinning(rclpy.create_node("test_station_reader"))
    end = time.monotonic() + 1.5
    while time.monotonic() < end:
        time.sleep(0.05)
    assert probe._state == "waiting" and probe._missing_subscribers() == [f"{c.TOPIC_STATION} (0/1)"]
    sub.create_subscription(SurveyStation, c.TOPIC_STATION, lambda m: None, c.reliable_qos(10))
    end = time.monotonic() + 5.0
    while time.monotonic() < end and probe._state == "waiting":
        time.sleep(0.05)
    assert probe._state != "waiting"
    with pytest.raises(InvalidParameterValueException, match="is not TOPIC=N"):
        ProbeNode(parameter_overrides=[Parameter("wait_for_topic_subscribers", value=["survey"])])


def _noisy_log(noise_acc, noise_mag, seed=2):
    """A simulated four-station stand log with the given white noise (m/s^2, nT per sample)."""
    probe = sim.build_probe(seed, noise_acc=noise_acc, noise_mag=noise_mag)
    refs = [(30.0, 60.0, 0.0), (40.0, 120.0, 0.0), (50.0, 200.0, 120.0), (20.0, 300.0, 240.0)]
    stations = [Station.planned(sim.orientation_matrix(*r), 3.0, ref=r) for r in refs]
    return sim.run_session(probe, Site(), stations, np.random.default_rng(seed), rate_hz=100.0, move_s=1.0,
                           survey=True)


def _diag(cov):
    return np.array([cov[0], cov[4], cov[8]])


def test_probe_replaying_a_csv_log_publishes_the_noise_measured_from_it(ros, tmp_path):
    from inclinometer_calib.io.probelog import write_csv

    path = tmp_path / "log.csv"
    write_csv(path, _noisy_log(0.005, 50.0))  # 2.5x the defaults
    node = ProbeNode(parameter_overrides=[Parameter("source", value="csv"), Parameter("path", value=str(path))])
    ros.append(node)
    acc, mag = np.sqrt(_diag(node.m_imu.linear_acceleration_covariance)), np.sqrt(_diag(node.m_mag.magnetic_field_covariance))
    assert np.allclose(acc, 0.005, rtol=0.15), acc
    assert np.allclose(mag, 50e-9, rtol=0.15), mag  # tesla
    # a noise parameter > 0 overrides the data for its sensor only
    node2 = ProbeNode(parameter_overrides=[Parameter("source", value="csv"), Parameter("path", value=str(path)),
                                           Parameter("noise_acc", value=0.01)])
    ros.append(node2)
    assert np.allclose(_diag(node2.m_imu.linear_acceleration_covariance), 1e-4)
    assert np.allclose(np.sqrt(_diag(node2.m_mag.magnetic_field_covariance)), 50e-9, rtol=0.15)


def test_probe_replaying_a_bag_keeps_its_recorded_covariance_and_measures_a_missing_one(ros, tmp_path):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu, MagneticField

    from inclinometer_calib.io import bag

    log = _noisy_log(0.004, 40.0)
    path = tmp_path / "rec.mcap"
    w = bag.BagWriter(path, compression="none")
    ch_imu = w.add_topic(c.TOPIC_IMU, "sensor_msgs/msg/Imu")
    ch_mag = w.add_topic(c.TOPIC_MAG, "sensor_msgs/msg/MagneticField")
    recorded = [1e-6, 0.0, 0.0, 0.0, 4e-6, 0.0, 0.0, 0.0, 9e-6]
    mi, mm = Imu(), MagneticField()
    mi.linear_acceleration_covariance = recorded  # the magnetometer's stays all zero: unknown
    for t, f, m in zip(log.t_s.tolist(), log.acc.tolist(), log.mag.tolist()):
        c.set_stamp(mi.header.stamp, t)
        mm.header.stamp = mi.header.stamp
        mi.linear_acceleration.x, mi.linear_acceleration.y, mi.linear_acceleration.z = f
        mm.magnetic_field.x, mm.magnetic_field.y, mm.magnetic_field.z = (x * 1e-9 for x in m)
        w.write(ch_imu, serialize_message(mi), int(t * 1e9) + 1, int(t * 1e9))
        w.write(ch_mag, serialize_message(mm), int(t * 1e9) + 1, int(t * 1e9))
    w.close()
    node = ProbeNode(parameter_overrides=[Parameter("source", value="mcap"), Parameter("path", value=str(path))])
    ros.append(node)
    assert list(node.m_imu.linear_acceleration_covariance) == recorded
    assert np.allclose(np.sqrt(_diag(node.m_mag.magnetic_field_covariance)), 40e-9, rtol=0.15)


def test_periodic_work_runs_on_steady_time_when_the_sim_clock_stops(spinning, tmp_path):
    """use_sim_time and a /clock that never ticks (the probe has stopped): the correction node's
    1 Hz timer runs on steady time, so its idle flush still closes the last station."""
    from inclinometer_calib.msg import SurveyStation

    path = tmp_path / "coeffs.yaml"
    _truth_calibration().save(path)
    node = spinning(CorrectionNode(parameter_overrides=[Parameter("use_sim_time", value=True),
                                                        Parameter("coeffs_file", value=str(path))]))
    stations = []
    sub = spinning(rclpy.create_node("test_sub"))
    sub.create_subscription(SurveyStation, c.TOPIC_STATION, stations.append, c.reliable_qos(10))
    log = _noisy_log(0.002, 20.0)
    for t, g, m in zip(log.t_s.tolist(), log.gravity.tolist(), log.mag.tolist()):
        node.stream.feed(t, tuple(g), tuple(m))
    assert node.get_clock().ros_time_is_active and node.get_clock().now().nanoseconds == 0  # no /clock
    end = time.monotonic() + 6.0
    while time.monotonic() < end and len(stations) < 4:
        time.sleep(0.05)
    assert len(stations) == 4, "the last station must be closed by the idle flush (a steady-clock timer)"
    assert math.isclose(c.stamp_to_sec(stations[-1].header.stamp), log.t_s[-1], abs_tol=1e-6)


def test_the_noise_the_messages_state_is_a_prior_the_data_overrule_and_the_node_says_so(ros, capfd):
    # a probe driver stating 0.002 m/s² / 20 nT for a probe 2.5× noisier: every hold is still one
    # station, and the node warns that the stated noise is not what the data show
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu, MagneticField

    log = _noisy_log(0.005, 50.0)
    node = CalibrationNode()
    ros.append(node)
    mi, mm = Imu(), MagneticField()
    mi.linear_acceleration_covariance = [0.002 ** 2, 0.0, 0.0, 0.0, 0.002 ** 2, 0.0, 0.0, 0.0, 0.002 ** 2]
    mm.magnetic_field_covariance = [(20e-9) ** 2, 0.0, 0.0, 0.0, (20e-9) ** 2, 0.0, 0.0, 0.0, (20e-9) ** 2]
    for t, f, m in zip(log.t_s.tolist(), log.acc.tolist(), log.mag.tolist()):
        c.set_stamp(mi.header.stamp, t)
        mm.header.stamp = mi.header.stamp
        mi.linear_acceleration.x, mi.linear_acceleration.y, mi.linear_acceleration.z = f
        mm.magnetic_field.x, mm.magnetic_field.y, mm.magnetic_field.z = (x * 1e-9 for x in m)
        node.stream._on_imu(serialize_message(mi), None)
        node.stream._on_mag(serialize_message(mm))
    assert node.detector.noise.prior == pytest.approx((0.002, 20.0))
    lvl = node.detector.noise_level
    assert lvl.acc_source == "data" and np.allclose(lvl.acc, 0.005, rtol=0.15)
    err = capfd.readouterr().err
    assert "[WARN]" in err and "the messages state a noise of 0.002 m/s^2" in err and "using the data" in err
    assert "magnetometer: the messages state a noise of 20 nT" in err


def test_the_calibration_node_fits_the_model_it_is_told_and_says_what_the_captures_cannot_identify(spinning):
    """``model.effects``: the twelve poses at 25 and 45 °C fit a magnetometer temperature bias
    (published latched, in the record); the accelerometer's, asked too, is named as not
    identifiable only if the captures cannot tell it (here they can: both rounds differ by 20 °C),
    and without a site the record's site is the stand's measured one, said at WARNING."""
    from inclinometer_calib.msg import CalibrationCoefficients

    node = spinning(CalibrationNode(parameter_overrides=[Parameter("model.effects", value="temperature_bias:mag")]))
    probe = sim.build_probe(6, ["temperature_bias:mag=3"])
    log = sim.run_session(probe, Site(), sim.twelve_pose_session(rounds_temp_c=(25.0, 45.0), duration_s=2.0),
                          np.random.default_rng(2), rate_hz=50.0)
    got = []
    listener = spinning(rclpy.create_node("test_listener"))
    _feed_to_the_end(node, log)
    cal = node.session.calibration
    assert cal is not None and cal.model.labels() == ["temperature_bias:mag:xyz"]
    est = cal.model.extra_terms[0].effect.values["c"]
    np.testing.assert_allclose(est, 3.0, atol=0.1)
    assert cal.site_source == "measured" and cal.not_identifiable == []
    # latched: a late subscriber gets the record, with the model named in the message
    listener.create_subscription(CalibrationCoefficients, c.TOPIC_COEFFICIENTS, got.append, c.latched_qos())
    end = time.monotonic() + 5
    while time.monotonic() < end and not got:
        time.sleep(0.05)
    assert got and got[-1].id == cal.id and "temperature_bias:mag:xyz" in list(got[-1].mag_model_effects)
    assert got[-1].site_source == "measured"


def _feed_to_the_end(node, log):
    """A log's samples and temperatures into the calibration node, then the end of the data (as
    the idle timer does it)."""
    for t, g, m, tc in zip(log.t_s, log.gravity, log.mag, log.temp_c):
        node.engine.temperature(float(t), float(tc))   # what the driver's /probe/temperature callback does
        node.stream.feed(float(t), tuple(g), tuple(m))
    node.stream.idle()


def test_a_model_the_captures_cannot_identify_is_said(spinning):
    node = spinning(CalibrationNode(parameter_overrides=[Parameter("model.effects", value="temperature_bias:mag")]))
    probe = sim.build_probe(6)
    log = sim.run_session(probe, Site(), sim.twelve_pose_session(duration_s=2.0), np.random.default_rng(2),
                          rate_hz=50.0)
    _feed_to_the_end(node, log)
    cal = node.session.calibration
    assert [x["parameter"] for x in cal.not_identifiable] == ["temperature_bias:mag:xyz"]
    assert "temperature span 0.0 °C is too small" in cal.not_identifiable[0]["reason"]
    assert any("not identifiable from these captures" in w for w in node.session.warnings)


def test_a_bad_model_is_refused_at_start_up(ros):
    with pytest.raises(InvalidParameterValueException, match="unknown effect"):
        CalibrationNode(parameter_overrides=[Parameter("model.effects", value="no_such_effect")])


def test_the_probes_serial_from_a_bag_is_published_and_a_contradicting_parameter_refused(ros, tmp_path):
    from std_msgs.msg import String

    from inclinometer_calib.correct.reprocess import write_probe_bag

    path = tmp_path / "sn.mcap"
    write_probe_bag(_noisy_log(0.002, 20.0), path, serial="SN-77")
    node = ProbeNode(parameter_overrides=[Parameter("source", value="mcap"), Parameter("path", value=str(path))])
    ros.append(node)
    got = []
    sub_node = rclpy.create_node("serial_listener")
    ros.append(sub_node)
    sub_node.create_subscription(String, c.TOPIC_SERIAL, lambda m: got.append(m.data), c.latched_qos())
    t0 = time.monotonic()
    while not got and time.monotonic() - t0 < 10:
        rclpy.spin_once(sub_node, timeout_sec=0.1)
    assert got == ["SN-77"]                       # latched: a late subscriber gets it
    with pytest.raises(ValueError, match="contradicts"):
        ProbeNode(parameter_overrides=[Parameter("source", value="mcap"), Parameter("path", value=str(path)),
                                       Parameter("probe_serial", value="SN-78")])


def test_the_correction_node_refuses_another_probes_record_and_says_so(spinning, tmp_path):
    from std_msgs.msg import String

    cal = _truth_calibration()
    cal.probe_id = "SN-2"
    path = tmp_path / "c.yaml"
    cal.save(path)
    node = spinning(CorrectionNode(parameter_overrides=[Parameter("coeffs_file", value=str(path))]))
    assert node.calibration is not None and node.calibration.probe_id == "SN-2"
    pub_node = spinning(rclpy.create_node("serial_publisher"))
    pub = pub_node.create_publisher(String, c.TOPIC_SERIAL, c.latched_qos())
    pub.publish(String(data="SN-1"))
    t0 = time.monotonic()
    while not node.engine.refusal and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    assert node.processor.probe_serial == "SN-1"
    assert node.calibration is None and "probe SN-2, the data are of probe SN-1" in node.engine.refusal
    # a record of the right probe is applied again
    node._apply(Calibration(acc=cal.acc, mag=cal.mag, probe_id="SN-1", site=Site()), "test")
    assert node.calibration is not None and node.engine.refusal == ""

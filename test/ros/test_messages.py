"""ROS 2 interface tests: the generated messages/service import, serialize, and go over DDS.

Skipped (not failed) when rclpy cannot be imported, so the numerical-core tests run without ROS.
Run with the environment of scripts/env.sh (after scripts/setup.sh).
"""
import math
import os
import subprocess
import sys
import textwrap
import time
import uuid

import pytest

try:
    import rclpy
    from rclpy.serialization import deserialize_message, serialize_message
except Exception as exc:  # ImportError, or missing shared libraries (OSError)
    pytest.skip(
        f"rclpy not importable ({exc!r}): ROS 2 tests need `bash scripts/setup.sh` and "
        "`source scripts/env.sh`",
        allow_module_level=True,
    )

import numpy as np

try:
    from inclinometer_calib.msg import CalibrationCoefficients, CalibrationStatus, SurveyStation
    from inclinometer_calib.srv import RecapturePose
except ImportError as exc:  # rclpy works, so this is a broken setup, not a missing ROS
    raise ImportError(
        "rclpy imports but the generated inclinometer_calib messages do not: build them with "
        "`bash scripts/setup.sh` and `source scripts/env.sh` (PYTHONPATH must contain the "
        f"colcon install site-packages): {exc}"
    ) from exc

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
NAN = float("nan")


def make_station(station_id=7):
    m = SurveyStation()
    m.header.stamp.sec = 1_700_000_000
    m.header.stamp.nanosec = 123_456_789
    m.header.frame_id = "probe"
    m.station_id = station_id
    m.drift_deg = 12.5
    m.azimuth_deg = 271.25
    m.azimuth_reference = SurveyStation.AZIMUTH_REFERENCE_TRUE
    m.toolface_deg = 45.0
    m.toolface_type = SurveyStation.TOOLFACE_GRAVITY
    m.gravity_toolface_deg = 45.0
    m.magnetic_toolface_deg = 130.5
    m.total_gravity_mps2 = 9.80665
    m.total_field_nt = 50123.4
    m.dip_deg = 67.2
    m.delta_g_mps2 = -0.0012
    m.delta_b_nt = 35.0
    m.delta_dip_deg = 0.05
    m.status = SurveyStation.STATUS_WARN
    m.is_static = True
    m.interference_suspected = True
    m.azimuth_undefined = False
    m.gravity_out_of_tolerance = False
    m.samples_averaged = 200
    m.duration_s = 2.0
    m.temperature_c = 21.5
    m.coefficients_id = "probe-42/2024-05-01"
    m.reference_drift_deg = 12.0
    m.reference_azimuth_deg = NAN
    m.reference_toolface_deg = NAN
    return m


def assert_station_equal(a, b):
    for name in a.get_fields_and_field_types():
        va, vb = getattr(a, name), getattr(b, name)
        if isinstance(va, float) and math.isnan(va):
            assert math.isnan(vb), name
        elif hasattr(va, "shape"):          # fixed-size arrays (numpy): element by element, NaN = NaN
            np.testing.assert_array_equal(va, vb, err_msg=name)
        else:
            assert va == vb, name


def roundtrip(msg):
    data = serialize_message(msg)
    assert isinstance(data, bytes) and len(data) > 0
    return deserialize_message(data, type(msg))


def test_import_layout():
    """Core modules come from the source tree, generated interfaces from the colcon install."""
    import inclinometer_calib
    import inclinometer_calib.msg

    src_pkg = os.path.join(REPO, "inclinometer_calib")
    assert os.path.dirname(os.path.abspath(inclinometer_calib.__file__)) == src_pkg
    assert inclinometer_calib.__path__[0] == src_pkg
    assert not os.path.abspath(inclinometer_calib.msg.__file__).startswith(src_pkg + os.sep)
    assert SurveyStation.__module__.startswith("inclinometer_calib.msg")


def test_constants():
    assert (SurveyStation.STATUS_OK, SurveyStation.STATUS_WARN, SurveyStation.STATUS_ERROR) == (0, 1, 2)
    assert SurveyStation.AZIMUTH_REFERENCE_MAGNETIC == "magnetic"
    assert SurveyStation.AZIMUTH_REFERENCE_GRID == "grid"
    assert SurveyStation.TOOLFACE_MAGNETIC == "magnetic"
    assert CalibrationStatus.STATE_COLLECTING == "collecting"
    assert CalibrationStatus.STATE_DONE == "done"


def test_survey_station_roundtrip():
    m = make_station()
    assert_station_equal(m, roundtrip(m))


def test_calibration_coefficients_roundtrip():
    m = CalibrationCoefficients()
    m.header.frame_id = "probe"
    m.id = "probe-42/2024-05-01"
    m.probe_id = "probe-42"
    m.created = "2024-05-01T12:00:00+00:00"
    m.accel_correction_matrix = np.eye(3).ravel() * 1.001
    m.accel_offset = [0.01, -0.02, 0.03]
    m.accel_parameter_names = ["bias_x", "scale_x"]
    m.accel_parameter_values = [0.01, 1.001]
    m.accel_parameter_units = ["m/s^2", "1"]
    m.poses_used = list(range(12))
    m.accel_residuals = np.linspace(-1e-3, 1e-3, 36)
    m.accel_residual_units = "m/s^2"
    m.accel_rms_residual = 4e-4
    m.accel_model_effects = ["bias", "scale", "misalignment"]
    m.mag_correction_matrix = np.arange(9, dtype=float)
    m.mag_offset = [120.0, -80.5, 33.0]
    m.mag_parameter_names = ["hard_iron_x"]
    m.mag_parameter_values = [120.0]
    m.mag_parameter_units = ["nT"]
    m.mag_residuals = np.full(36, 2.5)
    m.mag_residual_units = "nT"
    m.mag_rms_residual = 2.5
    m.mag_model_effects = ["hard_iron", "soft_iron"]
    m.coefficients_yaml = "id: probe-42/2024-05-01\naccelerometer: {}\n"
    r = roundtrip(m)
    # fixed-size arrays arrive as numpy arrays, unbounded float64[] as array.array
    assert isinstance(r.accel_correction_matrix, np.ndarray)
    np.testing.assert_array_equal(r.accel_correction_matrix, np.eye(3).ravel() * 1.001)
    np.testing.assert_array_equal(r.mag_offset, [120.0, -80.5, 33.0])
    np.testing.assert_array_equal(np.asarray(r.accel_residuals), np.linspace(-1e-3, 1e-3, 36))
    assert list(r.poses_used) == list(range(12))
    assert r.mag_model_effects == ["hard_iron", "soft_iron"]
    assert r.coefficients_yaml == m.coefficients_yaml
    assert r == m


def test_calibration_status_roundtrip():
    m = CalibrationStatus()
    m.total_poses = 12
    m.captured = [0, 1, 5]
    m.pending = [p for p in range(12) if p not in (0, 1, 5)]
    m.current_pose = -1
    m.is_static = False
    m.capture_progress = 0.5
    m.warnings = ["magnetic field unstable"]
    m.state = CalibrationStatus.STATE_COLLECTING
    m.message = "move the probe to pose 2"
    r = roundtrip(m)
    assert r == m
    assert r.current_pose == -1


def test_recapture_pose_roundtrip():
    req = RecapturePose.Request(pose=11)
    assert roundtrip(req).pose == 11
    res = RecapturePose.Response(success=True, message="pose 11 pending again")
    r = roundtrip(res)
    assert r.success is True and r.message == "pose 11 pending again"


PUBLISHER_CHILD = textwrap.dedent(
    """
    import sys, time
    import rclpy
    from rclpy.executors import ExternalShutdownException
    sys.path.insert(0, {test_dir!r})
    from test_messages import make_station
    topic, lifetime = sys.argv[1], float(sys.argv[2])
    rclpy.init()
    node = rclpy.create_node("ic_test_publisher")
    from inclinometer_calib.msg import SurveyStation
    pub = node.create_publisher(SurveyStation, topic, 10)
    deadline = time.monotonic() + lifetime
    i = 0
    try:
        while time.monotonic() < deadline:
            pub.publish(make_station(station_id=1000 + i))
            i += 1
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    """
)


def test_pubsub_between_processes(ros_env):
    """A child process publishes SurveyStation; this process receives it (own domain, localhost)."""
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    topic = "/ic_test_" + uuid.uuid4().hex[:8]
    code = PUBLISHER_CHILD.format(test_dir=os.path.dirname(os.path.abspath(__file__)))
    child = subprocess.Popen(
        [sys.executable, "-c", code, topic, "30"],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    received = []
    try:
        node = rclpy.create_node("ic_test_subscriber", context=context)
        node.create_subscription(SurveyStation, topic, received.append, 10)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 20.0
        while not received and time.monotonic() < deadline and child.poll() is None:
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
        if child.poll() is None:
            child.terminate()
        try:
            out, _ = child.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            out, _ = child.communicate()
    assert received, f"no SurveyStation received within 20 s; publisher output:\n{out}"
    msg = received[0]
    assert msg.station_id >= 1000
    expected = make_station(station_id=msg.station_id)
    assert_station_equal(expected, msg)

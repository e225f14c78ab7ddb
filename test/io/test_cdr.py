"""The probe's messages as CDR bytes (inclinometer_calib.io.cdr), checked against an independent
serializer: rosbags' type store writes the bytes, our fixed-offset decoders read them; our
encoder (:class:`cdr.Patcher`) writes bytes that rosbags reads back field for field."""
import numpy as np
import pytest

from inclinometer_calib.io import cdr

rosbags = pytest.importorskip("rosbags.typesys")

IMU, MAG, TEMP, REF = ("sensor_msgs/msg/Imu", "sensor_msgs/msg/MagneticField", "sensor_msgs/msg/Temperature",
                       "geometry_msgs/msg/Vector3Stamped")
FRAMES = ["", "p", "probe", "probe_frame_1234"]


@pytest.fixture(scope="module")
def store():
    return rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)


def _messages(st, frame_id, sec=1700000123, nanosec=450000000):
    T = st.types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id)
    V = T["geometry_msgs/msg/Vector3"]
    return {
        IMU: T[IMU](header=hdr, orientation=T["geometry_msgs/msg/Quaternion"](x=1.0, y=2.0, z=3.0, w=4.0),
                    orientation_covariance=np.arange(9.0), angular_velocity=V(x=5.0, y=6.0, z=7.0),
                    angular_velocity_covariance=np.arange(9.0) + 10, linear_acceleration=V(x=0.1, y=-0.2, z=-9.8),
                    linear_acceleration_covariance=np.arange(9.0) + 20),
        MAG: T[MAG](header=hdr, magnetic_field=V(x=2e-5, y=-1e-6, z=4e-5),
                    magnetic_field_covariance=np.arange(9.0) * 1e-18),
        TEMP: T[TEMP](header=hdr, temperature=31.5, variance=0.1),
        REF: T[REF](header=hdr, vector=V(x=12.0, y=230.0, z=float("nan"))),
    }


@pytest.mark.parametrize("frame_id", FRAMES)
@pytest.mark.parametrize("little_endian", [True, False])
def test_the_decoders_read_what_rosbags_writes(store, frame_id, little_endian):
    msgs = _messages(store, frame_id)
    ser = {t: bytes(store.serialize_cdr(m, t, little_endian=little_endian)) for t, m in msgs.items()}
    key = (1700000123, 450000000)
    assert cdr.decode_imu(ser[IMU]) == (key, (0.1, -0.2, -9.8))
    assert cdr.decode_imu_gravity(ser[IMU]) == (key, (-0.1, 0.2, 9.8))   # what the core takes: g = -f
    assert cdr.imu_covariance(ser[IMU]) == tuple(np.arange(9.0) + 20)
    assert cdr.decode_imu_covariance(ser[IMU]) == np.sqrt(20.0)
    assert cdr.decode_vector3(ser[MAG]) == (key, (2e-5, -1e-6, 4e-5))
    assert cdr.mag_covariance(ser[MAG]) == tuple(np.arange(9.0) * 1e-18)
    assert np.isnan(cdr.decode_mag_covariance(ser[MAG]))          # 0: not stated
    assert cdr.decode_temperature(ser[TEMP]) == (key, 31.5)
    k, v = cdr.decode_vector3(ser[REF])
    assert k == key and v[:2] == (12.0, 230.0) and np.isnan(v[2])
    assert cdr.stamp(ser[TEMP]) == 1700000123.45


@pytest.mark.parametrize("frame_id", FRAMES)
@pytest.mark.parametrize("little_endian", [True, False])
def test_a_patched_message_is_the_bytes_rosbags_writes_for_it(store, frame_id, little_endian):
    first = _messages(store, frame_id)
    later = _messages(store, frame_id, sec=1700000999, nanosec=7)
    later[IMU].linear_acceleration.x, later[IMU].linear_acceleration.z = 0.25, -9.5
    later[MAG].magnetic_field.y = 3e-6
    later[TEMP].temperature = -4.0
    for t, make in ((IMU, cdr.Patcher.imu), (MAG, cdr.Patcher.vector3), (TEMP, cdr.Patcher.temperature)):
        patch = make(bytes(store.serialize_cdr(first[t], t, little_endian=little_endian)))
        m = later[t]
        values = {IMU: lambda: (m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z),
                  MAG: lambda: (m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z),
                  TEMP: lambda: (m.temperature,)}[t]()
        got = patch(1700000999, 7, *values)
        assert got == bytes(store.serialize_cdr(m, t, little_endian=little_endian)), t


def test_stamp_parts_round_to_the_nanosecond_and_carry_into_the_second():
    assert cdr.stamp_parts(12.5) == (12, 500_000_000)
    assert cdr.stamp_parts(3.0000000004) == (3, 0)
    assert cdr.stamp_parts(2.9999999999) == (3, 0)


def test_bytes_that_are_not_the_message_raise_a_decode_error():
    with pytest.raises(cdr.DECODE_ERRORS):
        cdr.decode_imu(b"\x00\x01\x00\x00\x01")
    with pytest.raises(cdr.DECODE_ERRORS):
        cdr.decode_string(b"\x00\x01\x00\x00\xff\x00\x00\x00ab")

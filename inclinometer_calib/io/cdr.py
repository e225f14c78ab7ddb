"""The probe's messages as CDR bytes: decoded and encoded at fixed offsets, without a generic
(de)serializer.

One decoding boundary for every driver of the engine: ``reprocess`` (a bag's bytes), the nodes'
sample subscriptions (taken raw: the bytes DDS delivered, never built into Python message
objects) and the probe's replay of a bag all read ``/probe/imu``, ``/probe/mag``,
``/probe/temperature`` and ``/probe/reference`` here, so that live and offline see the very same
numbers.  ROS-free (no rclpy, no generated message modules): the layouts are those of
``sensor_msgs/Imu``, ``sensor_msgs/MagneticField``, ``sensor_msgs/Temperature``,
``geometry_msgs/Vector3Stamped``, ``std_msgs/Float64`` and ``std_msgs/String``.

CDR (XCDR1, as rmw_fastrtps writes it): a 4-byte encapsulation header (its byte 1: 1
little-endian, 0 big-endian), then the message; a primitive is aligned to its size, counted from
the end of the encapsulation header.  Every message here starts with a ``std_msgs/Header``
(``int32 sec``, ``uint32 nanosec``, ``string frame_id`` as ``uint32`` length with the NUL, the
bytes), after which the float64 fields begin on the next 8-byte boundary.

Costs (one core of the CI machine, measured): a decode of an ``Imu`` 0.4 µs, where ``rclpy``'s
``deserialize_message`` (what a subscription's take into a Python ``Imu`` does) costs 18.5 µs; an
encode (:class:`Patcher`) 0.6 µs, where ``publish`` of a Python ``Imu`` (no reader) takes 6.7 µs
against 2.1 µs for the same bytes published raw.
"""
from __future__ import annotations

import math
import struct

from ..core.frames import gravity_from_specific_force

NAN = float("nan")

_LE = (struct.Struct("<iiI"), struct.Struct("<ddd"), struct.Struct("<d"), struct.Struct("<iI"),
       struct.Struct("<9d"))
_BE = (struct.Struct(">iiI"), struct.Struct(">ddd"), struct.Struct(">d"), struct.Struct(">iI"),
       struct.Struct(">9d"))
#: ``sensor_msgs/Imu`` after its header: orientation (4), orientation_covariance (9),
#: angular_velocity (3), angular_velocity_covariance (9) float64, then linear_acceleration (3) and
#: linear_acceleration_covariance (9).
IMU_ACC_OFFSET = 8 * (4 + 9 + 3 + 9)


class CdrError(ValueError):
    """The bytes are not the message they were taken for."""


def header(data):
    """``(sec, nanosec, offset, structs)``: the header's stamp, the byte offset of the first
    float64 field after it, and the structs of the bytes' endianness.  Raises :class:`CdrError`
    (a ``ValueError``) on a stamp no ``builtin_interfaces/Time`` holds, :class:`struct.error`
    on bytes too short."""
    structs = _LE if data[1] == 1 else _BE
    sec, nsec, n = structs[0].unpack_from(data, 4)
    if sec < 0 or nsec >= 1_000_000_000 and nsec != 0xFFFFFFFF:
        raise CdrError(f"invalid header stamp {sec}.{nsec:09d}")
    pos = 12 + n                       # relative to the body: 4 (sec) + 4 (nanosec) + 4 (len) + n
    pos = (pos + 7) & ~7
    return sec, nsec, 4 + pos, structs


def stamp(data) -> float:
    """The header stamp of a stamped message, in seconds."""
    sec, nsec, _, _ = header(data)
    return sec + 1e-9 * nsec


def decode_imu(data):
    """``((sec, nanosec), (fx, fy, fz))`` from the CDR bytes of a ``sensor_msgs/Imu``: the linear
    acceleration as recorded (REP-145 specific force, m/s²) — for passing the message on (the
    probe's replay of a bag); what goes into the core is :func:`decode_imu_gravity`'s."""
    sec, nsec, pos, s = header(data)
    return (sec, nsec), s[1].unpack_from(data, pos + IMU_ACC_OFFSET)


def decode_imu_gravity(data):
    """``((sec, nanosec), (gx, gy, gz))`` from the CDR bytes of a ``sensor_msgs/Imu``: the gravity
    vector (down positive, m/s²) the core takes, ``g = -f`` of the REP-145 specific force
    (:func:`frames.gravity_from_specific_force`, converted here, once, for every driver of the
    engine: a bag, the nodes' raw subscriptions)."""
    sec, nsec, pos, s = header(data)
    return (sec, nsec), gravity_from_specific_force(s[1].unpack_from(data, pos + IMU_ACC_OFFSET))


def imu_covariance(data) -> tuple:
    """The nine entries (row-major, (m/s²)²) of a ``sensor_msgs/Imu``'s linear_acceleration_covariance."""
    _, _, pos, s = header(data)
    return s[4].unpack_from(data, pos + IMU_ACC_OFFSET + 24)


def mag_covariance(data) -> tuple:
    """The nine entries (row-major, T²) of a ``sensor_msgs/MagneticField``'s magnetic_field_covariance."""
    _, _, pos, s = header(data)
    return s[4].unpack_from(data, pos + 24)


def sigma(covariance) -> float:
    """σ per axis stated by a covariance (the square root of its first diagonal entry), NaN when
    not stated (≤ 0: sensor_msgs' "unknown")."""
    var = covariance[0]
    return math.sqrt(var) if var > 0 else NAN


def decode_imu_covariance(data) -> float:
    """σ per axis (m/s²) a ``sensor_msgs/Imu`` states for its linear acceleration (:func:`sigma`)."""
    _, _, pos, s = header(data)
    return sigma(s[2].unpack_from(data, pos + IMU_ACC_OFFSET + 24))


def decode_mag_covariance(data) -> float:
    """σ per axis (tesla) a ``sensor_msgs/MagneticField`` states (:func:`sigma`)."""
    _, _, pos, s = header(data)
    return sigma(s[2].unpack_from(data, pos + 24))


def decode_vector3(data):
    """``((sec, nanosec), (x, y, z))`` of a message whose first field after the header is a
    Vector3 (``sensor_msgs/MagneticField``, ``geometry_msgs/Vector3Stamped``)."""
    sec, nsec, pos, s = header(data)
    return (sec, nsec), s[1].unpack_from(data, pos)


def decode_temperature(data):
    """``((sec, nanosec), temperature °C)`` of a ``sensor_msgs/Temperature``."""
    sec, nsec, pos, s = header(data)
    return (sec, nsec), s[2].unpack_from(data, pos)[0]


def decode_float64(data) -> float:
    """The value of a ``std_msgs/Float64`` (no header: the double right after the 4-byte CDR
    encapsulation header, 8-byte aligned from there)."""
    return struct.unpack_from("<d" if data[1] == 1 else ">d", data, 4)[0]


def decode_string(data) -> str:
    """The text of a ``std_msgs/String`` (uint32 length including the terminating NUL, then the
    bytes, right after the 4-byte CDR encapsulation header)."""
    n = struct.unpack_from("<I" if data[1] == 1 else ">I", data, 4)[0]
    if n < 1 or 8 + n > len(data):
        raise CdrError(f"string length {n} does not fit the message ({len(data)} bytes)")
    return bytes(data[8:8 + n - 1]).decode("utf-8")


#: What a decode raises on bytes that are not the message they were taken for.
DECODE_ERRORS = (struct.error, ValueError, IndexError, UnicodeDecodeError)


def stamp_parts(t: float) -> tuple:
    """Float seconds ``t`` (≥ 0) as a ``builtin_interfaces/Time``'s ``(sec, nanosec)``, the
    nanoseconds rounded."""
    sec = math.floor(t)
    ns = int(round((t - sec) * 1e9))
    if ns >= 1_000_000_000:
        sec, ns = sec + 1, ns - 1_000_000_000
    return int(sec), ns


class Patcher:
    """One stamped message serialized once (``data``: its CDR bytes, every other field as it is
    to be sent), then sent again and again with a new stamp and new values of one run of float64
    fields ``offset`` bytes after the header: the bytes a serializer would write for that message
    (0.6 µs an ``Imu``; the module docstring compares)."""

    def __init__(self, data, offset: int, n: int):
        self._buf = bytearray(data)
        _, _, pos, s = header(self._buf)
        self._at = pos + offset
        self._stamp = s[3]
        self._values = struct.Struct(("<" if self._buf[1] == 1 else ">") + "d" * n)
        if self._at + self._values.size > len(self._buf):
            raise CdrError(f"{n} float64 at offset {offset} do not fit the message ({len(self._buf)} bytes)")

    def __call__(self, sec: int, nanosec: int, *values) -> bytes:
        buf = self._buf
        self._stamp.pack_into(buf, 4, sec, nanosec)
        self._values.pack_into(buf, self._at, *values)
        return bytes(buf)

    @classmethod
    def imu(cls, data) -> "Patcher":
        """For a ``sensor_msgs/Imu``: the linear acceleration."""
        return cls(data, IMU_ACC_OFFSET, 3)

    @classmethod
    def vector3(cls, data) -> "Patcher":
        """For a ``sensor_msgs/MagneticField`` or ``geometry_msgs/Vector3Stamped``: the vector."""
        return cls(data, 0, 3)

    @classmethod
    def temperature(cls, data) -> "Patcher":
        """For a ``sensor_msgs/Temperature``: the temperature."""
        return cls(data, 0, 1)

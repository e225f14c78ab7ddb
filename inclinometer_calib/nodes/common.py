"""Helpers shared by the nodes: parameters, QoS, message <-> core conversions, stream pairing.

Boundary conventions (converted here, once):

* ``sensor_msgs/Imu.linear_acceleration`` is REP-145 specific force in m/s^2; the core takes the
  gravity vector ``g = -f``: :func:`gravity` reads it, :func:`set_gravity` writes it back (the raw
  sample subscriptions decode with ``cdr.decode_imu_gravity``, the same conversion).
* ``sensor_msgs/MagneticField`` is in tesla; the core works in nT (``NT_PER_TESLA``).
* Header stamps become float seconds (``sec + 1e-9 nanosec``).

Per-sample helpers work on plain floats and tuples: no numpy arrays are allocated per message.
"""
from __future__ import annotations

import math
import sys

import numpy as np
import rclpy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..io.cdr import stamp_parts
from ..core.coeffs import Calibration, message_fields
from ..core.frames import NT_PER_TESLA, Site, gravity_from_specific_force, specific_force_from_gravity
from ..core.geomag import site_from_parameters, site_parameter_defaults
from ..core.survey import Tolerances
from .executor import HotPathExecutor, install_stop_hook, spin  # noqa: F401  (HotPathExecutor re-exported: c.HotPathExecutor)

TESLA_PER_NT = 1.0 / NT_PER_TESLA
NAN = float("nan")

from ..io.topics import (TOPIC_CLOCK, TOPIC_COEFFICIENTS, TOPIC_DEPTH, TOPIC_DIAGNOSTICS, TOPIC_IMU, TOPIC_PROGRESS,  # noqa: F401,E402,E501
                      TOPIC_IMU_CORRECTED, TOPIC_MAG, TOPIC_MAG_CORRECTED, TOPIC_REFERENCE, TOPIC_SERIAL, TOPIC_STATION,
                      TOPIC_STATUS, TOPIC_TEMPERATURE)   # the graph's names, one place (re-exported)


# --------------------------------------------------------------------------------------------
# Running a node
# --------------------------------------------------------------------------------------------
def run(node_factory, args=None) -> int:
    """Create the node, spin it, shut down cleanly; the body of every node's ``main()``.

    Spins until Ctrl-C/SIGTERM (exit 0), or until the node's ``done`` future (if it has one)
    completes (exit with its result).  A bad parameter or unusable input ends the node with a
    one-line error on stderr and exit status 2: ``<Node>: error: ...`` when the node refused them
    at its start (the launcher does not restart it: it would fail the same way), ``<Node>: error
    while running: ...`` when a callback raised (the launcher restarts it as a node that died).  A
    node with ``hot_subscriptions`` (its sample streams) is spun by a :class:`HotPathExecutor`,
    any other by rclpy's global executor.
    """
    install_stop_hook()
    rclpy.init(args=args)
    node = executor = None
    started = False
    try:
        node = node_factory()
        started = True
        hot = getattr(node, "hot_subscriptions", ())
        executor = HotPathExecutor(hot) if hot else None
        done = getattr(node, "done", None)
        spin(node, executor or rclpy.get_global_executor(), done)
        return int(done.result() or 0) if done is not None and done.done() else 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except (ParameterException, ValueError, OSError) as exc:
        name = node.get_name() if node is not None else getattr(node_factory, "__name__", "node")
        print(f"{name}: error{' while running' if started else ''}: {exc}", file=sys.stderr)
        return 2
    finally:
        # each step to its end even if a second stop signal lands in it (it would end the
        # node with a traceback, and skip the steps after it)
        if executor is not None:
            _uninterrupted(executor.shutdown)   # its hot-path thread has ended before the node goes
        if node is not None:
            _uninterrupted(node.destroy_node)
        _uninterrupted(rclpy.try_shutdown)


def _uninterrupted(step) -> None:
    """``step()``; a ``KeyboardInterrupt`` raised in it (a second Ctrl-C while the node stops)
    is dropped: the node is stopping already."""
    try:
        step()
    except KeyboardInterrupt:
        pass


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------
class Params:
    """Declares a node's parameters (description, range, read-only) and validates changes.

    Every parameter gets a :class:`ParameterDescriptor`.  Numeric ranges are enforced by rclpy
    from the descriptor; choices and custom checks by the set-parameters callback registered
    here *before* the first declaration, so a bad value from a params file or the command line
    is rejected at start-up (``InvalidParameterValueException``) just like a bad ``ros2 param
    set`` later.  Nothing is silently replaced by a default.
    """

    def __init__(self, node):
        self.node = node
        self._checks = {}
        node.add_on_set_parameters_callback(self._on_set)

    def declare(self, name, default, description, *, read_only=False, range=None, choices=None,
                check=None, ptype=None):
        """Declare ``name`` and return its value.

        ``range`` = (lo, hi) inclusive (int or float parameters); ``choices`` = allowed values
        (string parameters); ``check(value) -> str | None`` returns the reason a value is bad;
        ``ptype`` is needed for an empty-list default (e.g. ``Parameter.Type.STRING_ARRAY``).
        """
        desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
        if choices:
            desc.additional_constraints = "one of: " + ", ".join(map(str, choices))
        if range is not None:
            lo, hi = range
            if isinstance(default, bool):
                raise TypeError(f"{name}: a range makes no sense for a bool parameter")
            if isinstance(default, int):
                desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
            else:
                desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                                step=0.0)]
        checks = []
        if choices:
            allowed = tuple(choices)
            checks.append(lambda v: None if v in allowed else
                          f"{v!r} is not allowed (one of: {', '.join(map(str, allowed))})")
        if check is not None:
            checks.append(check)
        if checks:
            self._checks[name] = checks
        if ptype is not None and isinstance(default, (list, tuple)) and len(default) == 0:
            # rclpy infers BYTE_ARRAY from []: declare typed (writable), give it the empty value,
            # then apply the real (possibly read-only) descriptor
            writable = ParameterDescriptor(name=name, description=description,
                                           additional_constraints=desc.additional_constraints)
            self.node.declare_parameter(name, ptype, writable)
            if self.node.get_parameter_or(name).type_ == Parameter.Type.NOT_SET:
                self.node.set_parameters([Parameter(name, ptype, [])])
            desc.type = ptype.value
            self.node.set_descriptor(name, desc)
        else:
            self.node.declare_parameter(name, default, desc)
        return self.node.get_parameter(name).value

    def get(self, name):
        return self.node.get_parameter(name).value

    def _on_set(self, params):
        for p in params:
            if p.value is None:  # declared without a value yet (typed declaration)
                continue
            for chk in self._checks.get(p.name, ()):
                reason = chk(p.value)
                if reason:
                    return SetParametersResult(successful=False, reason=f"parameter {p.name}: {reason}")
        return SetParametersResult(successful=True)


def declare_site(params: Params, site: Site = Site(), prefix: str = "site", given_flag: str | None = None):
    """Site reference field parameters (read-only: the reference of a run does not change).

    With ``given_flag`` (a description) a bool parameter ``<prefix>.given`` says whether the values
    are a site at all: false (the default) returns None — the node then uses the site the
    calibration record owns (or the calibration node the one the stand measures), never these
    defaults silently."""
    p = prefix
    given = True
    if given_flag is not None:
        given = params.declare(f"{p}.given", False, given_flag, read_only=True)
    dflt = site_parameter_defaults(site)
    values = {
        "total_field_nt": params.declare(f"{p}.total_field_nt", dflt["total_field_nt"],
                                         "Reference total magnetic field |B|, nT", read_only=True,
                                         range=(1000.0, 100000.0)),
        "dip_deg": params.declare(f"{p}.dip_deg", dflt["dip_deg"],
                                  "Reference magnetic dip, degrees, positive down", read_only=True,
                                  range=(-90.0, 90.0)),
        "declination_deg": params.declare(f"{p}.declination_deg", dflt["declination_deg"],
                                          "Magnetic declination, degrees east of true north (0: azimuths "
                                          "are magnetic)", read_only=True, range=(-180.0, 180.0)),
        "gravity_mps2": params.declare(f"{p}.gravity_mps2", dflt["gravity_mps2"],
                                       "Reference local gravity |g|, m/s^2", read_only=True,
                                       range=(9.7, 9.9)),
        # the rig's site by location: the values from a geomagnetic model, the site.* values listed
        # in site.measured (IFR) winning value by value
        "latitude_deg": params.declare(f"{p}.latitude_deg", dflt["latitude_deg"], "Site latitude, degrees north "
                                       "(NaN: no location; the site.* values are the reference)", read_only=True),
        "longitude_deg": params.declare(f"{p}.longitude_deg", dflt["longitude_deg"], "Site longitude, degrees east",
                                        read_only=True),
        "altitude_m": params.declare(f"{p}.altitude_m", dflt["altitude_m"],
                                     "Site altitude above the WGS84 ellipsoid, m", read_only=True),
        "date": params.declare(f"{p}.date", dflt["date"], "Survey date (YYYY-MM-DD) for the geomagnetic model",
                               read_only=True),
        "model": params.declare(f"{p}.model", dflt["model"], "Geomagnetic model: WMM2025 or IGRF-14",
                                read_only=True, choices=("WMM2025", "IGRF-14")),
        "crs": params.declare(f"{p}.crs", dflt["crs"],
                              "Projected CRS for grid azimuths (e.g. EPSG:32631; empty: none)", read_only=True),
        "measured": params.declare(f"{p}.measured", dflt["measured"], "Comma-separated site.* values that are "
                                   "measured (IFR) and win over the model's, e.g. 'total_field_nt,dip_deg'",
                                   read_only=True),
    }
    # the one site reader (the CLI's, the record's, the launcher's): geomag.site_from_config
    s = site_from_parameters(values, prefix=p)
    return s if given else None


def declare_tolerances(params: Params, prefix: str = "tolerances") -> Tolerances:
    """Survey QC tolerances (defaults: 300 nT, 0.25 deg, 0.0981 m/s^2)."""
    d = Tolerances()
    p = prefix
    return Tolerances(
        field_nt=params.declare(f"{p}.field_nt", d.field_nt,
                                "QC tolerance on |B| minus the site reference, nT", range=(0.0, 10000.0)),
        dip_deg=params.declare(f"{p}.dip_deg", d.dip_deg,
                               "QC tolerance on dip minus the site reference, degrees", range=(0.0, 10.0)),
        gravity_mps2=params.declare(f"{p}.gravity_mps2", d.gravity_mps2,
                                    "QC tolerance on |g| minus the site reference, m/s^2", range=(0.0, 2.0)),
        min_drift_deg=params.declare(f"{p}.min_drift_deg", d.min_drift_deg,
                                     "Azimuth is undefined below this drift, degrees", range=(0.0, 10.0)),
        gravity_toolface_min_drift_deg=params.declare(
            f"{p}.gravity_toolface_min_drift_deg", d.gravity_toolface_min_drift_deg,
            "Above this drift the gravity toolface is reported, below it the magnetic one, degrees",
            range=(0.0, 20.0)),
    )


def declare_detector(params: Params, prefix: str = "detector", **defaults) -> dict:
    """Static-detector settings (keyword arguments of :class:`streaming.StaticDetector`).

    The noise is measured from the data by default (``noise_acc``/``noise_mag`` = 0); a value
    > 0 overrides the measurement.  The covariance the probe's messages state is a prior (see
    :func:`note_covariance`)."""
    p = prefix
    spec = {
        "noise_acc": (0.0, "Accelerometer noise per sample (1 sigma), m/s^2; 0: measured from the data "
                           "(default; the messages' covariance is only a prior), > 0: use this instead", (0.0, 1.0)),
        "noise_mag": (0.0, "Magnetometer noise per sample (1 sigma), nT; 0: measured from the data (default), "
                           "> 0: use this instead", (0.0, 5000.0)),
        "k_sigma": (6.0, "A sample further than k_sigma times its axis' noise from the running mean of a hold "
                         "is motion (break_samples in a row end the hold)", (1.0, 100.0)),
        "min_duration_s": (0.5, "Shortest static interval reported as a station, s (log time)", (0.05, 600.0)),
        "settle_s": (0.2, "Samples discarded after motion stops, s (log time)", (0.0, 60.0)),
        "max_duration_s": (30.0, "Long static intervals are closed (reported) after this, s", (0.1, 1e6)),
    }
    out = {}
    for key, (default, desc, rng) in spec.items():
        out[key] = params.declare(f"{p}.{key}", float(defaults.get(key, default)), desc, read_only=True,
                                  range=rng)
    out["break_samples"] = params.declare(f"{p}.break_samples", int(defaults.get("break_samples", 3)),
                                          "Consecutive samples beyond k_sigma that end a hold; fewer are spikes, "
                                          "left out of the means", read_only=True, range=(1, 1000))
    return out


def declare_qos(params: Params, prefix: str = "qos", reliability: str = "best_effort",
                depth: int = 1000) -> QoSProfile:
    """QoS of the raw sensor streams from parameters (sensor-data profile by default)."""
    rel = params.declare(f"{prefix}.reliability", reliability,
                         "Reliability of the raw sensor streams: best_effort (sensor-data QoS) or "
                         "reliable", read_only=True, choices=("best_effort", "reliable"))
    dep = params.declare(f"{prefix}.depth", int(depth),
                         "History depth (keep last) of the raw sensor streams", read_only=True,
                         range=(1, 100000))
    dur = params.declare(f"{prefix}.durability", "volatile", "Durability of the raw sensor streams and the side "
                         "streams (reference, depth): volatile, or transient_local (a paced replay's source keeps "
                         "its last qos.depth samples: a node restarted mid-run gets what it missed)",
                         read_only=True, choices=("volatile", "transient_local"))
    return sensor_qos(dep, rel, dur)


def sensor_qos(depth: int = 1000, reliability: str = "best_effort", durability: str = "volatile") -> QoSProfile:
    """Sensor-data QoS (best effort, volatile, keep last ``depth``), or reliable / transient local if asked."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if durability == "transient_local" else DurabilityPolicy.VOLATILE,
        reliability=ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT)


def latched_qos(depth: int = 1) -> QoSProfile:
    """Transient-local, reliable, keep last ``depth``: late joiners get the latest values (the
    coefficients; each node's progress; the side streams a restarted reader needs)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)


def reliable_qos(depth: int = 100) -> QoSProfile:
    """Reliable, volatile, keep last ``depth``: events that must not be lost (stations, status)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, durability=DurabilityPolicy.VOLATILE,
                      reliability=ReliabilityPolicy.RELIABLE)


# --------------------------------------------------------------------------------------------
# Stamps and per-sample conversion (plain floats)
# --------------------------------------------------------------------------------------------
def stamp_to_sec(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def set_stamp(stamp, t: float) -> None:
    """Write float seconds ``t`` (>= 0) into a builtin_interfaces/Time in place (:func:`cdr.stamp_parts`)."""
    stamp.sec, stamp.nanosec = stamp_parts(t)


def steady_timer(node, period_s: float, callback):
    """A timer on the steady (monotonic) clock, not the node's ROS clock.

    With ``use_sim_time`` the ROS clock follows ``/clock`` (the probe's log time) and stops when
    the probe stops; the periodic work of the nodes (status, idle flush, diagnostics heartbeat,
    pairing checks, publishing, discovery) must go on then, so it runs on steady time.
    """
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def ros_time_started(node) -> bool:
    """False while the node runs on simulated time (``use_sim_time``) and no ``/clock`` has come
    yet (its ROS time reads 0): a stamp taken then would lie outside the run's time base."""
    clock = node.get_clock()
    return not clock.ros_time_is_active or clock.now().nanoseconds > 0


def gravity(imu_msg) -> tuple:
    """The gravity vector (down positive, m/s^2) of an Imu message as a tuple of floats: ``-f`` of
    its REP-145 specific force (:func:`frames.gravity_from_specific_force`, once, here)."""
    a = imu_msg.linear_acceleration
    return gravity_from_specific_force((a.x, a.y, a.z))


def set_gravity(imu_msg, g) -> None:
    """Write the gravity vector ``g`` (down positive, m/s^2) into an Imu message's
    linear_acceleration as REP-145 specific force (:func:`frames.specific_force_from_gravity`)."""
    a = imu_msg.linear_acceleration
    a.x, a.y, a.z = specific_force_from_gravity(tuple(g))


def field_nt(mag_msg) -> tuple:
    """Magnetic field of a MagneticField message converted tesla -> nT, as a tuple of floats."""
    f = mag_msg.magnetic_field
    return (f.x * NT_PER_TESLA, f.y * NT_PER_TESLA, f.z * NT_PER_TESLA)


# --------------------------------------------------------------------------------------------
# Calibration coefficients <-> CalibrationCoefficients
# --------------------------------------------------------------------------------------------
def coefficients_to_msg(cal: Calibration, msg_type, stamp_msg=None, frame_id: str = "probe"):
    """A ``CalibrationCoefficients`` message from a :class:`coeffs.Calibration` (fields: see
    :func:`coeffs.message_fields`, shared with offline reprocessing)."""
    m = msg_type()
    if stamp_msg is not None:
        m.header.stamp = stamp_msg
    m.header.frame_id = frame_id
    for name, value in message_fields(cal).items():
        setattr(m, name, value)
    return m


def coefficients_from_msg(msg) -> Calibration:
    """The :class:`coeffs.Calibration` carried by a message (checked; raises CoefficientError)."""
    return Calibration.from_yaml(msg.coefficients_yaml, source=f"CalibrationCoefficients {msg.id!r}")


def finite_or_nan(x) -> float:
    x = float(x)
    return x if math.isfinite(x) else NAN


def as_list(a) -> list:
    return [float(x) for x in np.asarray(a, float).ravel()]

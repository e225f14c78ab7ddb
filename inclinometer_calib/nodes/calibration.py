"""Calibration node: live twelve-pose capture from the probe's streams; publishes the coefficients.

Subscribes ``/probe/imu``, ``/probe/mag`` (paired by header stamp) and ``/probe/temperature``;
feeds the static detector (:class:`streaming.StaticDetector`), offers every closed static segment
to the capture session (:class:`capture.CaptureSession`) and, when all twelve poses are in:

* publishes ``inclinometer_calib/CalibrationCoefficients`` on ``/calibration/coefficients``
  (reliable, transient local: late joiners get the latest set);
* writes the coefficient record (YAML) to the ``output`` parameter's path (atomically).

The record is the paper's twelve-position model, or — with ``model.effects`` (the package's effect
grammar, e.g. ``temperature_bias:mag`` when the rounds span a temperature range) — that model plus
the named effects fitted to the captures by the lab's fit; parameters the captures cannot
identify are said at WARNING and named in the record (``not_identifiable``).  Its site reference
is the one given (``site.given:=true`` and ``site.*``) or, without one, the one the stand
measures (dip and the horizontal field's direction; said at WARNING), never a default.

With ``method:=turntable`` the node runs the patent's procedure instead (:class:`turntable.
TurntableSession`): each static hold is a table step, its mount the one gravity shows (or the
``turntable.mount`` parameter, settable while running); the status counts the three mounts as
"poses" 1..3 (xy, xz, yz: captured when complete, ``capture_progress`` the share of the turn the
current mount covers, the message the steps and coverage per mount); the record (the magnetometer;
the accelerometer from ``turntable.acc_record``) is published when all three are complete, and
again at the end of the data with every step.

``/calibration/status`` (``CalibrationStatus``) is published on every change and at
``status_rate_hz``.  Pose numbers in messages and services are those of the paper's Table 1
(1..12), as everywhere in the package.  Services: ``~/reset`` (std_srvs/Trigger)
discards all captures; ``~/recapture`` (RecapturePose) discards one pose so that it is captured
again (the coefficients are re-solved and re-published once it is).
"""
from __future__ import annotations

import os
import sys
import time

from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, MagneticField, Temperature
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..capture import CaptureSession
from ..effects import parse_effects
from ..frames import gravity_from_specific_force
from ..gates import GateLimits
from ..plugins import NODE_PARAMETER, name_plugins
from ..streaming import StaticDetector
from ..turntable import MOUNTS, MOUNT_NAMES_ORDER, TurntableSession
from ..twelve_position import POSES
from . import common as c
from inclinometer_calib.msg import CalibrationCoefficients, CalibrationStatus
from inclinometer_calib.srv import RecapturePose


def _check_effects(text):
    try:
        parse_effects(text)
    except ValueError as exc:
        return str(exc)
    return None


def _check_method(value):
    return None if value in ("twelve_position", "turntable") else "must be twelve_position or turntable"


def _check_mount(value):
    return None if value in ("",) + tuple(MOUNTS) else "must be empty (recognised from gravity) or xy, xz, yz"


class CalibrationNode(Node):
    def __init__(self, **kwargs):
        super().__init__("calibration", **kwargs)
        p = c.Params(self)
        self.frame_id = p.declare("frame_id", "probe", "frame_id of the published messages", read_only=True)
        self.output = p.declare("output", "", "Write the coefficient record (YAML) here when solved; empty: "
                                "do not write", check=self._check_output)
        self.probe_id = p.declare("probe_id", "probe", "Id / serial number of the probe", read_only=True)
        self.status_rate = p.declare("status_rate_hz", 1.0, "Periodic status publication rate, Hz",
                                     read_only=True, range=(0.1, 100.0))
        self.idle_flush = p.declare("idle_flush_s", 1.0, "End of the data: when no sample arrived for this long "
                                    "(wall clock), s, close the current static interval and solve with what there "
                                    "is (poses missing: least squares), or say why not; data arriving later continue "
                                    "the session; 0 disables", read_only=True, range=(0.0, 60.0))
        self.max_warnings = p.declare("max_warnings", 10, "Most recent warnings carried in the status",
                                      range=(0, 50))
        min_capture = p.declare("min_capture_s", 0.5, "Shortest accepted capture, s (log time)",
                                read_only=True, range=(0.05, 600.0))
        max_creep = p.declare("gates.max_creep_deg", GateLimits.max_creep_deg, "Largest turn of the probe during a "
                              "hold that is not motion (the trend must also be significant against the noise), deg",
                              read_only=True, range=(0.0, 10.0))
        max_ratio = p.declare("gates.max_scatter_ratio", GateLimits.max_scatter_ratio, "A hold whose scatter "
                              "(after its trend) exceeds this multiple of the measured noise, significantly, is "
                              "unsteady (vibration, motion): rejected", read_only=True, range=(1.0, 100.0))
        pose_tol = p.declare("pose_tolerance_deg", 15.0, "How far the measured gravity may be from a "
                             "Table 1 pose, deg", read_only=True, range=(1.0, 44.0))
        rounds = p.declare("rounds", True, "After the first solve, accept further complete rounds of the twelve "
                           "poses in Table 1 order (starting at pose 1) and solve again with all of them; "
                           "false: the first solve is final", read_only=True)
        site = c.declare_site(p, given_flag="true: the site.* values are the site reference of the record; "
                              "false: the record's site is what the stand measures (dip, the horizontal field's "
                              "direction; the total field in the scale of the assumed vertical component)")
        effects = p.declare("model.effects", "", "Effects to fit beyond the paper's model on the captured poses, "
                            "NAME[:sensor[:axes]][@scope],... (e.g. temperature_bias:mag); empty: the paper's model",
                            read_only=True, check=_check_effects)
        self.method = p.declare("method", "twelve_position", "Calibration procedure: twelve_position (the paper's "
                                "stand) or turntable (the patent's: the magnetometer on a non-magnetic table, three "
                                "mounts turned in equal steps)", read_only=True, check=_check_method)
        mount = p.declare("turntable.mount", "", "turntable: the current mount (xy, xz, yz); empty: recognised from "
                          "gravity (the marked axis that is vertical)", check=_check_mount)
        acc_record = p.declare("turntable.acc_record", "", "turntable: a calibration record (e.g. the twelve "
                               "positions') whose accelerometer joins the turntable's magnetometer in the record",
                               read_only=True)
        # for the acc_record's plug-in effects (a bad one ends the node, exit 2)
        name_plugins(p.declare("plugins", [], NODE_PARAMETER, read_only=True, ptype=Parameter.Type.STRING_ARRAY))
        det = c.declare_detector(p, max_duration_s=600.0)
        qos = c.declare_qos(p)

        self.detector = StaticDetector(**det)
        self._prior_seen = set()     # sensors whose stated noise (covariance) was given to the detector
        self.implausible_samples = 0
        if self.method == "turntable":
            acc_cal = None
            if acc_record:
                from ..coeffs import Calibration
                try:
                    acc_cal = Calibration.load(acc_record)
                except (OSError, ValueError) as exc:
                    # a bad start-up parameter: one line on stderr, exit status 2 (common.run)
                    raise ValueError(f"turntable.acc_record {acc_record}: {exc}") from None
            self.session = TurntableSession(site=site, acc_cal=acc_cal, probe_id=self.probe_id, mount=mount)
        else:
            self.session = CaptureSession(site=site, min_capture_s=min_capture, pose_tolerance_deg=pose_tol,
                                          rounds=rounds, probe_id=self.probe_id, effects=effects,
                                          limits=GateLimits(max_creep_deg=max_creep, max_scatter_ratio=max_ratio))
        self.pairer = c.StreamPairer()
        self.bad_samples = 0         # non-finite samples seen (each closes the static interval)
        self._last = None            # latest paired sample (t, f, m)
        self._last_wall = None       # monotonic time of the latest sample
        self._live_pose = -1
        self.coefficients = None     # latest published message

        self.pub_status = self.create_publisher(CalibrationStatus, c.TOPIC_STATUS, c.reliable_qos(10))
        self.pub_coeffs = self.create_publisher(CalibrationCoefficients, c.TOPIC_COEFFICIENTS, c.latched_qos())
        # the sample streams on a wait set of their own (c.HotPathExecutor, as the correction node's):
        # on rclpy's stock executor each message walks the node's whole wait set, about twice the CPU
        # per sample (docs/benchmarks.md, section 5)
        self.hot_subscriptions = (self.create_subscription(Imu, c.TOPIC_IMU, self._on_imu, qos),
                                  self.create_subscription(MagneticField, c.TOPIC_MAG, self._on_mag, qos),
                                  self.create_subscription(Temperature, c.TOPIC_TEMPERATURE, self._on_temp, qos))
        self.create_subscription(String, c.TOPIC_SERIAL, self._on_serial, c.latched_qos())
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(RecapturePose, "~/recapture", self._on_recapture)
        c.steady_timer(self, 1.0 / self.status_rate, self._on_timer)  # runs on when /clock stops
        self.add_post_set_parameters_callback(self._after_set)
        self.get_logger().info(("waiting for the turntable's steps (mounts xy, xz, yz)" if self.turntable else
                                "waiting for the twelve poses") + f" on {c.TOPIC_IMU} + {c.TOPIC_MAG}"
                               + (f"; coefficients will be written to {self.output}" if self.output else ""))

    @property
    def turntable(self) -> bool:
        return self.method == "turntable"

    @staticmethod
    def _check_output(path):
        if path:
            d = os.path.dirname(os.path.abspath(path))
            if not os.path.isdir(d):
                return f"directory {d!r} does not exist"
        return None

    def _after_set(self, params):
        for prm in params:
            if prm.name in ("output", "max_warnings"):
                setattr(self, prm.name, prm.value)
            elif prm.name == "turntable.mount" and self.turntable:
                self.session.mount = prm.value
                self.get_logger().info(f"turntable mount set to {prm.value or '(recognised from gravity)'}")

    # ---- samples ---------------------------------------------------------------------------
    def _on_imu(self, msg):
        s = msg.header.stamp
        ooo = self.pairer.out_of_order
        if len(self._prior_seen) < 2:
            c.note_covariance(self, self.detector, imu_msg=msg)
        got = self.pairer.add_imu((s.sec, s.nanosec), c.specific_force(msg))
        if got is not None:
            self._sample(*got)
        elif self.pairer.out_of_order != ooo:
            c.warn_out_of_order(self, c.TOPIC_IMU, s, self.pairer)

    def _on_mag(self, msg):
        s = msg.header.stamp
        ooo = self.pairer.out_of_order
        if len(self._prior_seen) < 2:
            c.note_covariance(self, self.detector, mag_msg=msg)
        got = self.pairer.add_mag((s.sec, s.nanosec), c.field_nt(msg))
        if got is not None:
            self._sample(*got)
        elif self.pairer.out_of_order != ooo:
            c.warn_out_of_order(self, c.TOPIC_MAG, s, self.pairer)

    def _on_temp(self, msg):
        self.detector.add_temperature(c.stamp_to_sec(msg.header.stamp), msg.temperature)

    def _on_serial(self, msg):
        """The data's probe (latched): the records this node makes are that probe's."""
        serial = str(msg.data)
        if not serial or serial == self.session.probe_id:
            return
        if self.probe_id not in ("", "probe", serial):
            self.get_logger().warning(f"probe_id {self.probe_id!r} is not the probe on {c.TOPIC_SERIAL} ({serial}): "
                                      "the records are named for the data's probe")
        self.session.probe_id = serial
        self.get_logger().info(f"calibrating probe {serial}")

    def _sample(self, t, f, m):
        self._last = (t, f, m)
        c.feed_sample(self, t, f, m, self._offer)

    def _log_events(self):
        for e in self.detector.pop_events():
            self.get_logger().warning(e)

    def _offer(self, seg):
        """Offer a closed station to the session; every refusal is logged at WARNING, a failed solve
        at ERROR (never at INFO), and a solve is published."""
        self._report(lambda: self.session.offer(seg))

    def _report(self, action):
        s = self.session
        n_warn, n_info, n_solves, before = len(s.warnings), len(s.infos), s.solves, (s.state, s.message)
        result = action()
        for w in s.warnings[n_warn:]:
            if not (s.state == "error" and w == s.message):   # the failure itself: at ERROR, below
                self.get_logger().warning(w)
        for i in s.infos[n_info:]:
            self.get_logger().info(i)
        if result == "accepted" and not self.turntable:
            self.get_logger().info(f"captured pose {s.current_pose}; pending {s.pending}")
        if (s.solves != n_solves and s.calibration is not None
                and (self.coefficients is None or self.coefficients.id != s.calibration.id)):
            self._publish_coefficients()   # a solve that gives the same record again is not republished
        elif s.state == "error" and s.message and (s.state, s.message) != before:
            self.get_logger().error(s.message)   # once, when it happens
        self._publish_status()

    def _finish(self):
        self.session.finish()   # a failure is logged by _report, once
        return "finished"

    def _publish_coefficients(self):
        cal = self.session.calibration
        msg = c.coefficients_to_msg(cal, CalibrationCoefficients, self.get_clock().now().to_msg(), self.frame_id)
        self.pub_coeffs.publish(msg)
        self.coefficients = msg
        self.get_logger().info(f"solved: {self.session.message}; published coefficients {cal.id} "
                               f"(model {cal.model.describe()})")
        if cal.site_source == "measured":
            st = cal.site
            self.get_logger().warning(
                f"no site given (site.given is false): the record's site reference is what the stand measured — dip "
                f"{st.dip_deg:.3f} deg, horizontal field {st.declination_deg:+.3f} deg from the stand's north (azimuths "
                f"are from the stand's north), total field {st.total_field_nt:.0f} nT in the scale of an assumed "
                "vertical component; give the site for a survey elsewhere")
        if self.output:
            try:
                cal.save(self.output)
                self.get_logger().info(f"wrote {self.output}")
            except OSError as exc:
                self.get_logger().error(f"cannot write {self.output}: {exc}")

    # ---- status ----------------------------------------------------------------------------
    def _on_timer(self):
        # End of stream: close a static interval nobody will close (no sample after it).
        if (self.idle_flush > 0 and self._last_wall is not None
                and time.monotonic() - self._last_wall > self.idle_flush):
            self._last_wall = None
            closed = self.detector.flush()
            for st in closed:
                self._offer(st)
            self._log_events()
            # the end of the data: solve with what there is (the last round, poses missing) or say why not
            self._report(self._finish)
            return
        # Live pose while static (the session only identifies closed segments).
        if self._last is not None and self.detector.static_for_s > 0:
            g = gravity_from_specific_force(tuple(self._last[1]))
            if self.turntable:
                m = self.session.identify(g)
                self._live_pose = MOUNT_NAMES_ORDER.index(m) + 1 if m else -1
            else:
                pose, _ = self.session.identify(g, self._last[2])
                self._live_pose = pose if pose is not None else -1
        else:
            self._live_pose = -1
        if c.ros_time_started(self):  # use_sim_time: no periodic status before the first /clock
            self._publish_status()

    def _publish_status(self):
        if self.turntable:
            return self._publish_turntable_status()
        s = self.session
        msg = CalibrationStatus()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.frame_id
        msg.total_poses = len(POSES)
        redo = set(s.recapture)
        msg.captured = [q for q in s.captured if q not in redo]
        msg.pending = sorted(set(s.pending) | redo)
        pose = self._live_pose if self._live_pose > 0 else s.current_pose
        msg.current_pose = pose if pose > 0 else -1
        msg.is_static = self.detector.is_static
        min_s = max(s.min_capture_s, self.detector.min_duration_s)
        msg.capture_progress = float(min(self.detector.static_for_s / min_s, 1.0)) if s.state == "collecting" else 0.0
        msg.warnings = list(s.warnings[-self.max_warnings:]) if self.max_warnings else []
        msg.state = s.state
        msg.message = s.message or (f"{len(s.captured)} of {len(POSES)} poses captured" if s.state == "collecting"
                                    else "")
        self.pub_status.publish(msg)

    def _publish_turntable_status(self):
        """The status in turntable mode: the three mounts as poses 1..3 (xy, xz, yz)."""
        s = self.session
        msg = CalibrationStatus()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.frame_id
        prog = s.progress()
        msg.total_poses = len(MOUNTS)
        msg.captured = [k + 1 for k, m in enumerate(MOUNT_NAMES_ORDER) if prog[m][2]]
        msg.pending = [k + 1 for k, m in enumerate(MOUNT_NAMES_ORDER) if not prog[m][2]]
        msg.current_pose = self._live_pose if self._live_pose > 0 else -1
        msg.is_static = self.detector.is_static
        cur = MOUNT_NAMES_ORDER[self._live_pose - 1] if self._live_pose > 0 else None
        msg.capture_progress = float(min(prog[cur][1] / 360.0, 1.0)) if cur else 0.0
        msg.warnings = list(s.warnings[-self.max_warnings:]) if self.max_warnings else []
        msg.state = s.state
        msg.message = s.message if s.state != "collecting" else s.progress_text()
        self.pub_status.publish(msg)

    # ---- services --------------------------------------------------------------------------
    def _on_reset(self, request, response):
        self.session.reset()
        self.detector.reset()
        self.pairer.reset()
        self._live_pose = -1
        response.success = True
        response.message = "all captures discarded; collecting the twelve poses again"
        self.get_logger().info(response.message)
        self._publish_status()
        return response

    def _on_recapture(self, request, response):
        pose = int(request.pose)
        if self.turntable:       # poses 1..3 are the mounts: their steps are taken again
            if not 1 <= pose <= len(MOUNTS):
                response.success = False
                response.message = f"mount {pose} out of range (1..3: xy, xz, yz)"
                return response
            m = MOUNT_NAMES_ORDER[pose - 1]
            self.session.steps = [st for st in self.session.steps if st.mount != m]
            self.session.state = "collecting"
            response.success = True
            response.message = f"mount {m}: its steps discarded; turn it again"
            self.get_logger().info(response.message)
            self._publish_status()
            return response
        if pose not in POSES:
            response.success = False
            response.message = f"pose {pose} out of range (1..{len(POSES)})"
            return response
        response.message = self.session.request_recapture(pose)
        response.success = True
        self.get_logger().info(response.message)
        self._publish_status()
        return response


def main(args=None):
    return c.run(CalibrationNode, args)


if __name__ == "__main__":
    sys.exit(main())

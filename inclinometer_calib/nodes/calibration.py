"""Calibration node: live twelve-pose capture from the probe's streams; publishes the coefficients.

Subscribes ``/probe/imu``, ``/probe/mag`` (paired by header stamp) and ``/probe/temperature``
and drives the stream engine (:class:`engine.StreamEngine`, through :class:`.stream.StreamDriver`)
in its calibrate role — the static detector, the gates, the capture session
(:class:`capture.CaptureSession`), as ``reprocess --calibrate`` drives it offline — and, when all
twelve poses are in, after a further complete round, when the sequence is over with poses missing
(the probe left the stand: least squares, the missing poses said) and at the end of the data:

* publishes ``inclinometer_calib/CalibrationCoefficients`` on ``/calibration/coefficients``
  (reliable, transient local: late joiners get the latest set), stamped with the data time from
  which it applies (the correction node applies it to the stations that end after it);
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

Its progress (``/graph/progress``): how far it has taken the stream and how many records it
published — the correction node keeps step with it, a paced replay waits for it.  Restarted with
``resume.bags`` (the launcher, after it died), it rebuilds its session from the run's recording and
publishes only the records the recording does not hold (its latest again, for late readers).
"""
from __future__ import annotations

import math
import os
import sys

from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from ..calibrate.capture import CaptureSession
from ..core.effects import parse_effects, split_model_options
from ..correct.engine import RecordOut, StreamEngine
from ..core.plugins import NODE_PARAMETER, name_plugins
from ..calibrate.turntable import MOUNTS, MOUNT_NAMES_ORDER, TurntableSession
from ..calibrate.twelve_position import POSES
from . import common as c
from .stream import StreamDriver, declare_stream_params, make_detector
from inclinometer_calib.msg import CalibrationCoefficients, CalibrationStatus
from inclinometer_calib.srv import RecapturePose


def _check_effects(text):
    try:
        parse_effects(split_model_options(text)[0])   # what the lab recommends, stand_pose_error too
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
        self.max_warnings = p.declare("max_warnings", 10, "Most recent warnings carried in the status",
                                      range=(0, 50))
        min_capture = p.declare("min_capture_s", 0.5, "Shortest accepted capture, s (log time)",
                                read_only=True, range=(0.05, 600.0))
        pose_tol = p.declare("pose_tolerance_deg", 15.0, "How far the measured gravity may be from a "
                             "Table 1 pose, deg", read_only=True, range=(1.0, 44.0))
        rounds = p.declare("rounds", True, "After the first solve, accept further complete rounds of the twelve "
                           "poses in Table 1 order (starting at pose 1) and solve again with all of them; "
                           "false: the first solve is final", read_only=True)
        end_after_stations = p.declare("session.end_after_stations", 2, "Before any solve, this many statics in a "
                                       "row that are not poses of the sequence end it (the probe left the stand): "
                                       "solve with the poses there are (missing ones said)", read_only=True,
                                       range=(1, 1000))
        end_after_s = p.declare("session.end_after_s", 120.0, "Before any solve, a static that starts this long "
                                "after the last capture (data time, s) ends the sequence too", read_only=True,
                                range=(1.0, 1e6))
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
        settings = declare_stream_params(p, calibration_sync=False)

        if self.method == "turntable":
            acc_cal = None
            if acc_record:
                from ..core.coeffs import Calibration
                try:
                    acc_cal = Calibration.load(acc_record)
                except (OSError, ValueError) as exc:
                    # a bad start-up parameter: one line on stderr, exit status 2 (common.run)
                    raise ValueError(f"turntable.acc_record {acc_record}: {exc}") from None
            self.session = TurntableSession(site=site, acc_cal=acc_cal, probe_id=self.probe_id, mount=mount)
        else:
            self.session = CaptureSession(site=site, min_capture_s=min_capture, pose_tolerance_deg=pose_tol,
                                          rounds=rounds, probe_id=self.probe_id, effects=effects,
                                          limits=settings["gates"], end_after_stations=end_after_stations,
                                          end_after_s=end_after_s)
        # the same engine as the correction node's and reprocess's, in the calibrate role
        self.engine = StreamEngine(make_detector(settings), session=self.session, gate_limits=settings["gates"],
                                   gravity_mps2=site.gravity_mps2 if site is not None else None)
        self.detector = self.engine.det
        self._live_pose = -1
        self.coefficients = None     # latest published message

        self.pub_status = self.create_publisher(CalibrationStatus, c.TOPIC_STATUS, c.reliable_qos(10))
        self.pub_coeffs = self.create_publisher(CalibrationCoefficients, c.TOPIC_COEFFICIENTS, c.latched_qos())
        # the sample streams on a wait set of their own (c.HotPathExecutor, as the correction node's)
        self.stream = StreamDriver(self, settings, self.engine, self._on_events, side=False)
        self.hot_subscriptions = tuple(self.stream.hot_subscriptions)
        self._replayed = []          # records solved again while resuming (published after, if new)
        if any(os.path.exists(b) for b in settings["resume"]):
            # a restart: the session of the node that died, rebuilt from the run's recording
            self.stream.resume(settings["resume"], records=False)
            for ev in self._replayed:
                if ev.calibration.id not in self.stream.recorded_records:
                    self._publish_coefficients(ev.calibration, ev.stamp)
            if self._replayed and self._replayed[-1].calibration.id in self.stream.recorded_records:
                # published before: again, latched, for readers that join from now on
                self._publish_coefficients(self._replayed[-1].calibration, self._replayed[-1].stamp, again=True)
            self._replayed = []
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

    # ---- what the engine produced ---------------------------------------------------------
    def _on_events(self, events, msg=None, info=None):
        """Records are published (and written), the status follows every change."""
        if not events:
            return
        for ev in events:
            if isinstance(ev, RecordOut):
                if self.stream.replaying:
                    self._replayed.append(ev)
                else:
                    self._publish_coefficients(ev.calibration, ev.stamp)
        self._publish_status()

    def _publish_coefficients(self, cal, stamp: float, again: bool = False):
        """Publish a record, stamped with the data time from which it applies (the correction node
        and reprocess apply it to the stations that end after it), and write it to ``output``
        (``again``: a restarted node's latest record, published again for late readers: only that)."""
        msg = c.coefficients_to_msg(cal, CalibrationCoefficients, None, self.frame_id)
        c.set_stamp(msg.header.stamp, max(stamp, 0.0) if math.isfinite(stamp) else max(self.engine.t_last, 0.0))
        self.pub_coeffs.publish(msg)
        self.coefficients = msg
        if again:
            self.get_logger().info(f"published again the record {cal.id} the node that died had published")
            return
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
        # Live pose while static (the session only identifies closed segments).
        last = self.engine.last_pair
        if last is not None and self.detector.static_for_s > 0:
            g = last[1]    # the engine's last pair: gravity already (converted where it came in)
            if self.turntable:
                m = self.session.identify(g)
                self._live_pose = MOUNT_NAMES_ORDER.index(m) + 1 if m else -1
            else:
                pose, _ = self.session.identify(g, last[2])
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
        self.engine.release_undecided()
        self.detector.reset()
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

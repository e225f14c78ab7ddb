"""Correction node: applies the latest calibration and publishes quality-checked survey stations.

Inputs: ``/probe/imu`` + ``/probe/mag`` (paired by header stamp), ``/probe/temperature``,
``/probe/reference`` (optional reference attitudes), ``/probe/depth`` (optional measured depth: a
station takes the latest when it closes, and gets its trajectory by minimum curvature from the
station before it in depth — :meth:`pipeline.SurveyProcessor`), and the coefficients: the latched topic
``/calibration/coefficients`` (transient-local subscription; ``use_topic``) and/or a coefficient
YAML file (``coeffs_file``, may be changed at run time: the file is checked before it is
accepted).  The most recently received set is applied.

Recovery (a node restarted mid-run, e.g. by the launcher, after the calibration node is gone):
``fallback_coeffs_file`` is the last valid record on disk (the calibration node's ``output``); it
is applied at start-up, with a warning, until a record arrives on the topic (one that differs
replaces it).  ``state_file`` keeps the next station id (JSON, written atomically after every
station), so the ids of a restarted node continue instead of starting again at 0.

Outputs:

* ``/survey/station`` (``SurveyStation``, reliable): one per static interval closed by the
  static detector, through the survey pipeline (:class:`pipeline.SurveyProcessor`): corrected by
  the current record's model (its lab effects too, with the station's temperature and time),
  evaluated against the site reference **the record owns** (``site.given:=true`` overrides it
  with the ``site.*`` parameters, said at WARNING for every record it overrides; before any
  record and without a given site there is no reference and the stations say so), and checked
  by the field monitor (:class:`lab.field.FieldMonitor`, ``monitor.window`` stations): when the
  residuals against the site follow temperature, time or orientation beyond chance, the station
  carries ``model_misfit`` and ``model_diagnosis`` (the likely missing effect, in words);
* ``/probe/imu_corrected``, ``/probe/mag_corrected`` (``publish_corrected``): the corrected
  streams, sample by sample, once coefficients are known (the same correction path, with the
  latest temperature);
* ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``): G-total, B-total and dip of the latest
  station against the site reference and the configured tolerances, and the field monitor's
  verdict on the model (per station and at 1 Hz).

Per-sample work is one static-detector update (and, with ``publish_corrected``, one correction);
stations (a few per minute) do the heavier evaluation.
"""
from __future__ import annotations

import bisect
import collections
import json
import math
import os
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, MagneticField, Temperature
from std_msgs.msg import Float64, String

from ..coeffs import Calibration, CoefficientError
from ..frames import gravity_from_specific_force, specific_force_from_gravity
from ..lab.field import FieldMonitor
from ..pipeline import NO_SITE, ProbeMismatch, SurveyProcessor
from ..plugins import NODE_PARAMETER, name_plugins
from ..probelog import atomic_write_text
from ..streaming import TIME_EPS, ReferenceTrack, StaticDetector
from . import common as c
from inclinometer_calib.msg import CalibrationCoefficients, SurveyStation

#: Imu messages whose source timestamps are kept to place a late depth (about 20 s at 1 kHz).
SENT_KEPT = 20_000

_LEVEL_NAMES = {DiagnosticStatus.OK: "OK", DiagnosticStatus.WARN: "WARN", DiagnosticStatus.ERROR: "ERROR",
                DiagnosticStatus.STALE: "STALE"}


class CorrectionNode(Node):
    def __init__(self, **kwargs):
        super().__init__("correction", **kwargs)
        p = c.Params(self)
        self.frame_id = p.declare("frame_id", "probe", "frame_id of the published messages", read_only=True)
        self.probe_id = p.declare("probe_id", "probe", "Hardware id in the diagnostics", read_only=True)
        # named before any record is read (a bad one ends the node, exit 2)
        name_plugins(p.declare("plugins", [], NODE_PARAMETER, read_only=True, ptype=Parameter.Type.STRING_ARRAY))
        coeffs_file = p.declare("coeffs_file", "", "Coefficient record (YAML) to apply; empty: wait for "
                                "the topic. May be changed while running (checked first)",
                                check=self._check_coeffs_file)
        self.use_topic = p.declare("use_topic", True, f"Apply coefficients received on {c.TOPIC_COEFFICIENTS}",
                                   read_only=True)
        fallback = p.declare("fallback_coeffs_file", "", "Last valid coefficient record on disk (the "
                             "calibration node's output), applied at start-up until a record arrives on "
                             f"{c.TOPIC_COEFFICIENTS} (one that differs replaces it); ignored when coeffs_file "
                             "is given; a missing file is skipped, an invalid one reported; empty: none",
                             read_only=True)
        self.state_file = p.declare("state_file", "", "JSON file keeping the next station id, written after "
                                    "every station and read at start-up, so that the ids of a restarted node "
                                    "continue; empty: ids start at 0", read_only=True)
        self.publish_corrected = p.declare("publish_corrected", False, "Publish the corrected streams "
                                           f"{c.TOPIC_IMU_CORRECTED} and {c.TOPIC_MAG_CORRECTED}")
        axial = p.declare("axial_correction", False, "Azimuths from the short-collar correction of axial "
                          "drill-string interference (site total field and dip); QC stays on the measured "
                          "field; degenerate stations keep the standard azimuth and are flagged")
        self.publish_short = p.declare("publish_short", False, "Also publish static intervals shorter "
                                       "than detector.min_duration_s (is_static = false)")
        self.reference_wait = p.declare("reference_wait_s", 2.0, f"A closed station waits at most this long (wall "
                                        f"clock, s) for {c.TOPIC_REFERENCE} to be current up to its end (the reference "
                                        "is another topic and may come late); then it is published with the last "
                                        "reference received, with a warning", read_only=True, range=(0.0, 60.0))
        self.wait_readers = p.declare("wait_for_station_readers", 0, f"A station waits (at most reference_wait_s, "
                                      f"then said) until {c.TOPIC_STATION} has this many matched readers: stations are "
                                      "reliable but volatile, and a reader the graph shows but DDS has not yet matched "
                                      "misses what is published before (the launcher sets it to the readers it "
                                      "starts)", read_only=True, range=(0, 100))
        self.idle_flush = p.declare("idle_flush_s", 1.0, "Close the current static interval when no sample "
                                    "arrived for this long (wall clock), s; 0 disables", read_only=True,
                                    range=(0.0, 60.0))
        site = c.declare_site(p, given_flag="true: the site.* values are the site reference and override the one "
                              "the calibration record owns (said at WARNING for every record they override); "
                              "false: the record's site is used")
        self.tol = c.declare_tolerances(p)
        window = p.declare("monitor.window", 30, "The field monitor tests the residuals of the last this many "
                           "stations against the site for the trend a missing effect leaves (temperature, time, "
                           "orientation); 0 disables it", read_only=True, range=(0, 1000))
        materiality = p.declare("monitor.materiality", 0.1, "Smallest trend that counts, as a fraction of each "
                                "channel's QC tolerance (RMS of the part it explains)", read_only=True,
                                range=(0.0, 10.0))
        force_probe = p.declare("force_probe", False, "Apply a calibration record of another probe than the one "
                                f"on {c.TOPIC_SERIAL} (refused otherwise); every station then says so",
                                read_only=True)
        det = c.declare_detector(p)
        qos = c.declare_qos(p)
        self.add_post_set_parameters_callback(self._after_set)

        self.detector = StaticDetector(**det)
        self.detector.retain_temperatures = True   # stations wait for their reference: forgotten once published
        self._prior_seen = set()     # sensors whose stated noise (covariance) was given to the detector
        self.implausible_samples = 0
        monitor = FieldMonitor(window=window, materiality=materiality, tolerances=self.tol) if window else None
        self.processor = SurveyProcessor(self.tol, site=site, axial=axial, monitor=monitor, force_probe=force_probe)
        self._mismatch = ""          # why the record offered is not applied (another probe's), said in diagnostics
        self.processor._next_id = self._read_state()  # station ids continue across restarts
        if site is None:
            self.get_logger().info("the site reference is the calibration record's (site.given is false)")
        self._fallback_id = None     # id of the record applied from fallback_coeffs_file, until replaced
        self.pairer = c.StreamPairer()
        self.bad_samples = 0         # non-finite samples seen (each closes the static interval)
        self._unpaired_seen = self._paired_seen = self._waiting_seen = 0
        self._temp = c.NAN
        self._have_temp = False
        self._last_wall = None
        self.refs = ReferenceTrack()
        # /probe/depth has no stamp: each value holds from the last sample *sent* before it (by the
        # DDS source timestamps of the depth and of the Imu messages: see _on_depth)
        self.depths = ReferenceTrack()
        self._t_sample = -math.inf
        self._sent = collections.deque(maxlen=SENT_KEPT)   # (Imu source timestamp ns, its stamp s)
        self._depths_waiting = []                          # (source timestamp ns, depth m)
        self._pending = collections.deque()   # (station, monotonic time) waiting: _current_at
        self._last_diag = None
        self._last_verdict = None
        self._no_site_said = False
        if coeffs_file:
            self._apply(Calibration.load(coeffs_file), f"file {coeffs_file}")
        elif fallback:
            self._apply_fallback(fallback)

        self.pub_station = self.create_publisher(SurveyStation, c.TOPIC_STATION, c.reliable_qos(100))
        self.pub_diag = self.create_publisher(DiagnosticArray, c.TOPIC_DIAGNOSTICS, c.reliable_qos(10))
        self.pub_imu = self.create_publisher(Imu, c.TOPIC_IMU_CORRECTED, qos)
        self.pub_mag = self.create_publisher(MagneticField, c.TOPIC_MAG_CORRECTED, qos)
        # the sample streams (the probe publishes a temperature with every sample): served on a wait set
        # of their own when the node runs as a process (common.HotPathExecutor, through common.run)
        # The depth and the record are on the hot path too, taken in turn with the samples:
        # * the depth (unstamped) holds from the last sample sent before it (with the message info:
        #   the DDS source timestamps say which, however late either is taken; see _on_depth);
        # * a record (latched) applies from the first station that closes after it is taken: the
        #   calibration node publishes it once the last pose has ended, so that pose stays raw
        #   (on rclpy's executor, in the other thread, a lagging node applied it sooner).
        hot = [self.create_subscription(Imu, c.TOPIC_IMU, lambda m, info: self._on_imu(m, info), qos),
               self.create_subscription(MagneticField, c.TOPIC_MAG, self._on_mag, qos),
               self.create_subscription(Temperature, c.TOPIC_TEMPERATURE, self._on_temp, qos),
               self.create_subscription(Float64, c.TOPIC_DEPTH, lambda m, info: self._on_depth(m, info),
                                       c.reliable_qos(100))]
        if self.use_topic:
            hot.append(self.create_subscription(CalibrationCoefficients, c.TOPIC_COEFFICIENTS, self._on_coefficients,
                                                c.latched_qos()))
        self.hot_subscriptions = tuple(hot)
        self.create_subscription(Vector3Stamped, c.TOPIC_REFERENCE, self._on_reference, c.reliable_qos(100))
        self.create_subscription(String, c.TOPIC_SERIAL, self._on_serial, c.latched_qos())
        c.steady_timer(self, 1.0, self._on_timer)  # keeps running when /clock (use_sim_time) stops

    # ---- coefficients ----------------------------------------------------------------------
    @staticmethod
    def _check_coeffs_file(path):
        if not path:
            return None
        try:
            Calibration.load(path)
        except (OSError, CoefficientError) as exc:
            return f"cannot use {path!r}: {exc}"
        return None

    def _after_set(self, params):
        for prm in params:
            if prm.name == "coeffs_file" and prm.value:
                self._fallback_id = None  # an explicit record replaces the fallback
                self._apply(Calibration.load(prm.value), f"file {prm.value}")
            elif prm.name in ("publish_corrected", "publish_short"):
                setattr(self, prm.name, prm.value)

    @property
    def calibration(self):
        return self.processor.calibration

    def _on_serial(self, msg):
        """The data's probe (latched): a record of another probe stops being applied (unless forced)."""
        if msg.data == self.processor.probe_serial:
            return
        try:
            for note in self.processor.set_probe_serial(msg.data):
                self.get_logger().warning(note)
            self.get_logger().info(f"the data are of probe {msg.data}")
        except ProbeMismatch as exc:
            self._mismatch = str(exc)
            self.get_logger().error(f"{exc}: the stations go uncorrected")

    def _apply(self, cal: Calibration, origin: str, fallback: bool = False):
        try:
            notes = self.processor.set_calibration(cal)
        except ProbeMismatch as exc:
            self._mismatch = f"{exc} (from {origin})"
            self.get_logger().error(f"{self._mismatch}; force_probe:=true applies it anyway")
            return
        self._mismatch = ""
        self.get_logger().info(f"applying coefficients {cal.id} (probe {cal.probe_id}, model {cal.model.describe()}, "
                               f"site {cal.site_source}) from {origin}")
        for note in notes:
            self.get_logger().warning(note)
        if "temperature" in cal.needs and not self._have_temp:
            self.get_logger().warning(f"record {cal.id} has temperature effects ({', '.join(cal.model.labels())}): "
                                      f"stations need {c.TOPIC_TEMPERATURE}, none received yet")

    def _apply_fallback(self, path):
        """Apply the last valid record on disk until the topic delivers one (see the module docstring)."""
        if not os.path.exists(path):
            self.get_logger().info(f"no fallback record at {path} (yet): waiting for {c.TOPIC_COEFFICIENTS}")
            return
        try:
            cal = Calibration.load(path)
        except (OSError, CoefficientError) as exc:
            self.get_logger().error(f"fallback record {path} is not valid, not used: {exc}")
            return
        self._apply(cal, f"the fallback record {path}")
        self._fallback_id = cal.id
        self.get_logger().warning(f"no record received yet; applying the last valid record on disk {path} "
                                  f"(id {cal.id}, created {cal.created}) until one arrives on "
                                  f"{c.TOPIC_COEFFICIENTS}")

    def _on_coefficients(self, msg):
        try:
            cal = c.coefficients_from_msg(msg)
        except CoefficientError as exc:
            self.get_logger().error(f"coefficients rejected, keeping the previous ones: {exc}")
            return
        fallback, self._fallback_id = self._fallback_id, None
        if fallback is not None and cal.id != fallback:
            self.get_logger().info(f"record {cal.id} received on {c.TOPIC_COEFFICIENTS} replaces the fallback "
                                   f"record {fallback} from disk")
        elif fallback is not None:
            self.get_logger().info(f"record {cal.id} received on {c.TOPIC_COEFFICIENTS} is the fallback record "
                                   "already applied")
        if self.calibration is None or cal.id != self.calibration.id:
            self._apply(cal, c.TOPIC_COEFFICIENTS)

    # ---- station-id state ------------------------------------------------------------------
    def _read_state(self) -> int:
        """The next station id from ``state_file`` (0 without one).  An unreadable file is reported
        at ERROR and ids start at 0 (they may then repeat those of the earlier run)."""
        if not self.state_file or not os.path.exists(self.state_file):
            return 0
        try:
            with open(self.state_file, encoding="utf-8") as fh:
                state = json.load(fh)
            next_id = state["next_station_id"]
            if not isinstance(next_id, int) or isinstance(next_id, bool) or next_id < 0:
                raise ValueError(f"next_station_id {next_id!r} is not a non-negative integer")
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            self.get_logger().error(f"state file {self.state_file} is not usable ({type(exc).__name__}: {exc}): "
                                    "station ids start at 0 and may repeat those of the earlier run")
            return 0
        self.get_logger().info(f"continuing station ids at {next_id} (from {self.state_file})")
        return next_id

    def _write_state(self):
        """Persist the next station id (atomically: a crash leaves the old or the new file, never half)."""
        if not self.state_file:
            return
        state = {"format": "inclinometer_calib/correction_state", "next_station_id": self.processor._next_id}
        try:
            atomic_write_text(self.state_file, json.dumps(state) + "\n")
        except OSError as exc:
            self.get_logger().error(f"cannot write the state file {self.state_file}: {exc}",
                                    throttle_duration_sec=10.0)

    # ---- samples ---------------------------------------------------------------------------
    def _on_imu(self, msg, info=None):
        s = msg.header.stamp
        if info is not None:
            self._note_sent(info["source_timestamp"], c.stamp_to_sec(s))
        ooo = self.pairer.out_of_order
        f = c.specific_force(msg)
        if len(self._prior_seen) < 2:
            c.note_covariance(self, self.detector, imu_msg=msg)
        got = self.pairer.add_imu((s.sec, s.nanosec), f)
        if got is not None:
            self._sample(*got)
        elif self.pairer.out_of_order != ooo:
            c.warn_out_of_order(self, c.TOPIC_IMU, s, self.pairer)
        if self.publish_corrected and self.calibration is not None:
            v = self._correct_stream("acc", gravity_from_specific_force(f), c.stamp_to_sec(s))
            if v is not None:
                la = msg.linear_acceleration
                la.x, la.y, la.z = specific_force_from_gravity(v)
                self.pub_imu.publish(msg)

    def _on_mag(self, msg):
        s = msg.header.stamp
        ooo = self.pairer.out_of_order
        m = c.field_nt(msg)
        if len(self._prior_seen) < 2:
            c.note_covariance(self, self.detector, mag_msg=msg)
        got = self.pairer.add_mag((s.sec, s.nanosec), m)
        if got is not None:
            self._sample(*got)
        elif self.pairer.out_of_order != ooo:
            c.warn_out_of_order(self, c.TOPIC_MAG, s, self.pairer)
        if self.publish_corrected and self.calibration is not None:
            v = self._correct_stream("mag", m, c.stamp_to_sec(s))
            if v is not None:
                mf = msg.magnetic_field
                mf.x, mf.y, mf.z = v[0] * c.TESLA_PER_NT, v[1] * c.TESLA_PER_NT, v[2] * c.TESLA_PER_NT
                self.pub_mag.publish(msg)

    def _correct_stream(self, sensor, h, t):
        """One sample of one stream through the record's correction (:meth:`model.CorrectionPlan.correct_sample`:
        the path the stations take, in plain floats), with the latest temperature and the time since
        the first sample; None (and a warning) when the model needs a temperature there is none of."""
        t0 = self.detector.t_first
        try:
            return self.calibration.plan.correct_sample(sensor, h, self._temp if self._have_temp else None,
                                                        t - t0 if t0 == t0 else 0.0)
        except ValueError as exc:
            self.get_logger().warning(f"corrected {sensor} stream not published: {exc}", throttle_duration_sec=10.0)
            return None

    def _on_temp(self, msg):
        self._temp = msg.temperature   # the latest: for the corrected streams
        self._have_temp = True
        self.detector.add_temperature(c.stamp_to_sec(msg.header.stamp), msg.temperature)
        if self._pending:
            self._release(force=False)

    def _current_at(self, t: float) -> bool:
        """The reference and the temperatures are in up to ``t`` and the station readers are
        matched (``wait_for_station_readers``): a station ending then can go.  Before the first
        temperature, a record whose model needs one waits for it too (the temperature topic may be
        matched after the samples' at start-up: its first messages come late, and a station
        without them could not be corrected)."""
        return self.refs.current_at(t) and self._temps_in(t) and self._readers_in()

    def _readers_in(self) -> bool:
        return self.wait_readers <= 0 or self.pub_station.get_subscription_count() >= self.wait_readers

    def _temps_in(self, t: float) -> bool:
        if self._have_temp:
            return self.detector.temps.latest >= t - TIME_EPS
        return self.calibration is None or "temperature" not in self.calibration.needs

    def _note_sent(self, src_ns: int, t: float) -> None:
        """An Imu message sent at ``src_ns`` (DDS source timestamp) with stamp ``t``: the depths
        waiting for a sample sent after them take effect at the last one sent before."""
        self._sent.append((src_ns, t))
        if self._depths_waiting and self._depths_waiting[0][0] < src_ns:
            ready = [d for d in self._depths_waiting if d[0] < src_ns]
            self._depths_waiting = [d for d in self._depths_waiting if d[0] >= src_ns]
            for d_src, value in ready:
                self._place_depth(d_src, value)

    def _place_depth(self, d_src: int, value: float) -> None:
        k = bisect.bisect_left(self._sent, (d_src, -math.inf)) - 1   # the last Imu sent before it
        self.depths.add(self._sent[k][1] if k >= 0 else -math.inf, (value,))

    def _on_depth(self, msg, info=None):
        """The unstamped depth holds from the sample the probe sent next: placed by the DDS source
        timestamps (the probe publishes it just before that sample), not by when it is taken here,
        which under load can be before or after samples sent earlier (each topic has its reader);
        it waits until a sample sent after it has arrived.  Without message info (a direct call),
        after the last sample processed."""
        value = float(msg.data)
        src = info.get("source_timestamp", 0) if info is not None else 0
        if not src:
            self.depths.add(self._t_sample, (value,))
        elif self._sent and self._sent[-1][0] > src:
            self._place_depth(src, value)            # late: samples sent after it are in already
        else:
            self._depths_waiting.append((src, value))

    def _on_reference(self, msg):
        self.refs.add(c.stamp_to_sec(msg.header.stamp), (msg.vector.x, msg.vector.y, msg.vector.z))
        self._release(force=False)

    def _release(self, force: bool, end: bool = False):
        """Publish the waiting stations whose reference is known (all of them with ``force``: the
        wait ran out, or the stream ended — ``end``: then what was received is all there is), in order."""
        pending = self._pending
        while pending and (force or self._current_at(pending[0][0].t_end)):
            st, since = pending.popleft()
            if not end and not self.refs.current_at(st.t_end):
                self.get_logger().warning(
                    f"station closed at t={st.t_end:.2f} s: no {c.TOPIC_REFERENCE} up to its end after "
                    f"{time.monotonic() - since:.1f} s (delayed or lost): published with the reference "
                    "last received, which may be the previous station's")
            if not end and not self._temps_in(st.t_end):
                self.get_logger().warning(
                    f"station closed at t={st.t_end:.2f} s: no {c.TOPIC_TEMPERATURE} up to its end after "
                    f"{time.monotonic() - since:.1f} s (delayed or lost): published with the temperatures "
                    "received so far")
            if not self._readers_in():
                self.get_logger().warning(
                    f"station closed at t={st.t_end:.2f} s: {self.pub_station.get_subscription_count()} of "
                    f"{self.wait_readers} {c.TOPIC_STATION} readers matched after {time.monotonic() - since:.1f} s: "
                    "published, and the readers not matched yet miss it")
            self._publish_station(st)

    def _sample(self, t, f, m):
        self._t_sample = t
        c.feed_sample(self, t, f, m, self._station)

    # ---- stations --------------------------------------------------------------------------
    def _station(self, seg):
        """A closed station: published at once, or when the reference is known to be current up to
        its end (:class:`streaming.ReferenceTrack`) and its readers are matched (at most
        ``reference_wait_s`` later)."""
        if seg.short and not self.publish_short:
            return
        if not math.isfinite(seg.md_m):    # the depth it was held at (in effect at its middle)
            d = self.depths.at(seg.t_mid)
            seg.md_m = d[0] if d is not None else math.nan
        if self._pending or not self._current_at(seg.t_end):
            self._pending.append((seg, time.monotonic()))
            return
        self._publish_station(seg)

    def _publish_station(self, seg):
        ref = self.refs.at(0.5 * (seg.t_start + seg.t_end))
        has_ref = ref is not None   # a partial reference is used for what it gives
        if self._have_temp:   # the temperatures stamped within it, now that they are in (they may come late)
            seg.temp_c = self.detector.temps.mean(seg.t_start, seg.t_end)
            self.detector.temps.forget_before(seg.t_start)   # published in time order: no earlier one will ask
        fields = self.processor.process(seg, ref=ref, have_temperature=self._have_temp)
        for w in seg.warnings:
            if w == NO_SITE:          # said once, not at every station before the first record
                if self._no_site_said:
                    continue
                self._no_site_said = True
            self.get_logger().warning(f"station {fields['station_id']}: {w}")
        msg = SurveyStation()
        c.set_stamp(msg.header.stamp, seg.t_end)
        msg.header.frame_id = self.frame_id
        for name, value in fields.items():
            setattr(msg, name, value)
        verdict = self.processor.monitor.last if self.processor.monitor is not None else None
        if verdict is not None and verdict.misfit and (self._last_verdict is None or not self._last_verdict.misfit):
            self.get_logger().warning(f"station {msg.station_id}: {verdict.text}")   # said when it starts
        elif verdict is not None and not verdict.misfit and self._last_verdict is not None and \
                self._last_verdict.misfit:
            self.get_logger().info(f"station {msg.station_id}: the model explains the survey again")
        self._last_verdict = verdict
        self._write_state()  # before publishing: a crash in between skips an id, never repeats one
        self.pub_station.publish(msg)
        self._last_diag = self._diagnostics(msg)
        self.pub_diag.publish(self._last_diag)
        text = (f"station {msg.station_id}: drift {msg.drift_deg:.3f} azimuth {msg.azimuth_deg:.3f} toolface "
                f"{msg.toolface_deg:.2f} deg; dG {msg.delta_g_mps2:+.4f} m/s^2 dB {msg.delta_b_nt:+.0f} nT "
                f"ddip {msg.delta_dip_deg:+.3f} deg; status {msg.status}"
                + (f"; ref drift {ref[0]:g} azimuth {ref[1]:g}" if has_ref else ""))
        # a station not to be used (status error: the probe moved, |G| out of tolerance) is said at WARNING
        # (rclpy ties a severity to its call site: two calls)
        if msg.status == SurveyStation.STATUS_ERROR:
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)

    def _diagnostics(self, st):
        tol = self.tol

        def check(name, measured, reference, delta, tolerance, unit, bad_level):
            s = DiagnosticStatus(name=f"inclinometer_calib: {name}", hardware_id=self.probe_id)
            ok = math.isfinite(delta) and abs(delta) <= tolerance
            s.level = DiagnosticStatus.OK if ok else bad_level
            s.message = (f"{name} {measured:.5g} {unit} (reference {reference:.5g}, delta {delta:+.4g}, "
                         f"tolerance {tolerance:g})")
            s.values = [KeyValue(key="measured", value=f"{measured:.6g}"),
                        KeyValue(key="reference", value=f"{reference:.6g}"),
                        KeyValue(key="delta", value=f"{delta:.6g}"),
                        KeyValue(key="tolerance", value=f"{tolerance:g}"),
                        KeyValue(key="unit", value=unit),
                        KeyValue(key="station_id", value=str(st.station_id))]
            return s

        site = self.processor.site
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        probe = ([DiagnosticStatus(level=DiagnosticStatus.ERROR, name="inclinometer_calib: probe identity",
                                   hardware_id=self.probe_id, message=self._mismatch)] if self._mismatch else [])
        if site is None:
            arr.status = [DiagnosticStatus(level=DiagnosticStatus.WARN, name="inclinometer_calib: site reference",
                                           hardware_id=self.probe_id, message=NO_SITE)]
        else:
            arr.status = [
                check("total gravity", st.total_gravity_mps2, site.gravity_mps2, st.delta_g_mps2, tol.gravity_mps2,
                      "m/s^2", DiagnosticStatus.ERROR),
                check("total field", st.total_field_nt, site.total_field_nt, st.delta_b_nt, tol.field_nt, "nT",
                      DiagnosticStatus.WARN),
                check("dip", st.dip_deg, site.dip_deg, st.delta_dip_deg, tol.dip_deg, "deg", DiagnosticStatus.WARN),
            ]
        monitor = self.processor.monitor
        if monitor is not None and self.calibration is not None:
            v = monitor.last
            m = DiagnosticStatus(name="inclinometer_calib: model", hardware_id=self.probe_id)
            m.level = DiagnosticStatus.WARN if v.misfit else DiagnosticStatus.OK
            m.message = v.text if v.misfit else (
                f"record {self.calibration.id} explains the last {v.stations} stations (no trend of the residuals "
                "against temperature, time or orientation)" if v.stations >= monitor.min_stations else
                f"{v.stations} of {monitor.min_stations} stations needed to test the model")
            m.values = [KeyValue(key="coefficients_id", value=self.calibration.id),
                        KeyValue(key="stations_tested", value=str(v.stations)),
                        KeyValue(key="model", value=self.calibration.model.describe())]
            for k, cand in enumerate(v.candidates[:3]):
                m.values.append(KeyValue(key=f"candidate_{k + 1}", value=f"{cand['label']} (score {cand['score']:.2f})"))
            for k, tr in enumerate(v.trends[:3]):
                m.values.append(KeyValue(key=f"trend_{k + 1}", value=f"{tr['channel']} ~ {tr['regressor']} "
                                                                       f"(R² {tr['r2']:.2f})"))
            arr.status.append(m)
        arr.status.extend(probe)
        summary = DiagnosticStatus(name="inclinometer_calib: station", hardware_id=self.probe_id)
        summary.level = max(s.level for s in arr.status)
        summary.message = (f"station {st.station_id}: {_LEVEL_NAMES[summary.level]}; coefficients "
                           f"{st.coefficients_id or 'none (raw)'}")
        summary.values = [KeyValue(key="drift_deg", value=f"{st.drift_deg:.4f}"),
                          KeyValue(key="azimuth_deg", value=f"{st.azimuth_deg:.4f}"),
                          KeyValue(key="toolface_deg", value=f"{st.toolface_deg:.3f}"),
                          KeyValue(key="coefficients_id", value=st.coefficients_id)]
        arr.status.append(summary)
        return arr

    def _check_pairing(self):
        """Warn when samples of one stream find no partner of the other (absent field or imu): no
        pair completed since the last check while samples of one stream wait (or were evicted)."""
        pr = self.pairer
        waiting = pr.waiting
        new = pr.unpaired - self._unpaired_seen + max(waiting - self._waiting_seen, 0)
        if new > 0 and pr.paired == self._paired_seen:
            lone, other = ((c.TOPIC_IMU, c.TOPIC_MAG) if len(pr._imu) >= len(pr._mag)
                           else (c.TOPIC_MAG, c.TOPIC_IMU))
            self.get_logger().warning(f"{new} samples on {lone} without a {other} partner (same stamp) since the "
                                      f"last check: {other} absent or stamped differently; no stations from them")
        self._unpaired_seen, self._paired_seen, self._waiting_seen = pr.unpaired, pr.paired, waiting

    def _on_timer(self):
        self._check_pairing()
        if (self.idle_flush > 0 and self._last_wall is not None
                and time.monotonic() - self._last_wall > self.idle_flush):
            self._last_wall = None  # end of stream: close the last station
            closed = self.detector.flush()
            for st in closed:
                self._station(st)
            for e in self.detector.pop_events():
                self.get_logger().warning(e)
            self._release(force=True, end=True)
            if closed:
                return
        if self._pending and time.monotonic() - self._pending[0][1] > self.reference_wait:
            self._release(force=True)
        if not c.ros_time_started(self):
            return  # use_sim_time and no /clock yet: nothing to stamp the heartbeat with
        if self._last_diag is None:
            arr = DiagnosticArray()
            arr.header.stamp = self.get_clock().now().to_msg()
            arr.status = [DiagnosticStatus(level=DiagnosticStatus.STALE, name="inclinometer_calib: station",
                                           hardware_id=self.probe_id, message="no survey station yet")]
            self.pub_diag.publish(arr)
        else:
            self._last_diag.header.stamp = self.get_clock().now().to_msg()
            self.pub_diag.publish(self._last_diag)


def main(args=None):
    return c.run(CorrectionNode, args)


if __name__ == "__main__":
    sys.exit(main())

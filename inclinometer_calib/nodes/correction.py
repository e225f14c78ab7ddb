"""Correction node: applies the latest calibration and publishes quality-checked survey stations.

Inputs: ``/probe/imu`` + ``/probe/mag`` (paired by header stamp), ``/probe/temperature``,
``/probe/reference`` (optional reference attitudes), ``/probe/depth`` (optional measured depth: a
station takes the latest when it closes, and gets its trajectory by minimum curvature from the
station before it in depth — :meth:`pipeline.SurveyProcessor`), and the coefficients: the latched topic
``/calibration/coefficients`` (transient-local subscription; ``use_topic``) and/or a coefficient
YAML file (``coeffs_file``, may be changed at run time: the file is checked before it is
accepted).  Keeping step with the calibration node (``calibration.node``, the launcher sets it) a
record applies from the data time it was solved at (its header stamp) and a station waits until
that node has taken it too; otherwise a record applies from the next station.  All of it is the
stream engine's (:class:`engine.StreamEngine`, the one ``reprocess`` drives), in its survey role,
through :class:`.stream.StreamDriver`: the node publishes what the engine gives.

Recovery (a node restarted mid-run): with ``resume.bags`` (the launcher sets it) the node rebuilds
its state from the run's recording and publishes only the stations it does not hold.  Without a
recording, ``fallback_coeffs_file`` is the last valid record on disk (the calibration node's
``output``), applied at start-up with a warning until a record arrives on the topic (one that
differs replaces it), and ``state_file`` keeps the next station id (JSON, written atomically after
every station), so the ids of a restarted node continue instead of starting again at 0.

Outputs:

* ``/survey/station`` (``SurveyStation``, reliable, transient local keep 1000): one per static interval closed by the
  static detector, through the survey pipeline (:class:`pipeline.SurveyProcessor`): corrected by
  the current record's model (its lab effects too, with the station's temperature and time),
  evaluated against the site reference **the record owns** (``site.given:=true`` overrides it
  with the ``site.*`` parameters, said at WARNING for every record it overrides; before any
  record and without a given site there is no reference and the stations say so), with its
  azimuth, reference azimuth and position along one north (``north``: ``grid``, ``true``,
  ``magnetic`` or ``auto`` — grid on a site with a grid, else true, else magnetic; the azimuths
  from the other norths in ``azimuth_true_deg``, ``azimuth_magnetic_deg``, ``azimuth_grid_deg``),
  and checked by the field monitor (:class:`lab.field.FieldMonitor`, ``monitor.window`` stations): when the
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

import collections
import json
import math
import os
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, MagneticField, Temperature

from ..core.coeffs import Calibration, CoefficientError
from ..correct.engine import StationOut, StreamEngine
from ..core.geomag import NORTH_CHOICES, azimuth_reference
from ..lab.field import FieldMonitor
from ..correct.pipeline import NO_SITE, SurveyProcessor
from ..core.plugins import NODE_PARAMETER, name_plugins
from ..core.output import atomic_write_text
from ..io.surveystation import to_msg as station_to_msg
from . import common as c
from .stream import StreamDriver, declare_stream_params, make_detector
from inclinometer_calib.msg import CalibrationCoefficients, SurveyStation

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
        publish_short = p.declare("publish_short", False, "Also publish static intervals shorter "
                                  "than detector.min_duration_s (is_static = false)", read_only=True)
        self.wait_readers = p.declare("wait_for_station_readers", 0, f"A station waits (at most reference_wait_s, "
                                      f"then said) until {c.TOPIC_STATION} has this many matched readers: stations are "
                                      "reliable but volatile, and a reader the graph shows but DDS has not yet matched "
                                      "misses what is published before (the launcher sets it to the readers it "
                                      "starts)", read_only=True, range=(0, 100))
        north = p.declare("north", "auto", "North of every station's azimuth_deg, reference azimuth, north_m/east_m "
                          "and trajectory: grid, true or magnetic; auto: grid on a site with a grid (crs), else "
                          "true with a declination, else magnetic (the other azimuths are carried beside it)",
                          read_only=True, choices=NORTH_CHOICES)
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
        settings = declare_stream_params(p, calibration_sync=True)
        self.reference_wait = settings["patience"]
        self.add_post_set_parameters_callback(self._after_set)

        monitor = FieldMonitor(window=window, materiality=materiality, tolerances=self.tol) if window else None
        self.processor = SurveyProcessor(self.tol, site=site, axial=axial, monitor=monitor, force_probe=force_probe,
                                         north=north)   # ValueError (one line, exit 2): grid asked, the site has none
        # station ids continue across restarts: from the state file, or rebuilt from the recording
        self._published_next = self._read_state()
        resuming = any(os.path.exists(b) for b in settings["resume"])
        self.processor._next_id = 0 if resuming else self._published_next
        # the same engine as the calibration node's and reprocess's, in the survey role
        self.engine = StreamEngine(make_detector(settings), self.processor,
                                   sync_calibration=bool(settings["calibration_node"]),
                                   gate_limits=settings["gates"],
                                   gravity_mps2=site.gravity_mps2 if site is not None else None,
                                   publish_short=publish_short)
        self.detector = self.engine.det
        if site is None:
            self.get_logger().info("the site reference is the calibration record's (site.given is false); azimuths "
                                   f"and positions along north '{north}' on it")
        else:
            self.get_logger().info(f"azimuths and positions along {azimuth_reference(site, north)}")
        self._fallback_id = None     # id of the record applied from fallback_coeffs_file, until replaced
        self._temp = c.NAN           # the latest temperature (the corrected streams)
        self._outbox = collections.deque()   # (StationOut, monotonic time) waiting for their readers
        self._last_diag = None
        self._last_verdict = None
        self._no_site_said = False

        # reliable, and transient local (keep last 1000): a reader restarted mid-run (the recorder) gets
        # the stations it missed meanwhile
        self.pub_station = self.create_publisher(SurveyStation, c.TOPIC_STATION, c.latched_qos(depth=1000))
        self.pub_diag = self.create_publisher(DiagnosticArray, c.TOPIC_DIAGNOSTICS, c.reliable_qos(10))
        qos = settings["qos"]
        self.pub_imu = self.create_publisher(Imu, c.TOPIC_IMU_CORRECTED, qos)
        self.pub_mag = self.create_publisher(MagneticField, c.TOPIC_MAG_CORRECTED, qos)
        # the samples, reference and depth on a wait set of their own (common.HotPathExecutor, through
        # common.run), and the record there too, taken in turn with them
        self.stream = StreamDriver(self, settings, self.engine, self._on_events, side=True)
        hot = list(self.stream.hot_subscriptions)
        if self.use_topic:
            hot.append(self.create_subscription(CalibrationCoefficients, c.TOPIC_COEFFICIENTS, self._on_coefficients,
                                                c.latched_qos()))
        self.hot_subscriptions = tuple(hot)
        if coeffs_file:
            self._apply(Calibration.load(coeffs_file), f"file {coeffs_file}")
        if resuming:
            # a restart: the state of the node that died, rebuilt from the run's recording (the records
            # in it too, each from the data time it applies); what it published already is held back
            self.stream.resume(settings["resume"], records=self.use_topic)
        elif not coeffs_file and fallback:
            self._apply_fallback(fallback)
        elif self._published_next:
            self.get_logger().warning(f"restarted without the run's recording (resume.bags): station ids continue at "
                                      f"{self._published_next}, but the stations that closed while no node ran and "
                                      "the state before (noise estimate, trajectory, field monitor) are not rebuilt")
        c.steady_timer(self, 1.0, self._on_timer)  # keeps running when /clock (use_sim_time) stops
        c.steady_timer(self, 0.1, self._flush_outbox)

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
                self._apply(Calibration.load(prm.value), f"file {prm.value}", from_now=True)
            elif prm.name == "publish_corrected":
                self.publish_corrected = prm.value

    @property
    def calibration(self):
        """The newest record received (the one the next stations take, unless one is stamped later)."""
        return self.engine.calibration

    def _apply(self, cal: Calibration, origin: str, stamp=None, from_now: bool = False):
        """Hand a record to the engine: from the start of the data (a file given at start-up), from
        the next station (``from_now``), or — keeping step with the calibration node — from the data
        time it was solved at (``stamp``)."""
        if from_now:
            stamp = self.engine.released_t
        if not self.engine.record(cal, stamp, origin):
            self.stream._after()
            return
        self.get_logger().info(f"applying coefficients {cal.id} (probe {cal.probe_id}, model {cal.model.describe()}, "
                               f"site {cal.site_source}) from {origin}"
                               + (f" to the stations ending after t={stamp:.3f} s" if stamp is not None
                                  and math.isfinite(stamp) else ""))
        if "temperature" in cal.needs and not self.engine.have_temp:
            self.get_logger().warning(f"record {cal.id} has temperature effects ({', '.join(cal.model.labels())}): "
                                      f"stations need {c.TOPIC_TEMPERATURE}, none received yet")
        self.stream._after()

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
        if self.engine.sync:
            self._apply(cal, c.TOPIC_COEFFICIENTS, stamp=c.stamp_to_sec(msg.header.stamp))
        elif self.calibration is None or cal.id != self.calibration.id:
            self._apply(cal, c.TOPIC_COEFFICIENTS, from_now=True)

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

    def _write_state(self, next_id: int):
        """Persist the next station id (atomically: a crash leaves the old or the new file, never half)."""
        if not self.state_file:
            return
        state = {"format": "inclinometer_calib/correction_state", "next_station_id": next_id}
        try:
            atomic_write_text(self.state_file, json.dumps(state) + "\n")
        except OSError as exc:
            self.get_logger().error(f"cannot write the state file {self.state_file}: {exc}",
                                    throttle_duration_sec=10.0)

    # ---- what the engine produced ------------------------------------------------------------
    def _on_events(self, events, msg=None, info=None):
        if msg is not None and self.publish_corrected and self.calibration is not None:
            self._publish_corrected(msg)
        for ev in events:
            if isinstance(ev, StationOut):
                if ev.fields["station_id"] in self.stream.recorded_stations:
                    continue      # rebuilt after a restart: the recording holds it (published by the node that died)
                self._outbox.append((ev, time.monotonic()))
        if self._outbox:
            self._flush_outbox()

    def _publish_corrected(self, sample):
        """One sample the stream driver took (``(type, CDR bytes)``: taken raw) corrected and published."""
        msg_type, data = sample
        msg = deserialize_message(data, msg_type)
        if isinstance(msg, Temperature):
            self._temp = msg.temperature
            return
        t = c.stamp_to_sec(msg.header.stamp)
        if isinstance(msg, Imu):
            v = self._correct_stream("acc", c.gravity(msg), t)
            if v is not None:
                c.set_gravity(msg, v)
                self.pub_imu.publish(msg)
        elif isinstance(msg, MagneticField):
            v = self._correct_stream("mag", c.field_nt(msg), t)
            if v is not None:
                mf = msg.magnetic_field
                mf.x, mf.y, mf.z = v[0] * c.TESLA_PER_NT, v[1] * c.TESLA_PER_NT, v[2] * c.TESLA_PER_NT
                self.pub_mag.publish(msg)

    def _correct_stream(self, sensor, h, t):
        """One sample of one stream through the record's correction (:meth:`model.CorrectionPlan.correct_sample`:
        the path the stations take, in plain floats), with the latest temperature and the time since
        the first sample; None (and a warning) when the model needs a temperature there is none of."""
        t0 = self.detector.t_first
        have = self.engine.have_temp and self._temp == self._temp
        try:
            return self.calibration.plan.correct_sample(sensor, h, self._temp if have else None,
                                                        t - t0 if t0 == t0 else 0.0)
        except ValueError as exc:
            self.get_logger().warning(f"corrected {sensor} stream not published: {exc}", throttle_duration_sec=10.0)
            return None

    def _readers_in(self) -> bool:
        return self.wait_readers <= 0 or self.pub_station.get_subscription_count() >= self.wait_readers

    def _flush_outbox(self):
        """Publish the stations whose readers are matched (``wait_for_station_readers``), in order;
        after ``reference_wait_s`` they go anyway, said."""
        box = self._outbox
        while box:
            ev, since = box[0]
            if not self._readers_in():
                waited = time.monotonic() - since
                if waited <= self.reference_wait:
                    return
                self.get_logger().warning(
                    f"station {ev.fields['station_id']}: {self.pub_station.get_subscription_count()} of "
                    f"{self.wait_readers} {c.TOPIC_STATION} readers matched after {waited:.1f} s: published, and "
                    "the readers not matched yet miss it")
            box.popleft()
            self._publish_station(ev)

    # ---- stations --------------------------------------------------------------------------
    def _publish_station(self, ev):
        fields, seg, ref = ev.fields, ev.station, ev.ref
        for w in fields["warnings"]:
            if w == NO_SITE:          # said once, not at every station before the first record
                if self._no_site_said:
                    continue
                self._no_site_said = True
            self.get_logger().warning(f"station {fields['station_id']}: {w}")
        msg = SurveyStation()
        c.set_stamp(msg.header.stamp, seg.t_end)
        msg.header.frame_id = self.frame_id
        station_to_msg(fields, msg)
        verdict = self.processor.monitor.last if self.processor.monitor is not None else None
        if verdict is not None and verdict.misfit and (self._last_verdict is None or not self._last_verdict.misfit):
            self.get_logger().warning(f"station {msg.station_id}: {verdict.text}")   # said when it starts
        elif verdict is not None and not verdict.misfit and self._last_verdict is not None and \
                self._last_verdict.misfit:
            self.get_logger().info(f"station {msg.station_id}: the model explains the survey again")
        self._last_verdict = verdict
        self.pub_station.publish(msg)
        # after publishing: a crash in between publishes it again after the restart (the same id and
        # values, counted once), never loses it
        self._published_next = msg.station_id + 1
        self._write_state(self._published_next)
        self._last_diag = self._diagnostics(msg)
        self.pub_diag.publish(self._last_diag)
        text = (f"station {msg.station_id}: drift {msg.drift_deg:.3f} azimuth {msg.azimuth_deg:.3f} toolface "
                f"{msg.toolface_deg:.2f} deg; dG {msg.delta_g_mps2:+.4f} m/s^2 dB {msg.delta_b_nt:+.0f} nT "
                f"ddip {msg.delta_dip_deg:+.3f} deg; status {msg.status}"
                + (f"; ref drift {ref[0]:g} azimuth {ref[1]:g}" if ref is not None else "")
                + (f"; uncorrected ({msg.uncorrected_reason})" if msg.uncorrected_reason else ""))
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
        refusal = self.engine.refusal
        probe = ([DiagnosticStatus(level=DiagnosticStatus.ERROR, name="inclinometer_calib: probe identity",
                                   hardware_id=self.probe_id, message=refusal)] if refusal else [])
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

    def _on_timer(self):
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

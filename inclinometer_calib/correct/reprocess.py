"""Offline reprocessing of a recorded bag: read → pair → detect stations → correct → write.

ROS-free on purpose (no rclpy, no generated message modules): the probe's messages are decoded
from their CDR bytes by :mod:`inclinometer_calib.io.cdr` (the fast path of :mod:`io.bag`'s
decoding), the output ``SurveyStation`` messages are serialized with ``bag.MessageEncoder`` (the
``rosbags`` type store, our ``msg/SurveyStation.msg`` registered), and the bag is read and
written with :mod:`inclinometer_calib.io.bag`.  It does offline what the correction node does live:

* ``/probe/imu`` (``sensor_msgs/Imu``: REP-145 specific force, m/s²) and ``/probe/mag``
  (``sensor_msgs/MagneticField``: tesla, converted once to nT) are paired by header stamp;
* ``/probe/temperature`` (``sensor_msgs/Temperature``) gives the temperature of later samples;
* ``/probe/reference`` (``geometry_msgs/Vector3Stamped``, drift/azimuth/toolface in degrees,
  NaN = none), if present, is copied into the stations' ``reference_*`` fields;
* every message goes to the stream engine (:class:`engine.StreamEngine`, through
  :class:`BagFeeder`) exactly as the live nodes hand it theirs: pairs through the static detector
  (thresholds from the noise the data show; the messages' covariance a prior), each closed station
  — once what it waits for is in — through the gates and the survey pipeline
  (:class:`pipeline.SurveyProcessor`: the record's model with the station's temperature and time,
  QC against the record's site, the field monitor), written as one ``/survey/station`` message
  (the correction node's fields);
* with ``calibrate`` the same stations go through the live calibration node's twelve-pose
  session (:class:`capture.CaptureSession`): each solve is written as one
  ``/calibration/coefficients`` message, stamped with the data time from which it applies, and
  corrects the stations that end after it — offline, the whole live graph, whose replay of the
  same bag gives the same stations bit for bit.

The input messages of those four topics are copied through unchanged (same bytes, log and publish
times), so the output bag can be replayed again.  Other topics are skipped with a warning that
names them and their type (e.g. a previous run's ``/survey/station``, which the new one replaces).

Damage does not lose data: a truncated or corrupt input is read up to the damage (and past a bad
chunk when the framing allows), everything readable is processed and written, and the report's
``bag_errors`` say where the damage is (file and byte offset).  Per-message problems (a message
that does not decode, a pair whose stamp goes backwards, an implausible field) are counted and
reported with the topic and the log time of the first one.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np

from ..io.bag import DEFAULT_QOS_PROFILE, BagError, BagWriter, MessageEncoder, message_encoder, open_bag, read_messages
from ..calibrate.capture import CaptureSession
from ..io.cdr import (DECODE_ERRORS, Patcher, decode_float64, decode_imu_covariance, decode_imu_gravity, decode_mag_covariance,
                  decode_string, decode_temperature, decode_vector3, header)
from ..core.deps import require
from ..core.frames import NT_PER_TESLA, Site
from ..core.coeffs import message_fields
from .engine import Expect, RecordOut, StationOut, StreamEngine
from .pipeline import SurveyProcessor
from ..detect.streaming import StaticDetector
from ..core.survey import Tolerances
from ..io.topics import (COEFFICIENTS_TYPE, DEPTH_TYPE, GRAPH_OUTPUTS, IMU_TYPE, MAG_TYPE, PROBE_TOPICS,
                     REFERENCE_TYPE, STATION_TYPE, TEMPERATURE_TYPE, TOPIC_COEFFICIENTS, TOPIC_DEPTH, TOPIC_IMU,
                     TOPIC_MAG, TOPIC_REFERENCE, SERIAL_TYPE, TOPIC_SERIAL, TOPIC_STATION,
                     TOPIC_TEMPERATURE)

#: Input topics read (and copied through) and the type each must have.
INPUT_TOPICS = PROBE_TOPICS



class ReprocessError(ValueError):
    """The input cannot be reprocessed at all (no probe samples, wrong units throughout...)."""


def bag_probe_serial(path) -> Optional[str]:
    """The probe serial a bag records (its first ``/probe/serial`` message), or None when it has
    none.  Raises :class:`bag.BagError` if ``path`` is not a bag."""
    try:
        for _m, serial in read_messages(path, [TOPIC_SERIAL], strict=False):
            return serial
    except DECODE_ERRORS as exc:
        raise ReprocessError(f"{path}: undecodable {TOPIC_SERIAL} message ({exc})") from None
    return None


class BagFeeder:
    """Hands a bag's probe messages to a :class:`engine.StreamEngine` as the live nodes hand it
    theirs (the same decoding boundary: MagneticField tesla → nT, the first covariance a prior;
    a depth placed by its publish time, the send order the recorder keeps).  With
    ``records=True`` the coefficient records in the bag go to the engine too, by their stamps,
    (a restarted node resuming from its run's recording).  :attr:`last` keeps, per topic, the key
    of the last message fed (the stamp, or the publish time of the unstamped depth); with
    ``dedupe`` a message whose key is not after it is skipped (a bag part written by a restarted
    recorder begins with what the last one ended with) — and what a resuming node skips live."""

    _STAMPED = (TOPIC_IMU, TOPIC_MAG, TOPIC_TEMPERATURE, TOPIC_REFERENCE)

    def __init__(self, engine, *, records: bool = False, dedupe: bool = False):
        self.engine = engine
        self.records = records
        self.dedupe = dedupe
        self.prior = {}
        self.last: Dict[str, float] = {}
        self.record_ids: List[str] = []        # ids of the coefficient records seen, in order
        self.duplicates = 0

    def seen(self, m) -> bool:
        """Whether ``m`` was fed already (its key is not after the last one of its topic)."""
        last = self.last.get(m.topic)
        if last is None:
            return False
        if m.topic == TOPIC_DEPTH:
            return m.publish_time <= last
        if m.topic in self._STAMPED:
            sec, nsec, _, _ = header(m.data)
            return sec + 1e-9 * nsec <= last
        return False

    def feed(self, m) -> str:
        """Feed one bag message; returns "" or what is wrong with it (undecodable)."""
        eng, topic = self.engine, m.topic
        try:
            if self.dedupe and self.seen(m):
                self.duplicates += 1
                return ""
            if topic == TOPIC_IMU:
                key, g = decode_imu_gravity(m.data)
                if "acc" not in self.prior:
                    self.prior["acc"] = decode_imu_covariance(m.data)
                eng.imu(key, g, m.publish_time, self.prior["acc"])
                self.last[topic] = key[0] + 1e-9 * key[1]
            elif topic == TOPIC_MAG:
                key, b = decode_vector3(m.data)
                if "mag" not in self.prior:
                    self.prior["mag"] = decode_mag_covariance(m.data) * NT_PER_TESLA
                eng.mag(key, (b[0] * NT_PER_TESLA, b[1] * NT_PER_TESLA, b[2] * NT_PER_TESLA), self.prior["mag"])
                self.last[topic] = key[0] + 1e-9 * key[1]
            elif topic == TOPIC_DEPTH:
                eng.depth(decode_float64(m.data), m.publish_time)
                self.last[topic] = m.publish_time
            elif topic == TOPIC_TEMPERATURE:
                key, temp = decode_temperature(m.data)
                eng.temperature(key[0] + 1e-9 * key[1], temp)   # by stamp, as the nodes do
                self.last[topic] = key[0] + 1e-9 * key[1]
            elif topic == TOPIC_REFERENCE:
                key, v = decode_vector3(m.data)
                eng.reference(key[0] + 1e-9 * key[1], v)
                self.last[topic] = key[0] + 1e-9 * key[1]
            elif topic == TOPIC_SERIAL:
                eng.set_serial(decode_string(m.data))
            elif topic == TOPIC_COEFFICIENTS:
                fields = self.codec.decode(COEFFICIENTS_TYPE, m.data)
                if fields["id"] not in self.record_ids:
                    self.record_ids.append(fields["id"])
                    if self.records:
                        from ..core.coeffs import Calibration
                        cal = Calibration.from_yaml(fields["coefficients_yaml"], source=f"{topic} in {m.topic}")
                        eng.record(cal, fields["stamp"] if eng.sync else eng.released_t, topic)
        except DECODE_ERRORS as exc:
            return f"undecodable {topic} message ({exc})"
        return ""

    @property
    def codec(self) -> MessageEncoder:
        """Our messages' CDR (the records here, a resuming node's progress and stations)."""
        return message_encoder()


# ---------------------------------------------------------------------------------------------

@dataclass
class _Issue:
    """A kind of per-message problem: how often, and where it happened first."""

    count: int = 0
    first: str = ""

    def add(self, where: str, n: int = 1) -> None:
        if not self.count:
            self.first = where
        self.count += n


@dataclass
class ReprocessReport:
    """What :func:`reprocess` read, produced and had to skip."""

    source: Path
    destination: Path
    stations: List[dict] = field(default_factory=list)    # SurveyStation fields per station
    messages_read: int = 0
    copied: Dict[str, int] = field(default_factory=dict)  # input messages copied, per topic
    skipped_topics: Dict[str, str] = field(default_factory=dict)  # topic -> "type: reason"
    graph_outputs: Dict[str, str] = field(default_factory=dict)   # a recorded run's own outputs, not read
    pairs: int = 0
    short_intervals: int = 0                               # static but shorter than min_duration_s
    issues: Dict[str, _Issue] = field(default_factory=dict)
    bag_errors: List[BagError] = field(default_factory=list)
    log_span_s: float = 0.0                                # time the input's samples cover (their stamps), s
    seconds: float = 0.0                                   # wall time of the run
    events: List[str] = field(default_factory=list)        # the detector's messages (pieces, noise)
    calibration_warnings: List[str] = field(default_factory=list)   # the capture session's (calibrate)
    calibrations: List[object] = field(default_factory=list)        # each solve (calibrate), in order
    calibration_state: str = ""                            # calibrate: done | error | collecting
    calibration_message: str = ""
    noise: object = None                                   # the noise.NoiseLevel the detector used
    probe_serial: str = ""                                 # the data's probe (the bag's /probe/serial)
    notes: List[str] = field(default_factory=list)         # what the pipeline said (a site override)
    raw_stations: List[object] = field(default_factory=list)   # each station.Station published, raw means, with
    #                                                            its reference in .ref (NaN: none): the lab's input
    captures: List[object] = field(default_factory=list)   # calibrate: the capture session's accepted poses
    counts: Dict[str, int] = field(default_factory=dict)    # what came in and what became of it (engine.Counts)

    def stamped_stations(self) -> list:
        """The stations as the written bag reads them back: the ``SurveyStation`` fields and their
        ``stamp`` (s, the data time of the hold's end, as in the header)."""
        return [dict(s, stamp=float(st.t_end)) for s, st in zip(self.stations, self.raw_stations)]

    def _issue(self, kind: str, where: str, n: int = 1) -> None:
        self.issues.setdefault(kind, _Issue()).add(where, n)

    def warnings(self) -> List[str]:
        out = [f"skipped topic {t} ({why})" for t, why in self.skipped_topics.items()]
        for kind, iss in self.issues.items():
            out.append(f"{iss.count} × {kind} (first: {iss.first})")
        if self.short_intervals:
            out.append(f"{self.short_intervals} static interval(s) shorter than the minimum duration "
                       "not reported as stations (static window too short)")
        out.extend(self.notes)
        out.extend(self.events)
        out.extend(self.calibration_warnings)
        moved = sum(1 for st in self.stations if st["moved_during_capture"])
        if moved:
            out.append(f"{moved} station(s) where the probe moved during the hold (status error, reasons in "
                       "their warnings)")
        return out


class _NoWriter:
    """Stands in for the BagWriter when only the report is wanted (``dst`` None)."""

    def add_topic(self, *args, **kwargs) -> int:
        return -1

    def write(self, *args) -> None:
        pass

    def close(self) -> None:
        pass


def _where(topic: str, log_time: int) -> str:
    return f"{topic} at log time {log_time / 1e9:.9f} s"


def reprocess(src, dst, calibration=None, site: Optional[Site] = None, tolerances: Tolerances = Tolerances(),
              detector: Optional[StaticDetector] = None, *, compression: str = "zstd",
              frame_id: str = "probe", copy_input: bool = True,
              warn: Optional[Callable[[str], None]] = None, calibrate: bool = False,
              probe_id: str = "probe", effects: str = "", monitor=None, force_probe: bool = False,
              probe_serial: Optional[str] = None, north: str = "auto",
              progress: Optional[Callable[[int, int], None]] = None) -> ReprocessReport:
    """Reprocess the bag ``src`` into a new bag ``dst`` (which must not exist: never overwritten;
    None: nothing is written, the report's stations are the result).

    ``calibration``: a :class:`coeffs.Calibration` or None (uncorrected figures).  ``site``: a site
    reference overriding the record's (None: the record owns it; with ``calibrate`` and no site,
    the stand's measured one).  ``effects``: with ``calibrate``, the model to fit on the captures
    beyond the paper's (the package's effect grammar).  ``monitor``: a
    :class:`lab.field.FieldMonitor` (the correction node's model check) or None.  ``north``: the
    north of the stations' azimuths and positions, as the correction node's ``north``
    (:class:`pipeline.SurveyProcessor`).  ``detector``:
    a configured :class:`streaming.StaticDetector` (default: thresholds from the noise the data
    show).  The data's probe is the bag's ``/probe/serial`` (:func:`bag_probe_serial`; ``probe_serial``
    gives it for a bag without one): a record of another probe is refused (:class:`ReprocessError`)
    unless ``force_probe``, and then every station says so; with ``calibrate`` the records made are
    that probe's (else ``probe_id``'s).  ``calibrate``: run the live calibration node's twelve-pose session
    (:class:`capture.CaptureSession`) on the bag's stations, as the live graph does: each solve
    is written as ``/calibration/coefficients`` and applied to the stations that close after it
    (a station is never corrected by coefficients solved from itself — live, the station that
    completes a calibration may or may not be, as the coefficients race it to the correction
    node); ``calibration`` then
    only corrects the stations before the first solve.  ``warn`` is called with a message for
    each skipped topic as soon as it is seen.  Returns a :class:`ReprocessReport`; damage to
    ``src`` is in ``report.bag_errors`` (not raised).  ``progress(messages read, messages in the
    bag)`` every few thousand messages.  Raises :class:`FileExistsError` if
    ``dst`` exists, :class:`bag.BagError` if ``src`` is not a bag at all, :class:`ReprocessError`
    if it holds no probe samples.
    """
    t_wall = time.perf_counter()
    for module in ("mcap.writer", "rosbags.typesys"):  # MissingDependency before any work
        require(module, "bag", "reprocess")
    reader = open_bag(src)                      # BagError: not an MCAP / unreadable header
    report = ReprocessReport(Path(src), Path(dst) if dst is not None else None)
    det = detector if detector is not None else StaticDetector()
    # the side streams a station waits for: those the bag has (offline, waiting changes when a
    # station goes out, never what it is); a finalized bag says how many of each in its summary
    counts = reader.summary_counts()
    if counts is None:
        counts = {t: info.count for t, info in reader.topics.items()}
    if probe_serial is None:
        serial = bag_probe_serial(src) if counts.get(TOPIC_SERIAL, 0) else None
    else:
        serial = str(probe_serial)
    report.probe_serial = serial or ""
    proc = SurveyProcessor(tolerances, site=site, monitor=monitor, probe_serial=serial or "", force_probe=force_probe,
                           north=north)
    session = CaptureSession(site=site, probe_id=serial or probe_id, effects=effects) if calibrate else None
    engine = StreamEngine(det, proc, session, expect=Expect(reference=counts.get(TOPIC_REFERENCE, 0) > 0,
                                                               temperature=counts.get(TOPIC_TEMPERATURE, 0) > 0,
                                                               depth=counts.get(TOPIC_DEPTH, 0) > 0),
                          gravity_mps2=site.gravity_mps2 if site is not None else None)
    engine.set_serial(serial or "")
    if calibration is not None:
        if not engine.record(calibration, None, "given"):
            raise ReprocessError(f"{src}: {engine.refusal.split(': ', 1)[1]}: not applied (--force-probe applies it "
                                 "anyway)")
    encoder = message_encoder()

    # FileExistsError before anything is read; no destination: the stations only (the lab's input)
    writer = BagWriter(dst, compression=compression) if dst is not None else _NoWriter()
    station_cid = writer.add_topic(TOPIC_STATION, STATION_TYPE,
                                   qos_profiles=[dict(DEFAULT_QOS_PROFILE, depth=100)])
    coeff_cid = writer.add_topic(TOPIC_COEFFICIENTS, COEFFICIENTS_TYPE, qos_profiles=[dict(
        DEFAULT_QOS_PROFILE, depth=1, durability="transient_local")]) if calibrate else None
    out_cid: Dict[str, Optional[int]] = {}     # input topic -> output channel, None = skipped
    feeder = BagFeeder(engine)
    t_first_pair = t_last_pair = None
    copied = report.copied
    issue = report._issue
    where = [("", 0)]                           # the message being read (for what the engine says)
    first_seen = {}                             # per-sample issue (index in _SAMPLE_ISSUES) -> where first
    log_time = 0

    def drain():
        """What the engine produced, written in the order it came (log time: the input message's
        that completed it)."""
        for ev in engine.pop():
            if isinstance(ev, StationOut):
                st, fields = ev.station, ev.fields
                if ev.ref is not None:
                    st.ref = np.asarray(ev.ref, dtype=float)
                report.raw_stations.append(st)
                writer.write(station_cid, encoder.encode(STATION_TYPE, int(round(st.t_end * 1e9)), frame_id, fields),
                             log_time)
                report.stations.append(fields)
                for n in proc.notes:
                    if n not in report.notes:
                        report.notes.append(n)
            elif isinstance(ev, RecordOut):
                report.calibrations.append(ev.calibration)
                stamp = ev.stamp if math.isfinite(ev.stamp) else (t_last_pair or 0.0)
                writer.write(coeff_cid, encoder.encode(COEFFICIENTS_TYPE, int(round(stamp * 1e9)), frame_id,
                                                       message_fields(ev.calibration)), log_time)
            elif ev.level == "warning" and session is not None and _from_session(ev.text, session):
                report.calibration_warnings.append(ev.text)
            elif ev.text.startswith(_SAMPLE_ISSUES):
                first_seen.setdefault(_SAMPLE_ISSUES.index(next(k for k in _SAMPLE_ISSUES if ev.text.startswith(k))),
                                      _where(*where[0]) + ": " + ev.text)
            elif ev.level in ("warning", "error"):
                report.events.append(ev.text)

    def register(m) -> Optional[int]:
        want = INPUT_TOPICS.get(m.topic)
        if want is None:
            why = f"{m.type or 'unknown type'}: not a probe input topic (reads {', '.join(INPUT_TOPICS)})"
            if m.topic in GRAPH_OUTPUTS:
                why = f"{m.type}: an output of the live graph, not an input"
            if m.topic == TOPIC_STATION:
                why = f"{m.type}: stations of an earlier run, replaced by the reprocessed ones"
            elif m.topic == TOPIC_COEFFICIENTS and calibrate:
                why = f"{m.type}: coefficients of an earlier run, replaced by the reprocessed calibration"
        elif m.type != want:
            why = f"{m.type or 'unknown type'}: expected {want}"
        else:
            cid = -1
            if copy_input:
                info = reader.topic_info(m.topic)
                cid = writer.add_topic(m.topic, m.type, qos_yaml=info.qos_yaml, type_hash=info.type_hash,
                                       definition=info.definition,
                                       schema_encoding=info.schema_encoding or "ros2msg")
            out_cid[m.topic] = cid
            copied[m.topic] = 0
            return cid
        out_cid[m.topic] = None
        if m.topic in GRAPH_OUTPUTS and m.topic not in (TOPIC_STATION, TOPIC_COEFFICIENTS) or \
                (m.topic == TOPIC_STATION) or (m.topic == TOPIC_COEFFICIENTS and calibrate):
            report.graph_outputs[m.topic] = why   # a recorded run's own outputs: expected, made anew or not needed
            return None
        report.skipped_topics[m.topic] = why
        if warn is not None:
            warn(f"{src}: skipped topic {m.topic} ({why})")
        return None

    total = int(sum(counts.values()))
    try:
        for m in reader.messages(strict=False):
            report.messages_read += 1
            if progress is not None and report.messages_read % 4096 == 0:
                progress(report.messages_read, total)
            topic, log_time = m.topic, m.log_time
            cid = out_cid[topic] if topic in out_cid else register(m)
            if cid is None:
                continue
            if cid >= 0:
                writer.write(cid, m.data, log_time, m.publish_time)
                copied[topic] += 1
            where[0] = (topic, log_time)      # said only when something is wrong with it
            if topic == TOPIC_SERIAL:       # read before the loop (bag_probe_serial)
                try:
                    if decode_string(m.data) != report.probe_serial:
                        issue(f"a second probe serial in one bag ({decode_string(m.data)!r} after "
                              f"{report.probe_serial!r}), ignored", _where(topic, log_time))
                except DECODE_ERRORS as exc:
                    issue(f"undecodable {topic} message ({exc})", _where(topic, log_time))
                continue
            n_pairs = engine.counts.pairs
            problem = feeder.feed(m)
            if problem:
                issue(problem, _where(topic, log_time))
                continue
            if topic in (TOPIC_IMU, TOPIC_MAG) and engine.counts.pairs != n_pairs:
                t = engine.pairer.last_t
                if t_first_pair is None:
                    t_first_pair = t
                t_last_pair = t
            drain()
        engine.end()
        drain()
        c = engine.counts
        for k, (kind, n) in enumerate(((_ISSUE_KINDS[0], c.implausible), (_ISSUE_KINDS[1], c.nonfinite),
                                       (_ISSUE_KINDS[2], c.out_of_order))):
            if n:
                issue(kind, first_seen.get(k, ""), n)
        if c.unpaired:   # never paired: the other stream had no sample of that stamp
            issue("unpaired sample (no partner on the other stream with the same stamp)",
                  f"{engine.pairer.waiting} still waiting at the end of the bag", c.unpaired)
        if session is not None:
            report.calibration_state, report.calibration_message = session.state, session.message
            report.captures = list(session.captures)
    finally:
        writer.close()
    report.pairs = engine.counts.used
    report.short_intervals = engine.counts.short
    report.counts = engine.counts.as_dict()
    report.noise = det.noise_level
    report.bag_errors = list(reader.errors)
    report.log_span_s = (t_last_pair - t_first_pair) if t_first_pair is not None else 0.0   # the data's own time
    report.seconds = time.perf_counter() - t_wall
    if not report.pairs:
        # what is missing first, in words (a bag without one of the two streams said so, not as
        # thousands of samples "without a partner"); the output is the caller's to remove
        # (a topic of the wrong type is skipped, said among the reasons; ``copied`` has every topic
        # read, copied to the output or not)
        absent = [t for t in (TOPIC_IMU, TOPIC_MAG) if t not in report.copied and t not in report.skipped_topics]
        said = [w for w in report.warnings() if not (absent and "partner" in w)]   # absent: no partners
        reasons = "; ".join(([f"no {' and no '.join(absent)} messages in the bag"] if absent else [])
                            + said + [str(e) for e in report.bag_errors]) or "no messages"
        raise ReprocessError(f"{src}: no usable {TOPIC_IMU} + {TOPIC_MAG} sample pairs ({reasons})")
    return report


#: How the engine's per-sample warnings begin, and the report's name for each kind.
_SAMPLE_ISSUES = ("sample at t=", "non-finite sample", "a sample pair stamped")
_ISSUE_KINDS = ("implausible sample, pair dropped", "non-finite (NaN/inf) sample, it ends the hold",
                "non-monotonic timestamp (pair stamp not after the previous one), pair dropped")


def _from_session(text: str, session) -> bool:
    """Whether a warning the engine passed on is the capture session's (the report keeps those apart)."""
    return text in session.warnings


# ---------------------------------------------------------------------------------------------
# Probe log (CSV / simulator) → bag, as the probe node would have recorded it

def write_probe_bag(log, path, *, epoch_ns: int = 1_700_000_000_000_000_000, frame_id: str = "probe",
                    reference: bool = True, compression: str = "zstd", latency_ns: int = 0,
                    serial: str = "", progress: Optional[Callable[[int], None]] = None) -> Dict[str, int]:
    """Write a :class:`probelog.ProbeLog` as a bag of ``/probe/imu``, ``/probe/mag``,
    ``/probe/temperature`` (one of each per sample, same header stamp ``epoch + t_s``), if
    ``reference``, ``/probe/reference`` at every change of the log's ``ref`` (NaN = none), and when
    the log has depths ``/probe/depth`` as the probe node publishes it (before the first sample at
    a depth that holds; while it runs at most every 0.5 s), and with a ``serial`` the probe's
    ``/probe/serial`` (latched) before everything else, as the probe node publishes it.

    Serialized with the ``rosbags`` type store (no ROS needed): each sample's messages are the
    bytes of the first one's, stamp and values patched (:class:`cdr.Patcher`, the same bytes).
    Accelerometer as REP-145 specific force (m/s², as in the log), magnetometer converted nT →
    tesla; the covariances state the noise the log shows (:func:`noise.estimate_noise`), as the
    probe node does.  ``progress(samples written)`` every few thousand samples.  Returns messages
    per topic.
    """
    for module in ("mcap.writer", "rosbags.typesys"):  # MissingDependency before any work
        require(module, "bag", "writing a probe log as a bag")
    from rosbags.typesys import Stores, get_typestore

    st = get_typestore(Stores.ROS2_JAZZY)
    T = st.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Vec, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    Imu, Mag, Temp, V3S = (T[IMU_TYPE], T[MAG_TYPE], T[TEMPERATURE_TYPE], T[REFERENCE_TYPE])
    ser = st.serialize_cdr
    from ..detect.noise import estimate_noise

    # the covariance the probe node publishes for a log: the noise the data show, per axis
    lvl = estimate_noise(log.t_s, log.acc, log.mag)
    cov_acc, cov_mag = np.zeros(9), np.zeros(9)
    for k in range(3):
        if np.isfinite(lvl.acc[k]):
            cov_acc[4 * k] = lvl.acc[k] ** 2
        if np.isfinite(lvl.mag[k]):
            cov_mag[4 * k] = (lvl.mag[k] / NT_PER_TESLA) ** 2
    unknown_cov = np.zeros(9)
    unknown_cov[0] = -1.0          # REP-145: orientation not provided
    q0 = Quat(x=0.0, y=0.0, z=0.0, w=1.0)
    v0 = Vec(x=0.0, y=0.0, z=0.0)
    with BagWriter(path, compression=compression) as w:
        sensor_qos = [dict(DEFAULT_QOS_PROFILE, reliability="best_effort", depth=1000)]
        c_imu = w.add_topic(TOPIC_IMU, IMU_TYPE, qos_profiles=sensor_qos)
        c_mag = w.add_topic(TOPIC_MAG, MAG_TYPE, qos_profiles=sensor_qos)
        c_tmp = w.add_topic(TOPIC_TEMPERATURE, TEMPERATURE_TYPE, qos_profiles=sensor_qos)
        c_ref = w.add_topic(TOPIC_REFERENCE, REFERENCE_TYPE,
                            qos_profiles=[dict(DEFAULT_QOS_PROFILE, depth=100)]) if reference else None
        md = np.asarray(log.md_m, float)
        c_dep = w.add_topic(TOPIC_DEPTH, DEPTH_TYPE, qos_profiles=[dict(DEFAULT_QOS_PROFILE, depth=100)]) \
            if np.any(np.isfinite(md)) else None
        F64 = T[DEPTH_TYPE]
        if serial:
            c_ser = w.add_topic(TOPIC_SERIAL, SERIAL_TYPE, qos_profiles=[dict(DEFAULT_QOS_PROFILE, depth=1,
                                                                              durability="transient_local")])
            w.write(c_ser, bytes(ser(T[SERIAL_TYPE](data=str(serial)), SERIAL_TYPE)), int(epoch_ns) + latency_ns)
        hdr0 = Header(stamp=Time(sec=0, nanosec=0), frame_id=frame_id)
        p_imu = Patcher.imu(bytes(ser(Imu(header=hdr0, orientation=q0, orientation_covariance=unknown_cov,
                                          angular_velocity=v0, angular_velocity_covariance=unknown_cov,
                                          linear_acceleration=v0, linear_acceleration_covariance=cov_acc), IMU_TYPE)))
        p_mag = Patcher.vector3(bytes(ser(Mag(header=hdr0, magnetic_field=v0, magnetic_field_covariance=cov_mag),
                                          MAG_TYPE)))
        p_tmp = Patcher.temperature(bytes(ser(Temp(header=hdr0, temperature=0.0, variance=0.0), TEMPERATURE_TYPE)))
        p_ref = Patcher.vector3(bytes(ser(V3S(header=hdr0, vector=v0), REFERENCE_TYPE)))
        last_md, md_sent = None, -np.inf
        t_s = np.asarray(log.t_s, float)
        stamps = (epoch_ns + np.round(t_s * 1e9).astype(np.int64)).tolist()
        mag_t = np.asarray(log.mag, float) / NT_PER_TESLA
        acc, temp = np.asarray(log.acc, float).tolist(), np.asarray(log.temp_c, float).tolist()
        mag_l = mag_t.tolist()
        # the rows whose reference differs from the row before (NaN equal to NaN), found at once:
        # a generator and a comparison per row were a third of the loop's time
        ref = np.asarray(log.ref, float)
        ref_l = ref.tolist()
        if c_ref is not None and len(ref):
            same = np.all((ref[1:] == ref[:-1]) | (np.isnan(ref[1:]) & np.isnan(ref[:-1])), axis=1)
            ref_rows = set(np.flatnonzero(np.r_[True, ~same]).tolist())
        else:
            ref_rows = set()
        md_l, t_l = md.tolist(), t_s.tolist()
        depth_rows = set(np.flatnonzero(np.isfinite(md)).tolist()) if c_dep is not None else set()
        n = len(log)
        for i in range(n):
            if progress is not None and i % 4096 == 0:
                progress(i)
            ns = stamps[i]
            sec, nsec = divmod(ns, 1_000_000_000)
            lt = ns + latency_ns
            if i in depth_rows and md_l[i] != last_md:
                held = i + 1 >= n or md_l[i + 1] == md_l[i]
                if held or t_l[i] - md_sent >= 0.5:
                    w.write(c_dep, bytes(ser(F64(data=md_l[i]), DEPTH_TYPE)), lt)
                    last_md, md_sent = md_l[i], t_l[i]
            if i in ref_rows:
                w.write(c_ref, p_ref(sec, nsec, *ref_l[i]), lt)
            w.write(c_imu, p_imu(sec, nsec, *acc[i]), lt)
            w.write(c_mag, p_mag(sec, nsec, *mag_l[i]), lt)
            w.write(c_tmp, p_tmp(sec, nsec, temp[i]), lt)
        if progress is not None:
            progress(len(log))
        return w.message_counts()

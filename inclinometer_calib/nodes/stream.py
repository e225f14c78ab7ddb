"""The ROS adapter of the stream engine (:class:`engine.StreamEngine`), shared by the calibration
and correction nodes: subscriptions, message → core conversions, the source's announcement and
end, the step with a calibration node, the node's progress, and the wall-clock patience of a
source that does not pace itself.

What a station is, when it may go out and what it becomes is the engine's, as in ``reprocess``:
this module only hands it the messages, in whatever order DDS delivers them.

The source (the probe node) announces itself on ``/graph/progress`` (``StreamProgress``, transient
local): the side streams it keeps current (a station then waits for them on the data's time
alone), its flow-control window (a paced replay: no wall-clock patience at all — every message
will come) and, at the end, how many messages it sent per topic; the stream ends here once all of
them have arrived (or, after ``end_wait_s`` without a sample, with what is missing said and
counted; a message after that is not used and not counted taken).  A source
that announces nothing (a live driver) is taken as it comes: the side streams are waited for once
seen, for at most ``reference_wait_s``; ``idle_flush_s`` without samples closes the open hold.

This node's own progress goes out on the same topic: the data time of the last sample it took
(the probe paces its replay on it), how far its stations are handled (``settled``), and its
counts — the run's accounting.
"""
from __future__ import annotations

import math
import os
import time

from geometry_msgs.msg import Vector3Stamped
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import Imu, MagneticField, Temperature
from std_msgs.msg import Float64, String

from ..io import cdr
from ..correct.engine import Expect, Say, StreamEngine
from ..core.frames import NT_PER_TESLA
from ..detect.gates import GateLimits
from ..detect.streaming import StaticDetector
from . import common as c
from ..io.topics import PROGRESS_TYPE, STATION_TYPE
from inclinometer_calib.msg import StreamProgress

#: The progress goes out at least this often while something changed (wall time, s).
PROGRESS_PERIOD_S = 0.05
#: Without an announced window, progress goes out every this many samples taken (and on the timer).
PROGRESS_STEP = 100
#: The source's end, with messages it sent still missing here: wait this long (wall, s) for them.
END_WAIT_S = 10.0
#: An unpaced source's end over best-effort streams: once nothing has arrived for this long (wall,
#: s) after it, what is still missing was dropped from a full queue (best effort repairs nothing):
#: the end is taken with the loss counted, not after the whole ``end_wait_s``.
UNPACED_QUIET_S = 1.0
#: A calibration node not in the graph for this long (wall, s) is gone: stations stop waiting for it.
GONE_S = 5.0


def declare_stream_params(p: c.Params, *, calibration_sync: bool):
    """The parameters every engine-driven node shares (detector, QoS, gates, the source, patience).
    Returns a dict of what the driver needs."""
    out = {"detector": c.declare_detector(p), "qos": c.declare_qos(p)}
    out["gates"] = GateLimits(
        max_creep_deg=p.declare("gates.max_creep_deg", GateLimits.max_creep_deg, "Largest turn of the probe during a "
                                "hold that is not motion (the trend must also be significant against the noise), deg",
                                read_only=True, range=(0.0, 10.0)),
        max_scatter_ratio=p.declare("gates.max_scatter_ratio", GateLimits.max_scatter_ratio, "A hold whose scatter "
                                    "(after its trend) exceeds this multiple of the measured noise, significantly, is "
                                    "unsteady (vibration, motion)", read_only=True, range=(1.0, 100.0)))
    out["source_node"] = p.declare("source.node", "probe", f"The node whose {c.TOPIC_PROGRESS} messages announce the "
                                   "source: the side streams it keeps current, its pacing, its end and what it sent",
                                   read_only=True)
    out["source_wait"] = p.declare("source.wait", False, "Stations wait until the source has announced itself (a "
                                   "replay: what a station waits for then never depends on which topic's first "
                                   "message came first; the launcher sets it)", read_only=True)
    out["patience"] = p.declare("reference_wait_s", 2.0, "A source that does not pace itself (live): a closed "
                                "station waits at most this long (wall clock, s) for the reference, temperatures and "
                                "depth up to its end (they are other topics and may come late); then it goes out with "
                                "what arrived, said and counted. A paced replay waits for them as long as it runs",
                                read_only=True, range=(0.0, 600.0))
    out["idle_flush"] = p.declare("idle_flush_s", 1.0, "A source that does not announce its end: when no sample "
                                  "arrived for this long (wall clock, s), close the open hold (and solve with what "
                                  "there is); data arriving later continue; 0 disables", read_only=True,
                                  range=(0.0, 60.0))
    out["end_wait"] = p.declare("end_wait_s", END_WAIT_S, "After the source's end, wait this long (wall clock, s) "
                                "without a sample for the messages it says it sent and that have not arrived; then end "
                                "with what came (the loss said and counted)", read_only=True, range=(0.0, 3600.0))
    out["resume"] = list(p.declare("resume.bags", [], "The run's recording (the recorder's bag parts, in order) to "
                                   "rebuild this node's state from at start-up: a node restarted mid-run takes up "
                                   "where the one that died left off (the launcher sets it at a restart)",
                                   read_only=True, ptype=Parameter.Type.STRING_ARRAY))
    if calibration_sync:
        out["calibration_node"] = p.declare("calibration.node", "", "The calibration node to keep step with (its "
                                            "records apply from the data time they were solved at, and a station "
                                            "waits until that node has taken it too: the stations of a replay are "
                                            "then reprocess's whatever the timing); empty: a record applies from "
                                            "the next station after it arrives", read_only=True)
    return out


class StreamDriver:
    """Feeds a node's :class:`engine.StreamEngine` from the graph and publishes its progress.

    ``on_events(events)`` (the node) gets what the engine produced after each message, in order
    (:class:`engine.Say` lines are logged here first); ``side`` subscribes the reference and depth
    too (the correction node)."""

    def __init__(self, node, settings: dict, engine: StreamEngine, on_events, *, side: bool):
        self.node = node
        self.engine = engine
        self.on_events = on_events
        self.log = node.get_logger()
        self.source = settings["source_node"]
        self.patience = settings["patience"]
        self.idle_flush = settings["idle_flush"]
        self.end_wait = settings["end_wait"]
        self.cal_node = settings.get("calibration_node", "")
        self.side = side
        self.announced = None          # the source's announcement (its first StreamProgress)
        self.source_end = None         # the source's last StreamProgress, once it says end
        self.window = 0
        self._source_wait = settings["source_wait"]
        if self._source_wait:
            engine.hold("the source's announcement")
        self._end_seen = None          # wall time the source's end came while messages were missing
        self._last_wall = None         # wall time of the last sample (idle flush)
        self._waiting = None           # (station, wall time) of the oldest waiting station
        self._cal_seen = None          # wall time the calibration node was last seen in the graph
        self._cal_check = 0.0
        self._pairing_checked = -math.inf   # monotonic time of the last pairing check (_check_pairing)
        self._pairing_seen = (0, 0, 0)      # the pairer's (unpaired, paired, waiting) then
        self._reported = (None,)
        self._used_reported = 0
        self._progress_wall = 0.0
        self._t_started = time.monotonic()
        self.replaying = False         # resuming from the recording (resume)
        self.recorded_stations = set() # station ids the recording holds (resume)
        self.recorded_records = []     # record ids the recording holds (resume)
        self._skip = {}                # topic -> key up to which live messages were in the recording
        self.resent = 0
        self.undecodable = {}          # topic -> messages that did not decode
        self.late = {}                 # topic -> messages that came after the end was declared (not used)
        qos = settings["qos"]
        self._best_effort = qos.reliability == ReliabilityPolicy.BEST_EFFORT
        self.pub_progress = node.create_publisher(StreamProgress, c.TOPIC_PROGRESS, c.latched_qos(depth=1))
        self.msg = StreamProgress()
        self.msg.node = node.get_name()
        # the samples are taken raw and decoded where reprocess decodes a bag's (inclinometer_calib.io.cdr):
        # the same numbers by the same code, without building a Python message of each (19 µs a message)
        self.hot_subscriptions = [
            node.create_subscription(Imu, c.TOPIC_IMU, self._on_imu, qos, raw=True),
            node.create_subscription(MagneticField, c.TOPIC_MAG, self._on_mag, qos, raw=True),
            node.create_subscription(Temperature, c.TOPIC_TEMPERATURE, self._on_temp, qos, raw=True)]
        # as deep as the samples' (a delivery that stalls until a repair does not drop the oldest), transient
        # local in a paced replay (a restart misses nothing)
        side_qos = c.reliable_qos(max(100, qos.depth))
        side_qos.durability = qos.durability
        if side:
            # the reference and the depth on the hot path too, taken in turn with the samples
            self.hot_subscriptions += [
                node.create_subscription(Vector3Stamped, c.TOPIC_REFERENCE, self._on_reference, side_qos, raw=True),
                node.create_subscription(Float64, c.TOPIC_DEPTH, self._on_depth, side_qos)]
        node.create_subscription(String, c.TOPIC_SERIAL, self._on_serial, c.latched_qos())
        node.create_subscription(StreamProgress, c.TOPIC_PROGRESS, self._on_progress, c.latched_qos(depth=100))
        c.steady_timer(node, PROGRESS_PERIOD_S, self._on_timer)
        self._prior = [False, False]

    # ---- messages ---------------------------------------------------------------------------
    def _on_imu(self, data, info):
        # (two parameters without a default: rclpy then passes the message info — its source timestamp)
        if self.engine.ended:
            return self._late(c.TOPIC_IMU)
        try:
            key, g = cdr.decode_imu_gravity(data)
            sigma = math.nan if self._prior[0] else cdr.decode_imu_covariance(data)
        except cdr.DECODE_ERRORS as exc:
            return self._undecodable(c.TOPIC_IMU, exc)
        if self._skip and self._resent(c.TOPIC_IMU, key[0] + 1e-9 * key[1]):
            return
        self._prior[0] = True
        self._last_wall = time.monotonic()
        self.engine.imu(key, g, info.get("source_timestamp", 0) if info else 0, sigma)
        self._after((Imu, data), info)

    def _on_mag(self, data):
        if self.engine.ended:
            return self._late(c.TOPIC_MAG)
        try:
            key, f = cdr.decode_vector3(data)
            sigma = math.nan if self._prior[1] else cdr.decode_mag_covariance(data) * NT_PER_TESLA
        except cdr.DECODE_ERRORS as exc:
            return self._undecodable(c.TOPIC_MAG, exc)
        if self._skip and self._resent(c.TOPIC_MAG, key[0] + 1e-9 * key[1]):
            return
        self._prior[1] = True
        self._last_wall = time.monotonic()
        self.engine.mag(key, (f[0] * NT_PER_TESLA, f[1] * NT_PER_TESLA, f[2] * NT_PER_TESLA), sigma)
        self._after((MagneticField, data))

    def _on_temp(self, data):
        got = self._stamped(c.TOPIC_TEMPERATURE, data, cdr.decode_temperature)
        if got is not None:
            self.engine.temperature(*got)
            self._after((Temperature, data))

    def _on_reference(self, data):
        got = self._stamped(c.TOPIC_REFERENCE, data, cdr.decode_vector3)
        if got is not None:
            self.engine.reference(*got)
            self._after()

    def _stamped(self, topic: str, data, decode):
        """``(stamp s, value)`` of a stamped side message's bytes, or None when it is not to be used
        (after the end, undecodable, or already in the recording a restarted node resumed from)."""
        if self.engine.ended:
            return self._late(topic)
        try:
            key, value = decode(data)
        except cdr.DECODE_ERRORS as exc:
            return self._undecodable(topic, exc)
        t = key[0] + 1e-9 * key[1]
        if self._skip and self._resent(topic, t):
            return None
        return t, value

    def _late(self, topic: str) -> None:
        """A message after the node ended the data (it gave up waiting for the rest: see
        :meth:`_check_end`): not used and not counted as taken — the counts stay those of the end,
        so the run's summary says the loss the node's log line said."""
        n = self.late[topic] = self.late.get(topic, 0) + 1
        if n == 1:
            self.log.warning(f"{topic}: messages still arrive after the end of the data was declared: not used "
                             "(they are among those said lost)")

    def _undecodable(self, topic: str, exc) -> None:
        """A message whose bytes are not its type's (a raw publisher's): counted, said once a topic."""
        n = self.undecodable[topic] = self.undecodable.get(topic, 0) + 1
        if n == 1:
            self.log.error(f"a {topic} message does not decode ({exc}): skipped (and every such message "
                           "after it, counted)")

    def _on_depth(self, msg, info):
        if self.engine.ended:
            return self._late(c.TOPIC_DEPTH)
        order = info.get("source_timestamp", 0) if info else 0
        if self._skip and self._resent(c.TOPIC_DEPTH, order):
            return
        self.engine.depth(msg.data, order)
        self._after()

    def _on_serial(self, msg):
        self.engine.set_serial(msg.data)
        self.log.info(f"the data are of probe {msg.data}")
        self._after()

    def _on_progress(self, msg):
        if msg.node == self.source:
            if self.announced is None:
                self.announced = msg
                self.window = int(msg.window)
                if getattr(msg, "serial", ""):
                    self.engine.set_serial(msg.serial)   # before any station goes out: records are checked
                side = self.side   # the calibration takes neither reference nor depth: it never waits for them
                self.engine.set_expect(Expect(reference=msg.has_reference and side, temperature=msg.has_temperature,
                                              depth=msg.has_depth and side))
                self.log.info(f"source {self.source}: " + (f"a paced replay (window {self.window} samples)"
                                                           if self.window else "not paced") +
                              "; it keeps current: " + (", ".join(n for n, h in (
                                  ("reference", msg.has_reference), ("temperature", msg.has_temperature),
                                  ("depth", msg.has_depth)) if h) or "nothing besides the samples"))
            if msg.end and self.source_end is None:
                self.source_end = msg
                self._check_end()
        elif self.cal_node and msg.node == self.cal_node:
            self.engine.calibration_progress(msg.settled, msg.records, msg.end)
        self._after()

    # ---- a restart: resume from the run's recording ----------------------------------------------
    def resume(self, paths, *, records: bool) -> bool:
        """Rebuild the engine's state from the run's recording (the recorder's bag parts, in order):
        every message recorded goes through the engine as it came live, so its detector, session,
        field monitor and trajectory are those of the node that died; what the node had published
        already is the node's to hold back (:attr:`replaying`: its ``on_events`` sees it).  Live
        messages the recording holds already are skipped (transient-local history delivers the
        probe's last qos.depth samples again).  ``records``: the coefficient records recorded go to
        the engine too (the correction node).  Returns False when there is nothing to resume from."""
        from types import SimpleNamespace

        from ..io.bag import BagError, open_bag
        from ..correct.reprocess import BagFeeder

        paths = [p for p in paths if os.path.exists(p)]
        if not paths:
            return False
        feeder = BagFeeder(self.engine, records=records, dedupe=True)
        self.replaying = True
        t0 = time.monotonic()
        n = 0
        try:
            for path in paths:
                try:
                    reader = open_bag(path)
                except BagError as exc:
                    self.log.error(f"resume: {exc}: that part is not read")
                    continue
                for m in reader.messages(strict=False):
                    n += 1
                    if m.topic == c.TOPIC_PROGRESS:
                        fields = feeder.codec.decode(PROGRESS_TYPE, m.data)
                        if fields["node"] != self.node.get_name():      # its own earlier self: not
                            self._on_progress(SimpleNamespace(**fields))
                        continue
                    if m.topic == c.TOPIC_STATION:
                        self.recorded_stations.add(feeder.codec.decode(STATION_TYPE, m.data)["station_id"])
                        continue
                    problem = feeder.feed(m)
                    if problem:
                        self.log.warning(f"resume: {path}: {problem}")
                    self._after()
        finally:
            self.replaying = False
        self.recorded_records = list(feeder.record_ids)
        self._skip = dict(feeder.last)
        cnt = self.engine.counts
        self.log.warning(f"resumed from the run's recording ({', '.join(os.path.basename(p) for p in paths)}: {n} "
                         f"messages, {cnt.used} samples, {cnt.stations} stations rebuilt, up to t="
                         f"{self.engine.t_last:.3f} s) in {time.monotonic() - t0:.1f} s; continuing live")
        self.publish_progress(force=True)
        return True

    def _resent(self, topic: str, key: float) -> bool:
        """Live, after a resume: the message is one the recording held (skipped, counted)."""
        last = self._skip.get(topic)
        if last is None:
            return False
        if key <= last:
            self.resent += 1
            return True
        del self._skip[topic]        # past the recording: from here on everything is new
        return False

    # ---- direct use (in-process: a test, another driver) -----------------------------------------
    def feed(self, t: float, g, m) -> None:
        """A paired sample (s, gravity vector m/s² down positive, field nT) handed in directly."""
        self.engine.counts.imu += 1
        self.engine.counts.mag += 1
        self._last_wall = time.monotonic()
        self.engine._pair(float(t), tuple(g), tuple(m))
        self._after()

    def close_hold(self) -> None:
        """Close the open hold now (a test's end of data without the source's end)."""
        self.engine.close_hold()
        self._after()

    def idle(self) -> None:
        """What the idle timer does for a source that does not announce its end (:meth:`engine.StreamEngine.idle`)."""
        self.engine.idle()
        self._after()

    # ---- after each message --------------------------------------------------------------------
    def _after(self, msg=None, info=None):
        eng = self.engine
        if eng._out:
            events = eng.pop()
            for ev in events:
                if isinstance(ev, Say):
                    self.say(ev.level, ev.text)
            self.on_events(events, msg, info)
        elif msg is not None:
            self.on_events((), msg, info)
        step = max(1, self.window // 4) if self.window else PROGRESS_STEP
        if eng.counts.used - self._used_reported >= step:
            self.publish_progress()
        if self.source_end is not None and not eng.ended:
            self._check_end()

    def say(self, level: str, text: str) -> None:
        """Log one line at ``level`` (rclpy ties a severity to its call site: one call per level)."""
        if level == "error":
            self.log.error(text)
        elif level == "warning":
            self.log.warning(text)
        elif level == "info":
            self.log.info(text)
        else:
            self.log.debug(text)

    def _missing_at_end(self) -> dict:
        """Messages the source says it sent that have not arrived here, per topic."""
        e, s = self.engine.counts, self.source_end
        mine = [("imu", e.imu, s.imu), ("mag", e.mag, s.mag), ("temperature", e.temperature, s.temperature)]
        if self.side:
            mine += [("reference", e.reference, s.reference), ("depth", e.depth, s.depth)]
        return {n: sent - got for n, got, sent in mine if got < sent}

    def _check_end(self, give_up: bool = False):
        missing = self._missing_at_end()
        if missing and not give_up:
            if self._end_seen is None:
                self._end_seen = time.monotonic()
            return
        if missing:
            text = ", ".join(f"{n} {k}" for n, k in missing.items())
            self.log.error(f"the source's end came {time.monotonic() - self._end_seen:.1f} s ago and messages it "
                           f"sent never arrived here ({text}): the data end with what came; stations that needed "
                           "them may be missing or cut")
            self.engine.counts.lost = dict(missing)
        self._end_seen = None
        self.engine.end()
        self._after()
        self.publish_progress(force=True)

    def publish_progress(self, force: bool = False):
        """This node's :class:`StreamProgress` (when something changed, or ``force``)."""
        eng, m = self.engine, self.msg
        cnt = eng.counts
        key = (cnt.imu, cnt.mag, cnt.temperature, cnt.reference, cnt.depth, cnt.used, cnt.published,
               cnt.records, cnt.forced, eng.settled, eng.done)
        if key == self._reported and not force:
            return
        self._reported = key
        self._used_reported = cnt.used
        self._progress_wall = time.monotonic()
        t = eng.t_last if math.isfinite(eng.t_last) else 0.0
        c.set_stamp(m.header.stamp, max(t, 0.0))
        m.settled = float(eng.settled) if math.isfinite(eng.settled) else (math.inf if eng.settled > 0 else -1.0)
        m.imu, m.mag, m.temperature, m.reference, m.depth = cnt.imu, cnt.mag, cnt.temperature, cnt.reference, cnt.depth
        m.pairs_used = cnt.used
        m.pairs_dropped = cnt.nonfinite + cnt.implausible + cnt.out_of_order
        m.stations = self.stations_count()
        m.stations_uncorrected = cnt.uncorrected
        m.records = cnt.records if eng.session is not None else 0   # records this node published
        m.forced = cnt.forced
        m.end = eng.done
        self.pub_progress.publish(m)

    def stations_count(self) -> int:
        eng = self.engine
        return eng.counts.published if eng.proc is not None else eng.counts.stations

    # ---- the timer ---------------------------------------------------------------------------------
    def _on_timer(self):
        eng = self.engine
        now = time.monotonic()
        paced = self.announced is not None and self.window > 0
        if self.source_end is not None and not eng.ended and self._end_seen is not None:
            # waited for since the end came, or since the last sample if samples still come (a loaded
            # machine, a restarted node catching up): never given up while the data still flow
            quiet = now - max(self._end_seen, self._last_wall or -math.inf)
            dropped = self._best_effort and not paced and quiet > UNPACED_QUIET_S
            if dropped or quiet > self.end_wait:
                self._check_end(give_up=True)
        if eng.ended and not eng.done:       # the end came; stations still wait for the calibration node
            if self._end_seen is None:
                self._end_seen = now
            elif now - self._end_seen > self.end_wait:
                eng.release(force=True, why=f"{self.end_wait:g} s after the end of the data")
                self._after()
        if self.announced is None and self.idle_flush > 0 and self._last_wall is not None \
                and now - self._last_wall > self.idle_flush:
            self._last_wall = None      # a source that does not announce its end: the data paused or ended
            self.idle()
        if eng._pending and not paced:
            oldest = eng._pending[0].station
            if self._waiting is None or self._waiting[0] is not oldest:
                self._waiting = (oldest, now)
            elif now - self._waiting[1] > self.patience:
                eng.release(force=True, why=f"after {now - self._waiting[1]:.1f} s")
                self._waiting = None
                self._after()
        if now - self._pairing_checked >= 1.0:
            self._pairing_checked = now
            self._check_pairing()
        if self.cal_node and now - self._cal_check > 1.0:
            self._cal_check = now
            present = any(i.node_name == self.cal_node for i in self.node.get_publishers_info_by_topic(c.TOPIC_PROGRESS))
            if present:
                if eng.cal_gone:
                    self.log.info(f"calibration node {self.cal_node} is back: stations keep step with it again")
                    eng.calibration_gone(False)
                self._cal_seen = now
            elif not eng.cal_gone and not eng.cal_ended and now - (self._cal_seen or self._t_started) > \
                    (GONE_S if self._cal_seen else 30.0):
                self.log.warning(f"calibration node {self.cal_node} is not in the graph (for {GONE_S:g} s): stations "
                                 "no longer wait for it; the records it published stay in force")
                eng.calibration_gone(True)
                self._after()
        if now - self._progress_wall > PROGRESS_PERIOD_S:
            self.publish_progress()

    def _check_pairing(self):
        """Once a second (the timer): warn when samples of one stream find no partner of the other
        (an absent field or imu): no pair completed since the last check while samples of one stream
        wait (or were evicted)."""
        pr = self.engine.pairer
        waiting = pr.waiting
        unpaired_seen, paired_seen, waiting_seen = self._pairing_seen
        new = pr.unpaired - unpaired_seen + max(waiting - waiting_seen, 0)
        if new > 0 and pr.paired == paired_seen:
            lone, other = ((c.TOPIC_IMU, c.TOPIC_MAG) if len(pr._imu) >= len(pr._mag)
                           else (c.TOPIC_MAG, c.TOPIC_IMU))
            self.log.warning(f"{new} samples on {lone} without a {other} partner (same stamp) since the "
                             f"last check: {other} absent or stamped differently; no stations from them")
        self._pairing_seen = (pr.unpaired, pr.paired, waiting)


def make_detector(settings: dict) -> StaticDetector:
    return StaticDetector(**settings["detector"])

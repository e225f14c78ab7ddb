"""Probe node: publishes a probe's raw streams from the simulator, a probe-log CSV or an MCAP bag.

Publishes (sensor-data QoS unless ``qos.reliability`` says otherwise), all three with the same
header stamp per sample:

* ``/probe/imu`` (``sensor_msgs/Imu``): REP-145 specific force in m/s^2 (a resting probe reads
  -gravity); ``orientation_covariance[0] = angular_velocity_covariance[0] = -1`` (the probe
  measures neither); ``linear_acceleration_covariance``: see below;
* ``/probe/mag`` (``sensor_msgs/MagneticField``): tesla, covariance in tesla^2;
* ``/probe/temperature`` (``sensor_msgs/Temperature``): degrees Celsius;
* ``/probe/reference`` (``geometry_msgs/Vector3Stamped``, reliable): the known reference attitude
  (x = drift, y = azimuth, z = toolface, degrees), piecewise constant from ``header.stamp`` on;
  NaN = no reference (the probe is moving or the attitude is unknown), per component (a vertical
  pose has no azimuth).  Published when it changes, and again every second of log time while it
  does not (``REFERENCE_PERIOD_S``), so that a reader knows the last one it has is current.
* ``/probe/depth`` (``std_msgs/Float64``, reliable): the probe's measured depth, m (a log's
  ``md_m``, a bag's ``/probe/depth``, the simulated well path's stations 30 m apart).  It has no
  stamp: published just before the first sample at a new depth, so it holds from there on in the
  order of the stream; while it runs (the probe moving) at most every ``DEPTH_PERIOD_S``.

The script is prepared in pieces of :data:`CHUNK_SAMPLES` samples while it is published (the
simulator generates it piece by piece with the same numbers as a whole simulation,
:meth:`simulate.SessionPlan.chunks`; a CSV log or a bag is read whole into arrays — the noise
measured from the whole log and the pairing of a bag's streams by stamp need every sample — and
turned into messages piece by piece), so that the node's memory does not grow with the length
of a simulated script.  It is published sample by sample from a timer that follows the log's time
line scaled by ``speed`` (several samples per tick at high rates).  Stamps are the log time (``stamp:=log``, a simulation time base starting
at the log's first sample) or the wall-clock time the sample is due (``stamp:=now``).  With
``stamp:=log`` the node also publishes ``/clock`` (``rosgraph_msgs/Clock``): the log time of the
samples published so far (the first sample's while waiting; at most every
:data:`CLOCK_PERIOD_S` of wall time), so that nodes run with ``use_sim_time:=true`` stamp their
own messages (status, diagnostics, coefficients) in the same time base as the samples.  Its own
publishing timer runs on the steady clock.

The start waits until ``/probe/imu``, ``/probe/mag`` and ``/probe/temperature`` each have
``wait_for_subscribers`` subscribers and ``/probe/reference`` has
``wait_for_reference_subscribers`` (the launcher sets both from the nodes it starts), so that a
recorder does not miss the first messages of a topic it subscribed to last.

Covariances (per-axis variances on the diagonal): ``simulate`` publishes the simulated noise;
``csv`` and ``mcap`` the noise measured from the whole log (:func:`noise.estimate_noise`), except
that a bag whose messages carry a positive covariance keeps the recorded one, and a ``noise_acc``
/ ``noise_mag`` parameter > 0 overrides both for its sensor.

Pacing (``flow.readers``, the launcher sets it for every replay): the node announces itself on
``/graph/progress`` (``StreamProgress``: the side streams it keeps current, its window) and never
runs more than ``flow.window`` samples ahead of the slowest reader named — their own progress
messages say how far each has taken the stream — so no reader loses a sample whatever the machine;
``speed`` is then a ceiling.  The streams are then reliable and transient local (``qos.depth``
kept: a reader restarted mid-run gets what it missed), the reference and the depth are repeated
every second of log time also while there is none (NaN), and after the last sample it says
``end`` with what it sent per topic and exits once every reader has taken all of it (and the
recorder has every station and record), at most ``flow.end_timeout_s`` later.

At the end: ``on_end:=stop`` exits with status 0 — or :data:`INPUT_DAMAGED` (3) when the MCAP
input was damaged (truncated, corrupt chunks, undecodable messages: the readable part was
replayed) — ``on_end:=idle`` keeps the node alive.
"""
from __future__ import annotations

import collections
import json
import math
import os
import sys
import time

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import Imu, MagneticField, Temperature
from std_msgs.msg import Float64, String

from ..io import cdr
from ..core import effects as fx
from ..calibrate import simulate as sim
from ..io.cdr import stamp_parts
from ..core.coeffs import Calibration
from ..detect.noise import estimate_noise
from ..core.output import atomic_write_text
from ..io.probelog import MAG_UNITS, ProbeLog, label_runs, read_csv
from ..detect.streaming import depth_per_sample
from ..io.topics import GRAPH_OUTPUTS, PROBE_TOPICS
from . import common as c
from inclinometer_calib.msg import StreamProgress

SOURCES = ("simulate", "csv", "mcap")
#: While the depth changes (the probe moving), it is published at most this often (log time, s).
DEPTH_PERIOD_S = 0.5
#: The reference and the depth in effect are published again after this much log time without a
#: change, so that a reader knows its last one is current (a station waits for that before it goes).
REFERENCE_PERIOD_S = 1.0
#: The progress (StreamProgress) goes out at most this often while publishing (wall time, s).
PROGRESS_PERIOD_S = 0.02
#: After the last sample the progress (with the end) is repeated this often (wall, s).
ENDING_PROGRESS_PERIOD_S = 1.0
#: Exit status at the end of the script when the MCAP input was damaged (the launcher reports it).
INPUT_DAMAGED = 3
#: Shortest wall-clock interval between two /clock messages, s: enough for the other nodes'
#: stamps (10 ms of wall time), a fraction of the sample rate's message load.
CLOCK_PERIOD_S = 0.01
#: Shortest period of the publishing timer, s (wall time): at higher sample rates each tick sends
#: every sample due.  Each tick costs rclpy's executor a walk of the node's whole wait set (about
#: 0.1 ms of CPU); a 2 ms floor made that most of the node's CPU at 1-2 kHz (replay at speed 10-20).
#: 10 ms is the clock's own granularity (CLOCK_PERIOD_S); the readers' queues hold far more than
#: one tick's samples.
MIN_TICK_S = 0.01
#: Unpaced (no flow readers): after the last sample, wait at most this long (wall clock, s) for
#: every matched reader to acknowledge the end (and, with reliable streams, every sample): a
#: process that exits at once takes its writers' undelivered messages with it.
UNPACED_END_S = 30.0
_NO_WAIT = Duration(seconds=0)
KNOWN_BAG_TOPICS = PROBE_TOPICS   # what a replay publishes again, with the type each must have
#: Samples prepared (simulated, converted to messages' floats) at a time by default (the
#: ``chunk_samples`` parameter): 10 s at 1 kHz, a few MB.
CHUNK_SAMPLES = 10000


class _Script:
    """The samples to publish, in order, as pieces: ``n`` samples from ``t_first`` to ``t_last``
    (s, log time); :meth:`pieces` yields ``(ProbeLog, field in tesla (k, 3))`` of at most
    ``chunk_samples`` rows each."""

    def __init__(self, n: int, t_first: float, t_last: float, pieces):
        self.n, self.t_first, self.t_last = n, t_first, t_last
        self._pieces = pieces

    @classmethod
    def whole(cls, log: ProbeLog, tesla, size: int) -> "_Script":
        """A log held whole (read from a file): cut into pieces as it is published."""
        n = len(log)
        def piece(a, b):
            return ProbeLog(log.t_s[a:b], log.acc[a:b], log.mag[a:b], log.temp_c[a:b], log.pose[a:b], log.ref[a:b],
                            md_m=log.md_m[a:b])
        pieces = ((piece(a, a + size), tesla[a:a + size]) for a in range(0, n, size))
        return cls(n, float(log.t_s[0]) if n else 0.0, float(log.t_s[-1]) if n else 0.0, pieces)

    def pieces(self):
        return self._pieces


def _same(a: float, b: float) -> bool:
    """Equal depths, NaN equal to NaN (no depth)."""
    return a == b or (a != a and b != b)


def _changes(rows, base: int, prev):
    """``(changes, last key)``: ``(sample index, row)`` wherever ``rows`` (k, d) change from the row
    before (``prev``: the key of the row before the first; NaN = none), indices from ``base``."""
    out = []
    for i, row in enumerate(rows):
        key = tuple(None if not math.isfinite(x) else x for x in row)
        if key != prev:
            out.append((base + i, tuple(row)))
            prev = key
    return out, prev


def _check_effects(values):
    try:
        for spec in fx.parse_effects(list(values)):
            spec.build(need_values=True)
    except ValueError as exc:
        return str(exc)
    return None


def _check_topic_counts(values):
    for v in values:
        topic, sep, n = v.rpartition("=")
        if not sep or not topic.startswith("/") or not n.isdigit():
            return f"{v!r} is not TOPIC=N (e.g. /survey/station=1)"
    return None


def _check_finite_list(lo, hi):
    def check(values):
        bad = [v for v in values if not (math.isfinite(v) and lo <= v <= hi)]
        return f"values {bad} outside {lo}..{hi}" if bad else None
    return check


class ProbeNode(Node):
    def __init__(self, **kwargs):
        super().__init__("probe", **kwargs)
        p = c.Params(self)
        self.source = p.declare("source", "simulate", "Where the samples come from: simulate, csv or mcap",
                                read_only=True, choices=SOURCES)
        self.mag_unit = p.declare("mag_unit", "nT", "source:=csv: unit of the log's magnetometer columns",
                                  read_only=True, choices=tuple(MAG_UNITS))
        self.path = p.declare("path", "", "Input file for source:=csv (probe-log CSV) or source:=mcap (bag)",
                              read_only=True)
        self.speed = p.declare("speed", 1.0, "Playback speed factor (log time / wall time); may be changed "
                               "while running", range=(0.01, 1000.0))
        self.stamp_mode = p.declare("stamp", "log", "Header stamps: log (the log's time base) or now (wall "
                                    "clock when the sample is due)", read_only=True, choices=("log", "now"))
        self.on_end = p.declare("on_end", "stop", "At the end of the script: stop (exit 0) or idle",
                                choices=("stop", "idle"))
        self.frame_id = p.declare("frame_id", "probe", "frame_id of the published messages", read_only=True)
        self.max_batch = p.declare("max_batch", 2000, "Most samples published per timer tick",
                                   range=(1, 100000))
        self.chunk_samples = p.declare("chunk_samples", CHUNK_SAMPLES, "Samples prepared at a time (simulated, "
                                       "turned into message values) while publishing: the memory a script takes "
                                       "does not grow with its length", read_only=True, range=(1, 1000000))
        self.wait_subs = p.declare("wait_for_subscribers", 0, f"Start publishing once {c.TOPIC_IMU}, "
                                   f"{c.TOPIC_MAG} and {c.TOPIC_TEMPERATURE} each have this many subscribers "
                                   "(0: do not wait for them)", read_only=True, range=(0, 100))
        self.wait_ref_subs = p.declare("wait_for_reference_subscribers", 0, "Start publishing only once "
                                       f"{c.TOPIC_REFERENCE} has this many subscribers too (its readers: the "
                                       "correction node, a recorder; 0: do not wait for them)", read_only=True,
                                       range=(0, 100))
        self.wait_topics = p.declare("wait_for_topic_subscribers", [], "Start publishing only once these "
                                     "topics of the other nodes have subscribers too, TOPIC=N each (e.g. "
                                     f"{c.TOPIC_STATION}=1: a recorder that must not miss the first stations)",
                                     read_only=True, check=_check_topic_counts, ptype=Parameter.Type.STRING_ARRAY)
        self.wait_timeout = p.declare("wait_timeout_s", 30.0, "Start anyway after this long waiting for "
                                      "subscribers, s", read_only=True, range=(0.0, 3600.0))
        self.start_delay = p.declare("start_delay_s", 0.5, "Pause before the first sample (after the "
                                     "subscribers are there), s", read_only=True, range=(0.0, 60.0))
        self.truth_file = p.declare("truth_file", "", "source:=simulate: write the simulator truth (probe "
                                    "model, stations) to this JSON file, plus truth_coeffs.yaml beside it",
                                    read_only=True)
        # simulation
        self.rate_hz = p.declare("rate_hz", 100.0, "Simulated sample rate, Hz", read_only=True,
                                 range=(1.0, 10000.0))
        self.seed = p.declare("seed", 7, "Simulator seed (probe errors and noise)", read_only=True,
                              range=(0, 2**31 - 1))
        self.serial = p.declare("probe_serial", "", f"The probe's serial number, published latched on "
                                f"{c.TOPIC_SERIAL} (its identity in the fleet registry, the records and every "
                                "station). Empty: simulate SIM-<seed>, mcap the bag's; a csv log then names no probe "
                                "(said)", read_only=True)
        self.effects = p.declare("effects", [], "Extra simulated effects, NAME[:sensor[:axes]]=V[,V...] "
                                 "(e.g. axial_interference=300)", read_only=True, check=_check_effects,
                                 ptype=Parameter.Type.STRING_ARRAY)
        self.severity = p.declare("severity", 1.0, "Scale of the random probe errors", read_only=True,
                                  range=(0.0, 10.0))
        self.noise_acc = p.declare("noise_acc", 0.0, "Accelerometer noise (1 sigma), m/s^2, published as the "
                                   "covariance. simulate: the simulated noise (0: the simulator's 0.002); csv, "
                                   "mcap: overrides the noise measured from the data (0: measured from the data, "
                                   "or a bag's recorded covariance)", read_only=True, range=(0.0, 1.0))
        self.noise_mag = p.declare("noise_mag", 0.0, "Magnetometer noise (1 sigma), nT, published as the "
                                   "covariance. simulate: the simulated noise (0: the simulator's 20); csv, mcap: "
                                   "overrides the noise measured from the data (0: measured from the data, or a "
                                   "bag's recorded covariance)", read_only=True, range=(0.0, 5000.0))
        self.site = c.declare_site(p)
        self.calibrate = p.declare("calibration_session", True, "Simulate the twelve-pose calibration "
                                   "first", read_only=True)
        self.cal_temps = p.declare("calibration_temperatures_c", [25.0], "One round of the twelve poses "
                                   "per temperature, degC", read_only=True,
                                   check=_check_finite_list(-40.0, 200.0))
        self.station_s = p.declare("station_duration_s", 2.0, "Time held at each station, s",
                                   read_only=True, range=(0.1, 600.0))
        self.move_s = p.declare("move_s", 1.0, "Time of each move between stations, s", read_only=True,
                                range=(0.0, 600.0))
        self.survey = p.declare("survey", "well_path", "Survey after the calibration: stand_grid, well_path "
                                "or none", read_only=True, choices=("stand_grid", "well_path", "none"))
        self.survey_gap = p.declare("survey_gap_s", 2.0, "Time between calibration and survey (the probe "
                                    "moves from the stand to the first station, streaming), s",
                                    read_only=True, range=(0.0, 3600.0))
        self.grid_drifts = p.declare("grid.drifts_deg", [float(x) for x in sim.VAL_DRIFTS],
                                     "Stand grid set drifts, deg", read_only=True,
                                     check=_check_finite_list(0.0, 180.0))
        self.grid_azimuths = p.declare("grid.azimuths_deg", [float(x) for x in sim.VAL_AZIMUTHS],
                                       "Stand grid set azimuths, deg", read_only=True,
                                       check=_check_finite_list(0.0, 360.0))
        self.grid_toolfaces = p.declare("grid.toolfaces_deg", [float(x) for x in sim.VAL_TOOLFACES],
                                        "Stand grid set toolfaces, deg", read_only=True,
                                        check=_check_finite_list(0.0, 360.0))
        self.well_n = p.declare("well.n_stations", 30, "Stations down the synthetic well path",
                                read_only=True, range=(1, 100000))
        self.well_build = p.declare("well.build_deg_per_station", 3.0, "Drift build per station, deg",
                                    read_only=True, range=(0.0, 90.0))
        self.well_kickoff = p.declare("well.kickoff_deg", 0.0, "Drift of the first station, deg",
                                      read_only=True, range=(0.0, 180.0))
        qos = c.declare_qos(p)
        self.flow_readers = list(p.declare(
            "flow.readers", [], f"Pace the replay on these nodes' {c.TOPIC_PROGRESS} (e.g. calibration, correction, "
            "recorder): never more than flow.window samples ahead of the slowest of them, so that no reader loses a "
            "sample whatever the machine (speed is then a ceiling); empty: paced by speed alone, as a live source",
            read_only=True, ptype=Parameter.Type.STRING_ARRAY))
        self.window = p.declare("flow.window", 500, "Samples the replay may run ahead of its slowest reader (at most "
                                "qos.depth: the readers' queues hold them)", read_only=True, range=(1, 100000))
        self.gone_s = p.declare("flow.gone_s", 30.0, "A reader that is not in the graph for this long (wall clock, s: "
                                "it died and was not restarted) is no longer waited for (said)", read_only=True,
                                range=(0.1, 3600.0))
        self.end_timeout = p.declare("flow.end_timeout_s", 120.0, "After the last sample, wait at most this long "
                                     "(wall clock, s) for every reader to have taken the end (and the recorder every "
                                     "station and record) before exiting", read_only=True, range=(0.0, 3600.0))
        end_readers = list(p.declare(
            "flow.end_readers", [], f"Unpaced (no flow.readers): before exiting, wait (at most "
            f"{UNPACED_END_S:g} s, wall clock) until these nodes say on {c.TOPIC_PROGRESS} that they have taken the "
            "end — with what they lost counted — so that the run's accounting has every reader's final counts",
            read_only=True, ptype=Parameter.Type.STRING_ARRAY))
        #: the readers whose end the probe waits for: the paced ones, or (unpaced) flow.end_readers
        self.end_readers = self.flow_readers or end_readers
        self.recorder_name = p.declare("flow.recorder", "recorder", "The reader that records the others' stations "
                                       "and records: the end waits until it has every one of them", read_only=True)
        if self.flow_readers and qos.reliability != ReliabilityPolicy.RELIABLE:
            raise ValueError("flow.readers needs qos.reliability:=reliable (a paced replay loses nothing)")
        if self.flow_readers and self.window > qos.depth:
            raise ValueError(f"flow.window {self.window} exceeds qos.depth {qos.depth}: the readers' queues would "
                             "drop what the window lets through")
        if self.flow_readers and qos.durability != DurabilityPolicy.TRANSIENT_LOCAL:
            raise ValueError("flow.readers needs qos.durability:=transient_local (a reader restarted mid-run gets "
                             "what it missed from the history)")
        self.add_post_set_parameters_callback(self._after_set)

        self.input_damaged = 0  # problems found in an MCAP input (exit status INPUT_DAMAGED at the end)
        self.script, self.cov = self._load()  # raises ValueError/OSError on bad input
        self._pieces = iter(self.script.pieces())
        self._next_piece = next(self._pieces, None)
        self._base = 0                 # sample index of the current piece's first row
        self._t, self._acc, self._mag, self._temp = [], [], [], []
        self._ref_changes, self._depth_changes = [], []   # of the current piece, sample indices
        self._ref_key = self._depth_key = None            # the last row's, across pieces
        self._load_piece()

        self.pub_imu = self.create_publisher(Imu, c.TOPIC_IMU, qos)
        self.pub_mag = self.create_publisher(MagneticField, c.TOPIC_MAG, qos)
        self.pub_temp = self.create_publisher(Temperature, c.TOPIC_TEMPERATURE, qos)
        # as deep as the samples' history: a reader whose delivery stalled until the next heartbeat
        # repair (a loaded machine) gets every reference and depth sent meanwhile
        side_qos = c.latched_qos(depth=qos.depth) if self.flow_readers else c.reliable_qos(100)
        self.pub_ref = self.create_publisher(Vector3Stamped, c.TOPIC_REFERENCE, side_qos)
        self.pub_depth = self.create_publisher(Float64, c.TOPIC_DEPTH, side_qos)
        # the source's announcement, its pacing and what it sent (StreamProgress): the readers'
        # stations wait on the data's time alone, and the run's accounting starts here
        self.pub_progress = self.create_publisher(StreamProgress, c.TOPIC_PROGRESS, c.latched_qos())
        # what the end waits to have acknowledged by every matched reader (_drained)
        self._reliable_pubs = [self.pub_ref, self.pub_depth, self.pub_progress] + (
            [self.pub_imu, self.pub_mag, self.pub_temp] if qos.reliability == ReliabilityPolicy.RELIABLE else [])
        self.progress = StreamProgress(node=self.get_name(), settled=math.nan, window=self.window if self.flow_readers
                                       else 0, **self._announcement)
        self._acks = {}              # reader -> data time of the last sample it took
        self._reader_ends = {}       # reader -> its last StreamProgress once it says end
        self._reader_counts = {}     # reader -> (stations, records) it reports
        self._gone = set()           # readers no longer waited for
        self._absent_since = {}
        self._in_flight = collections.deque()   # stamps of the samples sent and not yet taken by every reader
        self._stall_said = 0.0
        self._graph_check = 0.0
        self._progress_wall = -math.inf
        if self.end_readers:
            self.create_subscription(StreamProgress, c.TOPIC_PROGRESS, self._on_progress, c.latched_qos(depth=100))
        self.pub_serial = self.create_publisher(String, c.TOPIC_SERIAL, c.latched_qos())
        self._publish_serial()
        self.pub_clock = (self.create_publisher(ClockMsg, c.TOPIC_CLOCK, c.sensor_qos(10))
                          if self.stamp_mode == "log" else None)
        self._clock_msg = ClockMsg()
        self._clock_wall = -math.inf
        self._init_messages()

        self.done = Future()
        self._i = 0                   # the next sample to publish (index in the script)
        self._next_ref = 0            # the next change to publish (index in the piece's lists)
        self._next_depth = 0
        self._depth_sent = -math.inf
        self._ref_now = None          # the reference in effect (published), None before the first
        self._depth_now = math.nan    # the depth in effect (published), NaN before the first
        self._sent_t = -math.inf      # stamp of the last sample published
        self._last_sent_wall = time.monotonic()
        self._ref_sent = -math.inf    # stamp of the last reference published
        self._state = "waiting"
        self._created = time.monotonic()
        self._wall0 = self._log0 = 0.0
        self._stamp0 = 0.0
        self._publish_progress(force=True)   # the announcement, before the first sample
        period = min(max(1.0 / (self.rate_hz * self.speed), MIN_TICK_S), 0.02)
        self._timer = c.steady_timer(self, period, self._tick)
        dur = self.script.t_last - self.script.t_first
        self.get_logger().info(
            f"source={self.source}: {self.script.n} samples over {dur:.1f} s of log time; speed {self.speed:g} "
            f"-> about {dur / self.speed:.1f} s; timer {1e3 * period:.1f} ms")

    # ---- preparation -----------------------------------------------------------------------
    def _load(self):
        if self.source == "simulate":
            return self._simulate()
        if not self.path:
            raise ValueError(f"source:={self.source} needs the parameter path")
        if self.source == "csv":
            log, rejections = read_csv(self.path, mag_unit=self.mag_unit)
            for r in rejections[:10]:
                self.get_logger().warning(f"{self.path}: {r}")
            if rejections:
                self.get_logger().warning(f"{self.path}: {len(rejections)} rows rejected")
            # tesla: a log's nT divided as reprocess and `bag from-csv` do, so that every path sees the
            # same numbers
            self._announce(log.ref, log.temp_c, log.md_m)
            return _Script.whole(log, log.mag / c.NT_PER_TESLA, self.chunk_samples), self._covariance(log)
        log, cov = self._read_bag(self.path)
        self._announce(log.ref, log.temp_c, log.md_m)
        # a bag's recorded values unchanged (bit for bit)
        return _Script.whole(log, self._recorded_tesla, self.chunk_samples), cov

    def _announce(self, ref, temp_c, md_m):
        """The side streams this script keeps current (published at least every
        REFERENCE_PERIOD_S of log time while defined; the temperature with every sample)."""
        self._announcement = dict(has_reference=bool(np.isfinite(np.asarray(ref, float)).any()),
                                  has_temperature=bool(np.isfinite(np.asarray(temp_c, float)).any()),
                                  has_depth=bool(np.isfinite(np.asarray(md_m, float)).any()))

    def _simulate(self):
        noise = {k: v for k, v in (("noise_acc", self.noise_acc), ("noise_mag", self.noise_mag)) if v > 0}
        probe = sim.build_probe(self.seed, list(self.effects), severity=self.severity, **noise)
        rng = np.random.default_rng(self.seed + 1)
        # Each session's pieces are set aside (chunks) before the next session is planned: the
        # generator then runs as in one whole simulation (:meth:`simulate.SessionPlan.chunks`).
        plans, pieces, t0, lead_in = [], [], 0.0, None
        if self.calibrate:
            # The stand faces true north (the lab's convention for Table 1's poses, calibrate.labmodel: a
            # surveyed reference line); a stand facing elsewhere is the lab's heading offset.
            stations = sim.twelve_pose_session(self.cal_temps, duration_s=self.station_s)
            plans.append(sim.SessionPlan(probe, self.site, stations, rng, rate_hz=self.rate_hz,
                                         move_s=self.move_s, t0=t0, survey=False))
            pieces.append(plans[-1].chunks(self.chunk_samples))
            t0 = plans[-1].t_last + 1.0 / self.rate_hz
            # the probe keeps streaming while it is taken from the stand to the survey
            lead_in = (stations[-1].rotation, self.survey_gap)
        if self.survey == "stand_grid":
            stations = sim.stand_grid_session(self.grid_drifts, self.grid_azimuths, self.grid_toolfaces,
                                              duration_s=self.station_s)
        elif self.survey == "well_path":
            stations = sim.well_path_session(self.well_n, kickoff_deg=self.well_kickoff,
                                             build_deg_per_station=self.well_build,
                                             duration_s=self.station_s, seed=self.seed)
        else:
            stations = []
        if stations:
            plans.append(sim.SessionPlan(probe, self.site, stations, rng, rate_hz=self.rate_hz,
                                         move_s=self.move_s, t0=t0, survey=True, lead_in=lead_in))
            pieces.append(plans[-1].chunks(self.chunk_samples))
        if not plans:
            raise ValueError("nothing to simulate: calibration_session is false and survey is none")
        every = [st for plan in plans for st in plan.stations]
        self._announce([st.ref for st in every], [st.temp_c for st in every], [st.md_m for st in every])
        if self.truth_file:
            self._write_truth(probe, plans)
        script = _Script(sum(p.n for p in plans), float(plans[0].labels(0, 1)[0][0]), plans[-1].t_last,
                         ((log, log.mag / c.NT_PER_TESLA) for it in pieces for log in it))
        return script, (self._diagonal((probe.noise_acc,) * 3),
                        self._diagonal((probe.noise_mag * c.TESLA_PER_NT,) * 3))

    def _write_truth(self, probe, plans):
        # The stations as simulated (labels), not as detected: the label runs of the script, found on
        # one row per segment of the plans (a segment's rows all carry its labels), so that no
        # per-sample list of the whole script is built.
        segs = [(plan, base, j) for plan, base in zip(plans, np.cumsum([0] + [p.n for p in plans]).tolist())
                for j in range(len(plan.segments))]
        pose = np.array([p.stations[p.segments[j][2]].pose if p.segments[j][2] >= 0 else 0 for p, _, j in segs])
        ref = np.array([p.stations[p.segments[j][2]].ref if p.segments[j][2] >= 0 else (np.nan,) * 3
                        for p, _, j in segs], dtype=float).reshape(-1, 3)
        z = np.zeros(len(segs))
        runs = []
        for j0, j1, pose_k, ref_k in label_runs(ProbeLog(z, np.zeros((len(segs), 3)), np.zeros((len(segs), 3)), z,
                                                         pose, ref)):
            (p0, b0, s0), (p1, b1, s1) = segs[j0], segs[j1]
            runs.append((b0 + p0.offsets[s0], b1 + p1.offsets[s1 + 1] - 1, pose_k, ref_k,
                         float(p0.labels(p0.offsets[s0], p0.offsets[s0] + 1)[0][0]),
                         float(p1.labels(p1.offsets[s1 + 1] - 1, p1.offsets[s1 + 1])[0][0])))
        n = sum(p.n for p in plans)
        truth_cal = Calibration(probe.model, probe_id=self.serial or f"SIM-{self.seed}", method="simulator truth",
                                site=self.site)     # the probe's own record: named by the serial it publishes
        truth = {
            "source": "simulate", "seed": self.seed, "effects": list(self.effects),
            "severity": self.severity, "rate_hz": self.rate_hz, "site": self.site.to_dict(),
            "probe": probe.to_dict(),
            "coefficients": {s: {"parameters": truth_cal.triad(s).parameters(),
                                 "correction_matrix": c.as_list(truth_cal.triad(s).correction_matrix),
                                 "offset": c.as_list(truth_cal.triad(s).correction_offset),
                                 "convention": "gravity vector (acc), nT (mag)"} for s in ("acc", "mag")},
            "stations": [{"pose": int(pose), "ref": [None if not math.isfinite(x) else float(x) for x in ref],
                          "t_start": t0, "t_end": t1} for _, _, pose, ref, t0, t1 in runs],
            "samples": n,
        }
        d = os.path.dirname(os.path.abspath(self.truth_file))
        os.makedirs(d, exist_ok=True)
        atomic_write_text(self.truth_file, json.dumps(truth, indent=1) + "\n")
        truth_cal.save(os.path.join(d, "truth_coeffs.yaml"))
        self.get_logger().info(f"wrote {self.truth_file} and truth_coeffs.yaml")

    def _publish_serial(self):
        """The probe's serial, latched: the parameter, else the bag's, else SIM-<seed> for the
        simulator; a parameter contradicting the bag's is a bad start-up parameter."""
        bag = getattr(self, "_bag_serial", "")
        if self.serial and bag and self.serial != bag:
            raise ValueError(f"probe_serial {self.serial!r} contradicts the bag's {c.TOPIC_SERIAL} ({bag!r})")
        serial = self.serial or bag or (f"SIM-{self.seed}" if self.source == "simulate" else "")
        self.progress.serial = serial      # in the announcement too: readers check records before any station
        if not serial:
            self.get_logger().warning("the data name no probe (no probe_serial, none in the input): the records and "
                                      "stations cannot be checked against it")
            return
        self.pub_serial.publish(String(data=serial))
        self.get_logger().info(f"probe {serial}")

    def _read_bag(self, path):
        """Samples of a recorded bag: imu, mag (and temperature, reference) paired by stamp.

        Read with the tolerant reader (:func:`bag.open_bag`): a truncated or damaged file (a
        recorder that was killed) is replayed up to its last readable chunk, with a warning naming
        the file and byte offset of the damage.  Topics other than the four probe topics, or with
        another type, are skipped with a warning naming them; a message that does not decode is
        skipped with a warning naming topic and log time.
        """
        from ..io.bag import BagError, open_bag

        try:
            reader = open_bag(path)
        except BagError as exc:
            raise ValueError(str(exc)) from None
        log = self.get_logger()
        skipped, undecodable = {}, {}
        imu, mag, temp, ref = {}, {}, {}, []
        depth, imu_sent = [], {}     # the depth has no stamp: it holds from the sample sent before it
        cov_acc = cov_mag = None
        self._bag_serial = ""
        for m in reader.messages(strict=False):
            want = KNOWN_BAG_TOPICS.get(m.topic)
            if want is None or m.type != want:
                if m.topic not in skipped:
                    skipped[m.topic] = 0
                    if want is None and m.topic in GRAPH_OUTPUTS:   # a recorded run's own outputs: expected
                        log.info(f"{path}: {m.topic} is an output of the recorded graph: not replayed")
                    else:
                        log.warning(f"{path}: topic {m.topic} ({m.type or '?'}) is not replayed: skipped"
                                    if want is None else
                                    f"{path}: topic {m.topic} has type {m.type or '?'}, expected {want}: skipped")
                skipped[m.topic] += 1
                continue
            # decoded where reprocess decodes the same bytes (inclinometer_calib.io.cdr)
            try:
                if m.topic == c.TOPIC_DEPTH:
                    depth.append((m.publish_time, cdr.decode_float64(m.data)))   # the send order (as reprocess)
                elif m.topic == c.TOPIC_SERIAL:    # latched, published once at the start (not replayed)
                    self._bag_serial = self._bag_serial or cdr.decode_string(m.data)
                elif m.topic == c.TOPIC_IMU:
                    key, imu[key] = cdr.decode_imu(m.data)
                    imu_sent[key] = m.publish_time
                    cov_acc = cdr.imu_covariance(m.data)
                elif m.topic == c.TOPIC_MAG:
                    key, mag[key] = cdr.decode_vector3(m.data)   # tesla as recorded: republished unchanged
                    cov_mag = cdr.mag_covariance(m.data)
                elif m.topic == c.TOPIC_TEMPERATURE:
                    key, temp[key] = cdr.decode_temperature(m.data)
                else:
                    key, v = cdr.decode_vector3(m.data)
                    ref.append((key[0] + 1e-9 * key[1], v))
            except cdr.DECODE_ERRORS as exc:
                if m.topic not in undecodable:
                    log.warning(f"{path}: {m.topic} message at log time {m.log_time} ns does not decode "
                                f"({type(exc).__name__}: {exc}): skipped")
                undecodable[m.topic] = undecodable.get(m.topic, 0) + 1
        for err in reader.errors:
            log.warning(f"{err}; replaying the messages read before it")
        self.input_damaged = len(reader.errors) + sum(undecodable.values())
        for topic, n in skipped.items():
            if topic not in GRAPH_OUTPUTS:
                log.warning(f"{path}: {n} messages on {topic} skipped")
        for topic, n in undecodable.items():
            log.warning(f"{path}: {n} undecodable messages on {topic} skipped")
        keys = sorted(set(imu) & set(mag))
        if not keys:
            raise ValueError(f"{path}: no {c.TOPIC_IMU} and {c.TOPIC_MAG} samples with matching stamps")
        lost = len(set(imu) ^ set(mag))
        if lost:
            self.get_logger().warning(f"{path}: {lost} imu/mag samples without a partner: skipped")
        t = np.array([k[0] + 1e-9 * k[1] for k in keys])
        refs = np.full((len(keys), 3), np.nan)
        ref.sort(key=lambda x: x[0])
        for k, (t_r, v) in enumerate(ref):
            t_next = ref[k + 1][0] if k + 1 < len(ref) else np.inf
            refs[(t >= t_r - 1e-10) & (t < t_next - 1e-10)] = v
        self._recorded_tesla = np.array([mag[k] for k in keys])
        log = ProbeLog(t, np.array([imu[k] for k in keys]), self._recorded_tesla * c.NT_PER_TESLA,
                       np.array([temp.get(k, np.nan) for k in keys]), np.zeros(len(keys), dtype=int), refs,
                       md_m=depth_per_sample(depth, [imu_sent[k] for k in keys]))
        self.get_logger().info(f"{path}: {len(keys)} samples, {len(ref)} reference changes")
        return log, self._covariance(log, (cov_acc, cov_mag))

    @staticmethod
    def _diagonal(sigmas):
        """A row-major 3x3 covariance with the squares of the per-axis ``sigmas`` on the diagonal."""
        cov = [0.0] * 9
        for k, v in zip((0, 4, 8), sigmas):
            cov[k] = float(v) ** 2
        return cov

    def _covariance(self, log, recorded=(None, None)):
        """Covariances to publish for a replayed log: (acc in (m/s^2)^2, mag in T^2), row-major 3x3.

        Per sensor: the ``noise_*`` parameter if > 0; else a recorded covariance with a positive
        diagonal (``recorded``: the bag's last message's, kept as is); else the per-axis noise
        measured from the whole log (:func:`noise.estimate_noise`); else (too little static data)
        zeros, which sensor_msgs reads as "unknown", with a warning.
        """
        level, out, says = None, [], []
        for k, (name, override, rec, unit, to_msg) in enumerate((
                ("accelerometer", self.noise_acc, recorded[0], "m/s^2", 1.0),
                ("magnetometer", self.noise_mag, recorded[1], "nT", c.TESLA_PER_NT))):
            if override > 0:
                sig, src = (override,) * 3, "the noise parameter"
            elif rec is not None and all(rec[i] > 0 for i in (0, 4, 8)):
                out.append([float(x) for x in rec])
                sig = tuple(math.sqrt(rec[i]) / to_msg for i in (0, 4, 8))
                says.append(f"{name} {'/'.join(f'{x:.3g}' for x in sig)} {unit} (recorded in the bag)")
                continue
            else:
                if level is None:
                    level = estimate_noise(log.t_s, log.acc, log.mag)
                sig = level.acc if k == 0 else level.mag
                src = f"measured from the data, {level.blocks} blocks"
                if not all(math.isfinite(x) and x > 0 for x in sig):
                    self.get_logger().warning(f"{name} noise cannot be measured from {len(log)} samples "
                                              "(too little static data): publishing a zero covariance (unknown)")
                    sig, src = (0.0,) * 3, "unknown"
            out.append(self._diagonal(tuple(x * to_msg for x in sig)))
            says.append(f"{name} {'/'.join(f'{x:.3g}' for x in sig)} {unit} ({src})")
        self.get_logger().info("published noise (1 sigma per axis x/y/z): " + "; ".join(says))
        return out[0], out[1]

    def _publish_reference(self, stamp_s):
        ref = Vector3Stamped()
        ref.header.frame_id = self.frame_id
        c.set_stamp(ref.header.stamp, stamp_s)
        ref.vector.x, ref.vector.y, ref.vector.z = self._ref_now
        self.pub_ref.publish(ref)
        self._ref_sent = stamp_s
        self.progress.reference += 1

    def _load_piece(self) -> bool:
        """Make the next piece of the script current (its samples as floats, the reference and
        depth changes in it); False at the end of the script.  One piece ahead is prepared, so
        that a depth change at a piece's last sample knows whether it holds."""
        piece, self._next_piece = self._next_piece, next(self._pieces, None)
        if piece is None:
            return False
        log, tesla = piece
        self._base += len(self._t)
        self._t = log.t_s.tolist()
        self._acc = log.acc.tolist()
        self._mag = np.asarray(tesla).tolist()
        self._temp = log.temp_c.tolist()
        first = self._base == 0
        self._ref_changes, self._ref_key = _changes(log.ref.tolist(), self._base, self._ref_key)
        if first and self._ref_changes and all(not math.isfinite(x) for x in self._ref_changes[0][1]):
            self._ref_changes.pop(0)  # no reference at the start: nothing to announce
        md = log.md_m.tolist()
        if self._next_piece is not None and len(self._next_piece[0]):
            md.append(float(self._next_piece[0].md_m[0]))   # the sample after the piece's last
        changes, _ = _changes([(x,) for x in md], self._base, self._depth_key)
        changes = [ch for ch in changes if ch[0] < self._base + len(self._t)]
        if first and changes and not math.isfinite(changes[0][1][0]):
            changes.pop(0)
        # a depth that holds (the next sample has the same) goes out at once; a running one throttled
        self._depth_changes = [(k, v, k + 1 - self._base >= len(md) or _same(md[k - self._base], md[k + 1 - self._base]))
                               for k, v in changes]
        self._depth_key = (None if not math.isfinite(md[len(self._t) - 1]) else md[len(self._t) - 1],) if self._t \
            else self._depth_key
        self._next_ref = self._next_depth = 0
        return True

    def _init_messages(self):
        """The sample messages as the probe sends them (``m_imu``, ``m_mag``, ``m_temp``: what a
        reader receives, less stamp and values), serialized once: each sample goes out as these
        bytes with its stamp and values patched in (:class:`cdr.Patcher`, the same bytes)."""
        cov_acc, cov_mag = self.cov
        self.m_imu = Imu()
        self.m_imu.header.frame_id = self.frame_id
        self.m_imu.orientation_covariance[0] = -1.0
        self.m_imu.angular_velocity_covariance[0] = -1.0
        self.m_imu.linear_acceleration_covariance = [float(x) for x in cov_acc]
        self.m_mag = MagneticField()
        self.m_mag.header.frame_id = self.frame_id
        self.m_mag.magnetic_field_covariance = [float(x) for x in cov_mag]
        self.m_temp = Temperature()
        self.m_temp.header.frame_id = self.frame_id
        self.m_temp.variance = 0.0
        self._cdr_imu = cdr.Patcher.imu(serialize_message(self.m_imu))
        self._cdr_mag = cdr.Patcher.vector3(serialize_message(self.m_mag))
        self._cdr_temp = cdr.Patcher.temperature(serialize_message(self.m_temp))

    # ---- publishing ------------------------------------------------------------------------
    def _after_set(self, params):
        for prm in params:
            if prm.name == "speed":
                self._anchor()  # keep the current log position, continue at the new speed
                self.speed = prm.value
            elif prm.name in ("on_end", "max_batch"):
                setattr(self, prm.name, prm.value)

    def _anchor(self):
        now = time.monotonic()
        if self._state == "running":
            self._log0 = self._log0 + (now - self._wall0) * self.speed
            self._stamp0 = self._stamp0 + (now - self._wall0)
        self._wall0 = now

    def _start(self):
        self._state = "running"
        self._wall0 = time.monotonic()
        self._log0 = self.script.t_first
        self._stamp0 = self.get_clock().now().nanoseconds * 1e-9
        self.get_logger().info("publishing")

    def _publish_clock(self, t: float, force: bool = False):
        """/clock := log time ``t`` (s), at most every CLOCK_PERIOD_S of wall time unless ``force``."""
        if self.pub_clock is None:
            return
        now = time.monotonic()
        if force or now - self._clock_wall >= CLOCK_PERIOD_S:
            self._clock_wall = now
            c.set_stamp(self._clock_msg.clock, max(t, 0.0))
            self.pub_clock.publish(self._clock_msg)

    def _missing_subscribers(self) -> list:
        """``topic (have/want)`` for every topic still short of the subscribers it waits for."""
        want = [(pub, self.wait_subs) for pub in (self.pub_imu, self.pub_mag, self.pub_temp)]
        want.append((self.pub_ref, self.wait_ref_subs))
        missing = [f"{pub.topic_name} ({pub.get_subscription_count()}/{n})" for pub, n in want
                   if pub.get_subscription_count() < n]
        for topic, n in (spec.rsplit("=", 1) for spec in self.wait_topics):
            have = self.count_subscribers(topic)   # other nodes' topics, from the graph
            if have < int(n):
                missing.append(f"{topic} ({have}/{n})")
        return missing

    def _tick(self):
        if self._state == "running":
            self._publish_due()
        elif self._state == "waiting":
            if self.script.n:
                self._publish_clock(self.script.t_first)  # the other nodes' clocks start at the log's start
            waited = time.monotonic() - self._created
            missing = self._missing_subscribers()
            if not missing and waited >= self.start_delay:
                self._start()
            elif waited > self.wait_timeout + self.start_delay:
                self.get_logger().warning(f"still waiting for subscribers after {self.wait_timeout:g} s on "
                                          f"{', '.join(missing)}: starting anyway")
                self._start()
        elif self._state == "ending":
            # the end is latched: repeated once a second, not every tick, so that the acknowledgements
            # the end waits for (_drained) are not always one message behind
            self._publish_progress(period=ENDING_PROGRESS_PERIOD_S)
            if self._drained() or time.monotonic() >= self._end_at:
                self._finish()
        if self.flow_readers:
            self._watch_readers()

    def _finish(self):
        self._state = "ended"
        if not self._drained():     # a reader that did not take the end, or a stream not acknowledged
            self.get_logger().error(
                f"the readers did not all take the end within "
                f"{f'flow.end_timeout_s ({self.end_timeout:g} s)' if self.flow_readers else f'{UNPACED_END_S:g} s'}: "
                + "; ".join(self._not_drained()) + " — the run's summary counts what they missed")
        status = 0
        if self.input_damaged:
            status = INPUT_DAMAGED
            self.get_logger().error(f"{self.path}: the input was damaged ({self.input_damaged} problem(s), "
                                    f"see the warnings above): only its readable part was replayed; exit "
                                    f"status {INPUT_DAMAGED}")
        if self.on_end == "stop":
            self.done.set_result(status)
        else:
            self.get_logger().info("script finished; idling (on_end:=idle)")

    # ---- flow control ----------------------------------------------------------------------------
    def _on_progress(self, msg):
        name = msg.node
        if name not in self.end_readers:
            return
        t = c.stamp_to_sec(msg.header.stamp)
        if t > self._acks.get(name, -math.inf):
            self._acks[name] = t
        self._reader_counts[name] = (int(msg.stations), int(msg.records))
        if msg.end:
            self._reader_ends[name] = msg
        elif name in self._reader_ends:
            del self._reader_ends[name]       # restarted: it has not taken the end yet
        if name in self._gone:
            self._gone.discard(name)
            self.get_logger().info(f"reader {name} is back: the replay waits for it again")

    def _slowest(self) -> float:
        """The data time of the last sample every reader waited for has taken."""
        acks = [self._acks.get(r, -math.inf) for r in self.flow_readers if r not in self._gone]
        return min(acks) if acks else math.inf

    def _allowance(self) -> int:
        """How many more samples may go now: the window less those a reader has not taken."""
        if not self.flow_readers:
            return self.max_batch
        slowest, inflight = self._slowest(), self._in_flight
        while inflight and inflight[0] <= slowest:
            inflight.popleft()
        return self.window - len(inflight)

    def _watch_readers(self):
        """Readers that left the graph (died, not restarted) are waited for at most flow.gone_s; a
        replay that stalls on a slow reader says so every 10 s."""
        now = time.monotonic()
        if now - self._graph_check < 0.5:
            return
        self._graph_check = now
        present = {i.node_name for i in self.get_publishers_info_by_topic(c.TOPIC_PROGRESS)}
        for r in self.flow_readers:
            if r in present or r in self._gone:
                self._absent_since.pop(r, None)
                continue
            since = self._absent_since.setdefault(r, now)
            if now - since > self.gone_s and (r in self._acks or now - self._created > self.gone_s):
                self._gone.add(r)
                self.get_logger().error(f"reader {r} has not been in the graph for {self.gone_s:g} s: the replay no "
                                        "longer waits for it (what it misses is lost to it, and counted)")
        if self._state == "running" and self._allowance() <= 0 and now - self._stall_said > 10.0 \
                and now - self._progress_wall < 1.0:
            slow = [r for r in self.flow_readers if r not in self._gone and
                    self._acks.get(r, -math.inf) <= self._slowest()]
            if now - self._last_sent_wall > 10.0:
                self._stall_said = now
                self.get_logger().warning(f"the replay waits for {', '.join(slow)} (at t="
                                          f"{self._slowest():.2f} s, {self.window} samples behind) for "
                                          f"{now - self._last_sent_wall:.0f} s")

    def _not_drained(self) -> list:
        # every reliable stream acknowledged by every matched reader: a message lost in transport
        # waits for the writer's next heartbeat to be repaired (seconds), and a recorder stopped
        # before that never has it (the references a loaded machine's recorder lost at the end)
        out = [f"{pub.topic_name} is not acknowledged by every reader" for pub in self._reliable_pubs
               if not pub.wait_for_all_acked(_NO_WAIT)]
        out += [f"{r} has not" for r in self.end_readers if r not in self._gone and r not in self._reader_ends]
        rec = self.recorder_name
        if rec in self.flow_readers and rec not in self._gone and rec in self._reader_counts:
            have = self._reader_counts[rec]
            others = [v for r, v in self._reader_counts.items() if r != rec]
            want = (max((v[0] for v in others), default=0), max((v[1] for v in others), default=0))
            if have[0] < want[0] or have[1] < want[1]:
                out.append(f"{rec} has recorded {have[0]} of {want[0]} stations and {have[1]} of {want[1]} records")
        return out

    def _drained(self) -> bool:
        """Every reliable stream is acknowledged by every reader, every reader has taken the end,
        and the recorder every station and record the others published (their last counts, with
        the end)."""
        # the end (and every message of a reliable stream) is in every matched reader's queue —
        # acknowledged — before the writers go with this process; the end readers have taken it
        return not self._not_drained()

    def _publish_progress(self, force: bool = False, end: bool = False, period: float = PROGRESS_PERIOD_S):
        now = time.monotonic()
        if not force and now - self._progress_wall < period:
            return
        self._progress_wall = now
        m = self.progress
        if self._sent_t > -math.inf:
            c.set_stamp(m.header.stamp, max(self._sent_t, 0.0))
        m.end = m.end or end
        self.pub_progress.publish(m)

    # ---- publishing --------------------------------------------------------------------------
    def _publish_due(self):
        now = time.monotonic()
        target = self._log0 + (now - self._wall0) * self.speed
        allowed = self._allowance()
        budget, last = min(self.max_batch, allowed), None
        now_stamps = self.stamp_mode == "now"
        n = self.script.n
        held = False
        while budget > 0:
            t, base = self._t, self._base
            i = self._i - base
            if i >= len(t):
                if not self._load_piece():
                    break
                continue
            end = i
            while end < len(t) and t[end] <= target and end - i < budget:
                end += 1
            for k in range(i, end):
                tk = t[k]
                if now_stamps:
                    tk = self._stamp0 + (tk - self._log0) / self.speed
                self._publish_sample(base + k, tk)
            if end > i:
                last = t[end - 1]
            budget -= end - i
            self._i = base + end
            if end < len(t):
                held = budget <= 0 and t[end] <= target   # due, but the window (or the batch) is full
                break        # the samples due are out (or the batch is full)
        if self._i >= n and self._next_piece is None and self._i - self._base >= len(self._t):
            self._i = n
        if last is not None:
            self._last_sent_wall = now
            self._publish_clock(last, force=self._i >= n)  # stamp:=log only
        if held and allowed < self.max_batch and self.flow_readers and last is not None:
            # the readers set the pace: --speed is a ceiling, never caught up in a burst afterwards
            self._log0, self._wall0 = last, now
            self._stamp0 = now if now_stamps else self._stamp0
        if self._i >= n:
            self._state = "ending"
            self._end_at = time.monotonic() + (self.end_timeout if self.flow_readers else
                                               min(self.end_timeout, UNPACED_END_S))
            self._publish_progress(force=True, end=True)
            self.get_logger().info(f"end of script: {n} samples published (on_end:={self.on_end})"
                                   + (f"; waiting for {', '.join(self.end_readers)} to take it" if self.end_readers
                                      else ""))
        else:
            self._publish_progress()

    def _publish_sample(self, k, stamp_s):
        ch = self._depth_changes
        pg = self.progress
        if self._next_depth < len(ch) and ch[self._next_depth][0] <= k:
            # a depth running (a move) goes out at most every DEPTH_PERIOD_S; one that holds at once
            _, value, held = ch[self._next_depth]
            self._depth_now = value[0]
            if held or stamp_s - self._depth_sent >= DEPTH_PERIOD_S:
                self._publish_depth(stamp_s)
            self._next_depth += 1
        elif self.progress.has_depth and stamp_s - self._depth_sent >= REFERENCE_PERIOD_S:
            # unchanged: repeated — NaN while there is none — so readers know it is current
            self._publish_depth(stamp_s)
        if self._next_ref < len(self._ref_changes) and self._ref_changes[self._next_ref][0] <= k:
            self._ref_now = self._ref_changes[self._next_ref][1]
            self._publish_reference(stamp_s)
            self._next_ref += 1
        elif (self._ref_now is not None or self.progress.has_reference) and stamp_s - self._ref_sent >= REFERENCE_PERIOD_S:
            if self._ref_now is None:
                self._ref_now = (math.nan,) * 3   # none yet: said as NaN (not given), so readers know
            self._publish_reference(stamp_s)   # unchanged: repeated, so readers know it is current
        if self.flow_readers:
            self._in_flight.append(stamp_s)
        self._sent_t = stamp_s
        pg.imu += 1
        pg.mag += 1
        sec, nsec = stamp_parts(stamp_s)
        j = k - self._base
        a, m = self._acc[j], self._mag[j]
        # the bytes rclpy would serialize from the message _init_messages built, stamp and values patched
        self.pub_imu.publish(self._cdr_imu(sec, nsec, a[0], a[1], a[2]))
        self.pub_mag.publish(self._cdr_mag(sec, nsec, m[0], m[1], m[2]))
        tc = self._temp[j]
        if tc == tc:  # not NaN
            self.pub_temp.publish(self._cdr_temp(sec, nsec, tc))
            pg.temperature += 1

    def _publish_depth(self, stamp_s):
        self.pub_depth.publish(Float64(data=float(self._depth_now)))
        self._depth_sent = stamp_s
        self.progress.depth += 1


def main(args=None):
    return c.run(ProbeNode, args)


if __name__ == "__main__":
    sys.exit(main())

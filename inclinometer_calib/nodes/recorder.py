"""``recorder`` node: record topics to a rosbag2-compatible MCAP file (rosbag2 has no PyPI wheel).

    python -m inclinometer_calib.nodes.recorder --ros-args -p output:=run1.mcap
    python -m inclinometer_calib.nodes.recorder --ros-args --params-file config/recorder.yaml

Every ``discovery_period_s`` the graph is listed (``get_topic_names_and_types``); each new topic
that passes ``topics`` / ``exclude`` and has at least one publisher is subscribed with
``raw=True`` (serialized CDR, no deserialization) and a QoS matched to its publishers, as
``ros2 bag record`` does: reliable only if every publisher is reliable, transient-local only if
every publisher is (so latched messages such as calibration coefficients published before the
recorder started are still delivered). The callback hands the bytes straight to
:class:`inclinometer_calib.bag.BagWriter` (log time = the wall-clock receive time, publish time =
the publisher's source timestamp); as a process, the node serves these subscriptions on a wait set
of their own (:class:`.executor.HotPathExecutor`: every message waiting is written per wake-up).
Log times stay wall-clock time even when the graph runs on the
probe's ``/clock`` (header stamps in log time): what ``ros2 bag record`` does without
``--use-sim-time``; the header stamps inside the messages carry the run's time base.

Topic types are imported with importlib (``pkg.msg`` module + class; ``rosidl_runtime_py`` is
not on PyPI). A topic whose type cannot be imported is skipped with a warning; at shutdown the
recorded topics are listed with their message counts.

SIGINT/SIGTERM finalize the file (summary, statistics, ``rosbag2`` metadata; ``metadata.yaml``
for a directory output). A crash or SIGKILL leaves a file whose complete chunks are readable
(``inclinometer_calib.bag.open_bag`` / ``recover``); chunks are closed at least every
``max_chunk_s`` seconds, so at most that much data is lost. An existing output is never
overwritten: the node refuses to start (exit status 1).
"""
from __future__ import annotations

import importlib
import math
import signal
import struct
import sys
import time
from datetime import datetime, timezone
from typing import Dict, List, Optional, Set

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..bag import BagWriter, UnknownTypeError, normalize_type
from ..topics import (TOPIC_COEFFICIENTS, TOPIC_DEPTH, TOPIC_IMU, TOPIC_MAG, TOPIC_PROGRESS, TOPIC_REFERENCE,
                      TOPIC_STATION, TOPIC_TEMPERATURE)
from .executor import HotPathExecutor, spin

NODE_NAME = "recorder"
DEFAULT_EXCLUDE = ["/rosout", "/parameter_events"]
#: graph scan period, s: the probe waits for the recorder's subscriptions before its first sample,
#: so a launcher run starts up to one period later (1 s made it 2 s; a scan costs about 10 us)
DISCOVERY_PERIOD_S = 0.25
SUBSCRIPTION_DEPTH = 1000  # keep-last depth of each recording subscription (absorbs stalls)
#: What the recorder counts and reports (StreamProgress): the run's accounting, and the data time
#: of the last sample written, on which a paced replay waits.
COUNTED = {TOPIC_IMU: "imu", TOPIC_MAG: "mag", TOPIC_TEMPERATURE: "temperature", TOPIC_REFERENCE: "reference",
           TOPIC_DEPTH: "depth", TOPIC_STATION: "stations", TOPIC_COEFFICIENTS: "records"}
#: A chunk is closed (handed to the operating system) at least every this many samples, so that
#: what a killed recorder loses is still in the probe's history (qos.depth, 20 000 in a paced
#: replay) for the restarted one.
FLUSH_SAMPLES = 4000
#: The progress goes out at most this often (wall, s).
PROGRESS_PERIOD_S = 0.05


def default_output() -> str:
    return datetime.now(timezone.utc).strftime("survey_%Y%m%dT%H%M%SZ.mcap")


def import_message_type(type_name: str):
    """``pkg/msg/Type`` -> the generated Python class (ImportError/AttributeError if missing)."""
    pkg, sub, name = normalize_type(type_name).split("/")
    module = importlib.import_module(f"{pkg}.{sub}")
    return getattr(module, name)


def _enum_name(value) -> str:
    name = getattr(value, "name", None)
    return str(name if name is not None else value).lower()


def _ns(duration) -> int:
    ns = getattr(duration, "nanoseconds", None)
    if ns is None:
        ns = int(getattr(duration, "sec", 0)) * 1_000_000_000 + int(getattr(duration, "nanosec", 0))
    return int(ns)


def qos_to_dict(qos) -> dict:
    """rclpy QoSProfile (as offered by a publisher) -> mapping for ``bag.qos_profiles_yaml``."""
    return {
        "history": _enum_name(qos.history),
        "depth": int(qos.depth),
        "reliability": _enum_name(qos.reliability),
        "durability": _enum_name(qos.durability),
        "deadline_ns": _ns(qos.deadline),
        "lifespan_ns": _ns(qos.lifespan),
        "liveliness": _enum_name(qos.liveliness),
        "liveliness_lease_duration_ns": _ns(qos.liveliness_lease_duration),
        "avoid_ros_namespace_conventions": bool(qos.avoid_ros_namespace_conventions),
    }


def subscription_qos(offered) -> QoSProfile:
    """QoS compatible with all offered profiles, as strong as they all allow (rosbag2's rule), with a
    history at least as deep as theirs: a recorder restarted mid-run takes all the history a
    transient-local publisher keeps for it (a paced replay's last 20 000 samples)."""
    reliable = bool(offered) and all(
        q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(
        q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max([SUBSCRIPTION_DEPTH] + [int(q.depth) for q in offered]),
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _make_callback(write, channel_id: int, now=time.time_ns):
    # two positional parameters: rclpy then passes the message info (source timestamp)
    def callback(data, info):
        write(channel_id, data, now(), info["source_timestamp"])
    return callback


_STAMP = {0: struct.Struct(">iI"), 1: struct.Struct("<iI")}


def cdr_stamp(data) -> float:
    """The header stamp (s) of a message whose CDR bytes begin with a ``std_msgs/Header``."""
    sec, nsec = _STAMP[data[1] & 1].unpack_from(data, 4)
    return sec + 1e-9 * nsec


def _topic_name(name: str) -> str:
    name = name.strip()
    return name if name.startswith("/") else "/" + name


class Recorder(Node):
    """Records the chosen topics to one bag; :meth:`close` finalizes it."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        ro = dict(read_only=True)
        self.declare_parameter("output", "", ParameterDescriptor(
            description="Output bag: a *.mcap file, or a directory (ros2 bag layout "
                        "dir/metadata.yaml + dir/dir_0.mcap). Empty: survey_<UTC time>.mcap. "
                        "An existing path is never overwritten.",
            type=ParameterType.PARAMETER_STRING, **ro))
        self.declare_parameter("topics", [""], ParameterDescriptor(
            description="Topics to record (exact names); empty list = every topic seen.",
            type=ParameterType.PARAMETER_STRING_ARRAY, **ro))
        self.declare_parameter("exclude", list(DEFAULT_EXCLUDE), ParameterDescriptor(
            description="Topics never recorded (exact names).",
            type=ParameterType.PARAMETER_STRING_ARRAY, **ro))
        self.declare_parameter("discovery_period_s", DISCOVERY_PERIOD_S, ParameterDescriptor(
            description="Period of the graph scan for new topics, seconds (> 0): a new topic's first "
                        "messages may be missed for up to this long.",
            type=ParameterType.PARAMETER_DOUBLE, **ro))
        self.declare_parameter("max_chunk_s", 1.0, ParameterDescriptor(
            description="Longest time span of one MCAP chunk, seconds (> 0): a crash loses at "
                        "most this much data.",
            type=ParameterType.PARAMETER_DOUBLE, **ro))
        self.declare_parameter("compression", "zstd", ParameterDescriptor(
            description="Chunk compression: zstd, lz4 or none.",
            type=ParameterType.PARAMETER_STRING, **ro))

        self.declare_parameter("source.node", "probe", ParameterDescriptor(
            description="The node whose /graph/progress announces the source (its end and what it sent): the "
                        "recorder's own progress says end once it holds every sample sent.",
            type=ParameterType.PARAMETER_STRING, **ro))
        gp = self.get_parameter
        self.source_node = str(gp("source.node").value)
        output = gp("output").value or default_output()
        self.only: Set[str] = {_topic_name(t) for t in (gp("topics").value or []) if t.strip()}
        self.exclude: Set[str] = {_topic_name(t) for t in (gp("exclude").value or []) if t.strip()}
        period = float(gp("discovery_period_s").value)
        max_chunk_s = float(gp("max_chunk_s").value)
        if period <= 0 or max_chunk_s <= 0:
            raise ValueError("discovery_period_s and max_chunk_s must be > 0")
        # the tick timer closes a chunk at most tick_s after its deadline: split the budget so
        # the oldest unflushed message is never older than max_chunk_s
        tick_s = min(0.1, max_chunk_s / 10.0)
        self.bag = BagWriter(output, compression=str(gp("compression").value),
                             max_chunk_s=max_chunk_s - tick_s)
        self.output = str(self.bag.path)
        self._subs: Dict[str, object] = {}
        #: called with each new recording subscription (main(): the executor's ``add_hot``)
        self.on_subscribed = None
        self._skipped: Dict[str, str] = {}
        self._closed = False
        # the run's accounting and the replay's pacing (StreamProgress on /graph/progress)
        self.counts = {k: 0 for k in COUNTED.values()}
        self._t_imu = -math.inf          # stamp of the last /probe/imu written
        self._unflushed = 0
        self._source = None              # the source's last StreamProgress
        self._reported = None
        self._progress_wall = 0.0
        self._progress_type = None
        try:
            from inclinometer_calib.msg import StreamProgress
        except ImportError:              # messages not built: a plain recorder, no progress
            StreamProgress = None
        if StreamProgress is not None:
            def latched(depth):
                return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self._progress_type = StreamProgress
            self.pub_progress = self.create_publisher(StreamProgress, TOPIC_PROGRESS, latched(1))
            self.create_subscription(StreamProgress, TOPIC_PROGRESS, self._on_progress, latched(100))
        self.get_logger().info(
            f"recording to {self.output} (topics: {sorted(self.only) or 'all'}, "
            f"excluding {sorted(self.exclude)}, chunks <= {max_chunk_s:g} s, "
            f"compression {self.bag.compression or 'none'})")
        self._discover()
        # steady clock: discovery and chunk closing go on whatever the ROS clock does (a node
        # started with use_sim_time would otherwise stall when /clock stops)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._discover, clock=steady)
        self.create_timer(tick_s, self.bag.tick, clock=steady)
        if self._progress_type is not None:
            self.create_timer(PROGRESS_PERIOD_S, self._publish_progress, clock=steady)

    # -- discovery ---------------------------------------------------------------------------
    def _wanted(self, topic: str) -> bool:
        if topic in self.exclude:
            return False
        return not self.only or topic in self.only

    def _discover(self) -> None:
        if self._closed:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or topic in self._skipped or not self._wanted(topic):
                continue
            if len(types) != 1:
                self._skip(topic, f"published with several types {types}")
                continue
            type_name = types[0]
            try:
                msg_type = import_message_type(type_name)
            except (ImportError, AttributeError, ValueError) as exc:
                self._skip(topic, f"type {type_name} is not importable here ({exc}); "
                                  "build/source its interface package to record it")
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers so far: QoS unknown, look again later
            offered = [p.qos_profile for p in publishers]
            hashes = {str(getattr(p, "topic_type_hash", "") or "") for p in publishers}
            try:
                cid = self.bag.add_topic(topic, type_name,
                                         qos_profiles=[qos_to_dict(q) for q in offered])
            except (UnknownTypeError, ValueError) as exc:
                self._skip(topic, str(exc))
                continue
            recorded_hash = self.bag.topics[topic].type_hash
            live = {h for h in hashes if h.startswith("RIHS01_")}
            if live and recorded_hash not in live:
                self.get_logger().warning(
                    f"{topic}: type hash of the installed {type_name} ({recorded_hash or 'none'}) "
                    f"differs from the publisher's {sorted(live)}: definitions differ")
            qos = subscription_qos(offered)
            callback = (self._counting_callback(cid, COUNTED[topic]) if topic in COUNTED
                        else _make_callback(self.bag.write, cid))
            self._subs[topic] = self.create_subscription(msg_type, topic, callback, qos, raw=True)
            if self.on_subscribed is not None:
                self.on_subscribed(self._subs[topic])
            self.get_logger().info(
                f"recording {topic} [{type_name}] ({qos.reliability.name.lower()}, "
                f"{qos.durability.name.lower()})")

        for topic in self.only:
            if topic not in self._subs and topic not in self._skipped and topic in self.exclude:
                self._skip(topic, "listed in both topics and exclude")

    # -- accounting and pacing --------------------------------------------------------------
    def _counting_callback(self, channel_id: int, key: str, now=time.time_ns):
        """The write callback of a topic the recorder counts (:data:`COUNTED`); for ``/probe/imu``
        it keeps the last stamp written and closes a chunk every :data:`FLUSH_SAMPLES`."""
        write, counts = self.bag.write, self.counts
        if key != "imu":
            def callback(data, info):
                write(channel_id, data, now(), info["source_timestamp"])
                counts[key] += 1
            return callback

        def imu_callback(data, info):
            write(channel_id, data, now(), info["source_timestamp"])
            counts["imu"] += 1
            self._t_imu = cdr_stamp(data)
            self._unflushed += 1
            if self._unflushed >= FLUSH_SAMPLES:
                self._unflushed = 0
                self.bag.flush()
        return imu_callback

    def _on_progress(self, msg) -> None:
        if msg.node == self.source_node:
            self._source = msg

    def _publish_progress(self) -> None:
        """This recorder's StreamProgress: what it wrote per topic, the stamp of the last sample
        written (a paced replay waits on it), and the end once it holds every sample the source
        says it sent."""
        if self._closed:
            return
        cnt, src = self.counts, self._source
        end = bool(src is not None and src.end and cnt["imu"] >= src.imu and cnt["mag"] >= src.mag)
        key = (tuple(cnt.values()), self._t_imu, end)
        if key == self._reported:
            return
        self._reported = key
        m = self._progress_type(node=self.get_name(), settled=math.nan, end=end)
        if math.isfinite(self._t_imu):
            sec = math.floor(self._t_imu)
            m.header.stamp.sec, m.header.stamp.nanosec = int(sec), min(int(round((self._t_imu - sec) * 1e9)), 999999999)
        for k in ("imu", "mag", "temperature", "reference", "depth", "stations", "records"):
            setattr(m, k, cnt[k])
        self.pub_progress.publish(m)

    def _skip(self, topic: str, reason: str) -> None:
        self._skipped[topic] = reason
        self.get_logger().warning(f"not recording {topic}: {reason}")

    # -- shutdown ----------------------------------------------------------------------------
    def close(self) -> Dict[str, int]:
        """Finalize the bag (idempotent); returns messages per recorded topic."""
        if self._closed:
            return self.bag.message_counts()
        self._closed = True
        for sub in list(self._subs.values()):
            try:
                self.destroy_subscription(sub)
            except Exception:  # noqa: BLE001 - context may already be shut down
                pass
        self.bag.close()
        counts = self.bag.message_counts()
        lines = [f"  {t}: {n}" for t, n in sorted(counts.items())]
        missing = [t for t in sorted(self.only) if t not in counts and t not in self._skipped]
        text = (f"bag {self.output} finalized: {sum(counts.values())} messages on "
                f"{len(counts)} topic(s)\n" + "\n".join(lines))
        if self._skipped:
            text += "\nnot recorded:\n" + "\n".join(
                f"  {t}: {r}" for t, r in sorted(self._skipped.items()))
        if missing:
            text += "\nrequested but never seen: " + ", ".join(missing)
        print(f"[{NODE_NAME}] {text}", file=sys.stderr, flush=True)
        return counts


def main(args: Optional[List[str]] = None) -> int:
    # rclpy 7 (Jazzy) init() returns None, not a context manager: shut down in finally
    rclpy.init(args=args)
    node: Optional[Recorder] = None
    executor: Optional[HotPathExecutor] = None
    try:
        try:
            node = Recorder()
        except (FileExistsError, ValueError, OSError) as exc:
            print(f"[{NODE_NAME}] error: {exc}", file=sys.stderr, flush=True)
            return 1
        # every recording subscription on the hot path: each wake-up writes every message waiting,
        # instead of rclpy's stock executor walking the node's whole wait set per message (the
        # recorder takes every stream of the graph; measured on a 49 400-sample replay at 2 kHz:
        # 12.6 -> 3.7 s of CPU); discovery, chunk closing and the parameter services stay here
        executor = HotPathExecutor(node._subs.values())
        node.on_subscribed = executor.add_hot
        spin(node, executor)   # waits of at most executor.WAKE_S: a lost SIGTERM wake-up cannot hang it
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            executor.shutdown()   # no write from the hot path while the bag is finalized
        if node is not None:
            _finalize(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _finalize(node: Recorder) -> None:
    # a second Ctrl-C / SIGTERM must not interrupt writing the summary
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, signal.SIG_IGN)
        except (ValueError, OSError):
            pass
    try:
        node.close()
    finally:
        for sig, handler in old.items():
            try:
                signal.signal(sig, handler)
            except (ValueError, OSError, TypeError):
                pass


if __name__ == "__main__":
    sys.exit(main())

"""``recorder`` node: record topics to a rosbag2-compatible MCAP file (rosbag2 has no PyPI wheel).

    python -m inclinometer_calib.nodes.recorder --ros-args -p output:=run1.mcap
    python -m inclinometer_calib.nodes.recorder --ros-args --params-file config/recorder.yaml

Every ``discovery_period_s`` the graph is listed (``get_topic_names_and_types``); each new topic
that passes ``topics`` / ``exclude`` and has at least one publisher is subscribed with
``raw=True`` (serialized CDR, no deserialization) and a QoS matched to its publishers, as
``ros2 bag record`` does: reliable only if every publisher is reliable, transient-local only if
every publisher is (so latched messages such as calibration coefficients published before the
recorder started are still delivered). The callback hands the bytes straight to
:class:`inclinometer_calib.io.bag.BagWriter` (log time = the wall-clock receive time, publish time =
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
(``inclinometer_calib.io.bag.open_bag`` / ``recover``); chunks are closed at least every
``max_chunk_s`` seconds, so at most that much data is lost. An existing output is never
overwritten: the node refuses to start (exit status 1).

A write the disk refuses (any ``OSError``: full ``ENOSPC``, quota ``EDQUOT``, ``EFBIG``, ``EIO``)
does not end the node. It says so once, at ERROR: the file, the error in words, when, and what the
file holds (its messages, the receive time and header stamp of the last one). The file is left as
the bag writer leaves it (cut back to its last complete chunk, not finalized: readable as the file
of a killed recorder). From then on the messages are counted per topic, not recorded. Every
``retry_s`` seconds, once the disk has :data:`RETRY_MIN_FREE_BYTES` free again, the node starts a
NEW part beside the first (``survey_1.mcap`` after ``survey.mcap``, the launcher's naming),
never appending after a torn chunk, and says so once at WARNING. An output that cannot even be
created for want of space (``ENOSPC``, ``EDQUOT``) starts the node in that state: it keeps
trying under the output's own name. The shutdown report's last line counts the messages not
recorded per topic (``recording incomplete: 1520 messages on /probe/imu, ... not recorded: disk
full``) and the node exits with :data:`RECORDING_INCOMPLETE` (4): a part not finalized or a
message not recorded.
"""
from __future__ import annotations

import errno
import importlib
import math
import os
import re
import signal
import struct
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Dict, List, Optional, Set, Tuple

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from ..io.bag import (BagError, BagWriter, UnknownTypeError, normalize_type, open_bag, run_parts,
                   type_hash)
from ..core.output import refused_write_words
from ..io.topics import (TOPIC_COEFFICIENTS, TOPIC_DEPTH, TOPIC_IMU, TOPIC_MAG, TOPIC_PROGRESS, TOPIC_REFERENCE,
                      TOPIC_STATION, TOPIC_TEMPERATURE)
from .executor import HotPathExecutor, install_stop_hook, spin

NODE_NAME = "recorder"
DEFAULT_EXCLUDE = ["/rosout", "/parameter_events"]
#: graph scan period, s: the probe waits for the recorder's subscriptions before its first sample,
#: so a launcher run starts up to one period later (1 s made it 2 s; a scan costs about 10 us)
DISCOVERY_PERIOD_S = 0.25
#: Keep-last depth of each recording subscription: a backlog this deep is held, not dropped.  DDS
#: does not tell a subscriber the depth a remote publisher keeps (rmw reports 0), so it is not
#: taken from the publishers: 1000 lost samples of a reliable topic whose delivery stalled for a
#: moment (a repair) at 5 000 samples/s; 20 000 is a paced replay's history (its qos.depth).
SUBSCRIPTION_DEPTH = 20_000
#: What the recorder counts in its progress (StreamProgress on /graph/progress): the run's
#: accounting, and the data time of the last sample written, on which a paced replay waits.
COUNTED = {TOPIC_IMU: "imu", TOPIC_MAG: "mag", TOPIC_TEMPERATURE: "temperature", TOPIC_REFERENCE: "reference",
           TOPIC_DEPTH: "depth", TOPIC_STATION: "stations", TOPIC_COEFFICIENTS: "records"}
#: A chunk is closed (handed to the operating system) at least every this many samples, so that
#: what a killed recorder loses is still in the probe's history (qos.depth, 20 000 in a paced
#: replay) for the restarted one.
FLUSH_SAMPLES = 4000
#: The progress goes out at most this often (wall, s).
PROGRESS_PERIOD_S = 0.05
#: Exit status when the recording is incomplete: a write the disk refused (messages not recorded,
#: a part left unfinalized) or no bag at all for want of space.  The launcher reads it as a
#: problem of the run, not as a node to restart.
RECORDING_INCOMPLETE = 4
#: Free bytes the output's file system must have before a recorder stopped by a refused write
#: tries a new part (a chunk is at most about 1 MiB): less would fill again within a chunk
RETRY_MIN_FREE_BYTES = 1 << 20
#: Errors that mean "no space" when the output is created: the node starts and waits for space
#: (any other error creating it, e.g. a read-only or forbidden path, refuses to start: exit 1)
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
#: Types whose CDR payload starts with a stamp (sec int32, nanosec uint32): the header stamp of
#: the last recorded message can be named without deserializing it
_STAMP_FIRST = ("std_msgs/Header", "builtin_interfaces/Time")


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
    history of :data:`SUBSCRIPTION_DEPTH` (or deeper, where a publisher says so): a recorder
    restarted mid-run takes all the history a transient-local publisher keeps for it."""
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


def _recorded_station_ids(output, station_type) -> Set[int]:
    """The station ids the run's earlier bag parts hold (``output`` a run part, ``survey_<k>.mcap``:
    the parts before it in its directory; anything else: none).  A killed recorder's part is read
    as far as it is readable."""
    out: Set[int] = set()
    path = os.path.abspath(str(output))
    own = re.match(r"^survey(?:_(\d+))?\.mcap$", os.path.basename(path))
    if own is None:
        return out
    k_own = int(own.group(1) or 0)
    for part in run_parts(os.path.dirname(path)):
        k = re.match(r"^survey(?:_(\d+))?\.mcap$", os.path.basename(part)).group(1)
        if int(k or 0) >= k_own:
            break
        try:
            for m in open_bag(part).messages([TOPIC_STATION], strict=False):
                try:
                    out.add(int(deserialize_message(bytes(m.data), station_type).station_id))
                except Exception:  # noqa: BLE001 — not a station of this type
                    continue
        except (BagError, OSError):
            continue
    return out


def _make_callback(write, channel_id: int, now=time.time_ns):
    # two positional parameters: rclpy then passes the message info (source timestamp)
    def callback(data, info):
        write(channel_id, data, now(), info["source_timestamp"])
    return callback


def _topic_name(name: str) -> str:
    name = name.strip()
    return name if name.startswith("/") else "/" + name


def _utc(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-4] + " UTC"


def _stamp_s(data: bytes) -> Optional[float]:
    """The stamp at the start of a CDR payload (after the 4-byte encapsulation), seconds."""
    if len(data) < 12:
        return None
    sec, nsec = struct.unpack_from("<iI" if data[1] & 1 else ">iI", data, 4)
    return sec + 1e-9 * nsec


def next_part_path(path: Path) -> Path:
    """The first ``<base>_<k>`` beside ``path`` that does not exist: ``survey.mcap`` ->
    ``survey_1.mcap``, ``survey_1.mcap`` -> ``survey_2.mcap`` (the launcher's part naming)."""
    suffix = path.suffix if path.suffix == ".mcap" else ""
    stem = path.name[:-len(suffix)] if suffix else path.name
    m = re.match(r"^(.*)_(\d+)$", stem)
    base, k = (m.group(1), int(m.group(2)) + 1) if m else (stem, 1)
    while (path.parent / f"{base}_{k}{suffix}").exists():
        k += 1
    return path.parent / f"{base}_{k}{suffix}"


class Recorder(Node):
    """Records the chosen topics to one bag (further parts after a full disk: the module
    docstring); :meth:`close` finalizes it."""

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
        self.declare_parameter("retry_s", 5.0, ParameterDescriptor(
            description="After a write the disk refused (full disk): how often, seconds (> 0), the "
                        "node looks for space again to go on recording into a new part.",
            type=ParameterType.PARAMETER_DOUBLE, **ro))

        gp = self.get_parameter
        self.source_node = str(gp("source.node").value)
        output = gp("output").value or default_output()
        self.only: Set[str] = {_topic_name(t) for t in (gp("topics").value or []) if t.strip()}
        self.exclude: Set[str] = {_topic_name(t) for t in (gp("exclude").value or []) if t.strip()}
        period = float(gp("discovery_period_s").value)
        max_chunk_s = float(gp("max_chunk_s").value)
        self.retry_s = float(gp("retry_s").value)
        if period <= 0 or max_chunk_s <= 0 or self.retry_s <= 0:
            raise ValueError("discovery_period_s, max_chunk_s and retry_s must be > 0")
        # the tick timer closes a chunk at most tick_s after its deadline: split the budget so
        # the oldest unflushed message is never older than max_chunk_s
        tick_s = min(0.1, max_chunk_s / 10.0)
        self._bag_args = dict(compression=str(gp("compression").value), max_chunk_s=max_chunk_s - tick_s)
        self.output = str(Path(output))
        # recording state: the part being written (None after a refused write), every part
        # written, each topic's channel in the current part, and the messages received per topic
        # (received - what the parts hold = not recorded)
        self.bag: Optional[BagWriter] = None
        self.parts: List[BagWriter] = []
        self._channels: Dict[str, int] = {}
        self._received: Dict[str, int] = {}
        self._specs: Dict[str, Tuple[str, list]] = {}   # topic -> (type, offered QoS): for a new part
        self._stamped: Set[str] = set()
        self.error: Optional[OSError] = None      # the first refused write
        self._stopped_at: Optional[float] = None  # wall time recording stopped (None: recording)
        self._next_try = 0.0
        self._subs: Dict[str, object] = {}
        #: called with each new recording subscription (main(): the executor's ``add_hot``)
        self.on_subscribed = None
        self._skipped: Dict[str, str] = {}
        self._closed = False
        # the run's accounting and the replay's pacing (StreamProgress on /graph/progress)
        self._t_imu = -math.inf          # stamp of the last /probe/imu taken
        self._unflushed = 0
        self._source = None              # the source's last StreamProgress
        self._reported = None
        self._progress_type = None
        try:
            from inclinometer_calib.msg import StreamProgress, SurveyStation
        except ImportError:              # messages not built: a plain recorder, no progress
            StreamProgress = SurveyStation = None
        # the stations the run's recording holds, by id, all parts: a recorder restarted into a new
        # part counts what its predecessor recorded too (the paced probe's end waits until the
        # recording has every station published; counting this part alone it waited in vain)
        self._station_type = SurveyStation
        self._station_ids: Set[int] = _recorded_station_ids(self.output, SurveyStation) if SurveyStation else set()
        if StreamProgress is not None:
            def latched(depth):
                return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self._progress_type = StreamProgress
            self.pub_progress = self.create_publisher(StreamProgress, TOPIC_PROGRESS, latched(1))
            self.create_subscription(StreamProgress, TOPIC_PROGRESS, self._on_progress, latched(100))
        try:
            self._start_part(Path(self.output))
        except OSError as exc:
            if isinstance(exc, FileExistsError) or exc.errno not in NO_SPACE:
                raise
            self._stopped(exc, f"cannot create {self.output}", "nothing recorded yet")
        else:
            self.get_logger().info(
                f"recording to {self.output} (topics: {sorted(self.only) or 'all'}, "
                f"excluding {sorted(self.exclude)}, chunks <= {max_chunk_s:g} s, "
                f"compression {self._bag_args['compression'] or 'none'})")
        self._discover()
        # steady clock: discovery and chunk closing go on whatever the ROS clock does (a node
        # started with use_sim_time would otherwise stall when /clock stops)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._discover, clock=steady)
        self.create_timer(tick_s, self._tick, clock=steady)
        if self._progress_type is not None:
            self.create_timer(PROGRESS_PERIOD_S, self._publish_progress, clock=steady)

    # -- writing and a disk that refuses it ----------------------------------------------------
    def _start_part(self, path: Path) -> None:
        """Open a part and register every topic seen so far on it (raises its ``OSError``)."""
        bag = BagWriter(path, **self._bag_args)
        channels = {}
        for topic, (type_name, qos) in self._specs.items():
            try:
                channels[topic] = bag.add_topic(topic, type_name, qos_profiles=qos)
            except OSError:
                bag.mcap_path.unlink(missing_ok=True)   # ours, holding no message: no empty part left
                raise
        self.bag, self._channels = bag, channels
        self.parts.append(bag)

    def _write(self, topic: str, data: bytes, log_time: int, publish_time: int) -> None:
        """The subscriptions' callback (hot path): count the message, write it to the current
        part if there is one."""
        self._received[topic] += 1
        cid = self._channels.get(topic)
        if topic == TOPIC_IMU:
            self._t_imu = _stamp_s(data) or self._t_imu
        elif topic == TOPIC_STATION and self._station_type is not None:
            try:
                self._station_ids.add(int(deserialize_message(data, self._station_type).station_id))
            except Exception:  # noqa: BLE001 — a station of another type: counted as a message, not by id
                pass
        if cid is None:
            return   # not recording: counted as not recorded
        try:
            self.bag.write(cid, data, log_time, publish_time)
            if topic == TOPIC_IMU:
                self._unflushed += 1
                if self._unflushed >= FLUSH_SAMPLES:
                    self._unflushed = 0
                    self.bag.flush()
        except OSError as exc:
            self._stopped(exc, f"cannot write {self.bag.path}", None)

    # -- accounting and pacing --------------------------------------------------------------
    def _on_progress(self, msg) -> None:
        if msg.node == self.source_node:
            self._source = msg

    def _publish_progress(self) -> None:
        """This recorder's StreamProgress: the messages it took per topic, the stamp of the last
        sample (a paced replay waits on it; a full disk does not stop the survey: what it could
        not record is said and counted apart), and the end once it holds every sample sent."""
        if self._closed:
            return
        got, src = self._received, self._source
        counts = {k: got.get(t, 0) for t, k in COUNTED.items()}
        if self._station_type is not None:
            counts["stations"] = len(self._station_ids)   # by id, over all the run's parts
        end = bool(src is not None and src.end and counts["imu"] >= src.imu and counts["mag"] >= src.mag)
        key = (tuple(counts.values()), self._t_imu, end)
        if key == self._reported:
            return
        self._reported = key
        m = self._progress_type(node=self.get_name(), settled=math.nan, end=end)
        if math.isfinite(self._t_imu):
            sec = math.floor(self._t_imu)
            m.header.stamp.sec, m.header.stamp.nanosec = int(sec), min(int(round((self._t_imu - sec) * 1e9)), 999999999)
        for k, v in counts.items():
            setattr(m, k, v)
        self.pub_progress.publish(m)

    def _tick(self) -> None:
        """Steady timer: close an old chunk; while stopped by a refused write, look for space."""
        if self._closed:
            return
        if self.bag is not None:
            try:
                self.bag.tick()
            except OSError as exc:
                self._stopped(exc, f"cannot write {self.bag.path}", None)
        elif time.monotonic() >= self._next_try:
            self._try_again()

    def _holds(self, bag: BagWriter) -> str:
        """What a part holds, in words: messages, and the receive time and header stamp of its last."""
        n = sum(bag.committed_counts().values())
        last = bag.last_committed()
        if not n or last is None:
            return f"{bag.path.name} holds no message"
        topic, data, log_ns = last
        stamp = _stamp_s(data) if topic in self._stamped else None
        return (f"{bag.path.name} holds {n} messages, the last one received at {_utc(log_ns * 1e-9)}"
                + (f" (header stamp {stamp:.3f} s, on {topic})" if stamp is not None else f" (on {topic})"))

    def _stopped(self, exc: OSError, what: str, holds: Optional[str]) -> None:
        """A write the disk refused: stop recording, say it once at ERROR, try again later."""
        bag, self.bag, self._channels = self.bag, None, {}
        self.error = self.error or exc
        self._stopped_at = time.time()
        self._next_try = time.monotonic() + self.retry_s
        if holds is None and bag is not None:
            holds = self._holds(bag) + ", its complete chunks readable (not finalized)"
        self.get_logger().error(
            f"{what}: {refused_write_words(exc)[1]}; not recording from {_utc(self._stopped_at)} on; {holds}. "
            f"Messages from now on are counted per topic, not recorded; looking for space every "
            f"{self.retry_s:g} s to go on in a new part")

    def _try_again(self) -> None:
        """While stopped: with room on the disk again, go on in a new part (said once at WARNING)."""
        self._next_try = time.monotonic() + self.retry_s
        path = Path(self.output)
        target = path if not self.parts and not path.exists() else next_part_path(path)
        try:
            st = os.statvfs(target.parent)
            if st.f_bavail * st.f_frsize < RETRY_MIN_FREE_BYTES:
                return
        except OSError:
            pass   # no statistics: let the write itself tell
        try:
            self._start_part(target)
        except OSError:
            return   # still no room (the writer left no file behind): try again later
        lost = sum(self._not_recorded().values())
        self.get_logger().warning(
            f"the disk takes writes again: recording goes on in {target} (a new part) after "
            f"{time.time() - self._stopped_at:.1f} s; {lost} messages were not recorded meanwhile")
        self._stopped_at = None

    def _recorded(self) -> Dict[str, int]:
        """Messages per topic in the parts (what a reader finds in them)."""
        counts: Dict[str, int] = {t: 0 for t in self._received}
        for bag in self.parts:
            for t, n in bag.committed_counts().items():
                counts[t] = counts.get(t, 0) + n
        return counts

    def _not_recorded(self) -> Dict[str, int]:
        rec = self._recorded()
        return {t: n - rec.get(t, 0) for t, n in self._received.items() if n > rec.get(t, 0)}

    @property
    def incomplete(self) -> bool:
        """True when the recording misses something: a refused write (or no part at all)."""
        return self.error is not None

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
            qos_dicts = [qos_to_dict(q) for q in offered]
            if self.bag is not None:
                try:
                    self._channels[topic] = self.bag.add_topic(topic, type_name, qos_profiles=qos_dicts)
                except (UnknownTypeError, ValueError) as exc:
                    self._skip(topic, str(exc))
                    continue
                except OSError as exc:   # a full chunk went to disk on the way
                    self._stopped(exc, f"cannot write {self.bag.path}", None)
            self._specs[topic] = (type_name, qos_dicts)
            self._received[topic] = 0
            fields = getattr(msg_type, "get_fields_and_field_types", dict)()
            if next(iter(fields.values()), "") in _STAMP_FIRST:
                self._stamped.add(topic)
            recorded_hash = (self.parts[-1].topics[topic].type_hash if self.parts and topic in self.parts[-1].topics
                             else type_hash(type_name))
            live = {h for h in hashes if h.startswith("RIHS01_")}
            if live and recorded_hash not in live:
                self.get_logger().warning(
                    f"{topic}: type hash of the installed {type_name} ({recorded_hash or 'none'}) "
                    f"differs from the publisher's {sorted(live)}: definitions differ")
            qos = subscription_qos(offered)
            self._subs[topic] = self.create_subscription(
                msg_type, topic, _make_callback(self._write, topic), qos, raw=True)
            if self.on_subscribed is not None:
                self.on_subscribed(self._subs[topic])
            self.get_logger().info(
                f"{'recording' if self.bag is not None else 'counting (not recording, see the error above)'} "
                f"{topic} [{type_name}] ({qos.reliability.name.lower()}, {qos.durability.name.lower()})")

        for topic in self.only:
            if topic not in self._subs and topic not in self._skipped and topic in self.exclude:
                self._skip(topic, "listed in both topics and exclude")

    def _skip(self, topic: str, reason: str) -> None:
        self._skipped[topic] = reason
        self.get_logger().warning(f"not recording {topic}: {reason}")

    # -- shutdown ----------------------------------------------------------------------------
    def close(self) -> Dict[str, int]:
        """Finalize the bag (idempotent); returns messages per recorded topic (all parts)."""
        if self._closed:
            return self._recorded()
        self._closed = True
        for sub in list(self._subs.values()):
            try:
                self.destroy_subscription(sub)
            except Exception:  # noqa: BLE001 - context may already be shut down
                pass
        if self.bag is not None:
            try:
                self.bag.close()
            except OSError as exc:
                self._stopped_words(exc)
        counts = self._recorded()
        lines = [f"  {t}: {n}" for t, n in sorted(counts.items())]
        missing = [t for t in sorted(self.only) if t not in self._specs and t not in self._skipped]
        if len(self.parts) == 1 and self.error is None:
            text = (f"bag {self.output} finalized: {sum(counts.values())} messages on "
                    f"{len(counts)} topic(s)\n" + "\n".join(lines))
        else:
            said = [f"{b.path} " + ("NOT finalized (a write was refused): " + self._holds(b) + ", its complete "
                                    "chunks readable (inclinometer_calib.io.bag.open_bag / recover)"
                                    if b.error is not None else
                                    f"finalized: {sum(b.committed_counts().values())} messages") for b in self.parts]
            text = (f"bag parts ({len(self.parts)}): " + ("; ".join(said) or f"none: {self.output} never created")
                    + f"\nrecorded in all: {sum(counts.values())} messages on {len(counts)} topic(s)\n"
                    + "\n".join(lines))
        if self._skipped:
            text += "\nnot recorded:\n" + "\n".join(
                f"  {t}: {r}" for t, r in sorted(self._skipped.items()))
        if missing:
            text += "\nrequested but never seen: " + ", ".join(missing)
        if self.error is not None:
            # the last line: what the recording misses, for the operator and the launcher
            lost = sorted(self._not_recorded().items(), key=lambda kv: (-kv[1], kv[0]))
            named = ", ".join(f"{n} messages on {t}" if i == 0 else f"{n} on {t}"
                              for i, (t, n) in enumerate(lost))
            unfinal = [b.path.name for b in self.parts if b.error is not None]
            reason = refused_write_words(self.error)[0]
            text += ("\nrecording incomplete: " + (f"{named} not recorded: {reason}" if named else
                                                   f"every message received was recorded ({reason})")
                     + (f"; not finalized: {', '.join(unfinal)}" if unfinal else "")
                     + ("" if self.parts else f"; no bag written, {self.output} could not be created"))
        print(f"[{NODE_NAME}] {text}", file=sys.stderr, flush=True)
        return counts

    def _stopped_words(self, exc: OSError) -> None:
        """A refused write while finalizing: said once at ERROR (rcutils logging outlives the
        context that a signal shut down)."""
        bag, self.bag, self._channels = self.bag, None, {}
        self.error = self.error or exc
        self.get_logger().error(
            f"cannot finalize {bag.path}: {refused_write_words(exc)[1]}; {self._holds(bag)}, its complete chunks "
            "readable (not finalized)")


def main(args: Optional[List[str]] = None) -> int:
    # rclpy 7 (Jazzy) init() returns None, not a context manager: shut down in finally
    install_stop_hook()
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
                # what the DDS readers hold was delivered: recorded, not lost at the stop (an
                # unpaced source's last samples and its end, which a busy machine had not served yet)
                try:
                    executor.take_waiting()
                except Exception as exc:  # noqa: BLE001 — the bag is finalized whatever this says
                    print(f"[{NODE_NAME}] the messages waiting at the stop were not all recorded: {exc}",
                          file=sys.stderr, flush=True)
        if node is not None:
            _finalize(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return RECORDING_INCOMPLETE if node is not None and node.incomplete else 0


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

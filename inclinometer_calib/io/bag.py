"""rosbag2-compatible MCAP files: message definitions, type hashes, writing, reading, recovery.

ROS-free on purpose: this module imports neither rclpy nor any generated message module, so
bags can be written from CDR bytes and read back on machines without ROS (tests, analysis).
The libraries do the format work: ``rosbags.typesys`` the message definitions and RIHS01 type
hashes (:class:`MessageDefinitions`: its ROS 2 Jazzy type store, plus our ``msg/*.msg`` and any
other interface package's ``.msg`` files registered on demand), ``mcap`` the writing
(``mcap.writer.Writer``) and the parsing of every record, decompression and CRC checks included
(``mcap.records``, ``mcap.stream_reader.get_chunk_data_stream``, the seeking reader for the
summary). What is ours is what they lack: crash safety when writing (below), and reading a
damaged or unfinalized file up to the damage and past a bad chunk, naming the file and byte
offset (:class:`BagReader`). All of them, and PyYAML, come with the extra ``bag``
(``pip install 'inclinometer_calib[bag]'``); without them the functions that need them raise
:class:`deps.MissingDependency`, which says so in one line.

What makes the file a rosbag2 bag (what ``ros2 bag record`` with the mcap storage writes, and
what ``rosbags`` and ``mcap_ros2`` need to decode it):

* header profile ``ros2``;
* one schema per type, name ``pkg/msg/Type``, encoding ``ros2msg``, data = the complete message
  definition (:func:`message_definition`);
* one channel per topic, ``message_encoding`` ``cdr``, metadata ``offered_qos_profiles`` (YAML,
  :func:`qos_profiles_yaml`) and ``topic_type_hash`` (``RIHS01_...``, :func:`type_hash`);
* messages with ``log_time`` = receive time and ``publish_time`` = send time (ns since epoch),
  data = the CDR bytes as on the wire;
* a metadata record ``rosbag2`` with ``serialized_metadata`` (the ``metadata.yaml`` content),
  then the summary with statistics and chunk indexes, written by :meth:`BagWriter.close`.

The QoS YAML and ``metadata.yaml`` mappings are built here (:func:`qos_profiles_yaml`,
:meth:`BagWriter.rosbag2_metadata`) and dumped by PyYAML: ``rosbags`` writes them only from its own
``rosbag2.Writer.close`` (its storage, without the crash safety below; its ``dump_qos_v9`` is not
public API), and ``mcap`` knows nothing of rosbag2.

Crash safety (:class:`BagWriter`)
--------------------------------
The bag is written **directly to its final path**, never to a temporary name that is renamed at
the end: after a crash (SIGKILL, power cut) the file is where the user expects it, and every
chunk that was completely written is readable (:func:`open_bag` reads it sequentially and
reports where it stops; :func:`recover` rewrites the readable prefix into a finalized bag).
Chunks are closed when they exceed ``chunk_size`` bytes *or* span ``max_chunk_s`` seconds of
log time (checked on every write and, for idle topics, by :meth:`BagWriter.tick`), and every
finished chunk goes to the operating system at once (no user-space buffer), so a crash of the
process loses at most the open chunk, i.e. at most ``max_chunk_s`` of data. ``fsync=True``
extends that to power loss, at the cost of one fsync per chunk.

An existing file (or bag directory) is **never** overwritten or appended to: the file is created
with ``O_EXCL`` and :class:`BagWriter` raises :class:`FileExistsError` if the path exists, so a
good earlier recording can never be replaced by a half-written one. Choose a new name (the
recorder's default name carries a UTC timestamp).

A write the operating system refuses (``OSError``: a full disk ``ENOSPC``, a quota ``EDQUOT``,
``EFBIG``, ``EIO``) ends the file: the writer raises the error, keeps it in
:attr:`BagWriter.error`, cuts the file back to the end of the last record written whole (a chunk
the disk took only part of is removed, which also gives its space back) and writes nothing more to
it, not even at :meth:`BagWriter.close`: appending after a torn record, or a summary that points
at data that is not there, would make the file unreadable past the tear. What is left is an
unfinalized bag of complete chunks, read by :func:`open_bag` and :func:`recover` like the file of
a killed recorder; :meth:`BagWriter.committed_counts` says how many messages per topic it holds. A
bag whose header cannot be written is not left behind as an empty file: it is removed and the
error raised.

Reading damaged files (:class:`BagReader`)
-----------------------------------------
mcap's readers stop at the first damage and do not say where. ``make_reader`` looks for the
footer a crash never wrote and reads nothing of an unfinalized file; the sequential
``StreamReader`` parses each record body straight from the stream, so a truncated last chunk (a
killed recorder) ends it with a bare ``EndOfFile``, and a damaged field inside a chunk (a string
length) desynchronizes it for the rest of the file. So :class:`BagReader` walks the records by
opcode and length alone (:func:`_frames`, the one hand-written piece of the format), hands each
body, cut to its declared length, to the library's record parser, skips a chunk that fails
parsing, decompression or its CRC, and records every problem as a :class:`BagError` with the
byte offset of the record. Inside a decompressed chunk, message records are unpacked with one
``struct`` call each: ``mcap.records.Message.read`` makes reading about 2.6 times slower
(``benchmarks/bench_reprocess.py``, which times the library's ``StreamReader`` beside ours).

Layouts: a path ending in ``.mcap`` is a bare MCAP file; any other path is a ``ros2 bag record``
style directory ``<dir>/<dir-name>_0.mcap`` plus ``<dir>/metadata.yaml`` (written at close, or by
:func:`recover`), which ``rosbags`` needs to open a directory and uses to check type hashes.
"""
from __future__ import annotations

import functools
import io
import itertools
import mmap
import os
import re
import struct
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, Iterator, List, Mapping, NamedTuple, Optional, Sequence, Union

from ..core import yamltext

from ..core.deps import MissingDependency, require
from ..core.output import final_name

__all__ = [
    "BagError", "UnknownTypeError", "MessageDefinitions", "message_definition", "type_hash",
    "normalize_type", "qos_profiles_yaml", "parse_qos_profiles", "DEFAULT_QOS_PROFILE",
    "BagWriter", "BagReader", "BagMessage", "TopicInfo", "RecoveryReport", "open_bag", "recover",
    "available_compressions", "BagDecoder", "read_messages", "DECODE_ERRORS", "MessageEncoder", "message_encoder",
]

PathLike = Union[str, "os.PathLike[str]"]

_REPO_MSG_DIR = Path(__file__).resolve().parents[2] / "msg"
_OWN_PACKAGE = "inclinometer_calib"
_ROSBAG2_VERSION = 9  # metadata.yaml / serialized_metadata version of Jazzy's rosbag2


#: A run's recording: the first part; a recorder restarted mid-run writes survey_1.mcap, survey_2.mcap, …
RUN_BAG = "survey.mcap"
_PART_RE = re.compile(r"^survey(?:_(\d+))?\.mcap$")


def run_parts(out) -> List[str]:
    """The recorder's bag parts in the run directory ``out`` in the order they were written (= time
    order): ``survey.mcap``, ``survey_1.mcap``, ``survey_2.mcap`` … (not ``*.recovered.mcap`` copies)."""
    found = []
    for name in os.listdir(out) if os.path.isdir(out) else ():
        m = _PART_RE.match(name)
        if m:
            found.append((int(m.group(1) or 0), os.path.join(out, name)))
    return [p for _, p in sorted(found)]


def next_run_part(out) -> str:
    """The first ``survey_<k>.mcap`` (k = 1, 2, …) that does not exist in ``out``."""
    k = 1
    while os.path.exists(os.path.join(out, f"survey_{k}.mcap")):
        k += 1
    return os.path.join(out, f"survey_{k}.mcap")


class BagError(Exception):
    """A bag file is damaged or not a bag. ``path`` and byte ``offset`` say where."""

    def __init__(self, path: PathLike, offset: int, reason: str, *, more: int = 0):
        self.path = str(path)
        self.offset = int(offset)
        self.reason = reason
        self.more = more
        text = f"{self.path}: {reason} (at byte offset {self.offset})"
        if more:
            text += f"; {more} further problem(s) after it"
        super().__init__(text)


class UnknownTypeError(LookupError):
    """No usable ``.msg`` definition found for a message type."""


# ---------------------------------------------------------------------------------------------
# message definitions and type hashes (rosbags' type store)


def normalize_type(type_name: str) -> str:
    """``pkg/Type`` or ``pkg/msg/Type`` -> ``pkg/msg/Type`` (raises ValueError otherwise)."""
    parts = type_name.strip().split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and all(parts):
        return type_name.strip()
    raise ValueError(f"not a ROS message type name: {type_name!r} (expected pkg/msg/Type)")


_STRING_CONSTANT = re.compile(r"^(string(?:<=\d+)?\s+\w+)=(.*)$", re.M)  # fields have no "="


class MessageDefinitions:
    """Message definitions and type hashes from a ``rosbags`` type store.

    The store is rosbags' ROS 2 Jazzy store (:attr:`typestore`); a type it does not hold (ours,
    or any other interface package) is registered from its ``.msg`` file, with the types that
    file references. ``.msg`` files are searched as ``share/<pkg>/msg/<Type>.msg`` under every
    prefix of ``AMENT_PREFIX_PATH`` (or ``prefixes``), then ``sys.prefix`` (the venv, which holds
    the ROS message wheels), then this repository's ``msg/`` directory for our own package.
    """

    def __init__(self, prefixes: Optional[Sequence[PathLike]] = None,
                 extra_msg_dirs: Optional[Mapping[str, PathLike]] = None):
        if prefixes is None:
            prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
        roots = [Path(p) for p in prefixes]
        if Path(sys.prefix) not in roots:
            roots.append(Path(sys.prefix))
        self.prefixes = roots
        self.extra_msg_dirs: Dict[str, Path] = {_OWN_PACKAGE: _REPO_MSG_DIR}
        for pkg, d in (extra_msg_dirs or {}).items():
            self.extra_msg_dirs[pkg] = Path(d)
        self._store = None
        self.hash_errors: Dict[str, str] = {}  # type -> why type_hash() gave ""

    @property
    def typestore(self):
        """The ``rosbags`` type store (ROS 2 Jazzy plus the types registered so far)."""
        if self._store is None:
            typesys = require("rosbags.typesys", "bag", "message definitions for a bag")
            self._store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
        return self._store

    def find(self, type_name: str) -> Optional[Path]:
        """The ``.msg`` file of a type, or None."""
        pkg, sub, name = normalize_type(type_name).split("/")
        for prefix in self.prefixes:
            p = prefix / "share" / pkg / sub / f"{name}.msg"
            if p.is_file():
                return p
        extra = self.extra_msg_dirs.get(pkg)
        if extra is not None and sub == "msg":
            p = extra / f"{name}.msg"
            if p.is_file():
                return p
        return None

    def text(self, type_name: str) -> str:
        """The verbatim ``.msg`` text of one type (no nested types)."""
        full = normalize_type(type_name)
        path = self.find(full)
        if path is None:
            raise UnknownTypeError(
                f"no .msg file for {full}: looked for share/{full.split('/')[0]}/msg/"
                f"{full.split('/')[2]}.msg under {[str(p) for p in self.prefixes]}")
        return path.read_text(encoding="utf-8")

    def register(self, type_name: str) -> str:
        """Make sure the type store holds ``type_name`` and every type it references (registered
        from ``.msg`` files where missing); returns the normalized name."""
        from rosbags.typesys import TypesysError, get_types_from_msg
        from rosbags.typesys.base import Nodetype

        full = normalize_type(type_name)
        store = self.typestore
        pending = [full]
        while pending:
            name = pending.pop()
            if name in store.fielddefs:
                continue
            try:
                types = get_types_from_msg(self.text(name), name)
                store.register(types)
            except (UnknownTypeError, TypesysError) as exc:
                needed = "" if name == full else f" (referenced by {full})"
                raise UnknownTypeError(f"{exc}{needed}") from None
            for _field, (kind, rest) in types[name][1]:
                if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                    kind, rest = rest[0]
                if kind == Nodetype.NAME:
                    pending.append(rest)
        return full

    def definition(self, type_name: str) -> str:
        """The complete ``ros2msg`` definition as rosbag2 stores it in a schema: the type's fields,
        then each nested type once after a line of 80 ``=`` and ``MSG: pkg/Type``
        (``generate_msgdef`` of the type store).

        String constants are quoted again: ``generate_msgdef`` writes them bare, and a bare
        ``true`` or ``1`` then reads back as a bool or a number (rosbags 0.11)."""
        full = self.register(type_name)
        text = self.typestore.generate_msgdef(full, ros_version=2)[0]
        return _STRING_CONSTANT.sub(
            lambda m: f'{m[1]}="{m[2]}"' if '"' not in m[2] else m[0], text)

    def type_hash(self, type_name: str) -> str:
        """The REP-2011 type hash ``RIHS01_<sha256 hex>`` (``hash_rihs01`` of the type store), or
        ``""`` if the type is unknown or rosbags cannot hash it (``hash_errors[type]`` says why).

        Equal to the hash rosidl installs in ``share/<pkg>/msg/<Type>.json`` (and rclpy reports)
        for every type this package records; rosbags 0.11 differs for types with ``char``
        fields (it hashes ``char`` as char, rosidl as uint8).
        """
        full = normalize_type(type_name)
        try:
            return self.typestore.hash_rihs01(self.register(full))
        except (UnknownTypeError, KeyError, ValueError) as exc:
            self.hash_errors[full] = f"{type(exc).__name__}: {exc}"
            return ""


_default_definitions: Optional[MessageDefinitions] = None


def _defaults() -> MessageDefinitions:
    global _default_definitions
    if _default_definitions is None:
        _default_definitions = MessageDefinitions()
    return _default_definitions


def message_definition(type_name: str) -> str:
    """Complete ``ros2msg`` definition of ``pkg/msg/Type`` (see :class:`MessageDefinitions`)."""
    return _defaults().definition(type_name)


def type_hash(type_name: str) -> str:
    """``RIHS01_...`` hash of ``pkg/msg/Type`` or ``""`` (see :meth:`MessageDefinitions.type_hash`)."""
    return _defaults().type_hash(type_name)


# ---------------------------------------------------------------------------------------------
# QoS profiles in rosbag2's YAML

_INF_NS = 2**63 - 1
DEFAULT_QOS_PROFILE = {
    "history": "keep_last", "depth": 10, "reliability": "reliable", "durability": "volatile",
    "deadline_ns": _INF_NS, "lifespan_ns": _INF_NS, "liveliness": "automatic",
    "liveliness_lease_duration_ns": _INF_NS, "avoid_ros_namespace_conventions": False,
}


def _sec_nsec(ns: int) -> dict:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def qos_profiles_yaml(profiles: Iterable[Mapping]) -> str:
    """rosbag2 (Jazzy, metadata version 9) ``offered_qos_profiles`` YAML for a list of profiles.

    Each profile is a mapping with the keys of :data:`DEFAULT_QOS_PROFILE` (missing keys take
    those defaults): enum policies as lower-case rmw names (``keep_last``, ``best_effort``,
    ``transient_local``, ``automatic``...), durations as integer nanoseconds. An empty list gives
    ``""`` as rosbag2 does.  The mapping is rosbag2's (the one ``rosbags`` writes, whose
    ``dump_qos_v9`` is not public API), dumped by PyYAML.
    """
    items = []
    for prof in profiles:
        p = dict(DEFAULT_QOS_PROFILE)
        p.update(prof)
        items.append({
            "history": p["history"], "depth": int(p["depth"]), "reliability": p["reliability"],
            "durability": p["durability"], "deadline": _sec_nsec(p["deadline_ns"]),
            "lifespan": _sec_nsec(p["lifespan_ns"]), "liveliness": p["liveliness"],
            "liveliness_lease_duration": _sec_nsec(p["liveliness_lease_duration_ns"]),
            "avoid_ros_namespace_conventions": bool(p["avoid_ros_namespace_conventions"])})
    return yamltext.dump(items, sort_keys=False).strip() if items else ""


_QOS_ENUMS = {
    "history": {0: "system_default", 1: "keep_last", 2: "keep_all", 3: "unknown"},
    "reliability": {0: "system_default", 1: "reliable", 2: "best_effort", 3: "unknown",
                    4: "best_available"},
    "durability": {0: "system_default", 1: "transient_local", 2: "volatile", 3: "unknown",
                   4: "best_available"},
    "liveliness": {0: "system_default", 1: "automatic", 3: "manual_by_topic", 4: "unknown",
                   5: "best_available"},
}


def parse_qos_profiles(text) -> List[dict]:
    """Inverse of :func:`qos_profiles_yaml`; also reads rosbag2's older integer-enum form and
    an already-parsed list. Returns mappings shaped like :data:`DEFAULT_QOS_PROFILE`."""
    if not text:
        return []
    items = yamltext.load(text) if isinstance(text, str) else text
    out = []
    for item in items or []:
        p = dict(DEFAULT_QOS_PROFILE)
        for key, names in _QOS_ENUMS.items():
            if key in item:
                v = item[key]
                p[key] = names.get(v, "unknown") if isinstance(v, int) else str(v).lower()
        if "depth" in item:
            p["depth"] = int(item["depth"])
        for key in ("deadline", "lifespan", "liveliness_lease_duration"):
            if isinstance(item.get(key), Mapping):
                p[key + "_ns"] = (int(item[key].get("sec", 0)) * 1_000_000_000
                                  + int(item[key].get("nsec", 0)))
        if "avoid_ros_namespace_conventions" in item:
            p["avoid_ros_namespace_conventions"] = bool(item["avoid_ros_namespace_conventions"])
        out.append(p)
    return out


# ---------------------------------------------------------------------------------------------
# writing


def available_compressions() -> List[str]:
    """Chunk compressions the installed ``mcap`` writer can use (``""`` = none)."""
    out = [""]
    try:
        import zstandard  # noqa: F401
        out.append("zstd")
    except ImportError:
        pass
    try:
        import lz4.frame  # noqa: F401
        out.append("lz4")
    except ImportError:
        pass
    return out


class _UnbufferedSink:
    """File object handed to ``mcap.writer.Writer``: every write goes straight to the OS.

    (The mcap writer wraps raw files in a BufferedWriter and only flushes them at the end; a
    crash would then also lose whatever sits in that buffer. It writes whole records at chunk
    boundaries, so unbuffered writes cost nothing per message.)
    """

    def __init__(self, fileobj, fsync: bool):
        self._f = fileobj
        self._fsync = fsync
        self._pos = 0   # bytes written whole: the end of the last record the OS took completely
        #: called after every write the OS took completely (the writer's commit point)
        self.on_written = None
        self._refused: Optional[OSError] = None

    def write(self, data) -> int:
        if self._refused is not None:
            raise OSError(self._refused.errno, self._refused.strerror)
        view = memoryview(data)
        total = len(view)
        done = 0
        while done < total:
            done += self._f.write(view[done:])
        self._pos += total
        if total and self.on_written is not None:   # (the mcap writer also writes b"")
            self.on_written()
        return total

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        if self._refused is None and self._fsync:
            os.fsync(self._f.fileno())

    def abandon(self, error: OSError) -> None:
        """After a failed write: cut the file back to the last whole write (a torn record would
        hide nothing from a reader but leave garbage; removing it frees its space), close it, and
        refuse every later write with ``error``'s errno."""
        self._refused = OSError(error.errno, f"{error.strerror}; nothing more is written to this file "
                                             "after an earlier failed write")
        try:
            os.ftruncate(self._f.fileno(), self._pos)
        except (OSError, ValueError):
            pass   # the file keeps its torn tail: the reader stops there all the same
        try:
            self._f.close()
        except OSError:
            pass   # the failed write has said it already

    def close(self) -> None:
        self._f.close()


def _library_string() -> str:
    try:
        from importlib.metadata import version
        mv = version("mcap")
    except Exception:  # noqa: BLE001
        mv = "?"
    try:
        from .. import __version__ as own
    except Exception:  # noqa: BLE001
        own = "?"
    return f"inclinometer_calib-{own} (mcap-python-{mv})"


def _split_layout(path: Path):
    """(bag directory or None, mcap file path) for a writer/recover destination."""
    if path.suffix == ".mcap":
        return None, path
    return path, path / f"{path.name}_0.mcap"


@dataclass
class _TopicRecord:
    channel_id: int
    topic: str
    type: str
    qos_yaml: str
    type_hash: str


#: A message record's header in MCAP: opcode 0x05, record length, channel id, sequence, log and
#: publish time (https://mcap.dev/spec#message-op0x05)
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
#: A message index record's header: opcode 0x07, record length, channel id, records' byte length
#: (https://mcap.dev/spec#message-index-op0x07)
_INDEX_HEAD = struct.Struct("<BQHI")


@functools.lru_cache(maxsize=1)
def _packed_index_class():
    """mcap's ``MessageIndex`` whose ``write`` packs its (log time, offset) pairs in one
    ``struct.pack`` and writes the record at once: the library writes each number with a call of
    its own (two ``write8`` per message: 2 µs a message, a quarter of a bag's writing); the same
    bytes (test/io/test_bag.py compares the files)."""
    from mcap.records import MessageIndex

    class PackedMessageIndex(MessageIndex):
        def write(self, stream):
            recs = self.records
            n = 16 * len(recs)
            stream.write(_INDEX_HEAD.pack(0x07, 6 + n, self.channel_id, n))
            stream.write(struct.pack(f"<{2 * len(recs)}Q", *itertools.chain.from_iterable(recs)))
    return PackedMessageIndex


def _fast_message_add(writer, chunk_size: int):
    """``writer.add_message(channel_id, log_time, data, publish_time)`` of mcap 1.6's chunked
    :class:`mcap.writer.Writer`, the same bytes in less than half the time (:meth:`BagWriter.write`
    5.1 → 2.3 µs a message, docs/benchmarks.md section 2: the writer builds a ``Message`` dataclass
    and writes its five fields one ``struct.pack`` and ``BytesIO.write`` at a time; here one pack,
    one write; its message indexes :func:`_packed_index_class`'s).  It keeps the writer's own state as
    ``add_message`` does: the file's statistics, the open chunk's time range, message index and
    records, and closes the chunk past ``chunk_size`` with the writer's own method.  None when the
    writer is not the one this was written against (another mcap version, no chunking): then the
    library's ``add_message`` is used.  test/io/test_bag.py compares the files byte for byte."""
    try:
        MessageIndex = _packed_index_class()

        stats = writer._Writer__statistics
        builder = writer._Writer__chunk_builder
        finalize = writer._Writer__finalize_chunk
        counts = stats.channel_message_counts
        indices = builder.message_indices
        records = builder.record_writer
        records._buffer.tell
    except (AttributeError, ImportError):
        return None
    pack = _MESSAGE_HEAD.pack

    def add(channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        if stats.message_count == 0 or log_time < stats.message_start_time:
            stats.message_start_time = log_time
        if log_time > stats.message_end_time:
            stats.message_end_time = log_time
        counts[channel_id] += 1
        stats.message_count += 1
        if builder.num_messages == 0 or log_time < builder.message_start_time:
            builder.message_start_time = log_time
        if log_time > builder.message_end_time:
            builder.message_end_time = log_time
        index = indices.get(channel_id)
        if index is None:
            index = indices[channel_id] = MessageIndex(channel_id=channel_id, records=[])
        buf = records._buffer            # a new one after each chunk (RecordBuilder.end)
        offset = buf.tell()
        index.records.append((log_time, offset))
        builder.num_messages += 1
        buf.write(pack(5, 22 + len(data), channel_id, 0, log_time, publish_time))
        buf.write(data)
        if buf.tell() > chunk_size:
            finalize()
    return add


class BagWriter:
    """Write a rosbag2-compatible MCAP (see the module docstring for the file-safety rules).

    ``path``: ``*.mcap`` for a bare file, otherwise a bag directory (``ros2 bag record`` layout).
    ``compression``: ``"zstd"`` (default), ``"lz4"`` or ``""``/``"none"``.
    ``chunk_size``: bytes of (uncompressed) records per chunk before it is closed.
    ``max_chunk_s``: a chunk is closed once it spans this much log time (and by :meth:`tick`).
    ``fsync``: fsync after each chunk (survives power loss, not only process crashes).

    Hot path: :meth:`write` (``channel_id, data, log_time, publish_time``) does one comparison
    and hands the bytes to the mcap writer's open chunk (:func:`_fast_message_add`).

    A write the OS refuses raises its ``OSError`` (from :meth:`write`, :meth:`tick`,
    :meth:`flush`, :meth:`add_topic` or :meth:`close`) and ends the file (module docstring):
    :attr:`error` keeps it, the writer is closed, :meth:`committed_counts` are the messages the
    file holds.  A header that cannot be written raises from the constructor, the file removed.
    """

    def __init__(self, path: PathLike, *, compression: str = "zstd", chunk_size: int = 1 << 20,
                 max_chunk_s: float = 1.0, fsync: bool = False, library: Optional[str] = None,
                 definitions: Optional[MessageDefinitions] = None):
        require("mcap.writer", "bag", "writing a bag")
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.bag_dir, self.mcap_path = _split_layout(self.path)
        comp = (compression or "").lower()
        ctype = {"": CompressionType.NONE, "none": CompressionType.NONE,
                 "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}.get(comp)
        if ctype is None:
            raise ValueError(f"unknown compression {compression!r} (zstd, lz4 or none)")
        if comp not in ("", "none") and comp not in available_compressions():
            raise ValueError(f"compression {comp!r} is not available in this environment")
        self.compression = "" if comp == "none" else comp
        if max_chunk_s <= 0:
            raise ValueError("max_chunk_s must be > 0")
        self.max_chunk_ns = int(max_chunk_s * 1e9)
        self.definitions = definitions or _defaults()
        if self.path.exists():
            raise FileExistsError(
                f"{self.path} already exists; refusing to overwrite a recording "
                "(choose another output name)")
        if self.bag_dir is not None:
            self.bag_dir.mkdir(parents=True, exist_ok=False)
        else:
            self.mcap_path.parent.mkdir(parents=True, exist_ok=True)
        raw = None
        try:
            raw = open(self.mcap_path, "xb", buffering=0)  # O_EXCL: never replace an existing file
            self._sink = _UnbufferedSink(raw, fsync)
            self._mcap = Writer(self._sink, chunk_size=chunk_size, compression=ctype)
            self._mcap.start(profile="ros2", library=library or _library_string())
        except OSError:
            # no room for the header (a full disk): leave no empty or torn file behind, it holds
            # nothing and a reader refuses it; the caller may try again later under the same name
            if raw is not None:
                raw.close()
                self.mcap_path.unlink(missing_ok=True)
            if self.bag_dir is not None:
                try:
                    self.bag_dir.rmdir()
                except OSError:
                    pass   # not empty: not only ours
            raise
        self.error: Optional[OSError] = None
        self._add = _fast_message_add(self._mcap, chunk_size) or self._mcap.add_message
        # messages per channel and the log-time range, counted here: mcap's writer keeps its own
        # statistics private (Writer.__statistics, no public accessor in mcap 1.6); 0.1 µs a message
        self._counts: Dict[int, int] = {}
        self._t_range = [_INF_NS, 0]
        self._deadline = 0  # log time at which the open chunk must be closed (0: not armed)
        self._schemas: Dict[str, int] = {}
        self.topics: Dict[str, _TopicRecord] = {}
        self.closed = False
        self.chunks_flushed = 0
        # what the file holds: messages per channel, end log time and the last message (channel,
        # CDR bytes) as of the last write the OS took whole (the sink's commit point)
        self._last_cid, self._last_data = 0, b""
        self._committed = ({}, 0, None)
        self._sink.on_written = self._commit

    # -- registration --------------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str, *, qos_profiles: Iterable[Mapping] = (),
                  qos_yaml: Optional[str] = None, type_hash: Optional[str] = None,
                  definition: Optional[str] = None, schema_encoding: str = "ros2msg",
                  extra_metadata: Optional[Mapping[str, str]] = None) -> int:
        """Register a topic; returns the channel id for :meth:`write`.

        The definition and hash come from :class:`MessageDefinitions` unless given. A type
        without a usable definition is still recorded (schema with empty encoding) with a
        warning: the CDR bytes are kept, readers then need the type from elsewhere.
        """
        if self.error is not None:
            raise OSError(self.error.errno, f"{self.path}: not written after an earlier failed write "
                                            f"({self.error.strerror})")
        if self.closed:
            raise ValueError("bag is closed")
        if topic in self.topics:
            raise ValueError(f"topic {topic} is already registered")
        full = normalize_type(type_name)
        schema_id = self._schemas.get(full)
        if schema_id is None:
            if definition is None:
                try:
                    definition = self.definitions.definition(full)
                except UnknownTypeError as exc:
                    warnings.warn(f"{topic}: {exc}; recording without a message definition",
                                  stacklevel=2)
                    definition, schema_encoding = "", ""
            try:
                schema_id = self._mcap.register_schema(
                    name=full, encoding=schema_encoding if definition else "",
                    data=definition.encode("utf-8"))
            except OSError as exc:   # a full chunk went to disk on the way
                self._fail(exc)
                raise
            self._schemas[full] = schema_id
        if type_hash is None:
            type_hash = self.definitions.type_hash(full) if definition != "" else ""
        if qos_yaml is None:
            qos_yaml = qos_profiles_yaml(qos_profiles)
        metadata = {"offered_qos_profiles": qos_yaml, "topic_type_hash": type_hash}
        if extra_metadata:
            metadata.update({k: v for k, v in extra_metadata.items() if k not in metadata})
        try:
            cid = self._mcap.register_channel(topic=topic, message_encoding="cdr",
                                              schema_id=schema_id, metadata=metadata)
        except OSError as exc:
            self._fail(exc)
            raise
        self.topics[topic] = _TopicRecord(cid, topic, full, qos_yaml, type_hash)
        return cid

    # -- hot path ------------------------------------------------------------------------------
    def write(self, channel_id: int, data: bytes, log_time: int, publish_time: int = 0) -> None:
        """Append one message (CDR bytes); times in ns since the epoch (publish_time 0 = log_time).
        Raises the ``OSError`` of a write the OS refused (then the file is ended: class docstring)."""
        try:
            if log_time >= self._deadline:
                self._roll(log_time)
            # remembered and counted before the add: a chunk full with this message is written by
            # the add, and what the file then holds includes it (_commit)
            self._last_cid, self._last_data = channel_id, data
            self._count(channel_id, log_time)
            self._add(channel_id, log_time, data, publish_time or log_time)
        except OSError as exc:
            self._fail(exc)
            raise

    def _count(self, channel_id: int, log_time: int) -> None:
        counts, t = self._counts, self._t_range
        counts[channel_id] = counts.get(channel_id, 0) + 1
        if log_time < t[0]:
            t[0] = log_time
        if log_time > t[1]:
            t[1] = log_time

    def _roll(self, log_time: int) -> None:
        if self._deadline:
            self._mcap.flush()
            self.chunks_flushed += 1
        self._deadline = log_time + self.max_chunk_ns

    def tick(self, now_ns: Optional[int] = None) -> bool:
        """Close the open chunk if it is older than ``max_chunk_s`` (call periodically, e.g. from
        a timer, so a quiet topic's last messages do not wait in memory). Returns True if it did.
        Raises the ``OSError`` of a write the OS refused."""
        if not self._deadline or self.closed:
            return False
        now = time.time_ns() if now_ns is None else now_ns
        if now >= self._deadline:
            try:
                self._mcap.flush()
            except OSError as exc:
                self._fail(exc)
                raise
            self.chunks_flushed += 1
            self._deadline = 0
            return True
        return False

    def flush(self) -> None:
        """Close the open chunk now and hand everything to the OS (raises a refused write's
        ``OSError``)."""
        if not self.closed:
            try:
                self._mcap.flush()
            except OSError as exc:
                self._fail(exc)
                raise
            self._deadline = 0

    # -- a write the OS refused ----------------------------------------------------------------
    def _commit(self) -> None:
        """The sink took a write whole: what the writer has counted is now in the file (the chunk
        builder is empty at every write the writer makes: a write is a chunk, its message indexes,
        the header, metadata or the summary)."""
        counts, end = self._counts, self._t_range[1]
        last = (self._last_cid, self._last_data) if self._last_data else None
        self._committed = (dict(counts), end, last)

    def _fail(self, exc: OSError) -> None:
        """End the file after a refused write (module docstring: cut back, closed, nothing more)."""
        if self.error is None:
            self.error = exc
        self.closed = True
        self._sink.abandon(exc)
        refused = self._sink._refused

        def refuse(channel_id, *_args):
            self._counts[channel_id] -= 1          # counted by write(); the file never held it
            raise OSError(refused.errno, refused.strerror)
        self._add = refuse

    def committed_counts(self) -> Dict[str, int]:
        """Messages per topic the file holds: all of :meth:`message_counts` once finalized; after a
        refused write, those in the chunks written whole before it."""
        counts = self._committed[0]
        return {t: int(counts.get(r.channel_id, 0)) for t, r in self.topics.items()}

    def last_committed(self):
        """``(topic, CDR bytes, log time ns)`` of the last message the file holds (None: none)."""
        _counts, end, last = self._committed
        if last is None:
            return None
        topic = next((t for t, r in self.topics.items() if r.channel_id == last[0]), "")
        return topic, last[1], end

    # -- statistics ----------------------------------------------------------------------------
    def message_counts(self) -> Dict[str, int]:
        """Messages written per topic so far."""
        return {t: int(self._counts.get(r.channel_id, 0)) for t, r in self.topics.items()}

    def _time_range(self):
        lo, hi = self._t_range
        return (0, 0) if lo == _INF_NS else (lo, hi)

    def rosbag2_metadata(self) -> dict:
        """The ``rosbag2_bagfile_information`` mapping (metadata.yaml) for what was written."""
        start, end = self._time_range()
        counts = self.message_counts()
        # the name it will have: output_path writes under a temporary one, renamed at the end
        return _rosbag2_info(final_name(self.mcap_path).name, start, end,
                             [(r, counts[t]) for t, r in self.topics.items()])

    # -- finalize ------------------------------------------------------------------------------
    def close(self) -> None:
        """Finalize: last chunk, ``rosbag2`` metadata record, summary/statistics, footer;
        ``metadata.yaml`` in directory mode. Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            info = self.rosbag2_metadata()
            self._mcap.flush()
            self._mcap.add_metadata("rosbag2", {
                "serialized_metadata": yamltext.dump(info, sort_keys=False).strip(),
                "ROS_DISTRO": os.environ.get("ROS_DISTRO", "jazzy"),
            })
            self._mcap.finish()
            self._sink.flush()
            self._sink.close()
        except OSError as exc:
            # not finalized: cut back to the last whole record so that the file reads as the
            # complete chunks of an unfinalized bag, not as a summary that is half there
            self._fail(exc)
            raise
        except BaseException:
            self._sink.close()
            raise
        if self.bag_dir is not None:
            _write_metadata_yaml(self.bag_dir, info)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _rosbag2_info(file_name: str, start: int, end: int, topics) -> dict:
    duration = max(0, end - start)
    total = sum(n for _, n in topics)
    return {
        "version": _ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": total,
        "topics_with_message_count": [
            {"topic_metadata": {
                "name": r.topic, "type": r.type, "serialization_format": "cdr",
                "offered_qos_profiles": _qos_for_yaml(r.qos_yaml),
                "type_description_hash": r.type_hash},
             "message_count": n}
            for r, n in topics],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [{"path": file_name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": total}],
        "custom_data": {},
        "ros_distro": os.environ.get("ROS_DISTRO", "jazzy"),
    }


def _qos_for_yaml(qos_yaml: str):
    try:
        return yamltext.load(qos_yaml) or []
    except yamltext.YAMLError:
        return qos_yaml


def _write_metadata_yaml(bag_dir: Path, info: dict) -> None:
    text = yamltext.dump({"rosbag2_bagfile_information": info}, sort_keys=False)
    tmp = bag_dir / "metadata.yaml.tmp"
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, bag_dir / "metadata.yaml")
    except OSError:
        tmp.unlink(missing_ok=True)   # no half-written metadata.yaml.tmp left beside the bag
        raise


# ---------------------------------------------------------------------------------------------
# reading


class BagMessage(NamedTuple):
    topic: str
    type: str
    data: bytes          # CDR bytes as recorded
    log_time: int        # ns since epoch (receive time)
    publish_time: int    # ns since epoch (send time)


@dataclass
class TopicInfo:
    topic: str
    type: str
    channel_id: int
    message_encoding: str
    schema_encoding: str
    definition: str
    qos_yaml: str
    type_hash: str
    metadata: Dict[str, str] = field(default_factory=dict)
    count: int = 0   # messages seen by the last complete scan


_REC_HDR = struct.Struct("<BQ").unpack_from   # opcode, body length: the framing of every record
_MSG_HDR = struct.Struct("<HIQQ").unpack_from  # channel id, sequence, log time, publish time
_COMPRESSIONS = {"": None, "zstd": "zstandard", "lz4": "lz4"}  # chunk compression -> module


class _Truncated(Exception):
    def __init__(self, offset: int, reason: str):
        super().__init__(reason)
        self.offset = offset


def _op_name(op: int) -> str:
    from mcap.opcode import Opcode

    try:
        return Opcode(op).name
    except ValueError:
        return f"opcode 0x{op:02x}"


def _frames(buf, start: int, end: int):
    """``(offset, opcode, body)`` of each record in ``buf[start:end]``, by opcode and length only;
    raises :class:`_Truncated` at a record that runs past ``end``. (Why: the module docstring.)"""
    pos = start
    while pos < end:
        if end - pos < 9:
            raise _Truncated(pos, f"truncated record header ({end - pos} of 9 bytes)")
        op, length = _REC_HDR(buf, pos)
        body_end = pos + 9 + length
        if body_end > end:
            raise _Truncated(pos, f"truncated {_op_name(op)} record "
                                  f"(declares {length} bytes, {end - pos - 9} present)")
        yield pos, op, buf[pos + 9:body_end]
        pos = body_end


def _parse(record_class, body):
    """One record body parsed by the ``mcap`` library's record class."""
    from mcap.data_stream import ReadDataStream

    return record_class.read(ReadDataStream(io.BytesIO(body)))


class BagReader:
    """Sequential reader of a (possibly damaged) rosbag2 MCAP file or bag directory.

    Messages come in file order (the recorder writes in receive order). Everything before a
    damage is delivered; a chunk that fails parsing, decompression or its CRC is skipped and
    reading continues after it if the framing allows (see the module docstring).
    """

    def __init__(self, path: PathLike):
        require("mcap.records", "bag", "reading a bag")
        from mcap.records import Header
        from mcap.stream_reader import MAGIC_SIZE, StreamReader
        from mcap.writer import MCAP0_MAGIC

        self.path = Path(path)
        self.mcap_path = _find_mcap(self.path)
        self.profile = ""
        self.library = ""
        self.finalized = False
        self.errors: List[BagError] = []
        self.metadata: Dict[str, Dict[str, str]] = {}
        self._topics: Dict[int, TopicInfo] = {}
        self._schemas: Dict[int, object] = {}
        self._scanned = False
        self.chunks_read = 0
        with open(self.mcap_path, "rb") as f:
            head = f.read(MAGIC_SIZE + 9 + 4096)
        if head[:MAGIC_SIZE] != MCAP0_MAGIC:
            raise BagError(self.mcap_path, 0, "not an MCAP file (bad or missing magic bytes)")
        try:
            header = next(StreamReader(io.BytesIO(head)).records)
            if not isinstance(header, Header):
                raise ValueError("first record is not an MCAP header")
        except Exception as exc:  # noqa: BLE001 - whatever the library raises: unreadable
            raise BagError(self.mcap_path, MAGIC_SIZE,
                           f"unreadable MCAP header record: {exc!r}") from None
        self.profile, self.library = header.profile, header.library

    # -- topics ----------------------------------------------------------------------------
    @property
    def topics(self) -> Dict[str, TopicInfo]:
        """Topics (channels) in the file; counts filled after a full pass over the messages."""
        if not self._scanned:
            for _ in self.messages(strict=False):
                pass
        return {t.topic: t for t in self._topics.values()}

    def summary_counts(self) -> Optional[Dict[str, int]]:
        """Messages per topic from the file's summary section (its statistics), without reading the
        messages; None when the file has no usable summary (not finalized, damaged): then
        :attr:`topics` counts them by reading."""
        from mcap.exceptions import McapError
        from mcap.reader import SeekingReader

        try:
            with open(self.mcap_path, "rb") as f:
                summary = SeekingReader(f).get_summary()
        except (McapError, OSError, ValueError, struct.error, EOFError):
            return None
        if summary is None or summary.statistics is None:
            return None
        counts = summary.statistics.channel_message_counts
        out: Dict[str, int] = {}
        for cid, ch in summary.channels.items():
            out[ch.topic] = out.get(ch.topic, 0) + int(counts.get(cid, 0))
        return out

    def topic_info(self, topic: str) -> Optional[TopicInfo]:
        """The channel of ``topic`` as read so far (during or after :meth:`messages`), or None."""
        for t in self._topics.values():
            if t.topic == topic:
                return t
        return None

    # -- messages --------------------------------------------------------------------------
    def messages(self, topics: Optional[Iterable[str]] = None, *,
                 strict: bool = True) -> Iterator[BagMessage]:
        """Yield :class:`BagMessage` for every readable message (of ``topics``, default all).

        Damage (truncation, a bad chunk, a file that was never finalized) does not stop the
        good data: all readable messages are yielded first; then, if ``strict``, the first
        problem is raised as :class:`BagError` (with file and byte offset); otherwise the
        problems are only kept in :attr:`errors`.
        """
        wanted = None if topics is None else set(topics)
        self.errors = []
        counts: Dict[int, int] = {}
        with open(self.mcap_path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
            try:
                yield from self._scan(f, memoryview(mm), size, wanted, counts)
            finally:
                if size:
                    try:
                        mm.close()
                    except BufferError:  # views still referenced; the GC closes it
                        pass
        for t in self._topics.values():
            t.count = counts.get(t.channel_id, 0)
        self._scanned = True
        if strict and self.errors:
            first = self.errors[0]
            raise BagError(first.path, first.offset, first.reason, more=len(self.errors) - 1)

    def _err(self, offset: int, reason: str) -> None:
        self.errors.append(BagError(self.mcap_path, offset, reason))

    def _scan(self, f, buf, size, wanted, counts):
        from mcap.exceptions import McapError
        from mcap.opcode import Opcode
        from mcap.records import Metadata
        from mcap.stream_reader import MAGIC_SIZE

        message_op, definition_ops = Opcode.MESSAGE, (Opcode.SCHEMA, Opcode.CHANNEL)
        topics = self._topics
        self.finalized = False
        try:
            for pos, op, body in _frames(buf, MAGIC_SIZE, size):
                try:
                    if op == Opcode.CHUNK:
                        records = self._chunk_records(body, pos)
                        if records is None:
                            continue
                        self.chunks_read += 1
                    elif op == message_op or op in definition_ops:
                        records = ((pos, op, body),)
                    elif op == Opcode.METADATA:
                        meta = _parse(Metadata, body)
                        self.metadata[meta.name] = meta.metadata
                        continue
                    elif op == Opcode.DATA_END:
                        self._check_summary(f, size)
                        return
                    else:
                        continue
                    for _ipos, iop, ibody in records:
                        if iop == message_op:
                            cid, _seq, log_time, pub_time = _MSG_HDR(ibody, 0)
                            t = topics.get(cid)
                            if t is None:
                                self._err(pos, f"message for unknown channel {cid}")
                                continue
                            counts[cid] = counts.get(cid, 0) + 1
                            if wanted is None or t.topic in wanted:
                                yield BagMessage(t.topic, t.type, bytes(ibody[22:]), log_time,
                                                 pub_time)
                        elif iop in definition_ops:
                            self._definition_record(iop, ibody)
                except (struct.error, ValueError, McapError) as exc:
                    self._err(pos, f"malformed {_op_name(op)} record: {exc!r}")
        except _Truncated as bad:
            self._err(bad.offset, f"{bad}; the file is truncated or corrupt (e.g. the recorder "
                      "was killed); data before this point is intact")
            return
        self._err(size, "file ends without a data-end record: the recording was not "
                  "finalized (recorder crashed or was killed); all complete chunks were read")

    def _check_summary(self, f, size) -> None:
        """After a complete data section: footer, closing magic and the summary they point to
        must be readable by mcap's seeking reader."""
        from mcap.reader import SeekingReader
        from mcap.stream_reader import MAGIC_SIZE
        from mcap.writer import MCAP0_MAGIC

        try:
            f.seek(size - MAGIC_SIZE)
            if f.read(MAGIC_SIZE) != MCAP0_MAGIC:
                raise ValueError("no closing magic bytes")
            f.seek(0)
            SeekingReader(f).get_summary()
            self.finalized = True
        except Exception:  # noqa: BLE001 - whatever the library raises: not finalized
            self._err(size, "summary section or footer is missing or damaged "
                      "(data section is complete)")

    def _chunk_records(self, body, pos):
        """The records of one chunk (``mcap`` parses, decompresses and checks its CRC), or None
        (said in :attr:`errors`) if it is damaged."""
        from mcap.exceptions import UnsupportedCompressionError
        from mcap.records import Chunk
        from mcap.stream_reader import get_chunk_data_stream

        try:
            chunk = _parse(Chunk, body)
            if chunk.compression not in _COMPRESSIONS:  # the library would take it as raw
                raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
            try:
                stream, usize = get_chunk_data_stream(chunk, validate_crc=True)
            except UnsupportedCompressionError:  # not damage: this environment lacks the codec
                raise MissingDependency(_COMPRESSIONS[chunk.compression], "bag",
                                        f"reading a {chunk.compression}-compressed bag") from None
            return list(_frames(memoryview(stream.read(usize)), 0, usize))
        except MissingDependency:
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of this chunk: skip it, say why
            self._err(pos, f"damaged chunk skipped ({type(exc).__name__}: {exc})")
            return None

    def _definition_record(self, op, body):
        from mcap.opcode import Opcode
        from mcap.records import Channel, Schema

        if op == Opcode.SCHEMA:
            schema = _parse(Schema, body)
            self._schemas[schema.id] = schema
            return
        ch = _parse(Channel, body)
        schema = self._schemas.get(ch.schema_id)
        self._topics[ch.id] = TopicInfo(
            topic=ch.topic, type=schema.name if schema else "", channel_id=ch.id,
            message_encoding=ch.message_encoding,
            schema_encoding=schema.encoding if schema else "",
            definition=str(schema.data, "utf-8") if schema else "",
            qos_yaml=ch.metadata.get("offered_qos_profiles", ""),
            type_hash=ch.metadata.get("topic_type_hash", ""), metadata=ch.metadata)


def _find_mcap(path: Path) -> Path:
    if path.is_dir():
        meta = path / "metadata.yaml"
        if meta.is_file():
            try:
                info = yamltext.load(meta.read_text())["rosbag2_bagfile_information"]
                files = info.get("relative_file_paths") or []
                if files and (path / Path(files[0]).name).is_file():
                    return path / Path(files[0]).name
            except (yamltext.YAMLError, KeyError, TypeError):
                pass
        found = sorted(path.glob("*.mcap"))
        if not found:
            raise BagError(path, 0, "bag directory holds no .mcap file")
        return found[0]
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such bag file or directory")
    return path


def open_bag(path: PathLike) -> BagReader:
    """Open a bag (``.mcap`` file or bag directory) for reading; see :class:`BagReader`.

    ``for m in open_bag(p).messages(): m.topic, m.type, m.data, m.log_time, m.publish_time``
    """
    return BagReader(path)


# ---------------------------------------------------------------------------------------------
# decoding: the one layer every reader of a bag's messages goes through

def _fast_decoders() -> dict:
    from . import cdr, topics

    return {topics.IMU_TYPE: cdr.decode_imu, topics.MAG_TYPE: cdr.decode_vector3,
            topics.TEMPERATURE_TYPE: cdr.decode_temperature, topics.REFERENCE_TYPE: cdr.decode_vector3,
            topics.DEPTH_TYPE: cdr.decode_float64, topics.SERIAL_TYPE: cdr.decode_string}


class BagDecoder:
    """A bag's messages as values: the probe's six types by :mod:`cdr` (the fast path, ~1 µs a
    message: ``((sec, nanosec), values)`` as its ``decode_*`` give them, a depth's float, a serial's
    text), every other type by ``rosbags``' deserializer into its dataclass, with the definition the
    bag's own schema records (as ``rosbags.highlevel.AnyReader`` does: a station recorded before a
    field existed reads without it), else the installed one (:class:`MessageDefinitions`).
    ``fast=False`` decodes the probe's types with ``rosbags`` too.  A message that does not decode
    raises what the decoder raises (:data:`DECODE_ERRORS`)."""

    def __init__(self, *, fast: bool = True, definitions: Optional[MessageDefinitions] = None):
        self.fast = _fast_decoders() if fast else {}
        self.definitions = definitions
        self._stores: Dict[tuple, object] = {}

    def store(self, type_name: str, definition: str = ""):
        """The ``rosbags`` type store that holds ``type_name`` as ``definition`` describes it
        (one store per definition: two parts of a run may record two versions of a type)."""
        key = (type_name, definition)
        st = self._stores.get(key)
        if st is None:
            if definition:
                require("rosbags.typesys", "bag", "decoding a bag's messages")
                from rosbags.typesys import Stores, get_types_from_msg, get_typestore

                st = get_typestore(Stores.EMPTY)
                st.register(get_types_from_msg(definition, type_name))
            else:
                defs = self.definitions or _defaults()
                defs.register(type_name)
                st = defs.typestore
            self._stores[key] = st
        return st

    def decode(self, info: "TopicInfo", data):
        """One message of the channel ``info`` (:meth:`BagReader.topic_info`) from its CDR bytes."""
        fast = self.fast.get(info.type)
        if fast is not None:
            return fast(data)
        return self.store(info.type, info.definition).deserialize_cdr(bytes(data), info.type)


class MessageEncoder:
    """Serializes ``SurveyStation`` and ``CalibrationCoefficients`` messages to CDR without rclpy
    (``rosbags`` type store with our message definitions registered)."""

    def __init__(self, definitions: Optional[MessageDefinitions] = None):
        require("rosbags.typesys", "bag", "writing our messages into a bag")
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        from .topics import COEFFICIENTS_TYPE, PROGRESS_TYPE, STATION_TYPE

        defs = definitions or MessageDefinitions()
        self.store = get_typestore(Stores.ROS2_JAZZY)
        for name in (STATION_TYPE, COEFFICIENTS_TYPE, PROGRESS_TYPE):
            self.store.register(get_types_from_msg(defs.text(name), name))
        self._header = self.store.types["std_msgs/msg/Header"]
        self._time = self.store.types["builtin_interfaces/msg/Time"]

    def encode(self, type_name: str, stamp_ns: int, frame_id: str, fields: dict) -> bytes:
        import numpy as np

        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        cls = self.store.types[type_name]
        # rosbags wants numpy arrays for numeric sequences
        vals = {k: (np.asarray(v, dtype=np.uint8 if k == "poses_used" else float)
                    if isinstance(v, list) and (not v or not isinstance(v[0], str)) else v)
                for k, v in fields.items()}
        msg = cls(header=self._header(stamp=self._time(sec=sec, nanosec=nsec), frame_id=frame_id), **vals)
        return bytes(self.store.serialize_cdr(msg, type_name))

    def decode(self, type_name: str, data) -> dict:
        """The fields of one of our messages from its CDR bytes (``stamp``: the header's, s), as this
        version defines it (a run's own recording; a bag's other messages: :class:`BagDecoder`)."""
        msg = self.store.deserialize_cdr(bytes(data), type_name)
        out = {k: getattr(msg, k) for k in msg.__dataclass_fields__ if k != "header"}
        out["stamp"] = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        return out


_default_encoder: Optional[MessageEncoder] = None


def message_encoder() -> MessageEncoder:
    """The process's :class:`MessageEncoder` of the installed definitions, made on the first call
    (registering our types into a type store takes about 16 ms, once per run of ``reprocess``
    before; encoding and decoding leave it as it is)."""
    global _default_encoder
    if _default_encoder is None:
        _default_encoder = MessageEncoder()
    return _default_encoder


def _decode_errors() -> tuple:
    from .cdr import DECODE_ERRORS as CDR_ERRORS

    try:
        from rosbags.serde import SerdeError
        from rosbags.typesys import TypesysError
    except ImportError:              # no rosbags: only the fast path decodes
        return CDR_ERRORS
    return CDR_ERRORS + (SerdeError, TypesysError)


#: What decoding a message raises on bytes that are not the message (:mod:`cdr`'s, rosbags').
DECODE_ERRORS = _decode_errors()


def read_messages(bag, topics: Optional[Iterable[str]] = None, *, decode: bool = True, strict: bool = True,
                  fast: bool = True) -> Iterator[tuple]:
    """``(message, value)`` for each message of ``topics`` (default all) of ``bag`` (a path, or a
    :class:`BagReader` whose :attr:`~BagReader.errors` the caller reads after) in file order: the
    :class:`BagMessage` and, with ``decode``, its value (:class:`BagDecoder`: the probe's types by
    :mod:`cdr`, the others as ``rosbags`` dataclasses), else None.  ``strict``: a damaged bag
    raises :class:`BagError` after its readable messages (:meth:`BagReader.messages`).  A message
    that does not decode raises (:data:`DECODE_ERRORS`)."""
    reader = bag if isinstance(bag, BagReader) else open_bag(bag)
    decoder = BagDecoder(fast=fast) if decode else None
    infos: Dict[str, TopicInfo] = {}
    for m in reader.messages(topics, strict=strict):
        if decoder is None:
            yield m, None
            continue
        info = infos.get(m.topic)
        if info is None:
            info = infos[m.topic] = reader.topic_info(m.topic)
        yield m, decoder.decode(info, m.data)


#: StreamProgress fields read into the accounting (accounting.account).
PROGRESS_FIELDS = ("node", "settled", "has_reference", "has_temperature", "has_depth", "window", "imu", "mag",
                   "temperature", "reference", "depth", "pairs_used", "pairs_dropped", "stations",
                   "stations_uncorrected", "records", "forced", "end")


def read_bag(path, progress=None):
    """Stations (:func:`surveystation.from_msg`), coefficient messages and the last calibration status of
    a bag as plain dicts, in receive order (:func:`bag.read_messages`: each message decoded with the
    definition the bag records); with a list ``progress``, the ``/graph/progress`` messages are
    appended to it (dicts of :data:`PROGRESS_FIELDS`).  Raises ``ValueError`` (one line) for what is
    not a readable bag."""
    from .surveystation import from_msg as station_dict
    from .topics import TOPIC_COEFFICIENTS, TOPIC_PROGRESS, TOPIC_STATION, TOPIC_STATUS

    require("rosbags.typesys", "bag", "the run summary")
    stations, coefficients, status = [], [], None
    wanted = {TOPIC_STATION, TOPIC_COEFFICIENTS, TOPIC_STATUS}
    if progress is not None:
        wanted.add(TOPIC_PROGRESS)
    try:
        for m, msg in read_messages(path, wanted):
            if m.topic == TOPIC_PROGRESS:
                progress.append({k: getattr(msg, k) for k in PROGRESS_FIELDS})
            elif m.topic == TOPIC_STATION:
                stations.append(station_dict(msg))
            elif m.topic == TOPIC_STATUS:
                status = {"state": msg.state, "message": msg.message, "captured": [int(x) for x in msg.captured],
                          "pending": [int(x) for x in msg.pending], "warnings": list(msg.warnings)}
            else:
                coefficients.append({"id": msg.id, "coefficients_yaml": msg.coefficients_yaml,
                                     "stamp": msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec,
                                     "accel_correction_matrix": [float(x) for x in msg.accel_correction_matrix],
                                     "mag_correction_matrix": [float(x) for x in msg.mag_correction_matrix]})
    except BagError as exc:          # not a bag, or a damaged one: said, not raised raw (the caller names the file)
        raise ValueError(f"not a readable bag ({exc.reason} at byte offset {exc.offset})") from None
    except DECODE_ERRORS as exc:
        raise ValueError(f"not a readable bag (a message that does not decode: {type(exc).__name__}: {exc})") from None
    return stations, coefficients, status


@dataclass
class RecoveryReport:
    source: Path
    destination: Path
    saved: int                       # messages written to the destination
    per_topic: Dict[str, int]
    errors: List[BagError]           # problems found in the source
    finalized_source: bool           # the source was already a complete bag

    def __str__(self) -> str:
        s = f"recovered {self.saved} messages from {self.source} into {self.destination}"
        if self.errors:
            s += f" ({len(self.errors)} problem(s); first: {self.errors[0]})"
        return s


def recover(src: PathLike, dst: PathLike, *, compression: Optional[str] = None) -> RecoveryReport:
    """Rewrite every readable message of a damaged (or unfinalized) bag into a new, finalized
    bag at ``dst`` (``.mcap`` file or directory; must not exist). Schemas, QoS and type-hash
    metadata are copied. Returns a :class:`RecoveryReport` with the number of messages saved."""
    reader = BagReader(src)
    comp = compression
    if comp is None:
        comp = "zstd" if "zstd" in available_compressions() else ""
    writer = BagWriter(dst, compression=comp, library=reader.library or None)
    cids: Dict[str, int] = {}
    saved = 0
    try:
        for m in reader.messages(strict=False):
            cid = cids.get(m.topic)
            if cid is None:
                t = next(x for x in reader._topics.values() if x.topic == m.topic)
                extra = {k: v for k, v in t.metadata.items()
                         if k not in ("offered_qos_profiles", "topic_type_hash")}
                cid = writer.add_topic(t.topic, t.type, qos_yaml=t.qos_yaml,
                                       type_hash=t.type_hash, definition=t.definition,
                                       schema_encoding=t.schema_encoding or "ros2msg",
                                       extra_metadata=extra)
                cids[m.topic] = cid
            writer._count(cid, m.log_time)         # as read: no chunk cut by time (write() would)
            writer._add(cid, m.log_time, m.data, m.publish_time)
            saved += 1
        # topics that had no readable message still get their channel
        for t in reader._topics.values():
            if t.topic not in cids:
                cids[t.topic] = writer.add_topic(
                    t.topic, t.type, qos_yaml=t.qos_yaml, type_hash=t.type_hash,
                    definition=t.definition, schema_encoding=t.schema_encoding or "ros2msg")
    finally:
        writer.close()
    return RecoveryReport(Path(src), Path(dst), saved, writer.message_counts(),
                          list(reader.errors), reader.finalized and not reader.errors)

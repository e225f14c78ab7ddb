"""Reprocessing many bags on Dask into one Parquet dataset (issue 13, item 4).

Bags are grouped into tasks of ``bags_per_task`` (default :func:`auto_bags_per_task`: up to
:data:`MAX_BAGS_PER_TASK`, while every worker still gets at least :data:`TASKS_PER_WORKER` tasks;
chosen from the measurement in ``docs/fleet.md``), run on a Dask cluster — a local one by default
(:class:`distributed.LocalCluster`, one thread per worker process, on loopback), or the cluster of
the scheduler address given, unchanged. A task:

1. hashes the bag (SHA-256 of its MCAP file) and reads the probe serial it records
   (:func:`inclinometer_calib.correct.reprocess.bag_probe_serial`) and its survey time (the log time of
   its first message, UTC);
2. looks up the calibration record valid for that probe at that time
   (:meth:`registry.Registry.valid_record`: never guessed; an unknown probe, no record before
   the survey, or an overdue one fails the bag with the registry's reason);
3. if the bag is in the done-index with the same key — bag content, record id, the pipeline
   settings and this package's version — it is skipped;
4. otherwise runs the one pipeline, :func:`inclinometer_calib.correct.reprocess.reprocess` (no output
   bag), with the same defaults as the single-bag ``reprocess`` command (static detector from the
   data's noise, default QC tolerances, field monitor over 30 stations), so its stations are the
   single-bag command's exactly;
5. writes the stations as one Parquet fragment of the dataset ``OUT/stations/``, hive-partitioned
   by ``probe`` (the serial) and ``survey_date`` (``YYYY-MM-DD``, UTC):
   ``OUT/stations/probe=SN-1/survey_date=2026-11-03/part-<key>.parquet``. Written to a hidden
   temporary file in the same folder and renamed: a crashed task leaves no half fragment (a hidden
   ``.part-*.tmp`` at most, which readers skip).

Columns of a fragment: ``bag`` (absolute path), ``bag_sha256``, ``record_id``, ``survey_start``
(timestamp, UTC), ``probe_forced`` (the record was applied to a bag that records another serial,
with ``force_probe``), ``stamp`` (the station message's header stamp, s since the epoch, as
``io.bag.read_bag`` gives it), then every field of ``SurveyStation`` in the message's order, typed
from the message definition (float64, uint32, uint8, bool, string; ``string[]`` as a list of
strings; ``float64[N]`` as a fixed-size list of N float64: ``raw_gravity_mps2``, ``raw_field_nt``,
``position_covariance_ned_m2``). Read the dataset with :func:`read_stations`.

A bag that fails — not a bag, truncated or damaged, no serial recorded, unknown probe, no valid
record — is reported with its reason in the summary and does not stop the others; a truncated
bag's readable part is not written (the dataset holds only complete bags: ``bag recover`` it, and
reprocess the recovered bag). The driver keeps ``OUT/done-index.json`` (written atomically, every
few seconds and at the end) and ``OUT/summary.csv`` (this run, one row per bag). A bag redone
under a new key (new record, new content, new settings) replaces its old fragment. One run at a
time per output folder (``OUT/.lock``, released when the run's process ends, however it ends).

A Dask worker lost while on a bag (its process died: out of memory, a crash in native code, a
kill) is put on that bag: each task notes the bag it begins (``OUT/.running/``), and a note its
worker could not remove names the bag. Dask retries the task on another worker; the bag then says
it was retried and how it ended, or, when the bag was on as many lost workers as Dask allows, fails
as lost with its workers while the rest of its batch is done in a new task (:func:`_run_dask`).

The output folder, the bags and the registry must be reachable from every worker (on a cluster: a
shared file system and a shared database URL such as PostgreSQL).
"""
from __future__ import annotations

import csv
import datetime as _dt
import hashlib
import io
import json
import os
import time
import urllib.parse
from dataclasses import asdict, dataclass, field
from typing import Callable, Dict, List, Optional, Sequence

from .. import __version__
from ..io.bag import BagError, open_bag
from ..core.output import OutputError, atomic_write_text, check_output
from ..io.progress import progress_bar
from ..core.survey import Tolerances
from .manifest import BagEntry, dedupe, entries_from_paths

#: Version of the dataset's layout and of the key: a change redoes every bag.
LAYOUT_VERSION = 1
DATASET_DIR = "stations"
INDEX_FILE = "done-index.json"
SUMMARY_FILE = "summary.csv"
LOCK_FILE = ".lock"
#: Where each Dask task notes the bags it begins (``OUT/.running/<task key>@<worker address>``): a note
#: left behind is a worker process that died while on its last bag (see :func:`dask_batch`).
RUNNING_DIR = ".running"
INDEX_FORMAT = "inclinometer_calib/fleet-done-index"
#: Partition keys of the dataset (hive style, values URI-encoded), in folder order.
PARTITION_KEYS = ("probe", "survey_date")
#: Columns each fragment has before the station's own fields.
PROVENANCE_COLUMNS = ("bag", "bag_sha256", "record_id", "survey_start", "probe_forced", "stamp")
#: Bags per task at most by default: 10 short bags (~0.6 s of work) made the most of 2 local workers
#: in benchmarks/fleet_reprocess.py (1.59× the single-process loop, against 1.17× with 1 bag per task).
MAX_BAGS_PER_TASK = 10
#: Tasks per worker at least by default (so that no worker idles at the end while another has a batch).
TASKS_PER_WORKER = 4
#: Seconds between rewrites of the done-index while a run goes on (and once at its end).
INDEX_FLUSH_S = 5.0
#: How the reason of a bag whose workers were lost begins (Dask gave up on its task: KilledWorker).
LOST_REASON = "lost with its worker"

Resolver = Callable[[str, _dt.datetime], object]   # (serial, survey time UTC) -> coeffs.Calibration


# ---------------------------------------------------------------------------------------------
# settings and the key

@dataclass(frozen=True)
class Settings:
    """What, besides the bag and the record, decides a bag's stations; part of the done key.

    Defaults are the single-bag ``reprocess`` command's: QC tolerances ``Tolerances()``, the static
    detector's thresholds from the data's noise, the field monitor over ``monitor_window`` = 30
    stations (0: off). ``force_probe``: apply the record of the serial the manifest gives to a bag
    that records another serial or none (every station then says so in its warnings)."""

    field_nt: float = Tolerances.field_nt
    dip_deg: float = Tolerances.dip_deg
    gravity_mps2: float = Tolerances.gravity_mps2
    monitor_window: int = 30
    force_probe: bool = False

    @property
    def tolerances(self) -> Tolerances:
        return Tolerances(field_nt=self.field_nt, dip_deg=self.dip_deg, gravity_mps2=self.gravity_mps2)


def done_key(bag_path: str, bag_sha256: str, record_id: str, serial: str, settings: Settings) -> str:
    """The key a bag's result is done under (and its fragment's name): SHA-256 over the bag's
    absolute path and content hash, the record id, the serial it was filed under, the settings,
    this package's version and the layout version.  The path is in it: the same bytes surveyed
    twice (two copies of a bag, under two names) are two surveys, two fragments."""
    blob = json.dumps({"path": os.path.abspath(bag_path), "bag": bag_sha256, "record": record_id, "serial": serial,
                       "settings": asdict(settings), "package": __version__, "layout": LAYOUT_VERSION},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


# ---------------------------------------------------------------------------------------------
# the registry, seen from a worker

_REGISTRIES: Dict[str, object] = {}


def absolute_db_url(url: str) -> str:
    """The registry's URL (:func:`registry.normalize_url`) with a relative SQLite path
    (``sqlite:///fleet.db``) made absolute against this working directory: a worker's may differ."""
    from .registry import normalize_url

    url = normalize_url(url)
    prefix = "sqlite:///"
    if url.startswith(prefix) and not url.startswith(prefix + "/"):
        rest = url[len(prefix):]
        path, sep, query = rest.partition("?")
        if path and path != ":memory:":
            return prefix + os.path.abspath(path) + sep + query
    return url


class RegistryResolver:
    """The valid record of a probe at a date from the registry at ``url`` (a picklable callable:
    it travels to the workers as its URL and the schema revision the first process to open it
    found; each worker process opens the registry once, checking it is still at that revision)."""

    def __init__(self, url: str):
        self.url = absolute_db_url(url)
        self.revision = None

    def registry(self):
        reg = _REGISTRIES.get(self.url)
        if reg is None:
            from .registry import Registry

            reg = _REGISTRIES[self.url] = Registry(self.url, revision=self.revision)
        if self.revision is None:            # this process opened it, migrated: it is at the head now
            from .registry import head_revision

            self.revision = head_revision()
        return reg

    def __call__(self, serial: str, at: _dt.datetime):
        return self.registry().valid_record(serial, at)

    def __repr__(self):
        return f"RegistryResolver({self.url!r})"


def _lookup_errors() -> tuple:
    """The exceptions a resolver raises for a bag it has no valid record for."""
    from .registry import RegistryError

    return (RegistryError,)


# ---------------------------------------------------------------------------------------------
# bags

def bag_sha256(path) -> str:
    """SHA-256 (hex) of a bag's MCAP file (the file itself for a ``.mcap``, the one a bag folder's
    ``metadata.yaml`` names otherwise). Raises :class:`bag.BagError` for what is not a bag."""
    reader = open_bag(path)
    with open(reader.mcap_path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def survey_start(path) -> _dt.datetime:
    """The log time of a bag's first message as an aware UTC datetime (the survey's date for the
    registry). Raises :class:`bag.BagError` when the bag holds no readable message."""
    reader = open_bag(path)
    for m in reader.messages(strict=False):
        return _dt.datetime.fromtimestamp(m.log_time / 1e9, _dt.timezone.utc)
    first = reader.errors[0] if reader.errors else None
    raise BagError(reader.mcap_path, first.offset if first else 0,
                   f"no readable message{f' ({first.reason})' if first else ''}")


# ---------------------------------------------------------------------------------------------
# Parquet

_SCHEMA = None


def station_schema():
    """The Arrow schema of a fragment: the provenance columns, then every ``SurveyStation`` field
    (but the header) as :func:`surveystation.arrow_types` types it (the one field table)."""
    global _SCHEMA
    if _SCHEMA is None:
        import pyarrow as pa
        from ..io.surveystation import arrow_types

        fields = [pa.field("bag", pa.string()), pa.field("bag_sha256", pa.string()),
                  pa.field("record_id", pa.string()), pa.field("survey_start", pa.timestamp("ns", tz="UTC")),
                  pa.field("probe_forced", pa.bool_()), pa.field("stamp", pa.float64())]
        fields += [pa.field(name, t) for name, t in arrow_types(pa)]
        _SCHEMA = pa.schema(fields)
    return _SCHEMA


def header_stamp_s(t_end: float) -> float:
    """A station's header stamp (s since the epoch) as ``io.bag.read_bag`` gives it: the message
    stamp ``round(t_end·1e9)`` ns read back as ``sec + 1e-9·nanosec``."""
    sec, nsec = divmod(int(round(t_end * 1e9)), 1_000_000_000)
    return sec + 1e-9 * nsec


def stations_table(stations: Sequence[dict], provenance: dict, stamps: Sequence[float]):
    """The stations (``reprocess`` report dicts) with their provenance and header stamps (s) as
    one Arrow table. Raises :class:`ValueError` for a station field the message does not declare."""
    import pyarrow as pa

    from ..io.surveystation import to_row

    rows = [{**provenance, **to_row({**st, "stamp": stamp})} for st, stamp in zip(stations, stamps, strict=True)]
    return pa.Table.from_pylist(rows, schema=station_schema())


def partition_dir(serial: str, date: str) -> str:
    """The fragment folder of a probe and a date, relative to the dataset (hive style, values
    URI-encoded as pyarrow reads them)."""
    q = lambda v: urllib.parse.quote(v, safe="")  # noqa: E731
    return os.path.join(f"{PARTITION_KEYS[0]}={q(serial)}", f"{PARTITION_KEYS[1]}={q(date)}")


def write_fragment(table, out_dir, rel_path: str) -> None:
    """Write ``table`` as ``out_dir/rel_path`` via a hidden temporary file in the same folder and a
    rename (atomic: a reader sees the old file, the new one or none, never half of one)."""
    import pyarrow.parquet as pq

    path = os.path.join(out_dir, rel_path)
    folder, name = os.path.split(path)
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{name}.{os.getpid()}.tmp")
    try:
        pq.write_table(table, tmp, compression="zstd")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_stations(out_dir, filter=None):
    """The dataset's stations as one Arrow table (``probe`` and ``survey_date`` columns from the
    folders); ``filter``: a ``pyarrow.dataset`` expression, e.g. ``pc.field("probe") == "SN-1"``."""
    import pyarrow as pa
    import pyarrow.dataset as ds

    root = os.path.join(os.fspath(out_dir), DATASET_DIR)
    part = ds.partitioning(pa.schema([(k, pa.string()) for k in PARTITION_KEYS]), flavor="hive")
    if not os.path.isdir(root):
        return station_schema().empty_table().append_column(
            PARTITION_KEYS[0], pa.array([], pa.string())).append_column(PARTITION_KEYS[1], pa.array([], pa.string()))
    return ds.dataset(root, format="parquet", partitioning=part, schema=None).to_table(filter=filter)


# ---------------------------------------------------------------------------------------------
# one bag: the task body

@dataclass
class BagResult:
    """What became of one bag. ``status``: ``ok``, ``failed`` (``reason`` says why) or
    ``skipped`` (done before under the same key). ``fragment``: relative to the output folder
    ("" when none: failed, or no station)."""

    bag: str
    status: str
    reason: str = ""
    serial: str = ""
    survey_start: str = ""
    record_id: str = ""
    stations: int = 0
    seconds: float = 0.0
    bag_sha256: str = ""
    key: str = ""
    fragment: str = ""
    probe_forced: bool = False
    #: The Dask workers (addresses) that were lost — their process died — while on this bag. With a
    #: status ``ok`` (or ``skipped``) it was retried and done; ``failed``, Dask gave up (KilledWorker).
    workers_lost: List[str] = field(default_factory=list)


def _serial_for(entry: BagEntry, recorded: Optional[str], settings: Settings):
    """(serial whose record applies, forced?) or raise ValueError with the reason.

    The bag's recorded serial is the data's probe. A bag that records none takes the manifest's
    (as ``reprocess --probe-serial`` does); a manifest serial that contradicts the bag's is
    refused unless ``force_probe``."""
    if recorded is None:
        if entry.serial is None:
            raise ValueError("no probe serial recorded in the bag (no /probe/serial topic): give it in the "
                             "manifest's serial column")
        return entry.serial, False
    if entry.serial is None or entry.serial == recorded:
        return recorded, False
    if not settings.force_probe:
        raise ValueError(f"the bag records probe {recorded!r} but the manifest says {entry.serial!r}: refused "
                         "(--force-probe applies that probe's record anyway, and every station says so)")
    return entry.serial, True


def process_bag(entry: BagEntry, resolver: Resolver, out_dir: str, settings: Settings = Settings(),
                done: Optional[str] = None) -> BagResult:
    """Reprocess one bag into its fragment (the module docstring's steps 1–5). ``done``: the key
    the bag is done under in the index (skipped when it is the key now). Expected failures
    (not a bag, damage, no serial, no valid record, no probe samples) come back as a ``failed``
    result with the reason; anything else is a bug and raises."""
    from ..lab.field import FieldMonitor
    from ..correct.reprocess import ReprocessError, bag_probe_serial, reprocess

    t0 = time.perf_counter()
    res = BagResult(bag=entry.path, status="failed")
    try:
        res.bag_sha256 = bag_sha256(entry.path)
        start = survey_start(entry.path)
        res.survey_start = start.isoformat()
        recorded = bag_probe_serial(entry.path)
        serial, forced = _serial_for(entry, recorded, settings)
        res.serial, res.probe_forced = serial, forced
        try:
            cal = resolver(serial, start)
        except _lookup_errors() as exc:
            raise ValueError(f"no valid record in the registry: {exc}") from None
        res.record_id = cal.id
        res.key = done_key(entry.path, res.bag_sha256, cal.id, serial, settings)
        if done is not None and done == res.key:
            res.status, res.reason = "skipped", "done before with the same bag, record and settings"
            return res
        monitor = FieldMonitor(window=settings.monitor_window) if settings.monitor_window else None
        rep = reprocess(entry.path, None, cal, None, settings.tolerances, monitor=monitor, force_probe=forced,
                        probe_serial=serial if recorded is None else None)
        if rep.bag_errors:
            e = rep.bag_errors[0]
            more = f" (+{len(rep.bag_errors) - 1} more)" if len(rep.bag_errors) > 1 else ""
            raise ValueError(f"damaged bag: {e}{more}; nothing written (the dataset holds complete bags only: "
                             "`inclinometer-calib bag recover` it and reprocess the recovered bag)")
        res.stations = len(rep.stations)
        if rep.stations:
            date = start.date().isoformat()
            res.fragment = os.path.join(DATASET_DIR, partition_dir(serial, date), f"part-{res.key[:24]}.parquet")
            prov = {"bag": entry.path, "bag_sha256": res.bag_sha256, "record_id": cal.id, "survey_start": start,
                    "probe_forced": forced}
            stamps = [header_stamp_s(st.t_end) for st in rep.raw_stations]
            write_fragment(stations_table(rep.stations, prov, stamps), out_dir, res.fragment)
        res.status = "ok"
    except (BagError, ReprocessError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        res.reason = str(exc)
    except ValueError as exc:            # the reasons raised above (serial, record, damage)
        res.reason = str(exc)
    finally:
        res.seconds = time.perf_counter() - t0
    return res


def process_batch(entries: Sequence[BagEntry], resolver: Resolver, out_dir: str, settings: Settings,
                  done: Sequence[Optional[str]], begin: Optional[Callable[[int, BagEntry], None]] = None
                  ) -> List[BagResult]:
    """One task: the bags of ``entries`` one after the other. A bag that raises (a bug, not an
    expected failure) is reported failed with the exception and does not take its batch-mates
    down with it. ``begin(i, entry)`` is called before the ``i``-th bag."""
    out = []
    for i, (entry, key) in enumerate(zip(entries, done)):
        if begin is not None:
            begin(i, entry)
        try:
            out.append(process_bag(entry, resolver, out_dir, settings, key))
        except Exception as exc:  # noqa: BLE001 - task boundary: one bag's bug must not fail the others
            out.append(BagResult(bag=entry.path, status="failed", reason=f"internal error: {type(exc).__name__}: {exc}"))
    return out


def _running_note(out_dir: str, task_key, worker: str) -> str:
    q = lambda v: urllib.parse.quote(str(v), safe="")  # noqa: E731
    return os.path.join(out_dir, RUNNING_DIR, f"{q(task_key)}@{q(worker)}")


def dask_batch(entries: Sequence[BagEntry], resolver: Resolver, out_dir: str, settings: Settings,
               done: Sequence[Optional[str]], before_bag: Optional[Callable[[BagEntry], None]] = None
               ) -> List[BagResult]:
    """:func:`process_batch` as a Dask task, noting the bags it begins: ``OUT/.running/<task
    key>@<worker address>`` gets the batch index of each bag as it begins (flushed to the OS before
    the bag starts) and is removed when the task ends.  A worker process that dies — out of memory,
    a crash in native code, a kill — cannot remove it: a note left behind names the worker and the
    bag it was on (:func:`lost_attempts`), which Dask's own retry or ``KilledWorker`` do not say.
    ``before_bag(entry)``: called before each bag (a test's hook: a worker that dies on a bag)."""
    from distributed import get_worker

    worker = get_worker()
    note = _running_note(out_dir, worker.get_current_task(), worker.address)
    os.makedirs(os.path.dirname(note), exist_ok=True)

    def begin(i, entry):
        fh.write(f"{i}\n")
        fh.flush()
        if before_bag is not None:
            before_bag(entry)

    with open(note, "w", encoding="ascii") as fh:
        try:
            return process_batch(entries, resolver, out_dir, settings, done, begin=begin)
        finally:
            os.unlink(note)


def lost_attempts(out_dir: str, task_key=None) -> List[tuple]:
    """The notes of task attempts whose worker was lost (:func:`dask_batch`), removed as they are
    read: ``(task key, worker address, index in the batch of the bag it was on, or None when it had
    begun none)``, of ``task_key`` only when given. Read when no attempt of the task can still run."""
    folder = os.path.join(out_dir, RUNNING_DIR)
    try:
        names = sorted(os.listdir(folder))
    except FileNotFoundError:
        return []
    out = []
    for name in names:
        key, sep, worker = name.rpartition("@")
        key, worker = urllib.parse.unquote(key), urllib.parse.unquote(worker)
        if not sep or (task_key is not None and key != str(task_key)):
            continue
        path = os.path.join(folder, name)
        try:
            with open(path, encoding="ascii") as fh:
                begun = fh.read().split()
            os.unlink(path)
        except FileNotFoundError:
            continue
        out.append((key, worker, int(begun[-1]) if begun and begun[-1].isdigit() else None))
    return out


# ---------------------------------------------------------------------------------------------
# the done-index and the summary

class DoneIndex:
    """``OUT/done-index.json``: per bag path, the key it is done under and its fragment."""

    def __init__(self, out_dir: str):
        self.path = os.path.join(out_dir, INDEX_FILE)
        self.bags: Dict[str, dict] = {}
        if os.path.exists(self.path):
            try:
                with open(self.path, encoding="utf-8") as fh:
                    doc = json.load(fh)
            except (OSError, json.JSONDecodeError) as exc:
                raise ValueError(f"{self.path}: cannot read the done-index ({exc}); remove it to redo every bag") \
                    from None
            if not isinstance(doc, dict) or doc.get("format") != INDEX_FORMAT or not isinstance(doc.get("bags"), dict):
                raise ValueError(f"{self.path}: not a done-index of this package (format {INDEX_FORMAT!r})")
            self.bags = doc["bags"]

    def key(self, bag: str) -> Optional[str]:
        e = self.bags.get(bag)
        return e.get("key") if e else None

    def record(self, res: BagResult, out_dir: str) -> None:
        """Take a finished result: an ok one replaces the bag's entry (and removes its old fragment
        when the new key wrote another); a failed or skipped one changes nothing."""
        if res.status != "ok":
            return
        old = self.bags.get(res.bag)
        if old and old.get("fragment") and old["fragment"] != res.fragment:
            try:
                os.unlink(os.path.join(out_dir, old["fragment"]))
            except FileNotFoundError:
                pass
        self.bags[res.bag] = {"key": res.key, "bag_sha256": res.bag_sha256, "record_id": res.record_id,
                              "serial": res.serial, "survey_start": res.survey_start, "stations": res.stations,
                              "fragment": res.fragment, "probe_forced": res.probe_forced,
                              "finished": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()}

    def save(self) -> None:
        atomic_write_text(self.path, json.dumps({"format": INDEX_FORMAT, "version": LAYOUT_VERSION,
                                                 "bags": self.bags}, indent=1, sort_keys=True) + "\n")


SUMMARY_COLUMNS = ("bag", "status", "reason", "serial", "survey_start", "record_id", "stations", "seconds",
                   "probe_forced", "bag_sha256", "fragment", "workers_lost")


@dataclass
class FleetSummary:
    """A run's outcome: one :class:`BagResult` per bag (in the order given), where it wrote, how it
    ran and how long it took."""

    results: List[BagResult]
    out_dir: str
    seconds: float = 0.0
    engine: str = ""
    bags_per_task: int = 1
    paths: Dict[str, str] = field(default_factory=dict)

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def failed(self) -> List[BagResult]:
        return [r for r in self.results if r.status == "failed"]

    @property
    def lost(self) -> List[BagResult]:
        """The bags that failed because their workers were lost (Dask gave up: KilledWorker)."""
        return [r for r in self.results if r.status == "failed" and r.reason.startswith(LOST_REASON)]

    @property
    def retried(self) -> List[BagResult]:
        """The bags done (or skipped) on a retry after a worker was lost while on them."""
        return [r for r in self.results if r.status != "failed" and r.workers_lost]

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(SUMMARY_COLUMNS)
        for r in self.results:
            d = asdict(r)
            d["seconds"] = f"{r.seconds:.3f}"
            d["workers_lost"] = " ".join(r.workers_lost)
            w.writerow([d[c] for c in SUMMARY_COLUMNS])
        return buf.getvalue()

    def lines(self) -> List[str]:
        """The summary as printed: one line per bag, then the totals."""
        out = []
        for r in self.results:
            what = (f"{r.stations} stations, record {r.record_id} ({r.serial}"
                    + (", FORCED onto this bag" if r.probe_forced else "") + f"), {r.seconds:.2f} s")
            line = f"{r.status:7s} {r.bag}: " + (what if r.status == "ok" else
                                                 f"{r.reason}" + (f" [{r.record_id}]" if r.record_id else ""))
            if r.workers_lost and r.status != "failed":
                line += f"; RETRIED: {_lost_words(r.workers_lost)} while on this bag"
            elif r.workers_lost and not r.reason.startswith(LOST_REASON):
                line += f"; retried after {_lost_words(r.workers_lost)} while on this bag"
            out.append(line)
        n = len(self.results)
        rate = n / self.seconds if self.seconds > 0 else float("inf")
        lost, retried = len(self.lost), len(self.retried)
        out.append(f"{n} bags: {self.count('ok')} ok, {self.count('skipped')} skipped (done), "
                   f"{self.count('failed')} failed" + (f" ({lost} lost with their workers)" if lost else "")
                   + (f", {retried} retried after a worker was lost" if retried else "")
                   + f"; {sum(r.stations for r in self.results if r.status == 'ok')} "
                   f"stations written in {self.seconds:.1f} s ({rate:.1f} bags/s, {self.engine}, "
                   f"{self.bags_per_task} bag(s) per task)")
        return out


def _lost_words(workers: Sequence[str]) -> str:
    return (f"worker {workers[0]} was lost" if len(workers) == 1 else
            f"{len(workers)} workers were lost ({', '.join(workers)})")


# ---------------------------------------------------------------------------------------------
# the run

class _RunLock:
    """``OUT/.lock`` held with ``flock`` for the run (released by the OS when the process ends)."""

    def __init__(self, out_dir: str):
        import fcntl

        self.path = os.path.join(out_dir, LOCK_FILE)
        self.fh = open(self.path, "a+")
        try:
            fcntl.flock(self.fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.fh.close()
            raise ValueError(f"{out_dir}: another fleet reprocess run is writing there (it holds {self.path})") \
                from None

    def release(self) -> None:
        self.fh.close()


def default_workers() -> int:
    """Worker processes of the local cluster by default: the cores this process may run on."""
    return len(os.sched_getaffinity(0))


def reprocess_fleet(bags, *, out_dir, registry_url: Optional[str] = None, resolver: Optional[Resolver] = None,
                    scheduler: Optional[str] = None, n_workers: Optional[int] = None, progress: bool = True,
                    force_probe: bool = False, bags_per_task: Optional[int] = None, settings: Optional[Settings] = None,
                    client=None, before_bag: Optional[Callable[[BagEntry], None]] = None) -> FleetSummary:
    """Reprocess ``bags`` (paths or :class:`manifest.BagEntry`) into the dataset in ``out_dir``.

    The record of each bag comes from the registry at ``registry_url`` or from ``resolver``
    (``resolver(serial, survey_time_utc) -> Calibration``, raising ``RegistryError`` when there
    is none; it must pickle, to travel to the workers). Engine: ``client`` (a
    ``distributed.Client`` the caller owns), else the scheduler at ``scheduler``
    (``tcp://HOST:PORT``), else a local cluster of ``n_workers`` processes (default: the cores;
    0: no Dask, the bags one after the other in this process). ``force_probe``: see
    :class:`Settings` (``settings`` gives them all). ``progress``: a progress bar of bags done on
    stderr. Writes ``OUT/stations/``, ``OUT/done-index.json`` and ``OUT/summary.csv``; returns the
    :class:`FleetSummary`. Raises ``ValueError`` for bad arguments, an unreadable done-index or a
    run already writing to ``out_dir``, :class:`output.OutputError` when ``out_dir`` cannot be written
    (its parent folder missing, read-only, a full disk: a new ``out_dir`` is then not left behind
    empty); a bag's own failure is in the summary, never raised.
    A Dask worker lost while on a bag is put on that bag (:attr:`BagResult.workers_lost`): retried
    and done, or failed when Dask gave up (:func:`_run_dask`). ``before_bag(entry)``: called before
    each bag where it runs (for tests: a worker that dies on a bag; it must pickle).
    """
    if (registry_url is None) == (resolver is None):
        raise ValueError("give either registry_url or resolver")
    if bags_per_task is not None and bags_per_task < 1:
        raise ValueError(f"bags_per_task must be at least 1, not {bags_per_task}")
    if n_workers is not None and n_workers < 0:
        raise ValueError(f"n_workers must be 0 (in this process) or more, not {n_workers}")
    settings = settings or Settings(force_probe=force_probe)
    entries = dedupe(b if isinstance(b, BagEntry) else entries_from_paths([b])[0] for b in bags)
    out_dir = os.path.abspath(os.fspath(out_dir))
    check_output(out_dir, folder=True)    # its folder missing, read-only or not ours: said before the work
    if resolver is None:
        resolver = RegistryResolver(registry_url)
        resolver.registry()          # created and migrated here, once, before workers open it
    made = not os.path.isdir(out_dir)
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise OutputError.from_os(out_dir, exc) from None
    lock = _RunLock(out_dir)
    try:
        index = DoneIndex(out_dir)
        results: Dict[str, BagResult] = {}
        t0 = time.perf_counter()
        last_flush = [time.monotonic()]

        def take(batch_results):
            for r in batch_results:
                results[r.bag] = r
                index.record(r, out_dir)
            if time.monotonic() - last_flush[0] > INDEX_FLUSH_S:
                index.save()
                last_flush[0] = time.monotonic()

        bar = progress_bar(len(entries), "bag", "bags", progress)
        try:
            if client is None and scheduler is None and n_workers == 0:
                engine = "in this process (no Dask)"
                bags_per_task = bags_per_task or 1
                begin = None if before_bag is None else (lambda i, entry: before_bag(entry))
                for batch in _batches(entries, bags_per_task):
                    take(process_batch(batch, resolver, out_dir, settings, [index.key(e.path) for e in batch], begin))
                    bar.update(len(batch))
            else:
                engine, bags_per_task, lost_on = _run_dask(entries, bags_per_task, resolver, out_dir, settings, index,
                                                           take, bar, client, scheduler, n_workers, before_bag)
                for bag, workers in lost_on.items():
                    results[bag].workers_lost = list(workers)
        finally:
            bar.close()
            index.save()
        summary = FleetSummary([results[e.path] for e in entries], out_dir, time.perf_counter() - t0, engine,
                               bags_per_task)
        summary.paths = {"dataset": os.path.join(out_dir, DATASET_DIR), "index": index.path,
                         "summary": os.path.join(out_dir, SUMMARY_FILE)}
        atomic_write_text(summary.paths["summary"], summary.to_csv())
        return summary
    except BaseException:
        if made:                     # a new folder a run wrote nothing into (a full disk, say) is not left
            _remove_if_nothing_written(out_dir)
        raise
    finally:
        lock.release()


def _remove_if_nothing_written(out_dir: str) -> None:
    """Remove the lock and the empty folders of ``out_dir``, and so ``out_dir`` itself when it holds
    nothing else (``rmdir`` removes only empty folders: no file of a run is ever removed)."""
    try:
        os.unlink(os.path.join(out_dir, LOCK_FILE))
    except OSError:
        return
    for folder, _, _ in os.walk(out_dir, topdown=False):
        try:
            os.rmdir(folder)
        except OSError:
            pass


def local_cluster(n_workers: int):
    """A local Dask cluster of ``n_workers`` processes of one thread each, on loopback, without
    the dashboard and without the workers' statistical profiler: sampling the task thread's stack
    every 10 ms costs this Python-heavy pipeline 2–3× its time (``docs/fleet.md``). Workers of a
    cluster started elsewhere: ``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False`` in their
    environment does the same."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.worker.profile.enabled": False}):
        return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                            dashboard_address=None)


def auto_bags_per_task(n_bags: int, n_workers: int) -> int:
    """The default task size: as many bags as keep at least :data:`TASKS_PER_WORKER` tasks per
    worker, at most :data:`MAX_BAGS_PER_TASK`."""
    return max(1, min(MAX_BAGS_PER_TASK, n_bags // (TASKS_PER_WORKER * max(1, n_workers))))


def _batches(entries, size):
    return [entries[i:i + size] for i in range(0, len(entries), size)]


def _outcome(fut) -> tuple:
    """``(result, None)`` of a completed task, or ``(None, exception)``.  A task that finished
    may still fail when its result is fetched: the result lives in its worker's memory, and a
    worker lost before the client fetched it (a batch-mate's bag killed it) makes Dask run the task
    again — and give up with ``KilledWorker`` if more workers die with it.  That is the task's
    outcome, handled as any other, not an exception out of the run."""
    if fut.status != "finished":
        return None, fut.exception()
    try:
        return fut.result(), None
    except Exception as exc:   # noqa: BLE001 — any failure of the task is its outcome (the caller sorts them)
        return None, exc


def _run_dask(entries, bags_per_task, resolver, out_dir, settings, index, take, bar, client, scheduler, n_workers,
              before_bag):
    """Submit one task per batch (:func:`dask_batch`) and take results as they complete; a task that
    errors fails its bags with the reason and the others go on.

    A worker lost while on a task — its process died: out of memory, a crash in native code, a kill —
    is retried by Dask on another worker until ``distributed.scheduler.allowed-failures`` + 1 workers
    (4 by default) were lost with the task on them, then Dask gives up (``KilledWorker``). Dask
    counts the workers lost while the task only waited its turn on them too; the notes the tasks
    leave (:func:`lost_attempts`) say which bag each lost worker was running. So when Dask gives up,
    a bag that allowed-failures + 1 workers, over all its tasks, were lost on fails
    (:data:`LOST_REASON`, its workers named), and the rest of its batch is submitted again as a new
    task: a failed bag never stops the others, and a bag is not given up for workers its batch-mates
    or its neighbours in a worker's queue killed (it may then cost more workers than the limit, up to
    twice).  A batch given up before any of its bags began is submitted again once.  Returns the
    engine's name, the task size used, and the workers lost while on each bag (path → addresses)."""
    from distributed import Client, as_completed
    from distributed.scheduler import KilledWorker

    cluster = own = None
    try:
        if client is not None:
            engine = f"Dask client {client.scheduler.address}"
        elif scheduler is not None:
            client = own = Client(scheduler)
            engine = f"Dask cluster {scheduler}"
        else:
            n = n_workers or default_workers()
            cluster = local_cluster(n)
            client = own = Client(cluster)
            engine = f"local Dask cluster, {n} worker process(es)"
        if bags_per_task is None:
            bags_per_task = auto_bags_per_task(len(entries), len(client.nthreads()))
        futures, batches = {}, {}      # future -> (batch, submitted again blind); task key -> batch
        lost_on: Dict[str, List[str]] = {}
        running = as_completed()

        def submit(batch, blind=False):
            fut = client.submit(dask_batch, batch, resolver, out_dir, settings, [index.key(e.path) for e in batch],
                                before_bag, pure=False)
            futures[fut], batches[fut.key] = (batch, blind), batch
            running.add(fut)

        def note_losses(key=None):
            """Put the lost attempts' workers on their bags; the task keys they were of."""
            keys = set()
            for k, worker, i in lost_attempts(out_dir, key):
                if k in batches and i is not None:
                    lost_on.setdefault(batches[k][i].path, []).append(worker)
                    keys.add(k)
            return keys

        for batch in _batches(entries, bags_per_task):
            submit(batch)
        for fut in running:
            batch, blind = futures.pop(fut)
            result, exc = _outcome(fut)
            if exc is None:
                take(result)
                bar.update(len(batch))
                continue
            if not isinstance(exc, KilledWorker):
                take([BagResult(bag=e.path, status="failed", reason=f"task failed: {type(exc).__name__}: {exc}")
                      for e in batch])
                bar.update(len(batch))
                continue
            began = bool(note_losses(fut.key))
            limit = exc.allowed_failures + 1
            if began or not blind:
                gone = [e for e in batch if len(lost_on.get(e.path, ())) >= limit]
                rest = [e for e in batch if e not in gone]
                reason = (f"{LOST_REASON}: {{}} while on this bag, given up after {limit} "
                          f"(distributed.scheduler.allowed-failures {exc.allowed_failures}, + 1); a worker process "
                          "that dies ran out of memory, crashed in native code or was killed: see the workers' logs")
                failed = [BagResult(bag=e.path, status="failed", workers_lost=list(lost_on[e.path]),
                                    reason=reason.format(_lost_words(lost_on[e.path]))) for e in gone]
            else:       # given up twice before any of its bags began: not for ever
                failed = [BagResult(bag=e.path, status="failed", reason=f"{LOST_REASON}s before it began: Dask gave "
                                    f"up on its task twice ({limit} workers lost with it each time)") for e in batch]
                rest = []
            take(failed)
            bar.update(len(failed))
            if rest:
                submit(rest, blind=not began)
        note_losses()         # attempts lost, then retried by Dask and done
        return engine, bags_per_task, lost_on
    finally:
        try:
            os.rmdir(os.path.join(out_dir, RUNNING_DIR))
        except OSError:      # absent, or a note of an attempt that still runs somewhere
            pass
        if own is not None:
            own.close()
        if cluster is not None:
            cluster.close()

"""Probe logs: the CSV format, row validation, and segmentation into static stations.

CSV format (columns by name; this is their canonical order)::

    t_s,ax,ay,az,mx,my,mz,temp_c,pose,ref_drift_deg,ref_azimuth_deg,ref_toolface_deg

``t_s`` and the six sensor columns are required; the others may be absent (read as empty: not
given) and all may come in any order (:func:`canonical_text` rewrites such a log in this layout,
row for row); an unknown or repeated column is refused naming line 1.

* ``ax..az``: accelerometer as REP-145 *specific force* in m/s², uncalibrated (a resting probe
  reads -gravity).  Converted once, where the samples enter the static detector
  (:class:`streaming.StaticDetector`), to the seed paper's gravity vector (down positive).
* ``mx..mz``: magnetometer, uncalibrated, in nT — or in the unit the reader is told
  (``mag_unit``: nT, uT, mT, T, G, mG), converted to nT when read.
* ``temp_c``: probe temperature, °C; empty (or ``nan``) when the probe has no sensor.
* ``pose``: 1..12 while the probe sits in that pose of the paper's Table 1, empty otherwise.
* optional columns after these, in this order: a turntable log (the patent's procedure,
  :mod:`turntable`) has ``mount`` (``xy``, ``xz`` or ``yz``: the two marked axes in the table
  plane) and ``table_deg`` (the table angle the operator set, empty when not recorded), on the
  static rows; a survey log may have ``md_m``, the measured depth of the probe (m, empty where not
  known) — the stations' depth, from which the trajectory follows (:mod:`trajectory`).
* ``ref_*``: the stand's set orientation where known, empty otherwise.  Rows recorded while the
  probe moves have all four of ``pose`` and ``ref_*`` empty.  A reference is used for what it
  defines: a vertical pose gives drift and toolface but no azimuth (the azimuth of a vertical
  tool is undefined; the toolface is then the rotation about the vertical, as for azimuth 0).

Stations are found by the same static detector as the live nodes (:func:`segment_stations`),
with thresholds from the noise the data show; the labels of a station's rows name it.  Unusable
rows are rejected with a message naming the row and the reason; the rest is kept.  A ``.gz``
file is read decompressed.

Two readers give the same log and the same rejections (:data:`ENGINES`): the default splits and
converts the columns with pyarrow and checks every row at once with numpy (about 0.3 µs a row
against 6–9 µs; no Python object per row), handing only the rows that fail a check to the
per-row code; ``engine="rows"`` runs the per-row code on every row, the reference it is tested
against (``test/io/test_probelog_engines.py``; figures in ``docs/benchmarks.md``).
"""
from __future__ import annotations

import csv
import gzip
import io
import math
import mmap
import os
from collections import Counter
from dataclasses import dataclass

import numpy as np

from ..core.deps import installed, require
from ..core.output import atomic_write_text
from ..core.frames import STANDARD_GRAVITY, gravity_from_specific_force

HEADER = ["t_s", "ax", "ay", "az", "mx", "my", "mz", "temp_c", "pose",
          "ref_drift_deg", "ref_azimuth_deg", "ref_toolface_deg"]
#: Magnetometer units a log may be written in, as nT per unit.
MAG_UNITS = {"nT": 1.0, "uT": 1e3, "mT": 1e6, "T": 1e9, "G": 1e5, "mG": 1e2}
#: The turntable log's two extra columns (after :data:`HEADER`).
TURNTABLE_COLUMNS = ["mount", "table_deg"]
#: The optional columns after :data:`HEADER`, in their order (any of them may be left out).
OPTIONAL_COLUMNS = TURNTABLE_COLUMNS + ["md_m"]
#: The columns every log has; the rest of :data:`HEADER` may be absent (read as empty: not given).
REQUIRED_COLUMNS = HEADER[:7]
MOUNT_NAMES = ("xy", "xz", "yz")
UNIT_NAMES = {"nT": "nanotesla", "uT": "microtesla", "mT": "millitesla", "T": "tesla", "G": "gauss",
              "mG": "milligauss"}


@dataclass
class ProbeLog:
    """Samples of one probe log.

    Attributes: ``t_s`` (N,) s; ``acc`` (N, 3) REP-145 specific force, m/s²; ``mag`` (N, 3) nT;
    ``temp_c`` (N,) °C; ``pose`` (N,) int, 0 = none; ``ref`` (N, 3) deg (drift, azimuth,
    toolface), NaN where unknown; ``row`` (N,) int, the data row of the file each sample came from
    (1-based; rows rejected by the reader are missing), for messages that point into the file;
    a turntable log's ``mount`` (N,) str ('' where none) and ``table_deg`` (N,) deg (NaN where
    none); ``md_m`` (N,) the measured depth (m, NaN where not known); ``station`` (N,) the planned
    station a simulated row belongs to (-1: moving; not written).
    """

    t_s: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    temp_c: np.ndarray
    pose: np.ndarray
    ref: np.ndarray
    row: np.ndarray = None
    mount: np.ndarray = None
    table_deg: np.ndarray = None
    station: np.ndarray = None
    md_m: np.ndarray = None

    def __post_init__(self):
        n = len(self.t_s)
        if self.row is None:
            self.row = np.arange(1, n + 1)
        if self.mount is None:
            self.mount = np.full(n, "", dtype=object)
        if self.table_deg is None:
            self.table_deg = np.full(n, np.nan)
        if self.station is None:
            self.station = np.full(n, -1)
        if self.md_m is None:
            self.md_m = np.full(n, np.nan)

    @property
    def gravity(self) -> np.ndarray:
        """(N, 3) the gravity vector (down positive, m/s²) of the rows: ``-acc``
        (:func:`frames.gravity_from_specific_force`), what every core API takes.  A new array at
        each access (``acc`` is the record as read and written)."""
        return gravity_from_specific_force(self.acc)

    @property
    def is_turntable(self) -> bool:
        return bool(np.any(self.mount != "") or np.any(np.isfinite(self.table_deg)))

    def __len__(self):
        return len(self.t_s)

    @classmethod
    def empty(cls):
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                   np.zeros(0, dtype=int), np.zeros((0, 3)))

    @classmethod
    def concatenate(cls, logs):
        """One log after the other (rows numbered on through the whole)."""
        logs = list(logs)
        out = cls(*(np.concatenate([getattr(lg, f) for lg in logs]) for f in
                    ("t_s", "acc", "mag", "temp_c", "pose", "ref")))
        for name in ("mount", "table_deg", "md_m"):
            if logs:
                setattr(out, name, np.concatenate([getattr(lg, name) for lg in logs]))
        return out


@dataclass(frozen=True)
class Rejection:
    """A row that was not used: ``row`` counts data rows from 1; ``line`` is the file line."""

    row: int
    line: int
    reason: str

    def __str__(self):
        return f"row {self.row} (line {self.line}): {self.reason}"


@dataclass(frozen=True)
class Limits:
    """Plausibility limits applied to every row.

    ``acc_full_scale`` (m/s²) and ``mag_full_scale`` (nT): an axis at or beyond 99.9 % of full
    scale is saturated.  Totals outside the ranges are physically implausible for a probe on the
    Earth's surface or in a borehole.
    """

    acc_full_scale: float = 2.0 * STANDARD_GRAVITY
    mag_full_scale: float = 100000.0
    acc_total_range: tuple = (0.5 * STANDARD_GRAVITY, 1.5 * STANDARD_GRAVITY)
    mag_total_range: tuple = (5000.0, 100000.0)
    temp_range_c: tuple = (-40.0, 200.0)


def check_sample(acc, mag, temp, limits: Limits):
    """Reason a sample is unusable (saturated, implausible totals or units), or None.

    ``acc`` REP-145 specific force m/s², ``mag`` nT, ``temp`` °C or NaN.  Shared by the CSV
    reader, offline reprocessing and the live nodes, so a sample is judged alike everywhere."""
    for name, v in zip(("ax", "ay", "az"), acc):
        if abs(v) >= 0.999 * limits.acc_full_scale:
            return f"{name}={v:g} m/s² is saturated (full scale ±{limits.acc_full_scale:g})"
    for name, v in zip(("mx", "my", "mz"), mag):
        if abs(v) >= 0.999 * limits.mag_full_scale:
            return f"{name}={v:g} nT is saturated (full scale ±{limits.mag_full_scale:g})"
    a = math.sqrt(sum(x * x for x in acc))
    m = math.sqrt(sum(x * x for x in mag))
    if not limits.acc_total_range[0] <= a <= limits.acc_total_range[1]:
        return (f"total acceleration {a:.4g} m/s² is implausible (expected "
                f"{limits.acc_total_range[0]:.3g}..{limits.acc_total_range[1]:.3g}; units must be m/s²)")
    if 0 < m < limits.mag_total_range[0]:
        unit = _unit_guess(m)
        if unit:
            return (f"total field {m:.3g} nT is implausible — the magnetometer columns look like {UNIT_NAMES[unit]}: "
                    f"give the unit (--mag-unit {unit}) or write nT")
    if not limits.mag_total_range[0] <= m <= limits.mag_total_range[1]:
        return (f"total field {m:.4g} nT is implausible (expected "
                f"{limits.mag_total_range[0]:g}..{limits.mag_total_range[1]:g} nT)")
    if math.isfinite(temp) and not limits.temp_range_c[0] <= temp <= limits.temp_range_c[1]:
        return f"temp_c={temp:g} °C is implausible"
    return None


def _unit_guess(total: float):
    """The unit in which ``total`` (read as nT) would be an Earth field of 20 000–70 000 nT."""
    for unit, scale in MAG_UNITS.items():
        if unit != "nT" and 20000.0 <= total * scale <= 70000.0:
            return unit
    return None


#: The readers of :func:`parse_csv` and :func:`read_csv`.  ``"arrow"`` splits and converts the
#: columns with pyarrow (the ``fast`` extra) and checks them with numpy; ``"rows"`` is one Python
#: pass per row, the reference; ``"auto"`` (the default) is arrow when pyarrow is installed, else
#: rows.  Both give the same log and the same rejections, message for message: the arrow reader
#: hands the rows its vectorised checks do not pass (rare) to the same per-row code.
ENGINES = ("auto", "arrow", "rows")


def parse_csv(text: str, limits: Limits = Limits(), source: str = "<csv>", mag_unit: str = "nT",
              engine: str = "auto"):
    """Parse probe-log CSV text.  Returns ``(ProbeLog, [Rejection, ...])``.

    ``mag_unit``: the unit of the magnetometer columns (a key of :data:`MAG_UNITS`), converted to
    nT here.  ``engine``: one of :data:`ENGINES` (the same results; ``"rows"`` is the slow
    reference).  Raises ``ValueError`` only when the file as a whole is unusable (wrong header,
    no data, unknown unit).
    """
    engine = _check_engine(engine)
    text = canonical_text(text, source) or text
    if engine == "arrow":
        try:
            data = text.encode("utf-8")
        except UnicodeEncodeError:       # lone surrogates: text no file read as UTF-8 can hold
            pass
        else:
            return _parse_arrow(data, limits, source, mag_unit)
    return _parse_rows(text, limits, source, mag_unit)


def read_csv(path, limits: Limits = Limits(), mag_unit: str = "nT", engine: str = "auto"):
    """Read a probe-log CSV file (``.gz``: compressed).  Returns ``(ProbeLog, [Rejection, ...])``.

    ``engine``: as for :func:`parse_csv`."""
    engine = _check_engine(engine)
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rt", encoding="utf-8", errors="replace", newline="") as fh:
        first = fh.readline()
    if first.strip() and not _canonical_header(first):
        # columns in another order, or optional ones absent: rewritten in the canonical layout
        with opener(path, "rt", encoding="utf-8") as fh:
            return parse_csv(fh.read(), limits, str(path), mag_unit, engine)
    if engine == "rows":
        with opener(path, "rt", encoding="utf-8") as fh:
            return _parse_rows(fh.read(), limits, str(path), mag_unit)
    with opener(path, "rb") as fh:
        if opener is gzip.open or not os.fstat(fh.fileno()).st_size:
            data = fh.read()
        else:                    # mapped, not copied: the page cache's pages are read in place
            data = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    return _parse_arrow(data, limits, str(path), mag_unit)


def _check_engine(engine) -> str:
    """The reader ``engine`` names (``auto`` resolved); raises ValueError for an unknown one,
    :class:`deps.MissingDependency` for ``arrow`` without pyarrow."""
    if engine not in ENGINES:
        raise ValueError(f"probe-log reader {engine!r} unknown (one of {', '.join(ENGINES)})")
    if engine == "auto":
        return "arrow" if installed("pyarrow") else "rows"
    if engine == "arrow":
        require("pyarrow", "fast", "the column-wise probe-log reader")
    return engine


def _mag_scale(mag_unit, source) -> float:
    if mag_unit not in MAG_UNITS:
        raise ValueError(f"{source}: magnetometer unit {mag_unit!r} unknown (one of {', '.join(MAG_UNITS)})")
    return MAG_UNITS[mag_unit]


@dataclass(frozen=True)
class _Layout:
    """The columns a header line gives: their ``names``; whether the turntable columns are there
    (fields 12 and 13); the index of ``md_m`` (None without it)."""

    names: tuple
    turntable: bool
    depth_col: int | None

    @property
    def n_fields(self) -> int:
        return len(self.names)


def _layout(first_line: str, source) -> _Layout:
    """The layout of a log from its first line, or ``ValueError`` naming line 1."""
    header = [h.strip() for h in first_line.lstrip("\ufeff").split(",")]
    extra = header[len(HEADER):]
    if header[:len(HEADER)] != HEADER or extra != [c for c in OPTIONAL_COLUMNS if c in extra]:
        raise ValueError(f"{source}: line 1: header must be exactly {','.join(HEADER)!r}, optionally followed by "
                         f"any of {','.join(OPTIONAL_COLUMNS)!r} in that order, got {first_line!r}")
    turntable = "mount" in extra
    if turntable != ("table_deg" in extra):
        raise ValueError(f"{source}: line 1: a turntable log has both 'mount' and 'table_deg' columns")
    return _Layout(tuple(header), turntable, header.index("md_m") if "md_m" in extra else None)


def _canonical_header(first_line: str) -> bool:
    try:
        _layout(first_line, "")
    except ValueError:
        return False
    return True


def canonical_text(text: str, source: str = "<csv>"):
    """A log whose header names known columns in another order, or leaves optional ones out (a
    turntable rig's ``t_s,ax,ay,az,mx,my,mz,temp_c,mount,table_deg``): its text in the canonical
    layout — :data:`HEADER` then the optional columns it has, absent ones empty (not given), the
    same rows on the same lines (a rejection names the row it names in the file).  None when the
    header is canonical already.  ``ValueError`` naming line 1 when a required column
    (:data:`REQUIRED_COLUMNS`) is missing, a column is unknown or given twice."""
    end = text.find("\n")
    first = text if end < 0 else text[:end]     # the header alone: a canonical log is not copied
    if not first.strip() or _canonical_header(first):
        return None
    rest = "" if end < 0 else text[end + 1:]
    header = [h.strip() for h in first.lstrip("\ufeff").rstrip("\r").split(",")]
    known = HEADER + OPTIONAL_COLUMNS
    unknown = [h for h in header if h not in known]
    twice = sorted({h for h in header if header.count(h) > 1})
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if unknown or twice or missing:
        why = "; ".join(part for part in (
            f"missing {', '.join(missing)}" if missing else "",
            f"unknown {', '.join(map(repr, unknown))}" if unknown else "",
            f"given twice: {', '.join(twice)}" if twice else "") if part)
        raise ValueError(f"{source}: line 1: the columns are {','.join(REQUIRED_COLUMNS)} and any of "
                         f"{','.join(HEADER[7:] + OPTIONAL_COLUMNS)}, in any order ({why})")
    if ("mount" in header) != ("table_deg" in header):
        raise ValueError(f"{source}: line 1: a turntable log has both 'mount' and 'table_deg' columns")
    columns = HEADER + [c for c in OPTIONAL_COLUMNS if c in header]
    where = [header.index(c) if c in header else None for c in columns]
    out = io.StringIO()
    out.write(",".join(columns) + "\n")
    writer = csv.writer(out, lineterminator="\n")
    lines = rest.split("\n")
    if lines and lines[-1] == "":
        lines.pop()                          # the newline that ends the file
    for line in lines:
        fields = next(csv.reader([line]), [])
        if len(fields) != len(header):
            out.write(line + "\n")          # blank, or a row of another length: rejected as it is
            continue
        writer.writerow(["" if k is None else fields[k] for k in where])
    text_out = out.getvalue()
    return text_out if text.endswith("\n") else text_out[:-1]


def _empty_file(source):
    return ValueError(f"{source}: empty file (expected header {','.join(HEADER)})")


def _no_rows(source, rejections):
    detail = f"; first rejection: {rejections[0]}" if rejections else ""
    return ValueError(f"{source}: no usable rows{detail}")


def _nonmonotonic(t, last_t) -> str:
    return f"time t_s={t:g} does not increase (previous {last_t:g}): non-monotonic timestamp"


#: The values of a row refused before its time check (see :func:`_parse_row`): none.
_NO_VALUES = (math.nan, (), (), math.nan, 0, (), "", math.nan, math.nan)


def _parse_row(fields, layout: _Layout, mag_scale: float, limits: Limits):
    """One row's fields (as ``csv.reader`` splits its line), or None for a blank row:
    ``(before, after, t, acc, mag, temp, pose, ref, mount, table, md)`` — why the row is unusable,
    ``before``: a reason found before the time check (field count, numbers, the sample's
    plausibility), ``after``: one found after it (labels, turntable columns, depth); then its
    values (t_s, s; acc, m/s²; mag, nT; temp_c, °C; pose; ref, deg; mount; table_deg, deg; md_m,
    m).  The time check needs the rows kept before it, so the callers make it.  The format's
    per-row rules, in one place for both readers (a plain tuple: the row reader's hot path)."""
    if not fields or all(not f.strip() for f in fields):
        return None
    if len(fields) != layout.n_fields:
        return (f"{len(fields)} fields, expected {layout.n_fields}", None) + _NO_VALUES
    try:
        # an empty temp_c is an unknown temperature (a probe without a sensor), not a bad row
        nums = [float(f) for f in fields[:7]] + [float(fields[7]) if fields[7].strip() else math.nan]
    except ValueError:
        bad = next(n for n, f in zip(HEADER, fields) if not _is_float(f))
        return (f"{bad}={fields[HEADER.index(bad)]!r} is not a number", None) + _NO_VALUES
    nonfinite = [n for n, v in zip(HEADER, nums) if not math.isfinite(v)
                 and not (n == "temp_c" and math.isnan(v))]
    if nonfinite:
        return (f"{', '.join(nonfinite)} not finite (NaN/inf)", None) + _NO_VALUES
    t, acc, mag, temp = nums[0], nums[1:4], [v * mag_scale for v in nums[4:7]], nums[7]
    reason = check_sample(acc, mag, temp, limits)
    if reason is not None:
        return (reason, None) + _NO_VALUES
    pose, ref, reason = _parse_labels(fields[8:12])
    mount, table = "", math.nan
    if reason is None and layout.turntable:
        mount, table, reason = _parse_turntable(fields[12:14])
    md = math.nan
    col = layout.depth_col
    if reason is None and col is not None and fields[col].strip():
        try:
            md = float(fields[col])
        except ValueError:
            reason = f"md_m={fields[col]!r} is not a number"
        else:
            if not math.isfinite(md):
                reason, md = "md_m not finite", math.nan
    return None, reason, t, acc, mag, temp, pose, ref or (math.nan,) * 3, mount, table, md


def _parse_rows(text: str, limits, source, mag_unit):
    """The row reader: ``csv.reader`` and :func:`_parse_row` on every row, one pass."""
    mag_scale = _mag_scale(mag_unit, source)
    lines = text.splitlines()
    if not lines:
        raise _empty_file(source)
    layout = _layout(lines[0], source)
    rows, rejections, mounts, tables, depths = [], [], [], [], []
    last_t = -math.inf
    reader = csv.reader(io.StringIO("\n".join(lines[1:])))
    for k, fields in enumerate(reader, start=1):
        r = _parse_row(fields, layout, mag_scale, limits)
        if r is None:
            continue
        reason, after, t, acc, mag, temp, pose, ref, mount, table, md = r
        if reason is None and t <= last_t:
            reason = _nonmonotonic(t, last_t)
        if reason is None:
            reason = after
        if reason is not None:
            rejections.append(Rejection(k, k + 1, reason))
            continue
        last_t = t
        rows.append((t, *acc, *mag, temp, pose, *ref, k))
        mounts.append(mount)
        tables.append(table)
        depths.append(md)
    if not rows:
        raise _no_rows(source, rejections)
    a = np.array(rows, dtype=float)
    log = ProbeLog(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7], a[:, 8].astype(int), a[:, 9:12], a[:, 12].astype(int),
                   mount=np.array(mounts, dtype=object), table_deg=np.array(tables, dtype=float),
                   md_m=np.array(depths, dtype=float))
    return log, rejections


# ---- the vectorised reader ---------------------------------------------------------------------
#: Characters with which the row reader splits a file differently from pyarrow's CSV parser:
#: quotes (``csv`` unquotes them, and a quoted field may span lines) and the line breaks of
#: ``str.splitlines`` other than \n and \r.  A file holding any of them is read row by row.  No
#: need to look for them: a field holding one is no number and no mount name, so its row goes
#: to the row code, which looks at its line.
_ROWS_ONLY_CHARS = ('"', "\x0b", "\x0c", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029")
#: Numbers that pyarrow's cast and Python's ``float`` both read, to the same double (both round
#: correctly).  pyarrow's CSV parser also reads ``nan(...)``, which ``float`` refuses: a file
#: with a "(" has its numeric columns read as text and checked against this.
_PLAIN_NUMBER = r"^[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?$|^[+-]?(?i:inf|infinity|nan)$"
_MOUNTS = ("",) + MOUNT_NAMES


class _RowsOnly(Exception):
    """pyarrow cannot split this file as ``csv.reader`` would: read it row by row."""


def _parse_arrow(data, limits, source, mag_unit):
    """The vectorised reader (``data``: the file's bytes, UTF-8, as ``bytes`` or a read-only
    ``mmap``): :func:`_parse_rows`' results.

    pyarrow's CSV parser splits the rows of the header's columns and converts the numeric columns
    to float64 (exactly, as ``float`` does); numpy applies every per-row check to all rows at
    once.  A row that fails any check, or that pyarrow cannot split into the header's columns, is
    handed with its line to :func:`_parse_row`, which gives the reason (or the values of a row
    that is only written unusually, e.g. " xy" for a mount).  The time check — each row after
    the last row kept — is a running maximum: a row that would be kept but for its time never
    raises the maximum, so the maximum over the rows passing the other checks is the last time
    kept.  UTF-8 is checked where the bytes are read: by pyarrow (an invalid sequence in a field
    sends the file to the row reader, whose decoding raises the ``UnicodeDecodeError``), in the
    header and in the lines the row code reads.  Memory: the bytes (mapped, for a file),
    pyarrow's columns and the log's arrays; no Python object per row.
    """
    mag_scale = _mag_scale(mag_unit, source)

    def row_reader():
        return _parse_rows(bytes(data).decode("utf-8"), limits, source, mag_unit)

    if not data:
        raise _empty_file(source)
    end = data.find(b"\n")
    end = len(data) if end < 0 else end
    cr = data.find(b"\r", 0, end)
    end = end if cr < 0 else cr
    first = data[:end].decode("utf-8")
    if any(c in first for c in _ROWS_ONLY_CHARS):
        return row_reader()
    layout = _layout(first, source)
    body = memoryview(data)[end + (2 if data[end:end + 2] == b"\r\n" else 1):]
    if not len(body):
        raise _no_rows(source, [])
    try:
        cols, invalid = _arrow_columns(body, layout, numbers_as_text=data.find(b"(") >= 0)
    except _RowsOnly:
        return row_reader()
    n = len(cols["t_s"])
    for c in ("mx", "my", "mz"):
        cols[c] *= mag_scale                     # nT, as float() * scale does row by row
    ok = _checks(cols, limits)                 # kept, unless the time goes back (below)
    late = []                                  # refused only after the time check: (row, data row, reason)
    # pyarrow's row j is line j + 2 of the file, but for the rows pyarrow set aside (a wrong number
    # of fields: always refused, so they neither enter the log nor move the time check)
    set_aside = np.asarray(invalid, dtype=np.int64) - 1        # their 0-based data rows, ascending
    shift = set_aside - np.arange(len(set_aside))              # pyarrow rows before each of them

    def data_row(j):                                           # 0-based data row of pyarrow's row j
        return j + np.searchsorted(shift, j, side="right") if len(shift) else j

    reasons = {}                                               # 0-based data row → reason
    slow = np.flatnonzero(~ok)
    lines = np.union1d(data_row(slow), set_aside)
    at = dict(zip(data_row(slow).tolist(), slow.tolist()))     # data row → pyarrow row
    for k0, line in zip(lines.tolist(), _lines(body, lines, len(lines) and data.find(b"\r") >= 0)):
        if any(c in line for c in _ROWS_ONLY_CHARS):
            return row_reader()
        r = _parse_row(next(csv.reader([line]), []), layout, mag_scale, limits)
        j = at.get(k0)
        if r is None:
            continue
        before, after, t, acc, mag, temp, pose, ref, mount, table, md = r
        if before is not None:
            reasons[k0] = before
            continue
        if j is None:        # a line pyarrow set aside that the row code takes: they split it differently
            return row_reader()
        # a row the vectorised checks refused but the row code takes as written (" xy"), or refuses
        # only after its time was checked: its values
        cols["t_s"][j], cols["temp_c"][j], cols["pose"][j] = t, temp, pose
        for c, v in zip(("ax", "ay", "az", "mx", "my", "mz", *HEADER[9:12]), (*acc, *mag, *ref)):
            cols[c][j] = v
        if layout.turntable:
            cols["mount"][j], cols["table_deg"][j] = _MOUNTS.index(mount), table
        if layout.depth_col is not None:
            cols["md_m"][j] = md
        if after is None:
            ok[j] = True
        else:
            late.append((j, k0, after))
    t = cols["t_s"]
    last = np.where(ok, t, -np.inf)            # the last time kept up to each row: a running maximum
    np.maximum.accumulate(last, out=last)
    back = np.zeros(n, dtype=bool)
    np.less_equal(t[1:], last[:-1], out=back[1:])
    back &= ok
    for j in np.flatnonzero(back).tolist():
        reasons[int(data_row(j))] = _nonmonotonic(float(t[j]), float(last[j - 1]))
    ok[back] = False
    for j, k0, after in late:
        reasons[k0] = _nonmonotonic(float(t[j]), float(last[j - 1])) if j and t[j] <= last[j - 1] else after
    rejections = [Rejection(k0 + 1, k0 + 2, reasons[k0]) for k0 in sorted(reasons)]
    kept = np.flatnonzero(ok)
    if not len(kept):
        raise _no_rows(source, rejections)
    m = len(kept)

    def triad(names):                          # (m, 3), column-major: one contiguous copy per column
        out = np.empty((3, m))
        for i, c in enumerate(names):
            out[i] = take(c)
        return out.T

    def take(name):                            # the kept rows of a column, which is then let go
        return cols.pop(name)[ok]

    pose = take("pose")
    pose[np.isnan(pose)] = 0
    log = ProbeLog(take("t_s"), triad(("ax", "ay", "az")), triad(("mx", "my", "mz")), take("temp_c"),
                   pose.astype(np.int64), triad(HEADER[9:12]), data_row(kept) + 1)
    if layout.turntable:
        log.mount = np.array(_MOUNTS, dtype=object)[take("mount")]
        log.table_deg = take("table_deg")
    if layout.depth_col is not None:
        log.md_m = take("md_m")
    return log, rejections


def _arrow_columns(body, layout: _Layout, numbers_as_text: bool):
    """The columns of the data rows by pyarrow: ``({name: array}, invalid)``.

    Numeric columns come as float64 (NaN where empty) with a ``<name>_null`` mask for the
    optional ones; ``mount`` as indices into :data:`_MOUNTS` (-1: anything else); ``_text`` marks
    rows holding a field not of the plain form pyarrow and ``float`` read alike (their line is
    checked row by row).  ``invalid``: the line numbers (1 = first data row) of rows without the
    header's number of fields.  Columns the file does not have are left out.
    """
    import pyarrow as pa
    from pyarrow import compute as pc
    from pyarrow import csv as pacsv

    names = list(layout.names)
    invalid = []

    def on_invalid(row):
        if row.number is None:
            raise _RowsOnly()
        invalid.append(row.number)
        return "skip"

    def read(types):
        invalid.clear()
        return pacsv.read_csv(
            pa.py_buffer(body),
            read_options=pacsv.ReadOptions(use_threads=False, column_names=names),   # threads: no row numbers
            parse_options=pacsv.ParseOptions(quote_char=False, ignore_empty_lines=False,
                                              invalid_row_handler=on_invalid),
            convert_options=pacsv.ConvertOptions(column_types=types, null_values=[""], strings_can_be_null=True))

    numeric = [c for c in names if c != "mount"]
    table = None
    if not numbers_as_text:
        try:
            table = read({c: (pa.string() if c == "mount" else pa.float64()) for c in names})
        except pa.ArrowInvalid:              # text pyarrow does not read as a number: see below
            table = None
    text = None
    if table is None:
        try:
            table = read({c: pa.string() for c in names})
        except pa.ArrowInvalid as exc:
            raise _RowsOnly() from exc
        text = np.zeros(table.num_rows, dtype=bool)
    n = table.num_rows
    cols = {}
    for c in numeric:
        col = table.column(c)
        table = table.drop_columns([c])      # its text or parsed chunks go once the array is made
        if text is not None:
            plain = pc.fill_null(pc.match_substring_regex(col, _PLAIN_NUMBER), True)
            text |= ~_numpy(plain)
            col = pc.cast(pc.if_else(plain, col, pa.scalar(None, pa.string())), pa.float64())
        cols[c] = _numpy(col)
        if c in ("pose", "table_deg", "md_m") or c in HEADER[9:12]:
            cols[c + "_null"] = _numpy(col.is_null())
    if "mount" in names:
        col = pc.fill_null(table.column("mount"), "")
        cols["mount"] = _numpy(pc.fill_null(pc.index_in(col, value_set=pa.array(_MOUNTS)), -1))
    cols["_text"] = text if text is not None else np.zeros(n, dtype=bool)
    return cols, invalid


def _checks(cols, limits: Limits):
    """Rows (of :func:`_arrow_columns`, magnetometer in nT) that pass every check of
    :func:`_parse_row` as written plainly — the rest go through it.  Row for row the same
    arithmetic as :func:`check_sample` (IEEE double: the same sums of squares in the same order, a
    correctly rounded sqrt).  Computed in place, with two scratch arrays."""
    t = cols["t_s"]
    n = len(t)
    ok = np.isfinite(t)
    ok &= ~cols["_text"]
    x, b = np.empty(n), np.empty(n, dtype=bool)
    for names, full_scale, (lo, hi) in ((("ax", "ay", "az"), limits.acc_full_scale, limits.acc_total_range),
                                        (("mx", "my", "mz"), limits.mag_full_scale, limits.mag_total_range)):
        sat = 0.999 * full_scale
        if not hi * (1.0 + 1e-9) < sat:          # else an axis at full scale fails the total's range too
            for c in names:
                ok &= np.less(np.abs(cols[c], out=x), sat, out=b)     # refuses NaN and inf
        total = np.multiply(cols[names[0]], cols[names[0]])
        for c in names[1:]:
            total += np.multiply(cols[c], cols[c], out=x)
        np.sqrt(total, out=total)
        ok &= np.greater_equal(total, lo, out=b)            # NaN and inf fail the range
        ok &= np.less_equal(total, hi, out=b)
    temp = cols["temp_c"]
    np.isnan(temp, out=b)
    b |= (limits.temp_range_c[0] <= temp) & (temp <= limits.temp_range_c[1])
    ok &= b
    pose = cols["pose"]
    if not cols["pose_null"].all():
        ok &= cols["pose_null"] | ((pose >= 1) & (pose <= 12) & (np.floor(pose, out=x) == pose))
    for c in HEADER[9:12] + [c for c in ("table_deg", "md_m") if c in cols]:
        if not cols[c + "_null"].all():
            ok &= cols[c + "_null"] | np.isfinite(cols[c])
    drift = cols["ref_drift_deg"]
    if not cols["ref_drift_deg_null"].all():
        ok &= cols["ref_drift_deg_null"] | ((drift >= 0) & (drift <= 180))
    if "mount" in cols:
        ok &= cols["mount"] >= 0
    return ok


def _numpy(col) -> np.ndarray:
    """A pyarrow float64, int32 or boolean (chunked) array as a new, writable numpy array read from
    its buffers, a null as NaN (float64; the other types come without nulls here).  pyarrow's own
    ``to_numpy`` gives the same values, but its conversion imports pandas, a quarter of a CPU-second
    in every process that reads a log (test/io/test_probelog_engines.py compares the two)."""
    import pyarrow as pa

    arr = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    n, off = len(arr), arr.offset
    if pa.types.is_boolean(arr.type):
        dtype = np.dtype(bool)
    elif arr.type == pa.float64():
        dtype = np.dtype(np.float64)
    elif arr.type == pa.int32():
        dtype = np.dtype(np.int32)
    else:
        raise TypeError(f"no numpy conversion for {arr.type}")
    if not n:
        return np.empty(0, dtype)
    validity, data = arr.buffers()[:2]

    def bits(buf):
        return np.unpackbits(np.frombuffer(buf, np.uint8), count=off + n, bitorder="little")[off:].astype(bool)
    if dtype == bool:
        out = bits(data)
    else:
        out = np.frombuffer(data, dtype, count=n, offset=off * dtype.itemsize).copy()
    if arr.null_count:
        if dtype != np.float64:
            raise TypeError(f"nulls in a {arr.type} column")
        out[~bits(validity)] = np.nan
    return out


def _lines(body, which, has_cr: bool, block: int = 1 << 20):
    """The text of the lines ``which`` (0-based, ascending) of ``body``: lines end at \\n, \\r or
    \\r\\n, as for ``str.splitlines`` and pyarrow (``has_cr``: whether there is any \\r).  The line
    breaks are found block by block (1 MiB), up to the last line asked for."""
    if not len(which):
        return
    b = np.frombuffer(body, dtype=np.uint8)
    ends, n_found, is_break = [], 0, np.empty(block + 1, dtype=bool)
    for i in range(0, len(b), block):
        x = b[i:i + block + 1]                 # one byte more: a \r\n across the blocks' edge
        brk = np.equal(x, 10, out=is_break[:len(x)])
        if has_cr:
            brk |= x == 13
            brk[1:] &= ~((x[1:] == 10) & (x[:-1] == 13))    # the \n of a \r\n is no break of its own
            if i and b[i] == 10 and b[i - 1] == 13:
                brk[0] = False
        pos = np.flatnonzero(brk[:min(block, len(x))]) + i
        ends.append(pos)
        n_found += len(pos)
        if n_found > which[-1]:
            break
    pos = np.concatenate(ends)
    for k in which:
        start = 0
        if k:
            p = int(pos[k - 1])
            start = p + (2 if b[p] == 13 and p + 1 < len(b) and b[p + 1] == 10 else 1)
        stop = int(pos[k]) if k < len(pos) else len(b)
        yield bytes(body[start:stop]).decode("utf-8")


def _parse_turntable(fields):
    """``(mount, table_deg, reason)`` of a turntable row's two extra fields."""
    mount = fields[0].strip()
    if mount and mount not in MOUNT_NAMES:
        return "", math.nan, f"mount={mount!r} is not one of {', '.join(MOUNT_NAMES)}"
    f = fields[1].strip()
    if not f:
        return mount, math.nan, None
    try:
        v = float(f)
    except ValueError:
        return "", math.nan, f"table_deg={f!r} is not a number"
    if not math.isfinite(v):
        return "", math.nan, "table_deg not finite"
    return mount, v, None


def _is_float(s):
    try:
        float(s)
        return True
    except ValueError:
        return False


def _parse_labels(fields):
    pose_s = fields[0].strip()
    pose = 0
    if pose_s:
        try:
            v = float(pose_s)
            pose = int(v)
        except ValueError:                     # not a number, or NaN
            return 0, None, f"pose={pose_s!r} is not a number"
        except OverflowError:                  # ±inf
            return 0, None, f"pose={pose_s!r} is not one of 1..12"
        if v != pose or not 1 <= pose <= 12:
            return 0, None, f"pose={pose_s!r} is not one of 1..12"
    ref = []
    for name, f in zip(HEADER[9:], fields[1:]):
        f = f.strip()
        if not f:
            ref.append(math.nan)
            continue
        try:
            v = float(f)
        except ValueError:
            return 0, None, f"{name}={f!r} is not a number"
        if not math.isfinite(v):
            return 0, None, f"{name} not finite"
        ref.append(v)
    if math.isfinite(ref[0]) and not 0 <= ref[0] <= 180:
        return 0, None, f"ref_drift_deg={ref[0]:g} outside 0..180"
    return pose, ref, None


def report(path, rejections, problems, warn, limit: int = 20) -> None:
    """Pass rejected rows (the first ``limit``) and station problems to ``warn``, naming the file."""
    for r in rejections[:limit]:
        warn(f"{path}: {r}")
    if len(rejections) > limit:
        warn(f"{path}: ... and {len(rejections) - limit} more rejected rows")
    for p in problems:
        warn(f"{path}: {p}")


def _column(values, fmt, blank_nan: bool = True) -> list:
    """One column's fields: ``values`` (a float array) each formatted with ``fmt``, NaN/inf as an
    empty field where ``blank_nan``.  Python floats format several times faster than numpy's
    scalars, and the digits are the same (both are the float64's shortest-round-trip value)."""
    out = [format(v, fmt) for v in values.tolist()]
    if blank_nan:
        bad = np.flatnonzero(~np.isfinite(values))
        for i in bad.tolist():
            out[i] = ""
    return out


def format_csv(log: ProbeLog, mag_unit: str = "nT") -> str:
    """Render a ProbeLog in the CSV format (full precision where it matters); the magnetometer in
    ``mag_unit`` (the file then needs that unit given when it is read).  Built column by column (a
    10⁶-row log: 3.3 s against 9.2 s row by row, the same text; the sensor columns by row: below)."""
    scale = 1.0 / MAG_UNITS[mag_unit]
    mfmt = ".3f" if mag_unit == "nT" else ".6g"
    turntable = log.is_turntable
    depth = bool(np.any(np.isfinite(log.md_m)))
    mag = log.mag * scale
    # the time and the six sensor columns (never blank) one row at a time through a %-template:
    # one formatting call a row instead of seven and a join (the same digits: both are Python's
    # float formatting; the simulator's survey log, 39 500 rows, 0.16 → 0.13 s)
    row = "%.4f,%.6f,%.6f,%.6f" + (",%" + mfmt) * 3
    sensors = [row % r for r in zip(log.t_s.tolist(), *(log.acc[:, j].tolist() for j in range(3)),
                                    *(mag[:, j].tolist() for j in range(3)))]
    cols = [sensors,
            _column(log.temp_c, ".3f"),
            [str(p) if p else "" for p in log.pose.astype(int).tolist()],
            *(_column(log.ref[:, j], ".4f") for j in range(3))]
    if turntable:
        cols += [[str(m or "") for m in log.mount.tolist()], _column(log.table_deg, ".4f")]
    if depth:
        cols.append(_column(log.md_m, ".3f"))
    header = ",".join(HEADER + (TURNTABLE_COLUMNS if turntable else []) + (["md_m"] if depth else []))
    if not len(log):
        return header + "\n"
    return header + "\n" + "\n".join(map(",".join, zip(*cols))) + "\n"


def write_csv(path, log: ProbeLog, mag_unit: str = "nT") -> None:
    atomic_write_text(path, format_csv(log, mag_unit))


# --------------------------------------------------------------------------------------------
# Static stations
# --------------------------------------------------------------------------------------------
def _ref_key(row):
    return tuple(None if not math.isfinite(v) else round(float(v), 9) for v in row)


def label_runs(log: ProbeLog):
    """Runs of consecutive rows with the same label (pose and reference), labelled runs only.

    Returns ``[(first_row, last_row, pose, ref), ...]`` with 0-based inclusive row indices and
    ``ref`` (3,) degrees (NaN where not given) — indices into the log, not file rows (``log.row``).
    What the log *says* its stations are — used to
    report labelled holds the detector did not find, and for a simulator's truth."""
    return [(k, j, key[0], log.ref[k].copy()) for k, j, key in _key_runs(log)
            if key[0] or any(v is not None for v in key[1])]


def _key_runs(log: ProbeLog) -> list:
    """Runs of consecutive rows with the same label key ``(pose, _ref_key(ref))``, all of them:
    ``[(first_row, last_row, key), ...]``.  Rows whose pose and reference equal the previous row's
    (NaN as NaN) share its key; the key is computed only where they do not (about 10⁶ rows:
    a per-row key was 2 s of ``lab diagnose``)."""
    n = len(log)
    if not n:
        return []
    pose, ref = log.pose, log.ref
    same = (pose[1:] == pose[:-1]) & np.all((ref[1:] == ref[:-1]) | (np.isnan(ref[1:]) & np.isnan(ref[:-1])), axis=1)
    out = []
    k = 0
    key = (int(pose[0]), _ref_key(ref[0].tolist()))
    for r in (np.flatnonzero(~same) + 1).tolist():
        new = (int(pose[r]), _ref_key(ref[r].tolist()))
        if new != key:
            out.append((k, r - 1, key))
            k, key = r, new
    out.append((k, n - 1, key))
    return out


def segment_stations(log: ProbeLog, detector=None, use_labels: bool = True):
    """The static stations of a log, found by the live nodes' detector; labels name them.

    The rows go through :class:`streaming.StaticDetector` (default settings: thresholds from the
    noise the log shows) exactly as a stream does, so a log, its bag and the live graph give the
    same stations.  With ``use_labels``, each station takes the pose and reference of its rows
    (a station whose rows carry different labels takes the most common one, with a message).

    Returns ``(stations, problems)``: ``problems`` are messages for the user — a labelled hold in
    which no station was found (and what the detector saw there), holds cut into pieces and why,
    the noise stated vs measured.
    """
    from ..detect.streaming import StaticDetector  # streaming imports the station type, not this module

    det = detector if detector is not None else StaticDetector()
    found = []
    t, g, mag, temp = log.t_s, log.gravity, log.mag, log.temp_c
    found.extend(det.run(t, g, mag, temp))    # = det.update row by row, in bulk (test_streaming pins it)
    found.extend(det.flush())
    problems = list(det.pop_events())
    stations = []
    starts = np.searchsorted(t, [st.t_start for st in found])
    ends = np.searchsorted(t, [st.t_end for st in found])
    runs = _key_runs(log) if use_labels else []
    run_first = np.array([r[0] for r in runs], dtype=np.int64)
    for st, i0, i1 in zip(found, starts, ends):
        st.first_row, st.last_row = int(log.row[i0]), int(log.row[min(i1, len(log) - 1)])   # the file's rows
        if use_labels:
            keys = Counter()       # rows per key, in the order the keys appear (as a per-row count)
            for a, b, key in runs[max(int(np.searchsorted(run_first, i0, side="right")) - 1, 0):]:
                if a > i1:
                    break
                keys[key] += min(b, i1) - max(a, i0) + 1
            labelled = [k for k in keys if k[0] or any(v is not None for v in k[1])]
            n_rows = sum(keys.values())
            n_lab = sum(keys[k] for k in labelled)
            pose, ref = 0, (None, None, None)
            if labelled and 2 * n_lab >= n_rows:
                pose, ref = max(labelled, key=lambda k: keys[k])
            if len(labelled) > 1:
                problems.append(f"station at {st.where} spans rows labelled {', '.join(_label_text(k) for k in labelled)} "
                                f"without motion between them: labelled {_label_text((pose, ref))} (the most rows)")
            elif labelled and not pose and all(v is None for v in ref):
                problems.append(f"station at {st.where}: only {n_lab} of its {n_rows} rows carry the label "
                                f"{_label_text(labelled[0])}: taken as unlabelled (no pose, no reference)")
            st.pose = pose
            st.ref = np.array([np.nan if v is None else v for v in ref], dtype=float)
        depth = log.md_m[i0:i1 + 1]
        if np.any(np.isfinite(depth)):         # the depth the rows of the hold give
            st.md_m = float(np.nanmedian(depth))
        if not st.short:
            st.index = len(stations)
            stations.append(st)
    if use_labels:
        problems.extend(_unfound_holds(log, found, det))
    return stations, problems


def _label_text(key) -> str:
    pose, ref = key
    if pose:
        return f"pose {pose}"
    return "ref ({})".format(", ".join("-" if v is None else f"{v:g}" for v in ref))


def _unfound_holds(log, found, det) -> list:
    """Labelled holds in which the detector found no station long enough, with what it did find."""
    out = []
    t = log.t_s
    for i0, i1, pose, ref in label_runs(log):
        t0, t1 = float(t[i0]), float(t[i1])
        inside = [st for st in found if st.t_end >= t0 and st.t_start <= t1]
        if any(not st.short for st in inside):
            continue
        label = _label_text((pose, _ref_key(ref)))
        r0, r1 = int(log.row[i0]), int(log.row[i1])
        pieces = [st for st in inside if st.short]
        if pieces:
            why = (f"only pieces shorter than {det.min_duration_s:g} s ({', '.join(f'{st.duration_s:.2f}' for st in pieces)} s): "
                   "the hold was cut by motion or noise (see the messages about pieces) or is too short — "
                   "detector.min_duration_s / min_capture_s set the shortest hold")
        elif t1 - t0 < det.min_duration_s + det.settle_s:
            why = (f"the hold lasts {t1 - t0:.2f} s, less than the detector needs ({det.min_duration_s:g} s after "
                   f"{det.settle_s:g} s settling)")
        else:
            why = "the probe was never still there (every sample moved beyond the noise)"
        out.append(f"{label} at rows {r0}-{r1} (t={t0:.2f}-{t1:.2f} s): no static station found: {why}")
    return out

"""Probe logs: the CSV format, row validation, and segmentation into static stations.

CSV format (the header line is literal)::

    t_s,ax,ay,az,mx,my,mz,temp_c,pose,ref_drift_deg,ref_azimuth_deg,ref_toolface_deg

* ``ax..az``: accelerometer as REP-145 *specific force* in m/s², uncalibrated (a resting probe
  reads -gravity).  Converted once, in :func:`segment_stations`, to the seed paper's gravity
  vector (down positive) with :func:`frames.gravity_from_specific_force`.
* ``mx..mz``: magnetometer in nT, uncalibrated.
* ``temp_c``: probe temperature, °C; empty (or ``nan``) when the probe has no sensor.
* ``pose``: 1..12 while the probe sits in that pose of the paper's Table 1, empty otherwise.
* ``ref_*``: the stand's set orientation where known, empty otherwise.  Rows recorded while the
  probe moves have all four of ``pose`` and ``ref_*`` empty.

Consecutive rows with the same pose (or the same ``ref_*`` triple) form one static station.
Unusable rows are rejected with a message naming the row and the reason; the rest is kept.
"""
from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from dataclasses import dataclass, field

import numpy as np

from .frames import STANDARD_GRAVITY, gravity_from_specific_force

HEADER = ["t_s", "ax", "ay", "az", "mx", "my", "mz", "temp_c", "pose",
          "ref_drift_deg", "ref_azimuth_deg", "ref_toolface_deg"]


@dataclass
class ProbeLog:
    """Samples of one probe log.

    Attributes: ``t_s`` (N,) s; ``acc`` (N, 3) REP-145 specific force, m/s²; ``mag`` (N, 3) nT;
    ``temp_c`` (N,) °C; ``pose`` (N,) int, 0 = none; ``ref`` (N, 3) deg (drift, azimuth,
    toolface), NaN where unknown.
    """

    t_s: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    temp_c: np.ndarray
    pose: np.ndarray
    ref: np.ndarray

    def __len__(self):
        return len(self.t_s)

    @classmethod
    def empty(cls):
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                   np.zeros(0, dtype=int), np.zeros((0, 3)))

    @classmethod
    def concatenate(cls, logs):
        logs = list(logs)
        return cls(*(np.concatenate([getattr(lg, f) for lg in logs]) for f in
                     ("t_s", "acc", "mag", "temp_c", "pose", "ref")))


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


def _check_row(acc, mag, temp, limits: Limits):
    """Reason a sample is unusable, or None."""
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
    if 0 < m < 1e-3:
        return (f"total field {m:.3g} is implausible for nT — the magnetometer columns look like tesla; "
                f"multiply by 1e9 to give nT")
    if not limits.mag_total_range[0] <= m <= limits.mag_total_range[1]:
        return (f"total field {m:.4g} nT is implausible (expected "
                f"{limits.mag_total_range[0]:g}..{limits.mag_total_range[1]:g} nT)")
    if math.isfinite(temp) and not limits.temp_range_c[0] <= temp <= limits.temp_range_c[1]:
        return f"temp_c={temp:g} °C is implausible"
    return None


def parse_csv(text: str, limits: Limits = Limits(), source: str = "<csv>"):
    """Parse probe-log CSV text.  Returns ``(ProbeLog, [Rejection, ...])``.

    Raises ``ValueError`` only when the file as a whole is unusable (wrong header, no data).
    """
    lines = text.splitlines()
    if not lines:
        raise ValueError(f"{source}: empty file (expected header {','.join(HEADER)})")
    header = [h.strip() for h in lines[0].lstrip("\ufeff").split(",")]
    if header != HEADER:
        raise ValueError(f"{source}: line 1: header must be exactly {','.join(HEADER)!r}, got {lines[0]!r}")
    rows, rejections = [], []
    last_t = -math.inf
    reader = csv.reader(io.StringIO("\n".join(lines[1:])))
    for k, fields in enumerate(reader, start=1):
        line = k + 1
        if not fields or all(not f.strip() for f in fields):
            continue
        if len(fields) != len(HEADER):
            rejections.append(Rejection(k, line, f"{len(fields)} fields, expected {len(HEADER)}"))
            continue
        try:
            # an empty temp_c is an unknown temperature (a probe without a sensor), not a bad row
            nums = [float(f) for f in fields[:7]] + [float(fields[7]) if fields[7].strip() else math.nan]
        except ValueError:
            bad = next(n for n, f in zip(HEADER, fields) if not _is_float(f))
            rejections.append(Rejection(k, line, f"{bad}={fields[HEADER.index(bad)]!r} is not a number"))
            continue
        nonfinite = [n for n, v in zip(HEADER, nums) if not math.isfinite(v)
                     and not (n == "temp_c" and math.isnan(v))]
        if nonfinite:
            rejections.append(Rejection(k, line, f"{', '.join(nonfinite)} not finite (NaN/inf)"))
            continue
        t, acc, mag, temp = nums[0], nums[1:4], nums[4:7], nums[7]
        reason = _check_row(acc, mag, temp, limits)
        if reason is None and t <= last_t:
            reason = f"time t_s={t:g} does not increase (previous {last_t:g}): non-monotonic timestamp"
        if reason is None:
            pose, ref, reason = _parse_labels(fields[8:])
        if reason is not None:
            rejections.append(Rejection(k, line, reason))
            continue
        last_t = t
        rows.append((t, *acc, *mag, temp, pose, *ref))
    if not rows:
        detail = f"; first rejection: {rejections[0]}" if rejections else ""
        raise ValueError(f"{source}: no usable rows{detail}")
    a = np.array(rows, dtype=float)
    log = ProbeLog(a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7], a[:, 8].astype(int), a[:, 9:12])
    return log, rejections


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
            pose = int(float(pose_s))
        except ValueError:
            return 0, None, f"pose={pose_s!r} is not a number"
        if float(pose_s) != pose or not 1 <= pose <= 12:
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
    n_known = sum(math.isfinite(v) for v in ref)
    if n_known not in (0, 3):
        return 0, None, "ref_drift/azimuth/toolface must be given all three or none"
    if n_known == 3 and not 0 <= ref[0] <= 180:
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


def read_csv(path, limits: Limits = Limits()):
    """Read a probe-log CSV file.  Returns ``(ProbeLog, [Rejection, ...])``."""
    with open(path, encoding="utf-8") as fh:
        return parse_csv(fh.read(), limits, source=str(path))


def _fmt(v, fmt):
    return "" if not np.isfinite(v) else format(v, fmt)


def format_csv(log: ProbeLog) -> str:
    """Render a ProbeLog in the CSV format (full precision where it matters)."""
    out = io.StringIO()
    out.write(",".join(HEADER) + "\n")
    for i in range(len(log)):
        fields = [f"{log.t_s[i]:.4f}",
                  *(f"{v:.6f}" for v in log.acc[i]),
                  *(f"{v:.3f}" for v in log.mag[i]),
                  f"{log.temp_c[i]:.3f}",
                  str(int(log.pose[i])) if log.pose[i] else "",
                  *(_fmt(v, ".4f") for v in log.ref[i])]
        out.write(",".join(fields) + "\n")
    return out.getvalue()


def atomic_write_text(path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file and rename: never a half-written file."""
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=d)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_csv(path, log: ProbeLog) -> None:
    atomic_write_text(path, format_csv(log))


# --------------------------------------------------------------------------------------------
# Static stations
# --------------------------------------------------------------------------------------------
@dataclass
class Station:
    """One static station: the average of consecutive rows with the same label.

    ``g`` is the mean gravity vector (down positive, m/s²) — already converted from REP-145;
    ``b`` the mean field (nT); ``g_std``/``b_std`` the per-axis scatter inside the station (the
    noise estimate); ``ref`` the stand's set (drift, azimuth, toolface) in degrees, NaN if unknown.
    """

    index: int
    pose: int
    ref: np.ndarray
    g: np.ndarray
    b: np.ndarray
    temp_c: float
    t_start: float
    t_end: float
    n: int
    g_std: np.ndarray
    b_std: np.ndarray
    first_row: int
    warnings: list = field(default_factory=list)

    @property
    def has_ref(self) -> bool:
        return bool(np.all(np.isfinite(self.ref)))

    @property
    def label(self) -> str:
        if self.pose:
            return f"pose {self.pose}"
        if self.has_ref:
            return "I={:g} A={:g} T={:g}".format(*self.ref)
        return f"station {self.index}"


def segment_stations(log: ProbeLog, min_samples: int = 5, max_motion_sigma: float = 6.0):
    """Group consecutive rows with the same label into stations.

    Returns ``(stations, problems)`` where ``problems`` are strings naming stations that were
    dropped (too short) or flagged (the probe moved during the capture: the scatter of one axis
    is more than ``max_motion_sigma`` times the median scatter of all stations, a robust noise
    reference, *and* the within-station trend dominates it).
    """
    n = len(log)
    if n == 0:
        return [], ["log has no rows"]
    has_ref = np.all(np.isfinite(log.ref), axis=1)
    labelled = (log.pose > 0) | has_ref
    refkey = np.where(has_ref[:, None], log.ref, -999.0)
    change = np.ones(n, dtype=bool)
    change[1:] = (log.pose[1:] != log.pose[:-1]) | np.any(refkey[1:] != refkey[:-1], axis=1) | \
        (labelled[1:] != labelled[:-1])
    starts = np.flatnonzero(change)
    ends = np.append(starts[1:], n)
    g_all = gravity_from_specific_force(log.acc)
    stations, problems = [], []
    for s, e in zip(starts, ends):
        if not labelled[s]:
            continue
        label = f"pose {log.pose[s]}" if log.pose[s] else "ref ({:g}, {:g}, {:g})".format(*log.ref[s])
        if e - s < min_samples:
            problems.append(f"station at rows {s + 1}-{e} ({label}): only {e - s} samples, "
                            f"need {min_samples}: static window too short, dropped")
            continue
        g, b = g_all[s:e], log.mag[s:e]
        stations.append(Station(
            index=len(stations), pose=int(log.pose[s]), ref=log.ref[s].copy(),
            g=g.mean(axis=0), b=b.mean(axis=0), temp_c=_mean_known(log.temp_c[s:e]),
            t_start=float(log.t_s[s]), t_end=float(log.t_s[e - 1]), n=int(e - s),
            g_std=g.std(axis=0, ddof=1), b_std=b.std(axis=0, ddof=1), first_row=int(s + 1)))
    _flag_motion(stations, max_motion_sigma, problems)
    return stations, problems


def _mean_known(x) -> float:
    """Mean of the finite values (temperatures may be unknown), NaN if none."""
    ok = np.isfinite(x)
    return float(x[ok].mean()) if ok.any() else float("nan")


def _flag_motion(stations, k, problems):
    """Flag stations whose scatter is far above the typical (median) scatter: the probe moved."""
    if len(stations) < 3:
        return
    gs = np.array([st.g_std for st in stations])
    bs = np.array([st.b_std for st in stations])
    g_ref = np.maximum(np.median(gs, axis=0), 1e-6)
    b_ref = np.maximum(np.median(bs, axis=0), 1e-3)
    for st, g, b in zip(stations, gs, bs):
        ratio = max(np.max(g / g_ref), np.max(b / b_ref))
        if ratio > k:
            msg = (f"station {st.index} ({st.label}, rows from {st.first_row}): scatter {ratio:.1f}× the "
                   f"typical — the probe moved during the capture")
            st.warnings.append(msg)
            problems.append(msg)

"""The static station: one interval in which the probe held still — ROS-free.

One type for every path: the live nodes' detector closes it from a stream, a probe log's rows
are segmented into it (the same detector, :func:`probelog.segment_stations`), the twelve-pose
capture keeps it, the survey corrects it.

Conventions: ``g`` is the seed paper's **gravity vector** (down positive, m/s²) — the REP-145
specific force of ``sensor_msgs/Imu`` and of the probe-log CSV is negated once, where samples
enter :class:`streaming.StaticDetector`; ``b`` is the field in nT.  Times are seconds in the
data's own time base (log time, or the stream's header stamps).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

NAN3 = (math.nan, math.nan, math.nan)


def _vec(v) -> np.ndarray:
    return np.asarray(v, dtype=float).reshape(3)


@dataclass
class Station:
    """A static interval and what is known about it.

    Measured (from the samples; filled by the detector):

    * ``t_start``, ``t_end`` (s), ``n`` samples averaged;
    * ``g`` (3,) mean gravity vector, m/s²; ``b`` (3,) mean field, nT;
    * ``g_std``, ``b_std`` (3,): per-axis sample standard deviation inside the station;
    * ``g_rate``, ``b_rate`` (3,): per-axis least-squares slope over the station, per second
      (a probe creeping during the hold); ``t_std`` (s): standard deviation of the sample times
      (with the slope it gives the part of the scatter the trend explains);
    * ``g_noise``, ``b_noise`` (3,): the per-sample noise σ the data showed when the detector closed
      the station (:attr:`noise.NoiseEstimator.measured`; a user's override of the detector's
      thresholds does not change it), NaN when unknown;
    * ``temp_c``: mean of the known temperatures, NaN if none;
    * ``outliers``: isolated samples left out of the means (spikes shorter than the detector's
      ``break_samples``);
    * ``short``: shorter than the detector's minimum duration (kept only for reporting);
    * ``ended_by``: why the interval closed — ``motion``, ``max_duration`` (a long hold is cut
      to report it live; the next station continues it), ``gap`` (a non-finite sample), ``end``.

    Labels (from a log; a stream has none): ``pose`` 1..12 of the paper's Table 1 (0: none),
    ``ref`` (3,) the stand's set (drift, azimuth, toolface) in degrees, NaN where unknown — a
    vertical stand pose gives drift and toolface but no azimuth; ``first_row`` the 1-based data
    row of the first sample and ``last_row`` of the last (0 for streams).  ``index`` numbers the stations of one log/stream.
    ``warnings`` collects what the acceptance gates (:mod:`gates`) found, as text; ``unusable``
    names the sensors (``"acc"``, ``"mag"``) whose data in this station a gate refused; ``moved``
    says the probe moved during the hold (in-hold motion gates); ``gated``: the gates have run.
    """

    t_start: float
    t_end: float
    n: int
    g: np.ndarray
    b: np.ndarray
    g_std: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    b_std: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    temp_c: float = math.nan
    g_rate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    b_rate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t_std: float = 0.0
    g_noise: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    b_noise: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    outliers: int = 0
    short: bool = False
    ended_by: str = ""
    index: int = 0
    pose: int = 0
    ref: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    first_row: int = 0
    last_row: int = 0
    warnings: list = field(default_factory=list)
    unusable: tuple = ()
    moved: bool = False
    gated: bool = False

    def __post_init__(self):
        for name in ("g", "b", "g_std", "b_std", "g_rate", "b_rate", "g_noise", "b_noise", "ref"):
            setattr(self, name, _vec(getattr(self, name)))

    @property
    def duration_s(self) -> float:
        return self.t_end - self.t_start

    @property
    def has_ref(self) -> bool:
        """The full reference attitude (drift, azimuth and toolface) is known."""
        return bool(np.all(np.isfinite(self.ref)))

    @property
    def has_partial_ref(self) -> bool:
        """Some of the reference is known (e.g. drift and toolface of a vertical pose)."""
        return bool(np.any(np.isfinite(self.ref)))

    @property
    def where(self) -> str:
        """Where the station is, for messages: rows of a log, else times."""
        if self.first_row:
            return f"rows {self.first_row}-{self.last_row} (t={self.t_start:.2f}-{self.t_end:.2f} s)"
        return f"t={self.t_start:.2f}-{self.t_end:.2f} s"

    @property
    def label(self) -> str:
        if self.pose:
            return f"pose {self.pose}"
        if self.has_partial_ref:
            return "I={} A={} T={}".format(*("-" if not math.isfinite(v) else f"{v:g}" for v in self.ref))
        return f"station {self.index}"


def merge_stations(a: Station, b: Station) -> Station:
    """One station from two pieces of the same hold (``a`` before ``b``).

    Means are weighted by the sample counts; the scatter is the pooled one, including the
    difference of the two means (exactly the scatter of all samples together); the trend is the
    count-weighted slope of the pieces; the time scatter is that of all sample times.
    """
    na, nb = a.n, b.n
    n = na + nb
    wa, wb = na / n, nb / n
    ta, tb = 0.5 * (a.t_start + a.t_end), 0.5 * (b.t_start + b.t_end)

    def pooled(sa, sb, ma, mb):
        va, vb = np.square(sa) * (na - 1), np.square(sb) * (nb - 1)
        return np.sqrt((va + vb + na * nb / n * np.square(np.asarray(ma) - np.asarray(mb))) / (n - 1))

    temps = [(x.temp_c, x.n) for x in (a, b) if math.isfinite(x.temp_c)]
    return Station(
        t_start=a.t_start, t_end=b.t_end, n=n, g=wa * a.g + wb * b.g, b=wa * a.b + wb * b.b,
        g_std=pooled(a.g_std, b.g_std, a.g, b.g), b_std=pooled(a.b_std, b.b_std, a.b, b.b),
        temp_c=sum(t * k for t, k in temps) / sum(k for _, k in temps) if temps else math.nan,
        g_rate=wa * a.g_rate + wb * b.g_rate, b_rate=wa * a.b_rate + wb * b.b_rate,
        t_std=float(pooled(a.t_std, b.t_std, ta, tb)),
        g_noise=b.g_noise, b_noise=b.b_noise, outliers=a.outliers + b.outliers, short=False,
        ended_by=b.ended_by, index=a.index, pose=a.pose or b.pose, ref=a.ref if a.has_partial_ref else b.ref,
        first_row=a.first_row, last_row=b.last_row, warnings=a.warnings + b.warnings,
        unusable=tuple(sorted(set(a.unusable) | set(b.unusable))), moved=a.moved or b.moved,
        gated=a.gated and b.gated)

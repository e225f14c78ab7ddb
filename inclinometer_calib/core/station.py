"""The static station: one interval in which the probe held still — ROS-free.

One type for every path: the live nodes' detector closes it from a stream, a probe log's rows
are segmented into it (the same detector, :func:`probelog.segment_stations`), the twelve-pose
capture keeps it, the survey corrects it, the simulator plans its sessions with it
(:meth:`Station.planned`).  :class:`Stations` is the same thing as a struct of arrays, for the
lab's fits (built only from :class:`Station` objects).

Conventions: ``g`` is the seed paper's **gravity vector** (down positive, m/s²) — the REP-145
specific force of ``sensor_msgs/Imu`` and of the probe-log CSV is negated once, where samples
enter the package (:func:`frames.gravity_from_specific_force`); ``b`` is the field in nT.  Times are seconds in the
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
    vertical stand pose gives drift and toolface but no azimuth; ``rotation`` (3, 3) the set
    orientation (tool → NED) when it is known as a matrix (a plan of the simulator; NaN
    otherwise); ``first_row`` the 1-based data row of the first sample and ``last_row`` of the
    last (0 for streams).  ``index`` numbers the stations of one log/stream; ``t_origin`` is the
    time of the data's first sample (the probe's power-on: the origin of time-dependent effects).
    ``warnings`` collects what the acceptance gates (:mod:`gates`) found, as text; ``unusable``
    names the sensors (``"acc"``, ``"mag"``) whose data in this station a gate refused; ``moved``
    says the probe moved during the hold (in-hold motion gates); ``gated``: the gates have run,
    ``findings``: what they found.
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
    #: the gates' findings (:class:`gates.Finding`) when they ran on this station
    findings: tuple = ()
    rotation: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    t_origin: float = 0.0
    #: Measured depth of the station (m; NaN: not known): a log's ``md_m`` rows, a stream's
    #: ``/probe/depth``, a plan's set depth.
    md_m: float = math.nan
    #: The detector's running sums through the hold (None: not kept): ``origin`` (6,) the first
    #: sample (gravity vector, field) the sums are taken from; ``profile`` (k, 22) a row per
    #: :data:`streaming.PROFILE_AT` passed — the time from the first sample of the sample that
    #: passed it, then the sums *before* that sample: ``n``, Σd, Σd², Στd (six each, ``d`` the
    #: sample less ``origin``, ``τ`` its time from the first sample), Στ, Στ² — and a last row with
    #: the whole hold's sums at its last sample's time.  :meth:`settled_from` takes the station from
    #: any row to its end.
    origin: np.ndarray | None = None
    profile: np.ndarray | None = None
    #: Seconds left out at the start of the hold (a sensor settling after the move: :mod:`gates`).
    settled_s: float = 0.0

    def __post_init__(self):
        for name in ("g", "b", "g_std", "b_std", "g_rate", "b_rate", "g_noise", "b_noise", "ref"):
            setattr(self, name, _vec(getattr(self, name)))
        self.rotation = np.asarray(self.rotation, dtype=float).reshape(3, 3)

    @classmethod
    def planned(cls, rotation, duration_s: float, pose: int = 0, ref=NAN3, temp_c: float = 25.0,
                md_m: float = math.nan) -> "Station":
        """A station to be held (the simulator's session plan): set orientation ``rotation`` (tool →
        NED), how long, its labels, temperature and measured depth; nothing measured yet."""
        return cls(t_start=0.0, t_end=float(duration_s), n=0, g=NAN3, b=NAN3, temp_c=float(temp_c), pose=int(pose),
                   ref=np.asarray(ref, dtype=float), rotation=rotation, md_m=float(md_m))

    @property
    def t_mid(self) -> float:
        return 0.5 * (self.t_start + self.t_end)

    @property
    def time_s(self) -> float:
        """Seconds from the data's first sample to the middle of the hold (time-dependent effects)."""
        return self.t_mid - self.t_origin

    @property
    def duration_s(self) -> float:
        return self.t_end - self.t_start

    @duration_s.setter
    def duration_s(self, value: float) -> None:   # a plan's hold made longer or shorter
        self.t_end = self.t_start + float(value)

    def segments(self):
        """The hold cut at the rows of :attr:`profile` (a quarter second apart), as arrays
        ``(start, n, mean)``: each piece's first sample's time from the hold's first sample (s),
        its samples, and the mean of the six values — the hold's shape (a sensor settling after
        the move); None without a profile."""
        p = self.profile
        if p is None or len(p) < 2:
            return None
        if self.settled_s == 0:                # the hold from its first sample: sums of nothing before it
            p = np.vstack([np.zeros((1, p.shape[1])), p])
        dn = np.diff(p[:, 1])
        ok = dn > 0
        mean = np.diff(p[:, 2:8], axis=0)[ok] / dn[ok, None] + self.origin
        return p[:-1, 0][ok], dn[ok], mean

    def settled_from(self, row: int) -> "Station":
        """A copy of the station from the sample that passed :attr:`profile` row ``row`` to its end:
        means, scatter, trends and times of those samples only, from the running sums (the same
        formulas as the detector's).  Labels, noise, gate outcome and temperature are kept (the
        temperature of the whole hold: a few seconds do not change it)."""
        import dataclasses

        p = self.profile
        a, z = p[row], p[-1]
        n = int(round(z[1] - a[1]))
        if n < 2:
            raise ValueError(f"{self.where}: fewer than 2 samples after {a[0]:.2f} s")
        mean, std, rate, t_std = hold_statistics(n, self.origin, z[2:8] - a[2:8], z[8:14] - a[8:14],
                                                 z[14:20] - a[14:20], z[20] - a[20], z[21] - a[21])
        t0 = self.t_start - self.settled_s
        return dataclasses.replace(
            self, t_start=t0 + float(a[0]), n=n, g=mean[:3], b=mean[3:], g_std=std[:3], b_std=std[3:],
            g_rate=rate[:3], b_rate=rate[3:], t_std=t_std, settled_s=float(a[0]),
            warnings=list(self.warnings), profile=p[row:].copy())

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


def hold_statistics(n: int, origin, s1, s2, st, tt: float, tt2: float) -> tuple:
    """A hold's statistics from its running sums over ``n`` samples (the detector's, and a hold
    taken from a point of its profile): ``origin`` (6,) the values the sums are taken from, ``s1``,
    ``s2``, ``st`` (6,) Σd, Σd², Στd (``d`` a sample less ``origin``, ``τ`` its time from the
    hold's first sample), ``tt``, ``tt2`` Στ, Στ².  Returns ``(mean, std, rate, t_std)``: means,
    sample standard deviations and least-squares slopes (per s) of the six values, (6,) each, and
    the standard deviation of the sample times (s)."""
    s1 = np.asarray(s1, dtype=float)
    mean_d = s1 / n
    var = np.maximum(np.asarray(s2, dtype=float) / n - mean_d * mean_d, 0.0) * n / (n - 1)
    mean = np.asarray(origin, dtype=float) + mean_d
    tbar = tt / n
    stt = tt2 - n * tbar * tbar
    rate = (np.asarray(st, dtype=float) - tbar * s1) / stt if stt > 0 else np.zeros(6)
    return mean, np.sqrt(var), rate, math.sqrt(max(stt, 0.0) / (n - 1))


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
        gated=a.gated and b.gated, findings=a.findings + b.findings, rotation=a.rotation, t_origin=a.t_origin,
        settled_s=a.settled_s)


# ---------------------------------------------------------------------------------------------
# Stations as a struct of arrays (the lab's fits)
# ---------------------------------------------------------------------------------------------
def _object_array(items, n) -> np.ndarray:
    out = np.full(n, None, dtype=object)
    if items is not None:
        for i, x in enumerate(items):
            out[i] = x
    return out


#: Floors of the per-station noise estimate of a mean (std/√n): m/s², nT.
SIGMA_FLOOR = {"acc": 2e-6, "mag": 0.05}
@dataclass(frozen=True)
class Loss:
    """Data left out (or changed) on the way into a fit: where (a file, a log), what (``rows``,
    ``stations``, ``poses``, ``log``, ``temperatures``), how many, and why."""

    source: str
    what: str
    count: int
    reason: str

    def __str__(self):
        return f"{self.source}: {self.count} {self.what} — {self.reason}"

    def to_json(self):
        return {"source": self.source, "what": self.what, "count": self.count, "reason": self.reason}


#: What constrains a station's model residuals: a twelve-position pose (orientation from Table 1),
#: a reference attitude (stand grid, survey with a reference), or nothing (site invariants only).
KINDS = ("pose", "ref", "free")


@dataclass
class Stations:
    """N stations as arrays, built from :class:`Station` objects by :meth:`from_list`.

    g, b : (N, 3) measured means (gravity vector m/s², field nT)
    g_sigma, b_sigma : (N, 3) noise of the means (within-station std / √n, floored)
    g_scatter, b_scatter : (N, 3) within-station sample std (the raw noise estimate)
    temp_c : (N,) °C;  time_s : (N,) s since the data's first sample (:attr:`Station.time_s`)
    rotation : (N, 3, 3) tool→NED for pose/ref stations, NaN for free ones
    kind : (N,) 'pose' | 'ref' | 'free';   role : (N,) 'cal' (the stand) | 'val' (the survey)
    pose : (N,) 1..12 or 0;   ref : (N, 3) deg or NaN;   n : (N,) samples;  source : (N,) where from
    """

    g: np.ndarray
    b: np.ndarray
    g_sigma: np.ndarray
    b_sigma: np.ndarray
    g_scatter: np.ndarray
    b_scatter: np.ndarray
    temp_c: np.ndarray
    time_s: np.ndarray
    rotation: np.ndarray
    kind: np.ndarray
    role: np.ndarray
    pose: np.ndarray
    ref: np.ndarray
    n: np.ndarray
    source: np.ndarray
    #: The sequence (:class:`effects.History`): place in its log, the previous hold's attitude
    #: (NaN: unknown or none) and means, each station's samples (None: not kept).
    order: np.ndarray = None
    prev_rotation: np.ndarray = None
    prev_g: np.ndarray = None
    prev_b: np.ndarray = None
    samples: np.ndarray = None
    #: The part of each hold a station keeps (:attr:`Station.settled_s`, :attr:`Station.duration_s`):
    #: seconds left out at the hold's start (a sensor settling after the move) and kept, (N,).
    settled_s: np.ndarray = None
    duration_s: np.ndarray = None
    #: What reading left out or changed, with the reason (:class:`Loss`): the lab's verdict, JSON
    #: and report count it.  Not per station: a subset keeps the whole ledger.
    losses: list = field(default_factory=list)

    def __post_init__(self):
        n = len(self.g)
        if self.order is None:
            self.order = np.arange(n)
        for name, shape in (("prev_rotation", (n, 3, 3)), ("prev_g", (n, 3)), ("prev_b", (n, 3))):
            if getattr(self, name) is None:
                setattr(self, name, np.full(shape, np.nan))
        if self.samples is None:
            self.samples = np.full(n, None, dtype=object)
        if self.settled_s is None:
            self.settled_s = np.zeros(n)
        if self.duration_s is None:
            self.duration_s = np.full(n, np.nan)

    def __len__(self):
        return len(self.g)

    def _arrays(self):
        return [k for k in self.__dataclass_fields__ if k != "losses"]

    def subset(self, mask) -> "Stations":
        mask = np.asarray(mask)
        return Stations(**{k: getattr(self, k)[mask] for k in self._arrays()}, losses=list(self.losses))

    @classmethod
    def concatenate(cls, parts, losses=()) -> "Stations":
        every = [p for p in parts]
        parts = [p for p in every if len(p)]
        ledger = [x for p in every for x in p.losses] + list(losses)
        return cls(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in parts[0]._arrays()},
                   losses=ledger)

    @property
    def oriented(self) -> np.ndarray:
        return self.kind != "free"

    def describe(self) -> str:
        parts = []
        for role in ("cal", "val"):
            m = self.role == role
            if m.any():
                kinds = ", ".join(f"{int(np.sum(m & (self.kind == k)))} {k}" for k in KINDS
                                  if np.any(m & (self.kind == k)))
                t = self.temp_c[m]
                parts.append(f"{role}: {int(m.sum())} stations ({kinds}), {t.min():.1f}–{t.max():.1f} °C")
        return "; ".join(parts)

    @classmethod
    def from_list(cls, stations, role: str, source: str = "", use_ref: bool = True,
                  t_origin: float | None = None, samples=None) -> "Stations":
        """Stations of one log or stream with a role (``cal``: the stand, ``val``: the survey).

        Orientation: a pose label gives Table 1's matrix, a reference attitude its matrix (a
        vertical reference without azimuth too: its rotation about the vertical is the
        toolface, as for azimuth 0); otherwise the station is ``free``.  ``t_origin``: the time
        origin of time effects when several logs are read together (default: each station's).
        An unknown temperature becomes the log's mean (else the effects' reference): temperature
        effects then see no span and are reported as not identifiable, instead of poisoning the fit.
        The stations are in time order: each knows its place and the previous hold (its attitude
        and means); ``samples`` (optional, per station an (n, 7) array of time, gravity vector and
        field) keeps the samples for effects that need them (:class:`effects.History`).
        """
        from .effects import T_REF_C
        from .frames import orientation_matrix, pose_matrix
        from .survey import Tolerances, in_vertical_cone

        if role not in ("cal", "val"):
            raise ValueError(f"role must be 'cal' or 'val', got {role!r}")
        n = len(stations)
        rot = np.full((n, 3, 3), np.nan)
        kind = np.empty(n, dtype=object)
        for i, st in enumerate(stations):
            if st.pose:
                rot[i] = pose_matrix(st.pose)
                kind[i] = "pose"
            elif use_ref and st.has_ref:
                rot[i] = orientation_matrix(*st.ref)
                kind[i] = "ref"
            elif (use_ref and np.isfinite(st.ref[0]) and np.isfinite(st.ref[2])
                  and in_vertical_cone(st.ref[0], Tolerances().min_drift_deg)):
                rot[i] = orientation_matrix(st.ref[0], 0.0, st.ref[2])
                kind[i] = "ref"
            else:
                kind[i] = "free"
        cnt = np.array([max(st.n, 1) for st in stations], dtype=float)
        temps = np.array([st.temp_c for st in stations], dtype=float)
        losses = []
        if not np.all(np.isfinite(temps)):
            known = temps[np.isfinite(temps)]
            fill = known.mean() if len(known) else T_REF_C
            losses.append(Loss(source or role, "temperatures", int(np.sum(~np.isfinite(temps))),
                               f"station temperature unknown: set to {fill:.1f} °C (the " +
                               ("log's mean" if len(known) else "effects' reference") + ")"))
            temps = np.where(np.isfinite(temps), temps, fill)
        g_sc = np.array([st.g_std for st in stations]).reshape(n, 3)
        b_sc = np.array([st.b_std for st in stations]).reshape(n, 3)
        times = np.array([st.t_mid - (st.t_origin if t_origin is None else t_origin) for st in stations], dtype=float)
        return cls(
            g=np.array([st.g for st in stations]).reshape(n, 3), b=np.array([st.b for st in stations]).reshape(n, 3),
            g_sigma=np.maximum(np.nan_to_num(g_sc) / np.sqrt(cnt)[:, None], SIGMA_FLOOR["acc"]),
            b_sigma=np.maximum(np.nan_to_num(b_sc) / np.sqrt(cnt)[:, None], SIGMA_FLOOR["mag"]),
            g_scatter=g_sc, b_scatter=b_sc, temp_c=temps, time_s=times,
            rotation=rot, kind=kind.astype(str), role=np.full(n, role), pose=np.array([st.pose for st in stations]),
            ref=np.array([st.ref for st in stations], dtype=float).reshape(n, 3), n=cnt.astype(int),
            source=np.full(n, source), losses=losses, order=np.arange(n),
            prev_rotation=np.concatenate([np.full((min(n, 1), 3, 3), np.nan), rot[:-1]]),
            prev_g=np.concatenate([np.full((min(n, 1), 3), np.nan), np.array([st.g for st in stations]).reshape(n, 3)[:-1]]),
            prev_b=np.concatenate([np.full((min(n, 1), 3), np.nan), np.array([st.b for st in stations]).reshape(n, 3)[:-1]]),
            samples=_object_array(samples, n), settled_s=np.array([st.settled_s for st in stations], dtype=float),
            duration_s=np.array([st.duration_s for st in stations], dtype=float))


def correct_stations(stations, cal, strict: bool = False, previous=None):
    """Corrected gravity vectors (m/s²) and fields (nT) of stations, (N, 3) each, with each
    station's temperature and time (``cal`` None: the raw vectors).  A station without the
    temperature the model needs comes out NaN (:func:`context_warnings` says why); ``strict``:
    raise :class:`model.ModelContextError` instead when no station has one (a log without a
    temperature column).

    A model with effects that depend on the sequence of holds (a sensor settling after the move,
    :class:`effects.Settling`) corrects the stations one after another, in the order given, each
    with its place in its hold and the previous hold's corrected vectors as that hold's input
    and the earlier stations' times and temperatures (a sensor feeling the temperature late);
    ``previous``: the :class:`StationSequence` before the first (None: none — a stream's first)."""
    g = np.array([s.g for s in stations], dtype=float).reshape(-1, 3)
    b = np.array([s.b for s in stations], dtype=float).reshape(-1, 3)
    if cal is None:
        return g, b
    temps = np.array([s.temp_c for s in stations], dtype=float)
    times = np.array([s.time_s for s in stations], dtype=float)
    if strict and "temperature" in cal.needs and len(temps) and not np.isfinite(temps).any():
        return cal.correct(g, b, None, times)   # raises: the model needs a temperature, the data give none
    if "history" not in cal.needs:
        return cal.correct(g, b, temps, times)
    out_g, out_b = np.empty_like(g), np.empty_like(b)
    prev = previous if previous is not None else StationSequence()
    for i, st in enumerate(stations):
        h = prev.history(st)
        out_g[i:i + 1], out_b[i:i + 1] = cal.correct(g[i:i + 1], b[i:i + 1], temps[i:i + 1], times[i:i + 1], history=h)
        prev = prev.after(st, out_g[i], out_b[i])
    return out_g, out_b


#: Earlier stations a :class:`StationSequence` keeps (their times and temperatures).
STATIONS_KEPT = 5000


class StationSequence:
    """What a station corrected on its own needs of the ones before it (:class:`effects.History`):
    the previous hold's corrected vectors (a settling's input) and the earlier stations' times and
    temperatures (a sensor feeling the temperature late).  Immutable: :meth:`after` gives the next."""

    def __init__(self, g=None, b=None, times=(), temps=()):
        self.g = np.full(3, np.nan) if g is None else np.asarray(g, dtype=float)
        self.b = np.full(3, np.nan) if b is None else np.asarray(b, dtype=float)
        self.times, self.temps = tuple(times), tuple(temps)

    def after(self, st: Station, g, b) -> "StationSequence":
        keep = STATIONS_KEPT - 1      # a lag forgets what lies many time constants back
        if not (math.isfinite(st.temp_c) and math.isfinite(st.time_s)):     # nothing to feel late
            return StationSequence(g, b, self.times, self.temps)
        return StationSequence(g, b, self.times[-keep:] + (st.time_s,), self.temps[-keep:] + (st.temp_c,))

    def history(self, st: Station):
        from . import effects as fx

        return fx.History(source=np.zeros(1, dtype=int), order=np.array([st.index]),
                          previous_g=self.g.reshape(1, 3), previous_b=self.b.reshape(1, 3),
                          settled_s=np.array([st.settled_s]), duration_s=np.array([st.duration_s]),
                          n=np.array([st.n]), earlier_time_s=np.array(self.times, dtype=float),
                          earlier_temp_c=np.array(self.temps, dtype=float))

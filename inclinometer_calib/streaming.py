"""Streaming (sample-by-sample) processing for live nodes — ROS-free.

* :class:`StaticDetector` finds static intervals in a live stream and closes them as stations.
* :class:`SurveyProcessor` corrects each closed station with the current calibration and evaluates
  it against the site reference (QC), producing plain records that a node converts to messages.

Inputs follow the boundary convention: accelerometer as REP-145 specific force (m/s²), converted
here once to the gravity vector; magnetometer in nT (a node converts from tesla before calling).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .frames import Site
from .axial import evaluate_with_axial
from .survey import Tolerances, evaluate


@dataclass
class StaticSegment:
    """A closed static interval: means in the gravity-vector convention (m/s²) and nT."""

    t_start: float
    t_end: float
    n: int
    g: np.ndarray
    b: np.ndarray
    g_std: np.ndarray
    b_std: np.ndarray
    temp_c: float
    short: bool = False

    @property
    def duration_s(self) -> float:
        return self.t_end - self.t_start


@dataclass
class StaticDetector:
    """Detects static intervals from sample-to-mean deviations.

    A sample belongs to the current static candidate when every accelerometer axis is within
    ``k_sigma·noise_acc`` and every magnetometer axis within ``k_sigma·noise_mag`` of the
    candidate's running mean (plus ``acc_floor``/``mag_floor`` for sensors quieter than stated).
    A sample outside closes the candidate; it is reported if it lasted ``min_duration_s``,
    otherwise counted in ``too_short``.  The first ``settle_s`` of a candidate are discarded
    (vibration after a move).  ``max_duration_s`` closes long stations so they are reported live.
    """

    noise_acc: float = 0.002
    noise_mag: float = 20.0
    k_sigma: float = 6.0
    acc_floor: float = 0.003
    mag_floor: float = 30.0
    min_duration_s: float = 1.0
    settle_s: float = 0.2
    max_duration_s: float = 30.0
    short_report_s: float = 0.3

    _n: int = 0
    _t0: float = 0.0
    _t_last: float = 0.0
    _sum_t: float = 0.0
    _n_t: int = 0
    _settle_until: float = -math.inf
    too_short: int = 0

    def __post_init__(self):
        self._tol_f = max(self.k_sigma * self.noise_acc, self.acc_floor)
        self._tol_m = max(self.k_sigma * self.noise_mag, self.mag_floor)
        # Per-axis accumulators as plain floats (this is the per-sample path of the live nodes:
        # no numpy per sample).  Sums are of deviations from the candidate's first sample, which
        # keeps the variance free of cancellation for fields of 50 000 nT.
        self._x0 = [0.0] * 6
        self._s1 = [0.0] * 6
        self._s2 = [0.0] * 6

    def reset(self):
        self._n = 0
        self._s1 = [0.0] * 6
        self._s2 = [0.0] * 6
        self._sum_t = 0.0
        self._n_t = 0

    @property
    def is_static(self) -> bool:
        return self._n > 0 and (self._t_last - self._t0) >= self.min_duration_s

    @property
    def static_for_s(self) -> float:
        return (self._t_last - self._t0) if self._n else 0.0

    def update(self, t: float, f, m, temp_c: float = float("nan")):
        """Feed one sample (specific force m/s², field nT).  Returns a closed segment or None."""
        fx, fy, fz = float(f[0]), float(f[1]), float(f[2])
        mx, my, mz = float(m[0]), float(m[1]), float(m[2])
        t = float(t)
        if not math.isfinite(fx + fy + fz + mx + my + mz + t):
            return self._close(t, restart=None)  # a bad sample breaks the station
        if t < self._settle_until:
            return None
        x = (fx, fy, fz, mx, my, mz)
        n = self._n
        if n:
            x0, s1 = self._x0, self._s1
            tf, tm = self._tol_f, self._tol_m
            # deviation of the sample from the candidate's running mean, axis by axis
            if (abs(fx - x0[0] - s1[0] / n) > tf or abs(fy - x0[1] - s1[1] / n) > tf
                    or abs(fz - x0[2] - s1[2] / n) > tf or abs(mx - x0[3] - s1[3] / n) > tm
                    or abs(my - x0[4] - s1[4] / n) > tm or abs(mz - x0[5] - s1[5] / n) > tm):
                out = self._close(t, restart=None)
                self._settle_until = t + self.settle_s
                return out
            if t - self._t0 >= self.max_duration_s:
                return self._close(t, restart=(t, x, temp_c))
        self._add(t, x, temp_c)
        return None

    def _add(self, t, x, temp_c):
        if self._n == 0:
            self._t0 = t
            self._x0 = list(x)
        self._n += 1
        self._t_last = t
        x0, s1, s2 = self._x0, self._s1, self._s2
        for k in range(6):
            d = x[k] - x0[k]
            s1[k] += d
            s2[k] += d * d
        if math.isfinite(temp_c):  # the mean is over the samples that had a temperature
            self._sum_t += temp_c
            self._n_t += 1

    def _close(self, t, restart):
        seg = None
        dur = self._t_last - self._t0
        if self._n >= 2 and dur >= min(self.short_report_s, self.min_duration_s):
            n = self._n
            s1 = np.array(self._s1)
            mean_d = s1 / n
            var = np.maximum(np.array(self._s2) / n - mean_d * mean_d, 0.0) * n / (n - 1)
            mean = np.array(self._x0) + mean_d
            std = np.sqrt(var)
            short = dur < self.min_duration_s
            self.too_short += short
            seg = StaticSegment(self._t0, self._t_last, n, -mean[:3], mean[3:], std[:3], std[3:],
                                self._sum_t / self._n_t if self._n_t else float("nan"), short=short)
        self.reset()
        if restart is not None:
            self._add(*restart)
        return seg

    def flush(self):
        """Close the current candidate (end of stream)."""
        return self._close(self._t_last, restart=None)


class StreamPairer:
    """Pairs Imu and MagneticField samples of the same header stamp, cheaply and in time order.

    ``add_imu``/``add_mag`` return ``(t, f, m)`` when the stamp's partner is already there,
    else None.  Unpaired samples wait in small insertion-ordered dicts (the oldest is evicted
    beyond ``max_pending``); a completed pair older than the last one emitted is dropped
    (``out_of_order``), so consumers always see increasing times.
    """

    __slots__ = ("_imu", "_mag", "max_pending", "last_t", "paired", "unpaired", "out_of_order")

    def __init__(self, max_pending: int = 64):
        self._imu = {}
        self._mag = {}
        self.max_pending = max_pending
        self.last_t = -math.inf
        self.paired = 0
        self.unpaired = 0
        self.out_of_order = 0

    def reset(self):
        self._imu.clear()
        self._mag.clear()
        self.last_t = -math.inf

    def _add(self, key, value, mine, other, imu_first):
        partner = other.pop(key, None)
        if partner is None:
            mine[key] = value
            if len(mine) > self.max_pending:
                del mine[next(iter(mine))]
                self.unpaired += 1
            return None
        t = key[0] + 1e-9 * key[1]
        if t <= self.last_t:
            self.out_of_order += 1
            return None
        self.last_t = t
        self.paired += 1
        return (t, value, partner) if imu_first else (t, partner, value)

    def add_imu(self, key, f):
        return self._add(key, f, self._imu, self._mag, True)

    def add_mag(self, key, m):
        return self._add(key, m, self._mag, self._imu, False)


@dataclass
class StationRecord:
    """A corrected, quality-checked survey station (plain data for a SurveyStation message)."""

    station_id: int
    segment: StaticSegment
    values: dict
    coefficients_id: str


class SurveyProcessor:
    """Corrects closed static segments with the current calibration and checks them against the site.

    ``axial=True``: azimuths from the short-collar correction of axial drill-string interference
    (:func:`axial.evaluate_with_axial`); QC stays on the measured field.
    """

    def __init__(self, site: Site, tolerances: Tolerances = Tolerances(), calibration=None, axial: bool = False):
        self.site = site
        self.tolerances = tolerances
        self.calibration = calibration
        self.axial = axial
        self._next_id = 0

    def set_calibration(self, calibration):
        self.calibration = calibration

    def correct_vectors(self, g, b):
        """Corrected gravity vector (m/s²) and field (nT); identity without a calibration."""
        if self.calibration is None:
            return np.asarray(g, float), np.asarray(b, float)
        return self.calibration.correct(g, b)

    def process(self, seg: StaticSegment, ref=None) -> StationRecord:
        g, b = self.correct_vectors(seg.g, seg.b)
        if self.axial:
            res = evaluate_with_axial(g, b, self.site, self.tolerances, ref=None if ref is None else [ref])
        else:
            res = evaluate(g, b, self.site, self.tolerances, ref=None if ref is None else [ref])
        values = {k: (v[0].item() if hasattr(v[0], "item") else v[0]) for k, v in res.items()}
        rec = StationRecord(self._next_id, seg, values,
                            self.calibration.id if self.calibration is not None else "none")
        self._next_id += 1
        return rec


NAN = float("nan")


def _finite_or_nan(x) -> float:
    x = float(x)
    return x if math.isfinite(x) else NAN


def station_fields(rec: StationRecord, ref, azimuth_reference: str, have_temperature: bool,
                   calibrated: bool) -> dict:
    """The fields of a ``SurveyStation`` message (all but the header) for a processed station.

    Plain Python values, shared by the correction node (rclpy message) and offline reprocessing
    (rosbags type store), so both publish the same thing.  Undefined values are NaN, never 0.
    """
    v, seg = rec.values, rec.segment
    has_ref = ref is not None and all(math.isfinite(x) for x in ref)
    axial = "azimuth_method" in v
    return dict(
        station_id=int(rec.station_id),
        drift_deg=_finite_or_nan(v["drift_deg"]),
        azimuth_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v["azimuth_deg"]),
        azimuth_reference=azimuth_reference,
        azimuth_method=str(v["azimuth_method"]) if axial else "standard",
        axial_field_nt=_finite_or_nan(v["axial_field_nt"]) if axial else NAN,
        azimuth_sigma_deg=_finite_or_nan(v["azimuth_sigma_deg"]) if axial else NAN,
        axial_degenerate=bool(v["axial_degenerate"]) if axial else False,
        toolface_deg=_finite_or_nan(v["toolface_deg"]),
        toolface_type="gravity" if v["toolface_is_gravity"] else "magnetic",
        # defined down to the azimuth threshold; it is *reported* (toolface_deg) above the switch-over
        gravity_toolface_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v["gravity_toolface_deg"]),
        magnetic_toolface_deg=_finite_or_nan(v["magnetic_toolface_deg"]),
        total_gravity_mps2=float(v["total_gravity"]),
        total_field_nt=float(v["total_field"]),
        dip_deg=_finite_or_nan(v["dip_deg"]),
        delta_g_mps2=float(v["delta_g"]),
        delta_b_nt=float(v["delta_b"]),
        delta_dip_deg=_finite_or_nan(v["delta_dip"]),
        status=int(v["status"]),
        is_static=not seg.short,
        interference_suspected=bool(v["interference_suspected"]),
        azimuth_undefined=bool(v["azimuth_undefined"]),
        gravity_out_of_tolerance=bool(v["gravity_out_of_tolerance"]),
        samples_averaged=int(seg.n),
        duration_s=float(seg.duration_s),
        temperature_c=float(seg.temp_c) if have_temperature else NAN,
        coefficients_id=rec.coefficients_id if calibrated else "",
        reference_drift_deg=float(ref[0]) if has_ref else NAN,
        reference_azimuth_deg=float(ref[1]) if has_ref else NAN,
        reference_toolface_deg=float(ref[2]) if has_ref else NAN,
    )


def detect_stations(log, detector: StaticDetector | None = None) -> list:
    """Static stations of a whole log found by the detector, ignoring any labels ('free' stations).

    For logs recorded without a stand (the probe turned by hand through many attitudes): each
    closed, long-enough static interval becomes a :class:`probelog.Station` with no pose and no
    reference; only the site invariants constrain it.
    """
    from .probelog import Station

    det = detector or StaticDetector()
    segs = []
    for i in range(len(log)):
        seg = det.update(log.t_s[i], log.acc[i], log.mag[i], log.temp_c[i])
        if seg is not None and not seg.short:
            segs.append(seg)
    seg = det.flush()
    if seg is not None and not seg.short:
        segs.append(seg)
    first_rows = np.searchsorted(log.t_s, [s.t_start for s in segs]) + 1
    nan3 = np.full(3, np.nan)
    return [Station(index=k, pose=0, ref=nan3.copy(), g=s.g, b=s.b, temp_c=s.temp_c, t_start=s.t_start,
                    t_end=s.t_end, n=s.n, g_std=s.g_std, b_std=s.b_std, first_row=int(r))
            for k, (s, r) in enumerate(zip(segs, first_rows))]

"""Streaming (sample-by-sample) processing for live nodes — ROS-free.

* :class:`StaticDetector` finds static intervals in a live stream and closes them as stations
  (:class:`station.Station`), with thresholds taken from the noise the data show (:mod:`noise`);
  :meth:`StaticDetector.run` takes a whole log at once: the same stations, bit for bit, at about
  a quarter of the per-sample cost on a 2 kHz log (at 100 Hz, holds of ~100 samples, about the same);
* :class:`StreamPairer` pairs the Imu and MagneticField samples of one stamp;
* :class:`ReferenceTrack` keeps the reference attitudes of a stream and says when they are current.

What happens to a closed station next (correction, QC, the field monitor) is in :mod:`pipeline`.

Inputs are the core's: accelerometer as the gravity vector (down positive, m/s²: converted from
REP-145 specific force where the samples entered, :func:`frames.gravity_from_specific_force`);
magnetometer in nT (a node converts from tesla before calling).
"""
from __future__ import annotations

import bisect
import math

import numpy as np

from ..core.frames import angle_between_deg
from .noise import AXES6, UNITS6, NoiseEstimator
from ..core.station import Station, hold_statistics


_NO_STATIONS = ()
#: A time step this many times the usual sample interval (and over GAP_MIN_S) is a gap: samples lost.
GAP_FACTOR = 5.0
GAP_MIN_S = 0.05
#: Time comparisons allow this much (s): a log's times written as text ("0.25") and the same
#: times stamped in a bag (sec + nanosec, far from zero) differ in their last bits, and durations
#: nominally equal to a limit must fall on the same side of it in both.
TIME_EPS = 1e-6
#: The hold's running sums are kept at these times from its first sample (s, less TIME_EPS): a
#: station can then be taken from any of them to its end (:meth:`station.Station.settled_from`) —
#: a sensor that settles after each move has the start of its holds trimmed (:mod:`gates`).
PROFILE_STEP_S = 0.25
PROFILE_SPAN_S = 8.0
PROFILE_AT = tuple(k * PROFILE_STEP_S - TIME_EPS for k in range(1, int(round(PROFILE_SPAN_S / PROFILE_STEP_S)) + 1))


class StaticDetector:
    """Finds static intervals in a stream of samples and closes them as :class:`station.Station`.

    A sample belongs to the current static candidate when every axis is within ``k_sigma``
    times that axis' noise σ of the candidate's running mean (never less than ``acc_floor`` /
    ``mag_floor``: motion smaller than that is not motion).  ``break_samples`` consecutive
    samples outside end the candidate at the last sample inside it; fewer are isolated spikes,
    left out of the means and counted (``Station.outliers``).  The first ``settle_s`` after a
    break are discarded (ringing after a move).  A candidate is reported when it lasted
    ``min_duration_s``; shorter ones are reported as ``short`` from ``short_report_s`` on (for
    diagnostics) and counted in ``too_short``.  ``max_duration_s`` closes long holds so that they
    are reported live (the next station continues the hold).

    **The noise comes from the data** (:class:`noise.NoiseEstimator`: robust block statistics
    over the stream), so a probe noisier or quieter than any default is handled alike.  Until the
    estimator has seen enough blocks (a few seconds) the samples are buffered, then replayed
    with the measured thresholds: the first stations come out a few seconds late, never cut
    with a guessed noise.  ``noise_acc`` / ``noise_mag`` > 0 override the data (per-sample σ,
    m/s² and nT); a noise stated by the messages (covariance) is a prior: :meth:`set_prior`.

    Inputs are the core's: ``g`` the gravity vector (down positive, m/s²; REP-145 specific force is
    converted where it enters, :func:`frames.gravity_from_specific_force`); ``m`` the field in nT.

    :meth:`update` returns a tuple of the stations closed by that sample (usually empty; several
    when the warm-up buffer is replayed).  Messages for the user (a hold cut into pieces and why,
    the stated noise contradicted by the data) accumulate in :attr:`events`; take them with
    :meth:`pop_events`.
    """

    def __init__(self, k_sigma: float = 6.0, noise_acc: float = 0.0, noise_mag: float = 0.0,
                 acc_floor: float = 0.003, mag_floor: float = 30.0, min_duration_s: float = 0.5,
                 settle_s: float = 0.2, max_duration_s: float = 30.0, break_samples: int = 3,
                 short_report_s: float = 0.3, warmup_max_s: float = 10.0, noise_block_s: float = 0.25):
        if not (k_sigma > 0 and min_duration_s > 0 and settle_s >= 0 and max_duration_s > 0
                and break_samples >= 1 and acc_floor >= 0 and mag_floor >= 0):
            raise ValueError("StaticDetector: k_sigma, min_duration_s, max_duration_s must be > 0, settle_s, "
                             "floors >= 0, break_samples >= 1")
        self.k_sigma = float(k_sigma)
        self.acc_floor = float(acc_floor)
        self.mag_floor = float(mag_floor)
        self.min_duration_s = float(min_duration_s)
        self.settle_s = float(settle_s)
        self.max_duration_s = float(max_duration_s)
        self.break_samples = int(break_samples)
        self.short_report_s = float(short_report_s)
        self.warmup_max_s = float(warmup_max_s)
        self.noise = NoiseEstimator(block_s=noise_block_s, override_acc=noise_acc, override_mag=noise_mag)
        self.too_short = 0
        self.gaps = 0                # breaks in the sample times (lost samples)
        self.samples_missing = 0
        self._t_prev = math.inf
        self.t_first = math.nan      # time of the first sample: the origin of time-dependent effects
        self.temps = TemperatureTrack()
        #: Keep every temperature until the consumer forgets it (:meth:`TemperatureTrack.forget_before`):
        #: for a consumer that holds closed stations back (a node waiting for their reference) and
        #: takes their temperature later; otherwise they are forgotten as stations close.
        self.retain_temperatures = False
        self._dt = math.inf          # the typical sample interval (running mean of the non-gap ones)
        self.events: list = []
        self._warming = not (noise_acc > 0 and noise_mag > 0)
        self._buf: list = []
        self._settle_until = -math.inf
        self._tol = [math.inf] * 6
        self._sigma = (math.nan,) * 6
        self._prev = None            # the last station closed by motion: is the next one its continuation?
        self._last_break = None      # (axis, deviation in σ) of the last break
        self._reported_prior = False
        self._refresh()
        self.reset()

    # ---- state -----------------------------------------------------------------------------
    def reset(self):
        """Forget the current candidate (the noise estimate is kept)."""
        self._n = 0
        self._out = 0
        self._outliers = 0
        self._t0 = self._t_last = 0.0
        self._x0 = [0.0] * 6
        self._s1 = [0.0] * 6
        self._s2 = [0.0] * 6
        self._st = [0.0] * 6
        self._tt = self._tt2 = 0.0
        self._profile = []       # the running sums before the first sample at each PROFILE_AT
        self._pj = 0             # the next PROFILE_AT to pass

    def set_prior(self, noise_acc: float | None = None, noise_mag: float | None = None) -> None:
        """The per-sample σ stated by the messages (covariance): used until the data give one."""
        self.noise.set_prior(noise_acc, noise_mag)

    def _refresh(self):
        lvl = self.noise.level
        sig = lvl.sigma6
        self._sigma = sig
        k, fa, fm = self.k_sigma, self.acc_floor, self.mag_floor
        self._tol = [max(k * v, fa if j < 3 else fm) if math.isfinite(v) else math.inf for j, v in enumerate(sig)]
        if not self._reported_prior and self.noise.ready:
            msgs = self.noise.check_prior()
            if msgs:
                self._reported_prior = True
                self.events.extend(msgs)

    @property
    def noise_level(self):
        """The :class:`noise.NoiseLevel` in use."""
        return self.noise.level

    @property
    def warming_up(self) -> bool:
        return self._warming

    @property
    def is_static(self) -> bool:
        return self._n > 0 and (self._t_last - self._t0) >= self.min_duration_s - TIME_EPS

    @property
    def static_for_s(self) -> float:
        return (self._t_last - self._t0) if self._n else 0.0

    def pop_events(self) -> list:
        out, self.events = self.events, []
        return out

    # ---- samples ---------------------------------------------------------------------------
    def add_temperature(self, t: float, temp_c: float) -> None:
        """A temperature (°C) stamped ``t``: a station's temperature is the mean of those stamped
        within it (:class:`TemperatureTrack`), however they arrive — with the sample (a log), or
        on a topic of their own (a node, a bag)."""
        self.temps.add(t, temp_c)

    def update(self, t: float, g, m, temp_c: float = math.nan):
        """Feed one sample (gravity vector m/s², field nT, and its temperature °C, or NaN when the
        temperature comes separately by :meth:`add_temperature` or not at all).

        Returns the stations closed by it (a tuple, usually empty)."""
        x = (float(g[0]), float(g[1]), float(g[2]), float(m[0]), float(m[1]), float(m[2]))
        t = float(t)
        if temp_c == temp_c:
            self.temps.add(t, temp_c)
        if self.t_first != self.t_first:
            self.t_first = t
        if not math.isfinite(x[0] + x[1] + x[2] + x[3] + x[4] + x[5] + t):
            self.noise.gap()
            if self._warming:
                self._buf.append((t, None))
                return _NO_STATIONS
            return self._close("gap")
        out = _NO_STATIONS
        dt = t - self._t_prev
        self._t_prev = t
        if dt > GAP_FACTOR * self._dt and dt > GAP_MIN_S:
            # samples lost (a reader that could not keep up on best-effort QoS, the source): what the
            # probe did meanwhile went unseen, so a hold ends at a gap
            self._note_gap(t, dt)
            self.noise.gap()
            if self._warming:
                self._buf.append((t, None))
            else:
                out = self._close("gap")
        elif dt > 0:
            self._dt = dt if self._dt == math.inf else 0.9 * self._dt + 0.1 * dt   # the typical interval
        if self.noise.add(t, x):
            self._refresh()
        if self._warming:
            buf = self._buf
            buf.append((t, x))
            if self.noise.ready or (t - buf[0][0] >= self.warmup_max_s - TIME_EPS and self._can_estimate()):
                return out + self._end_warmup()
            return out
        return out + self._step(t, x)

    # ---- a whole log at once ----------------------------------------------------------------
    def run(self, t, g, m, temp_c=None):
        """Feed a block of samples at once: what calling :meth:`update` on each row in turn does,
        with the same stations, events and state after it, bit for bit (``test_streaming`` pins
        it), at a fraction of the cost — for a log or a recorded stream.

        ``t`` (N,) s, ``g`` (N, 3) gravity vector m/s², ``m`` (N, 3) nT, ``temp_c`` (N,) °C or None.
        Returns the stations closed (a tuple; :meth:`flush` closes the last one).

        There is one detection rule, :meth:`_step`.  What is done here in bulk is only what it
        does to a sample of a candidate that is inside the tolerance (``|x − x₀ − s₁/n| ≤ tol``
        on every axis, before ``max_duration_s``): add it to the running sums, as ``np.cumsum``
        from the running sums — sequential additions, the per-sample path's exactly.  Every other
        sample (the first of a candidate, one outside, the settling after a move, a gap, a
        non-finite sample, a sample whose noise block changes the thresholds) goes through the
        per-sample code itself.  The noise estimator's blocks (:class:`noise.NoiseEstimator`)
        depend on times and gaps only, so they are found first and their standard deviations
        computed together, again by sequential sums; each is handed to the estimator at the
        sample that closes it.  The warm-up (samples buffered until the noise is known) runs per
        sample, as do logs whose times go backwards.
        """
        t = np.asarray(t, dtype=float)
        g = np.asarray(g, dtype=float)
        m = np.asarray(m, dtype=float)
        n_all = len(t)
        temp = np.full(n_all, np.nan) if temp_c is None else np.asarray(temp_c, dtype=float)
        out = []
        i = 0
        # per sample until the noise is known and the estimator's block boundary is reached
        while i < n_all and (self._warming or self.noise.block_open or self.t_first != self.t_first):
            out.extend(self.update(t[i], g[i], m[i], temp[i]))
            i += 1
        tf = t[i:][np.isfinite(t[i:])]
        if n_all - i < 64 or np.any(np.diff(tf) < 0):
            for j in range(i, n_all):
                out.extend(self.update(t[j], g[j], m[j], temp[j]))
            return tuple(out)
        out.extend(_BatchRun(self, t[i:], g[i:], m[i:], temp[i:]).run())
        return tuple(out)

    def _note_gap(self, t, dt):
        self.gaps += 1
        self.samples_missing += max(int(round(dt / self._dt)) - 1, 1)
        if self.gaps & (self.gaps - 1) == 0:   # said at the 1st, 2nd, 4th, 8th ... gap: bounded
            self.events.append(
                f"{self.gaps} gap(s) in the sample times so far, about {self.samples_missing} samples missing (this "
                f"one {dt:.3f} s at t={t - dt:.2f} s, {dt / self._dt:.0f}× the usual interval): a pause in the log, or "
                "samples lost (live: a reader that could not keep up with best-effort QoS — for a replay use "
                "qos.reliability:=reliable or a lower speed); each gap ends a hold")

    def _can_estimate(self) -> bool:
        lvl = self.noise.level
        return all(math.isfinite(v) for v in lvl.sigma6)

    def _end_warmup(self):
        self._warming = False
        lvl = self.noise.level
        if not all(math.isfinite(v) for v in lvl.sigma6):
            # too few blocks for the full estimate: take what the blocks there are say
            self.noise.force()
            self._refresh()
            lvl = self.noise.level
        out = []
        for t, x in self._buf:
            out.extend(self._close("gap") if x is None else self._step(t, x))
        self._buf = []
        return tuple(out)

    def _step(self, t, x):
        if t < self._settle_until - TIME_EPS:
            return _NO_STATIONS
        n = self._n
        if n:
            x0, s1, tol = self._x0, self._s1, self._tol
            for k in range(6):
                dev = x[k] - x0[k] - s1[k] / n
                if dev > tol[k] or -dev > tol[k]:
                    break
            else:
                k = -1
            if k >= 0:                       # outside: a spike, or the start of a move
                self._out += 1
                if self._out < self.break_samples:
                    self._outliers += 1
                    return _NO_STATIONS
                self._outliers -= self.break_samples - 1   # the pending ones were the move, not spikes
                sig = self._sigma[k]
                self._last_break = (k, abs(x[k] - x0[k] - s1[k] / n) / sig if sig > 0 else math.inf)
                out = self._close("motion")
                self._settle_until = t + self.settle_s
                return out
            self._out = 0
            if t - self._t0 >= self.max_duration_s - TIME_EPS:
                out = self._close("max_duration")
                self._add(t, x)
                return out
        self._add(t, x)
        return _NO_STATIONS

    def _add(self, t, x):
        if self._n == 0:
            self._t0 = t
            self._x0 = list(x)
        tau = t - self._t0
        if self._pj < len(PROFILE_AT) and tau >= PROFILE_AT[self._pj]:
            self._profile.append(self._sums(tau))
            self._pj = bisect.bisect_right(PROFILE_AT, tau)
        self._n += 1
        self._t_last = t
        self._tt += tau
        self._tt2 += tau * tau
        x0, s1, s2, st = self._x0, self._s1, self._s2, self._st
        for k in range(6):
            d = x[k] - x0[k]
            s1[k] += d
            s2[k] += d * d
            st[k] += tau * d

    def _sums(self, tau) -> tuple:
        """A row of :attr:`station.Station.profile`: ``tau`` (s from the hold's first sample), then the
        running sums before that sample: ``n``, Σd, Σd², Στd (six each, ``d`` from the first
        sample), Στ, Στ²."""
        return (tau, float(self._n), *self._s1, *self._s2, *self._st, self._tt, self._tt2)

    def _close(self, reason):
        st = None
        n = self._n
        dur = self._t_last - self._t0
        if n >= 2 and dur >= min(self.short_report_s, self.min_duration_s) - TIME_EPS:
            st = self._station(reason)
            if st.short:
                self.too_short += 1
        self.reset()
        if st is None:
            return _NO_STATIONS
        if not self._warming and not self.retain_temperatures:
            self.temps.forget_before(st.t_start)   # stations close in time order: later ones start later
        self._pieces(st)
        return (st,)

    def _station(self, reason):
        n = self._n
        mean, std, rate, t_std = hold_statistics(n, self._x0, self._s1, self._s2, self._st, self._tt, self._tt2)
        sig = np.array(self.noise.measured)   # the gates judge against the data's noise, not an override
        profile = np.array(self._profile + [self._sums(self._t_last - self._t0)])   # the last row: the totals
        return Station(t_start=self._t0, t_end=self._t_last, n=n, g=mean[:3], b=mean[3:], g_std=std[:3],
                       b_std=std[3:], temp_c=self.temps.mean(self._t0, self._t_last),
                       g_rate=rate[:3], b_rate=rate[3:], t_std=t_std,
                       g_noise=sig[:3], b_noise=sig[3:], outliers=self._outliers,
                       short=(self._t_last - self._t0) < self.min_duration_s - TIME_EPS, ended_by=reason,
                       t_origin=self.t_first, origin=np.array(self._x0), profile=profile)

    def _pieces(self, st):
        """Say so when a hold was cut into pieces, with the likely reason and the setting that fixes
        it.  Pieces of one hold: the previous station ended by motion, this one starts right after
        (nothing but the settling time between them) and the probe points the same way (< 1°)."""
        prev, self._prev = self._prev, (st if st.ended_by == "motion" else None)
        if prev is None or self._last_break is None:
            return
        gap = st.t_start - prev.t_end
        if gap > self.settle_s + 0.25 or angle_between_deg(prev.g, st.g) > 1.0 or angle_between_deg(prev.b, st.b) > 1.0:
            return
        k, dev = self._last_break
        sig = self._sigma[k]
        unit = UNITS6[k]
        ang = max(angle_between_deg(prev.g, st.g), angle_between_deg(prev.b, st.b))
        # how far apart the two pieces' means are, against what the noise of two means allows
        sep = max(abs(float(st.g[j] - prev.g[j])) / (self._sigma[j] * math.sqrt(1 / st.n + 1 / prev.n))
                  for j in range(3)) if all(self._sigma[j] > 0 for j in range(3)) else math.inf
        where = f"hold at t={prev.t_start:.2f}-{st.t_end:.2f} s cut at t={prev.t_end:.2f} s"
        if sep < 5.0:
            self.events.append(
                f"{where} by a {dev:.1f}σ excursion on {AXES6[k]} (σ = {sig:.3g} {unit}), but both pieces point the "
                f"same way: the noise has outliers beyond {self.k_sigma:g}σ (not white, or spikes longer than "
                f"{self.break_samples} samples) — raise detector.k_sigma (e.g. {math.ceil(1.3 * max(dev, self.k_sigma)):g}) "
                f"or detector.break_samples")
        else:
            self.events.append(
                f"{where}: the probe moved slowly during the hold ({ang:.2f}° between the pieces, the break was "
                f"a {dev:.1f}σ step on {AXES6[k]}) — the stand or probe creeps; re-seat the probe (each piece is "
                "checked for in-hold motion)")

    def flush(self):
        """Close the current candidate (end of the stream).  Returns the stations closed."""
        out = []
        if self._warming:
            out.extend(self._end_warmup())
        out.extend(self._close("end"))
        return tuple(out)


class _BatchRun:
    """The bulk part of :meth:`StaticDetector.run` (see there): rows of one log, entered with the
    detector past its warm-up and the noise estimator at a block boundary."""

    #: Bounds of the look-ahead window of the bulk step (rows); it doubles while whole windows are
    #: inside and restarts small after a stop, so a noisy log does not pay for long windows.
    W_MIN, W_MAX = 64, 65536
    #: After a bulk step that added fewer rows than this, that many rows go per sample (spikes:
    #: the bulk step's fixed cost would exceed the per-sample path's).
    SHORT = 16

    def __init__(self, det, t, g, m, temp):
        self.det = det
        self.t = t
        self.x = np.concatenate([g, m], axis=1)
        self.temp = temp
        self.n = len(t)
        self._temps_done = 0
        self._w = self.W_MIN

    # ---- what update() does before the detection rule ------------------------------------------
    def _timing(self):
        """Finite rows (the per-sample path's test: the sum of the six values and the time), the
        time gaps with the interval estimate before each, the estimate after the last row."""
        x, t = self.x, self.t
        fin = np.isfinite(x[:, 0] + x[:, 1] + x[:, 2] + x[:, 3] + x[:, 4] + x[:, 5] + t)
        det = self.det
        tp, e = det._t_prev, det._dt
        gaps = {}
        rows = np.flatnonzero(fin)
        # the running interval is a recurrence: plain floats, as in update()
        for r, tv in zip(rows.tolist(), t[rows].tolist()):
            dt = tv - tp
            tp = tv
            if dt > GAP_FACTOR * e and dt > GAP_MIN_S:
                gaps[r] = (dt, e)
            elif dt > 0:
                e = dt if e == math.inf else 0.9 * e + 0.1 * dt
        return fin, gaps, tp, e

    def _blocks(self, fin, gaps):
        """The noise estimator's blocks: ``{closing row: (n, std (6,))}`` and the first row of the
        block left open at the end (None: none).  A block starts at the first finite row after
        the last one closed; a gap row discards it and starts the next; a non-finite row discards
        it; it closes at the first row with ``min_block_samples`` rows and ``block_s`` of time."""
        t, n = self.t, self.n
        ne = self.det.noise
        span, mb = ne.block_s - 1e-6, ne.min_block_samples
        nonfin = np.flatnonzero(~fin)
        breaks = np.union1d(nonfin, np.fromiter(gaps, dtype=np.int64, count=len(gaps)))
        finite_rows = np.flatnonzero(fin)

        def next_finite(r):
            k = np.searchsorted(finite_rows, r)
            return int(finite_rows[k]) if k < len(finite_rows) else None

        closes, starts = [], []
        s = next_finite(0)
        open_start = None
        while s is not None:
            k = np.searchsorted(breaks, s, side="right")
            nb = int(breaks[k]) if k < len(breaks) else n          # the next break after the start
            lo = s + mb - 1
            c = nb
            if lo < nb:
                t0 = t[s]
                c = max(s + int(np.searchsorted(t[s:nb], t0 + span)), lo)
                while c > lo and t[c - 1] - t0 >= span:            # the exact test, as in add()
                    c -= 1
                while c < nb and not (t[c] - t0 >= span):
                    c += 1
            if c < nb:
                closes.append(c)
                starts.append(s)
                s = next_finite(c + 1)
            elif nb == n:
                open_start = s
                break
            else:
                s = nb if fin[nb] else next_finite(nb + 1)
        out = {}
        if closes:
            cs, ss = np.array(closes), np.array(starts)
            length = cs - ss + 1
            std = np.empty((len(cs), 6))
            for ln in np.unique(length):
                sel = np.flatnonzero(length == ln)
                blk = self.x[ss[sel][:, None] + np.arange(ln)]            # (blocks, ln, 6)
                d = blk - blk[:, :1, :]
                # sequential sums (cumsum; np.sum may sum pairwise): add()'s numbers, bit for bit
                s1 = np.cumsum(d, axis=1)[:, -1]
                s2 = np.cumsum(d * d, axis=1)[:, -1]
                std[sel] = np.sqrt(np.maximum(s2 - s1 * s1 / ln, 0.0) / (ln - 1))
            out = {int(c): (int(ln), std[k]) for k, (c, ln) in enumerate(zip(cs, length))}
        return out, open_start

    def _temps_through(self, r):
        """The temperatures of the rows up to ``r`` (update() adds a row's before anything else)."""
        a, b = self._temps_done, r + 1
        if b - a > 8:
            self.det.temps.extend(self.t[a:b], self.temp[a:b])
        else:                                  # a row or a few: numpy's call overhead would dominate
            for j in range(a, b):
                v = float(self.temp[j])
                if v == v:
                    self.det.temps.add(float(self.t[j]), v)
        self._temps_done = max(a, b)

    # ---- the rows -------------------------------------------------------------------------------
    def run(self) -> list:
        det, t, x, n = self.det, self.t, self.x, self.n
        if n and float(t[0]) > det.temps.latest + TIME_EPS and bool(np.all(np.diff(t) > TIME_EPS)):
            # the rows' temperatures at once, not row by row as update() adds them: a station's
            # temperature is the mean of those stamped within it (± TIME_EPS), and where the times
            # rise by more than that each row, a row after the one that closes a station is
            # stamped outside it: the same means
            self._temps_through(n - 1)
        fin, gaps, t_prev, dt_last = self._timing()
        blocks, open_start = self._blocks(fin, gaps)
        # the thresholds change only where a block's close recomputes the estimate: there the
        # blocks closed so far are handed over and the thresholds refreshed (update() refreshes at
        # every close, the same thresholds again in between)
        due, ahead, more = [], 0, 0
        for r, (nb, _) in sorted(blocks.items()):
            ahead += 1
            more += nb
            if det.noise.estimate_due(ahead, more):
                due.append(r)
        pending = iter(sorted(blocks))
        special = np.union1d(np.flatnonzero(~fin), np.array(sorted(set(gaps) | set(due)), dtype=np.int64))
        due = set(due)
        out = []
        i = 0
        for r in special.tolist() + [n]:
            if r > i:
                self._rows(i, r, out)
            if r == n:
                break
            self._temps_through(r)
            if not fin[r]:                     # update(): a non-finite sample ends the hold
                det.noise.gap()
                out.extend(det._close("gap"))
                i = r + 1
                continue
            tr = float(t[r])
            if r in gaps:
                dt, det._dt = gaps[r]
                det._note_gap(tr, dt)
                det.noise.gap()
                out.extend(det._close("gap"))
            if r in due:
                for c in pending:
                    det.noise.add_block(*blocks[c])
                    if c == r:
                        break
                det._refresh()
            out.extend(det._step(tr, x[r].tolist()))
            i = r + 1
        self._temps_through(n - 1)
        det._t_prev, det._dt = t_prev, dt_last
        for c in pending:
            det.noise.add_block(*blocks[c])
        det.noise.gap()                      # the block left open: sample by sample, as add() holds it
        if open_start is not None:
            for r in range(open_start, n):
                det.noise.add(float(t[r]), x[r].tolist())
        return out

    def _rows(self, a, b, out):
        """Rows ``a`` to ``b`` (excluded): finite, no gap, no noise block closing (the thresholds
        fixed)."""
        det, t = self.det, self.t
        i = a
        while i < b:
            if det._n == 0:
                su = det._settle_until - TIME_EPS
                if t[i] < su:                  # settling after a move: skipped
                    w = min(b - i, self.W_MAX)
                    late = ~(t[i:i + w] < su)
                    i += int(np.argmax(late)) if late.any() else w
                    continue
                self._one(i, out)
                i += 1
                continue
            k = self._inside(i, b)
            i += k
            if i < b:                          # a stop: outside, or the longest hold reached
                self._one(i, out)
                i += 1
                if k < self.SHORT:             # moving, or spiky: per sample for a few rows
                    for j in range(i, min(i + self.SHORT, b)):
                        self._one(j, out)
                    i = min(i + self.SHORT, b)

    def _one(self, r, out):
        self._temps_through(r)
        out.extend(self.det._step(float(self.t[r]), self.x[r].tolist()))

    def _inside(self, a, b) -> int:
        """Add the rows from ``a`` on that :meth:`StaticDetector._step` would add to the open
        candidate without a decision — inside the tolerance on every axis against the running
        mean, before ``max_duration_s`` — and return how many (the row after them is a stop)."""
        det = self.det
        n0 = det._n
        # the first row alone, as _step judges it (the same operations on the same doubles): while
        # the probe moves it is a stop, and the window's numpy calls would cost ten times more (a
        # row called a stop here goes through _step itself, the authority, whatever this says)
        t0, x0, s1, tol = det._t0, det._x0, det._s1, det._tol
        xa = self.x[a].tolist()
        if float(self.t[a]) - t0 >= det.max_duration_s - TIME_EPS or any(
                abs((xa[k] - x0[k]) - s1[k] / n0) > tol[k] for k in range(6)):
            self._w = self.W_MIN
            return 0
        w = min(b - a, self._w)
        xs, ts = self.x[a:a + w], self.t[a:a + w]
        d = xs - np.array(det._x0)
        s1 = np.cumsum(np.vstack([np.array(det._s1)[None], d]), axis=0)     # s1 before each row, then after
        dev = d - s1[:-1] / (n0 + np.arange(w))[:, None]                    # x − x₀ − s₁/n, as _step
        stop = np.any(np.abs(dev) > np.array(det._tol), axis=1) | (ts - det._t0 >= det.max_duration_s - TIME_EPS)
        k = int(np.argmax(stop)) if stop.any() else w
        self._w = min(2 * w, self.W_MAX) if k == w else self.W_MIN
        if k:
            dk = d[:k]
            tau = ts[:k] - det._t0
            s2 = np.cumsum(np.vstack([np.array(det._s2)[None], dk * dk]), axis=0)     # before each row, then after
            st = np.cumsum(np.vstack([np.array(det._st)[None], tau[:, None] * dk]), axis=0)
            tt = np.cumsum(np.r_[det._tt, tau])
            tt2 = np.cumsum(np.r_[det._tt2, tau * tau])
            # the profile's rows that fall among these (as _add keeps them, sample by sample)
            while det._pj < len(PROFILE_AT) and tau[-1] >= PROFILE_AT[det._pj]:
                r = int(np.searchsorted(tau, PROFILE_AT[det._pj], side="left"))
                det._profile.append((float(tau[r]), float(n0 + r), *s1[r].tolist(), *s2[r].tolist(), *st[r].tolist(),
                                     float(tt[r]), float(tt2[r])))
                det._pj = bisect.bisect_right(PROFILE_AT, float(tau[r]))
            det._s1 = s1[k].tolist()
            det._s2 = s2[-1].tolist()
            det._st = st[-1].tolist()
            det._tt = float(tt[-1])
            det._tt2 = float(tt2[-1])
            det._n = n0 + k
            det._t_last = float(ts[k - 1])
            det._out = 0
        return k


class StreamPairer:
    """Pairs Imu and MagneticField samples of the same header stamp, cheaply and in time order.

    ``add_imu``/``add_mag`` return ``(t, g, m)`` when the stamp's partner is already there,
    else None.  Unpaired samples wait in small insertion-ordered dicts (the oldest is evicted
    beyond ``max_pending``: with reliable QoS on a loaded machine one topic may run hundreds of
    samples behind the other); a completed pair older than the last one emitted is dropped
    (``out_of_order``), so consumers always see increasing times.
    """

    __slots__ = ("_imu", "_mag", "max_pending", "last_t", "paired", "unpaired", "out_of_order")

    def __init__(self, max_pending: int = 4096):
        self._imu = {}
        self._mag = {}
        self.max_pending = max_pending
        self.last_t = -math.inf
        self.paired = 0
        self.unpaired = 0
        self.out_of_order = 0

    @property
    def waiting(self) -> int:
        """Samples waiting for their partner."""
        return len(self._imu) + len(self._mag)

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

    def add_imu(self, key, g):
        return self._add(key, g, self._imu, self._mag, True)

    def add_mag(self, key, m):
        return self._add(key, m, self._mag, self._imu, False)


class TemperatureTrack:
    """Temperatures (°C) by stamp; a station's temperature is the mean of those stamped within it.

    Deterministic whatever the order in which a temperature topic and the sensor topics arrive
    (a node), the same as a log's per-row temperatures (a CSV) and a bag's messages (reprocess)."""

    def __init__(self):
        self._t: list = []
        self._v: list = []

    def add(self, t: float, temp_c: float) -> None:
        if not math.isfinite(temp_c):
            return
        if self._t and t < self._t[-1]:
            k = bisect.bisect_right(self._t, t)
            self._t.insert(k, t)
            self._v.insert(k, temp_c)
        else:
            self._t.append(t)
            self._v.append(temp_c)

    def extend(self, t, temp_c) -> None:
        """:meth:`add` for arrays of stamps and temperatures (NaN ones left out), in bulk when they
        come in time order after those held."""
        t = np.asarray(t, dtype=float)
        v = np.asarray(temp_c, dtype=float)
        ok = np.isfinite(v)
        t, v = t[ok], v[ok]
        if not len(t):
            return
        if np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0) and (not self._t or t[0] >= self._t[-1]):
            self._t.extend(t.tolist())
            self._v.extend(v.tolist())
        else:
            for a, b in zip(t.tolist(), v.tolist()):
                self.add(a, b)

    @property
    def latest(self) -> float:
        return self._t[-1] if self._t else -math.inf

    def mean(self, t0: float, t1: float) -> float:
        """Mean of the temperatures stamped in [t0, t1] (NaN: none)."""
        i = bisect.bisect_left(self._t, t0 - TIME_EPS)
        j = bisect.bisect_right(self._t, t1 + TIME_EPS)
        return math.fsum(self._v[i:j]) / (j - i) if j > i else math.nan

    def forget_before(self, t: float) -> None:
        """Drop what is stamped before ``t`` (no station will ask for it again)."""
        k = bisect.bisect_left(self._t, t - TIME_EPS)
        if k > 512:     # in bulk: deleting the head of a list is a copy
            del self._t[:k]
            del self._v[:k]


def depth_per_sample(depth_messages, sample_log_times) -> np.ndarray:
    """The measured depth of each sample of a recorded stream (NaN before the first depth):
    ``depth_messages`` [(log time, m)], ``sample_log_times`` the samples' log times, both in the
    bag's one clock (a depth message has no stamp: it holds from where it was recorded)."""
    out = np.full(len(sample_log_times), np.nan)
    if not depth_messages:
        return out
    d = sorted(depth_messages)
    times = np.array([x[0] for x in d])
    vals = np.array([x[1] for x in d], dtype=float)
    k = np.searchsorted(times, np.asarray(sample_log_times), side="right") - 1
    ok = k >= 0
    out[ok] = vals[k[ok]]
    return out


class ReferenceTrack:
    """The reference attitude over time, from ``/probe/reference`` messages — ROS-free.

    Each message holds (drift, azimuth, toolface) in degrees from its stamp on (NaN: not given);
    messages may arrive late and out of order (another topic, reliable delivery repairs losses
    later), so they are kept sorted by stamp.  A station's reference is the one in effect at its
    middle — but only once the track is known to be current up to the station's end
    (:meth:`current_at`: a message stamped at or after it has arrived; the probe repeats the
    reference every second for that), else a late message would leave the station with the
    previous station's reference.  Streams without any reference never wait.
    """

    def __init__(self, keep: int = 4000):
        self._t: list = []
        self._v: list = []
        self.keep = keep
        self.latest = -math.inf     # the newest stamp received

    @property
    def seen(self) -> bool:
        return bool(self._t)

    def add(self, t: float, v) -> None:
        k = bisect.bisect_right(self._t, t)
        self._t.insert(k, t)
        self._v.insert(k, tuple(float(x) for x in v))
        self.latest = max(self.latest, t)
        if len(self._t) > self.keep:
            del self._t[:self.keep // 2], self._v[:self.keep // 2]

    def at(self, t: float):
        """The reference in effect at ``t`` (a tuple, NaN where not given), or None."""
        k = bisect.bisect_right(self._t, t) - 1
        return self._v[k] if k >= 0 and any(math.isfinite(x) for x in self._v[k]) else None

    def current_at(self, t: float) -> bool:
        """No reference can still arrive for times up to ``t`` (or there is no reference at all)."""
        return not self._t or self.latest >= t - TIME_EPS

"""The sensors' noise model from static data: Allan deviation per axis and its IEEE figures — ROS-free.

A static hold's samples of one axis are a constant (the input) plus the sensor's noise.  Their
overlapping Allan variance at averaging time ``τ`` (``allantools.oadev``'s, :func:`oadev_octaves`; the values
treated as rate data) separates the noise processes by their slope (IEEE Std 952 / 1554)::

    σ²(τ) = N²/τ  +  (2·ln2/π)·B²  +  K²·τ/3

* ``N``  white noise density (``unit·√s`` = ``unit/√Hz``; for an accelerometer the *velocity
  random walk*, m/s/√s); read as σ(τ = 1 s) on the ``τ^-1/2`` line; equals the per-sample σ over
  √(sample rate);
* ``B``  bias instability (flicker floor, ``unit``): the flat part, σ_min = 0.664·B;
* ``K``  bias random walk density (``unit/√s``): the ``τ^+1/2`` line, read as σ(τ = 3 s); a bias
  that wanders by ``K·√Δt`` over ``Δt``.

The variance at each τ is pooled over all holds (weighted by its equivalent degrees of freedom,
:func:`edf_simple`), and the three terms are fitted by non-negative weighted least squares
(the weights from those degrees of freedom, so a τ seen by few averages counts little).  A term is
*resolved* when it exceeds three of its standard deviations; otherwise its one-sided 95 % upper
bound is what the data say.

Short holds (a few seconds) see the white noise well but rarely a random walk that matters over a
survey: its ``τ^+1/2`` line crosses the white-noise line only at ``τ = √3·N/K`` (minutes for a
magnetometer wandering by 10 nT over a quarter of an hour).  The walk is then measured across the
holds (:func:`sequence_walk`): the difference of two consecutive stations' residuals (the model's
misfit, the white noise of their means taken out) grows as ``K²·Δt`` — the same two-sample
statistic at ``τ`` = the spacing of the stations.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..core.memo import CopyMemo

#: (2·ln2/π): the Allan variance of flicker noise of bias instability B is this times B².
FLICKER = 2.0 * math.log(2.0) / math.pi
#: A noise term is resolved when it exceeds this many of its standard deviations.
RESOLVED_Z = 3.0
#: One-sided 95 % quantile (for upper bounds of unresolved terms).
Z95 = 1.645
UNITS = {"acc": "m/s^2", "mag": "nT"}
#: The last curves computed, by their segments' content: the lab takes the noise model of the same
#: holds again and again (each diagnosis, its stochastic check, every step of a ladder), and
#: ``allantools.oadev`` per hold and axis is most of its cost (a third of a diagnosis).
CURVE_CACHE_SIZE = 16
_curves = CopyMemo(CURVE_CACHE_SIZE)


@dataclass
class AllanCurve:
    """Pooled overlapping Allan deviation of one sensor's three axes.

    ``tau`` (s, ascending); ``adev`` (len(tau), 3) in the sensor's unit; ``edf`` (len(tau), 3)
    equivalent degrees of freedom of each point (summed over the holds that reach that τ; per
    hold the fewer of white and random-walk noise's, :func:`edf_simple`)."""

    tau: np.ndarray
    adev: np.ndarray
    edf: np.ndarray
    rate_hz: float
    n_segments: int


def allan_curve(segments, rate_hz: float | None = None) -> AllanCurve:
    """Pooled overlapping Allan deviation per axis over static segments.

    ``segments``: iterable of (n, 1 + 3) arrays of time (s) and one sensor's three axes (any unit),
    each a static hold (no motion: its mean is the input).  ``rate_hz``: the sampling rate; by
    default the median of the segments' sample intervals.  At each octave ``τ = 2^j / rate`` up to
    a third of the longest segment, the Allan variance of every segment long enough
    (``n ≥ 3·m``) is averaged, weighted by its degrees of freedom.
    """
    segs = [np.asarray(s, dtype=float) for s in segments if s is not None and len(s) >= 3]
    if not segs:
        return AllanCurve(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), float("nan"), 0)
    h = hashlib.blake2b(repr(rate_hz).encode(), digest_size=20)
    for s in segs:
        h.update(np.ascontiguousarray(s).tobytes())
        h.update(str(s.shape).encode())
    key = h.digest()
    if key in _curves:
        return _curves.get(key)
    curve = _allan_curve(segs, rate_hz)
    _curves.put(key, curve)
    return curve


def _allan_curve(segs, rate_hz):
    """:func:`allan_curve` of the usable segments, computed."""
    if rate_hz is None:
        dts = np.concatenate([np.diff(s[:, 0]) for s in segs])
        dts = dts[dts > 0]
        rate_hz = 1.0 / float(np.median(dts)) if len(dts) else 1.0
    n_max = max(len(s) for s in segs)
    ms = 2 ** np.arange(0, max(int(math.log2(max(n_max // 3, 1))) + 1, 1))
    acc = np.zeros((len(ms), 3))
    wsum = np.zeros((len(ms), 3))
    edf = {}
    for s in segs:
        n = len(s)
        ok = ms[3 * ms <= n]
        if not len(ok):
            continue
        x = s[:, 1:4].T            # axis by axis, each row contiguous (its sums as of a 1-D array's)
        use = np.all(np.isfinite(x), axis=1) & (np.ptp(x, axis=1) != 0)   # a flat or broken axis says nothing
        if not use.any():
            continue
        ad = oadev_octaves(np.ascontiguousarray(x[use]), rate_hz, ok)
        for k, m in enumerate(ok):
            if (n, m) not in edf:        # the same for every axis of a hold: worked out once
                # the fewer of white and random-walk noise's (the process is not known yet)
                edf[n, m] = min(edf_simple(n, int(m), 0), edf_simple(n, int(m), -2))
            e = edf[n, m]
            i = int(np.searchsorted(ms, m))
            for j, a in zip(np.flatnonzero(use), ad[:, k]):
                if np.isfinite(a):
                    acc[i, j] += e * a ** 2
                    wsum[i, j] += e
    keep = np.any(wsum > 0, axis=1)        # an axis without data at a τ (flat, broken) is NaN there
    with np.errstate(invalid="ignore", divide="ignore"):
        adev = np.where(wsum[keep] > 0, np.sqrt(acc[keep] / np.where(wsum[keep] > 0, wsum[keep], 1.0)), np.nan)
    return AllanCurve(ms[keep] / rate_hz, adev, wsum[keep], float(rate_hz), len(segs))


def edf_simple(n: int, m: int, alpha: int) -> float:
    """Equivalent degrees of freedom of the overlapping Allan variance of ``n`` phase samples at
    averaging factor ``m``, for white frequency noise (``alpha`` 0) or random-walk frequency
    noise (``alpha`` −2): the simple approximations of NIST SP 1065, Table 5 (Howe, Allan and
    Barnes; ``allantools.edf_simple``'s numbers, test/detect/test_allan.py holds them equal —
    computed here because importing allantools, for these two lines, took 0.65 CPU-s of every
    process that computes a noise model)::

        white FM:        edf = [3(N−1)/(2m) − 2(N−2)/N] · 4m²/(4m² + 5)
        random-walk FM:  edf = (N−2)/(m(N−3)²) · [(N−1)² − 3m(N−1) + 4m²]

    The random-walk formula's limit at ``N`` = 3 (a hold of three samples, the shortest that has
    an Allan variance) is +∞, returned as such (allantools divides by zero there), so that the
    fewer of the two is the white noise's.
    """
    n, m = float(n), float(m)
    if alpha == 0:
        return ((3 * (n - 1) / (2 * m)) - (2 * (n - 2) / n)) * ((4 * pow(m, 2)) / ((4 * pow(m, 2)) + 5))
    if alpha == -2:
        if n == 3.0:
            return math.inf
        return (n - 2) / (m * (n - 3) ** 2) * ((n - 1) ** 2 - 3 * m * (n - 1) + 4 * m ** 2)
    raise ValueError(f"edf_simple: alpha {alpha} is not 0 (white FM) or -2 (random-walk FM)")


def oadev_octaves(x, rate_hz: float, ms) -> np.ndarray:
    """Overlapping Allan deviation of the rate data ``x`` (finite: one axis of a hold, or a row per
    axis) at the averaging factors ``ms`` (each with ``3·m ≤`` the samples): per row
    ``allantools.oadev(x, rate=rate_hz, data_type="freq", taus=ms / rate_hz)``'s values — the same
    operations on the same numbers, each row's sums along its contiguous samples as of a 1-D array
    (so the same bits: test/detect/test_allan.py holds them equal) — without its per-call
    preparation of the τ list, and the axes of a hold at once (a diagnosis took a third of its time
    in ``oadev``).  NIST SP 1065 eq. (11): the phase ``x_k = Σ (y − ȳ)·τ₀`` and
    ``σ²(mτ₀) = Σ (x_{k+2m} − 2x_{k+m} + x_k)² / (2 (mτ₀)² (N − 2m))``."""
    x = np.asarray(x, dtype=float)
    one = x.ndim == 1
    x = np.atleast_2d(x)
    # allantools.frequency2phase: the mean taken off before the sum (its precision), a 0 in front
    phase = np.insert(np.cumsum(x - np.mean(x, axis=1, keepdims=True), axis=1) * (1.0 / float(rate_hz)), 0, 0, axis=1)
    out = np.empty((len(x), len(ms)))
    for k, m in enumerate(ms):
        m = int(m)
        n = phase.shape[1] - 2 * m          # allantools.calc_adev_phase with stride 1
        v = phase[:, 2 * m:][:, :n] - 2 * phase[:, m:][:, :n] + phase[:, :n]
        out[:, k] = np.sqrt(np.sum(v * v, axis=1) / (2.0 * n)) / m * rate_hz
    return out[0] if one else out


@dataclass
class NoiseTerm:
    """One noise figure of one axis: value, 1σ, and whether the data resolve it (else ``value``
    is 0 and ``upper`` the one-sided 95 % bound)."""

    value: float
    std: float
    resolved: bool
    upper: float
    source: str = "holds"
    #: The test statistic against the term being zero: (value²/σ(value²))² from the holds, the
    #: likelihood ratio from a station sequence.
    chi2: float = float("nan")

    def to_json(self) -> dict:
        return {"value": self.value, "std": self.std, "resolved": self.resolved, "upper95": self.upper,
                "source": self.source, "chi2": self.chi2}


def fit_terms(curve: AllanCurve) -> list:
    """Fit ``σ²(τ) = N²/τ + (2·ln2/π)·B² + K²·τ/3`` per axis; returns per axis a dict of
    :class:`NoiseTerm` ``N``, ``B``, ``K`` (units: sensor unit·√s, unit, unit/√s).

    Non-negative weighted least squares on the variances, each weighted by ``√(edf/2)/σ²`` (the
    relative standard deviation of a variance with ``edf`` degrees of freedom is ``√(2/edf)``; σ²
    the model's, iterated);
    the standard deviations from the weighted normal matrix, scaled by the fit's reduced χ² when
    it exceeds 1 (a process the three terms do not describe)."""
    from scipy.optimize import nnls   # here, as below: scipy.optimize is 0.2 s of every process importing the lab
    out = []
    tau = curve.tau
    a = np.column_stack([1.0 / tau, np.full(len(tau), FLICKER), tau / 3.0]) if len(tau) else np.zeros((0, 3))
    for j in range(3):
        ok = np.isfinite(curve.adev[:, j]) if len(tau) else np.zeros(0, bool)
        if ok.sum() < 2:
            out.append({k: NoiseTerm(float("nan"), float("nan"), False, float("nan")) for k in "NBK"})
            continue
        y = curve.adev[ok, j] ** 2
        x = None
        # weights from the model's variance, not the measured one (which would favour the points
        # that came out low by chance); iterated from the measured
        for _ in range(4):
            pred = y if x is None else np.maximum(a[ok] @ x, 1e-300)
            w = np.sqrt(curve.edf[ok, j] / 2.0) / pred
            aw = a[ok] * w[:, None]
            scale = np.linalg.norm(aw, axis=0)
            scale[scale == 0] = 1.0
            x_s, _ = nnls(aw / scale, y * w)
            x = x_s / scale
        r = aw @ x - y * w
        dof = max(len(y) - int(np.sum(x > 0)), 1)
        infl = max(float(r @ r) / dof, 1.0)
        cov = np.linalg.pinv((aw / scale).T @ (aw / scale)) / np.outer(scale, scale) * infl
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        terms = {}
        for k, name in enumerate("NBK"):
            v2, s2 = float(x[k]), float(sd[k])
            resolved = v2 > RESOLVED_Z * s2 and v2 > 0
            v = math.sqrt(v2) if resolved else 0.0
            sv = s2 / (2.0 * v) if resolved else float("nan")
            terms[name] = NoiseTerm(v, sv, bool(resolved), math.sqrt(max(v2, 0.0) + Z95 * s2),
                                    chi2=(v2 / s2) ** 2 if s2 > 0 else float("nan"))
        out.append(terms)
    return out


def _pairs(t, r, s, g, dur):
    """Consecutive-station differences of one axis: (walk variance per K² on the diagonal and
    beside it, d, σ₁², σ₂², shares-a-station-with-next)."""
    ok = (g[1:] == g[:-1]) & (np.diff(t) > 0) & np.isfinite(r[1:]) & np.isfinite(r[:-1])
    idx = np.flatnonzero(ok)
    # two stations' means are averages of the walk over their holds: Var(m₂ − m₁) = K²·(Δc − (T₁+T₂)/6),
    # and consecutive differences sharing a station covary by K²·T/6
    walk = (t[1:] - t[:-1])[idx] - (dur[1:] + dur[:-1])[idx] / 6.0
    shared = dur[1:][idx] / 6.0
    d = (r[1:] - r[:-1])[idx]
    s1, s2 = s[:-1][idx] ** 2, s[1:][idx] ** 2
    chained = np.zeros(len(idx), bool)
    chained[:-1] = idx[1:] == idx[:-1] + 1     # pair i's second station is pair i+1's first
    return walk, shared, d, s1, s2, chained


def _walk_nll(k2, dt, shared, d, s1, s2, chained) -> float:
    """Negative log-likelihood (up to a constant) of the differences ``d`` under a random walk of
    density² ``k2`` plus white noise of the station means: ``Cov(d) = k2·W + T``, ``W`` the walk's
    (``Δt − (T₁+T₂)/6`` on the diagonal, ``T/6`` of a shared station beside it), ``T`` the noise's
    (``σ₁² + σ₂²`` on the diagonal, ``−σ²`` of a shared station beside it); by the banded Cholesky
    factor."""
    from scipy.linalg import cho_solve_banded, cholesky_banded
    diag = k2 * dt + s1 + s2
    off = np.where(chained[:-1], k2 * shared[:-1] - s2[:-1], 0.0)
    ab = np.zeros((2, len(d)))
    ab[0, 1:] = off
    ab[1] = diag
    try:
        c = cholesky_banded(ab)
    except np.linalg.LinAlgError:
        return float("inf")
    z = cho_solve_banded((c, False), d)
    return float(np.sum(np.log(c[1])) + 0.5 * d @ z)


def sequence_walk(time_s, residual, sigma, group=None, duration=None) -> list:
    """The bias random walk density per axis from a sequence of stations (``unit/√s``).

    ``time_s`` (N,), ``residual`` (N, 3) the model's misfit at each station (sensor unit; a
    wandering bias is in it), ``sigma`` (N, 3) the white-noise σ of each station's mean; ``group``
    (N,) optional: only consecutive stations of one group are paired; ``duration`` (N,) optional:
    each station's hold (s; ``time_s`` its centre) — a station's mean is the walk averaged over
    it.  The differences of consecutive stations ``d = r₂ − r₁`` (the constant level drops out) are
    Gaussian with ``Cov(d) = K²·W + T`` (``W`` the walk's, ``Δc − (T₁+T₂)/6`` for centres ``Δc``
    apart: the Brownian covariance of two window means; ``T`` the stations' white noise; both
    tridiagonal): ``K²`` by maximum
    likelihood; resolved when the likelihood ratio against ``K = 0`` exceeds 9 (≈ 3σ, one-sided),
    its 1σ from the likelihood's curvature, the upper bound where the profile likelihood drops
    by 1.35 (one-sided 95 %).  Returns per axis a :class:`NoiseTerm` (source ``stations``)."""
    from scipy.optimize import brentq, minimize_scalar
    t = np.asarray(time_s, dtype=float)
    r = np.asarray(residual, dtype=float)
    s = np.asarray(sigma, dtype=float)
    g = np.zeros(len(t)) if group is None else np.asarray(group)
    dur = np.zeros(len(t)) if duration is None else np.nan_to_num(np.asarray(duration, dtype=float))
    order = np.argsort(t, kind="stable")
    t, r, s, g, dur = t[order], r[order], s[order], g[order], dur[order]
    out = []
    for j in range(3):
        dt, shared, d, s1, s2, chained = _pairs(t, r[:, j], s[:, j], g, dur)
        if len(d) < 4:
            out.append(NoiseTerm(float("nan"), float("nan"), False, float("nan"), "stations"))
            continue
        f = partial(_walk_nll, dt=dt, shared=shared, d=d, s1=s1, s2=s2, chained=chained)
        # K² spans from far below to far above what the differences could show
        unit = float(np.median((s1 + s2) / dt))
        hi = max(float(np.mean(d ** 2 / dt)) * 10.0, unit)
        lo = unit * 1e-6
        res = minimize_scalar(lambda x: f(math.exp(x)), bounds=(math.log(lo), math.log(hi)), method="bounded",
                              options={"xatol": 1e-4})
        k2, nll_min = math.exp(res.x), float(res.fun)
        nll0 = f(0.0)
        if nll0 < nll_min:
            k2, nll_min = 0.0, nll0
        lr = 2.0 * (nll0 - nll_min)
        resolved = lr > RESOLVED_Z ** 2
        h = max(k2 * 1e-2, unit * 1e-4)
        curv = (f(k2 + h) - 2.0 * f(k2) + f(max(k2 - h, 0.0))) / h ** 2 if k2 > h else (f(k2 + 2 * h) - 2 * f(k2 + h) + f(k2)) / h ** 2
        sd = 1.0 / math.sqrt(curv) if curv > 0 else float("nan")
        try:
            up = brentq(lambda x: 2.0 * (f(x) - nll_min) - Z95 ** 2, k2, hi * 10.0)
        except ValueError:
            up = hi * 10.0
        v = math.sqrt(k2) if resolved else 0.0
        out.append(NoiseTerm(v, sd / (2.0 * v) if resolved and v > 0 else float("nan"), bool(resolved),
                             math.sqrt(up), "stations", chi2=lr))
    return out


@dataclass
class SensorNoise:
    """The noise model of one sensor: the pooled Allan curve and per axis the figures ``N``,
    ``B``, ``K`` (:class:`NoiseTerm`); ``K`` is the holds' when they resolve it, else the station
    sequence's (:func:`sequence_walk`) when given."""

    sensor: str
    curve: AllanCurve
    terms: list = field(default_factory=list)

    @property
    def unit(self) -> str:
        return UNITS.get(self.sensor, "")

    def walk_density(self) -> np.ndarray:
        """``K`` per axis (unit/√s) where resolved, else 0."""
        return np.array([t["K"].value if t["K"].resolved else 0.0 for t in self.terms])

    def table(self) -> list:
        """Rows per axis with the IEEE-style figures and their units."""
        u = self.unit
        rows = []
        for a, t in zip("xyz", self.terms):
            rows.append({"axis": f"{self.sensor} {a}",
                         "white_noise": t["N"].to_json() | {"unit": f"{u}/sqrt(Hz)"},
                         "bias_instability": t["B"].to_json() | {"unit": u},
                         "random_walk": t["K"].to_json() | {"unit": f"{u}/sqrt(s)"}})
        return rows

    def to_json(self) -> dict:
        c = self.curve
        return {"sensor": self.sensor, "rate_hz": c.rate_hz, "segments": c.n_segments,
                "tau_s": [float(x) for x in c.tau], "adev": [[float(v) for v in row] for row in c.adev],
                "figures": self.table()}


def sensor_noise(sensor: str, segments, sequence=None, rate_hz=None) -> SensorNoise:
    """The noise model of ``sensor`` from its static segments (see :func:`allan_curve`) and,
    optionally, a station sequence ``(time_s, residual, sigma[, group])`` for the random walk
    across holds (:func:`sequence_walk`)."""
    curve = allan_curve(segments, rate_hz)
    terms = fit_terms(curve)
    if sequence is not None:
        seq = sequence_walk(*sequence)
        for t, k in zip(terms, seq):
            held = t["K"]
            # the holds' own figure when they resolve it and are the sharper; else the sequence's
            if not (held.resolved and (not k.resolved or held.std <= k.std)) and np.isfinite(k.upper):
                t["K"] = k
    return SensorNoise(sensor, curve, terms)


def format_noise(models) -> str:
    """Plain-text table of the noise figures (one line per axis)."""

    def cell(t, unit):
        if not np.isfinite(t.upper):
            return "n/a"
        src = " (stations)" if t.source == "stations" else ""
        return (f"{t.value:.3g} ± {t.std:.2g} {unit}" if t.resolved else f"< {t.upper:.2g} {unit}") + src

    rows = [("axis", "white noise N", "bias instability B", "random walk K")]
    for m in models:
        u = m.unit
        for a, t in zip("xyz", m.terms):
            rows.append((f"{m.sensor} {a}", cell(t["N"], u + "/√Hz"), cell(t["B"], u), cell(t["K"], u + "/√s")))
    w = [max(len(r[i]) for r in rows) for i in range(4)]
    return "\n".join(f"{r[0]:<{w[0]}}  {r[1]:>{w[1]}}  {r[2]:>{w[2]}}  {r[3]:>{w[3]}}" for r in rows)

"""Sensor noise estimated from the data itself — ROS-free.

Static detection, pose capture and the acceptance gates all compare what they see with the
probe's noise.  A fixed assumption (say 0.002 m/s² and 20 nT) cuts every hold of a noisier probe
into pieces and lets a quieter one move unnoticed, so the noise is measured from the stream:

* the samples are cut into short blocks (``block_s`` of time, at least ``min_block_samples``);
* each block gives a per-axis sample standard deviation ``s`` (6 axes: accelerometer x, y, z in
  m/s², magnetometer x, y, z in nT);
* blocks taken while the probe moves have a large ``s``, blocks of a hold have ``s ≈ σ``.  The
  estimate is robust to motion in a majority of the blocks: a low quantile ``q`` (10 %) of the
  recent blocks' ``s``, unbiased by the same quantile of ``sqrt(χ²(n-1)/(n-1))`` (the
  distribution of ``s/σ`` for white noise over ``n`` samples), gives a first ``σ₀``; the blocks
  with ``s`` below the 0.999 quantile of that distribution (times ``σ₀``) are taken as static and
  their pooled variance is the estimate, ``σ² = mean(s²)`` (``E[s²] = σ²``; the cut removes a
  0.1 % white-noise tail and the slow starts and ends of moves, which a looser cut lets in and
  which inflate the estimate by several per cent);
* blocks in which an axis did not change at all (``s = 0``: a clipped, saturated or stuck axis)
  are left out — they say nothing about the noise and would drag the low quantile to zero; an
  axis that did not change in most blocks takes the noise of its triad's other axes
  (:func:`fill_flat_axes`; 0 only when no axis of the sensor shows noise: noiseless data).

The estimate is valid as soon as ``ready_blocks`` blocks of together ``ready_samples`` samples
have been seen; it keeps adapting over the last ``history_s`` seconds.  An explicit value (a node parameter, a CLI option) overrides the
data for that sensor; a stated noise (``sensor_msgs`` covariance) is kept as a *prior*: used
only until the data give an estimate, and compared with it (:meth:`NoiseEstimator.check_prior`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..core.specfun import gammaincinv

AXES6 = ("acc x", "acc y", "acc z", "mag x", "mag y", "mag z")
UNITS6 = ("m/s^2",) * 3 + ("nT",) * 3
#: The quantile of the block scatters used for the first, motion-robust estimate.
LOW_QUANTILE = 0.10
#: Blocks whose scatter exceeds this quantile of ``s/σ₀`` (white noise) are taken as motion.
STATIC_QUANTILE = 0.999
#: A stated noise (prior) and the measured one disagreeing by more than this factor is reported.
PRIOR_MISMATCH = 2.0
#: Blocks in the history from which the estimate is recomputed every 16th block, not every 4th.
LONG_HISTORY = 256


@lru_cache(maxsize=256)
def chi_quantile(n: int, q: float = LOW_QUANTILE) -> float:
    """Quantile ``q`` of ``s/σ`` for the sample std ``s`` of ``n`` white-noise samples:
    ``sqrt(χ²_q(n-1) / (n-1))``."""
    dof = max(int(n) - 1, 1)
    # χ²_q(k) = 2·P⁻¹(k/2, q), what scipy.stats' chi2.ppf computes (core.specfun: without
    # scipy.special's 0.25 CPU-s of imports in every node and CLI command that finds stations)
    return math.sqrt(2.0 * gammaincinv(0.5 * dof, q) / dof)


def estimate_from_blocks(block_std: np.ndarray, block_n: float) -> np.ndarray:
    """Per-axis noise σ from block standard deviations (rows: blocks, columns: axes).

    ``block_n`` is the typical number of samples per block.  NaN for an axis without usable
    blocks.  See the module docstring for the estimator.  Vectorized over the axes (about 40 µs
    for 1200 blocks × 6 axes).
    """
    s = np.asarray(block_std, dtype=float)
    if s.ndim != 2 or len(s) == 0:
        return np.full(s.shape[-1] if s.ndim == 2 else 6, np.nan)
    n = int(round(block_n))
    c, cut = chi_quantile(n), chi_quantile(n, STATIC_QUANTILE)
    # s == 0 (or NaN): the axis did not change at all in that block (clipped/stuck): left out
    usable = np.isfinite(s) & (s > 0.0)
    # blocks per axis counted as ones @ mask: whole numbers, exact in any order, in a third of the
    # time of a boolean sum down the columns (this runs every 1-4 s of a live stream)
    ones = np.ones(len(s))
    count = ones @ usable
    k = np.maximum(np.floor(LOW_QUANTILE * (count - 1)).astype(int), 0)
    # the k-th smallest of each axis: a partition puts it where a sort would
    low = np.partition(np.where(usable, s, np.inf), np.unique(k), axis=0)
    sigma0 = low[k, np.arange(s.shape[1])] / c
    # pooled variance of the blocks below the cut, the cut re-drawn from the pooled value: a low
    # quantile of few short blocks is itself noisy, and a first cut drawn from it too low would
    # leave out static blocks and bias the estimate down (three rounds converge)
    out = sigma0
    s2 = s * s
    for _ in range(3):
        keep = usable & (s <= cut * out)
        nk = ones @ keep
        with np.errstate(invalid="ignore", divide="ignore"):
            pooled = np.sqrt(np.where(keep, s2, 0.0).sum(axis=0) / nk)
        out = np.where(nk > 0, pooled, out)
    # an axis that did not change in most blocks (stuck, clipped throughout, noiseless or quantized
    # far below its resolution): its noise is 0, known — not the scatter of the moves left over;
    # NaN only where there are no blocks at all
    finite = ones @ np.isfinite(s)
    flat = (2 * count < finite)
    return np.where(finite == 0, np.nan, np.where(flat, 0.0, out))


def fill_flat_axes(sigma6) -> tuple:
    """An axis flat in most blocks (σ 0) while the same sensor's other axes show noise takes their
    median: a clipped or stuck axis still has the noise of its triad once it moves again, and a
    threshold of 0 would cut every hold on it.  (A sensor with no noise at all keeps 0.)"""
    out = list(sigma6)
    for k in (0, 3):
        trio = out[k:k + 3]
        noisy = [v for v in trio if math.isfinite(v) and v > 0]
        if noisy and len(noisy) < 3:
            fill = float(np.median(noisy))
            out[k:k + 3] = [fill if v == 0 else v for v in trio]
    return tuple(out)


@dataclass(frozen=True)
class NoiseLevel:
    """Per-axis white-noise σ of one sample: ``acc`` (3,) m/s², ``mag`` (3,) nT, and where each
    sensor's value comes from (``data``, ``prior`` = stated in the messages, ``override`` =
    set by the user, ``none``)."""

    acc: tuple
    mag: tuple
    acc_source: str
    mag_source: str
    blocks: int = 0

    @property
    def sigma6(self) -> tuple:
        return tuple(self.acc) + tuple(self.mag)

    def describe(self) -> str:
        def fmt(v, unit, src):
            vals = "/".join(f"{x:.3g}" for x in v) if all(math.isfinite(x) for x in v) else "unknown"
            return f"{vals} {unit} ({src})"
        return (f"noise per sample x/y/z: accelerometer {fmt(self.acc, 'm/s^2', self.acc_source)}, "
                f"magnetometer {fmt(self.mag, 'nT', self.mag_source)}")


class NoiseEstimator:
    """Streaming per-axis noise estimate (see the module docstring).

    Feed every sample with :meth:`add` (time s, six floats: specific force m/s² or gravity
    vector — the sign does not matter — and field nT).  :attr:`level` is the current
    :class:`NoiseLevel`; :attr:`ready` says whether the data have produced one yet.

    ``override_acc`` / ``override_mag`` (> 0): that sensor's σ is this value, whatever the data.
    """

    def __init__(self, block_s: float = 0.25, min_block_samples: int = 5, history_s: float = 300.0,
                 ready_blocks: int = 8, ready_samples: int = 100, override_acc: float = 0.0,
                 override_mag: float = 0.0):
        if not block_s > 0 or min_block_samples < 3 or not history_s > 0 or ready_blocks < 1:
            raise ValueError("NoiseEstimator: block_s and history_s must be > 0, min_block_samples >= 3, "
                             "ready_blocks >= 1")
        self.block_s = float(block_s)
        self.min_block_samples = int(min_block_samples)
        self.ready_blocks = int(ready_blocks)
        self.ready_samples = int(ready_samples)
        self._samples = 0          # samples in closed blocks
        self._cap = max(int(math.ceil(history_s / block_s)), 4 * ready_blocks)
        self._std = np.full((self._cap, 6), np.nan)
        self._nb = np.zeros(self._cap)
        self._count = 0            # blocks seen in all
        self.override = (float(override_acc), float(override_mag))
        self.prior = (math.nan, math.nan)   # stated σ (from message covariance), per sensor
        self._sigma = (math.nan,) * 6
        self._reset_block()

    def _reset_block(self):
        self._bn = 0
        self._bt0 = 0.0
        self._bx0 = [0.0] * 6
        self._b1 = [0.0] * 6
        self._b2 = [0.0] * 6

    # ---- feeding ---------------------------------------------------------------------------
    def add(self, t: float, x) -> bool:
        """Add one sample (six finite floats).  True when a block closed (the estimate may have moved)."""
        n = self._bn
        if n == 0:
            self._bt0 = t
            self._bx0 = list(x)
        x0, b1, b2 = self._bx0, self._b1, self._b2
        for k in range(6):
            d = x[k] - x0[k]
            b1[k] += d
            b2[k] += d * d
        self._bn = n + 1
        # (1e-6 s: times nominally one block apart close it alike as text or as bag stamps)
        if self._bn >= self.min_block_samples and t - self._bt0 >= self.block_s - 1e-6:
            self._close_block()
            return True
        return False

    def gap(self):
        """A break in the stream (non-finite sample, time jump): the open block is discarded."""
        self._reset_block()

    @property
    def block_open(self) -> int:
        """Samples in the open block (0: the last sample closed one, or a gap discarded it)."""
        return self._bn

    def _close_block(self):
        n = self._bn
        std = [math.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1)) for s1, s2 in zip(self._b1, self._b2)]
        self.add_block(n, std)

    def add_block(self, n: int, std) -> None:
        """A block closed: its ``n`` samples' per-axis standard deviation ``std`` (6).  What
        :meth:`add` does when a block closes; a batch path (``StaticDetector.run``) that computes
        the blocks at once calls it in their order."""
        i = self._count % self._cap
        self._std[i] = std
        self._nb[i] = n
        self._count += 1
        self._samples += n
        self._reset_block()
        m = min(self._count, self._cap)
        if self.estimate_due():
            self._sigma = fill_flat_axes(float(v) for v in estimate_from_blocks(self._std[:m],
                                                                                 float(np.median(self._nb[:m]))))

    def estimate_due(self, blocks: int = 0, samples: int = 0) -> bool:
        """Whether the estimate is recomputed at the close of the block that brings the closed ones
        ``blocks`` more, with ``samples`` more samples (0, 0: the last one closed): once it
        stands, every fourth block (about once a second), and once the history holds
        :data:`LONG_HISTORY` blocks every sixteenth (about every 4 s): sixteen new blocks of
        256 or more move its low quantile and pooled variance by a few per cent at most, and
        the recomputation over a full history (1200 blocks) was a third of the detection's CPU
        time on a long log."""
        count = self._count + blocks
        m = min(count, self._cap)
        return (m >= self.ready_blocks and self._samples + samples >= self.ready_samples
                and (m <= 4 * self.ready_blocks or count % (4 if m < LONG_HISTORY else 16) == 0))

    def force(self) -> None:
        """Estimate from the blocks there are, even fewer than ``ready_blocks`` (a short stream)."""
        m = min(self._count, self._cap)
        if m:
            self._sigma = fill_flat_axes(float(v) for v in estimate_from_blocks(self._std[:m],
                                                                                 float(np.median(self._nb[:m]))))

    # ---- results ---------------------------------------------------------------------------
    @property
    def blocks(self) -> int:
        return self._count

    @property
    def ready(self) -> bool:
        """The data have produced an estimate for every sensor not overridden."""
        need = [k for k in range(2) if not self.override[k] > 0]
        return all(all(math.isfinite(v) for v in self._sigma[3 * k:3 * k + 3]) for k in need)

    def set_prior(self, acc: float | None = None, mag: float | None = None) -> None:
        """The noise the messages state (σ per axis, from their covariance), if > 0."""
        a, m = self.prior
        if acc is not None and acc > 0 and math.isfinite(acc):
            a = float(acc)
        if mag is not None and mag > 0 and math.isfinite(mag):
            m = float(mag)
        self.prior = (a, m)

    @property
    def level(self) -> NoiseLevel:
        sig = self._sigma
        vals, srcs = [], []
        for k in range(2):
            data = sig[3 * k:3 * k + 3]
            if self.override[k] > 0:
                vals.append((self.override[k],) * 3)
                srcs.append("override")
            elif all(math.isfinite(v) for v in data):
                vals.append(tuple(data))
                srcs.append("data")
            elif self.prior[k] > 0:
                vals.append((self.prior[k],) * 3)
                srcs.append("prior")
            else:
                vals.append((math.nan,) * 3)
                srcs.append("none")
        return NoiseLevel(vals[0], vals[1], srcs[0], srcs[1], self._count)

    @property
    def measured(self) -> tuple:
        """The six σ as the data show them (or as the messages state them, until the data do),
        whatever the overrides: what the gates compare a station's scatter with."""
        out = []
        for k in range(2):
            data = self._sigma[3 * k:3 * k + 3]
            if all(math.isfinite(v) for v in data):
                out.extend(data)
            elif self.prior[k] > 0:
                out.extend((self.prior[k],) * 3)
            elif self.override[k] > 0:
                out.extend((self.override[k],) * 3)
            else:
                out.extend((math.nan,) * 3)
        return tuple(out)

    def check_prior(self) -> list:
        """Messages comparing the stated noise (prior) with the measured one, where they disagree
        by more than :data:`PRIOR_MISMATCH`×."""
        out = []
        for k, (name, unit) in enumerate((("accelerometer", "m/s^2"), ("magnetometer", "nT"))):
            data = self._sigma[3 * k:3 * k + 3]
            p = self.prior[k]
            if not (p > 0) or not all(math.isfinite(v) for v in data) or self.override[k] > 0:
                continue
            d = sorted(data)[1]   # the median of the three (np.median's value; called at every block until they differ)
            if d > PRIOR_MISMATCH * p or p > PRIOR_MISMATCH * d:
                out.append(f"{name}: the messages state a noise of {p:.3g} {unit} (covariance) but the data show "
                           f"{d:.3g} {unit}; using the data")
        return out


def estimate_noise(t, acc, mag, block_s: float = 0.25, min_block_samples: int = 5) -> NoiseLevel:
    """The noise of a whole log: the estimator of :class:`NoiseEstimator` over all its blocks.

    ``t`` (N,) s, ``acc`` (N, 3) m/s², ``mag`` (N, 3) nT.  Blocks hold a fixed number of samples
    (``block_s`` at the log's median sample interval, at least ``min_block_samples``) and do not
    span non-finite samples.  Vectorized: about 50 ms for 10⁶ samples.
    """
    t = np.asarray(t, float)
    x = np.concatenate([np.asarray(acc, float), np.asarray(mag, float)], axis=1)
    finite = np.all(np.isfinite(x), axis=1) & np.isfinite(t)
    dt = np.diff(t[finite])
    dt = dt[dt > 0]
    per = max(int(min_block_samples), int(round(block_s / float(np.median(dt)))) if len(dt) else min_block_samples)
    stds = []
    # runs of finite samples, cut into whole blocks of `per` samples
    edges = np.flatnonzero(np.diff(np.r_[0, finite.astype(np.int8), 0]))
    for a, b in zip(edges[::2], edges[1::2]):
        nb = (b - a) // per
        if nb:
            blk = x[a:a + nb * per].reshape(nb, per, 6)
            stds.append(blk.std(axis=1, ddof=1))
    if not stds:
        return NoiseLevel((math.nan,) * 3, (math.nan,) * 3, "none", "none", 0)
    s = np.concatenate(stds)
    sig = np.array(fill_flat_axes(float(v) for v in estimate_from_blocks(s, per)))
    src = ["data" if np.all(np.isfinite(sig[3 * k:3 * k + 3])) else "none" for k in range(2)]
    return NoiseLevel(tuple(float(v) for v in sig[:3]), tuple(float(v) for v in sig[3:]), src[0], src[1], len(s))

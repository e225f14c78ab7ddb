"""The one regression test of the lab's diagnosis and of the field monitor.

Does a set of regressors explain a residual channel beyond chance?  An F-test of nested linear
models: ``y = a + ε`` against ``y = a + X·c + ε`` (least squares, an intercept in both), with the
residual variance estimated from the data — so "significant" means beyond the scatter the
channel shows, whatever its unit.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.specfun import fdtrc, stdtr


@dataclass
class Trend:
    """The outcome of :func:`regress`: the F statistic with its ``k`` and ``dof`` degrees of
    freedom and its p-value, the share of the channel's variance the regressors explain (R²),
    the coefficients (per regressor), the RMS of the explained part and the scatter left (in the
    channel's unit), the number of points.

    ``p = P(F(k, dof) > f)`` is computed when first read (:func:`specfun.fdtrc`, a continued
    fraction in Python: about 20 µs, half of the field monitor's regressions' time when each
    took it; the monitor reads it only for a trend large enough to matter)."""

    f: float
    k: int
    dof: int
    r2: float
    coef: np.ndarray
    explained_rms: float
    residual_rms: float
    n: int
    _p: float | None = field(default=None, repr=False, compare=False)

    @property
    def p(self) -> float:
        if self._p is None:
            self._p = fdtrc(self.k, self.dof, self.f)
        return self._p


def regress(y, x) -> Trend | None:
    """F-test of the regressors ``x`` ((N,) or (N, k)) on the channel ``y`` (N,), NaNs left out.

    None when it cannot be tested (too few points, no regressor that varies, a perfect fit)."""
    return regress_many([(y, x)])[0]


def regress_many(pairs) -> list:
    """:func:`regress` of each ``(y, x)`` pair, in order: the same test, in fewer numpy calls.

    The pairs without a NaN are fitted together, stacked by shape (one SVD call per shape, numpy's
    stacked linear algebra): each one's figures are those it gets alone, bit for bit (the same
    operations on each pair's own numbers, whatever else is in the stack)."""
    out: list = [None] * len(pairs)
    groups: dict = {}
    for i, (y, x) in enumerate(pairs):
        y = np.asarray(y, dtype=float)
        x = np.asarray(x, dtype=float)
        x = x[:, None] if x.ndim == 1 else x
        groups.setdefault((len(y),) + x.shape, []).append((i, y, x))
    for (_, n, k), items in groups.items():
        ys = np.array([y for _, y, _ in items]).reshape(len(items), n)
        xs = np.array([x for _, _, x in items]).reshape(len(items), n, k)
        finite = np.isfinite(ys).all(axis=1) & np.isfinite(xs).all(axis=(1, 2))
        if not finite.all():
            for b in np.flatnonzero(~finite).tolist():        # NaNs left out: a stack of one
                ok = np.isfinite(ys[b]) & np.all(np.isfinite(xs[b]), axis=1)
                out[items[b][0]] = _fit(ys[b][ok][None], xs[b][ok][None])[0]
            items, ys, xs = [it for it, f in zip(items, finite) if f], ys[finite], xs[finite]
        for (i, _, _), tr in zip(items, _fit(ys, xs)):
            out[i] = tr
    return out


def _fit(y, x) -> list:
    """The test of :func:`regress` on stacked finite data: ``y`` (B, N), ``x`` (B, N, k)."""
    nb, n, k_all = x.shape
    if n == 0 or k_all == 0:
        return [None] * nb
    xc = x - x.mean(axis=1, keepdims=True)
    yc = y - y.mean(axis=1, keepdims=True)
    # regressors that do not vary (or repeat another) carry no information: the test's degrees of
    # freedom are the rank of what varies (the dropped directions get no coefficient: the
    # minimum-norm least-squares solution)
    u, sv, vt = np.linalg.svd(xc, full_matrices=False)      # one SVD: the rank and the solution
    rank = np.sum(sv > sv[:, :1] * max(n, k_all) * np.finfo(float).eps, axis=1) * (sv[:, 0] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):    # a rank below k: done again below
        coef = np.matmul(vt.transpose(0, 2, 1), np.matmul(u.transpose(0, 2, 1), yc[:, :, None]) / sv[:, :, None])
    coef = coef[:, :, 0]
    coef[rank == 0] = 0.0                                   # nothing varies: not tested
    for b in np.flatnonzero((rank < k_all) & (rank > 0)).tolist():   # the dropped directions left out
        k = rank[b]
        coef[b] = vt[b, :k].T @ ((u[b, :, :k].T @ yc[b]) / sv[b, :k])
    fitted = np.matmul(xc, coef[:, :, None])[:, :, 0]
    ss_reg = np.matmul(fitted[:, None, :], fitted[:, :, None])[:, 0, 0]
    ss_res = np.sum((yc - fitted) ** 2, axis=1)
    dof = n - rank - 1
    ok = np.flatnonzero((rank > 0) & (n >= rank + 3) & (ss_res > 0) & (dof > 0))
    out: list = [None] * nb
    if not ok.size:
        return out
    k, dof, sr, se = rank[ok], dof[ok], ss_reg[ok], ss_res[ok]
    f = (sr / k) / (se / dof)
    fields = zip(ok.tolist(), f.tolist(), k.tolist(), dof.tolist(), (sr / (sr + se)).tolist(),
                 np.sqrt(sr / n).tolist(), np.sqrt(se / dof).tolist())
    for b, fb, kb, db, r2, explained, residual in fields:
        out[b] = Trend(f=fb, k=kb, dof=db, r2=r2, coef=coef[b], explained_rms=explained, residual_rms=residual,
                       n=int(n))
    return out


def mean_above_zero_p(x) -> float:
    """The p-value of the one-sided one-sample t-test that the mean of ``x`` is above 0:
    ``t = mean / (s / √n)`` (``s`` with n − 1), ``p = P(T > t) = stdtr(n − 1, −t)`` for Student's
    T with n − 1 degrees of freedom; ``scipy.stats.ttest_1samp(x, 0, alternative="greater")``'s,
    without scipy.stats' imports (0.3 CPU-s in each process that diagnoses): :mod:`core.specfun`."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.mean(x) / (np.std(x, ddof=1) / np.sqrt(n))
    return float(stdtr(n - 1, -t))

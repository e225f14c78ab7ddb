"""The one regression test of the lab's diagnosis and of the field monitor.

Does a set of regressors explain a residual channel beyond chance?  An F-test of nested linear
models: ``y = a + ε`` against ``y = a + X·c + ε`` (least squares, an intercept in both), with the
residual variance estimated from the data — so "significant" means beyond the scatter the
channel shows, whatever its unit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import fdtrc


@dataclass
class Trend:
    """The outcome of :func:`regress`: the F statistic and its p-value, the share of the
    channel's variance the regressors explain (R²), the coefficients (per regressor), the RMS of
    the explained part and the scatter left (in the channel's unit), the number of points."""

    f: float
    p: float
    r2: float
    coef: np.ndarray
    explained_rms: float
    residual_rms: float
    n: int


def regress(y, x) -> Trend | None:
    """F-test of the regressors ``x`` ((N,) or (N, k)) on the channel ``y`` (N,), NaNs left out.

    None when it cannot be tested (too few points, no regressor that varies, a perfect fit)."""
    return regress_channels([y], x)[0]


def regress_channels(ys, x) -> list:
    """:func:`regress` of each channel of ``ys`` on the same regressors ``x``: the regressors'
    centring and SVD done once for the channels that leave out the same points (the field monitor
    tests three channels against each regressor at every station) — each result the same numbers
    as :func:`regress` alone."""
    x = np.asarray(x, dtype=float)
    x = x[:, None] if x.ndim == 1 else x
    x_ok = np.all(np.isfinite(x), axis=1)
    out, done = [], {}
    for y in ys:
        y = np.asarray(y, dtype=float)
        ok = np.isfinite(y) & x_ok
        key = ok.tobytes()
        if key not in done:
            done[key] = _design(x[ok])
        out.append(_trend(y[ok], *done[key]))
    return out


def _design(x):
    """The centred regressors of the points used, their SVD and rank (None: nothing to test)."""
    n = len(x)
    if n == 0:
        return None, n
    xc = x - x.mean(axis=0)
    # regressors that do not vary (or repeat another) carry no information: the test's degrees of
    # freedom are the rank of what varies (lstsq gives them the minimum-norm coefficients)
    u, sv, vt = np.linalg.svd(xc, full_matrices=False)      # one SVD: the rank and the solution
    k = int(np.sum(sv > sv[0] * max(xc.shape) * np.finfo(float).eps)) if sv.size and sv[0] > 0 else 0
    if k == 0 or n < k + 3:
        return None, n
    return (xc, u, sv, vt, k), n


def _trend(y, design, n) -> Trend | None:
    if design is None:
        return None
    xc, u, sv, vt, k = design
    yc = y - y.mean()
    coef = vt[:k].T @ ((u[:, :k].T @ yc) / sv[:k])
    fitted = xc @ coef
    ss_reg = float(fitted @ fitted)
    ss_res = float(np.sum((yc - fitted) ** 2))
    dof = n - k - 1
    if ss_res <= 0 or dof <= 0:
        return None
    f = (ss_reg / k) / (ss_res / dof)
    return Trend(f=float(f), p=float(fdtrc(k, dof, f)), r2=ss_reg / (ss_reg + ss_res), coef=coef,
                 explained_rms=float(np.sqrt(ss_reg / n)), residual_rms=float(np.sqrt(ss_res / dof)), n=int(n))

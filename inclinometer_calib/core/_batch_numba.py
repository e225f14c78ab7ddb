"""The fused batch-correction kernel, compiled by numba (imported only through :mod:`batchkernel`,
which sets numba's on-disk cache directory first; never imported when numba is missing).

One pass over the samples, no temporaries: per sample, read the raw triads, correct them with the
record's base model, compute drift, azimuth, toolface, |G|, |B|, dip and the QC flags, write the
outputs.  The formulas, their evaluation order and the QC rules are those of
:func:`survey.evaluate` / :func:`survey.correct_samples` (see :mod:`batchkernel` for the
conventions and the agreement with the station path).

The arc tangents are not libm's: a scalar ``atan2`` call (≈ 18 ns) would cost more than the whole
sample may take, and it stops the loop from being vectorised.  :func:`_atan2` is Cephes' ``atan``
(S. L. Moshier; a degree 4/5 rational function on |t| ≤ 0.66 and the reduction
``atan t = π/4 + atan((t − 1)/(t + 1))`` above it) behind the usual octant reduction, written
branch-free so that LLVM vectorises the whole loop; it is within 1 ulp of numpy's ``arctan2``
(pinned by ``test/core/test_batch_kernel.py``) and has its special values (signed zeros, infinities,
NaN).  The main pass uses the same arithmetic without the special values (:func:`_atan2_core`,
``careful`` False) and redoes the rare samples where they matter (:func:`fused`).
``asin s = atan2(s, √((1 − s)(1 + s)))`` (exact factors: ``1 − s`` is exact for s ≥ ½).
No ``fastmath``: without it LLVM keeps the order of every addition and multiplication and does not
contract them into FMAs, so the arithmetic outside the arc tangents gives numpy's bits.

What stops LLVM's loop vectoriser here, found by measurement (``docs/benchmarks.md`` section 1):
a call inside the loop even on a branch never taken (Python's float modulo, for a declination
of 360° or more, is therefore a pass of its own), a loop that starts at a run-time index (as a
loop over blocks would: the kernel always runs from 0, on a slice per thread), and an inlined call
with more than 30 arguments (CPython passes those as ``*args``, which numba's inliner refuses:
the coefficients travel as tuples).
"""
from __future__ import annotations

import math

import numba
import numpy as np

# Cephes atan.c: atan(x) = x + x³·P(x²)/Q(x²) on 0 ≤ x ≤ 0.66 (Q monic)
_P0, _P1, _P2, _P3, _P4 = (-8.750608600031904122785e-1, -1.615753718733365076637e1, -7.500855792314704667340e1,
                           -1.228866684490136173410e2, -6.485021904942025371773e1)
_Q0, _Q1, _Q2, _Q3, _Q4 = (2.485846490142306297962e1, 1.650270098316988542046e2, 4.328810604912902668951e2,
                           4.853903996359136964868e2, 1.945506571482613964425e2)
_MOREBITS_HALF = 0.5 * 6.123233995736765886130e-17   # π/4 − fl(π/4)
_PIO4 = math.pi / 4.0
_PIO2 = math.pi / 2.0
_PI = math.pi
_R2D = 180.0 / math.pi        # np.degrees multiplies by this constant: same bits
_INF = math.inf

_JIT = dict(cache=True, error_model="numpy", nogil=True)


@numba.njit(inline="always", **_JIT)
def _atan2_core(y, x, careful):
    """atan2(y, x) in radians, (−π, π]; ``careful`` (a constant at each call site, so the unused
    branches compile away) adds C's special values: both zero, both infinite, a NaN.  Without it
    the same arithmetic gives the same bits for every other input and NaN for those (0/0, ∞/∞ and
    NaN propagate), which the caller detects (see :func:`fused`)."""
    ax = abs(x)
    ay = abs(y)
    sw = ay > ax                               # a select, not max/min: a NaN reaches t below
    mx = ay if sw else ax
    mn = ax if sw else ay
    big = mn > 0.66 * mx                       # t = mn/mx in (0.66, 1]: reduce by π/4
    num = mn - mx if big else mn
    den = mn + mx if big else mx
    if careful:
        if mx == _INF:                         # inf/inf: t = 1 (π/4); finite/inf: t = 0
            big = mn == _INF
            num = 0.0
            den = 1.0
        elif mx == 0.0:                        # both zero: t = 0 (then the signs decide)
            num = 0.0
            den = 1.0
    t = num / den
    z = t * t
    p = ((((_P0 * z + _P1) * z + _P2) * z + _P3) * z + _P4) * z
    q = ((((z + _Q0) * z + _Q1) * z + _Q2) * z + _Q3) * z + _Q4
    r = t * (p / q) + t
    if big:
        r = (r + _MOREBITS_HALF) + _PIO4
    if sw:
        r = _PIO2 - r
    if math.copysign(1.0, x) < 0.0:            # x < 0, or x = −0.0
        r = _PI - r
    r = math.copysign(r, y)
    if careful and (x != x or y != y):
        r = math.nan
    return r


@numba.njit(inline="always", **_JIT)
def _atan2(y, x):
    """atan2(y, x) in radians, (−π, π], IEEE special values as C's atan2; ≤ 1 ulp from numpy's."""
    return _atan2_core(y, x, True)


@numba.njit(inline="always", **_JIT)
def _wrap_atan2_deg(w):
    """[0, 360) for atan2 in degrees, as survey._wrap_atan2_deg (+360 below 0; 360.0 → 0)."""
    w = w + (360.0 if w < 0.0 else 0.0)
    return 0.0 if w >= 360.0 else w


@numba.njit(inline="always", **_JIT)
def _sample(i, careful, g, m, linear, coef, qc, wrap_big, drift_o, az_o, tf_o, gn_o, bn_o, dip_o, flags_o,
            status_o):
    """Sample i: correct, evaluate, write the outputs; True when an angle came out NaN (with
    ``careful`` False: perhaps a special value of an arc tangent, see :func:`fused`).  ``coef``,
    ``qc``: tuples of scalars (values: no aliasing with the outputs; fewer than 30 arguments, which
    numba's inliner needs)."""
    (a00, a01, a02, a10, a11, a12, a20, a21, a22, ba0, ba1, ba2,
     m00, m01, m02, m10, m11, m12, m20, m21, m22, bm0, bm1, bm2) = coef
    decl, thr_tf, min_drift, field_nt, dip_deg, gravity_mps2, tol_field, tol_dip, tol_gravity = qc
    hx = g[3 * i + 0]
    hy = g[3 * i + 1]
    hz = g[3 * i + 2]
    px = m[3 * i + 0]
    py = m[3 * i + 1]
    pz = m[3 * i + 2]
    if linear:   # v = C·(h − B), each row (x·C[r,0] + y·C[r,1]) + z·C[r,2] (frames.rotate)
        ux = hx - ba0
        uy = hy - ba1
        uz = hz - ba2
        gx = ux * a00 + uy * a01 + uz * a02
        gy = ux * a10 + uy * a11 + uz * a12
        gz = ux * a20 + uy * a21 + uz * a22
        ux = px - bm0
        uy = py - bm1
        uz = pz - bm2
        bx = ux * m00 + uy * m01 + uz * m02
        by = ux * m10 + uy * m11 + uz * m12
        bz = ux * m20 + uy * m21 + uz * m22
    else:
        gx, gy, gz = hx, hy, hz
        bx, by, bz = px, py, pz
    h2 = gx * gx + gy * gy
    drift = _atan2_core(math.sqrt(h2), gz, careful) * _R2D                       # frames.drift_deg
    gn = math.sqrt(h2 + gz * gz)
    bn = math.sqrt((bx * bx + by * by) + bz * bz)
    # azimuth = atan2(|g|(by gx − bx gy), bz(gx² + gy²) − gz(bx gx + by gy))   (frames.azimuth_deg)
    num = gn * (by * gx - bx * gy)
    bg = bx * gx + by * gy
    az = _wrap_atan2_deg(_atan2_core(num, bz * h2 - gz * bg, careful) * _R2D)
    if decl != 0.0:
        az = az + decl
        if not wrap_big:   # |decl| ≥ 360: Python's modulo after the loop (a libm call here stops vectorisation)
            az = az + (360.0 if az < 0.0 else 0.0)
            az = az - (360.0 if az >= 360.0 else 0.0)
            az = 0.0 if az >= 360.0 else az
    # dip = asin(clip(g·b / (|g||b|), −1, 1))                        (frames.dip_deg)
    sd = (bg + gz * bz) / (gn * bn)
    sd = 1.0 if sd > 1.0 else sd
    sd = -1.0 if sd < -1.0 else sd
    dip = _atan2_core(sd, math.sqrt((1.0 - sd) * (1.0 + sd)), careful) * _R2D
    # toolface: gravity atan2(gy, −gx) outside the cone of tol.gravity_toolface_min_drift_deg,
    # magnetic atan2(−by, bx) inside it (and for a NaN drift)
    is_g = drift >= thr_tf and drift <= 180.0 - thr_tf
    tf = _wrap_atan2_deg(_atan2_core(gy if is_g else -by, -gx if is_g else bx, careful) * _R2D)
    # QC (survey.evaluate)
    az_undef = drift < min_drift or drift > 180.0 - min_drift
    interf = abs(bn - field_nt) > tol_field or abs(dip - dip_deg) > tol_dip
    grav = abs(gn - gravity_mps2) > tol_gravity
    prod = gn * bn
    bad = not (abs(prod) < _INF)                                   # a component NaN/inf
    drift_o[i] = drift
    az_o[i] = az
    tf_o[i] = tf
    gn_o[i] = gn
    bn_o[i] = bn
    dip_o[i] = dip
    flags_o[i] = np.uint8(az_undef) | (np.uint8(interf) << 1) | (np.uint8(grav) << 2) | \
        (np.uint8(is_g) << 3) | (np.uint8(bad) << 4)
    status_o[i] = np.uint8(2) if (grav or bad) else np.uint8(az_undef or interf)
    return (drift != drift) | (az != az) | (tf != tf) | (dip != dip)


@numba.njit(**_JIT)
def fused(g, m, linear, ca, ba, cm, bm, decl, thr_tf, min_drift, field_nt, dip_deg, gravity_mps2,
          tol_field, tol_dip, tol_gravity, drift_o, az_o, tf_o, gn_o, bn_o, dip_o, flags_o, status_o):
    """Correct and evaluate every sample, one thread (:mod:`batchkernel` runs it on slices, one
    per thread: the loop always starts at 0, since a loop from a run-time start is not
    vectorised).

    ``g``, ``m``: (3N,) float64 — (N, 3) arrays in C order, flattened (so that LLVM sees the
    stride of 3 and vectorises the loads) — the gravity vector (down positive, m/s²: REP-145
    specific force is converted where it enters) and the field, nT.
    ``linear``: apply the base model ``v = C·(h − B)`` with ``ca``, ``ba`` (accelerometer, 3×3 and
    3) and ``cm``, ``bm`` (magnetometer); else the triads are taken as corrected.  Site, declination
    and tolerances as :class:`frames.Site` / :class:`survey.Tolerances`.  Outputs (N,) C order:
    float64 drift, azimuth, toolface (deg), |G| (m/s²), |B| (nT), dip (deg); uint8 flags, status.

    Two passes: first every sample with the arc tangents' arithmetic alone, counting the samples
    whose angles came out NaN; then, only if there were any, those samples again with the special
    values (an input NaN or infinite; an exactly vertical tool, whose azimuth is atan2(0, 0)).
    Both passes give the same bits wherever the first is not NaN, so the result does not depend
    on how the samples are split.  This keeps the special-value selects of four arc tangents out
    of the vectorised loop (about 10 % of its time).
    """
    wrap_big = not (abs(decl) < 360.0)
    # the record's coefficients as scalars: loaded once, not per sample (the outputs could alias them)
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = (ca[0, 0], ca[0, 1], ca[0, 2], ca[1, 0], ca[1, 1], ca[1, 2],
                                                   ca[2, 0], ca[2, 1], ca[2, 2])
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = (cm[0, 0], cm[0, 1], cm[0, 2], cm[1, 0], cm[1, 1], cm[1, 2],
                                                   cm[2, 0], cm[2, 1], cm[2, 2])
    ba0, ba1, ba2, bm0, bm1, bm2 = ba[0], ba[1], ba[2], bm[0], bm[1], bm[2]
    coef = (a00, a01, a02, a10, a11, a12, a20, a21, a22, ba0, ba1, ba2,
            m00, m01, m02, m10, m11, m12, m20, m21, m22, bm0, bm1, bm2)
    qc = (decl, thr_tf, min_drift, field_nt, dip_deg, gravity_mps2, tol_field, tol_dip, tol_gravity)
    nan = 0
    for i in range(g.shape[0] // 3):
        nan += _sample(i, False, g, m, linear, coef, qc, wrap_big, drift_o, az_o, tf_o, gn_o, bn_o, dip_o,
                       flags_o, status_o)
    if nan:   # again, with the special values, where an angle came out NaN
        for i in range(g.shape[0] // 3):
            if drift_o[i] != drift_o[i] or az_o[i] != az_o[i] or tf_o[i] != tf_o[i] or dip_o[i] != dip_o[i]:
                _sample(i, True, g, m, linear, coef, qc, wrap_big, drift_o, az_o, tf_o, gn_o, bn_o, dip_o,
                        flags_o, status_o)
    if decl != 0.0 and wrap_big:   # |decl| ≥ 360: az = (az + decl) mod 360, as survey.evaluate
        for i in range(g.shape[0] // 3):
            az = az_o[i] % 360.0
            az_o[i] = 0.0 if az >= 360.0 else az

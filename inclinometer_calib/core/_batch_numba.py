"""The fused batch-correction kernel, compiled by numba (imported only through :mod:`batchkernel`,
which sets numba's on-disk cache directory first; never imported when numba is missing).

One pass over the samples, no temporaries: per sample, read the raw triads, correct them with the
record's base model, compute drift, azimuth, toolface, |G|, |B|, dip and the QC flags, write the
outputs.  The formulas are not written here: they are :mod:`formulas`' (``corrected``,
``survey``: the text numpy runs for :func:`survey.evaluate` and :func:`survey.correct_samples`),
compiled by :func:`formulas.bind` against this module's scalar primitives (the arc tangent and
arc sine below, a scalar select) as ``njit(inline="always")`` functions, which numba inlines into
the loop.  They are bound twice, once per arc tangent (``careful`` or not, see below).  See
:mod:`batchkernel` for the conventions and the agreement with the station path.

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
of 360° or more, was one: the declination is now folded into a turn before the loop,
:func:`formulas.qc_parameters`), a loop that starts at a run-time index (as a
loop over blocks would: the kernel always runs from 0, on a slice per thread), and an inlined call
with more than 30 arguments (CPython passes those as ``*args``, which numba's inliner refuses:
the coefficients travel as tuples).
"""
from __future__ import annotations

import math
import types

import numba
from numba.core import types as nbtypes
from numba.extending import intrinsic

from . import formulas
from .formulas import corrected, survey  # what _sample calls (rebound per pass: _bound)

# Cephes atan.c: atan(x) = x + x³·P(x²)/Q(x²) on 0 ≤ x ≤ 0.66 (Q monic)
_P0, _P1, _P2, _P3, _P4 = (-8.750608600031904122785e-1, -1.615753718733365076637e1, -7.500855792314704667340e1,
                           -1.228866684490136173410e2, -6.485021904942025371773e1)
_Q0, _Q1, _Q2, _Q3, _Q4 = (2.485846490142306297962e1, 1.650270098316988542046e2, 4.328810604912902668951e2,
                           4.853903996359136964868e2, 1.945506571482613964425e2)
_MOREBITS_HALF = 0.5 * 6.123233995736765886130e-17   # π/4 − fl(π/4)
_PIO4 = math.pi / 4.0
_PIO2 = math.pi / 2.0
_PI = math.pi
_INF = math.inf

_JIT = dict(cache=True, error_model="numpy", nogil=True)
#: the functions numba inlines into the kernel (compiled as part of it, cached with it)
_INLINE = {"inline": "always", "error_model": "numpy", "nogil": True}


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


@intrinsic
def _select(typingctx, c, a, b):
    """``a if c else b`` as one LLVM ``select``: no branch, and nothing for numba's inliner to do
    (it would otherwise inline a function at each of the formulas' selects, which makes the
    kernel's compilation several times longer)."""
    t = typingctx.unify_types(nbtypes.unliteral(a), nbtypes.unliteral(b))

    def codegen(context, builder, sig, args):
        cond = context.cast(builder, args[0], sig.args[0], nbtypes.boolean)
        return builder.select(cond, context.cast(builder, args[1], sig.args[1], t),
                              context.cast(builder, args[2], sig.args[2], t))

    return t(c, a, b), codegen


def _primitives(careful: bool) -> dict:
    """The scalar primitives :mod:`formulas` is compiled against: the kernel's arc tangent
    (``careful``: with its special values), ``asin s = atan2(s, √((1 − s)(1 + s)))``, a select."""

    @numba.njit(**_INLINE)
    def atan2(y, x):
        return _atan2_core(y, x, careful)

    @numba.njit(**_INLINE)
    def asin(s):
        return _atan2_core(s, math.sqrt((1.0 - s) * (1.0 + s)), careful)

    return {"sqrt": math.sqrt, "atan2": atan2, "asin": asin, "select": _select}


def _sample(i, g, m, linear, ca, ba, cm, bm, qc, drift_o, az_o, tf_o, gn_o, bn_o, dip_o, flags_o, status_o):
    """Sample i: correct (``linear``: :func:`formulas.corrected` with the record's base model
    ``ca``, ``ba`` / ``cm``, ``bm``; else the triads are taken as corrected), evaluate
    (:func:`formulas.survey`), write the outputs; True when an angle came out NaN (in the main
    pass: perhaps a special value of an arc tangent, see :func:`fused`).  Coefficients and ``qc``
    are tuples of scalars (values: no aliasing with the outputs; fewer than 30 arguments, which
    numba's inliner needs).

    Written against the formulas' names and compiled with them, once per binding (:func:`_bound`):
    each pass inlines one copy of the formulas, not both."""
    hx, hy, hz = g[3 * i + 0], g[3 * i + 1], g[3 * i + 2]
    px, py, pz = m[3 * i + 0], m[3 * i + 1], m[3 * i + 2]
    if linear:
        gx, gy, gz = corrected(ca, ba, hx, hy, hz)
        bx, by, bz = corrected(cm, bm, px, py, pz)
    else:
        gx, gy, gz = hx, hy, hz
        bx, by, bz = px, py, pz
    r = survey(gx, gy, gz, bx, by, bz, qc)
    drift_o[i] = r.drift_deg
    az_o[i] = r.azimuth_deg
    tf_o[i] = r.toolface_deg
    gn_o[i] = r.total_gravity
    bn_o[i] = r.total_field
    dip_o[i] = r.dip_deg
    flags_o[i] = r.flags
    status_o[i] = r.status
    return (r.drift_deg != r.drift_deg) | (r.azimuth_deg != r.azimuth_deg) | (r.toolface_deg != r.toolface_deg) | \
        (r.dip_deg != r.dip_deg)


def _bound(careful: bool):
    """:func:`_sample` with the formulas bound to the primitives (``careful``: the arc tangents
    with their special values), all inlined into it."""
    ns = formulas.bind(_primitives(careful), numba.njit(**_INLINE))
    return numba.njit(**_INLINE)(types.FunctionType(_sample.__code__, ns, "_sample"))


# the main pass's (the arc tangents' arithmetic alone) and the careful pass's
_sample_fast = _bound(False)
_sample_careful = _bound(True)


@numba.njit(**_JIT)
def fused(g, m, linear, ca, ba, cm, bm, qc, drift_o, az_o, tf_o, gn_o, bn_o, dip_o, flags_o, status_o):
    """Correct and evaluate every sample, one thread (:mod:`batchkernel` runs it on slices, one
    per thread: the loop always starts at 0, since a loop from a run-time start is not
    vectorised).

    ``g``, ``m``: (3N,) float64 — (N, 3) arrays in C order, flattened (so that LLVM sees the
    stride of 3 and vectorises the loads) — the gravity vector (down positive, m/s²: REP-145
    specific force is converted where it enters) and the field, nT.
    ``linear``: apply the base model ``v = C·(h − B)`` with ``ca``, ``ba`` (accelerometer: C's
    nine entries row by row, B's three, as tuples of floats) and ``cm``, ``bm`` (magnetometer);
    else the triads are taken as corrected.  ``qc``: :func:`formulas.qc_parameters` (site and
    tolerances; the declination folded into a turn).  Outputs (N,) C order: float64 drift,
    azimuth, toolface (deg), |G| (m/s²), |B| (nT), dip (deg); uint8 flags, status.

    Two passes: first every sample with the arc tangents' arithmetic alone, counting the samples
    whose angles came out NaN; then, only if there were any, those samples again with the special
    values (an input NaN or infinite; an exactly vertical tool, whose azimuth is atan2(0, 0)).
    Both passes give the same bits wherever the first is not NaN, so the result does not depend
    on how the samples are split.  This keeps the special-value selects of four arc tangents out
    of the vectorised loop (about 10 % of its time).
    """
    nan = 0
    for i in range(g.shape[0] // 3):
        nan += _sample_fast(i, g, m, linear, ca, ba, cm, bm, qc, drift_o, az_o, tf_o, gn_o, bn_o, dip_o,
                            flags_o, status_o)
    if nan:   # again, with the special values, where an angle came out NaN
        for i in range(g.shape[0] // 3):
            if drift_o[i] != drift_o[i] or az_o[i] != az_o[i] or tf_o[i] != tf_o[i] or dip_o[i] != dip_o[i]:
                _sample_careful(i, g, m, linear, ca, ba, cm, bm, qc, drift_o, az_o, tf_o, gn_o, bn_o, dip_o,
                                flags_o, status_o)

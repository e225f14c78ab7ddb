"""The survey's formulas, each written once: a triad's correction ``v = C·(h − B)``, drift,
azimuth, toolface (and which one is reported), |G|, |B|, dip, the QC flags and the status.

Every path computes them from this text:

* **numpy** — this module's own functions, elementwise on arrays (or on scalars): the public
  functions of :mod:`frames` (``drift_deg``, ``azimuth_deg``, ``rotate`` ...), :func:`survey.evaluate`
  (the station path), the numpy backend of :func:`survey.correct_samples`,
  :meth:`errormodel.TriadModel.inverse`; :meth:`model.CorrectionPlan.correct_sample` calls
  :func:`corrected` on plain floats (arithmetic only).
* **numba** — :mod:`_batch_numba` compiles the same functions (their code, run against its own
  primitives: :func:`bind`) as ``numba.njit(inline="always")``, and its fused kernel inlines them
  per sample.

So the functions keep to what both can run: ``+ − × ÷`` (in the order written: the bits depend on
it, and neither numpy nor the kernel, which has no ``fastmath``, reorders or contracts them),
comparisons, ``&`` and ``|`` of truth values, ``abs``, tuples, calls of other formulas and the
primitives below — ``sqrt``, ``atan2``, ``asin``, ``select(c, a, b)`` (``a`` where ``c``, else
``b``; both evaluated), ``u8`` (a truth value as a 0/1 byte).  No ``if`` on a value (the kernel's
loop must stay branch-free to be vectorised), no loop, no keyword argument.

Units: gravity vector (down positive) in m/s² (any unit: only its ratios and its norm enter),
field in nT; angles in degrees.  Frames and angle definitions: :mod:`frames`.
"""
from __future__ import annotations

import math
import types
from collections import namedtuple

import numpy as np

# ---- the primitives, numpy's (elementwise; _batch_numba binds scalar ones of its own) ------------
sqrt = np.sqrt
atan2 = np.arctan2
asin = np.arcsin
select = np.where
u8 = np.uint8

#: degrees per radian: ``np.degrees`` multiplies by this constant (same bits)
R2D = 180.0 / math.pi
INF = math.inf

#: Bits of a sample's ``flags`` (:func:`survey.correct_samples`).
FLAG_AZIMUTH_UNDEFINED = 1
FLAG_INTERFERENCE = 2
FLAG_GRAVITY_OUT_OF_TOLERANCE = 4
FLAG_TOOLFACE_IS_GRAVITY = 8
FLAG_NOT_FINITE = 16

#: The formulas' names, in the order written (:func:`bind` rebinds these).
FORMULAS: list = []


def formula(f):
    """Mark ``f`` as a formula: written in the restricted style, rebound by :func:`bind`."""
    FORMULAS.append(f.__name__)
    return f


# ---- the correction of a triad -----------------------------------------------------------------
@formula
def mat_vec(c, x, y, z):
    """``C·v`` for ``v = (x, y, z)`` and ``c`` the nine entries of C row by row: each row
    ``(x·C[r,0] + y·C[r,1]) + z·C[r,2]`` — the same three products added in the same order
    whatever the batch (no BLAS), so that one sample alone and the same sample among a million
    give the same bits."""
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = c
    return (x * c00 + y * c01 + z * c02,
            x * c10 + y * c11 + z * c12,
            x * c20 + y * c21 + z * c22)


@formula
def corrected(c, b, hx, hy, hz):
    """The base model's correction of one triad, ``v = C·(h − B)`` (paper eqs. 17–19;
    :mod:`errormodel`): ``c`` C's nine entries row by row, ``b`` the bias (3), ``h`` the triad's
    output (m/s² gravity vector or nT, tool frame)."""
    return mat_vec(c, hx - b[0], hy - b[1], hz - b[2])


# ---- norms and angles --------------------------------------------------------------------------
@formula
def cross_sq(x, y):
    """``x² + y²``: the squared component across the tool axis."""
    return x * x + y * y


@formula
def norm(x, y, z):
    """``|v| = √((x² + y²) + z²)`` (numpy's norm over the last axis adds in this order too)."""
    return sqrt(cross_sq(x, y) + z * z)


@formula
def wrap360_near(w):
    """[0, 360) for ``w`` in (−360, 720) — an arc tangent in degrees, plus a declination of less
    than a turn: +360 below 0, −360 from 360 on (both exact there, as ``fmod``), and 360.0 (a tiny
    negative plus 360, rounded) → 0.  Branch-free; ``frames.wrap360`` is this after ``fmod``."""
    w = w + select(w < 0.0, 360.0, 0.0)
    w = w - select(w >= 360.0, 360.0, 0.0)
    return select(w >= 360.0, 0.0, w)


@formula
def angle360_deg(y, x):
    """``atan2(y, x)`` in degrees, [0, 360)."""
    return wrap360_near(atan2(y, x) * R2D)


@formula
def drift_deg(gx, gy, gz):
    """Drift (inclination) from the gravity vector: paper eq. (1) ``θ = arctan(√(gx² + gy²)/gz)``
    as ``atan2``, valid over 0–180° (``sqrt`` rather than ``hypot``: the same to 1 ulp for any
    m/s² value, and cheaper)."""
    return atan2(sqrt(cross_sq(gx, gy)), gz) * R2D


@formula
def azimuth_deg(gx, gy, gz, bx, by, bz):
    """Magnetic azimuth of the tool axis, [0, 360): paper eq. (2) in quadrant-resolving form,
    ``A = atan2(|g|(by gx − bx gy), bz(gx² + gy²) − gz(bx gx + by gy))`` (see
    :func:`frames.azimuth_deg` for the sign against the printed equation)."""
    num = norm(gx, gy, gz) * (by * gx - bx * gy)
    den = bz * cross_sq(gx, gy) - gz * (bx * gx + by * gy)
    return angle360_deg(num, den)


@formula
def clip(s, lo, hi):
    """``s`` limited to [lo, hi]; NaN stays NaN (as ``np.clip``)."""
    return select(s > hi, hi, select(s < lo, lo, s))


@formula
def dip_of(dot, gn, bn):
    """Magnetic dip (deg) from ``g·b`` and the norms ``|g|``, ``|B|``: ``asin(g·b / (|g||B|))``,
    clipped to ±90° (for callers that have the dot product and the norms already: the lab's fits)."""
    return asin(clip(dot / (gn * bn), -1.0, 1.0)) * R2D


@formula
def dip_deg(gx, gy, gz, bx, by, bz):
    """Magnetic dip, ``asin(g·b / (|g||b|))``: 90° minus the angle between g (down) and B."""
    return dip_of((bx * gx + by * gy) + gz * bz, norm(gx, gy, gz), norm(bx, by, bz))


@formula
def toolface_deg(gravity, gx, gy, bx, by):
    """Toolface, [0, 360): where ``gravity``, the gravity (high-side) toolface ``atan2(gy, −gx)``,
    else the magnetic toolface ``atan2(−by, bx)`` — one arc tangent of the chosen pair.
    (``gravity`` True or False throughout gives either toolface alone.)"""
    return angle360_deg(select(gravity, gy, -by), select(gravity, -gx, bx))


@formula
def in_vertical_cone(drift, cone):
    """True where a drift (deg) lies within ``cone`` of the vertical, down (0°) or up (180°)."""
    return (drift < cone) | (drift > 180.0 - cone)


@formula
def outside_vertical_cone(drift, cone):
    """True where a drift (deg) lies ``cone`` or more from the vertical (NaN: neither inside nor
    outside)."""
    return (drift >= cone) & (drift <= 180.0 - cone)


# ---- one sample's survey: angles, QC, status ---------------------------------------------------
#: What :func:`survey` gives per sample (arrays under numpy, scalars in the kernel).
Survey = namedtuple("Survey", (
    "drift_deg", "azimuth_deg", "toolface_deg", "total_gravity", "total_field", "dip_deg",
    "toolface_is_gravity", "delta_g", "delta_b", "delta_dip",
    "azimuth_undefined", "interference_suspected", "gravity_out_of_tolerance", "not_finite",
    "flags", "status"))


@formula
def survey(gx, gy, gz, bx, by, bz, qc):
    """Angles and QC of corrected vectors g (gravity, down positive) and b (field), ``qc`` the
    scalars of :func:`qc_parameters`: a :data:`Survey`.

    * ``azimuth_deg``: from the site's north, magnetic azimuth + declination, [0, 360);
    * ``toolface_deg``: the gravity toolface outside the cone of
      ``gravity_toolface_min_drift_deg`` about the vertical, the magnetic one inside it (and for
      a NaN drift); ``toolface_is_gravity`` says which;
    * ``azimuth_undefined``: the drift within ``min_drift_deg`` of the vertical;
      ``interference_suspected``: |ΔB| or |Δdip| beyond their tolerances;
      ``gravity_out_of_tolerance``: |ΔG| beyond its tolerance; ``not_finite``: a component NaN
      or infinite (|g|·|b| not finite);
    * ``flags``: those as the bits ``FLAG_*``; ``status``: 2 (error) for gravity out of
      tolerance or not finite, else 1 (warn) for azimuth undefined or interference, else 0.
    """
    decl, tf_cone, az_cone, field_nt, dip_ref, gravity, tol_field, tol_dip, tol_gravity = qc
    drift = drift_deg(gx, gy, gz)
    gn = norm(gx, gy, gz)
    bn = norm(bx, by, bz)
    dip = dip_deg(gx, gy, gz, bx, by, bz)
    is_g = outside_vertical_cone(drift, tf_cone)
    dg = gn - gravity
    db = bn - field_nt
    ddip = dip - dip_ref
    az_undef = in_vertical_cone(drift, az_cone)
    interf = (abs(db) > tol_field) | (abs(ddip) > tol_dip)
    grav = abs(dg) > tol_gravity
    bad = select(abs(gn * bn) < INF, False, True)
    flags = (u8(az_undef) * FLAG_AZIMUTH_UNDEFINED | u8(interf) * FLAG_INTERFERENCE
             | u8(grav) * FLAG_GRAVITY_OUT_OF_TOLERANCE | u8(is_g) * FLAG_TOOLFACE_IS_GRAVITY
             | u8(bad) * FLAG_NOT_FINITE)
    status = select(grav | bad, 2, select(az_undef | interf, 1, 0))
    return Survey(drift, wrap360_near(azimuth_deg(gx, gy, gz, bx, by, bz) + decl),
                  toolface_deg(is_g, gx, gy, bx, by), gn, bn, dip, is_g, dg, db, ddip,
                  az_undef, interf, grav, bad, flags, status)


# ---- around the formulas (plain Python, not rebound) -------------------------------------------
def qc_parameters(site, tol) -> tuple:
    """The ``qc`` scalars of :func:`survey` from a site (:class:`frames.Site`) and tolerances
    (:class:`survey.Tolerances`), as floats: declination (folded into (−360, 360) by ``fmod``,
    exact, so that one wrap of ``azimuth + declination`` is the true azimuth), toolface cone,
    azimuth cone, field (nT), dip (deg), gravity (m/s²) and the three tolerances."""
    return (math.fmod(float(site.declination_deg), 360.0), float(tol.gravity_toolface_min_drift_deg),
            float(tol.min_drift_deg), float(site.total_field_nt), float(site.dip_deg), float(site.gravity_mps2),
            float(tol.field_nt), float(tol.dip_deg), float(tol.gravity_mps2))


def bind(primitives: dict, wrap) -> dict:
    """The formulas over other primitives: a namespace (dict) holding this module's names with
    ``primitives`` (e.g. ``sqrt``, ``atan2``, ``asin``, ``select``) put in their place and each
    formula's code run against it, passed through ``wrap`` (numba: ``njit(inline="always")``).
    A formula calling another finds the rebound one, so the whole text is bound at once."""
    ns = dict(globals())
    ns.update(primitives)
    for name in FORMULAS:
        f = globals()[name]
        ns[name] = wrap(types.FunctionType(f.__code__, ns, name, f.__defaults__, f.__closure__))
    return ns

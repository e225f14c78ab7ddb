"""Survey evaluation: corrected angles, quality control against the site, errors against a reference.

Works on static stations (see :mod:`probelog`).  Gravity vectors are in the seed paper's
convention (down positive, m/s²), fields in nT.  Azimuths are reported from the NED frame's north:
magnetic azimuth plus the site declination (true azimuth when the declination is given; magnetic
when it is 0).

Quality control follows drilling practice: total field within 300 nT and dip within 0.25° of the
site reference (ISCWSA survey-QC e-book); the gravity tolerance is configurable (no industry-wide
fixed value; default 0.0981 m/s² = 10 mg).  Azimuth is flagged undefined below a minimum drift.

The formulas themselves (angles, QC rules, status, flag bits) are written once, in
:mod:`formulas`; this module applies them: to stations (:func:`evaluate`) and to raw samples in
bulk (:func:`correct_samples`: the same text on numpy blocks, or compiled into the numba kernel).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import formulas, frames
from .frames import Site, wrap180
from .geomag import azimuths
from . import batchkernel
from .batchkernel import BATCH_KEYS


@dataclass(frozen=True)
class Tolerances:
    """QC tolerances: |ΔB| nT, |Δdip| deg, |ΔG| m/s²; the azimuth is undefined within
    ``min_drift_deg`` of the vertical (drift below it, or above 180° minus it — the vertical cone).

    ``gravity_toolface_min_drift_deg``: outside this cone about the vertical the reported toolface
    is the gravity toolface, inside it the magnetic toolface (the usual switch-over, ~3–5°).
    """

    field_nt: float = 300.0
    dip_deg: float = 0.25
    gravity_mps2: float = 0.0981
    min_drift_deg: float = 0.5
    gravity_toolface_min_drift_deg: float = 3.0


def in_vertical_cone(drift_deg, cone_deg):
    """True where a drift (deg) lies within ``cone_deg`` of the vertical, down (0°) or up (180°)
    (:func:`formulas.in_vertical_cone`)."""
    return formulas.in_vertical_cone(np.asarray(drift_deg, dtype=float), cone_deg)


def evaluate(g, b, site: Site, tol: Tolerances = Tolerances(), ref=None) -> dict:
    """Angles, QC and (if ``ref`` (N, 3) deg is given) errors for corrected vectors ``g``, ``b``.

    Returns a dict of (N,) arrays: those of :func:`formulas.survey` (the one text of the angles,
    the QC and the status: flags are booleans, ``status`` is 0 ok, 1 warn, 2 error), and both
    toolfaces.  ``azimuth_deg`` is from the site's north (true when the site has a declination),
    with ``azimuth_magnetic_deg`` and ``azimuth_grid_deg`` (NaN when the site has no grid) beside it.

    A reference is used for what it defines (NaN: not given).  Within the vertical cone
    (``tol.min_drift_deg`` of 0° or 180°) the azimuth is undefined, and the toolface error is
    the error of the tool's rotation about the vertical: the measured magnetic toolface against
    the one the reference attitude implies in the site's field (a vertical stand pose gives drift
    and toolface without azimuth: its orientation about the vertical is the toolface, as for
    azimuth 0).  Elsewhere the toolface error is the gravity toolface's.
    """
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    gx, gy, gz, bx, by, bz = g[:, 0], g[:, 1], g[:, 2], b[:, 0], b[:, 1], b[:, 2]
    r = formulas.survey(gx, gy, gz, bx, by, bz, formulas.qc_parameters(site, tol))
    # the azimuth in every reference (geomag.azimuths): true with the site's declination (the
    # reported azimuth_deg), magnetic as measured, grid with its grid convergence (NaN without a grid)
    refs = azimuths(r.azimuth_deg, site.declination_deg, site.grid_convergence_deg)
    out = {"drift_deg": r.drift_deg, "azimuth_deg": refs["true"],
           "gravity_toolface_deg": formulas.toolface_deg(True, gx, gy, bx, by),
           "magnetic_toolface_deg": formulas.toolface_deg(False, gx, gy, bx, by),
           "total_gravity": r.total_gravity, "total_field": r.total_field, "dip_deg": r.dip_deg,
           "azimuth_magnetic_deg": refs["magnetic"], "azimuth_grid_deg": refs["grid"]}
    for key in ("toolface_deg", "toolface_is_gravity", "delta_g", "delta_b", "delta_dip", "azimuth_undefined",
                "interference_suspected", "gravity_out_of_tolerance", "status"):
        out[key] = getattr(r, key)
    if ref is not None:
        ref = np.atleast_2d(np.asarray(ref, dtype=float))
        out.update(reference_errors(out, ref, site, tol))
    return out


def compared_toolface_deg(res: dict, ref_drift_deg, tol: Tolerances = Tolerances()) -> np.ndarray:
    """The toolface :func:`reference_errors` compares with a reference of drift ``ref_drift_deg``:
    the gravity toolface, the magnetic one where the reference is vertical (within
    ``tol.min_drift_deg``) — not the reported ``toolface_deg``, which switches to the magnetic
    toolface inside ``tol.gravity_toolface_min_drift_deg`` (a predicted σ of a toolface error must
    be this one's: at 2° drift the gravity toolface's noise is ~15× the magnetic one's)."""
    with np.errstate(invalid="ignore"):
        vertical = in_vertical_cone(np.asarray(ref_drift_deg, dtype=float), tol.min_drift_deg)
    return np.where(vertical, res["magnetic_toolface_deg"], res["gravity_toolface_deg"])


def reference_errors(res: dict, ref, site: Site, tol: Tolerances = Tolerances()) -> dict:
    """``drift_err``, ``azimuth_err``, ``toolface_err`` (deg) of evaluated stations ``res`` against
    reference attitudes ``ref`` (N, 3): drift, azimuth, toolface in degrees, NaN where not given
    (see :func:`evaluate`)."""
    ref = np.atleast_2d(np.asarray(ref, dtype=float))
    rd, ra, rt = ref[:, 0], ref[:, 1], ref[:, 2]
    with np.errstate(invalid="ignore"):
        vertical = in_vertical_cone(rd, tol.min_drift_deg)
        az_err = wrap180(res["azimuth_deg"] - ra)
        azimuth_err = np.where(res["azimuth_undefined"] | vertical | ~np.isfinite(ra), np.nan, az_err)
        tf_ref = rt
        # vertical reference: the rotation about the vertical, from the field (magnetic toolface)
        if np.any(vertical & np.isfinite(rt)):
            r = frames.orientation_matrix(np.where(np.isfinite(rd), rd, 0.0), np.where(np.isfinite(ra), ra, 0.0),
                                          np.where(np.isfinite(rt), rt, 0.0))
            b_ref = np.swapaxes(r, -1, -2) @ site.field_ned()
            tf_ref = np.where(vertical, frames.magnetic_toolface_deg(b_ref), rt)
        tf_err = wrap180(compared_toolface_deg(res, rd, tol) - tf_ref)
        toolface_err = np.where(np.isfinite(rt), tf_err, np.nan)
    return {"drift_err": res["drift_deg"] - rd, "azimuth_err": azimuth_err, "toolface_err": toolface_err}


def summarize(result: dict) -> dict:
    """Overall error statistics over stations with a reference (azimuth only where defined)."""
    d = result.get("drift_err")
    if d is None:
        return {"stations": int(len(result["drift_deg"]))}
    known = np.isfinite(d)
    a = result["azimuth_err"][known]
    a = a[np.isfinite(a)]
    d = d[known]

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")

    def mx(x):
        return float(np.max(np.abs(x))) if len(x) else float("nan")

    return {"stations": int(known.sum()), "drift_rms_deg": rms(d), "drift_max_abs_deg": mx(d),
            "azimuth_rms_deg": rms(a), "azimuth_max_abs_deg": mx(a), "azimuth_stations": int(len(a))}


def table4(result: dict, ref) -> dict:
    """Paper Table 4 layout: drift error per set drift (mean over azimuth/toolface) and RMS.

    Returns ``{"drifts": [...], "mean_err": [...], "rms_err": [...], "overall_rms": x}``.
    """
    ref = np.asarray(ref, dtype=float)
    drifts = sorted({float(x) for x in ref[:, 0] if np.isfinite(x)})
    err = result["drift_err"]
    mean = [float(np.mean(err[ref[:, 0] == i])) for i in drifts]
    rms = [float(np.sqrt(np.mean(err[ref[:, 0] == i] ** 2))) for i in drifts]
    ok = np.isfinite(err)
    return {"drifts": drifts, "mean_err": mean, "rms_err": rms,
            "overall_rms": float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan")}


def table5(result: dict, ref, toolface_deg: float | None = None) -> dict:
    """Paper Table 5 layout: azimuth error by set drift (rows) × set azimuth (columns) at one set
    toolface (default: the grid's first), with the RMS of each drift row over *all* its stations."""
    ref = np.asarray(ref, dtype=float)
    drifts = sorted({float(x) for x in ref[:, 0] if np.isfinite(x)})
    azis = sorted({float(x) for x in ref[:, 1] if np.isfinite(x)})
    if toolface_deg is None:
        tfs = ref[np.isfinite(ref[:, 2]), 2]
        toolface_deg = float(tfs[0]) if len(tfs) else float("nan")
    err = result["azimuth_err"]
    cells = np.full((len(drifts), len(azis)), np.nan)
    rms = []
    for r, i in enumerate(drifts):
        row = ref[:, 0] == i
        for c, a in enumerate(azis):
            sel = row & (ref[:, 1] == a) & (ref[:, 2] == toolface_deg) & np.isfinite(err)
            if sel.any():
                cells[r, c] = float(np.mean(err[sel]))
        e = err[row & np.isfinite(err)]
        rms.append(float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan"))
    return {"drifts": drifts, "azimuths": azis, "toolface_deg": toolface_deg, "cells": cells.tolist(),
            "rms_err": rms}


def format_table4(before: dict | None, after: dict) -> str:
    cols = after["drifts"]
    w = 7
    lines = ["Table 4 — drift error (deg) by set drift: mean over azimuths/toolfaces",
             "state      " + "".join(f"{c:>{w}g}" for c in cols) + f"{'RMS':>{w + 1}}"]
    for name, t in (("before", before), ("after", after)):
        if t is None:
            continue
        lines.append(f"{name:<11}" + "".join(f"{v:>{w}.3f}" for v in t["mean_err"]) + f"{t['overall_rms']:>{w + 1}.3f}")
    return "\n".join(lines)


def format_table5(before: dict | None, after: dict) -> str:
    azis = after["azimuths"]
    w = 8
    lines = [f"Table 5 — azimuth error (deg) by set drift × set azimuth at toolface {after['toolface_deg']:g}; "
             "RMS per drift row over all toolfaces",
             "drift state  " + "".join(f"{a:>{w}g}" for a in azis) + f"{'RMS':>{w + 1}}"]
    for r, i in enumerate(after["drifts"]):
        for name, t in (("before", before), ("after", after)):
            if t is None:
                continue
            cells = "".join(f"{v:>{w}.2f}" if np.isfinite(v) else f"{'-':>{w}}" for v in t["cells"][r])
            lines.append(f"{i:>5g} {name:<7}" + cells + f"{t['rms_err'][r]:>{w + 1}.2f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Batch correction of raw samples (vectorized core)
# --------------------------------------------------------------------------------------------
#: Bits of the ``flags`` array returned by :func:`correct_samples` (:mod:`formulas`).
FLAG_AZIMUTH_UNDEFINED = formulas.FLAG_AZIMUTH_UNDEFINED
FLAG_INTERFERENCE = formulas.FLAG_INTERFERENCE
FLAG_GRAVITY_OUT_OF_TOLERANCE = formulas.FLAG_GRAVITY_OUT_OF_TOLERANCE
FLAG_TOOLFACE_IS_GRAVITY = formulas.FLAG_TOOLFACE_IS_GRAVITY
FLAG_NOT_FINITE = formulas.FLAG_NOT_FINITE


def correct_samples(g, m_nt, calibration=None, site: Site | None = None, tol: Tolerances = Tolerances(), *,
                    temperature_c=None, time_s=None, block: int = 16384, out: dict | None = None,
                    backend: str | None = None, threads: int | None = None) -> dict:
    """Correct and evaluate raw samples in bulk: both triads, angles and QC per sample.

    Parameters
    ----------
    g : (N, 3) float64 — accelerometer, the gravity vector (down positive), m/s² (REP-145
        specific force is converted where it enters, e.g. ``ProbeLog.gravity``).
    m_nt : (N, 3) float64 — magnetometer, nT.
    calibration : :class:`coeffs.Calibration` or None (uncorrected).  The correction is its
        :meth:`~coeffs.Calibration.correct` (the package's one correction path), block by block.
    site : the site reference; None: the calibration's (the record owns it).
    tol : QC tolerances, as for :func:`evaluate`.
    temperature_c, time_s : (N,) or scalars, °C and s since the data's first sample: needed when
        the calibration's model has effects that depend on them.
    block : samples per block: the work runs block by block so that every temporary stays in
        the CPU cache and the arrays of N samples are read once and written once.
    out : optional dict of preallocated output arrays (keys as returned) to write into.
    backend : ``numba`` (the fused kernel, :mod:`batchkernel`), ``numpy`` (the blocked body below:
        :func:`formulas.survey` on each block)
        or ``auto`` (numba when importable); None: ``$INCLINOMETER_CALIB_BATCH_BACKEND``, else auto.
    threads : threads of the numba kernel (:func:`batchkernel.resolve_threads`; None:
        ``$INCLINOMETER_CALIB_BATCH_THREADS``, else the CPUs this process may use).  The numbers
        do not depend on it; the numpy backend runs on the calling thread.

    Returns
    -------
    dict of (N,) arrays: ``drift_deg``, ``azimuth_deg`` (with the site declination, [0, 360)),
    ``toolface_deg`` (gravity toolface from ``tol.gravity_toolface_min_drift_deg`` on, magnetic
    below), ``total_gravity`` (m/s²), ``total_field`` (nT), ``dip_deg``, float64; ``flags`` uint8
    (bits ``FLAG_*``), ``status`` uint8 (0 ok, 1 warn, 2 error, as :func:`evaluate`).

    The values agree exactly with ``evaluate(*calibration.correct(g, m_nt, ...), site, tol)``:
    the same correction, then the same formulas (:func:`formulas.survey`) — on the numba backend
    compiled, with its own arc tangents (angles within 1e-9°, see :mod:`batchkernel`).
    """
    gs = np.asarray(g, dtype=np.float64)
    m = np.asarray(m_nt, dtype=np.float64)
    if gs.ndim != 2 or gs.shape[1] != 3 or m.shape != gs.shape:
        raise ValueError(f"correct_samples: g and m_nt must both be (N, 3), got {gs.shape} and {m.shape}")
    if site is None:
        if calibration is None:
            raise ValueError("correct_samples: no site reference: give a site, or a calibration (which owns one)")
        site = calibration.site
    n = len(gs)
    temp = None if temperature_c is None else np.broadcast_to(np.asarray(temperature_c, dtype=float), (n,))
    tim = None if time_s is None else np.broadcast_to(np.asarray(time_s, dtype=float), (n,))
    if calibration is not None:
        calibration.model.context(0, temp, tim, "val", "correct_samples: ")   # what the model needs: said up front
    kernel = batchkernel.resolve_backend(backend) == "numba"
    if out is None:
        out = {k: np.empty(n) for k in BATCH_KEYS}
        out["flags"] = np.empty(n, dtype=np.uint8)
        out["status"] = np.empty(n, dtype=np.uint8)
    if kernel:
        return batchkernel.fused(gs, m, calibration, site, tol, temp, tim, block, out,
                                 lambda g, b, tc, ts: calibration.correct(g, b, tc, ts), threads)
    blk = max(1, min(int(block), n)) if n else 1
    qc = formulas.qc_parameters(site, tol)
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN/inf samples are flagged, not warned
        for s in range(0, n, blk):
            e = min(s + blk, n)
            g = gs[s:e]
            if calibration is not None:
                g, b = calibration.correct(g, m[s:e], None if temp is None else temp[s:e],
                                           None if tim is None else tim[s:e])
            else:
                b = m[s:e]
            r = formulas.survey(g[:, 0], g[:, 1], g[:, 2], b[:, 0], b[:, 1], b[:, 2], qc)
            for key in BATCH_KEYS + ("flags", "status"):
                out[key][s:e] = getattr(r, key)
    return out

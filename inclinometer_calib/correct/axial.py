"""Short-collar (single-station axial) correction of drill-string magnetic interference.

A magnetised drill string adds a field Δ along the tool axis (ISCWSA term AMIL).  With the site
reference field |B| and dip known, Δ can be solved station by station: the corrected field
``b' = b - [0, 0, Δ]`` must have the reference total field and dip,

    r₁(Δ) = (|b'| − B) / σ_B,        r₂(Δ) = (dip(g, b') − dip) / σ_dip,

which is solved for Δ by Gauss–Newton (vectorised over stations, analytic derivatives).  The
azimuth is then computed from ``b'``.  The method degenerates where the axial component carries
no azimuth information — near east–west azimuths at high inclination (vendor manuals avoid
70–110° and 250–290° there): the azimuth's sensitivity to an error in Δ grows without bound.  Each
station therefore gets the propagated azimuth uncertainty ``σ_A = |∂A/∂Δ|·σ_Δ`` and a
``degenerate`` flag when it exceeds a limit.

Vectors are tool-frame: gravity vector (down positive, m/s²) and field in nT, as in ``frames``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core import frames
from ..core.frames import Site


@dataclass(frozen=True)
class AxialSettings:
    """Weights and limits: σ of the reference field (nT) and dip (deg) — IFR-like defaults —
    Gauss–Newton iterations, and the azimuth-uncertainty limit (deg) beyond which a station's
    correction is flagged degenerate."""

    sigma_field_nt: float = 50.0
    sigma_dip_deg: float = 0.1
    iterations: int = 8
    max_azimuth_sigma_deg: float = 1.0


def solve_axial_field(g, b, site: Site, settings: AxialSettings = AxialSettings()):
    """Axial interference Δ (nT) per station and its 1σ, from g (m/s²) and b (nT), (N, 3)."""
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    gn = np.linalg.norm(g, axis=1)
    u = g / gn[:, None]  # unit down vector in the tool frame
    s_b = settings.sigma_field_nt
    s_d = np.radians(settings.sigma_dip_deg)
    sin_dip = np.sin(np.radians(site.dip_deg))
    delta = np.zeros(len(g))
    for _ in range(settings.iterations):
        bp = b.copy()
        bp[:, 2] -= delta
        bn = np.linalg.norm(bp, axis=1)
        s = np.sum(u * bp, axis=1) / bn  # sin(dip) of the corrected field
        # residuals in comparable units: field over σ_B, sin(dip) over cos(dip)·σ_dip
        cos_dip = np.sqrt(np.maximum(1 - s * s, 1e-12))
        r1 = (bn - site.total_field_nt) / s_b
        r2 = (s - sin_dip) / (cos_dip * s_d)
        # derivatives with respect to Δ (b'_z = b_z − Δ)
        d_bn = -bp[:, 2] / bn
        d_s = (-u[:, 2] * bn - np.sum(u * bp, axis=1) * d_bn) / bn ** 2
        j1 = d_bn / s_b
        j2 = d_s / (cos_dip * s_d)
        jtj = j1 * j1 + j2 * j2
        step = -(j1 * r1 + j2 * r2) / np.maximum(jtj, 1e-30)
        delta = delta + step
        if np.all(np.abs(step) < 1e-6):
            break
    sigma = 1.0 / np.sqrt(np.maximum(jtj, 1e-30))
    return delta, sigma


def correct(g, b, site: Site, settings: AxialSettings = AxialSettings()) -> dict:
    """Short-collar corrected azimuth (deg, + declination) with Δ, its σ and the degeneracy flag.

    Returns arrays: ``azimuth_deg``, ``axial_field_nt`` (Δ), ``axial_field_sigma_nt``,
    ``azimuth_sigma_deg`` (propagated from σ_Δ), ``degenerate`` (bool), and ``field`` (the
    corrected field vectors, nT).
    """
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    delta, sigma = solve_axial_field(g, b, site, settings)
    bp = b.copy()
    bp[:, 2] -= delta
    az = frames.azimuth_deg(g, bp)
    # numerical ∂A/∂Δ (central difference of 1 nT), wrapped
    h = 1.0
    bp_p, bp_m = bp.copy(), bp.copy()
    bp_p[:, 2] -= h
    bp_m[:, 2] += h
    dadd = frames.wrap180(frames.azimuth_deg(g, bp_p) - frames.azimuth_deg(g, bp_m)) / (2 * h)
    az_sigma = np.abs(dadd) * sigma
    return {"azimuth_deg": frames.wrap360(az + site.declination_deg), "axial_field_nt": delta,
            "axial_field_sigma_nt": sigma, "azimuth_sigma_deg": az_sigma,
            "degenerate": az_sigma > settings.max_azimuth_sigma_deg, "field": bp}


def evaluate_with_axial(g, b, site: Site, tol=None, ref=None, settings: AxialSettings = AxialSettings()) -> dict:
    """``survey.evaluate`` with the azimuth from the short-collar corrected field.

    Quality control (|B|, dip: interference suspected) stays on the *measured* field — it is what
    shows the interference; after the correction the field matches the reference by construction.
    Where the correction is degenerate the ordinary azimuth is kept and ``axial_degenerate`` set
    (status at least warn).  Adds ``axial_field_nt``, ``axial_field_sigma_nt``,
    ``azimuth_sigma_deg`` and ``azimuth_method`` ('short_collar' or 'standard').
    """
    from ..core.geomag import azimuths
    from ..core.survey import Tolerances, evaluate

    tol = tol or Tolerances()
    res = evaluate(g, b, site, tol, ref=ref)
    ax = correct(g, b, site, settings)
    use = ~ax["degenerate"] & ~res["azimuth_undefined"]
    # the azimuth reported, in each of its references (survey.evaluate gave the uncorrected one's)
    refs = azimuths(np.where(use, ax["azimuth_deg"], res["azimuth_deg"]), site.declination_deg,
                    site.grid_convergence_deg)
    res["azimuth_deg"] = refs["true"]
    res["azimuth_magnetic_deg"], res["azimuth_grid_deg"] = refs["magnetic"], refs["grid"]
    res["axial_field_nt"] = ax["axial_field_nt"]
    res["axial_field_sigma_nt"] = ax["axial_field_sigma_nt"]
    res["azimuth_sigma_deg"] = ax["azimuth_sigma_deg"]
    res["axial_degenerate"] = ax["degenerate"]
    res["azimuth_method"] = np.where(use, "short_collar", "standard")
    res["status"] = np.where(ax["degenerate"] & (res["status"] == 0), 1, res["status"])
    if ref is not None and "azimuth_err" in res:
        ref = np.atleast_2d(np.asarray(ref, dtype=float))
        res["azimuth_err"] = np.where(res["azimuth_undefined"], np.nan,
                                      frames.wrap180(res["azimuth_deg"] - ref[:, 1]))
    return res

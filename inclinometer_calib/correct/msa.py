"""Multi-station analysis (MSA) of axial drill-string interference — ROS-free.

The short-collar correction (:mod:`axial`) solves the axial field Δ station by station from the
site's total field B and dip δ.  Everything the reference gets wrong goes into that station's Δ,
by an amount that depends on the station's attitude — and near east–west at high inclination a
station's |B| and dip hardly depend on Δ while its azimuth depends on it most.  MSA fits the
parameters the stations of a run share, by weighted least squares over all of them at once.

Model (tool frame: gravity vector g down positive in m/s², field b in nT, as in :mod:`frames`)
---------------------------------------------------------------------------------------------
The measured field of station i is the true one with a field fixed to the tool::

    b_x = b⁰_x + MBX,   b_y = b⁰_y + MBY,   b_z = (1 + MSZ)·b⁰_z + Δz

Δz (nT) is the axial field of the drill string (ISCWSA AMIL; a Z bias MBZ is the same thing to
MSA: both are constant along the axis), MSZ (dimensionless) a Z scale error, MBX/MBY (nT)
cross-axial biases.  The corrected field is ``b' = [b_x − MBX, b_y − MBY, (b_z − Δz)/(1 + MSZ)]``.

Residuals, with ``u = g/|g|``, ``F_i = |b'_i|``, ``S_i = u_i·b'_i / F_i = sin(dip_i)``::

    r_B,i = (F_i − (B + δB)) / σ_n,B            (station scatter of |B|, nT)
    r_D,i = (asin S_i − (δ + δD)) / σ_n,D         (station scatter of dip, rad)
    r_B,ref = δB / σ_ref,B,   r_D,ref = δD / σ_ref,D

The reference offsets δB, δD are shared by every station: the reference is uncertain by σ_ref
(IFR-like 50 nT / 0.1°, a main-field model such as WMM 152 nT / 0.22° — the WMM2015 technical
report's error model for F and I).  Fitting them with their prior is the generalised least
squares of residuals whose covariance is ``σ_n²·I + σ_ref²·11ᵀ`` — the error common to all
stations, which the short collar puts into Δ at every station.  Linearised, a station's |B|
residual is ``−δB + Δz·c_i`` with ``c_i = b'_z/F`` (the cosine of the angle between the tool axis
and the field): Δz and δB separate only where c_i varies over the run.

The fit is :func:`scipy.optimize.least_squares` with the analytic Jacobian

    ∂F/∂θ = (b'/F)·∂b'/∂θ,   ∂asin S/∂θ = (u − S·b'/F)/(F·√(1 − S²))·∂b'/∂θ,
    ∂b'/∂Δz = [0, 0, −1/(1+MSZ)],   ∂b'/∂MSZ = [0, 0, −b'_z/(1+MSZ)],   ∂b'/∂MBX = [−1, 0, 0], …

Station scatter σ_n is estimated from the data: ``σ_n,c² = Σ e_c,i² / Σ (1 − h_c,i)`` over the
channel's residuals e (unweighted) with the leverages h of the weighted Jacobian (refit until
stable).  The covariance is ``(JᵀJ)⁻¹`` of the weighted Jacobian J at the solution (so scaled by
the residuals' own scatter), computed by SVD after scaling J's columns to unit length; its
condition number is reported, and the smallest singular value of ``J·diag(limit)`` (each
parameter in units of its σ limit: below 1, some combination of the parameters at their limit
sizes changes χ² by less than 1).  A parameter is *observable* when its σ is below its limit
(:class:`MSASettings`).  The run is observable when every fitted tool parameter is; otherwise
its parameters must not be used (:func:`evaluate_with_msa` keeps the standard azimuths and flags
every station ``msa_unobservable``).  All stations near east–west at high inclination make Δz
unobservable: there ``c_i ≈ 0`` and ``∂dip/∂Δz ∝ cos I ≈ 0``.

How many parameters the data support (``parameters="auto"``): Δz alone, Δz + MSZ, Δz + MBX/MBY
and all four are fitted; the largest whose every parameter is observable is used (ties: the
smaller station scatter).  MSZ needs c_i spread (Δz shifts |B| by Δz·c_i, MSZ by MSZ·c_i²·B),
MBX/MBY a spread of toolfaces.

Outliers (a station with external interference): iterative rejection — while the largest
standardised residual ``|e|/(s·√(1 − h))``, with s the channel's robust scale (1.4826 × median
absolute standardised residual), exceeds ``reject_k`` (4), the worst station is left out and the
fit redone, at most ``max_reject_fraction`` of the stations (more is said: the interference is
not a few stations').  Rejected stations still get the run's correction, flagged.

Per station: the azimuth from b' (paper eq. 2, :func:`frames.azimuth_deg`, + declination) and its
σ propagated from the covariance of the tool parameters, ``σ_A² = ∇_θA · C · ∇_θAᵀ`` with the
analytic ``∂A/∂b'`` of eq. 2; a station whose σ_A exceeds ``max_azimuth_sigma_deg`` is
degenerate (as in :mod:`axial`) and keeps its standard azimuth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..core import frames
from ..core.formulas import dip_of
from .axial import AxialSettings
from .axial import correct as short_collar
from ..core.frames import Site

#: The tool parameters MSA can fit, in order, with units.
TOOL_PARAMETERS = ("dz", "msz", "mbx", "mby")
#: The reference offsets fitted with their prior.
REFERENCE_PARAMETERS = ("ref_field", "ref_dip")
UNITS = {"dz": "nT", "msz": "1", "mbx": "nT", "mby": "nT", "ref_field": "nT", "ref_dip": "deg"}
DESCRIPTION = {"dz": "axial field Δz (AMIL/MBZ)", "msz": "Z scale MSZ", "mbx": "X bias MBX", "mby": "Y bias MBY",
               "ref_field": "reference total field offset δB", "ref_dip": "reference dip offset δD"}
#: The nested parameter sets, smallest first (``parameters=`` one of these names, or ``auto``).
MODELS = {"dz": ("dz",), "dz+msz": ("dz", "msz"), "dz+mbxy": ("dz", "mbx", "mby"), "all": TOOL_PARAMETERS}
#: Reference σ (total field nT, dip deg): in-field referencing, and a main-field model (the
#: WMM2015 technical report's error model for F and I).
IFR_SIGMA = (50.0, 0.1)
MAIN_FIELD_MODEL_SIGMA = (152.0, 0.22)


@dataclass(frozen=True)
class MSASettings:
    """Settings of the multi-station fit.

    ``sigma_field_nt``, ``sigma_dip_deg``: 1σ of the site reference (the prior of the reference
    offsets; IFR-like defaults, as :class:`axial.AxialSettings`); ``fit_reference``: fit the
    offsets (False: the reference is taken as exact — what the short collar assumes);
    ``station_sigma_field_nt``, ``station_sigma_dip_deg``: the stations' scatter about the model,
    the starting value when ``estimate_station_sigma`` (from the residuals), else fixed;
    ``parameters``: a key of :data:`MODELS` or ``"auto"``; ``limit_*``: the σ below which a
    parameter counts as observable (Δz 50 nT — 0.11° of azimuth at worst for B·cos δ = 25 µT —;
    MSZ 0.002; MBX/MBY 50 nT); ``reject_k``: standardised residual beyond which a station is
    rejected; ``max_reject_fraction``; ``max_azimuth_sigma_deg``: a station's propagated azimuth σ
    beyond which its correction is degenerate; ``min_stations``.
    """

    sigma_field_nt: float = IFR_SIGMA[0]
    sigma_dip_deg: float = IFR_SIGMA[1]
    fit_reference: bool = True
    station_sigma_field_nt: float = 20.0
    station_sigma_dip_deg: float = 0.05
    estimate_station_sigma: bool = True
    parameters: str = "auto"
    limit_dz_nt: float = 50.0
    limit_msz: float = 0.002
    limit_mbxy_nt: float = 50.0
    reject_k: float = 4.0
    max_reject_fraction: float = 0.25
    max_azimuth_sigma_deg: float = AxialSettings.max_azimuth_sigma_deg
    min_stations: int = 3

    def __post_init__(self):
        if self.parameters != "auto" and self.parameters not in MODELS:
            raise ValueError(f"MSA parameters {self.parameters!r}: one of auto, {', '.join(MODELS)}")
        for name in ("sigma_field_nt", "sigma_dip_deg", "station_sigma_field_nt", "station_sigma_dip_deg",
                     "limit_dz_nt", "limit_msz", "limit_mbxy_nt", "reject_k", "max_azimuth_sigma_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"MSA setting {name} must be a positive number, not {v!r}")
        if not 0 <= self.max_reject_fraction < 1:
            raise ValueError(f"MSA setting max_reject_fraction must be in [0, 1), not {self.max_reject_fraction!r}")

    def limit(self, name: str) -> float:
        """The σ limit of a parameter (its unit: :data:`UNITS`; the reference offsets: their prior σ)."""
        return {"dz": self.limit_dz_nt, "msz": self.limit_msz, "mbx": self.limit_mbxy_nt, "mby": self.limit_mbxy_nt,
                "ref_field": self.sigma_field_nt, "ref_dip": self.sigma_dip_deg}[name]

    def axial(self) -> AxialSettings:
        """The short collar's settings with the same reference σ and degeneracy limit."""
        return AxialSettings(sigma_field_nt=self.sigma_field_nt, sigma_dip_deg=self.sigma_dip_deg,
                             max_azimuth_sigma_deg=self.max_azimuth_sigma_deg)


def reference_sigma(site: Site) -> tuple:
    """(σ total field nT, σ dip deg, why) of a site reference from where its values came from: a
    main-field model (WMM, IGRF) → :data:`MAIN_FIELD_MODEL_SIGMA`; measured (IFR) or typed in →
    :data:`IFR_SIGMA`."""
    sources = (site.reference or {}).get("sources", {})
    src = [str(sources.get(k, "")) for k in ("total_field_nt", "dip_deg")]
    if any(s and not s.startswith("measured") for s in src):
        return (*MAIN_FIELD_MODEL_SIGMA, f"reference from a main-field model ({src[0] or src[1]})")
    return (*IFR_SIGMA, "reference measured or given (IFR-like σ)")


@dataclass
class Candidate:
    """One parameter set tried: its parameters, their σ (tool parameters), whether all are
    observable, the station scatter and the stations rejected."""

    parameters: tuple
    sigma: dict
    observable: bool
    station_sigma_field_nt: float
    station_sigma_dip_deg: float
    rejected: list


@dataclass
class MSAResult:
    """The multi-station fit of a run (units: :data:`UNITS`).

    ``parameters``: the fitted names (tool parameters, then the reference offsets when fitted);
    ``values``/``sigma``: by name; ``covariance`` (in the order of ``parameters``, the reference
    dip offset in deg) and ``correlation``; ``condition_number`` of the column-scaled weighted
    Jacobian; ``smallest_singular_value`` of the weighted Jacobian with each parameter in units of
    its σ limit; ``parameter_observable`` by name; ``observable`` (every tool parameter); per
    station (N,): ``azimuth_deg`` (true: + declination), ``azimuth_sigma_deg``, ``degenerate``,
    ``used`` (entered the fit), ``rejected`` (outlier), ``residual_field_nt`` and
    ``residual_dip_deg`` (after the fit, against the fitted reference B + δB, δ + δD), ``field``
    (the corrected b', nT); ``station_sigma_*``: the scatter estimated; ``candidates``: every
    parameter set tried (``auto``); ``notes``: what was decided and why, in words.
    """

    parameters: tuple
    values: dict
    sigma: dict
    covariance: np.ndarray
    correlation: np.ndarray
    condition_number: float
    smallest_singular_value: float
    parameter_observable: dict
    observable: bool
    azimuth_deg: np.ndarray
    azimuth_sigma_deg: np.ndarray
    degenerate: np.ndarray
    used: np.ndarray
    rejected: np.ndarray
    residual_field_nt: np.ndarray
    residual_dip_deg: np.ndarray
    field: np.ndarray
    station_sigma_field_nt: float
    station_sigma_dip_deg: float
    reference_sigma: tuple
    candidates: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    @property
    def tool_parameters(self) -> tuple:
        return tuple(p for p in self.parameters if p in TOOL_PARAMETERS)

    def verdict(self) -> str:
        """The observability verdict in words."""
        if self.observable:
            return (f"observable: {', '.join(self.tool_parameters)} determined (σ below the limits); "
                    f"{int(self.degenerate.sum())} station(s) still degenerate")
        bad = [p for p in self.tool_parameters if not self.parameter_observable[p]]
        return (f"UNOBSERVABLE: σ of {', '.join(bad)} above the limit — the stations' attitudes do not separate "
                "the axial field from the reference's error (too little spread of the angle between tool axis and "
                "field: all near east-west at high inclination, or a straight tangent); the MSA correction is not "
                "used")

    def to_dict(self) -> dict:
        """Plain values (JSON): the parameters with σ and units, correlation, observability, the
        per-station azimuths and flags."""
        def f(x):
            return None if x is None or not np.isfinite(x) else float(x)
        return {
            "parameters": [{"name": p, "description": DESCRIPTION[p], "value": f(self.values[p]),
                            "sigma": f(self.sigma[p]), "unit": UNITS[p], "observable": self.parameter_observable[p]}
                           for p in self.parameters],
            "correlation": [[f(v) for v in row] for row in self.correlation],
            "condition_number": f(self.condition_number),
            "smallest_singular_value": f(self.smallest_singular_value),
            "observable": bool(self.observable), "verdict": self.verdict(),
            "reference_sigma": {"field_nt": self.reference_sigma[0], "dip_deg": self.reference_sigma[1]},
            "station_sigma": {"field_nt": f(self.station_sigma_field_nt), "dip_deg": f(self.station_sigma_dip_deg)},
            "stations_used": int(self.used.sum()), "rejected": [int(k) for k in np.flatnonzero(self.rejected)],
            "degenerate": [int(k) for k in np.flatnonzero(self.degenerate)],
            "azimuth_deg": [f(v) for v in self.azimuth_deg],
            "azimuth_sigma_deg": [f(v) for v in self.azimuth_sigma_deg],
            "candidates": [{"parameters": list(c.parameters), "observable": c.observable,
                            "sigma": {k: f(v) for k, v in c.sigma.items()},
                            "station_sigma_field_nt": f(c.station_sigma_field_nt),
                            "station_sigma_dip_deg": f(c.station_sigma_dip_deg), "rejected": c.rejected}
                           for c in self.candidates],
            "notes": list(self.notes),
        }


# --------------------------------------------------------------------------------------------
# The model and its derivatives
# --------------------------------------------------------------------------------------------
def corrected_field(b, values: dict) -> np.ndarray:
    """``b' = [b_x − MBX, b_y − MBY, (b_z − Δz)/(1 + MSZ)]`` (nT, (N, 3)); missing names are 0."""
    b = np.atleast_2d(np.asarray(b, dtype=float))
    out = b.copy()
    out[:, 0] -= values.get("mbx", 0.0)
    out[:, 1] -= values.get("mby", 0.0)
    out[:, 2] = (b[:, 2] - values.get("dz", 0.0)) / (1.0 + values.get("msz", 0.0))
    return out


def _dfield(bp, names, values) -> np.ndarray:
    """∂b'/∂θ, (N, 3, p) for the tool parameters ``names``."""
    k = 1.0 + values.get("msz", 0.0)
    d = np.zeros((len(bp), 3, len(names)))
    for j, n in enumerate(names):
        if n == "dz":
            d[:, 2, j] = -1.0 / k
        elif n == "msz":
            d[:, 2, j] = -bp[:, 2] / k
        elif n == "mbx":
            d[:, 0, j] = -1.0
        elif n == "mby":
            d[:, 1, j] = -1.0
    return d


def azimuth_gradient(g, b) -> np.ndarray:
    """∂A/∂b (rad per nT, (N, 3)) of the azimuth of paper eq. 2 (:func:`frames.azimuth_deg`):
    ``A = atan2(num, den)``, ``num = |g|(b_y g_x − b_x g_y)``, ``den = b_z(g_x² + g_y²) −
    g_z(b_x g_x + b_y g_y)``, so ``∂A = (den·∂num − num·∂den)/(num² + den²)``."""
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    gx, gy, gz = g[:, 0], g[:, 1], g[:, 2]
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    gn = np.linalg.norm(g, axis=1)
    num = gn * (by * gx - bx * gy)
    den = bz * (gx * gx + gy * gy) - gz * (bx * gx + by * gy)
    dnum = np.stack([-gn * gy, gn * gx, np.zeros_like(gx)], axis=1)
    dden = np.stack([-gz * gx, -gz * gy, gx * gx + gy * gy], axis=1)
    q = num * num + den * den
    with np.errstate(invalid="ignore", divide="ignore"):
        return (den[:, None] * dnum - num[:, None] * dden) / q[:, None]


@dataclass
class _Fit:
    x: np.ndarray           # tool parameters, then δB (nT), δD (rad)
    jac: np.ndarray         # weighted Jacobian of all rows (2n stations + 2 priors)
    e_field: np.ndarray     # unweighted residuals of the kept stations (nT)
    e_dip: np.ndarray       # (rad)
    h_field: np.ndarray     # leverages
    h_dip: np.ndarray
    s_field: float          # station scatter used (nT)
    s_dip: float            # (rad)


class _Problem:
    """The weighted least-squares problem of the kept stations."""

    def __init__(self, u, b, site: Site, names, settings: MSASettings):
        self.u, self.b, self.site, self.names, self.settings = u, b, site, tuple(names), settings
        self.p = len(self.names)
        self.ref = settings.fit_reference
        self.s_ref_b = settings.sigma_field_nt
        self.s_ref_d = math.radians(settings.sigma_dip_deg)
        self.dip0 = math.radians(site.dip_deg)

    def split(self, x):
        vals = dict(zip(self.names, x[:self.p]))
        db, dd = (x[self.p], x[self.p + 1]) if self.ref else (0.0, 0.0)
        return vals, db, dd

    def model(self, x, kept):
        vals, db, dd = self.split(x)
        u, b = self.u[kept], self.b[kept]
        bp = corrected_field(b, vals)
        fn = np.linalg.norm(bp, axis=1)
        s = np.clip(np.sum(u * bp, axis=1) / fn, -1.0, 1.0)
        e_b = fn - (self.site.total_field_nt + db)
        e_d = np.arcsin(s) - (self.dip0 + dd)
        return vals, bp, fn, s, e_b, e_d

    def residuals(self, x, kept, s_b, s_d):
        _, _, _, _, e_b, e_d = self.model(x, kept)
        r = [e_b / s_b, e_d / s_d]
        if self.ref:
            r.append(np.array([x[self.p] / self.s_ref_b, x[self.p + 1] / self.s_ref_d]))
        return np.concatenate(r)

    def jacobian(self, x, kept, s_b, s_d):
        vals, bp, fn, s, _, _ = self.model(x, kept)
        u = self.u[kept]
        dbp = _dfield(bp, self.names, vals)                                   # (n, 3, p)
        d_f = np.einsum("ni,nij->nj", bp / fn[:, None], dbp)                  # ∂F/∂θ
        ds_db = (u - s[:, None] * bp / fn[:, None]) / fn[:, None]             # ∂S/∂b'
        d_d = np.einsum("ni,nij->nj", ds_db, dbp) / np.sqrt(np.maximum(1 - s * s, 1e-15))[:, None]
        n = len(bp)
        q = self.p + (2 if self.ref else 0)
        jac = np.zeros((2 * n + (2 if self.ref else 0), q))
        jac[:n, :self.p] = d_f / s_b
        jac[n:2 * n, :self.p] = d_d / s_d
        if self.ref:
            jac[:n, self.p] = -1.0 / s_b
            jac[n:2 * n, self.p + 1] = -1.0 / s_d
            jac[2 * n, self.p] = 1.0 / self.s_ref_b
            jac[2 * n + 1, self.p + 1] = 1.0 / self.s_ref_d
        return jac

    def solve(self, kept, x0=None) -> _Fit:
        """Fit with the station scatter re-estimated from the residuals until stable."""
        st = self.settings
        s_b, s_d = st.station_sigma_field_nt, math.radians(st.station_sigma_dip_deg)
        x = np.zeros(self.p + (2 if self.ref else 0)) if x0 is None else np.array(x0, dtype=float)
        for _ in range(8):
            sol = least_squares(self.residuals, x, jac=self.jacobian, args=(kept, s_b, s_d), method="lm",
                                xtol=1e-12, ftol=1e-12, gtol=1e-12)
            x = sol.x
            jac = self.jacobian(x, kept, s_b, s_d)
            h = _leverages(jac)
            _, _, _, _, e_b, e_d = self.model(x, kept)
            n = len(e_b)
            h_b, h_d = h[:n], h[n:2 * n]
            if not st.estimate_station_sigma:
                break
            new = []
            for e, hh, old, floor in ((e_b, h_b, s_b, 1e-3), (e_d, h_d, s_d, 1e-8)):
                dof = float(np.sum(1.0 - hh))
                new.append(max(math.sqrt(float(np.sum(e * e)) / dof), floor) if dof >= 2.0 else old)
            done = abs(new[0] / s_b - 1) < 1e-3 and abs(new[1] / s_d - 1) < 1e-3
            s_b, s_d = new
            if done:
                jac = self.jacobian(x, kept, s_b, s_d)
                h = _leverages(jac)
                h_b, h_d = h[:n], h[n:2 * n]
                break
        return _Fit(x, jac, e_b, e_d, h_b, h_d, s_b, s_d)


def _leverages(jac) -> np.ndarray:
    """Diagonal of the hat matrix ``J(JᵀJ)⁻¹Jᵀ`` (rank-revealing: directions without information
    carry no leverage)."""
    u, s, _ = np.linalg.svd(jac, full_matrices=False)
    keep = s > s.max() * 1e-10 if s.size and s.max() > 0 else np.zeros(len(s), bool)
    return np.sum(u[:, keep] ** 2, axis=1)


def _covariance(jac):
    """(JᵀJ)⁻¹ by SVD of the column-scaled J, and that J's condition number (∞ where singular)."""
    norms = np.linalg.norm(jac, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
    _, s, vt = np.linalg.svd(jac * scale, full_matrices=False)
    with np.errstate(divide="ignore"):
        inv = np.where(s > 0, 1.0 / s ** 2, np.inf)
    cov = (vt.T * inv) @ vt if np.all(np.isfinite(inv)) else np.full((len(s), len(s)), np.inf)
    cov = cov * scale[:, None] * scale[None, :]
    cov[:, norms == 0] = np.inf
    cov[norms == 0, :] = np.inf
    cond = float(s.max() / s.min()) if s.size and s.min() > 0 else float("inf")
    return cov, cond


# --------------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------------
def _robust_fit(problem: _Problem, use: np.ndarray):
    """Fit with iterative rejection of outlier stations (module docstring); returns (fit, kept
    mask, rejected indices, note or None)."""
    st = problem.settings
    kept = use.copy()
    rejected = []
    max_reject = int(math.floor(st.max_reject_fraction * use.sum()))
    fit = problem.solve(kept)
    while True:
        idx = np.flatnonzero(kept)
        z = np.zeros(len(idx))
        for e, h in ((fit.e_field, fit.h_field), (fit.e_dip, fit.h_dip)):
            std = np.abs(e) / np.sqrt(np.maximum(1.0 - h, 1e-12))
            scale = max(1.4826 * float(np.median(std)), 1e-12)
            z = np.maximum(z, std / scale)
        worst = int(np.argmax(z))
        if z[worst] <= st.reject_k:
            return fit, kept, rejected, None
        if len(rejected) >= max_reject or kept.sum() - 1 < max(st.min_stations, len(fit.x)):
            return fit, kept, rejected, (
                f"station {int(idx[worst])} still departs {z[worst]:.1f} robust σ from the run's fit after "
                f"{len(rejected)} rejection(s) (limit {max_reject}): interference is not confined to a few stations")
        kept[idx[worst]] = False
        rejected.append(int(idx[worst]))
        fit = problem.solve(kept, fit.x)


def fit(g, b, site: Site, settings: MSASettings = MSASettings(), use=None) -> MSAResult:
    """Multi-station fit of a run's corrected vectors: g (m/s², down positive) and b (nT),
    (N, 3) each, tool frame, against ``site`` (total field, dip, declination) — see the module
    docstring for the model, the weights and the verdicts.

    ``use``: (N,) bool, the stations that may enter the fit (e.g. not those in which the probe
    moved); stations with non-finite vectors never do.  Every station gets the correction.
    Raises ``ValueError`` with fewer than ``settings.min_stations`` usable stations.
    """
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    if g.shape != b.shape or g.shape[1:] != (3,):
        raise ValueError(f"MSA: g and b must be (N, 3) arrays of one shape, not {g.shape} and {b.shape}")
    n = len(g)
    finite = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(b), axis=1)
    use = finite if use is None else (np.asarray(use, dtype=bool).reshape(n) & finite)
    if use.sum() < settings.min_stations:
        raise ValueError(f"MSA needs at least {settings.min_stations} stations with finite vectors; "
                         f"{int(use.sum())} of {n} given")
    gn = np.linalg.norm(np.where(finite[:, None], g, 1.0), axis=1)
    u = np.where(finite[:, None], g, 0.0) / gn[:, None]
    bb = np.where(finite[:, None], b, 0.0)

    names_tried = list(MODELS.values()) if settings.parameters == "auto" else [MODELS[settings.parameters]]
    tried = []
    for names in names_tried:
        pr = _Problem(u, bb, site, names, settings)
        f, kept, rejected, note = _robust_fit(pr, use)
        cov, cond = _covariance(f.jac)
        sig = {nm: float(np.sqrt(cov[j, j])) for j, nm in enumerate(names)}
        obs = all(sig[nm] <= settings.limit(nm) for nm in names)
        tried.append((pr, f, kept, rejected, note, cov, cond,
                      Candidate(tuple(names), sig, obs, f.s_field, math.degrees(f.s_dip), list(rejected))))
    notes = []
    ok = [t for t in tried if t[7].observable]
    if ok:
        best = max(ok, key=lambda t: (len(t[7].parameters), -math.log(t[7].station_sigma_field_nt)
                                      - math.log(t[7].station_sigma_dip_deg)))
    else:
        best = tried[0]
    pr, f, kept, rejected, note, cov, cond, cand = best
    if settings.parameters == "auto":
        more = [" + ".join(t[7].parameters) for t in tried if len(t[7].parameters) > len(cand.parameters)]
        notes.append(f"parameters the data support: {', '.join(cand.parameters)}"
                     + (f" (not {'; '.join(more)}: some σ above the limits)" if more and cand.observable else ""))
    if note:
        notes.append(note)
    if rejected:
        notes.append(f"rejected as outliers (standardised residual > {settings.reject_k:g}): stations "
                     + ", ".join(str(k) for k in rejected))

    names = pr.names + (REFERENCE_PARAMETERS if pr.ref else ())
    x = f.x.copy()
    conv = np.ones(len(names))
    if pr.ref:
        conv[-1] = math.degrees(1.0)      # the dip offset reported in degrees
    x = x * conv
    cov = cov * conv[:, None] * conv[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.sqrt(np.diag(cov))
        corr = cov / np.outer(sd, sd)
    limits = np.array([settings.limit(nm) for nm in names]) / conv
    s_lim = np.linalg.svd(f.jac * limits, compute_uv=False)
    values = dict(zip(names, x.tolist()))
    sigma = dict(zip(names, sd.tolist()))
    param_obs = {nm: bool(sigma[nm] <= settings.limit(nm)) for nm in names}
    observable = all(param_obs[nm] for nm in pr.names)

    # every station corrected with the run's parameters; azimuth σ from the tool parameters' covariance
    tool_vals = {nm: values[nm] for nm in pr.names}
    bp = corrected_field(bb, tool_vals)
    az = frames.wrap360(frames.azimuth_deg(u, bp) + site.declination_deg)
    grad = np.einsum("ni,nij->nj", azimuth_gradient(u, bp), _dfield(bp, pr.names, tool_vals))
    ct = cov[:len(pr.names), :len(pr.names)]
    with np.errstate(invalid="ignore"):
        var = np.einsum("ni,ij,nj->n", grad, ct, grad) if np.all(np.isfinite(ct)) else np.full(n, np.inf)
    az_sigma = np.degrees(np.sqrt(np.maximum(var, 0.0)))
    az_sigma = np.where(np.isfinite(az_sigma), az_sigma, np.inf)
    fn = np.linalg.norm(bp, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        dip = dip_of(np.sum(u * bp, axis=1), 1.0, fn)       # u: unit vectors
    db = values.get("ref_field", 0.0)
    dd = values.get("ref_dip", 0.0)
    nan = ~finite
    az[nan] = np.nan
    rej = np.zeros(n, bool)
    rej[rejected] = True
    return MSAResult(
        parameters=names, values=values, sigma=sigma, covariance=cov, correlation=corr, condition_number=cond,
        smallest_singular_value=float(s_lim.min()) if s_lim.size else float("nan"),
        parameter_observable=param_obs, observable=observable, azimuth_deg=az, azimuth_sigma_deg=az_sigma,
        degenerate=(az_sigma > settings.max_azimuth_sigma_deg) | nan, used=kept, rejected=rej,
        residual_field_nt=np.where(nan, np.nan, fn - (site.total_field_nt + db)),
        residual_dip_deg=np.where(nan, np.nan, dip - (site.dip_deg + dd)), field=np.where(nan[:, None], np.nan, bp),
        station_sigma_field_nt=f.s_field, station_sigma_dip_deg=math.degrees(f.s_dip),
        reference_sigma=(settings.sigma_field_nt, settings.sigma_dip_deg),
        candidates=[t[7] for t in tried], notes=notes)


def evaluate_with_msa(g, b, site: Site, tol=None, ref=None, settings: MSASettings = MSASettings(), use=None):
    """``survey.evaluate`` with the azimuth from the multi-station fit; returns ``(result dict,
    MSAResult)``.

    As :func:`axial.evaluate_with_axial`: QC stays on the measured field; the fields
    ``axial_field_nt`` (the run's Δz), ``axial_field_sigma_nt``, ``azimuth_sigma_deg``,
    ``axial_degenerate`` and ``azimuth_method`` ('msa' or 'standard') are added, plus
    ``msa_rejected`` and ``msa_unobservable``.  A degenerate station keeps its standard azimuth; an
    unobservable run keeps every standard azimuth (and every station says so, status at least
    warn).  The azimuth is replaced in all three references (true, magnetic, grid).
    """
    from ..core.geomag import azimuths
    from ..core.survey import Tolerances, evaluate, reference_errors

    tol = tol or Tolerances()
    res = evaluate(g, b, site, tol, ref=ref)
    m = fit(g, b, site, settings, use=use)
    n = len(res["status"])
    apply = m.observable & ~m.degenerate & ~res["azimuth_undefined"]
    az = np.where(apply, m.azimuth_deg, res["azimuth_deg"])
    refs = azimuths(az, site.declination_deg, site.grid_convergence_deg)
    res["azimuth_deg"] = refs["true"]
    res["azimuth_magnetic_deg"], res["azimuth_grid_deg"] = refs["magnetic"], refs["grid"]
    res["axial_field_nt"] = np.full(n, m.values["dz"])
    res["axial_field_sigma_nt"] = np.full(n, m.sigma["dz"])
    res["azimuth_sigma_deg"] = m.azimuth_sigma_deg
    res["axial_degenerate"] = m.degenerate
    res["msa_rejected"] = m.rejected
    res["msa_unobservable"] = np.full(n, not m.observable)
    res["azimuth_method"] = np.where(apply, "msa", "standard")
    flagged = m.degenerate | m.rejected | ~m.observable
    res["status"] = np.where(flagged & (res["status"] == 0), 1, res["status"])
    if ref is not None:
        res.update(reference_errors(res, ref, site, tol))
    return res, m


# --------------------------------------------------------------------------------------------
# Short collar against MSA on simulated runs
# --------------------------------------------------------------------------------------------
def compare_methods(g, b, site: Site, true_azimuth_deg, settings: MSASettings = MSASettings(), use=None,
                    score=None) -> dict:
    """Azimuth errors (deg, against ``true_azimuth_deg`` from the site's north) of the same
    stations three ways: ``none`` (the measured field), ``short_collar`` (:func:`axial.correct`
    station by station, degenerate stations keeping the standard azimuth, as
    :func:`axial.evaluate_with_axial` reports them) and ``msa`` (:func:`fit`; degenerate stations
    and unobservable runs keep the standard azimuth, as :func:`evaluate_with_msa` reports them).
    Both corrections use the same reference σ (``settings``).

    Returns per method ``rms_deg``, ``max_abs_deg`` and ``errors_deg`` over the stations with a
    defined azimuth (and ``score`` True: e.g. leaving out stations with known external
    interference, which no method corrects), ``degenerate`` counts, and ``fit`` (the
    :class:`MSAResult`).
    """
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    truth = np.asarray(true_azimuth_deg, dtype=float)
    defined = frames.azimuth_defined(g) & np.isfinite(truth)
    if score is not None:
        defined &= np.asarray(score, dtype=bool)
    plain = frames.wrap360(frames.azimuth_deg(g, b) + site.declination_deg)
    sc = short_collar(g, b, site, settings.axial())
    sc_az = np.where(sc["degenerate"], plain, sc["azimuth_deg"])
    m = fit(g, b, site, settings, use=use)
    msa_az = np.where(m.observable & ~m.degenerate, m.azimuth_deg, plain)

    def stats(az):
        e = frames.wrap180(az - truth)[defined]
        return {"rms_deg": float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan"),
                "max_abs_deg": float(np.max(np.abs(e))) if e.size else float("nan"), "errors_deg": e}

    return {"stations": int(defined.sum()), "none": stats(plain),
            "short_collar": {**stats(sc_az), "degenerate": int(sc["degenerate"][defined].sum())},
            "msa": {**stats(msa_az), "degenerate": int(m.degenerate[defined].sum()), "observable": m.observable,
                    "rejected": int(m.rejected.sum())},
            "fit": m}


#: Simulated well paths (:func:`simulate.well_path_session` arguments): a build-and-turn well
#: from near vertical to 85°, and a horizontal lateral near east–west (the degeneracy).
PATHS = {
    "build_turn": dict(kickoff_deg=2.0, build_deg_per_station=3.0, max_drift_deg=85.0, turn_deg_per_station=1.5),
    "east_west": dict(kickoff_deg=87.0, build_deg_per_station=0.2, max_drift_deg=92.0, turn_deg_per_station=0.15),
}


def simulate_run(seed: int, path: str = "build_turn", n_stations: int = 30, axial_nt: float = 500.0,
                 msz: float = 0.0, mbxy_nt=(0.0, 0.0), reference_sigma=IFR_SIGMA, reference_error=None,
                 site: Site = Site(total_field_nt=50000.0, dip_deg=60.0), noise_mag_nt: float = 20.0,
                 noise_acc_mps2: float = 0.002, samples_per_station: int = 200, station_noise_nt: float = 15.0,
                 outliers: int = 0, outlier_nt: float = 2000.0) -> dict:
    """A survey run with drill-string interference, at station level, through the simulator.

    Stations follow :func:`simulate.well_path_session` on ``path`` (:data:`PATHS`; the start
    azimuth is drawn from the seed — for ``east_west`` 88–92° or 268–272° at 87–92°); each
    station's true vectors in ``site`` go through a :class:`simulate.SimulatedProbe` whose
    magnetometer has the Z scale error ``msz``, the X/Y biases ``mbxy_nt`` and the survey-only axial
    interference (``axial_nt``, nT), with the white noise of ``samples_per_station`` samples
    averaged (``noise_*`` per sample).  ``station_noise_nt`` (1σ per axis, nT) is the
    station-to-station scatter that averaging does not remove — residual calibration errors, the
    local field's variation along the well — drawn per station.  ``outliers`` stations get an
    external field of ``outlier_nt`` in a random direction.  The reference the solver is given differs from ``site`` by
    ``reference_error`` (δB nT, δdip deg) or, when None, by a draw of ``reference_sigma``.

    Returns ``g``, ``b`` (corrected tool frame: the base model is ideal), ``inc_deg``,
    ``azimuth_deg``, ``toolface_deg`` (truth), ``site`` (the solver's reference), ``site_true``,
    ``dz_nt`` (the axial field as MSA sees it: (1 + MSZ)·Δ, the scale acting on the interference
    too), ``msz``, ``mbxy_nt``, ``outliers`` (indices), ``reference_error``.
    """
    from ..core import effects as fx
    from ..calibrate import simulate as sim
    from ..core.errormodel import TriadModel
    from ..core.model import ProbeModel

    if path not in PATHS:
        raise ValueError(f"path {path!r}: one of {', '.join(PATHS)}")
    rng = np.random.default_rng(seed)
    start = float(rng.uniform(0, 360)) if path == "build_turn" else float(88.0 + 180.0 * rng.integers(0, 2))
    plan = sim.well_path_session(n_stations=n_stations, azimuth_start_deg=start, seed=seed, **PATHS[path])
    ref = np.array([st.ref for st in plan])
    mag = TriadModel(scale=[1.0, 1.0, 1.0 + msz], bias=[mbxy_nt[0], mbxy_nt[1], 0.0])
    interference = fx.AxialInterference(sensor="mag", axes="z", values={"field": np.array([axial_nt])})
    probe = sim.SimulatedProbe(ProbeModel.base(TriadModel(), mag).with_effect(interference),
                               noise_acc=noise_acc_mps2 / math.sqrt(samples_per_station),
                               noise_mag=noise_mag_nt / math.sqrt(samples_per_station))
    g0, b0 = frames.tool_vectors(site, ref[:, 0], ref[:, 1], ref[:, 2])
    temps = np.array([st.temp_c for st in plan])
    times = 60.0 * np.arange(n_stations)
    g, m = probe.measure_gravity(g0, b0, temps, times, rng, survey=True)
    m = m + rng.normal(0.0, station_noise_nt, m.shape)
    out_idx = np.sort(rng.choice(n_stations, size=outliers, replace=False)) if outliers else np.array([], int)
    for k in out_idx:
        v = rng.normal(size=3)
        m[k] += frames.orientation_matrix(*ref[k]).T @ (outlier_nt * v / np.linalg.norm(v))
    if reference_error is None:
        reference_error = (float(rng.normal(0, reference_sigma[0])), float(rng.normal(0, reference_sigma[1])))
    solver_site = Site(total_field_nt=site.total_field_nt + reference_error[0],
                       dip_deg=site.dip_deg + reference_error[1], declination_deg=site.declination_deg,
                       gravity_mps2=site.gravity_mps2)
    return {"g": g, "b": m, "inc_deg": ref[:, 0], "azimuth_deg": ref[:, 1],
            "toolface_deg": ref[:, 2], "site": solver_site, "site_true": site, "dz_nt": (1.0 + msz) * axial_nt,
            "msz": msz, "mbxy_nt": tuple(mbxy_nt), "outliers": out_idx, "reference_error": tuple(reference_error)}


def compare_on_simulated_runs(seeds, settings: MSASettings | None = None, **run) -> dict:
    """:func:`compare_methods` on :func:`simulate_run` runs, one per seed (``run``: its
    arguments; ``settings`` default: the run's reference σ).  Returns per method (and ``floor``:
    the simulator's true tool parameters removed, what a perfect fit leaves) the azimuth RMS
    of every run (``rms_deg``, a list; stations with simulated external interference left out of
    the statistics, not of the fit), their median and mean, how many runs MSA beat the short
    collar, how many runs MSA found observable, and how many outlier stations it rejected
    (``rejected_outliers``) and how many clean ones (``rejected_clean``)."""
    rs = run.get("reference_sigma", IFR_SIGMA)
    settings = settings or MSASettings(sigma_field_nt=rs[0], sigma_dip_deg=rs[1])
    out = {k: [] for k in ("none", "short_collar", "msa", "floor")}
    observable = rej_out = rej_clean = 0
    for s in seeds:
        r = simulate_run(int(s), **run)
        clean = np.ones(len(r["g"]), bool)
        clean[r["outliers"]] = False
        c = compare_methods(r["g"], r["b"], r["site"], r["azimuth_deg"], settings, score=clean)
        for k in ("none", "short_collar", "msa"):
            out[k].append(c[k]["rms_deg"])
        # the floor: the simulator's own tool parameters removed (what a perfect fit would leave)
        true = {"dz": r["dz_nt"], "msz": r["msz"], "mbx": r["mbxy_nt"][0], "mby": r["mbxy_nt"][1]}
        az = frames.azimuth_deg(r["g"], corrected_field(r["b"], true)) + r["site"].declination_deg
        e = frames.wrap180(az - r["azimuth_deg"])[clean & frames.azimuth_defined(r["g"])]
        out["floor"].append(float(np.sqrt(np.mean(e ** 2))))
        observable += bool(c["msa"]["observable"])
        rej_out += int(np.sum(c["fit"].rejected & ~clean))
        rej_clean += int(np.sum(c["fit"].rejected & clean))
    summary = {k: {"rms_deg": v, "median_deg": float(np.median(v)), "mean_deg": float(np.mean(v))}
               for k, v in out.items()}
    summary["msa_beats_short_collar"] = int(np.sum(np.array(out["msa"]) < np.array(out["short_collar"])))
    summary["runs"] = len(out["msa"])
    summary["msa_observable"] = observable
    summary["rejected_outliers"], summary["rejected_clean"] = rej_out, rej_clean
    return summary


#: The scenarios of docs/interference.md (:func:`comparison_table`).
SCENARIOS = {
    "build-and-turn, IFR reference (50 nT, 0.1°), Δz 500 nT": dict(path="build_turn", axial_nt=500.0),
    "build-and-turn, WMM reference (152 nT, 0.22°), Δz 500 nT": dict(path="build_turn", axial_nt=500.0,
                                                                      reference_sigma=MAIN_FIELD_MODEL_SIGMA),
    "build-and-turn, WMM reference, Δz 800 nT, 3 stations with 2000 nT external": dict(
        path="build_turn", axial_nt=800.0, reference_sigma=MAIN_FIELD_MODEL_SIGMA, outliers=3),
    "east-west lateral (87–92°, azimuth 88–92° or 268–272°), IFR reference, Δz 300 nT": dict(
        path="east_west", axial_nt=300.0),
}


def comparison_table(seeds=range(20)) -> str:
    """The comparison of docs/interference.md as a Markdown table: azimuth RMS (deg; median and
    mean over the seeds' runs) of no correction, the short collar and MSA per scenario."""
    lines = ["| run | none | short collar | MSA | floor | MSA better | MSA observable |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, run in SCENARIOS.items():
        s = compare_on_simulated_runs(seeds, **run)
        cell = (lambda k: f"{s[k]['median_deg']:.3f} / {s[k]['mean_deg']:.3f}")
        lines.append(f"| {name} | {cell('none')} | {cell('short_collar')} | {cell('msa')} | "
                     f"{cell('floor')} | {s['msa_beats_short_collar']}/{s['runs']} | "
                     f"{s['msa_observable']}/{s['runs']} |")
    return "\n".join(lines)


def format_result(m: MSAResult, station_ids=None, inc_deg=None) -> str:
    """The fit in words and a per-station table (for the CLI)."""
    lines = ["Multi-station analysis (MSA) of axial interference:"]
    for p in m.parameters:
        lines.append(f"  {DESCRIPTION[p]:<36}{m.values[p]:>12.4g} ± {m.sigma[p]:.3g} {UNITS[p]}"
                     f"{'' if m.parameter_observable[p] else '   (σ above the limit)'}")
    if len(m.parameters) > 1:
        lines.append("  correlation " + " ".join(f"{p:>9}" for p in m.parameters))
        for i, p in enumerate(m.parameters):
            lines.append(f"  {p:>11} " + " ".join(f"{m.correlation[i, j]:>9.2f}" for j in range(len(m.parameters))))
    lines.append(f"  reference σ {m.reference_sigma[0]:g} nT, {m.reference_sigma[1]:g} deg; station scatter "
                 f"{m.station_sigma_field_nt:.3g} nT, {m.station_sigma_dip_deg:.3g} deg; {int(m.used.sum())} stations "
                 f"in the fit")
    lines.append(f"  condition number {m.condition_number:.3g}; smallest singular value in limit units "
                 f"{m.smallest_singular_value:.3g}")
    lines.append(f"  verdict: {m.verdict()}")
    for note in m.notes:
        lines.append(f"  {note}")
    ids = list(range(len(m.azimuth_deg))) if station_ids is None else list(station_ids)
    lines.append(f"  {'station':>7} {'drift':>8} {'azimuth':>9} {'σ':>7}  flags")
    for k, sid in enumerate(ids):
        flags = [n for n, v in (("degenerate", m.degenerate[k]), ("rejected", m.rejected[k]),
                                ("not_in_fit", not m.used[k] and not m.rejected[k])) if v]
        inc = "" if inc_deg is None else f"{inc_deg[k]:.3f}"
        lines.append(f"  {sid:>7} {inc:>8} {m.azimuth_deg[k]:>9.3f} {m.azimuth_sigma_deg[k]:>7.3f}  {' '.join(flags)}")
    return "\n".join(lines)


if __name__ == "__main__":   # the figures of docs/interference.md
    print(comparison_table())

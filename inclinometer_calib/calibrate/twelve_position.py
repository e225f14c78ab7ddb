"""The seed paper's twelve-position calibration (Table 1; eqs. 5–16) and its inversion (17–32).

The probe is rolled on a non-magnetic three-axis stand through the twelve poses of Table 1.  In
each pose every tool axis points along a stand axis (down/up/east/west/north/south), so each
sensor axis sees ±M_d (or ±g_d) in four poses and the horizontal components elsewhere.  The
closed-form solution uses only the vertical reference component (M_d for the magnetometer, g_d for
the accelerometer): the horizontal components cancel in eqs. 5–16, so neither a north reference nor
an exactly level stand is needed.

Inputs are per-pose mean vectors in the *gravity-vector* convention for the accelerometer (down
positive: stations carry it, converted from REP-145 specific force where the samples entered) and in
output units (nT or A/D counts) for the magnetometer.

Several rounds of the twelve poses (e.g. at different temperatures) are all used: the pose means
are averaged over rounds before eqs. 5–16 (which are linear in the outputs, so this equals the
average of the per-round solutions), and the round-to-round spread per pose is reported.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.errormodel import TriadModel
from ..core.formulas import dip_of
from ..core.frames import pose_matrix

POSES = tuple(range(1, 13))


def pose_reference(pose: int, ref_ned) -> np.ndarray:
    """True tool-frame vector in a pose for an NED reference vector (Table 1's M/G columns)."""
    return pose_matrix(pose).T @ np.asarray(ref_ned, dtype=float)


def _gravity_candidates(g_tool, tolerance_deg):
    g = np.asarray(g_tool, dtype=float)
    n = np.linalg.norm(g)
    if not np.isfinite(n) or n == 0:
        return []
    u = g / n
    out = []
    for p in POSES:
        down_tool = pose_matrix(p).T @ np.array([0.0, 0.0, 1.0])
        if np.degrees(np.arccos(np.clip(u @ down_tool, -1, 1))) <= tolerance_deg:
            out.append(p)
    return out


def field_heading_deg(pose: int, b_tool) -> float:
    """Heading (deg, from the stand's north towards its east) of the field's horizontal part in
    the stand frame, if the probe is in ``pose``: ``atan2(h_E, h_N)`` of ``h = P·b``.  Raw (not
    yet calibrated) fields give it to within a few degrees."""
    h = pose_matrix(pose) @ np.asarray(b_tool, dtype=float)
    return float(np.degrees(np.arctan2(h[1], h[0])))


def identify_pose(g_tool, b_tool, heading_deg: float = 0.0, tolerance_deg: float = 15.0):
    """Pose from gravity (which tool axis is vertical, and its sign: a pair of poses of Table 1,
    turned 180° about the vertical from each other) and, within the pair, the member whose field
    heading in the stand frame (:func:`field_heading_deg`) is nearest ``heading_deg`` — 0 for a
    stand set up against magnetic north as in the paper, else the stand's measured heading.

    Returns ``(pose, heading_misfit_deg)``, or ``(None, nan)`` when no tool axis is within
    ``tolerance_deg`` of the vertical.
    """
    cands = _gravity_candidates(g_tool, tolerance_deg)
    if not cands:
        return None, float("nan")
    miss = {p: abs(_wrap180(field_heading_deg(p, b_tool) - heading_deg)) for p in cands}
    best = min(cands, key=miss.get)
    return best, float(miss[best])


def _wrap180(a):
    return (a + 180.0) % 360.0 - 180.0


# --------------------------------------------------------------------------------------------
# Closed-form solution, eqs. 5–16
# --------------------------------------------------------------------------------------------
def solve_closed_form(h: np.ndarray, vertical_ref: float) -> TriadModel:
    """Paper eqs. 5–16 for one triad from the 12 pose means ``h`` (shape (12, 3), row i = pose i+1).

    ``vertical_ref`` is M_d (or g_d): the reference's down component, in input units.  Each group
    of four poses (1–4, 5–8, 9–12) puts one tool axis j on the vertical and gives bias B_j (eqs.
    5, 9, 13), scale K_j (6, 10, 14 — eq. 14 as printed drops the index of H_z12) and the
    terms of column j of E (7–8, 11–12, 15–16).
    """
    h = np.asarray(h, dtype=float)
    if h.shape != (12, 3):
        raise ValueError(f"twelve-position solve needs 12 pose means of 3 axes, got shape {h.shape}")
    if not np.all(np.isfinite(h)):
        bad = sorted({int(i) + 1 for i in np.argwhere(~np.isfinite(h))[:, 0]})
        raise ValueError(f"pose means not finite for pose(s) {bad}")
    if vertical_ref == 0 or not np.isfinite(vertical_ref):
        raise ValueError("the vertical reference component must be finite and non-zero")
    a = np.zeros((3, 3))
    bias = np.zeros(3)
    for j in range(3):  # j: the tool axis that is vertical in poses 4j+1 .. 4j+4
        p1, p2, p3, p4 = h[4 * j: 4 * j + 4]
        bias[j] = (p1[j] + p2[j] + p3[j] + p4[j]) / 4.0  # eqs. 5, 9, 13
        # (p1 + p2 - p3 - p4) / (4 Md): column j of K·E — the diagonal is K_j (eqs. 6, 10, 14),
        # the off-diagonals are K_i·e_ji (eqs. 7–8, 11–12, 15–16 before dividing by K_i).
        a[:, j] = (p1 + p2 - p3 - p4) / (4.0 * vertical_ref)
        if a[j, j] == 0.0:
            axis = "xyz"[j]
            raise ValueError(f"scale K_{axis} = 0 (from poses {_GROUPS[j]}): the {axis} axis output does not "
                             f"change between its up and down poses — a dead or stuck axis, or poses "
                             f"{_GROUPS[j]} not taken as labelled; no coefficients written")
    return TriadModel.from_matrix(a, bias)


def paper_correction_closed_form(model: TriadModel):
    """Eqs. 20–32 exactly as printed in the paper: returns ``(C, D)``.

    Kept for the record and for the test that shows where the printed closed forms agree with the
    matrix inverse and where they carry typos (B1, eq. 21 and D1, eq. 23).  Production code uses
    :attr:`TriadModel.correction_matrix` (a plain inverse) instead.
    """
    e = model.e
    eyx, ezx, exy, ezy, exz, eyz = (e[k] for k in ("e_yx", "e_zx", "e_xy", "e_zy", "e_xz", "e_yz"))
    kx, ky, kz = model.scale
    bx, by, bz = model.bias
    t = eyx * exy + ezx * exz + ezy * eyz - eyx * ezy * exz - ezx * exy * eyz - 1  # (32)
    c = np.array([
        [(ezy * eyz - 1) / (kx * t), (eyx - ezx * ezy) / (ky * t), (ezx - eyx * ezy) / (kz * t)],
        [(exy - ezy * exz) / (kx * t), (ezx * exz - 1) / (ky * t), (ezy - ezx * exy) / (kz * t)],
        [(exz - exy * eyz) / (kx * t), (eyz - eyx * exz) / (ky * t), (eyx * exy - 1) / (kz * t)],
    ])
    d = np.array([
        ((1 - ezy * eyz) * bx / kx + (ezx * eyz - eyx * ezx) * by / ky
         + (eyx * ezy - ezx * exy) * bz / kz) / t,  # (23)
        ((ezy * exz - exy) * bx / kx + (1 - ezx * exz) * by / ky + (ezx * exy - ezy) * bz / kz) / t,
        ((exy * eyz - exz) * bx / kx + (eyx * exz - eyz) * by / ky + (1 - eyx * exy) * bz / kz) / t,
    ])
    return c, d


# --------------------------------------------------------------------------------------------
# Full solve with rounds and residuals
# --------------------------------------------------------------------------------------------
@dataclass
class TriadSolution:
    """Result of the twelve-position solve for one triad.

    Attributes
    ----------
    model : TriadModel
    pose_means : (12, 3) output means per pose, averaged over rounds (output units); NaN rows for
        poses with no usable capture (least-squares solve)
    residuals : (12, 3) output minus model prediction per pose (output units), with the
        reference's horizontal components estimated from the corrected data; NaN where no capture
    round_spread : (12, 3) sample standard deviation of the pose means over rounds (NaN if one)
    rounds : (12,) how many stations were averaged per pose
    reference_ned : (3,) the reference vector implied by the corrected data, in the stand frame
    method : how the model was solved (the paper's closed form, or least squares over captures)
    z_rms : residual RMS in units of the noise the data show (≈ 1 when the model explains the
        data to the noise; NaN when the noise is unknown)
    left_out : messages naming the captures left out because they did not fit
    used : the names of the captures solved from (:attr:`CaptureSet.names`; empty when not solved
        from named captures)
    """

    model: TriadModel
    pose_means: np.ndarray
    residuals: np.ndarray
    round_spread: np.ndarray
    rounds: np.ndarray
    reference_ned: np.ndarray
    method: str = "closed form (eqs. 5-16)"
    z_rms: float = float("nan")
    left_out: list = field(default_factory=list)
    used: list = field(default_factory=list)
    uncertainty: dict = field(default_factory=dict)   # 1σ bias/scale of the corrected triad (fit_uncertainty)

    @property
    def rms_residual(self) -> float:
        r = self.residuals[np.all(np.isfinite(self.residuals), axis=1)]
        return float(np.sqrt(np.mean(r ** 2))) if len(r) else float("nan")


#: A solution whose sensitivity matrix K·E has a larger condition number is refused.
MAX_CONDITION = 1e3
#: A pose whose residual exceeds this fraction of the reference's magnitude is refused: that
#: station was not taken in the pose its label says (or the stand was not in it).
MAX_RESIDUAL_FRACTION = 0.2
#: Plausible scale factors K when outputs and reference share a unit (m/s², nT).
PLAUSIBLE_SCALE = (0.5, 2.0)
_GROUPS = {0: "1-4", 1: "5-8", 2: "9-12"}


def check_solution(sol: "TriadSolution", name: str = "triad", scale_range=None, unit: str = "") -> None:
    """Refuse an absurd twelve-position solution with a message naming the axis or pose.

    Checks: each scale K within ``scale_range`` (if given; only meaningful when outputs and
    reference share a unit); the condition number of K·E at most :data:`MAX_CONDITION`; no pose
    residual above :data:`MAX_RESIDUAL_FRACTION` of the reference magnitude.  Raises ValueError.
    """
    model = sol.model
    if scale_range is not None:
        lo, hi = scale_range
        for j, axis in enumerate("xyz"):
            k = float(model.scale[j])
            if not lo <= k <= hi:
                raise ValueError(
                    f"{name}: scale K_{axis} = {k:.4g} is outside the plausible {lo:g}..{hi:g} "
                    f"(from poses {_GROUPS[j]}): a dead or stuck {axis} axis, wrong units, or poses "
                    f"{_GROUPS[j]} not taken as labelled; no coefficients written")
    cond = float(np.linalg.cond(model.A))
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ValueError(f"{name}: the sensitivity matrix K·E is singular or ill-conditioned (condition "
                         f"number {cond:.3g} > {MAX_CONDITION:g}): poses duplicated or mislabelled, or an axis "
                         "dead; no coefficients written")
    ref = float(np.linalg.norm(sol.reference_ned))
    frac = np.linalg.norm(sol.residuals, axis=1) / ref if ref > 0 else np.full(12, np.inf)
    frac = np.where(np.all(np.isfinite(sol.residuals), axis=1) | (ref <= 0), frac, 0.0)  # NaN: pose not used
    bad = [POSES[i] for i in np.flatnonzero(~(frac <= MAX_RESIDUAL_FRACTION))]
    if bad:
        i = int(np.nanargmax(np.where(np.isfinite(frac), frac, np.inf)))
        spread = sol.round_spread[i]
        sp = (f"; its round-to-round spread is {np.max(spread):.3g} {unit}".rstrip()
              if np.all(np.isfinite(spread)) else "")
        raise ValueError(
            f"{name}: pose {POSES[i]} does not fit the twelve-pose model: residual "
            f"{np.linalg.norm(sol.residuals[i]):.4g} {unit} = {100 * frac[i]:.0f}% of the reference "
            f"(limit {100 * MAX_RESIDUAL_FRACTION:.0f}%){sp}; pose(s) {bad} over the limit — a station "
            "not taken in the pose its label says (mislabelled or duplicated pose), or the stand not in "
            "it; no coefficients written")


def solve_triad(stations_by_pose: dict, vertical_ref: float, *, name: str = "triad", scale_range=None,
                unit: str = "") -> TriadSolution:
    """Solve one triad from ``{pose: [mean vector of each station in that pose, ...]}``.

    Every pose 1..12 needs at least one station; all stations are used.  The solution is checked
    with :func:`check_solution` (``name``, ``scale_range`` and ``unit`` go to its messages and
    checks): an ill-conditioned or absurd solve raises ValueError instead of returning.
    """
    missing = [p for p in POSES if not stations_by_pose.get(p)]
    if missing:
        raise ValueError(f"twelve-position solve: pose(s) {missing} missing (every pose 1..12 is needed)")
    extra = sorted(set(stations_by_pose) - set(POSES))
    if extra:
        raise ValueError(f"twelve-position solve: unknown pose label(s) {extra}")
    per_pose = [np.atleast_2d(np.asarray(stations_by_pose[p], dtype=float)) for p in POSES]
    means = np.array([v.mean(axis=0) for v in per_pose])
    spread = np.array([v.std(axis=0, ddof=1) if len(v) > 1 else np.full(3, np.nan) for v in per_pose])
    rounds = np.array([len(v) for v in per_pose])
    try:
        model = solve_closed_form(means, vertical_ref)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    # Residuals: estimate the reference vector in the stand frame from the corrected data (this
    # recovers the horizontal components the closed form never needed), then predict each pose.
    corrected = model.inverse(means)
    ref_est = np.mean([pose_matrix(p) @ corrected[i] for i, p in enumerate(POSES)], axis=0)
    predicted = model.forward(np.array([pose_reference(p, ref_est) for p in POSES]))
    sol = TriadSolution(model, means, means - predicted, spread, rounds, ref_est)
    check_solution(sol, name, scale_range, unit)
    return sol


@dataclass
class TwelvePositionResult:
    """Both triads: accelerometer (gravity-vector convention) and magnetometer."""

    acc: TriadSolution
    mag: TriadSolution
    notes: list = field(default_factory=list)   # stations refused and other warnings, as text
    #: Poses left out of both triads alike: the stand holds them off (one rotation of the probe).
    poses_off: list = field(default_factory=list)

    def implied_site(self) -> dict:
        """Total field and dip implied by the corrected magnetometer (a check on the stand/site)."""
        m = self.mag.reference_ned
        g = self.acc.reference_ned
        b = float(np.linalg.norm(m))
        dip = float(dip_of(m @ g, b, np.linalg.norm(g)))
        tilt = float(np.degrees(np.arctan2(np.hypot(g[0], g[1]), g[2])))
        heading = float(np.degrees(np.arctan2(m[1], m[0])))
        return {"total_field": b, "dip_deg": dip, "gravity": float(np.linalg.norm(g)),
                "stand_tilt_deg": tilt, "field_heading_deg": heading}

    def site_estimate(self, gravity_mps2: float):
        """The site reference as the calibration data itself measure it, for when none is given.

        Dip and the direction of the horizontal field in the stand frame (``field_heading_deg``:
        declination plus the stand's heading offset) are independent of the assumed M_d; the total
        field is in the scale that M_d sets.  Azimuths corrected with this site are measured from
        the stand's north — the frame of the stand's reference angles.
        """
        from ..core.frames import Site

        imp = self.implied_site()
        return Site(total_field_nt=imp["total_field"], dip_deg=imp["dip_deg"],
                    declination_deg=imp["field_heading_deg"], gravity_mps2=gravity_mps2)


def solve(acc_by_pose: dict, mag_by_pose: dict, gravity: float, field_down: float,
          scale_range=None) -> TwelvePositionResult:
    """Solve both triads.  ``gravity`` = g_d (m/s² or counts), ``field_down`` = M_d (nT or counts).

    ``scale_range``: plausible scale factors, checked only if given (outputs in the reference's
    unit; e.g. :data:`PLAUSIBLE_SCALE`)."""
    return TwelvePositionResult(
        acc=solve_triad(acc_by_pose, gravity, name="accelerometer", scale_range=scale_range, unit="m/s^2"),
        mag=solve_triad(mag_by_pose, field_down, name="magnetometer", scale_range=scale_range, unit="nT"))


# --------------------------------------------------------------------------------------------
# Least squares over individual captures: missing poses, outlier screening
# --------------------------------------------------------------------------------------------
#: Residuals above this multiple of what the measured noise explains mean the captures do not all
#: fit the model: the screen looks for captures (or whole poses) to leave out, and otherwise the
#: solve is kept and the user told (a stand with pose errors, or an effect the model lacks).
NOISE_RATIO_WARN = 3.0
#: A capture or pose is left out only if the others then fit this many times better (noise-
#: normalised residual RMS) — a stand with random pose errors improves by a few per cent when any
#: one pose is removed, a wrong capture by orders of magnitude.
OUTLIER_IMPROVEMENT = 1.5
#: ... and only if it is at least this far (deg, as an angle of the reference vector) from what
#: the other captures predict.
OUTLIER_MIN_DEG = 0.02
#: A solve whose captures still miss the model by more than this (RMS, deg, as an angle of the
#: reference vector) after screening is refused: its coefficients would be worse than none.
MAX_RESIDUAL_DEG = 0.5


@dataclass
class TriadFit:
    """Weighted least-squares fit of one triad to individual captures.

    Model (paper eqs. 3/4 with the stand's reference unknown in its horizontal components):
    ``h_c = A·P_cᵀ·r + B`` for capture c in pose p_c (``P`` = :func:`pose_matrix`), with
    ``A = K·E`` (9), ``B`` (3) and ``r = (r_N, r_E, r_D)`` the reference vector in the stand frame,
    ``r_D`` fixed to the vertical reference (g_d or M_d, as in the closed form) and ``r_N, r_E``
    free (an unlevelled stand, a stand not aligned with north): 14 unknowns, 3 equations per
    capture, each weighted by the noise of the capture's mean.  Unlike the closed form it needs
    no complete set of poses, only enough to determine the 14 unknowns (``rank`` 14).

    ``residuals`` (M, 3): capture minus model (output units); ``z_rms``: residual RMS in units
    of the captures' noise, over the degrees of freedom left (≈ 1 when the model explains the
    data to the noise); ``model`` None when the captures do not determine it (``rank`` < 14).
    """

    model: TriadModel | None
    reference: np.ndarray
    residuals: np.ndarray
    z_rms: float
    rank: int
    weak: str = ""          # tool axes the captures do not determine (see _weak_axes)


def _design(poses, r, a):
    """Unweighted Jacobian rows (3 per capture) of ``A·Pᵀ·r + B`` in (vec A, B, r_N, r_E)."""
    m = len(poses)
    jac = np.zeros((3 * m, 14))
    for c, p in enumerate(poses):
        pt = pose_matrix(p).T
        u = pt @ r
        for i in range(3):
            jac[3 * c + i, 3 * i:3 * i + 3] = u
            jac[3 * c + i, 9 + i] = 1.0
        jac[3 * c:3 * c + 3, 12] = a @ pt[:, 0]
        jac[3 * c:3 * c + 3, 13] = a @ pt[:, 1]
    return jac


def _ab_given_r(poses, h, w, r):
    """Weighted linear least squares for A and B with the reference r fixed."""
    u = np.array([pose_matrix(p).T @ r for p in poses])
    x = np.c_[u, np.ones(len(poses))]
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for i in range(3):
        sol, *_ = np.linalg.lstsq(x * w[:, i:i + 1], h[:, i] * w[:, i], rcond=None)
        a[i], b[i] = sol[:3], sol[3]
    return a, b


def fit_triad(poses, h, sigma, vertical_ref: float, horizontal0=(0.0, 0.0), iterations: int = 50) -> TriadFit:
    """Weighted least-squares fit of one triad to captures (see :class:`TriadFit`).

    ``poses`` (M,) 1..12, ``h`` (M, 3) capture means (output units), ``sigma`` (M, 3) their noise
    (σ per sample / √n), ``vertical_ref`` r_D, ``horizontal0`` a start for (r_N, r_E).  Solved by
    Gauss–Newton from the linear solution at the start reference; with a magnetometer the start
    heading matters little (the horizontal components enter linearly once A is known).
    """
    poses = [int(p) for p in poses]
    h = np.asarray(h, float).reshape(-1, 3)
    w = 1.0 / np.asarray(sigma, float).reshape(-1, 3)
    r = np.array([horizontal0[0], horizontal0[1], float(vertical_ref)])
    a, b = _ab_given_r(poses, h, w, r)
    wv = w.reshape(-1)
    for _ in range(iterations):
        pred = np.array([a @ (pose_matrix(p).T @ r) for p in poses]) + b
        e = (h - pred).reshape(-1) * wv
        jac = _design(poses, r, a) * wv[:, None]
        step, *_ = np.linalg.lstsq(jac, e, rcond=None)
        a = a + step[:9].reshape(3, 3)
        b = b + step[9:12]
        r = r + np.r_[step[12:14], 0.0]
        if np.max(np.abs(step[12:14])) <= 1e-12 * abs(vertical_ref) and np.max(np.abs(step[:9])) < 1e-14:
            break
    pred = np.array([a @ (pose_matrix(p).T @ r) for p in poses]) + b
    res = h - pred
    sv = np.linalg.svd(_design(poses, r, a) * wv[:, None], compute_uv=False)
    rank = int(np.sum(sv > sv[0] * 1e-9)) if len(sv) else 0
    weak = _weak_axes(poses, r, a) if rank == 14 else "xyz"
    z = (res * w).reshape(-1)
    dof = max(len(z) - 14, 1)
    try:
        model = TriadModel.from_matrix(a, b) if rank == 14 and not weak else None   # undetermined: no model
    except np.linalg.LinAlgError:
        model = None
    if model is None:
        rank = min(rank, 13)
    return TriadFit(model, r, res, float(math.sqrt(z @ z / dof)), rank, weak)


def fit_uncertainty(poses, sigma, fit: TriadFit) -> dict:
    """1σ of the corrected triad's bias and scale from a fit's covariance (the sensor terms of the
    ISCWSA position uncertainty, :mod:`iscwsa`).

    The covariance of (vec A, B) is ``(JᵀWJ)⁻¹`` of the weighted design (:func:`_design`), inflated
    by the residuals' ratio to the measured noise when above 1 (a model that does not explain the
    data to its noise is that much less certain).  A corrected vector is ``v = A⁻¹(h − B)``: an error
    δB gives ``δv = −A⁻¹·δB`` (the bias σ, in the triad's input units: ``diag(A⁻¹ Σ_B A⁻ᵀ)``) and an
    error in the diagonal ``A_ii`` a relative scale error ``δA_ii/A_ii`` (the scale σ)."""
    w = 1.0 / np.asarray(sigma, float).reshape(-1, 3)
    jac = _design([int(p) for p in poses], fit.reference, fit.model.A) * w.reshape(-1)[:, None]
    cov = np.linalg.pinv(jac.T @ jac)
    z = fit.z_rms if np.isfinite(fit.z_rms) else 1.0
    cov = cov * max(1.0, z) ** 2
    c = np.linalg.inv(fit.model.A)
    bias = np.sqrt(np.maximum(np.diag(c @ cov[9:12, 9:12] @ c.T), 0.0))
    diag = np.array([0, 4, 8])
    scale = np.sqrt(np.maximum(np.diag(cov)[diag], 0.0)) / np.abs(np.diag(fit.model.A))
    return {"bias": [float(x) for x in bias], "scale": [float(x) for x in scale],
            "basis": f"twelve-position fit covariance over {len(poses)} captures, residuals {z:.2f}x the noise"}


def closed_form_uncertainty(means, sigma_means, vertical_ref: float, z_rms: float = float("nan")) -> dict:
    """1σ of the corrected triad's bias and scale from the paper's closed form (eqs. 5–16), the
    way :func:`fit_uncertainty` gives them for the least-squares fit: the closed form is linearised
    about the pose means (central differences of :func:`solve_closed_form`, 36 inputs) and the
    means' noise ``sigma_means`` (12, 3) propagated, inflated by the residuals' ratio to the noise
    when above 1.  The closed form weighs the poses otherwise than least squares (it is less
    efficient): its own propagation, not the fit's covariance, is the uncertainty of the record it
    makes."""
    means = np.asarray(means, float).reshape(12, 3)
    sig = np.asarray(sigma_means, float).reshape(12, 3)
    base = solve_closed_form(means, vertical_ref)
    step = 1e-6 * max(float(np.max(np.abs(means))), 1.0)
    jac = np.zeros((12, 36))
    for k in range(36):
        d = np.zeros(36)
        d[k] = step
        hi = solve_closed_form(means + d.reshape(12, 3), vertical_ref)
        lo = solve_closed_form(means - d.reshape(12, 3), vertical_ref)
        jac[:, k] = (np.r_[hi.bias, hi.A.ravel()] - np.r_[lo.bias, lo.A.ravel()]) / (2 * step)
    z = z_rms if np.isfinite(z_rms) else 1.0
    cov = (jac * sig.reshape(-1) ** 2) @ jac.T * max(1.0, z) ** 2
    c = np.linalg.inv(base.A)
    bias = np.sqrt(np.maximum(np.diag(c @ cov[:3, :3] @ c.T), 0.0))
    diag = 3 + np.array([0, 4, 8])
    scale = np.sqrt(np.maximum(np.diag(cov)[diag], 0.0)) / np.abs(np.diag(base.A))
    return {"bias": [float(x) for x in bias], "scale": [float(x) for x in scale],
            "basis": f"closed form (eqs. 5-16) linearised about the pose means, residuals {z:.2f}x the noise"}


#: A design whose parameters are this many times less certain than the complete twelve-pose
#: design's does not determine them (a design missing an axis' vertical poses on a level stand is
#: ≥ 100× worse, one missing a few poses ≤ 3×).
MAX_DEGRADATION = 10.0


def _weak_axes(poses, r, a) -> str:
    """Tool axes whose column of ``A = K·E`` the captures determine far worse than the complete
    twelve-pose design would (:data:`MAX_DEGRADATION`): formally rank 14, yet held only by a
    stand's slight tilt or such."""
    def sigma(ps):
        jac = _design(ps, r, a)
        return np.sqrt(np.abs(np.diag(np.linalg.pinv(jac.T @ jac))))

    ratio = sigma(list(poses)) / sigma(list(POSES))
    return "".join(ax for j, ax in enumerate("xyz") if np.max(ratio[[j, 3 + j, 6 + j]]) > MAX_DEGRADATION)


@dataclass
class CaptureSet:
    """The captures of one triad that a solve may use: pose, mean and noise of the mean per capture,
    with a text naming each (for messages)."""

    poses: list
    means: list
    sigmas: list
    names: list

    def subset(self, keep):
        return CaptureSet(*([x[i] for i in keep] for x in (self.poses, self.means, self.sigmas, self.names)))

    def __len__(self):
        return len(self.poses)


def screen_triad(caps: CaptureSet, vertical_ref: float, horizontal0, name: str, unit: str):
    """Fit a triad and leave out captures (or whole poses) that do not fit the twelve-pose model.

    While the noise-normalised residual RMS of the fit exceeds :data:`NOISE_RATIO_WARN`, every
    single capture and every pose with several captures (a pose wrong in every round: the
    captures support each other, so only leaving the pose out shows it) is tried: if without the
    best candidate the rest fit :data:`OUTLIER_IMPROVEMENT` × better and it lies more than
    :data:`OUTLIER_MIN_DEG` from what the rest predict, it is left out and the screen repeats.
    A single capture is preferred to its whole pose when leaving it out does nearly as well (a
    capture the others cannot do without cannot be tested: it is fitted exactly).  Returns ``(fit,
    kept CaptureSet, [messages about what was left out])``; raises ValueError when the captures
    cannot determine the triad.
    """
    notes = []
    keep = list(range(len(caps)))
    ref_norm = math.hypot(math.hypot(*horizontal0), vertical_ref)
    if len(caps) < 5:   # 14 unknowns, 3 equations per capture
        raise ValueError(f"{name}: {len(caps)} usable capture(s) ({', '.join(caps.names) or 'none'}): far too few to "
                         "determine bias, scale and non-orthogonality (the gates' messages say why the others "
                         "were refused)")
    while True:
        sub = caps.subset(keep)
        fit = fit_triad(sub.poses, sub.means, sub.sigmas, vertical_ref, horizontal0)
        if fit.rank < 14:
            missing = [p for p in POSES if p not in sub.poses]
            weak = "" if fit.weak == "xyz" else (f": tool axis {', '.join(fit.weak)} is never vertical "
                                                 f"(poses {', '.join(_GROUPS['xyz'.index(x)] for x in fit.weak)})")
            raise ValueError(f"{name}: the captures left ({len(sub)} in poses {sorted(set(sub.poses))}"
                             + (f"; none in pose(s) {missing}" if missing else "") +
                             ") do not determine bias, scale and non-orthogonality of all three axes" + weak)
        if fit.z_rms <= NOISE_RATIO_WARN:
            return fit, sub, notes
        trials = [("capture", [j], sub.names[j]) for j in range(len(sub))]
        for p in sorted(set(sub.poses)):
            idx = [j for j in range(len(sub)) if sub.poses[j] == p]
            if len(idx) > 1:
                trials.append(("pose", idx, f"pose {p} (all {len(idx)} captures)"))
        best = {}
        for kind, idx, label in trials:
            rest = [j for j in range(len(sub)) if j not in idx]
            rs = sub.subset(rest)
            f2 = fit_triad(rs.poses, rs.means, rs.sigmas, vertical_ref, horizontal0)
            if f2.rank < 14:
                z2 = math.inf
            else:
                z2 = f2.z_rms
            if kind not in best or z2 < best[kind][0]:
                best[kind] = (z2, idx, label, f2)
        cands = [best[k] for k in ("capture", "pose") if k in best]
        choice = min(cands, key=lambda c: c[0])
        if "capture" in best and best["capture"][0] <= 1.2 * choice[0]:
            choice = best["capture"]  # leave out as little as does the job
        z2, idx, label, f2 = choice
        if not math.isfinite(z2):
            return fit, sub, notes   # nothing can be left out: the rest would not determine the triad
        # how far the left-out captures are from what the rest predict
        pred = np.array([f2.model.forward(pose_matrix(sub.poses[j]).T @ f2.reference) for j in idx])
        dev = np.linalg.norm(np.asarray([sub.means[j] for j in idx]) - pred, axis=1)
        ang = math.degrees(float(np.max(dev)) / ref_norm)
        if not (fit.z_rms >= OUTLIER_IMPROVEMENT * z2 and ang > OUTLIER_MIN_DEG):
            return fit, sub, notes
        notes.append(f"{name}: {label} does not fit the twelve-pose model: {ang:.3f}° ({float(np.max(dev)):.4g} "
                     f"{unit}) from what the other captures predict; without it the residuals fall from "
                     f"{fit.z_rms:.1f}× to {z2:.1f}× the noise — left out")
        keep = [k for j, k in enumerate(keep) if j not in idx]


# --------------------------------------------------------------------------------------------
# From captures; to a coefficient record; tables laid out like the paper's
# --------------------------------------------------------------------------------------------
def _solution_from_fit(fit: TriadFit, caps: CaptureSet, method: str) -> TriadSolution:
    """A :class:`TriadSolution` (per-pose tables) from a least-squares fit over captures."""
    means = np.full((12, 3), np.nan)
    spread = np.full((12, 3), np.nan)
    rounds = np.zeros(12, dtype=int)
    for i, p in enumerate(POSES):
        v = np.array([m for q, m in zip(caps.poses, caps.means) if q == p], dtype=float).reshape(-1, 3)
        rounds[i] = len(v)
        if len(v):
            means[i] = v.mean(axis=0)
            if len(v) > 1:
                spread[i] = v.std(axis=0, ddof=1)
    pred = np.array([fit.model.forward(pose_reference(p, fit.reference)) for p in POSES])
    return TriadSolution(fit.model, means, means - pred, spread, rounds, fit.reference, method=method,
                         z_rms=fit.z_rms)


def solve_triad_captures(caps: CaptureSet, vertical_ref: float, horizontal0, *, name: str, unit: str,
                         scale_range=PLAUSIBLE_SCALE) -> TriadSolution:
    """Solve one triad from individual captures, screened for captures that do not fit.

    :func:`screen_triad` leaves out what does not fit; then the paper's closed form (eqs. 5–16,
    every round averaged per pose) is used when every pose keeps a capture, else the weighted
    least-squares fit (:func:`fit_triad`) of the captures left.  Checked by
    :func:`check_solution`.  Raises ValueError with a message naming what is missing or wrong.
    """
    fit, kept, left_out = screen_triad(caps, vertical_ref, horizontal0, name, unit)
    ref_norm = math.hypot(math.hypot(*horizontal0), vertical_ref)
    ang = np.degrees(np.linalg.norm(fit.residuals, axis=1) / ref_norm)
    rms = float(np.sqrt(np.mean(ang ** 2)))
    if rms > MAX_RESIDUAL_DEG:
        worst = np.argsort(ang)[::-1][:3]
        raise ValueError(f"{name}: the captures do not fit the twelve-pose model even after screening: residual "
                         f"{rms:.2f}° RMS ({fit.z_rms:.0f}× the noise; limit {MAX_RESIDUAL_DEG:g}°), worst "
                         + ", ".join(f"{kept.names[i]} {ang[i]:.2f}°" for i in worst)
                         + " — stand poses far off, a sensor that does not follow the model, or a log of "
                         "something else; no coefficients written")
    missing = [p for p in POSES if p not in kept.poses]
    if not missing:
        by_pose = {}
        for p, m in zip(kept.poses, kept.means):
            by_pose.setdefault(p, []).append(m)
        sol = solve_triad(by_pose, vertical_ref, name=name, scale_range=scale_range, unit=unit)
        sol.z_rms = fit.z_rms
        # the noise of each pose's mean: its captures' (each the σ of its own mean) averaged
        sig = np.array([np.sqrt(np.sum([np.asarray(s, float) ** 2 for q, s in zip(kept.poses, kept.sigmas) if q == p],
                                       axis=0)) / sum(1 for q in kept.poses if q == p) for p in POSES])
        sol.uncertainty = closed_form_uncertainty(sol.pose_means, sig, vertical_ref, fit.z_rms)
    else:
        sol = _solution_from_fit(fit, kept, f"least squares over {len(kept)} captures (no capture of pose(s) "
                                             f"{missing}: the closed form needs all twelve)")
        check_solution(sol, name, scale_range, unit)
    sol.left_out = left_out
    sol.used = list(kept.names)
    if not sol.uncertainty:        # least squares over the captures: the fit's own covariance
        sol.uncertainty = fit_uncertainty(kept.poses, kept.sigmas, fit)
    return sol


def solve_captures(acc: CaptureSet, mag: CaptureSet, site, field_down: float | None = None) -> TwelvePositionResult:
    """Solve both triads from captures (m/s² gravity vector and nT; see :class:`CaptureSet`).

    ``g_d`` is the site gravity, ``M_d`` the site's vertical field component unless given (the
    paper notes M_d need not be exact: it only scales the magnetometer).  The result's ``notes``
    name the captures left out and say when the residuals stay above what the measured noise
    explains (stand pose errors, or an effect the paper's model lacks).  Raises ValueError when
    either triad cannot be solved.
    """
    fn = site.field_ned()
    md = float(fn[2]) if field_down is None else float(field_down)
    hor = (float(math.hypot(fn[0], fn[1])), 0.0)   # the stand set up against (magnetic) north
    sols = {}
    errors = []
    for key, caps, vref, h0, name, unit in (("acc", acc, float(site.gravity_mps2), (0.0, 0.0), "accelerometer", "m/s^2"),
                                            ("mag", mag, md, hor, "magnetometer", "nT")):
        try:
            sols[key] = solve_triad_captures(caps, vref, h0, name=name, unit=unit)
        except (ValueError, np.linalg.LinAlgError) as exc:
            errors.append(str(exc))
    if errors:
        raise ValueError("; ".join(errors))
    notes = []
    captured = set(int(p) for p in acc.poses) & set(int(p) for p in mag.poses)
    both = [p for p in POSES if p in captured and sols["acc"].rounds[p - 1] == 0 and sols["mag"].rounds[p - 1] == 0]
    for p in both:
        notes.append(f"pose {p} was left out of both triads alike: the stand probably holds it off (a worn or badly "
                     "set stand; both sensors see one rotation of the probe) — check or re-seat the stand at that "
                     "pose; `inclinometer-calib lab diagnose` fits the stand's pose errors (stand_pose_error)")
    for key, name in (("acc", "accelerometer"), ("mag", "magnetometer")):
        sol = sols[key]
        notes.extend(sol.left_out)
        if sol.z_rms > NOISE_RATIO_WARN:
            notes.append(f"{name}: the residuals are {sol.z_rms:.1f}× what the measured noise explains: the stand's "
                         "poses are off (a worn or badly set stand) or the probe has an effect the twelve-position "
                         "model lacks (temperature, nonlinearity ...) — `inclinometer-calib lab diagnose` tells which")
    return TwelvePositionResult(acc=sols["acc"], mag=sols["mag"], notes=notes, poses_off=both)


def _diagnostics(sol: TriadSolution, unit: str) -> dict:
    spread = np.where(np.isfinite(sol.round_spread), sol.round_spread, None)
    return {
        "units": unit,
        "method": sol.method,
        "rms_residual": sol.rms_residual,
        "noise_ratio": None if not np.isfinite(sol.z_rms) else float(sol.z_rms),
        "left_out": list(sol.left_out),
        "reference_ned": [float(x) for x in sol.reference_ned],
        "per_pose": {
            int(p): {"mean": [None if not np.isfinite(x) else float(x) for x in sol.pose_means[i]],
                     "residual": [None if not np.isfinite(x) else float(x) for x in sol.residuals[i]],
                     "rounds": int(sol.rounds[i]),
                     "round_spread": [None if x is None else float(x) for x in spread[i]]}
            for i, p in enumerate(POSES)},
    }


def to_calibration(result: TwelvePositionResult, site, probe_id: str = "probe"):
    """Wrap a twelve-position result as a :class:`coeffs.Calibration` with per-pose diagnostics."""
    from ..core.coeffs import Calibration  # local: coeffs is the record layer, this the calibrator

    method = "twelve_position (Li, Li & Zhao 2021, eqs. 5-16; inverse by matrix)"
    lsq = [name for name, sol in (("accelerometer", result.acc), ("magnetometer", result.mag))
           if not sol.method.startswith("closed form")]
    if lsq:
        method += f"; {' and '.join(lsq)} by least squares over the captures (poses missing)"
    diagnostics = {"acc": _diagnostics(result.acc, "m/s^2"), "mag": _diagnostics(result.mag, "nT"),
                   "implied_site": result.implied_site()}
    if result.notes:
        diagnostics["notes"] = list(result.notes)
    return Calibration(acc=result.acc.model, mag=result.mag.model, probe_id=probe_id, method=method, site=site,
                       diagnostics=diagnostics,
                       uncertainty={k: s.uncertainty for k, s in (("acc", result.acc), ("mag", result.mag))
                                    if s.uncertainty})


_TABLE2_E = {0: ("e_xy", "e_xz"), 1: ("e_yx", "e_yz"), 2: ("e_zx", "e_zy")}


def format_table2(acc: TriadModel, mag: TriadModel) -> str:
    """Parameters laid out like the paper's Table 2: per axis bias, scale, and the two
    installation (non-orthogonality) terms found from that axis' group of poses."""
    lines = ["Table 2 — calibration parameters (acc: m/s^2 gravity vector; mag: nT)",
             f"{'sensor':<14}{'axis':<5}{'bias':>12}{'scale':>10}{'install.1':>16}{'install.2':>16}"]
    for name, m in (("magnetometer", mag), ("accelerometer", acc)):
        for j, a in enumerate("xyz"):
            n1, n2 = _TABLE2_E[j]
            lines.append(f"{name if j == 0 else '':<14}{a.upper():<5}{m.bias[j]:>12.4f}{m.scale[j]:>10.4f}"
                         f"{n1:>7}={m.e[n1]:>8.4f}{n2:>7}={m.e[n2]:>8.4f}")
    return "\n".join(lines)


def format_table3(acc: TriadModel, mag: TriadModel) -> str:
    """Correction coefficients laid out like the paper's Table 3: v_i = A_i·h_x + B_i·h_y + C_i·h_z + D_i."""
    lines = ["Table 3 — correction coefficients  v_i = A_i h_x + B_i h_y + C_i h_z + D_i",
             f"{'sensor':<14}{'axis':<5}{'A_i':>10}{'B_i':>10}{'C_i':>10}{'D_i':>12}"]
    for name, m in (("magnetometer", mag), ("accelerometer", acc)):
        c, d = m.correction_matrix, m.correction_offset
        for j, a in enumerate("xyz"):
            lines.append(f"{name if j == 0 else '':<14}{a.upper():<5}{c[j, 0]:>10.4f}{c[j, 1]:>10.4f}"
                         f"{c[j, 2]:>10.4f}{d[j]:>12.4f}")
    return "\n".join(lines)

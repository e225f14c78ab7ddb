"""The seed paper's twelve-position calibration (Table 1; eqs. 5–16) and its inversion (17–32).

The probe is rolled on a non-magnetic three-axis stand through the twelve poses of Table 1.  In
each pose every tool axis points along a stand axis (down/up/east/west/north/south), so each
sensor axis sees ±M_d (or ±g_d) in four poses and the horizontal components elsewhere.  The
closed-form solution uses only the vertical reference component (M_d for the magnetometer, g_d for
the accelerometer): the horizontal components cancel in eqs. 5–16, so neither a north reference nor
an exactly level stand is needed.

Inputs are per-pose mean vectors in the *gravity-vector* convention for the accelerometer (down
positive: convert REP-145 specific force with ``frames.gravity_from_specific_force`` first) and in
output units (nT or A/D counts) for the magnetometer.

Several rounds of the twelve poses (e.g. at different temperatures) are all used: the pose means
are averaged over rounds before eqs. 5–16 (which are linear in the outputs, so this equals the
average of the per-round solutions), and the round-to-round spread per pose is reported.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errormodel import TriadModel

_DIR = {
    "N": (1.0, 0.0, 0.0),
    "S": (-1.0, 0.0, 0.0),
    "E": (0.0, 1.0, 0.0),
    "W": (0.0, -1.0, 0.0),
    "D": (0.0, 0.0, 1.0),
    "U": (0.0, 0.0, -1.0),
}

#: Table 1: the stand direction (N/S/E/W/D=down/U=up) of tool X, Y, Z in each of the 12 poses.
TABLE1 = {
    1: "DWN", 2: "DES", 3: "UEN", 4: "UWS",
    5: "EDN", 6: "WDS", 7: "EUS", 8: "WUN",
    9: "NED", 10: "SWD", 11: "SEU", 12: "NWU",
}
POSES = tuple(range(1, 13))


def pose_matrix(pose: int) -> np.ndarray:
    """Tool→stand(NED) rotation of a Table 1 pose: its columns are the NED directions of X, Y, Z."""
    if pose not in TABLE1:
        raise ValueError(f"pose {pose!r} is not one of the twelve poses of Table 1 (1..12)")
    return np.array([_DIR[c] for c in TABLE1[pose]]).T


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


def identify_pose_with_field(g_tool, b_tool, site_field_ned, tolerance_deg: float = 20.0):
    """Pose from gravity (which axis is vertical) and the field's horizontal direction.

    Returns ``(pose, misfit_deg)`` of the best candidate, or ``(None, nan)``.  The misfit is the
    angle between the measured field and the pose's expected field direction.
    """
    cands = _gravity_candidates(g_tool, tolerance_deg)
    if not cands:
        return None, float("nan")
    b = np.asarray(b_tool, dtype=float)
    bn = b / np.linalg.norm(b)
    best, best_ang = None, np.inf
    for p in cands:
        exp = pose_reference(p, site_field_ned)
        ang = np.degrees(np.arccos(np.clip(bn @ exp / np.linalg.norm(exp), -1, 1)))
        if ang < best_ang:
            best, best_ang = p, ang
    return best, float(best_ang)


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
    pose_means : (12, 3) output means per pose, averaged over rounds (output units)
    residuals : (12, 3) output minus model prediction per pose (output units), with the
        reference's horizontal components estimated from the corrected data
    round_spread : (12, 3) sample standard deviation of the pose means over rounds (NaN if one)
    rounds : (12,) how many stations were averaged per pose
    reference_ned : (3,) the reference vector implied by the corrected data, in the stand frame
    """

    model: TriadModel
    pose_means: np.ndarray
    residuals: np.ndarray
    round_spread: np.ndarray
    rounds: np.ndarray
    reference_ned: np.ndarray

    @property
    def rms_residual(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2)))


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

    def implied_site(self) -> dict:
        """Total field and dip implied by the corrected magnetometer (a check on the stand/site)."""
        m = self.mag.reference_ned
        g = self.acc.reference_ned
        b = float(np.linalg.norm(m))
        dip = float(np.degrees(np.arcsin(np.clip(m @ g / (b * np.linalg.norm(g)), -1, 1))))
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
        from .frames import Site

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
# From stations; to a coefficient record; tables laid out like the paper's
# --------------------------------------------------------------------------------------------
def _station_where(st) -> str:
    first, n = getattr(st, "first_row", None), getattr(st, "n", None)
    if first is not None and n:
        return f"station at rows {first}-{first + n - 1}"
    return f"station {getattr(st, 'index', '?')}"


def _gravity_says(st, good, tolerance_deg) -> str:
    """Which pose(s) a station's gravity points to, resolved by the field of correctly labelled
    stations where gravity alone leaves two (each vertical axis direction fits two poses)."""
    cands = _gravity_candidates(st.g, tolerance_deg)
    if not cands:
        return "gravity matches no pose of Table 1"
    if len(cands) > 1:
        b = np.asarray(st.b, float)
        best, best_ang = None, 30.0
        for o in good:
            if o.pose in cands:
                ob = np.asarray(o.b, float)
                ang = np.degrees(np.arccos(np.clip(b @ ob / (np.linalg.norm(b) * np.linalg.norm(ob)), -1, 1)))
                if ang < best_ang:
                    best, best_ang = o.pose, ang
        if best is not None:
            cands = [best]
    return "gravity says pose " + " or ".join(str(c) for c in cands)


def check_pose_labels(stations, tolerance_deg: float = 30.0):
    """Split pose-labelled stations into those whose measured gravity fits their label and those
    that do not.  Returns ``(kept, refused)`` with ``refused`` a list of messages such as
    ``"station at rows 101-150: labelled pose 5 but gravity says pose 7; refused"``.

    Gravity (uncalibrated: a few degrees off at most) tells which tool axis is vertical and which
    way; that fixes the pose up to the pair sharing it, which is all the closed form needs (it
    uses the sum of each pair).  Stations flagged as moved during the capture are refused too.
    """
    good, bad = [], []
    for st in stations:
        if not st.pose:
            continue
        if st.pose not in _gravity_candidates(st.g, tolerance_deg):
            bad.append(st)
        else:
            good.append(st)
    refused = [f"{_station_where(st)}: labelled pose {st.pose} but {_gravity_says(st, good, tolerance_deg)}; "
               "station refused (mislabelled pose)" for st in bad]
    kept = []
    for st in good:
        if getattr(st, "warnings", None):
            refused.append(f"{_station_where(st)} (pose {st.pose}): the probe moved during the capture; "
                           "station refused")
        else:
            kept.append(st)
    return kept, refused


def solve_stations(stations, site, field_down: float | None = None, check_labels: bool = True) -> TwelvePositionResult:
    """Solve from :class:`probelog.Station` objects labelled with poses (all rounds are used).

    ``g_d`` is the site gravity; ``M_d`` the site's vertical field component unless given (the
    paper notes M_d need not be exact: it only scales the magnetometer).  With ``check_labels``,
    stations whose gravity contradicts their pose label, or taken while the probe moved, are
    refused (:func:`check_pose_labels`); the result's ``notes`` say which, and also flag poses
    captured more often than the others (a duplicated label?).  A pose left without a station is
    an error whose message includes the refusals.  Scale factors must lie in
    :data:`PLAUSIBLE_SCALE` (stations are in m/s² and nT).
    """
    notes = []
    if check_labels:
        stations, notes = check_pose_labels(stations)
    acc, mag = {}, {}
    for st in stations:
        if st.pose:
            acc.setdefault(st.pose, []).append(st.g)
            mag.setdefault(st.pose, []).append(st.b)
    counts = {p: len(v) for p, v in acc.items()}
    if counts:
        usual = int(np.median(list(counts.values())))
        extra = sorted(p for p, c in counts.items() if c > usual)
        if extra:
            notes.append("pose(s) " + ", ".join(f"{p} ×{counts[p]}" for p in extra) +
                         f" captured more often than the others (×{usual}): their means average every "
                         "capture; check for a duplicated pose label")
    md = float(site.field_ned()[2]) if field_down is None else float(field_down)
    try:
        res = solve(acc, mag, gravity=float(site.gravity_mps2), field_down=md, scale_range=PLAUSIBLE_SCALE)
    except ValueError as exc:
        if notes:
            raise ValueError(f"{exc}; " + "; ".join(notes)) from None
        raise
    res.notes = notes
    return res


def _diagnostics(sol: TriadSolution, unit: str) -> dict:
    spread = np.where(np.isfinite(sol.round_spread), sol.round_spread, None)
    return {
        "units": unit,
        "rms_residual": sol.rms_residual,
        "reference_ned": [float(x) for x in sol.reference_ned],
        "per_pose": {
            int(p): {"mean": [float(x) for x in sol.pose_means[i]],
                     "residual": [float(x) for x in sol.residuals[i]],
                     "rounds": int(sol.rounds[i]),
                     "round_spread": [None if x is None else float(x) for x in spread[i]]}
            for i, p in enumerate(POSES)},
    }


def to_calibration(result: TwelvePositionResult, site, probe_id: str = "probe"):
    """Wrap a twelve-position result as a :class:`coeffs.Calibration` with per-pose diagnostics."""
    from .coeffs import Calibration  # local: coeffs is the record layer, this the calibrator

    return Calibration(acc=result.acc.model, mag=result.mag.model, probe_id=probe_id,
                       method="twelve_position (Li, Li & Zhao 2021, eqs. 5-16; inverse by matrix)",
                       site=site,
                       diagnostics={"acc": _diagnostics(result.acc, "m/s^2"),
                                    "mag": _diagnostics(result.mag, "nT"),
                                    "implied_site": result.implied_site()})


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

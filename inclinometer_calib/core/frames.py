"""Frames, orientation angles and survey quality-control quantities.

Conventions (used everywhere in this package)
---------------------------------------------
* **Tool frame**: right-handed; Z along the tool axis pointing down-hole; X and Y across the tool.
  At toolface 0 the X axis points to the high side of the hole.
* **Earth frame**: NED (north, east, down).  "North" is whatever north the site reference field is
  given in (magnetic north when the declination is 0).
* **Orientation**: ``R = Rz(azimuth) @ Ry(drift) @ Rz(toolface)`` maps tool-frame vectors to NED,
  ``v_ned = R @ v_tool``.
* **Gravity vector** (the seed paper's convention): ``g_tool = R.T @ [0, 0, +g]``, down positive.
  ``sensor_msgs/Imu`` carries REP-145 *specific force* ``f = -g_tool`` (a resting probe reads
  -gravity).  Convert once with :func:`gravity_from_specific_force`, at the boundary: the
  probe-log reader (``ProbeLog.gravity``), the CDR decoder (``cdr.decode_imu_gravity``) and the
  nodes' ``Imu`` reader (``nodes.common.gravity``) are its only callers; every core API
  (detector, engine, batch correction, kernel, lab) takes the gravity vector
  (``test_the_specific_force_sign_flip_happens_at_the_entries_only`` pins it).
* **Magnetic field** in nT in the core (``sensor_msgs/MagneticField`` carries tesla).

Angles are in degrees at the public API.  All functions broadcast over leading dimensions: vectors
are ``(..., 3)`` arrays.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import formulas

#: Standard gravity, m/s² (used as default site gravity).
STANDARD_GRAVITY = 9.80665
#: nT per tesla.
NT_PER_TESLA = 1e9


def rot_x(angle_rad):
    """Rotation matrix about X by ``angle_rad`` (right-hand rule), broadcasting: (..., 3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle_rad):
    """Rotation matrix about Y by ``angle_rad`` (right-hand rule), broadcasting: (..., 3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle_rad):
    """Rotation matrix about Z by ``angle_rad`` (right-hand rule), broadcasting: (..., 3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def orientation_matrix(drift_deg, azimuth_deg, toolface_deg):
    """Tool→NED rotation ``R = Rz(A)·Ry(I)·Rz(T)`` from drift I, azimuth A, toolface T in degrees."""
    i, a, t = (np.radians(np.asarray(x, dtype=float)) for x in (drift_deg, azimuth_deg, toolface_deg))
    return rot_z(a) @ rot_y(i) @ rot_z(t)


def attitude_angles(r, vertical_cone_deg: float = 0.5):
    """(drift, azimuth, toolface) in degrees of a tool→NED rotation ``R = Rz(A)·Ry(I)·Rz(T)``.

    Within ``vertical_cone_deg`` of the vertical (down or up) the azimuth is undefined (NaN) and
    the toolface is the whole rotation about the vertical, as for azimuth 0 — what a stand's log
    gives for its vertical poses.  Inverse of :func:`orientation_matrix` elsewhere.
    """
    r = np.asarray(r, dtype=float)
    drift = float(np.degrees(np.arccos(np.clip(r[2, 2], -1.0, 1.0))))
    if drift < vertical_cone_deg or drift > 180.0 - vertical_cone_deg:
        # R ≈ Ry(I)·Rz(T): for I = 0 the top-left block is Rz(T); for I = 180, diag(-1, 1, -1)·Rz(T)
        sign = 1.0 if drift < 90.0 else -1.0
        tf = np.degrees(np.arctan2(r[1, 0], sign * r[0, 0]))
        return drift, float("nan"), float(wrap360(tf))
    az = np.degrees(np.arctan2(r[1, 2], r[0, 2]))
    tf = np.degrees(np.arctan2(r[2, 1], -r[2, 0]))
    return drift, float(wrap360(az)), float(wrap360(tf))


def angle_between_deg(u, v) -> float:
    """Angle between two vectors, degrees (NaN if either has no length)."""
    u, v = np.asarray(u, dtype=float), np.asarray(v, dtype=float)
    nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    if not (nu > 0 and nv > 0):
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(float(u @ v) / (nu * nv), -1.0, 1.0))))


def wrap360(angle_deg):
    """Wrap an angle to [0, 360) degrees: ``fmod``, then :func:`formulas.wrap360_near` (the
    same bits as ``np.mod``, and 360.0 — a tiny negative plus 360, rounded — becomes 0)."""
    return formulas.wrap360_near(np.fmod(angle_deg, 360.0))


def wrap180(angle_deg):
    """Wrap an angle (or angle difference) to [-180, 180) degrees."""
    return np.mod(np.asarray(angle_deg, dtype=float) + 180.0, 360.0) - 180.0


# --------------------------------------------------------------------------------------------
# Site reference field
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Site:
    """Reference field at the survey or calibration site.

    Attributes
    ----------
    total_field_nt : float
        Total magnetic field |B| in nT.
    dip_deg : float
        Magnetic dip (inclination of B below the horizontal), degrees, positive down.
    declination_deg : float
        Magnetic declination, degrees east of true north.  The NED frame's north is *true* north
        when this is non-zero; azimuths computed from the magnetometers are magnetic and become
        true azimuths by adding the declination.
    gravity_mps2 : float
        Local gravity |g| in m/s².
    reference : dict
        Where the values came from when the site was given by its location (:mod:`geomag`): the
        position, date, model, each value's source (the model or a measured IFR value) and, with a
        projected CRS, the grid convergence; empty for values typed in.
    """

    total_field_nt: float = 50000.0
    dip_deg: float = 45.1  # Chengdu, the seed paper's site
    declination_deg: float = 0.0
    gravity_mps2: float = STANDARD_GRAVITY
    reference: dict = field(default_factory=dict, compare=False, hash=False)

    @property
    def grid_convergence_deg(self) -> float:
        """Grid convergence (deg, east positive; grid azimuth = true − it), NaN without a grid."""
        return float(self.reference.get("grid_convergence_deg", float("nan")))

    def field_ned(self) -> np.ndarray:
        """Earth field vector in NED (nT): [B cos(dip) cos(dec), B cos(dip) sin(dec), B sin(dip)]."""
        d, dec = np.radians(self.dip_deg), np.radians(self.declination_deg)
        b = self.total_field_nt
        return np.array([b * np.cos(d) * np.cos(dec), b * np.cos(d) * np.sin(dec), b * np.sin(d)])

    def gravity_ned(self) -> np.ndarray:
        """Gravity vector in NED, m/s² (down positive)."""
        return np.array([0.0, 0.0, self.gravity_mps2])

    def to_dict(self) -> dict:
        """The site's values (and ``reference``), as a record stores them; read back (like every
        site section) by :func:`geomag.site_from_config`."""
        out = {
            "total_field_nt": float(self.total_field_nt),
            "dip_deg": float(self.dip_deg),
            "declination_deg": float(self.declination_deg),
            "gravity_mps2": float(self.gravity_mps2),
        }
        if self.reference:
            out["reference"] = dict(self.reference)
        return out


# --------------------------------------------------------------------------------------------
# Boundary conversions
# --------------------------------------------------------------------------------------------
def gravity_from_specific_force(f):
    """Paper-convention gravity vector (down positive) from REP-145 specific force: ``g = -f``.

    The one place where samples change convention on their way in, called only where they enter
    the package: ``io.probelog.ProbeLog.gravity`` (a log's rows), ``io.cdr.decode_imu_gravity``
    (the bytes of an ``Imu``: a bag, the nodes' raw subscriptions) and ``nodes.common.gravity``
    (a Python ``Imu``).  A tuple gives a tuple (the per-sample path), anything else an array."""
    if isinstance(f, tuple):
        return (-f[0], -f[1], -f[2])
    return -np.asarray(f, dtype=float)


def specific_force_from_gravity(g):
    """REP-145 specific force (a resting probe reads -gravity) from the gravity vector: ``f = -g``.

    The one place where values change convention on their way out (corrected ``Imu`` streams,
    the accelerometer fields of a ``CalibrationCoefficients`` message, the simulator's output,
    a stuck level said as the log records it)."""
    if isinstance(g, tuple):
        return (-g[0], -g[1], -g[2])
    return -np.asarray(g, dtype=float)


# --------------------------------------------------------------------------------------------
# Angles from sensor vectors (tool frame)
# --------------------------------------------------------------------------------------------
def _xyz(v):
    v = np.asarray(v, dtype=float)
    return v[..., 0], v[..., 1], v[..., 2]


def drift_deg(g):
    """Drift (inclination) in degrees from the tool-frame gravity vector ``g`` (down positive).

    Paper eq. (1), ``θ = arctan(sqrt(gx² + gy²) / gz)``, written as ``atan2`` so that it is
    valid over the whole range 0–180° (eq. 1 folds drifts above 90°): :func:`formulas.drift_deg`.
    """
    return formulas.drift_deg(*_xyz(g))


def gravity_toolface_deg(g):
    """Gravity (high-side) toolface in degrees [0, 360): the angle T of ``Rz(T)`` in R.

    With ``g_tool = R.T @ [0, 0, g]`` one finds ``gx = -g sinI cosT``, ``gy = g sinI sinT``, so
    ``T = atan2(gy, -gx)`` (:func:`formulas.toolface_deg`).  In REP-145 specific force this is the
    familiar ``atan2(-fy, fx)``.  Undefined (noise-dominated) when the drift is near zero.
    """
    gx, gy, _ = _xyz(g)
    return formulas.toolface_deg(True, gx, gy, 0.0, 0.0)


def magnetic_toolface_deg(b):
    """Magnetic toolface in degrees [0, 360): angle from the cross-axial projection of north to X.

    ``MTF = atan2(-by, bx)`` (:func:`formulas.toolface_deg`); for a vertical tool it equals
    azimuth + gravity toolface.
    """
    bx, by, _ = _xyz(b)
    return formulas.toolface_deg(False, 0.0, 0.0, bx, by)


def azimuth_deg(g, b):
    """Magnetic azimuth in degrees [0, 360) of the tool axis from tool-frame gravity and field.

    Implements the paper's eq. (2) in a quadrant-resolving form (:func:`formulas.azimuth_deg`)::

        A = atan2( |g| (by gx - bx gy),  bz (gx² + gy²) - gz (bx gx + by gy) )

    Eq. 2 is printed as ``arctan`` of the ratio ``|g|(bx gy - by gx) / (gz(bx gx + by gy) -
    bz(gx² + gy²))``, which loses the quadrant; feeding its numerator and denominator to atan2 as
    printed points 180° off in this frame.  Negating both leaves the paper's ratio unchanged and
    gives the full-circle azimuth (pinned by tests against rotations built from known angles).  Equivalent to
    levelling the field with the drift and toolface taken from ``g``.  Near vertical both
    arguments vanish and the azimuth is undefined: see :func:`azimuth_defined`.
    """
    return formulas.azimuth_deg(*_xyz(g), *_xyz(b))


def azimuth_defined(g, min_drift_deg: float = 0.5):
    """True where the tool is more than ``min_drift_deg`` from the vertical (down or up), so that
    the azimuth is meaningful."""
    return formulas.outside_vertical_cone(drift_deg(g), min_drift_deg)


def total_gravity(g):
    """Total gravity |g| (same units as ``g``): :func:`formulas.norm`."""
    return formulas.norm(*_xyz(g))


def total_field(b):
    """Total magnetic field |B| (same units as ``b``): :func:`formulas.norm`."""
    return formulas.norm(*_xyz(b))


def dip_deg(g, b):
    """Magnetic dip in degrees: 90° minus the angle between g (down) and B.

    ``dip = asin( (g·b) / (|g||b|) )`` — independent of orientation, so a survey-QC invariant
    (:func:`formulas.dip_deg`).
    """
    return formulas.dip_deg(*_xyz(g), *_xyz(b))


def angles_from_vectors(g, b):
    """All survey angles and QC quantities from tool-frame gravity ``g`` and field ``b``.

    Returns a dict of arrays: drift_deg, azimuth_deg (magnetic), gravity_toolface_deg,
    magnetic_toolface_deg, total_gravity, total_field, dip_deg.
    """
    return {
        "drift_deg": drift_deg(g),
        "azimuth_deg": azimuth_deg(g, b),
        "gravity_toolface_deg": gravity_toolface_deg(g),
        "magnetic_toolface_deg": magnetic_toolface_deg(b),
        "total_gravity": total_gravity(g),
        "total_field": total_field(b),
        "dip_deg": dip_deg(g, b),
    }


def tool_vectors(site: Site, drift, azimuth, toolface):
    """True tool-frame gravity (m/s², down positive) and field (nT) for the given orientation.

    ``azimuth`` is measured from the NED frame's north (true north if the site has a declination).
    """
    r = orientation_matrix(drift, azimuth, toolface)
    rt = np.swapaxes(r, -1, -2)
    return rt @ site.gravity_ned(), rt @ site.field_ned()


def rotate(m, v) -> np.ndarray:
    """``v @ m`` for (N, 3) ``v`` and a 3×3 ``m``: :func:`formulas.mat_vec` with ``C = mᵀ``,
    element by element (not through BLAS: each output element is the same three products added
    in the same order whatever N is, so one sample corrected alone (a node) and the same sample
    in a block of a million (the batch path) give the same bits)."""
    return np.stack(formulas.mat_vec(tuple(np.asarray(m).T.ravel()), v[:, 0], v[:, 1], v[:, 2]), axis=1)


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


def pose_matrix(pose: int) -> np.ndarray:
    """Tool→stand(NED) rotation of a Table 1 pose: its columns are the NED directions of X, Y, Z."""
    if pose not in TABLE1:
        raise ValueError(f"pose {pose!r} is not one of the twelve poses of Table 1 (1..12)")
    return np.array([_DIR[c] for c in TABLE1[pose]]).T

"""The well's trajectory from survey stations by minimum curvature — ROS-free.

Stations are (measured depth MD, inclination I, azimuth A) in m and degrees; the azimuth's north
(true or grid) is the north of the positions.  Between two stations the well is taken as a circular
arc (the industry's standard, SPE 84246 / ISCWSA):

    β  = dogleg angle = angle between the unit tangents t₁, t₂,  t = (sin I cos A, sin I sin A, cos I)
    RF = (2/β)·tan(β/2)                           (ratio factor; 1 when β → 0)
    ΔN, ΔE, ΔTVD = (ΔMD/2)·RF·(t₁ + t₂)            (north, east, down)
    DLS = β / ΔMD                                  (reported per 30 m, per 100 m or per 100 ft)

``β`` is computed as ``2·asin(|t₂ − t₁|/2)`` (exact, and accurate for tiny doglegs, where the
``acos`` form loses precision), and ``RF`` by its series below 10⁻⁴ rad.  The first station ties
the trajectory in (by default at TVD, north and east 0; a real tie-in point can be given).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The international foot, m.
FOOT_M = 0.3048
#: Dogleg severity reference lengths (m) by unit name.
DLS_LENGTH = {"deg/30m": 30.0, "deg/100m": 100.0, "deg/100ft": 30.48}


def tangents(inc_deg, azi_deg) -> np.ndarray:
    """(N, 3) unit tangents (north, east, down) of inclinations and azimuths (deg); a NaN azimuth
    (a vertical station) counts as 0."""
    i = np.radians(np.asarray(inc_deg, float))
    a = np.radians(np.nan_to_num(np.asarray(azi_deg, float)))
    return np.stack([np.sin(i) * np.cos(a), np.sin(i) * np.sin(a), np.cos(i)], axis=-1)


def dogleg_rad(t1, t2) -> np.ndarray:
    """Angle (rad) between unit tangents, ``2·asin(|t₂ − t₁|/2)``."""
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(np.asarray(t2) - np.asarray(t1), axis=-1) / 2.0, 0.0, 1.0))


def ratio_factor(beta) -> np.ndarray:
    """``(2/β)·tan(β/2)``; its series ``1 + β²/12 + β⁴/120`` for tiny β."""
    b = np.asarray(beta, float)
    small = b < 1e-4
    safe = np.where(small, 1.0, b)
    return np.where(small, 1.0 + b ** 2 / 12.0 + b ** 4 / 120.0, 2.0 / safe * np.tan(safe / 2.0))


@dataclass
class Trajectory:
    """Positions of the stations: ``md`` (m), ``inc_deg``, ``azi_deg``, ``tvd``, ``north``,
    ``east`` (m), ``dls`` (deg per ``dls_unit``; 0 at the first station) and ``dogleg_deg``."""

    md: np.ndarray
    inc_deg: np.ndarray
    azi_deg: np.ndarray
    tvd: np.ndarray
    north: np.ndarray
    east: np.ndarray
    dls: np.ndarray
    dogleg_deg: np.ndarray
    dls_unit: str = "deg/30m"

    def to_rows(self) -> list:
        return [{"md_m": float(m), "inc_deg": float(i), "azi_deg": float(a), "tvd_m": float(t), "north_m": float(n),
                 "east_m": float(e), f"dls_{self.dls_unit.replace('/', '_per_')}": float(d)}
                for m, i, a, t, n, e, d in zip(self.md, self.inc_deg, self.azi_deg, self.tvd, self.north, self.east,
                                               self.dls)]


def minimum_curvature(md, inc_deg, azi_deg, tie_in=(0.0, 0.0, 0.0), dls_unit: str = "deg/30m") -> Trajectory:
    """The trajectory of stations (ascending ``md``) by minimum curvature.  ``tie_in``: (TVD,
    north, east) of the first station (m).  A station repeated at one depth or out of order is
    refused (the arc between them is undefined)."""
    md = np.asarray(md, float)
    inc = np.asarray(inc_deg, float)
    azi = np.asarray(azi_deg, float)
    if not (md.shape == inc.shape == azi.shape) or md.ndim != 1:
        raise ValueError("md, inclination and azimuth must be 1-D arrays of one length")
    if dls_unit not in DLS_LENGTH:
        raise ValueError(f"dls_unit must be one of {', '.join(DLS_LENGTH)}")
    bad = np.flatnonzero(~np.isfinite(md) | ~np.isfinite(inc) | (inc < 0) | (inc > 180))
    if len(bad):
        raise ValueError(f"station {int(bad[0])}: md {md[bad[0]]}, inclination {inc[bad[0]]}: not a valid station")
    steps = np.diff(md)
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0])
        raise ValueError(f"station {k + 1} at md {md[k + 1]:g} m does not go deeper than station {k} ({md[k]:g} m): "
                         "stations must be in order of measured depth, one per depth")
    t = tangents(inc, azi)
    beta = dogleg_rad(t[:-1], t[1:])
    d = (steps / 2.0 * ratio_factor(beta))[:, None] * (t[:-1] + t[1:])
    pos = np.vstack([np.asarray(tie_in, float)[[1, 2, 0]], d]).cumsum(axis=0)     # north, east, tvd
    dls = np.concatenate([[0.0], np.degrees(beta) / steps * DLS_LENGTH[dls_unit]])
    return Trajectory(md, inc, azi, pos[:, 2], pos[:, 0], pos[:, 1], dls, np.concatenate([[0.0], np.degrees(beta)]),
                      dls_unit)

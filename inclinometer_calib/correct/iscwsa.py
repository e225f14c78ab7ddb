"""Wellbore position uncertainty by the ISCWSA MWD error model (revision 4), ROS-free.

The industry's error model (Williamson, SPE 67616, 2000; ISCWSA "Definition of the ISCWSA error
model", rev 4 tool set = OWSG MWD rev 2) treats each error source ε with a 1σ magnitude σ and a
*weighting function* ``w = ∂(D, I, A)/∂ε`` (measured depth in m, inclination and azimuth in rad)
evaluated at every survey station.  Its effect on the position of station K goes through the
position's derivatives with respect to each station's (D, I, A), taken from the balanced-tangential
formula (as the standard does, although positions themselves come by minimum curvature):

    ∂r_k/∂p_k     leg k−1 → k w.r.t. station k:
        D: ½(t_{k−1} + t_k)       I: ½ΔD_k·(cos I cos A, cos I sin A, −sin I)_k
        A: ½ΔD_k·(−sin I sin A, sin I cos A, 0)_k
    ∂r_{k+1}/∂p_k leg k → k+1 w.r.t. station k:
        D: −½(t_k + t_{k+1})      I, A: as above with ΔD_{k+1}

with ``t = (sin I cos A, sin I sin A, cos I)`` (north, east, vertical-down).  Per station and
source, ``e_k = σ·(∂r_k/∂p_k + ∂r_{k+1}/∂p_k)·w_k`` and, for the station where the position is
wanted, ``e*_K = σ·(∂r_K/∂p_K)·w_K``.  The covariance at station K (NEV, m²) sums over sources:

    random:               Σ_{k<K} e_k·e_kᵀ + e*_K·e*_Kᵀ
    systematic / global:  (Σ_{k<K} e_k + e*_K)·(Σ_{k<K} e_k + e*_K)ᵀ

Station 0 is the tie-in (the surface, or a point known perfectly): it carries no error (rev 4 has no
slot allowance).  Weighting functions of the rev 4 MWD terms (I inclination, A the azimuth of the
positions, Am the magnetic azimuth, Θ dip, G total gravity m/s², B total field nT, V TVD m):

    DRFR [1, 0, 0]   DSFS [D, 0, 0]   DSTG [D·V, 0, 0]
    ABXY-TI1S [0, −cos I/G, tanΘ cos I sin Am/G]     ABXY-TI2S [0, 0, (cot I − tanΘ cos Am)/G]
    ABZ       [0, −sin I/G, tanΘ sin I sin Am/G]
    ASXY-TI1S [0, sin I cos I/√2, −tanΘ sin I cos I sin Am/√2]
    ASXY-TI2S [0, sin I cos I/2,  −tanΘ sin I cos I sin Am/2]
    ASXY-TI3S [0, 0, (tanΘ sin I cos Am − cos I)/2]
    ASZ       [0, −sin I cos I, tanΘ sin I cos I sin Am]
    MBXY-TI1S [0, 0, −cos I sin Am/(B cosΘ)]          MBXY-TI2S [0, 0, cos Am/(B cosΘ)]
    MBZ, AMIL [0, 0, −sin I sin Am/(B cosΘ)]
    MSXY-TI1S [0, 0, sin I sin Am (tanΘ cos I + sin I cos Am)/√2]
    MSXY-TI2S [0, 0, sin Am (tanΘ sin I cos I − cos²I cos Am − cos Am)/2]
    MSXY-TI3S [0, 0, (cos I cos²Am − cos I sin²Am − tanΘ sin I cos Am)/2]
    MSZ       [0, 0, −(sin I cos Am + tanΘ cos I) sin I sin Am]
    DECG/DECR [0, 0, 1]     DBHG/DBHR [0, 0, 1/(B cosΘ)]     SAG, XYM1 [0, |sin I|, 0]   XYM2 [0, 0, −1]
    XYM3 [0, |cos I| cos A, −|cos I| sin A/sin I]     XYM4 [0, |cos I| sin A, |cos I| cos A/sin I]

Azimuth weights with a 1/sin I enter the position only through ``∂r/∂A ∝ sin I``; they are
evaluated as that product, so a vertical station gives a finite (horizontal) error rather than a
division by zero.

The sensor terms (AB*, AS*, MB*, MS*) come from the calibration's own uncertainties where the record
has them (:func:`terms_from_calibration`): what this probe's calibration determined, not the
standard's typical tool; everything else (depth, declination, interference, sag, misalignment) from
the rev 4 defaults, declination terms from the site reference's source (a global model or IFR).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

MODEL_NAME = "ISCWSA MWD Rev4"


@dataclass(frozen=True)
class Term:
    """One error source: ``name`` (ISCWSA code), 1σ ``magnitude`` in ``unit`` (angles in rad,
    DBH in rad·nT), ``propagation`` ('random', 'systematic' or 'global') and where the magnitude
    came from (``source``)."""

    name: str
    magnitude: float
    unit: str
    propagation: str
    source: str = MODEL_NAME


_D = math.radians
#: The rev 4 MWD tool model's terms with their default magnitudes (OWSG MWD rev 2, 2015).
REV4_TERMS = {t.name: t for t in (
    Term("DRFR", 0.35, "m", "random"),
    Term("DSFS", 0.00056, "-", "systematic"),
    Term("DSTG", 2.5e-7, "1/m", "global"),
    Term("ABXY-TI1S", 0.004, "m/s2", "systematic"),
    Term("ABXY-TI2S", 0.004, "m/s2", "systematic"),
    Term("ABZ", 0.004, "m/s2", "systematic"),
    Term("ASXY-TI1S", 0.0005, "-", "systematic"),
    Term("ASXY-TI2S", 0.0005, "-", "systematic"),
    Term("ASXY-TI3S", 0.0005, "-", "systematic"),
    Term("ASZ", 0.0005, "-", "systematic"),
    Term("MBXY-TI1S", 70.0, "nT", "systematic"),
    Term("MBXY-TI2S", 70.0, "nT", "systematic"),
    Term("MBZ", 70.0, "nT", "systematic"),
    Term("MSXY-TI1S", 0.0016, "-", "systematic"),
    Term("MSXY-TI2S", 0.0016, "-", "systematic"),
    Term("MSXY-TI3S", 0.0016, "-", "systematic"),
    Term("MSZ", 0.0016, "-", "systematic"),
    Term("DECG", _D(0.36), "rad", "global"),
    Term("DECR", _D(0.1), "rad", "random"),
    Term("DBHG", _D(5000.0), "rad.nT", "global"),
    Term("DBHR", _D(3000.0), "rad.nT", "random"),
    Term("AMIL", 220.0, "nT", "systematic"),
    Term("SAG", _D(0.2), "rad", "systematic"),
    Term("XYM1", _D(0.1), "rad", "systematic"),
    Term("XYM2", _D(0.1), "rad", "systematic"),
    Term("XYM3", _D(0.1), "rad", "systematic"),
    Term("XYM4", _D(0.1), "rad", "systematic"),
)}

#: 1σ of the declination from the site reference's source (rad): a global model's (ISCWSA rev 4
#: DECG) or in-field referencing's (IFR, about 0.15°: ../docs field facts).
DECLINATION_SIGMA = {"global": _D(0.36), "ifr": _D(0.15)}


def _weights(name, inc, azi, azi_mag, md, tvd, G, B, dip):
    """(N, 3) weighting functions ∂(D, I, A)/∂ε of one term; the azimuth column is returned
    multiplied by sin I (see the module docstring), so the caller does not multiply by it again."""
    si, ci = np.sin(inc), np.cos(inc)
    sa, ca = np.sin(azi_mag), np.cos(azi_mag)
    tt = math.tan(dip)
    bc = B * math.cos(dip)
    z = np.zeros_like(inc)
    r2 = math.sqrt(2.0)
    # each entry: (dD, dI, dA·sin I)
    table = {
        "DRFR": lambda: (np.ones_like(inc), z, z),
        "DSFS": lambda: (md, z, z),
        "DSTG": lambda: (md * tvd, z, z),
        "ABXY-TI1S": lambda: (z, -ci / G, si * tt * ci * sa / G),
        "ABXY-TI2S": lambda: (z, z, (ci - si * tt * ca) / G),
        "ABZ": lambda: (z, -si / G, si * tt * si * sa / G),
        "ASXY-TI1S": lambda: (z, si * ci / r2, -si * tt * si * ci * sa / r2),
        "ASXY-TI2S": lambda: (z, si * ci / 2, -si * tt * si * ci * sa / 2),
        "ASXY-TI3S": lambda: (z, z, si * (tt * si * ca - ci) / 2),
        "ASZ": lambda: (z, -si * ci, si * tt * si * ci * sa),
        "MBXY-TI1S": lambda: (z, z, -si * ci * sa / bc),
        "MBXY-TI2S": lambda: (z, z, si * ca / bc),
        "MBZ": lambda: (z, z, -si * si * sa / bc),
        "AMIL": lambda: (z, z, -si * si * sa / bc),
        "MSXY-TI1S": lambda: (z, z, si * si * sa * (tt * ci + si * ca) / r2),
        "MSXY-TI2S": lambda: (z, z, si * sa * (tt * si * ci - ci * ci * ca - ca) / 2),
        "MSXY-TI3S": lambda: (z, z, si * (ci * ca * ca - ci * sa * sa - tt * si * ca) / 2),
        "MSZ": lambda: (z, z, -si * (si * ca + tt * ci) * si * sa),
        "DECG": lambda: (z, z, si),
        "DECR": lambda: (z, z, si),
        "DBHG": lambda: (z, z, si / bc),
        "DBHR": lambda: (z, z, si / bc),
        "SAG": lambda: (z, si, z),
        "XYM1": lambda: (z, np.abs(si), z),
        "XYM2": lambda: (z, z, -si),
        "XYM3": lambda: (z, np.abs(ci) * np.cos(azi), -np.abs(ci) * np.sin(azi)),
        "XYM4": lambda: (z, np.abs(ci) * np.sin(azi), np.abs(ci) * np.cos(azi)),
    }
    try:
        return np.stack(table[name](), axis=-1)
    except KeyError:
        raise ValueError(f"unknown ISCWSA term {name!r} (known: {', '.join(table)})") from None


def _leg_derivatives(md, inc, azi):
    """∂r_k/∂p_k and ∂r_{k+1}/∂p_k, each (N, 3 position, 3 parameter) with the azimuth column
    divided by sin I (the weights carry it, :func:`_weights`)."""
    n = len(md)
    t = np.stack([np.sin(inc) * np.cos(azi), np.sin(inc) * np.sin(azi), np.cos(inc)], axis=-1)
    d_inc = np.stack([np.cos(inc) * np.cos(azi), np.cos(inc) * np.sin(azi), -np.sin(inc)], axis=-1)
    d_azi = np.stack([-np.sin(azi), np.cos(azi), np.zeros(n)], axis=-1)  # (÷ sin I)
    dmd_in = np.r_[0.0, np.diff(md)]             # ΔD of the leg into station k
    dmd_out = np.r_[np.diff(md), 0.0]            # ΔD of the leg out of station k
    t_prev = np.vstack([t[:1], t[:-1]])
    t_next = np.vstack([t[1:], t[-1:]])
    own = np.empty((n, 3, 3))
    nxt = np.empty((n, 3, 3))
    own[:, :, 0] = 0.5 * (t_prev + t)
    own[:, :, 1] = 0.5 * dmd_in[:, None] * d_inc
    own[:, :, 2] = 0.5 * dmd_in[:, None] * d_azi
    nxt[:, :, 0] = -0.5 * (t + t_next)
    nxt[:, :, 1] = 0.5 * dmd_out[:, None] * d_inc
    nxt[:, :, 2] = 0.5 * dmd_out[:, None] * d_azi
    own[0] = 0.0                                 # no leg into the tie-in
    nxt[-1] = 0.0                                # no leg out of the last station (yet)
    return own, nxt


@dataclass
class PositionUncertainty:
    """Covariance of station positions (NEV = north, east, vertical down; m²), ``cov`` (N, 3, 3)
    in total and ``by_term`` per term, for the stations (the tie-in included, with zero)."""

    cov: np.ndarray
    by_term: dict
    terms: dict

    def sigma(self) -> np.ndarray:
        """(N, 3) 1σ in north, east, vertical (m)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov, axis1=1, axis2=2), 0.0))

    def horizontal_semi_axes(self) -> np.ndarray:
        """(N, 2) 1σ semi-major and semi-minor axes of the horizontal error ellipse (m)."""
        ev = np.linalg.eigvalsh(self.cov[:, :2, :2])
        return np.sqrt(np.maximum(ev[:, ::-1], 0.0))


def position_covariance(md, inc_deg, azi_deg, *, total_gravity_mps2: float, total_field_nt: float,
                        dip_deg: float, declination_deg: float = 0.0, tvd=None, terms=None,
                        azi_magnetic_deg=None) -> PositionUncertainty:
    """ISCWSA covariance of every station of a survey (see the module docstring).

    ``md`` (m, ascending, the first row the tie-in), ``inc_deg``, ``azi_deg`` (the azimuth of the
    positions' north, true or grid); ``azi_magnetic_deg`` the magnetic azimuth (default
    ``azi_deg − declination_deg``); ``tvd`` (m, for DSTG; default by minimum curvature from the
    tie-in at 0); ``terms`` a dict of :class:`Term` (default :data:`REV4_TERMS`)."""
    md = np.asarray(md, float)
    if len(md) and np.any(np.diff(md) <= 0):
        k = int(np.argmax(np.diff(md) <= 0)) + 1
        raise ValueError(f"measured depths must increase from station to station: station {k} at {md[k]:g} m "
                         f"follows {md[k - 1]:g} m")
    inc = np.radians(np.asarray(inc_deg, float))
    azi = np.radians(np.nan_to_num(np.asarray(azi_deg, float)))
    if azi_magnetic_deg is None:
        azi_m = azi - math.radians(declination_deg)
    else:
        azi_m = np.radians(np.nan_to_num(np.asarray(azi_magnetic_deg, float)))
    if tvd is None:
        from .trajectory import minimum_curvature
        tvd = minimum_curvature(md, np.degrees(inc), np.degrees(azi)).tvd
    tvd = np.asarray(tvd, float)
    terms = REV4_TERMS if terms is None else terms
    own, nxt = _leg_derivatives(md, inc, azi)
    total = np.zeros((len(md), 3, 3))
    by_term = {}
    for term in terms.values():
        w = _weights(term.name, inc, azi, azi_m, md, tvd, total_gravity_mps2, total_field_nt,
                     math.radians(dip_deg)) * term.magnitude
        e = np.einsum("kij,kj->ki", own + nxt, w)
        e_star = np.einsum("kij,kj->ki", own, w)
        e[0] = 0.0
        e_star[0] = 0.0             # the tie-in is known
        if term.propagation == "random":
            acc = np.cumsum(np.einsum("ki,kj->kij", e, e), axis=0)
            cov = np.concatenate([np.zeros((1, 3, 3)), acc[:-1]]) + np.einsum("ki,kj->kij", e_star, e_star)
        elif term.propagation in ("systematic", "global"):
            s = np.concatenate([np.zeros((1, 3)), np.cumsum(e, axis=0)[:-1]]) + e_star
            cov = np.einsum("ki,kj->kij", s, s)
        else:
            raise ValueError(f"term {term.name}: unknown propagation {term.propagation!r}")
        by_term[term.name] = cov
        total += cov
    return PositionUncertainty(total, by_term, dict(terms))


#: Which calibration uncertainty becomes which ISCWSA sensor term: (triad, quantity, axes).
SENSOR_TERMS = {
    "ABXY-TI1S": ("acc", "bias", "xy"), "ABXY-TI2S": ("acc", "bias", "xy"), "ABZ": ("acc", "bias", "z"),
    "ASXY-TI1S": ("acc", "scale", "xy"), "ASXY-TI2S": ("acc", "scale", "xy"), "ASXY-TI3S": ("acc", "scale", "xy"),
    "ASZ": ("acc", "scale", "z"),
    "MBXY-TI1S": ("mag", "bias", "xy"), "MBXY-TI2S": ("mag", "bias", "xy"), "MBZ": ("mag", "bias", "z"),
    "MSXY-TI1S": ("mag", "scale", "xy"), "MSXY-TI2S": ("mag", "scale", "xy"), "MSXY-TI3S": ("mag", "scale", "xy"),
    "MSZ": ("mag", "scale", "z"),
}


def terms_from_calibration(cal, site=None, base=None) -> dict:
    """The tool model for a probe: :data:`REV4_TERMS` (or ``base``) with the sensor terms replaced
    by the calibration record's own 1σ (``cal.uncertainty``: per triad, ``bias`` in m/s² or nT and
    ``scale`` dimensionless, per axis), the cross-axial terms taking the RMS of x and y; and the
    declination term by the site reference's source (``site.reference['sources']['declination_deg']``,
    :func:`geomag.site_from_config`: a model → global, 'measured (IFR)' → :data:`DECLINATION_SIGMA`
    ['ifr']).  A record without uncertainties
    keeps the defaults (each term's ``source`` says which)."""
    terms = dict(REV4_TERMS if base is None else base)
    unc = getattr(cal, "uncertainty", None) or {}
    cal_id = getattr(cal, "id", "")
    for name, (triad, quantity, axes) in SENSOR_TERMS.items():
        sig = (unc.get(triad) or {}).get(quantity)
        if sig is None:
            continue
        sig = np.asarray(sig, float)
        value = float(sig[2]) if axes == "z" else float(np.sqrt(np.mean(sig[:2] ** 2)))
        if math.isfinite(value):
            terms[name] = replace(terms[name], magnitude=value, source=f"calibration {cal_id}")
    ref = getattr(site, "reference", None) or {}
    source = str((ref.get("sources") or {}).get("declination_deg", ""))
    if source and "DECG" in terms:
        kind = "ifr" if source.startswith("measured") else "global"
        terms["DECG"] = replace(terms["DECG"], magnitude=DECLINATION_SIGMA[kind], source=f"site reference: {source}")
    return terms


def describe_terms(terms: dict) -> list:
    """One line per term: name, magnitude in display units and source (for reports)."""
    out = []
    for t in terms.values():
        value, unit = t.magnitude, t.unit
        if unit == "rad":
            value, unit = math.degrees(value), "deg"
        elif unit == "rad.nT":
            value, unit = math.degrees(value), "deg.nT"
        out.append(f"{t.name:10s} {value:.4g} {unit} ({t.propagation}; {t.source})")
    return out

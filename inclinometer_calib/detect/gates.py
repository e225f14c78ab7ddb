"""Acceptance gates for static stations: in-hold motion and saturation — ROS-free.

Every station, whatever path found it (live detector, a log, a bag), is checked here against
the noise the data show (:mod:`noise`; the σ the detector used is carried by the station), so
the limits adapt to the probe.  A failed gate is a :class:`Finding` with a message that says
what, where and how much; callers log it at WARNING (never INFO), attach it to the station and
leave the station out of what it would spoil:

* ``creep`` — the probe turned during the hold: the least-squares trend of the accelerometer
  (or magnetometer) direction over the station is significant against the noise (``TREND_Z``
  standard errors) *and* larger than ``max_creep_deg``.  Both sensors are used: a rotation
  about the vertical leaves gravity unchanged but turns the field.
* ``transient`` — the magnetometer trends while the accelerometer holds still *and* the total
  field or the dip changes beyond the noise (``TREND_Z`` standard errors) and as much as a creep at
  the limit would move the field: a rigid rotation keeps both (turning about the vertical changes
  neither |B| nor the angle between the field and gravity), a sensor settling after the move does
  not.  The message says it is not motion.  The settling is then measured (:func:`settling`: ``y = c + A·exp(−τ/τ_s)`` fitted to
  the hold's shape, one time constant for the three axes) and the start of the hold left out
  until the gates find no transient in the rest (``settled``, said with the figures: the hold is
  kept, shorter; what the settling leaves in its mean the lab models, :class:`effects.Settling`);
  a hold that has not settled with ``min_settled_s`` left has its magnetometer data refused.
* ``unsteady`` — the scatter left after removing that trend is far above the noise (a χ² test
  at p < 1e-6 *and* more than ``max_scatter_ratio`` × σ): vibration, or motion no trend
  describes.
* ``flat`` — an axis that did not change at all, or far less than its noise (< 0.25 σ, a χ²
  impossibility for ≥ 10 white-noise samples): a clipped/saturated ADC or a stuck axis.  Only
  that sensor's data are refused.  :class:`SaturationMonitor` notices the same level repeating
  across stations and names it ("saturates at 9.6 m/s², below its stated full scale").
* ``gravity`` — the raw |g| is more than ``max_gravity_error`` (relative) away from the site's:
  no uncalibrated scale error is that large; a saturated axis, wrong units or a moving probe.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.effects import mean_decay
from ..core.frames import specific_force_from_gravity
from .noise import chi_quantile

#: Significance of a trend, in standard errors of the slope.
TREND_Z = 5.0
#: p-value of the scatter test (χ² with n-1 degrees of freedom).
SCATTER_P = 1e-6
#: Scatter below this fraction of the noise is an axis that does not respond (≥ 10 samples).
FLAT_RATIO = 0.25
#: The time constants (s) tried for a sensor settling after the move.
SETTLE_TAUS = np.geomspace(0.05, 30.0, 80)
#: The station fields a trimmed hold replaces (:meth:`station.Station.settled_from`).
_SETTLED_FIELDS = ("t_start", "n", "g", "b", "g_std", "b_std", "g_rate", "b_rate", "t_std", "settled_s", "profile")


@dataclass(frozen=True)
class GateLimits:
    """Gate limits.  ``max_creep_deg``: largest turn of the probe during a hold that is not
    motion (the stand's own settling); ``max_scatter_ratio``: scatter above this multiple of the
    noise (and significant) is unsteady; ``max_gravity_error``: relative |g| error beyond which
    the accelerometer reading is implausible before calibration."""

    max_creep_deg: float = 0.05
    max_scatter_ratio: float = 1.5
    max_gravity_error: float = 0.10
    #: A hold whose sensor settles after the move keeps at least this long (s) once trimmed.
    min_settled_s: float = field(default=0.5, kw_only=True)


@dataclass(frozen=True)
class Finding:
    """A gate that failed: ``code`` (creep, unsteady, flat, gravity), the ``sensors`` whose data
    it disqualifies (``("acc", "mag")`` for motion), the message for the user, and for ``flat`` the
    axis (e.g. ``"magnetometer y"``)."""

    code: str
    sensors: tuple
    message: str
    axis: str = ""
    #: The figures of the message, for summaries: ``settled``: (time constant s, seconds left out,
    #: size at the hold's start in the sensor's unit).
    values: tuple = ()


def _turn_deg(mean, rate, duration):
    """Angle (deg) by which the vector ``mean`` turns over ``duration`` at the per-axis ``rate``."""
    v = np.asarray(mean, float)
    nv = float(np.linalg.norm(v))
    if not nv > 0:
        return 0.0
    d = np.asarray(rate, float) * duration
    perp = d - (d @ v) / (nv * nv) * v
    return math.degrees(float(np.linalg.norm(perp)) / nv)


def _trend_z(rate, noise, n, t_std):
    """Largest per-axis slope in standard errors: se = σ / (t_std·sqrt(n-1))."""
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.asarray(noise, float) / (t_std * math.sqrt(max(n - 1, 1)))
        z = np.abs(np.asarray(rate, float)) / se
    z = z[np.isfinite(z)]
    return float(z.max()) if len(z) else 0.0


def _invariant_z(b, b_rate, b_noise, g, n, t_std) -> tuple:
    """How far the magnetometer's trend over a hold changes the invariants a rigid rotation keeps:
    ``(dB, z_B, ddip, z_dip)`` — the rate of |B| (unit/s) along b̂ and of the field's direction
    towards ĝ (rad/s), each in standard errors of the per-axis slopes (the accelerometer still)."""
    b, rate, g = (np.asarray(x, float) for x in (b, b_rate, g))
    nb, ng = float(np.linalg.norm(b)), float(np.linalg.norm(g))
    if not (nb > 0 and ng > 0):
        return 0.0, 0.0, 0.0, 0.0
    se = np.asarray(b_noise, float) / (t_std * math.sqrt(max(n - 1, 1)))
    bh, gh = b / nb, g / ng
    u = gh - bh * float(bh @ gh)                 # the direction in which the dip changes
    nu = float(np.linalg.norm(u))
    out = []
    for d in (bh, u / nu if nu > 0 else u):
        r = float(d @ rate)
        s = float(np.sqrt(np.sum((d * se) ** 2)))
        out += [r, abs(r) / s if s > 0 else 0.0]
    return out[0], out[1], out[2] / nb, out[3]


def station_findings(st, limits: GateLimits = GateLimits(), gravity_mps2: float | None = None) -> list:
    """The gates a :class:`station.Station` fails, as a list of :class:`Finding` (empty: fine).

    Needs the station's noise (``g_noise``, ``b_noise``); without it the motion and flatness
    tests are skipped (nothing to compare with).  ``gravity_mps2``: the site's |g| for the
    gravity gate (skipped if None).
    """
    out = []
    dur = st.duration_s
    where = f"{st.label} at {st.where}" if (st.pose or st.has_partial_ref) else st.where
    g_noise = np.asarray(st.g_noise, float)
    acc_still = bool(np.all(np.isfinite(g_noise) & (g_noise > 0))
                     and _trend_z(st.g_rate, g_noise, st.n, st.t_std) <= TREND_Z)
    for sensor, name, mean, std, rate, noise, unit in (
            ("acc", "accelerometer", st.g, st.g_std, st.g_rate, st.g_noise, "m/s^2"),
            ("mag", "magnetometer", st.b, st.b_std, st.b_rate, st.b_noise, "nT")):
        noise = np.asarray(noise, float)
        if not np.all(np.isfinite(noise) & (noise >= 0)):
            continue
        std = np.asarray(std, float)
        # flat: an axis that does not respond (noise 0: it did not change in the data while the
        # sensor's other axes did — a sensor with no noise at all cannot tell stuck from quiet)
        if st.n >= 10:
            noisy = bool(np.any(noise > 0))
            flat = [k for k in range(3) if std[k] < FLAT_RATIO * noise[k] or (noise[k] == 0 and std[k] == 0 and noisy)]
            if flat:
                k = flat[0]
                level = -mean[k] if sensor == "acc" else mean[k]  # as the sensor reports it (REP-145 for acc)
                out.append(Finding("flat", (sensor,), (
                    f"{where}: {name} {'xyz'[k]} reads a constant {level:.4f} {unit} (scatter {std[k]:.3g} vs noise "
                    f"{noise[k]:.3g} {unit} over {st.n} samples): clipped/saturated or stuck — its {name} data are "
                    "not used"), axis=f"{name} {'xyz'[k]}"))
                continue
        if not np.all(noise > 0):
            continue   # no noise to judge a trend or a scatter against
        # creep: the direction turns during the hold
        turn = _turn_deg(mean, rate, dur)
        z = _trend_z(rate, noise, st.n, st.t_std)
        if z > TREND_Z and sensor == "mag" and acc_still:
            db, z_b, ddip, z_dip = _invariant_z(mean, rate, noise, st.g, st.n, st.t_std)
            # as material as a creep: the direction turns beyond the limit, or |B| or the dip changes by
            # as much as that turn would move the field (a slow drift of a few nT over a long hold is not)
            limit = math.radians(limits.max_creep_deg)
            material = (turn > limits.max_creep_deg or abs(db * dur) > limit * float(np.linalg.norm(mean))
                        or abs(ddip * dur) > limit)
            if max(z_b, z_dip) > TREND_Z and material:
                out.append(Finding("transient", ("mag",), (
                    f"{where}: the magnetometer turned {turn:.3f}° during the {dur:.2f} s hold while the accelerometer "
                    f"held still, and |B| changed by {db * dur:+.1f} {unit} ({z_b:.0f} standard errors), the dip by "
                    f"{math.degrees(ddip * dur):+.3f}° ({z_dip:.0f}): a rigid rotation keeps both — a sensor transient "
                    "(the magnetometer settling after the move), not motion — its magnetometer data are not used")))
                continue
        if turn > limits.max_creep_deg and z > TREND_Z:
            out.append(Finding("creep", ("acc", "mag"), (
                f"{where}: the probe turned {turn:.3f}° during the {dur:.2f} s hold ({name} trend "
                f"{turn / dur if dur > 0 else math.inf:.3f}°/s, {z:.0f} standard errors; limit "
                f"{limits.max_creep_deg:g}°): it moved or crept on the stand — station not used")))
            continue
        # unsteady: scatter left after the trend, against the noise
        resid = np.sqrt(np.maximum(std * std - (np.asarray(rate, float) * st.t_std) ** 2, 0.0))
        ratio = resid / noise
        k = int(np.argmax(ratio))
        if st.n >= 5 and ratio[k] > max(limits.max_scatter_ratio, chi_quantile(st.n, 1.0 - SCATTER_P)):
            out.append(Finding("unsteady", ("acc", "mag"), (
                f"{where}: {name} {'xyz'[k]} scatters {ratio[k]:.1f}× its noise ({resid[k]:.3g} vs {noise[k]:.3g} "
                f"{unit}): vibration or motion during the hold — station not used"), axis=f"{name} {'xyz'[k]}"))
    if gravity_mps2 and not any(f.code == "flat" and "acc" in f.sensors for f in out):
        gn = float(np.linalg.norm(st.g))
        err = gn / gravity_mps2 - 1.0
        if abs(err) > limits.max_gravity_error:
            out.append(Finding("gravity", ("acc",), (
                f"{where}: raw |g| = {gn:.4g} m/s² is {100 * err:+.0f}% from the site's {gravity_mps2:.5g} (limit "
                f"±{100 * limits.max_gravity_error:g}%): a saturated axis, wrong units or a moving probe — its "
                "accelerometer data are not used")))
    return out


@dataclass(frozen=True)
class Settling:
    """A sensor settling after the move, measured over one hold: ``y(τ) = c + A·exp(−τ/tau_s)``
    per axis (``τ`` from the hold's first sample), ``amplitude`` ``A`` (3,) in the sensor's unit,
    and where the hold is settled: ``row`` of :attr:`station.Station.profile`, ``trim_s`` from
    its start."""

    sensor: str
    tau_s: float
    amplitude: np.ndarray
    row: int
    trim_s: float


def settling(st, sensor: str = "mag", limits: GateLimits = GateLimits(), gravity_mps2: float | None = None
             ) -> Settling | None:
    """Measure a sensor settling over the hold ``st`` (a :class:`station.Station` with its
    profile) and where it has settled; None when the hold's shape is not a settling (no profile,
    too few segments, a time constant as long as the hold) or it has not settled with
    ``limits.min_settled_s`` left.

    The hold's segments between profile rows (a quarter second each) give the shape; for each
    time constant of :data:`SETTLE_TAUS` the three axes' ``c`` and ``A`` are a weighted linear
    fit (weights the segments' sample counts, the axes by their noise), and the time constant of
    least χ² is taken; a time constant as long as the hold is a drift (or a hold too short to see
    the settling), not a settling.  The hold has settled from the first profile row after which the
    gates find neither a transient nor motion in what is left (:func:`station_findings`), at least
    ``min_settled_s`` long: what the settling
    still leaves in that part's mean is below what the gates can tell from the noise, and the lab
    models it (:class:`effects.Settling`)."""
    seg = st.segments()
    p = st.profile
    cols = slice(0, 3) if sensor == "acc" else slice(3, 6)
    noise = np.asarray(st.g_noise if sensor == "acc" else st.b_noise, float)
    if seg is None or len(seg[0]) < 4 or not np.all(np.isfinite(noise) & (noise > 0)) or st.n < 3:
        return None
    dt = float(p[-1, 0]) / max(float(p[-1, 1]) - 1.0, 1.0)    # the sample interval (counts from the first sample)
    starts, w, mean = seg
    y = mean[:, cols]
    e = mean_decay(starts[None, :], w[None, :], dt, SETTLE_TAUS[:, None])     # (taus, segments)
    sw = w.sum()
    eb = (e * w).sum(axis=1) / sw
    yb = (y * w[:, None]).sum(axis=0) / sw
    de, dy = e - eb[:, None], y - yb
    sxx = (w * de * de).sum(axis=1)
    sxy = (w[None, :, None] * de[:, :, None] * dy[None, :, :]).sum(axis=1)          # (taus, 3)
    syy = (w[:, None] * dy * dy).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        chi2 = ((syy[None, :] - sxy ** 2 / sxx[:, None]) / noise ** 2).sum(axis=1)
    chi2 = np.where(np.isfinite(chi2), chi2, np.inf)
    k = int(np.argmin(chi2))
    tau = float(SETTLE_TAUS[k])
    if k == len(SETTLE_TAUS) - 1 or not np.isfinite(chi2[k]) or tau >= p[-1, 0]:
        return None          # as slow as the hold or slower: a drift (or a hold too short to see it settle)
    amp = sxy[k] / sxx[k]
    for row in range(len(p) - 1):
        if p[-1, 0] - p[row, 0] < limits.min_settled_s - 1e-9 or p[-1, 1] - p[row, 1] < 3:
            return None
        rest = st.settled_from(row)
        left = station_findings(rest, limits, gravity_mps2)
        # settled: no trend of |B| or the dip left that the noise can tell, however small (the gate's
        # own test also asks for a material change; the part kept must not carry the transient on)
        z = _invariant_z(rest.b, rest.b_rate, noise, rest.g, rest.n, rest.t_std)
        if not any(f.code in ("transient", "creep", "unsteady") for f in left) and max(z[1], z[3]) <= TREND_Z:
            return Settling(sensor, tau, amp, row, float(p[row, 0]))
    return None


class SettlingTally:
    """A sensor that settles after every move gets a ``settled`` finding at every hold: the first
    :attr:`SAID` are said as they come, the rest counted, and :meth:`summary` gives one line with
    the figures over all of them."""

    SAID = 2

    def __init__(self):
        self.found = []

    def add(self, findings) -> list:
        """The messages of ``findings`` (a station's) to say now: all but the ``settled`` ones past
        the first :attr:`SAID`."""
        out = []
        for f in findings:
            if f.code == "settled":
                self.found.append(f.values)
                if len(self.found) > self.SAID:
                    continue
            out.append(f.message)
        return out

    def summary(self, holds: int | None = None, where: str = "") -> str | None:
        """One line over every settled hold (None when fewer than :attr:`SAID` + 1: all were said)."""
        if len(self.found) <= self.SAID:
            return None
        tau, trim, size = (np.array(x) for x in zip(*self.found))
        of = f" of {holds}" if holds else ""
        return (f"{where}{': ' if where else ''}the magnetometer settles after the move in {len(self.found)}{of} holds "
                f"(time constant {np.median(tau):.2f} s, {tau.min():.2f}–{tau.max():.2f}; up to {size.max():.0f} nT at a "
                f"hold's start): a sensor transient, not motion — {trim.min():.2f}–{trim.max():.2f} s left out at each "
                f"hold's start ({len(self.found) - self.SAID} of these holds not said one by one)")


class SaturationMonitor:
    """Notices an axis that goes flat at the same level in several stations: an ADC that
    saturates (below the full scale the data sheet states, or the limit is not known).

    :meth:`add` takes the ``flat`` findings of a station; it returns a message the first time
    a level repeats (a second flat station within ``level_tolerance`` of the same value).
    """

    def __init__(self, acc_tolerance: float = 1e-3, mag_tolerance: float = 1.0):
        self.tol = {"acc": acc_tolerance, "mag": mag_tolerance}
        self._levels = {}     # (sensor, axis) -> [level, count]
        self.reported = set()

    def add(self, st, findings) -> list:
        out = []
        # a stuck level is said as the log records it (REP-145 specific force)
        for sensor, mean, std, noise in (("acc", specific_force_from_gravity(st.g), st.g_std, st.g_noise),
                                         ("mag", np.asarray(st.b), st.b_std, st.b_noise)):
            if not any(f.code == "flat" and sensor in f.sensors for f in findings):
                continue
            for k in range(3):
                if not (std[k] < FLAT_RATIO * noise[k] or (noise[k] == 0 and std[k] == 0)):
                    continue
                key = (sensor, k)
                lvl = self._levels.setdefault(key, [float(mean[k]), 0])
                if abs(lvl[0] - mean[k]) <= self.tol[sensor]:
                    lvl[1] += 1
                else:
                    self._levels[key] = [float(mean[k]), 1]
                    continue
                if lvl[1] >= 2 and key not in self.reported:
                    self.reported.add(key)
                    unit = "m/s^2" if sensor == "acc" else "nT"
                    name = "accelerometer" if sensor == "acc" else "magnetometer"
                    out.append(f"{name} {'xyz'[k]} is flat at {lvl[0]:.4f} {unit} in {lvl[1]} stations: it saturates "
                               f"(clips) at that level — below the stated full scale if one is given; poses or stations "
                               f"where the axis reaches it cannot be used")
        return out


def apply_gates(st, limits: GateLimits = GateLimits(), gravity_mps2: float | None = None) -> list:
    """Run the gates on a station once and record the outcome on it: ``warnings`` (messages),
    ``unusable`` (sensors refused), ``moved`` (in-hold motion), ``gated``, ``findings``.  Returns the findings
    of this run (empty if the station was gated before: its messages were given then)."""
    if st.gated:
        return []
    found = station_findings(st, limits, gravity_mps2)
    # the magnetometer changing while the accelerometer holds: a sensor settling after the move?
    mag_only = [f for f in found if f.code == "transient" or (f.code == "unsteady" and f.axis.startswith("magnetometer"))]
    if mag_only and st.profile is not None and not any(
            f.code in ("creep", "unsteady") and f not in mag_only for f in found):
        found = _settle(st, found, limits, gravity_mps2)
    st.gated = True
    st.findings = tuple(found)
    st.warnings.extend(f.message for f in found)
    st.unusable = tuple(sorted(set(st.unusable) | {s for f in found if f.code in ("flat", "gravity", "transient")
                                                   for s in f.sensors}))
    st.moved = st.moved or any(f.code in ("creep", "unsteady") for f in found)
    return found


def _settle(st, found, limits, gravity_mps2) -> list:
    """A hold whose magnetometer changed while the accelerometer held: measure the settling
    (:func:`settling`) and, when the hold settles, keep it from there (``st`` changed in place, a
    ``settled`` finding that refuses nothing); else the findings as they were."""
    where = f"{st.label} at {st.where}" if (st.pose or st.has_partial_ref) else st.where
    s = settling(st, "mag", limits, gravity_mps2)
    if s is None:
        return found
    kept = st.settled_from(s.row)
    n0, dur0 = st.n, st.duration_s
    for name in _SETTLED_FIELDS:
        setattr(st, name, getattr(kept, name))
    size = float(np.linalg.norm(s.amplitude))
    note = Finding("settled", (), (
        f"{where}: the magnetometer settles after the move ({size:.0f} nT at the start of the hold, decaying with a "
        f"time constant of {s.tau_s:.2f} s) — a sensor transient, not motion: the first {s.trim_s:.2f} s of the "
        f"{dur0:.2f} s hold are left out ({st.n} of {n0} samples kept)"), values=(s.tau_s, s.trim_s, size))
    return [note] + station_findings(st, limits, gravity_mps2)

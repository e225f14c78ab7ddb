"""Predicted uncertainty of every station's drift, azimuth and toolface, and whether it holds.

Two parts, propagated to first order through the model's own correction and angle computation
(finite differences, so any effect and any plug-in is covered):

* the **measurement noise** of the station's means — ``g_sigma`` and ``b_sigma`` (per-axis sample
  scatter / √n, :class:`station.Stations`), independent per axis:
  ``σ²_noise = Σ_k (∂angle/∂m_k · σ_k)²`` over the six measured components;
* the **model's uncertainty** — the fit's covariance ``C`` of its free parameters:
  ``σ²_model = J_θ · C · J_θᵀ`` with ``J_θ = ∂angle/∂θ``;
* a **wandering bias's path** (:class:`effects.BiasWander`): its posterior σ at the station's
  time, per axis, propagated like the noise.

``σ = √(σ²_noise + σ²_model)``, in degrees.  On a validation log the normalised errors
``(angle − reference) / σ`` should scatter with an RMS near 1 when the model and its uncertainty
are right (:func:`normalised_errors`); a spread well above 1 means the model misses an effect
(or the noise is not white), well below 1 that the uncertainty is overstated.
"""
from __future__ import annotations

import copy

import numpy as np

from ..core.frames import Site, wrap180
from ..core.survey import compared_toolface_deg, evaluate

ANGLES = ("drift", "azimuth", "toolface")


def _angles(model, data) -> np.ndarray:
    """Drift, azimuth and the toolface a reference error compares (:func:`survey.compared_toolface_deg`:
    the gravity toolface, the magnetic one at a vertical reference), deg."""
    g, b = model.correct(data)
    site = Site(model.site.total_field_nt, model.site.dip_deg, model.site.declination_deg + model.heading_deg,
                model.site.gravity_mps2)
    r = evaluate(g, b, site)
    return np.stack([r["drift_deg"], r["azimuth_deg"], compared_toolface_deg(r, data.ref[:, 0])], axis=1)


def _diff(a, b) -> np.ndarray:
    d = a - b
    d[:, 1:] = wrap180(d[:, 1:])
    return d


def noise_variance(model, data, base=None) -> np.ndarray:
    """(N, 3) variance (deg²) of drift, azimuth, toolface from the measurement noise of the means."""
    base = _angles(model, data) if base is None else base
    var = np.zeros_like(base)
    for arr, sig in (("g", data.g_sigma), ("b", data.b_sigma)):
        for k in range(3):      # one component of every station at a time (stations are independent)
            d = data.subset(np.ones(len(data), bool))
            v = getattr(d, arr).copy()
            v[:, k] += sig[:, k]
            setattr(d, arr, v)
            var += _diff(_angles(model, d), base) ** 2     # (∂angle/∂m · σ)², step h = σ
    return var


def wander_variance(model, data, base=None) -> np.ndarray:
    """(N, 3) variance (deg²) of drift, azimuth, toolface from the uncertainty of a wandering
    bias's path (:meth:`effects.BiasWander.sigma_at`, per axis, taken independent): an error of
    the path is an error of the output it is taken from."""
    base = _angles(model, data) if base is None else base
    var = np.zeros_like(base)
    for t in model.terms:
        e = t.effect
        if not e.stochastic:
            continue
        sig = e.sigma_at(data.time_s)
        arr = "g" if e.sensor == "acc" else "b"
        for j, a in enumerate(e.axes):
            d = data.subset(np.ones(len(data), bool))
            v = getattr(d, arr).copy()
            v[:, "xyz".index(a)] += sig[:, j]
            setattr(d, arr, v)
            var += _diff(_angles(model, d), base) ** 2
    return var


def noise_floor(model, data) -> dict:
    """What a perfect model would still show on the stations with a reference: the RMS of the
    noise-only σ of drift, azimuth (where defined) and pointing (deg) — the floor of a ladder."""
    d = data.subset(np.isfinite(data.ref[:, 0]))
    if not len(d):
        return {}
    var = noise_variance(model, d)
    az = np.isfinite(d.ref[:, 1])
    sin_i = np.sin(np.radians(d.ref[:, 0]))
    point = var[:, 0] + np.where(az, sin_i ** 2 * var[:, 1], 0.0)
    return {"drift_rms_deg": float(np.sqrt(np.mean(var[:, 0]))),
            "azimuth_rms_deg": float(np.sqrt(np.mean(var[az, 1]))) if az.any() else float("nan"),
            "pointing_rms_deg": float(np.sqrt(np.mean(point)))}


def station_sigmas(model, fit_result, data) -> np.ndarray:
    """(N, 3) predicted 1σ (deg) of drift, azimuth and toolface of each station of ``data`` for a
    fitted ``model`` (its :class:`fit.FitResult` gives the covariance)."""
    base = _angles(model, data)
    var = noise_variance(model, data, base) + wander_variance(model, data, base)
    # the model's parameters
    cov = fit_result.covariance
    theta = model.get_vector()
    free = np.flatnonzero(np.isfinite(np.diag(cov)) & (np.diag(cov) > 0))
    if len(free):
        m = copy.deepcopy(model)
        jac = np.zeros((len(base), 3, len(free)))
        for j, i in enumerate(free):
            h = np.sqrt(cov[i, i]) * 1e-2
            t = theta.copy()
            t[i] += h
            m.set_vector(t)
            jac[:, :, j] = _diff(_angles(m, data), base) / h
        c = cov[np.ix_(free, free)]
        var += np.einsum("nap,pq,naq->na", jac, c, jac)
    return np.sqrt(var)


def normalised_errors(model, fit_result, data) -> dict:
    """The stations with a reference: errors over their predicted σ, per angle — the RMS (≈ 1
    when the uncertainty holds), the share within ±1σ and ±2σ (68 % and 95 % for a normal spread),
    and the counts.  Azimuth only where it is defined; toolface where the reference gives one."""
    has = np.isfinite(data.ref[:, 0])
    d = data.subset(has)
    if not len(d):
        return {}
    sig = station_sigmas(model, fit_result, d)
    r = model.angle_errors(d)
    errs = np.stack([r["drift_err"], np.asarray(r["azimuth_err"], float), np.asarray(r["toolface_err"], float)],
                    axis=1)
    out = {}
    for j, name in enumerate(ANGLES):
        ok = np.isfinite(errs[:, j]) & np.isfinite(d.ref[:, j]) & (sig[:, j] > 0)
        if name == "azimuth":
            ok &= ~np.asarray(r["azimuth_undefined"], bool)
        z = errs[ok, j] / sig[ok, j]
        out[name] = {"stations": int(ok.sum()),
                     "rms": float(np.sqrt(np.mean(z ** 2))) if ok.any() else float("nan"),
                     "within_1": float(np.mean(np.abs(z) <= 1)) if ok.any() else float("nan"),
                     "within_2": float(np.mean(np.abs(z) <= 2)) if ok.any() else float("nan"),
                     "median_sigma_deg": float(np.median(sig[ok, j])) if ok.any() else float("nan")}
    return out

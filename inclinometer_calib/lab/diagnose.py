"""Diagnosis: where does the model fail, which physical effect is missing, how much does it help?

1. **Residual structure.**  The fitted model's noise-normalised residuals (per sensor axis, and the
   validation drift/azimuth errors) are tested against candidate regressors — temperature, time,
   sign of the input, input², |input|, sin/cos of drift, azimuth and toolface and their products —
   with an F-test per (channel, regressor), Bonferroni-corrected.  The noise level is the scatter
   inside the static segments, so "significant" means "beyond the sensor noise".
2. **Candidates.**  Every catalogue (and plug-in) effect not yet in the model, for each sensor it
   acts on, is added in turn and scored by **held-out error**: K-fold cross-validation over the
   validation stations (fit on the calibration log plus the other folds, evaluate the angle errors
   of the held-out fold).  The score is the RMS pointing error of the tool axis,
   ``sqrt(Δdrift² + (sin(drift)·Δazimuth)²)``; the Bayesian information criterion of the fit on
   all data is reported beside it.
3. **Verdict.**  The best candidate is recommended when it lowers the held-out error by at least
   ``min_gain`` and its BIC by at least 10.  When the model still misfits the data beyond the noise
   and no candidate helps, the verdict says so and shows the structure that is left.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from .. import effects as fx
from .fit import fit, physical_hints
from .model import LabModel
from .stats import regress

Z_RMS_LIMIT = 1.3
#: Pseudo-effect: a heading offset between the stand's north and the site reference's north.
HEADING = "heading_offset"
HEADING_SIGNATURE = ("a constant azimuth error: the stand's north (or the declination) differs from the site "
                     "reference's — check the declination in the site file, or keep the offset fitted (--fit-heading)")


@dataclass
class Candidate:
    effect: str
    sensor: str
    axes: str
    scope: str
    val: dict
    score: float
    gain: float
    delta_bic: float
    significant: bool
    fit_all: object = None

    @property
    def label(self):
        if self.sensor == "site":
            return self.effect
        return f"{self.effect}:{self.sensor}:{self.axes}" + ("" if self.scope == "all" else f"@{self.scope}")

    def to_json(self):
        return {"effect": self.effect, "sensor": self.sensor, "axes": self.axes, "scope": self.scope,
                "val": self.val, "score": self.score, "gain": self.gain, "delta_bic": self.delta_bic,
                "significant": self.significant}


@dataclass
class Diagnosis:
    model: LabModel
    base_fit: object
    base_val: dict
    base_score: float
    structure: list
    ranked: list
    untestable: list
    significant_structure_left: bool
    verdict: str
    folds: int
    notes: list = field(default_factory=list)

    @property
    def recommended(self):
        return self.ranked[0] if self.ranked and self.ranked[0].significant else None

    def to_json(self):
        return {"model": self.model.describe(), "base": {"val": self.base_val, "score": self.base_score,
                                                          "z_rms": self.base_fit.z_rms},
                "ranked": [c.to_json() for c in self.ranked],
                "recommended": self.recommended.label if self.recommended else None,
                "significant_structure_left": bool(self.significant_structure_left),
                "structure": self.structure, "untestable": self.untestable, "verdict": self.verdict,
                "folds": self.folds}


# ------------------------------------------------------------------------------------------------
def val_metrics(model: LabModel, data) -> dict:
    """Angle errors of the stations with a reference: drift, azimuth and pointing RMS/max (deg)."""
    has = np.all(np.isfinite(data.ref), axis=1)
    if not has.any():
        return {"stations": 0}
    r = model.angle_errors(data.subset(has))
    de = r["drift_err"]
    ae = r["azimuth_err"]
    ok = np.isfinite(ae)
    sin_i = np.sin(np.radians(data.ref[has, 0]))
    pe = np.sqrt(de ** 2 + np.where(ok, sin_i * np.nan_to_num(ae), 0.0) ** 2)

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")

    return {"stations": int(has.sum()), "drift_rms_deg": rms(de), "drift_max_abs_deg": float(np.max(np.abs(de))),
            "azimuth_rms_deg": rms(ae[ok]), "azimuth_max_abs_deg": float(np.max(np.abs(ae[ok]))) if ok.any() else float("nan"),
            "pointing_rms_deg": rms(pe)}


def _folds(data, k, seed=0):
    idx = np.flatnonzero((data.role == "val") & np.all(np.isfinite(data.ref), axis=1))
    if len(idx) < 2 * k:
        return []
    rng = np.random.default_rng(seed)
    perm = rng.permutation(idx)
    return [perm[i::k] for i in range(k)]


def cross_validate(model: LabModel, data, folds) -> dict:
    """Held-out angle errors: each fold predicted by a fit on everything else (warm-started)."""
    if not folds:
        return {}
    n = len(data)
    errs = {"drift": [], "azimuth": [], "pointing": []}
    for hold in folds:
        train = np.ones(n, bool)
        train[hold] = False
        m = copy.deepcopy(model)
        fit(m, data.subset(train), max_nfev=50, uncertainty=False)
        r = m.angle_errors(data.subset(hold))
        de, ae = r["drift_err"], r["azimuth_err"]
        sin_i = np.sin(np.radians(data.ref[hold, 0]))
        ok = np.isfinite(ae)
        errs["drift"].append(de)
        errs["azimuth"].append(ae[ok])
        errs["pointing"].append(np.sqrt(de ** 2 + np.where(ok, sin_i * np.nan_to_num(ae), 0.0) ** 2))
    cat = {k: np.concatenate(v) for k, v in errs.items()}
    return {"stations": int(len(cat["drift"])),
            "drift_rms_deg": float(np.sqrt(np.mean(cat["drift"] ** 2))),
            "azimuth_rms_deg": float(np.sqrt(np.mean(cat["azimuth"] ** 2))) if len(cat["azimuth"]) else float("nan"),
            "pointing_rms_deg": float(np.sqrt(np.mean(cat["pointing"] ** 2)))}


# ------------------------------------------------------------------------------------------------
def candidate_effects(model: LabModel, names=None):
    """(effect, scope) pairs to try: registered effects not in the model that static data can
    reveal, per sensor, default axes; a survey-only effect both on the survey and on all data."""
    have = {t.effect.key for t in model.terms}
    out = []
    for name, cls in sorted(fx.CATALOGUE.items()):
        if cls.base or cls.not_from_static or cls.stage == fx.PROBE_STAGE:
            continue
        if names is not None and name not in names:
            continue
        for sensor in cls.sensors:
            eff = cls(sensor=sensor, axes=cls.default_axes)
            if eff.key in have:
                continue
            for scope in (("val", "all") if cls.survey_only else ("all",)):
                out.append((eff, scope))
    return out


def untestable_effects() -> list:
    """The registered effects static data can never reveal, with each class's own reason."""
    return [{"effect": name, "reason": cls.not_from_static} for name, cls in sorted(fx.CATALOGUE.items())
            if cls.not_from_static]


def regressors(data, model: LabModel) -> dict:
    """Candidate explanatory variables per oriented station."""
    g_t, b_t = model.true_vectors(data)
    out = {"temperature": data.temp_c, "time": data.time_s,
           "survey log (val vs cal)": (data.role == "val").astype(float)}
    for s, v in (("acc", g_t), ("mag", b_t)):
        scale = np.nanmax(np.abs(v)) or 1.0
        for j, a in enumerate("xyz"):
            out[f"sign({s}_{a} input)"] = np.sign(v[:, j])
            out[f"{s}_{a} input²"] = (v[:, j] / scale) ** 2
            out[f"|{s}_{a} input|"] = np.abs(v[:, j] / scale)
    ref = data.ref
    if np.all(np.isfinite(ref)):
        i, a, t = (np.radians(ref[:, k]) for k in range(3))
        out.update({"sin(drift)": np.sin(i), "cos(drift)": np.cos(i), "sin(azimuth)": np.sin(a),
                    "cos(azimuth)": np.cos(a), "sin(toolface)": np.sin(t), "cos(toolface)": np.cos(t),
                    "sin(drift)·sin(azimuth)": np.sin(i) * np.sin(a),
                    "sin(drift)·cos(azimuth)": np.sin(i) * np.cos(a)})
    return out


def residual_structure(model: LabModel, data, alpha: float = 1e-3, top: int = 8) -> list:
    """F-tests of residual channels against each regressor; the significant ones, strongest first."""
    ori = data.oriented
    d = data.subset(ori)
    if len(d) < 8:
        return []
    g_t, b_t = model.true_vectors(d)
    h_g, h_b = model.forward(d, g_t, b_t)
    chans = {f"acc_{a} residual": ((d.g - h_g) / d.g_sigma)[:, j] for j, a in enumerate("xyz")}
    chans.update({f"mag_{a} residual": ((d.b - h_b) / d.b_sigma)[:, j] for j, a in enumerate("xyz")})
    has = np.all(np.isfinite(d.ref), axis=1)
    if has.sum() >= 8:
        r = model.angle_errors(d)
        chans["drift error"] = np.where(has, r["drift_err"], np.nan)
        chans["azimuth error"] = np.where(has, np.nan_to_num(r["azimuth_err"], nan=np.nan), np.nan)
    regs = regressors(d, model)
    n_tests = len(chans) * len(regs)
    found = []
    for cname, y in chans.items():
        for rname, x in regs.items():
            tr = regress(y, x)          # y = a + b x: the F-test the field monitor uses too
            if tr is None or tr.n < 8:
                continue
            if tr.p * n_tests < alpha:
                found.append({"channel": cname, "regressor": rname, "r2": tr.r2, "p": tr.p * n_tests,
                              "slope": float(tr.coef[0])})
    found.sort(key=lambda e: -e["r2"])
    # keep the strongest regressor per channel first, then the rest
    best, rest, seen = [], [], set()
    for e in found:
        (rest if e["channel"] in seen else best).append(e)
        seen.add(e["channel"])
    return (best + rest)[:top]


# ------------------------------------------------------------------------------------------------
def diagnose(data, model: LabModel | None = None, site=None, k_folds: int = 4, min_gain: float = 0.1,
             candidates=None, progress=None) -> Diagnosis:
    """Fit ``model`` (default: the paper's base), test its residuals, rank candidate effects."""
    say = progress or (lambda m: None)
    if model is None:
        model = LabModel.base(site)
    model = copy.deepcopy(model)
    say(f"fitting {model.describe()}")
    base_fit = fit(model, data)
    folds = _folds(data, k_folds)
    base_cv = cross_validate(model, data, folds) if folds else val_metrics(model, data)
    base_score = base_cv.get("pointing_rms_deg", float("nan"))
    structure = residual_structure(model, data)
    pairs = candidate_effects(model, candidates)
    untestable = untestable_effects()
    ranked = []
    def score(trial, name, sensor, axes, scope):
        f_all = fit(trial, data, uncertainty=False)
        cv = cross_validate(trial, data, folds) if folds else val_metrics(trial, data)
        sc = cv.get("pointing_rms_deg", float("nan"))
        gain = 1.0 - sc / base_score if base_score > 0 else 0.0
        dbic = f_all.bic() - base_fit.bic()
        ranked.append(Candidate(name, sensor, axes, scope, cv, sc, gain, dbic,
                                significant=bool(gain >= min_gain and dbic < -10.0), fit_all=f_all))

    for i, (eff, scope) in enumerate(pairs):
        trial = model.with_effect(eff, scope)
        hints = [h for h in physical_hints(trial, data) if h.parameter == eff.key]
        if hints:
            untestable.append({"effect": f"{eff.key}" + ("" if scope == "all" else f"@{scope}"),
                               "reason": hints[0].reason})
            continue
        say(f"candidate {i + 1}/{len(pairs)}: {eff.key}" + ("" if scope == "all" else f"@{scope}"))
        score(trial, eff.name, eff.sensor, eff.axes, scope)
    # Not a sensor effect but a frequent cause of a constant azimuth error: the stand's north (or
    # the declination used) differs from the site reference's.
    has_ref = np.any((data.kind == "ref"))
    if not model.fit_heading and has_ref and (candidates is None or HEADING in candidates):
        say("candidate: heading offset of the stand / declination")
        trial = copy.deepcopy(model)
        trial.fit_heading = True
        score(trial, HEADING, "site", "", "all")
    ranked.sort(key=lambda c: (not np.isfinite(c.score), c.score, c.delta_bic))
    misfit = base_fit.z_rms > Z_RMS_LIMIT
    best = ranked[0] if ranked and ranked[0].significant else None
    # Structure = something a regressor or a candidate explains.  Excess scatter that nothing
    # explains is reported (with its size as an equivalent stand pose error), not called structure.
    left = bool(best is not None or structure)
    scatter = orientation_scatter_deg(model, data) if misfit else None
    verdict = _verdict(model, base_fit, base_cv, structure, best, ranked, misfit, scatter)
    return Diagnosis(model, base_fit, base_cv, base_score, structure, ranked, untestable, left, verdict,
                     len(folds))


def orientation_scatter_deg(model: LabModel, data) -> dict:
    """Residual scatter beyond the sensor noise, as an equivalent random orientation error (deg rms).

    A random small rotation δθ of a station moves a measured vector v by v×δθ, i.e. by |v|·δθ in the
    two directions across v.  So σ_θ² ≈ (mean |r|² − mean |σ|²) / (2 |v|²), from each triad.
    """
    d = data.subset(data.oriented)
    if not len(d):
        return {}
    g_t, b_t = model.true_vectors(d)
    h_g, h_b = model.forward(d, g_t, b_t)
    out = {}
    for name, r, sig, mag in (("acc", d.g - h_g, d.g_sigma, model.site.gravity_mps2),
                              ("mag", d.b - h_b, d.b_sigma, model.site.total_field_nt)):
        excess = np.mean(np.sum(r ** 2, axis=1)) - np.mean(np.sum(sig ** 2, axis=1))
        out[name] = float(np.degrees(np.sqrt(max(excess, 0.0) / (2 * mag ** 2))))
    return out


def signature(candidate) -> str:
    """The residual signature of a candidate, as its effect class states it."""
    if candidate.effect == HEADING:
        return HEADING_SIGNATURE
    cls = fx.CATALOGUE.get(candidate.effect)
    return (cls.signature if cls is not None else "") or "the residual structure above"


def _verdict(model, base_fit, base_cv, structure, best, ranked, misfit, scatter=None) -> str:
    lines = [f"Model: {model.describe()}.",
             f"Fit: noise-normalised residual RMS {base_fit.z_rms:.2f} (1.0 = explained to the sensor noise)."]
    if base_cv:
        lines.append(f"Held-out validation error: drift RMS {base_cv.get('drift_rms_deg', float('nan')):.4f}°, "
                     f"azimuth RMS {base_cv.get('azimuth_rms_deg', float('nan')):.4f}°, pointing RMS "
                     f"{base_cv.get('pointing_rms_deg', float('nan')):.4f}°.")
    if structure:
        s = structure[0]
        lines.append(f"Strongest residual structure: {s['channel']} follows {s['regressor']} "
                     f"(R² {s['r2']:.2f}, p {s['p']:.1e}).")
    if best is not None:
        sig = signature(best)
        changes = []
        for key, name, digits in (("azimuth_rms_deg", "azimuth", 3), ("drift_rms_deg", "drift", 4)):
            before, after = base_cv.get(key, float("nan")), best.val.get(key, float("nan"))
            if np.isfinite(before) and np.isfinite(after) and abs(after - before) > 0.05 * before:
                changes.append(f"the held-out {name} RMS from {before:.{digits}f}° to {after:.{digits}f}°")
        lowers = " and ".join(changes) if changes else "the held-out pointing error"
        lines.append(f"Recommended next effect: {best.label} — consistent with {sig}; adding it lowers {lowers} "
                     f"(pointing error −{100 * best.gain:.0f} %, ΔBIC {best.delta_bic:.0f}).")
        if len(ranked) > 1:
            runner = ranked[1]
            lines.append(f"Runner-up: {runner.label} (pointing error −{100 * runner.gain:.0f} %).")
    elif structure:
        lines.append("Significant structure is left that no catalogue effect explains (no candidate lowers the "
                     "held-out error): " + "; ".join(f"{s['channel']} ~ {s['regressor']} (R² {s['r2']:.2f})"
                                                    for s in structure[:3])
                     + ". Consider a plug-in effect with that signature.")
    elif misfit:
        sc = scatter or {}
        lines.append("The model misfits the data beyond the sensor noise, but no regressor and no catalogue effect "
                     "explains it: the excess scatter is unstructured — consistent with random calibration-stand "
                     f"pose errors (stand_pose_error) of about {sc.get('acc', float('nan')):.3f}° (from the "
                     f"accelerometer) / {sc.get('mag', float('nan')):.3f}° (from the magnetometer) rms, or with "
                     "sensor noise larger than the scatter inside the static segments shows.")
    else:
        lines.append("No significant structure left: the model explains the data to the noise level.")
    return "\n".join(lines)


def ladder(data, site, max_steps: int = 4, k_folds: int = 4, progress=None, candidates=None, start=None):
    """Add the recommended effect repeatedly: the 'effect ladder' of falling validation error.

    Starts from ``start`` (default: the paper's base model); stops when no candidate is
    significant or after ``max_steps`` additions.
    """
    model = start if start is not None else LabModel.base(site)
    steps = []
    for _ in range(max_steps + 1):
        dg = diagnose(data, model, k_folds=k_folds, progress=progress, candidates=candidates)
        steps.append(dg)
        rec = dg.recommended
        if rec is None:
            break
        if rec.effect == HEADING:
            model = copy.deepcopy(dg.model)
            model.fit_heading = True
            continue
        eff = fx.CATALOGUE[rec.effect](sensor=rec.sensor, axes=rec.axes)
        model = copy.deepcopy(dg.model).with_effect(eff, rec.scope)
    return steps

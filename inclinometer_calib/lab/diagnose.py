"""Diagnosis: where does the model fail, which physical effect is missing, how much does it help?

1. **The field situation.**  Every model is fitted on what a rig has (:func:`field_fit`): the
   calibration log(s), and the survey's own QC invariants (|g|, |B|, dip against the site, as in
   multi-station analysis — how an effect acting on the survey alone, such as axial drill-string
   interference, can be fitted at all), never the validation log's reference angles.  The
   headline figures are the errors on the whole validation log (:func:`validation`); with no
   validation log they are in-sample figures on the calibration log, and say so.
2. **Residual structure.**  The model's noise-normalised residuals (per sensor axis, and the
   angle errors) are tested against candidate regressors (temperature, time, input sign and
   powers, orientation) with F-tests, Bonferroni-corrected.
3. **Candidates.**  Every catalogue (and plug-in) effect not yet in the model, per sensor, is
   added and fitted.  Its significance is a test against the measured noise, not a fixed gain: the
   Wald test of its parameters (``θᵀC⁻¹θ``, C the fit's covariance, scaled by the reduced χ² when
   the model misfits), Bonferroni-corrected over the candidates, and per axis the same test on
   that axis's parameters — the effect is named with the axes that carry it
   (``temperature_bias:mag:z``) and refitted on those.  Significant candidates rank by their field
   validation error (each judged out of sample alike), or by the Bayesian information criterion of
   the fit when there is no validation log.
4. **Confounding.**  Two significant effects that act on the same sensor axes, or change the
   model's predictions alike (their residual changes nearly parallel), are told apart by how well each fits: when one fits clearly
   better, it is ranked first and the other is named as explained by it; when neither does, the
   verdict says they are confounded and which experiment separates them (the classes say it,
   :attr:`effects.Effect.separated_by`).
5. **Verdict.**  Names the data left out (:attr:`station.Stations.losses`), refuses to rank when
   the data cannot identify the base model, recommends the best significant candidate that does
   not raise the field error, and never calls a strong, structured misfit unexplained when a
   candidate is significant.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from ..core import effects as fx
from ..core.specfun import chdtrc
from ..core.station import Stations
from ..calibrate.blas import one_thread
from ..calibrate.fit import fit, physical_hints, residual_groups
from ..calibrate.labmodel import N_POSES, POSES_LABEL, LabModel
from .noise import noise_json, noise_model, walk_axes
from ..calibrate.wander import penalty_total
from .stats import mean_above_zero_p, regress_many
from .uncertainty import noise_floor, normalised_errors

#: Family-wise false-alarm rate of a diagnosis (Bonferroni over the candidates tested).
ALPHA = 1e-3
Z_RMS_LIMIT = 1.3
#: Share of the calibration misfit beyond the noise an effect must explain when the calibration
#: misfits, for its evidence elsewhere (the survey's invariants) to count.
ABSORB = 0.1
#: One-sided p below which a candidate is taken to make the field errors worse.
WORSE = 0.01
#: Residual structure that explains less of a channel's variance than this is not called structure.
MATERIAL_R2 = 0.3
#: Notes that set a significant candidate aside (another explains its residuals, or a physical
#: candidate predicts held-out data as well as this proxy does).
SET_ASIDE = ("explained by", "not preferred")
#: Cross-validation folds (blocks of consecutive validation stations) of the held-out comparison
#: of a proxy (a drift in time) with a physical candidate.
HELD_OUT_FOLDS = 4
#: Residual changes of two effects this parallel (cosine) make the effects alternatives.
PARALLEL = 0.9
#: χ² (in units of the reduced χ²) by which one of two alternatives must fit better to be preferred:
#: a likelihood ratio of e^5 ≈ 150.
PREFER_CHI2 = 10.0
#: Pseudo-effect: a heading offset between the stand's north and the site reference's north.
HEADING = fx.HEADING_OFFSET
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
    delta_chi2: float
    delta_bic: float
    wald_chi2: float
    p: float                  # Bonferroni-adjusted p of the Wald test
    significant: bool
    axis_tests: list = field(default_factory=list)
    params: list = field(default_factory=list)
    transfers: bool = True
    p_field: float = float("nan")   # p that the field errors got worse (one-sided t-test), NaN: no reference
    note: str = ""
    fit_all: object = None
    residual: np.ndarray | None = field(default=None, repr=False)
    #: The effect as fitted (a stochastic one carries its density from the noise model).
    instance: object = field(default=None, repr=False)
    #: A stochastic effect (:attr:`effects.Effect.stochastic`): tested by likelihood ratio on its
    #: effective degrees of freedom, tried after the deterministic effects.
    stochastic: bool = False
    #: A significant stochastic effect that a deterministic one does not explain away, but which
    #: ranks after it (the ladder adds the deterministic one first).
    after: bool = False

    @property
    def label(self):
        if self.sensor in ("site", "probe"):
            return self.effect
        return f"{self.effect}:{self.sensor}:{self.axes}" + ("" if self.scope == "all" else f"@{self.scope}")

    def to_json(self):
        return {"effect": self.effect, "sensor": self.sensor, "axes": self.axes, "scope": self.scope,
                "label": self.label, "val": self.val, "score": self.score, "gain": self.gain,
                "delta_chi2": self.delta_chi2, "delta_bic": self.delta_bic, "wald_chi2": self.wald_chi2,
                "p": self.p, "significant": self.significant, "transfers": self.transfers,
                "p_field": self.p_field,
                "axis_tests": self.axis_tests, "parameters": self.params, "note": self.note,
                "test": "likelihood ratio on the effective degrees of freedom" if self.stochastic else "Wald"}


@dataclass
class Diagnosis:
    model: LabModel
    base_fit: object
    base_val: dict
    base_score: float
    structure: list
    ranked: list
    untestable: list
    #: What the diagnosis found, one of :data:`FINDINGS` (:func:`finding`): the verdict's words and
    #: the JSON's ``significant_structure_left`` both come from it.
    finding: str
    verdict: str
    losses: list = field(default_factory=list)
    confounded: list = field(default_factory=list)
    refused: str = ""
    notes: list = field(default_factory=list)
    #: Normalised validation errors of the model (:func:`uncertainty.normalised_errors`), and the
    #: noise floor of its figures (:func:`uncertainty.noise_floor`).
    uncertainty: dict = field(default_factory=dict)
    floor: dict = field(default_factory=dict)
    #: The noise model per sensor (:class:`allan.SensorNoise`): Allan deviation of the holds, the
    #: random walk across the stations (:func:`lab.noise.noise_model`).
    noise: dict = field(default_factory=dict)
    #: Formulas found beyond the catalogue (:func:`lab.discover.propose`), best first; and the
    #: stand-in they withheld from the recommendation (a proxy or a wander fitting such a term).
    discovered: list = field(default_factory=list)
    stand_in: str = ""
    #: The candidate recommended in the stand-in's place (a catalogue cause the search beyond the
    #: catalogue pointed to: a temperature effect whose sensor feels the temperature late), or "".
    preferred: str = ""
    #: A recommended temperature effect whose residuals follow a lagged temperature better
    #: (:func:`lab.discover.lag_check`): channel, tau_s and the two cross-validated R².
    lag: dict = field(default_factory=dict)

    @property
    def significant_structure_left(self) -> bool:
        """Structure the model leaves: an effect to add, a significant one not recommended, material
        residual structure outside the catalogue, or a misfit beyond the noise."""
        return self.finding not in ("explained", "refused")

    @property
    def recommended(self):
        if self.stand_in:      # what fits best only stands in: for a term outside the catalogue, or a cause
            return next((c for c in self.ranked if c.label == self.preferred), None) if self.preferred else None
        for c in self.ranked:
            if c.significant and c.transfers and not c.note.startswith(SET_ASIDE):
                return c
        return None

    @property
    def validation_kind(self) -> str:
        return self.base_val.get("kind", "")

    def to_json(self):
        return {"model": self.model.describe(),
                "base": {"val": self.base_val, "score": self.base_score, "z_rms": self.base_fit.z_rms,
                         "chi2": self.base_fit.chi2, "dof": self.base_fit.dof},
                "validation_kind": self.validation_kind,
                "ranked": [c.to_json() for c in self.ranked],
                "recommended": self.recommended.label if self.recommended else None,
                "significant_structure_left": bool(self.significant_structure_left), "finding": self.finding,
                "confounded": self.confounded, "refused": self.refused,
                "normalised_errors": self.uncertainty, "noise_floor": self.floor,
                "structure": self.structure, "untestable": self.untestable, "verdict": self.verdict,
                "losses": [x.to_json() for x in self.losses], "notes": self.notes,
                "noise_model": noise_json(self.noise), "discovered": [p.to_json() for p in self.discovered],
                "stand_in": self.stand_in, "lag": self.lag}


# ------------------------------------------------------------------------------------------------
# The field situation: fit on the calibration logs, validate on the whole survey log
# ------------------------------------------------------------------------------------------------
def fit_data(data: Stations) -> Stations:
    """What a fit may use: the calibration stations as they are, the validation (survey) stations
    as ``free`` ones — only their site invariants, never their reference angles."""
    d = data.subset(np.ones(len(data), bool))
    val = d.role == "val"
    d.kind = np.where(val, "free", d.kind)
    d.rotation = np.where(val[:, None, None], np.nan, d.rotation)
    d.prev_rotation = np.where(val[:, None, None], np.nan, d.prev_rotation)   # a history from the means
    return d


def field_fit(model: LabModel, data: Stations, uncertainty: bool = True, progress=None, max_nfev: int = 200,
              survey_invariants: bool = True, fixed=None, hint=None, give_hint: bool = False):
    """Fit ``model`` (in place) as for a survey; returns the :class:`fit.FitResult`.

    The fit sees what a rig has: the calibration stations, and (``survey_invariants``) the survey
    stations' |g|, |B| and dip against the site — never their reference angles
    (:func:`fit_data`).  With ``survey_invariants=False`` it sees the calibration logs only (an
    effect acting on the survey alone then stays at its prior, zero).  ``fixed``: parameters held,
    ``hint``: the base model's :class:`fit.JacobianHint`, ``give_hint``: keep this one's (:func:`fit.fit`)."""
    fd = fit_data(data)
    use = fd if survey_invariants or not (fd.role == "cal").any() else fd.subset(fd.role == "cal")
    return fit(model, use, progress=progress, max_nfev=max_nfev, uncertainty=uncertainty, fixed=fixed, hint=hint,
               give_hint=give_hint)


def validation(model: LabModel, data: Stations, survey_invariants: bool = True, pointing: bool = False):
    """The headline errors of a field-fitted model (:func:`field_fit`): drift, azimuth and pointing
    RMS on every validation station with a reference (a vertical one counts for drift; its azimuth
    is undefined), labelled ``kind``: ``field`` (the validation references were not fitted) or
    ``in-sample`` (no validation log: the calibration stations the model was fitted on).
    ``pointing``: also each of those stations' pointing error (deg, :func:`val_metrics`'s, from the
    same corrected angles; None in-sample): ``(figures, errors)``."""
    val = data.role == "val"
    has_val = val & np.isfinite(data.ref[:, 0])
    if has_val.any():
        out, pe = _val_metrics(model, data.subset(has_val))
        out["kind"] = "field"
        cal = "calibration log" + ("s" if _n_sources(data, "cal") > 1 else "")
        out["label"] = (f"field: fitted on the {cal}" + (" and the survey's |g|, |B|, dip" if survey_invariants else
                        " only") + f", errors on the whole validation log ({int(has_val.sum())} stations, its "
                        "reference angles never fitted)")
        return (out, pe) if pointing else out
    has = np.isfinite(data.ref[:, 0])
    out = val_metrics(model, data.subset(has)) if has.any() else {"stations": 0}
    out["kind"] = "in-sample"
    out["label"] = ("in-sample: no validation log — errors on the calibration stations the model was fitted on "
                    "(they understate the field error)")
    return (out, None) if pointing else out


def _n_sources(data, role):
    return len(set(data.source[data.role == role]))


def val_metrics(model: LabModel, data) -> dict:
    """Angle errors of the stations with a reference drift: drift RMS over all of them, azimuth
    and pointing (``sqrt(Δdrift² + (sin(drift)·Δazimuth)²)``) over those with a reference azimuth
    (deg); the counts of each."""
    return _val_metrics(model, data)[0]


def _val_metrics(model: LabModel, data) -> tuple:
    """:func:`val_metrics` and the per-station pointing errors its RMS is taken from."""
    has = np.isfinite(data.ref[:, 0])
    if not has.any():
        return {"stations": 0}, np.zeros(0)
    d = data.subset(has)
    r = model.angle_errors(d)
    de = r["drift_err"]
    ae = np.asarray(r["azimuth_err"], dtype=float)
    ok = np.isfinite(ae) & np.isfinite(d.ref[:, 1])
    sin_i = np.sin(np.radians(d.ref[:, 0]))
    pe = np.sqrt(de ** 2 + np.where(ok, sin_i * np.nan_to_num(ae), 0.0) ** 2)

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")

    return {"stations": int(has.sum()), "azimuth_stations": int(ok.sum()),
            "drift_rms_deg": rms(de), "drift_max_abs_deg": float(np.max(np.abs(de))),
            "azimuth_rms_deg": rms(ae[ok]), "azimuth_max_abs_deg": float(np.max(np.abs(ae[ok]))) if ok.any()
            else float("nan"), "pointing_rms_deg": rms(pe)}, pe


def blocked_folds(data, k):
    """K cross-validation folds of the validation stations with a reference, each a block of
    consecutive stations in time (a history-dependent effect keeps its neighbours)."""
    idx = np.flatnonzero((data.role == "val") & np.isfinite(data.ref[:, 0]))
    if len(idx) < 2 * k:
        return []
    idx = idx[np.argsort(data.time_s[idx], kind="stable")]
    return [b for b in np.array_split(idx, k) if len(b)]


def cross_validate(model: LabModel, data, folds) -> dict:
    """Cross-validated angle errors: each block of ``folds`` predicted by a fit on everything else
    (validation stations included with their references; warm-started).  Labelled as such."""
    if not folds:
        return {}
    n = len(data)
    parts = []
    for hold in folds:
        train = np.ones(n, bool)
        train[hold] = False
        m = copy.deepcopy(model)
        fit(m, data.subset(train), max_nfev=50, uncertainty=False)
        parts.append((m, hold))
    de, ae, pe = [], [], []
    for m, hold in parts:
        d = data.subset(hold)
        r = m.angle_errors(d)
        a = np.asarray(r["azimuth_err"], dtype=float)
        ok = np.isfinite(a) & np.isfinite(d.ref[:, 1])
        de.append(r["drift_err"])
        ae.append(a[ok])
        pe.append(np.sqrt(r["drift_err"] ** 2 + np.where(ok, np.sin(np.radians(d.ref[:, 0])) * np.nan_to_num(a), 0) ** 2))
    de, ae, pe = (np.concatenate(x) for x in (de, ae, pe))
    return {"stations": int(len(de)), "kind": "cross-validated",
            "label": f"cross-validated: {len(folds)} folds of consecutive validation stations, each predicted by a "
                     "fit on all other data",
            "drift_rms_deg": float(np.sqrt(np.mean(de ** 2))),
            "azimuth_rms_deg": float(np.sqrt(np.mean(ae ** 2))) if len(ae) else float("nan"),
            "pointing_rms_deg": float(np.sqrt(np.mean(pe ** 2)))}


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
            if any(k.split(":")[:2] == [name, sensor] for k in have):
                continue
            if cls.requires and not any(t.effect.sensor == sensor and cls.requires in type(t.effect).context_needs()
                                        and not isinstance(t.effect, cls) for t in model.terms):
                continue          # it would change nothing: the model has nothing of the sensor's it acts through
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
    # y = a + b x: the F-test the field monitor uses too, each regressor against every channel at once
    tested = {rname: dict(zip(chans, regress_many([(y, x) for y in chans.values()]))) for rname, x in regs.items()}
    found = []
    for cname in chans:
        for rname in regs:
            tr = tested[rname][cname]
            if tr is None or tr.n < 8:
                continue
            if tr.p * n_tests < alpha:
                found.append({"channel": cname, "regressor": rname, "r2": tr.r2, "p": min(tr.p * n_tests, 1.0),
                              "slope": float(tr.coef[0])})
    found.sort(key=lambda e: -e["r2"])
    # keep the strongest regressor per channel first, then the rest
    best, rest, seen = [], [], set()
    for e in found:
        (rest if e["channel"] in seen else best).append(e)
        seen.add(e["channel"])
    return (best + rest)[:top]


# ------------------------------------------------------------------------------------------------
def _base_unidentified(base_fit) -> list:
    base = {f"{n}:" for n in fx.BASE}
    return [n for n in base_fit.not_identifiable if any(n.parameter.startswith(b) for b in base)]


def _param_rows(fit_result, idx) -> list:
    return [{"name": fit_result.names[i], "value": float(fit_result.values[i]), "std": float(fit_result.std[i]),
             "ci95": [float(fit_result.values[i] - 1.96 * fit_result.std[i]),
                      float(fit_result.values[i] + 1.96 * fit_result.std[i])], "unit": fit_result.units[i]}
            for i in idx]


def _test_term(trial: LabModel, label: str, data, n_tests: int, hint=None):
    """Field-fit ``trial`` and test the term ``label``: (fit, Wald χ², adjusted p, per-axis tests).

    An effect's parameters that the data say nothing of until the effect is there
    (:attr:`effects.Effect.held_in_test`: a settling's time constant) are held at their start, and
    the test (and the per-axis tests) is of the others in that fit — held at its start, not tested
    against zero, and not made to share the others' evidence (with it free, a settling's share and
    its time constant trade off and neither alone looks significant); when they are significant the
    term is fitted again with all free for its values.  ``hint``: the base model's
    :class:`fit.JacobianHint` (the trial is the base with the term added, absent at its start)."""
    idx = trial.param_index(label)
    eff = next((t.effect for t in trial.probe.terms if t.label == label), None)
    held = np.zeros(len(trial.get_vector()), bool)
    if eff is not None and eff.held_in_test:       # the effect's vector: spec by spec, each over its axes
        per = eff.n_params // max(len(eff.specs), 1)
        for k, spec in enumerate(eff.specs):
            if spec.name in eff.held_in_test:
                held[idx[k * per:(k + 1) * per]] = True
    f = field_fit(trial, data, fixed=held if held.any() else None, hint=hint)
    if held.any():
        idx = idx[~held[idx]]
    axis_tests = []
    if label == POSES_LABEL:      # per pose the data have: its three angles
        have = sorted(set(int(q) for q in data.pose[(data.kind == "pose") & (data.pose >= 1)]))
        idx = np.concatenate([idx[3 * (q - 1):3 * q] for q in have])
        for q in have:
            c, _, pq = f.wald(trial.param_index(label)[3 * (q - 1):3 * q])
            axis_tests.append({"axis": f"pose {q}", "wald_chi2": c, "p": min(pq * n_tests * len(have), 1.0),
                               "significant": bool(pq * n_tests * len(have) < ALPHA)})
    chi2, _, p = f.wald(idx)
    if label not in (HEADING, POSES_LABEL):
        if eff.stage != fx.PROBE_STAGE and len(eff.axes) > 1 and eff.n_params % len(eff.axes) == 0 \
                and len(idx) >= len(eff.axes):          # per-axis parameters (not one for the sensor)
            n_ax = len(eff.axes)
            for j, a in enumerate(eff.axes):
                sub = idx[[k * n_ax + j for k in range(len(idx) // n_ax)]]
                c, _, pa = f.wald(sub)
                axis_tests.append({"axis": a, "wald_chi2": c, "p": min(pa * n_tests * n_ax, 1.0),
                                   "significant": bool(pa * n_tests * n_ax < ALPHA)})
    if held.any() and p * n_tests < ALPHA:
        f = field_fit(trial, data)          # there is an effect: its values with every parameter free
    return f, chi2, min(p * n_tests, 1.0), axis_tests


def _test_stochastic(trial: LabModel, label: str, data, n_tests: int, base_fit, noise):
    """Field-fit ``trial`` and test its stochastic term ``label`` (a wandering bias) by likelihood
    ratio: the fall of χ² from the model without it, over the larger reduced χ² of the two fits (the
    test against the measured noise), against χ² on the path's effective degrees of freedom.  Its
    axes are those on which the noise model resolves a random walk (3σ); per axis the noise
    model's own test is reported."""
    f = field_fit(trial, data)
    eff = next(t.effect for t in trial.probe.terms if t.label == label)
    red = max(f.reduced_chi2, base_fit.reduced_chi2, 1.0)
    chi2 = max(base_fit.chi2 - f.chi2, 0.0) / red
    p = float(chdtrc(max(float(np.sum(eff.edf)), 1e-9), chi2))
    axis_tests = []
    for a in eff.axes:
        k = noise[eff.sensor].terms["xyz".index(a)]["K"]
        pa = 0.5 * float(chdtrc(1, k.chi2)) if np.isfinite(k.chi2) else float("nan")   # one-sided: K ≥ 0
        axis_tests.append({"axis": a, "wald_chi2": k.chi2, "p": pa, "significant": bool(k.resolved),
                           "test": f"random walk resolved by the noise model ({k.source}, 3σ)"})
    return f, chi2, min(p * n_tests, 1.0), axis_tests


def _narrow(eff, axes: str):
    """The effect on fewer ``axes``: a deterministic one afresh (its values fitted again), a
    stochastic one with its densities of those axes."""
    if not eff.stochastic:
        return type(eff)(sensor=eff.sensor, axes=axes)
    pick = [eff.axes.index(a) for a in axes]
    return type(eff)(sensor=eff.sensor, axes=axes, values={s.name: eff.values[s.name][pick] for s in eff.specs})


def _stochastic_rows(trial: LabModel, label: str, noise) -> list:
    """The parameter rows of a stochastic term: its density per axis (from the noise model, with
    its 1σ) and the RMS of the fitted path."""
    eff = next(t.effect for t in trial.probe.terms if t.label == label)
    unit = eff.specs[0].unit[eff.sensor]
    rows = []
    for j, a in enumerate(eff.axes):
        k = noise[eff.sensor].terms["xyz".index(a)]["K"] if noise else None
        v = float(eff.values["density"][j])
        sd = float(k.std) if k is not None and k.resolved else float("nan")
        rows.append({"name": f"{eff.key}.density_{a}", "value": v, "std": sd,
                     "ci95": [v - 1.96 * sd, v + 1.96 * sd], "unit": unit,
                     "source": k.source if k is not None else ""})
        if len(eff.knots_s):
            rows.append({"name": f"{eff.key}.path_rms_{a}", "value": float(np.sqrt(np.mean(eff.path[:, j] ** 2))),
                         "std": float(np.sqrt(np.nanmean(eff.path_std[:, j] ** 2))), "ci95": [float("nan")] * 2,
                         "unit": unit.split("/")[0]})
    return rows


def _walk_untestable(eff, noise) -> dict:
    """Why a wander cannot be tried on ``eff.sensor``: the noise model resolves no random walk."""
    sn = noise[eff.sensor]
    ups = ", ".join(f"{a} < {t['K'].upper:.2g}" for a, t in zip("xyz", sn.terms) if np.isfinite(t["K"].upper))
    return {"effect": eff.key, "reason": f"the noise model resolves no random walk on the {eff.sensor} axes "
                                         f"(K {ups} {sn.unit}/√s, from the holds' Allan deviation and the station "
                                         "sequence): nothing to smooth"}


@one_thread
def diagnose(data, model: LabModel | None = None, site=None, candidates=None, progress=None,
             alpha: float | None = None, fitted=None) -> Diagnosis:
    """Field-fit ``model`` (default: the paper's base), test its residuals, rank candidate effects.
    ``fitted``: ``(copy of model, its field_fit(..., give_hint=True))`` when the caller has made that
    very fit (:func:`ladder`), taken instead of making it again."""
    a_level = ALPHA if alpha is None else alpha
    say = progress or (lambda m: None)
    if model is None:
        model = LabModel.base(site)
    say(f"fitting {model.describe()}")
    if fitted is not None:
        model, base_fit = fitted
    else:
        model = copy.deepcopy(model)
        base_fit = field_fit(model, data, give_hint=True)     # its Jacobian serves every candidate's first
    base_val, pe_base = validation(model, data, pointing=True)   # and the stations' pointing errors
    base_score = base_val.get("pointing_rms_deg", float("nan"))
    fd = fit_data(data)
    r_base = base_fit.residuals          # residual_vector(model, fd, prior=False) at its solution
    losses = list(data.losses)
    missing = _base_unidentified(base_fit)
    if missing:
        why = "; ".join(f"{n.parameter}: {n.reason}" for n in missing[:4])
        refused = (f"the data left cannot identify the base model ({len(missing)} parameter(s): {why}), so no effect "
                   "can be ranked — add poses (all twelve, both rounds) or stations with references")
        verdict = _verdict(model, base_fit, base_val, [], None, [], False, losses=losses, refused=refused)
        return Diagnosis(model, base_fit, base_val, base_score, [], [], untestable_effects(), "refused", verdict,
                         losses=losses, refused=refused)
    structure = residual_structure(model, data)
    noise = noise_model(model, data)
    pairs = candidate_effects(model, candidates)
    untestable = untestable_effects()
    heading = not model.fit_heading and np.any(data.kind == "ref") and (candidates is None or HEADING in candidates)
    trials = []
    for eff, scope in pairs:
        if eff.stochastic:      # its density from the noise model: the axes whose walk it resolves
            axes, k = walk_axes(noise[eff.sensor])
            if not axes:
                untestable.append(_walk_untestable(eff, noise))
                continue
            eff = _narrow(type(eff)(sensor=eff.sensor, values={"density": noise[eff.sensor].walk_density()}), axes)
        trial = model.with_effect(eff, scope)
        hints = [h for h in physical_hints(trial, data) if h.parameter == eff.key]
        if hints:
            untestable.append({"effect": f"{eff.key}" + ("" if scope == "all" else f"@{scope}"),
                               "reason": hints[0].reason})
            continue
        trials.append((trial, eff, scope))
    n_tests = max(len(trials) + int(bool(heading)), 1)
    ranked = []
    by_field = base_val.get("kind") == "field"
    groups = residual_groups(fd)
    cal_rows = np.char.startswith(groups.astype(str), "cal ") & np.isin(groups, ["cal acc", "cal mag"])
    cal_misfit = bool(cal_rows.any() and np.mean(r_base[cal_rows] ** 2) > Z_RMS_LIMIT ** 2)

    def score(trial, label, name, sensor, axes, scope):
        term = next((t for t in trial.probe.terms if t.label == label), None)
        stochastic = term is not None and term.effect.stochastic

        def test(tr, lb):
            return _test_stochastic(tr, lb, data, n_tests, base_fit, noise) if stochastic else \
                _test_term(tr, lb, data, n_tests, hint=base_fit.hint)

        f, wchi2, p, axis_tests = test(trial, label)
        if axis_tests and p < a_level and label not in (HEADING, POSES_LABEL):
            sig_axes = "".join(t["axis"] for t in axis_tests if t["significant"])
            if sig_axes and sig_axes != axes:     # name and refit the axes that carry the effect
                trial = model.with_effect(_narrow(term.effect, sig_axes), scope)
                label = trial.probe.terms[-1].label
                f, wchi2, p, _ = test(trial, label)
                axes = sig_axes
        val, pe = validation(trial, data, pointing=True)     # and the stations' pointing errors
        sc = val.get("pointing_rms_deg", float("nan"))
        gain = 1.0 - sc / base_score if base_score > 0 and np.isfinite(sc) else 0.0
        r = f.residuals           # the fit's at its solution (residual_vector(trial, fd, prior=False))
        transfers, p_field, why = True, float("nan"), ""
        # An effect whose evidence lies only in the survey's invariants, while the calibration
        # itself is not explained (its poses misfit beyond the noise, and the effect does not help
        # there), absorbs the misfit of a base model the stand has biased: not a finding.
        cal_before, cal_after = float(np.sum(r_base[cal_rows] ** 2)), float(np.sum(r[cal_rows] ** 2))
        if cal_misfit and cal_before - cal_after < ABSORB * (cal_before - cal_rows.sum()):
            transfers = False
            why = (f"the calibration poses misfit beyond the noise (residual RMS {np.sqrt(cal_before / cal_rows.sum()):.1f}) "
                   "and it does not explain them")
        if by_field:
            # and it must not make the field errors worse beyond their scatter (one-sided t-test of
            # the stations' squared pointing errors, candidate minus base)
            diff = pe ** 2 - pe_base ** 2
            p_field = mean_above_zero_p(diff) if np.any(diff != 0) else 1.0
            if p_field < WORSE:
                transfers = False
                why = why or f"it makes the field errors worse (p {p_field:.2g})"
        significant = bool(p < a_level)
        idx = trial.param_index(label)
        if label == POSES_LABEL:     # the poses that are off, each with its three angles
            off = [int(t["axis"].split()[1]) for t in axis_tests if t["significant"]]
            idx = np.concatenate([idx[3 * (q - 1):3 * q] for q in off]) if off else idx[:0]
            if significant and not off and transfers:
                # a worn stand holds some poses off; rotations that help only all together, none
                # on its own, absorb a misfit spread over the session (a wandering bias, a drift)
                transfers = False
                why = ("no pose is off on its own (each pose's rotation is within the noise): the rotations absorb a "
                       "misfit spread over all the poses, not a stand holding some off")
        instance = next((copy.deepcopy(t.effect) for t in trial.probe.terms if t.label == label), None)
        ranked.append(Candidate(name, sensor, axes, scope, val, sc, gain, base_fit.chi2 - f.chi2,
                                f.bic() - base_fit.bic(), wchi2, p, significant, axis_tests,
                                _stochastic_rows(trial, label, noise) if stochastic else _param_rows(f, idx),
                                transfers=transfers, p_field=p_field, fit_all=f, residual=r,
                                note="" if transfers else f"not recommended: {why}", instance=instance,
                                stochastic=stochastic))

    for i, (trial, eff, scope) in enumerate(trials):
        say(f"candidate {i + 1}/{len(trials)}: {eff.key}" + ("" if scope == "all" else f"@{scope}"))
        score(trial, trial.probe.terms[-1].label, eff.name, eff.sensor, eff.axes, scope)
    # Not a sensor effect but a frequent cause of a constant azimuth error: the stand's north (or
    # the declination used) differs from the site reference's.
    if heading:
        say("candidate: heading offset of the stand / declination")
        trial = copy.deepcopy(model)
        trial.fit_heading = True
        score(trial, HEADING, HEADING, "site", "", "all")
    # Significant candidates rank by the headline error when the data have a validation reference
    # (every candidate is then judged out of sample alike); else by the information criterion.

    def order(c):
        merit = (c.score if by_field and np.isfinite(c.score) else c.delta_bic) if c.significant else c.p
        return (not c.significant, not c.transfers, c.note.startswith(SET_ASIDE), c.after, merit)

    # The stand's systematic pose errors: the same pose off the same way in every round.
    repeated = np.bincount(data.pose[(data.kind == "pose") & (data.pose >= 1)], minlength=N_POSES + 1)
    if not model.fit_poses and repeated.max() >= 2 and (candidates is None or POSES_LABEL in candidates):
        say("candidate: the stand's pose errors")
        trial = copy.deepcopy(model)
        trial.fit_poses = True
        score(trial, POSES_LABEL, POSES_LABEL, "probe", "", "cal")
    ranked.sort(key=order)
    confounded = _confounding(ranked, r_base, data, say)
    _settle_stochastic(ranked, model, data, n_tests, say)
    ranked.sort(key=order)
    misfit = base_fit.z_rms > Z_RMS_LIMIT
    dg = Diagnosis(model, base_fit, base_val, base_score, structure, ranked, untestable, "explained", "",
                   losses=losses, confounded=confounded, noise=noise)
    ref = np.isfinite(data.ref[:, 0]) & ((data.role == "val") if by_field else True)
    if ref.any():
        dg.uncertainty = normalised_errors(model, base_fit, data.subset(ref))
        dg.floor = noise_floor(model, data.subset(ref))
    best = dg.recommended
    material = any(e["r2"] >= MATERIAL_R2 for e in structure)
    if (best is not None and (best.stochastic or _proxy(best))) or (best is None and (material or misfit)):
        # the catalogue names nothing, or only a stand-in: look for the term itself
        say("looking beyond the catalogue: sparse regression of the residuals on physical features")
        dg.discovered, why = _discover(model, data)
        if why:
            dg.notes.append(why)
        outside = [p for p in dg.discovered if p.outside and (best is None or p.channel.startswith(best.sensor))]
        lagged = [p for p in dg.discovered if not p.outside and fx.ThermalLag.name in p.catalogue.split(", ")
                  and (best is None or p.channel.startswith(best.sensor))]
        if best is not None and outside:
            dg.stand_in = best.label
            best.note = (f"not preferred: it stands in for a term outside the catalogue ({outside[0].formula()})")
            best = None
        elif lagged and best is not None:
            # the residuals follow a temperature felt late: the catalogue's temperature effect first (the
            # lag acts through it, the next round), never the stand-in
            # (set aside by nothing but the stand-in itself)
            warm = next((c for c in ranked if c.significant and c.transfers
                         and (not c.note.startswith(SET_ASIDE) or c.note.startswith(f"explained by {best.label}"))
                         and c.sensor == lagged[0].channel.split()[0] and c.effect in fx.CATALOGUE
                         and "temperature" in fx.CATALOGUE[c.effect].context_needs()), None)
            if warm is not None and warm is not best:
                dg.stand_in, dg.preferred = best.label, warm.label
                warm.note = ""
                best.note = ("not preferred: it stands in for a temperature the sensor feels late "
                             f"({lagged[0].formula()})")
                best = warm
    if best is not None and best.effect in fx.CATALOGUE and "temperature" in fx.CATALOGUE[best.effect].context_needs():
        # a temperature effect: does the sensor feel the thermometer's temperature late?
        from .discover import lag_check
        dg.lag = lag_check(data, model, best.sensor, best.axes) or {}
    dg.finding = finding(best, ranked, structure, misfit, outside=any(p.outside for p in dg.discovered))
    scatter = orientation_scatter_deg(model, data) if misfit else None
    dg.verdict = _verdict(model, base_fit, base_val, structure, best, ranked, misfit, scatter, losses=losses,
                          confounded=confounded, uncertainty=dg.uncertainty, noise=noise, found=dg.finding,
                          discovered=dg.discovered, stand_in=dg.stand_in, lag=dg.lag)
    return dg


def _discover(model, data) -> tuple:
    """``(proposals, note)``: :func:`lab.discover.propose`, or nothing and why (scikit-learn missing)."""
    from .discover import propose
    try:
        return propose(data, model), ""
    except ImportError:
        return [], ("the search beyond the catalogue was skipped: it needs scikit-learn "
                    "(pip install 'inclinometer_calib[lab]')")


def _proxy(c) -> str:
    """What candidate ``c``'s effect stands in for (:attr:`effects.Effect.proxy`), '' if it is a cause."""
    return getattr(fx.CATALOGUE.get(c.effect), "proxy", "")


def _confounding(ranked, r_base, data=None, say=None) -> list:
    """Pairs of significant candidates on the same sensor axes, or whose residual changes are nearly
    parallel: the one that fits clearly better explains the other; otherwise they are confounded.
    Marks the explained ones.

    A proxy (:attr:`effects.Effect.proxy`: a drift in time) that fits better than a physical
    candidate is preferred only if it also predicts held-out data better (blocked cross-validation
    of the validation stations with a reference, :func:`cross_validate`); otherwise the physical
    one is, and the two are said to be confounded.  Without such data nothing is held out: the
    physical candidate is preferred."""
    # a stochastic effect fits any slow misfit: it is weighed against the deterministic ones apart
    # (:func:`_settle_stochastic`), not named as explaining them by its flexibility
    sig = [c for c in ranked if c.significant and c.residual is not None and not c.stochastic]
    out = []
    held = {}
    folds = blocked_folds(data, HELD_OUT_FOLDS) if data is not None else []

    def held_out(c):
        if c.label not in held:
            if say:
                say(f"held-out blocks: {c.label}")
            held[c.label] = cross_validate(c.fit_all.model, data, folds).get("pointing_rms_deg", float("nan"))
        return held[c.label]

    for i, top in enumerate(sig):
        if top.note:
            continue
        dt = r_base - top.residual
        for other in sig[i + 1:]:
            if other.note or (other.effect, other.sensor) == (top.effect, top.sensor):
                continue
            do = r_base - other.residual
            cos = float(dt @ do / (np.linalg.norm(dt) * np.linalg.norm(do) + 1e-300))
            same_channels = top.sensor == other.sensor and bool(set(top.axes) & set(other.axes))
            if cos < PARALLEL and not same_channels:
                continue
            red = max(top.fit_all.reduced_chi2, 1.0)
            margin = (other.fit_all.chi2 - top.fit_all.chi2) / red
            sep = (fx.CATALOGUE[top.effect].separated_by if top.effect in fx.CATALOGUE else "") or \
                  (fx.CATALOGUE[other.effect].separated_by if other.effect in fx.CATALOGUE else "")
            entry = {"first": top.label, "second": other.label, "cosine": cos, "delta_chi2": margin,
                     "separated": bool(margin >= PREFER_CHI2), "experiment": sep}
            if margin >= PREFER_CHI2 and _proxy(top) and not _proxy(other):
                a, b = (held_out(top), held_out(other)) if folds else (float("nan"), float("nan"))
                entry["held_out_pointing_rms_deg"] = {top.label: a, other.label: b}
                if not (a < b):
                    # the drift in time fits the fitted data better but predicts no better: the
                    # physical candidate is preferred, the two are confounded
                    entry.update(first=other.label, second=top.label, separated=False, proxy=True)
                    out.append(entry)
                    why = (f"on held-out blocks of the survey it predicts no better (pointing RMS {a:.4f}° against "
                           f"{b:.4f}°)" if folds else "no held-out data can tell them apart")
                    top.note = (f"not preferred over {other.label}: it fits the fitted data better (Δχ² {margin:.0f}) "
                                f"but {why}; a drift in time stands for {_proxy(top)}")
                    other.note = other.note or f"confounded with {top.label}"
                    break
                entry["held_out"] = True
            out.append(entry)
            if margin >= PREFER_CHI2:
                other.note = f"explained by {top.label}: it fits the same residuals worse (Δχ² {margin:.0f})"
            else:
                other.note = f"confounded with {top.label} (Δχ² {margin:.1f}: the data fit both alike)"
                top.note = top.note or f"confounded with {other.label}"
    return out


def _settle_stochastic(ranked, model: LabModel, data, n_tests: int, say) -> None:
    """A significant wander against the best significant deterministic candidate ``D``.

    A random walk fits any slow misfit, so it is not preferred for its flexibility: with ``D`` in
    the model, the noise model is estimated again; if it resolves no walk, the wander is explained
    by ``D``.  Otherwise the wander is fitted on top, and if ``D`` is no longer significant (Wald,
    Bonferroni) ``D`` is explained by the wander; else both stay, the wander ranked after ``D``."""
    det = [c for c in ranked if c.significant and c.transfers and not c.stochastic and not c.note.startswith(SET_ASIDE)]
    with_d = {}        # the model with D, fitted, its noise model and held-out figure: the same for every wander
    for sc in [c for c in ranked if c.stochastic and c.significant and not c.note]:
        if not det:
            return
        d = det[0]
        if d.instance is None:           # the stand's heading or poses: fitted first, the wander after
            sc.after = True
            continue
        say(f"weighing {sc.label} against {d.label}")
        if not with_d:
            md = model.with_effect(copy.deepcopy(d.instance), d.scope)
            field_fit(md, data, uncertainty=False)
            with_d.update(md=md, noise=noise_model(md, data))
        md = with_d["md"]
        d_label = md.probe.terms[-1].label
        k = with_d["noise"][sc.sensor].walk_density()
        axes = "".join(a for a in sc.axes if k["xyz".index(a)] > 0)
        if not axes:
            sc.note = (f"explained by {d.label}: with it in the model the noise model resolves no random walk on "
                       f"{sc.sensor} {sc.axes}")
            continue
        wander = _narrow(type(sc.instance)(sensor=sc.sensor, values={"density": k}), axes)
        mds = md.with_effect(wander, sc.scope)
        f = field_fit(mds, data, uncertainty=False)
        ms = model.with_effect(copy.deepcopy(wander), sc.scope)
        fs = field_fit(ms, data, uncertainty=False)
        # D tested by likelihood ratio between the penalised fits with and without it (a Wald test
        # would take the covariance with the path held, and call D significant whatever the path
        # could absorb)
        red = max(f.reduced_chi2, 1.0)
        lr = max((fs.chi2 + penalty_total(ms)) - (f.chi2 + penalty_total(mds)), 0.0) / red
        p = float(chdtrc(len(mds.param_index(d_label)), lr))
        if p * n_tests > ALPHA:
            # a path absorbs any slow misfit: the wander explains D only if it also predicts
            # held-out blocks of the survey better than D does (else D first, the wander after it)
            folds = blocked_folds(data, HELD_OUT_FOLDS)
            a = cross_validate(ms, data, folds).get("pointing_rms_deg", float("nan")) if folds else float("nan")
            if "held_out" not in with_d:
                with_d["held_out"] = cross_validate(md, data, folds).get("pointing_rms_deg", float("nan")) \
                    if folds else float("nan")
            b = with_d["held_out"]
            if a < b:
                d.note = (f"explained by {sc.label}: no longer significant once the wander is fitted "
                          f"(likelihood ratio χ² {lr:.1f}, p {min(p * n_tests, 1.0):.2g}), and the wander predicts "
                          f"held-out blocks better (pointing RMS {a:.4f}° against {b:.4f}°)")
            else:
                sc.after = True
                d.note = d.note or (f"preferred to {sc.label}, which fits it away but predicts held-out blocks no "
                                    f"better (pointing RMS {a:.4f}° against {b:.4f}°)" if folds else
                                    f"preferred to {sc.label}, which fits it away: no held-out data can tell them apart")
        else:
            sc.after = True


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


def losses_text(losses) -> str:
    """One line per kind of loss: what was left out, how many, why."""
    if not losses:
        return ""
    by = {}
    for x in losses:
        by.setdefault(x.what, []).append(x)
    parts = []
    for what, xs in by.items():
        n = sum(x.count for x in xs)
        parts.append(f"{n} {what} ({'; '.join(str(x) for x in xs[:3])}{' …' if len(xs) > 3 else ''})")
    return "Left out of the data: " + "; ".join(parts) + "."


def noise_line(noise) -> str:
    """One line of the noise model: white noise per sensor, and the random walk where resolved."""
    parts = []
    for s, m in noise.items():
        n = [t["N"].value for t in m.terms if t["N"].resolved]
        if n:
            parts.append(f"{s} white noise N {np.mean(n):.3g} {m.unit}/√Hz")
        k = [(a, t["K"]) for a, t in zip("xyz", m.terms) if t["K"].resolved]
        if k:
            src = "station sequence" if all(t.source == "stations" for _, t in k) else "holds"
            parts.append(f"{s} random walk K " + ", ".join(f"{a} {t.value:.3g}±{t.std:.2g}" for a, t in k)
                         + f" {m.unit}/√s (from the {src})")
    segs = max((m.curve.n_segments for m in noise.values()), default=0)
    tau = max((float(m.curve.tau[-1]) for m in noise.values() if len(m.curve.tau)), default=float("nan"))
    if not segs or not np.isfinite(tau):
        # no Allan deviation to show: said why, not as "0 holds, τ up to nan s"
        return ("Noise model: no Allan deviation — the data hold no samples of the holds (a recorded run keeps the "
                "stations' means only); the noise is the stations' scatter" + (": " + "; ".join(parts) if parts else "")
                + ".")
    return (f"Noise model (Allan deviation of {segs} holds, τ up to {tau:.3g} s; IEEE figures in the JSON and report): "
            + ("; ".join(parts) or "nothing resolved") + ".")


#: What a diagnosis can find (:func:`finding`), the first that holds.
FINDINGS = ("refused", "recommended", "significant, not recommended", "outside the catalogue", "unstructured misfit",
            "explained")
#: Each finding in the words of a report's summary ({effect}: the recommended one; {refused}: why).
FINDING_SUMMARY = {"refused": "no effect could be ranked: {refused}",
                   "recommended": "a further effect is still recommended: {effect}",
                   "significant, not recommended": "a candidate is significant but not recommended: it absorbs a "
                                                   "misfit rather than explaining it",
                   "outside the catalogue": "structure is left that no catalogue effect explains (a plug-in effect "
                                            "may)",
                   "unstructured misfit": "a misfit beyond the sensor noise is left, without structure",
                   "explained": "the model explains the data to the noise"}


def finding(best, ranked, structure, misfit: bool, refused: str = "", outside: bool = False) -> str:
    """The one word for what a diagnosis found (:data:`FINDINGS`): refused (the base model cannot be
    identified), an effect recommended, a significant candidate not recommended (it absorbs a
    misfit), material residual structure no catalogue effect explains (R² ≥ :data:`MATERIAL_R2`), a
    misfit beyond the noise without structure, or the data explained to the noise."""
    if refused:
        return "refused"
    if best is not None:
        return "recommended"
    if outside or (any(e["r2"] >= MATERIAL_R2 for e in structure) and not any(c.significant for c in ranked)):
        return "outside the catalogue"
    if any(c.significant for c in ranked):
        return "significant, not recommended"
    if misfit:
        return "unstructured misfit"
    return "explained"


def _verdict(model, base_fit, base_val, structure, best, ranked, misfit, scatter=None, losses=(), confounded=(),
             refused="", uncertainty=None, noise=None, found=None, discovered=(), stand_in="", lag=None) -> str:
    found = found or finding(best, ranked, structure, misfit, refused)
    lines = [f"Model: {model.describe()}.",
             f"Fit: noise-normalised residual RMS {base_fit.z_rms:.2f} (1.0 = explained to the sensor noise)."]
    lost = losses_text(losses)
    if lost:
        lines.append(lost)
    if base_val.get("stations"):
        lines.append(f"Validation ({base_val.get('label', '')}): drift RMS {base_val.get('drift_rms_deg', float('nan')):.4f}°, "
                     f"azimuth RMS {base_val.get('azimuth_rms_deg', float('nan')):.4f}°, pointing RMS "
                     f"{base_val.get('pointing_rms_deg', float('nan')):.4f}°.")
    if uncertainty:
        parts = [f"{k} {v['rms']:.2f} ({100 * v['within_2']:.0f} % within 2σ)" for k, v in uncertainty.items()
                 if v.get("stations")]
        if parts:
            lines.append("Errors over their predicted 1σ (noise and the fit's covariance; RMS 1 = the uncertainty "
                         "holds): " + ", ".join(parts) + ".")
    if noise:
        lines.append(noise_line(noise))
    if refused:
        lines.append(f"No effect ranked: {refused}.")
        return "\n".join(lines)
    if structure:
        s = structure[0]
        lines.append(f"Strongest residual structure: {s['channel']} follows {s['regressor']} "
                     f"(R² {s['r2']:.2f}, p {s['p']:.1e})" + ("" if s["r2"] >= MATERIAL_R2 else
                                                             f": significant but slight (R² < {MATERIAL_R2:g}), not "
                                                             "structure the model must explain") + ".")
    word = "field" if base_val.get("kind") == "field" else "in-sample"
    if best is not None:
        sig = signature(best)
        changes = []
        for key, name, digits in (("azimuth_rms_deg", "azimuth", 4), ("drift_rms_deg", "drift", 4)):
            before, after = base_val.get(key, float("nan")), best.val.get(key, float("nan"))
            if np.isfinite(before) and np.isfinite(after) and abs(after - before) > 0.05 * before:
                changes.append(f"the {word} {name} RMS from {before:.{digits}f}° to {after:.{digits}f}°")
        effect_size = "; ".join(f"{p['name']} = {p['value']:.4g} ± {p['std']:.2g} {p['unit']}"
                                for p in best.params[:6]) or "see above"
        if best.effect == POSES_LABEL:
            off = [t["axis"] for t in best.axis_tests if t["significant"]]
            rows = {r["name"]: r for r in best.params}
            desc = []
            for t in off:
                q = int(t.split()[1])
                v = [rows[f"{POSES_LABEL}.r{a}_p{q}"] for a in "xyz"]
                desc.append(f"{t} by (" + ", ".join(f"{r['value']:+.3f}±{r['std']:.3f}" for r in v) + ")°")
            lines.append("The stand holds some poses off the same way in every round: " + "; ".join(desc)
                         + " (rotations about the tool x, y, z axes, against the poses that are right, which define "
                         "the tool frame). Check or re-seat the stand at those poses.")
        test = (f"likelihood ratio χ² {best.wald_chi2:.0f} on {best.instance.edf.sum():.0f} effective degrees of "
                "freedom" if best.stochastic else f"Wald χ² {best.wald_chi2:.0f}")
        lines.append(f"Recommended next effect: {best.label} — consistent with {sig}; significant against the noise "
                     f"({test}, p {best.p:.1e}, ΔBIC {best.delta_bic:.0f}): {effect_size}"
                     + (f"; adding it changes {' and '.join(changes)}" if changes else "") + ".")
        if lag:
            lines.append(f"The {lag['channel']} residuals follow the temperature felt {lag['tau_s']:g} s late better "
                         f"than the logged one (cross-validated R² {lag['cv_r2_lagged']:.2f} against "
                         f"{lag['cv_r2_logged']:.2f}): the sensor lags the thermometer. Fit {best.label} now and "
                         f"then {fx.ThermalLag.name}:{best.sensor} (its time constant, fitted with its 1σ).")
        if _proxy(best) and not any(c["first"] == best.label and c["separated"] for c in confounded):
            lines.append(f"A drift in time is not itself a cause: it stands for {_proxy(best)} — no physical "
                         "candidate of the catalogue explains these residuals as well.")
        for c in confounded:
            if c["first"] != best.label:
                continue
            if c.get("proxy"):
                ho = c["held_out_pointing_rms_deg"]
                lines.append(f"Confounded: {c['second']} fits the fitted data better (Δχ² {c['delta_chi2']:.0f}) but "
                             + (f"predicts held-out blocks of the survey no better (pointing RMS {ho[c['second']]:.4f}° "
                                f"against {ho[best.label]:.4f}°)" if np.isfinite(ho[best.label]) else
                                "no held-out data can tell them apart")
                             + f": {best.label} is the physical explanation recommended; a drift in time is not a "
                             f"cause. The experiment that separates them: {c['experiment']}.")
            elif c["separated"] and _proxy(best):
                lines.append(f"{c['second']} fits the same residuals alike in shape but clearly worse (Δχ² "
                             f"{c['delta_chi2']:.0f}), on held-out blocks too: the data prefer {best.label}; a drift in "
                             f"time is not itself a cause — it stands for {_proxy(best)}.")
            elif c["separated"]:
                lines.append(f"{c['second']} fits the same residuals alike in shape but clearly worse (Δχ² "
                             f"{c['delta_chi2']:.0f}): the data separate them, and {best.label} is the physical cause.")
            else:
                lines.append(f"Confounded: {best.label} and {c['second']} fit these data alike (Δχ² "
                             f"{c['delta_chi2']:.1f}); the data cannot tell them apart. The experiment that separates "
                             f"them: {c['experiment']}.")
        if stand_in:
            lines.append(f"{stand_in} fits these residuals better only as a stand-in (the search beyond the catalogue "
                         f"finds them following a temperature felt late) and is not recommended as their cause.")
        others = [c for c in ranked if c is not best and c.significant and not c.note]
        if others:
            lines.append("Also significant: " + ", ".join(f"{c.label} (ΔBIC {c.delta_bic:.0f})" for c in others[:3])
                         + ".")
    else:
        strong = [c for c in ranked if c.significant]
        outside = [p for p in discovered if p.outside]
        if outside:
            p = outside[0]
            lines.append(f"Outside the catalogue: {p.formula()} (cross-validated R² {p.cv_r2:.2f} over {p.stations} "
                         f"stations){'; ' + '; '.join(p.notes) if p.notes else ''}"
                         + (f". {stand_in} fits these residuals only as a stand-in and is not recommended as their "
                            "cause" if stand_in else "")
                         + ": write the term as a plug-in effect and fit it (lab fit --plugin).")
        elif strong:
            c = strong[0]
            lines.append(f"{c.label} is significant in the fitted data (Wald χ² {c.wald_chi2:.0f}, ΔBIC "
                         f"{c.delta_bic:.0f}; {word} pointing RMS {base_val.get('pointing_rms_deg', float('nan')):.4f}° "
                         f"→ {c.score:.4f}°) but {c.note.replace('not recommended: ', '')}: it absorbs a misfit rather "
                         "than explaining it (e.g. a base model biased by the stand) — not recommended.")
        material = [e for e in structure if e["r2"] >= MATERIAL_R2]
        if material and not strong and not outside:
            lines.append("Significant structure is left that no catalogue effect explains (no candidate is significant "
                         "against the noise): " + "; ".join(f"{s['channel']} ~ {s['regressor']} (R² {s['r2']:.2f})"
                                                          for s in material[:3])
                         + ". Consider a plug-in effect with that signature.")
        elif misfit and not outside:
            sc = scatter or {}
            lines.append(("Otherwise the" if strong else "The") + " model misfits the data beyond the sensor noise, but no "
                         "regressor and no catalogue effect explains it: the excess scatter is unstructured — consistent "
                         f"with random calibration-stand pose errors (stand_pose_error, different at every station) of about {sc.get('acc', float('nan')):.3f}° (from the accelerometer) / "
                         f"{sc.get('mag', float('nan')):.3f}° (from the magnetometer) rms, or with sensor noise "
                         "larger than the scatter inside the static segments shows.")
        elif found == "explained":
            lines.append("No significant structure left: the model explains the data to the noise level.")
    return "\n".join(lines)


@one_thread
def ladder(data, site, max_steps: int = 4, progress=None, candidates=None, start=None):
    """Add the recommended effect repeatedly: the 'effect ladder' of falling validation error.

    Starts from ``start`` (default: the paper's base model); stops when no candidate is
    significant or after ``max_steps`` additions.  After each addition, an earlier effect that the
    new one makes redundant (its Wald test no longer significant in the larger model) is removed,
    and the next rung's diagnosis says so in its notes.
    """
    model = start if start is not None else LabModel.base(site)
    steps = []
    notes = []
    fitted = None
    for _ in range(max_steps + 1):
        dg = diagnose(data, model, progress=progress, candidates=candidates, fitted=fitted)
        fitted = None
        dg.notes = notes + dg.notes
        steps.append(dg)
        rec = dg.recommended
        if rec is None:
            break
        if rec.effect in fx.MODEL_OPTIONS:     # the stand's heading or pose errors: options of the fit
            model = dg.model.with_named(rec.effect)
            new_label = rec.effect
        else:
            eff = copy.deepcopy(rec.instance) if rec.instance is not None else \
                fx.CATALOGUE[rec.effect](sensor=rec.sensor, axes=rec.axes)
            model = copy.deepcopy(dg.model).with_effect(eff, rec.scope)
            new_label = model.probe.terms[-1].label
        notes = []
        # (a wander has no parameters for a Wald test; it is tried after the deterministic effects)
        earlier = [t.label for t in model.extra_terms if t.label != new_label and not t.effect.stochastic]
        if earlier:
            # the next rung's base fit (give_hint: as diagnose makes it), which it takes when no
            # effect is removed
            fm = copy.deepcopy(model)
            f = field_fit(fm, data, give_hint=True)
            fitted = (fm, f)
            for label in earlier:
                _, _, p = f.wald(model.param_index(label))
                if p * len(earlier) > ALPHA:
                    model = model.without(label)
                    fitted = None
                    notes.append(f"removed {label}: made redundant by {new_label} (its parameters are no longer "
                                 f"significant with {new_label} in the model, p {min(p * len(earlier), 1):.2f})")
    return steps

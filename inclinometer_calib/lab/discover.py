"""Discovery beyond the catalogue: the missing term of a model as a formula over physical features.

When the catalogue's candidates leave structure the lab cannot name — or only a proxy or a
wandering bias explains it — each residual channel of the oriented stations (a sensor axis,
measured minus predicted, in the sensor's unit) is regressed on physical features of the
stations, sparsely and cross-validated:

* the temperature, its rate, and the temperature a sensor *feels* through a first-order lag of
  time constant τ (15–480 s), ``τ·dT_s/dt = T − T_s``, exact for the temperature taken as linear
  between the stations of the session;
* the time (a drift), the change of input since the previous hold (a remanence, a settling), and
  the input's square and sign (nonlinearity, asymmetry).

The selection is scikit-learn's orthogonal matching pursuit with blocked cross-validation (the
folds are blocks of consecutive stations, so a slow process is not predicted from its neighbours),
then ordinary least squares on the features chosen gives each coefficient and its 1σ.  A feature
that a catalogue effect already models (the temperature: ``temperature_bias``) names that effect;
one it does not (a lagged temperature, the temperature's rate, the change since the previous
hold) is said to be **outside the catalogue**, with its formula.  The time is a proxy (:attr:`effects.Effect.proxy`)
and is never proposed as the cause.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core import effects as fx

#: Time constants (s) of the lagged temperatures tried.
LAGS_S = (15.0, 30.0, 60.0, 120.0, 240.0, 480.0)
#: Most features in one proposed term.
MAX_FEATURES = 2
#: Blocks of consecutive stations for the cross-validation.
FOLDS = 5
#: A channel is explained only when the cross-validated R² reaches this.
MIN_CV_R2 = 0.5
#: A second feature joins a term only if it raises the cross-validated R² by this much.
MIN_GAIN_R2 = 0.05
#: Family-wise significance of a coefficient (Bonferroni over channels and features).
ALPHA = 1e-3



def catalogue_features() -> tuple:
    """``(modelled, proxies)``: feature → the catalogue effect that models it
    (:attr:`effects.Effect.discovery_features`), and the features whose effect is a proxy
    (:attr:`effects.Effect.proxy`: they stand in for causes and are never proposed as one)."""
    modelled, proxies = {}, set()
    for name, cls in fx.CATALOGUE.items():
        for f in cls.discovery_features:     # a feature, or a family of them (``lag``: :func:`_family`)
            modelled.setdefault(f, name)
            if cls.proxy:
                proxies.add(f)
    return modelled, proxies


@dataclass
class Term:
    """One feature of a proposed formula: ``coef ± std`` (channel unit per feature unit)."""

    feature: str
    unit: str
    coef: float
    std: float
    lag_s: float = math.nan


@dataclass
class Proposal:
    """The formula found for one residual channel."""

    channel: str
    unit: str
    terms: list
    cv_r2: float
    stations: int
    outside: bool             # a feature no catalogue effect models
    catalogue: str = ""       # the catalogue effect the features name, when not outside
    notes: list = field(default_factory=list)

    def formula(self) -> str:
        parts = [f"({t.coef:+.4g} ± {t.std:.2g} {self.unit}/{t.unit})·{t.feature}" for t in self.terms]
        return f"{self.channel} residual ≈ " + " + ".join(parts) + " + const"

    def to_json(self) -> dict:
        return {"channel": self.channel, "unit": self.unit, "formula": self.formula(), "cv_r2": self.cv_r2,
                "stations": self.stations, "outside_catalogue": self.outside, "catalogue": self.catalogue,
                "terms": [{"feature": t.feature, "unit": t.unit, "coef": t.coef, "std": t.std,
                           **({"lag_s": t.lag_s} if np.isfinite(t.lag_s) else {})} for t in self.terms]}


def rate(time_s, temp_c) -> np.ndarray:
    """dT/dt (°C/s) at each station, by central differences over the stations in time order."""
    order = np.argsort(time_s, kind="stable")
    t, T = np.asarray(time_s, float)[order], np.asarray(temp_c, float)[order]
    r = np.gradient(T, t) if len(t) > 2 else np.zeros_like(T)
    out = np.empty_like(r)
    out[order] = r
    return out


def residual_channels(data, model):
    """The oriented stations of ``data`` in time order and, per channel (``"mag z"`` …), the
    sensor's true input on it and its residual — measured minus ``model``'s prediction, in the
    sensor's unit: ``(stations, {channel: (sensor, axis, input (N,), residual (N,))})``; None
    with fewer stations than the blocked cross-validation needs."""
    d = data.subset(data.oriented)
    if len(d) < 4 * FOLDS:
        return None
    d = d.subset(np.argsort(d.time_s, kind="stable"))
    g_t, b_t = model.true_vectors(d)
    h_g, h_b = model.forward(d, g_t, b_t)
    out = {}
    for sensor, meas, pred, v in (("acc", d.g, h_g, g_t), ("mag", d.b, h_b, b_t)):
        for j, a in enumerate("xyz"):
            y = meas[:, j] - pred[:, j]
            if np.all(np.isfinite(y)) and np.std(y) > 0:
                out[f"{sensor} {a}"] = (sensor, j, v[:, j], y)
    return d, out


def features(data, sensor: str, axis: int, v) -> dict:
    """name → (values (N,), unit, lag s) for the stations ``data`` of one channel (``v`` the
    sensor's true input on that axis)."""
    unit = "m/s²" if sensor == "acc" else "nT"
    out = {}
    temp = data.temp_c
    if np.all(np.isfinite(temp)) and np.ptp(temp) > 0:
        out["temperature"] = (temp, "°C", math.nan)
        out["temperature rate"] = (rate(data.time_s, temp), "°C/s", math.nan)
        for tau in LAGS_S:
            out[f"temperature felt {tau:g} s late"] = (fx.felt_temperature(data.time_s, temp, tau), "°C", tau)
    out["time"] = (data.time_s / 3600.0, "h", math.nan)
    prev = data.prev_g if sensor == "acc" else data.prev_b
    if prev is not None and np.all(np.isfinite(prev[:, axis])):
        out["change of input since the previous hold"] = (prev[:, axis] - v, unit, math.nan)
    scale = float(np.nanmax(np.abs(v))) or 1.0
    out["input²"] = ((v / scale) ** 2, "(full scale)²", math.nan)
    out["sign(input)"] = (np.sign(v), "1", math.nan)
    return out


def _blocks(n: int, k: int):
    idx = np.arange(n)
    return [(np.setdiff1d(idx, b), b) for b in np.array_split(idx, k) if len(b)]


def _family(name: str) -> str:
    if name.startswith("temperature felt") or name == "temperature rate":
        return "lag"
    return name


def propose(data, model, min_cv_r2: float = MIN_CV_R2) -> list:
    """The formulas found for the residual channels of ``model`` on the oriented stations of
    ``data`` (:class:`Proposal`, best cross-validated R² first; channels without one are left
    out).  Needs scikit-learn (the lab's extra)."""
    from scipy.stats import t as student
    from sklearn.linear_model import OrthogonalMatchingPursuitCV   # here: 1.3 s of import

    found = residual_channels(data, model)
    if found is None:
        return []
    d, channels = found
    out = []
    n_channels = 6
    modelled, proxies = catalogue_features()
    for channel, (sensor, j, v, y) in channels.items():
        unit = "m/s²" if sensor == "acc" else "nT"
        feats = features(d, sensor, j, v)
        names = [k for k, (x, _, _) in feats.items() if np.all(np.isfinite(x)) and np.std(x) > 0]
        if not names:
            continue
        X = np.column_stack([feats[k][0] for k in names])
        mu, sd = X.mean(axis=0), X.std(axis=0)
        Z = (X - mu) / sd
        yc = y - y.mean()
        omp = OrthogonalMatchingPursuitCV(cv=_blocks(len(y), FOLDS), max_iter=min(MAX_FEATURES, len(names)),
                                          fit_intercept=True)
        try:
            omp.fit(Z, yc)
        except ValueError:
            continue
        chosen = [k for k, c in zip(names, omp.coef_) if c != 0]
        # one family at a time: a lag and the temperature's rate say the same thing
        seen, keep = set(), []
        for k in sorted(chosen, key=lambda k: -abs(omp.coef_[names.index(k)])):
            if _family(k) not in seen:
                seen.add(_family(k))
                keep.append(k)
        if not keep:
            continue
        # a further feature only where it predicts held-out blocks clearly better
        cv = _cv_r2(np.column_stack([feats[keep[0]][0]]), y)
        for k in keep[1:]:
            more = _cv_r2(np.column_stack([feats[q][0] for q in keep[:keep.index(k)] + [k]]), y)
            if more < cv + MIN_GAIN_R2:
                keep = keep[:keep.index(k)]
                break
            cv = more
        if not cv >= min_cv_r2:
            continue
        A = np.column_stack([np.ones(len(y))] + [feats[k][0] for k in keep])
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        resid = y - A @ coef
        dof = max(len(y) - A.shape[1], 1)
        s2 = float(resid @ resid) / dof
        cov = s2 * np.linalg.pinv(A.T @ A)
        std = np.sqrt(np.maximum(np.diag(cov), 0.0))
        terms, notes = [], []
        for i, k in enumerate(keep, start=1):
            p = 2.0 * float(student.sf(abs(coef[i] / std[i]), dof)) if std[i] > 0 else 1.0
            if p * n_channels * len(names) > ALPHA:
                continue
            terms.append(Term(k, feats[k][1], float(coef[i]), float(std[i]), feats[k][2]))
        if not terms:
            continue
        kinds = {_family(t.feature) for t in terms}
        cat = [modelled.get(_family(t.feature), "") for t in terms if t.feature not in proxies]
        outside = any(_family(t.feature) not in modelled for t in terms)
        if any(t.feature in proxies for t in terms):
            notes.append("a drift in time is not itself a cause: it stands for whatever follows time")
        if "lag" in kinds:
            notes.append("the sensor feels the logged temperature late: a temperature effect with a time "
                         f"constant ({fx.ThermalLag.name} with the temperature effect)")
        out.append(Proposal(channel, unit, terms, float(cv), len(y), outside,
                            catalogue="" if outside else ", ".join(sorted({c for c in cat if c})), notes=notes))
    out.sort(key=lambda p: -p.cv_r2)
    return out


def lag_check(data, model, sensor: str, axes: str):
    """Whether the residuals of ``sensor``'s ``axes`` on the oriented stations follow the temperature
    felt through a first-order lag better than the logged one (cross-validated, blocks of
    consecutive stations; least squares only, no scikit-learn): ``{channel, tau_s, cv_r2_lagged,
    cv_r2_logged}`` of the clearest such channel (by :data:`MIN_GAIN_R2`), else None."""
    found = residual_channels(data, model)
    if found is None:
        return None
    d, channels = found
    if not (np.all(np.isfinite(d.temp_c)) and np.ptp(d.temp_c) > 0):
        return None
    best = None
    for a in axes:
        if f"{sensor} {a}" not in channels:
            continue
        y = channels[f"{sensor} {a}"][3]
        plain = _cv_r2(d.temp_c[:, None], y)
        for tau in LAGS_S:
            cv = _cv_r2(fx.felt_temperature(d.time_s, d.temp_c, tau)[:, None], y)
            if cv >= max(plain + MIN_GAIN_R2, MIN_CV_R2) and (
                    best is None or cv - plain > best["cv_r2_lagged"] - best["cv_r2_logged"]):
                best = {"channel": f"{sensor} {a}", "tau_s": tau, "cv_r2_lagged": cv, "cv_r2_logged": plain}
    return best


def _cv_r2(X, y) -> float:
    """Blocked cross-validated R² of ordinary least squares of ``y`` on ``X`` (with intercept)."""
    sse = sst = 0.0
    for train, test in _blocks(len(y), FOLDS):
        A = np.column_stack([np.ones(len(train)), X[train]])
        coef, *_ = np.linalg.lstsq(A, y[train], rcond=None)
        pred = np.column_stack([np.ones(len(test)), X[test]]) @ coef
        sse += float(np.sum((y[test] - pred) ** 2))
        sst += float(np.sum((y[test] - y[train].mean()) ** 2))
    return 1.0 - sse / sst if sst > 0 else float("nan")


#: How each feature of :func:`features` reads in a plug-in effect's ``_apply`` (``v`` the sensor's
#: true input, ``i`` the channel's axis, ``ctx`` the :class:`effects.Context`), and what it needs.
_FEATURE_CODE = {
    "temperature": ("(ctx.temperature_c - fx.T_REF_C)", ("temperature",)),
    "temperature rate": ("fx.over_sequence(ctx, rate)", ("temperature", "time", "history")),
    "time": ("ctx.time_s / 3600.0", ("time",)),
    "change of input since the previous hold": ("np.nan_to_num(PREVIOUS(ctx)[:, i] - v[:, i])", ("history",)),
    "input²": ("(v[:, i] / FULL_SCALE) ** 2", ()),
    "sign(input)": ("np.sign(v[:, i])", ()),
}


def plugin_name(proposal: Proposal) -> str:
    """The effect name a proposal's plug-in registers: ``discovered_mag_z``."""
    return "discovered_" + proposal.channel.replace(" ", "_")


def plugin_source(proposal: Proposal, where: str = "") -> str:
    """A plug-in module (Python source) with the proposal's formula as an effect the lab fits
    (``lab fit --plugin FILE --effects NAME``): one output term on the channel's axis, a parameter
    per feature (its value the proposal's coefficient, typical size its 1σ or the coefficient),
    readable and editable — the user owns it.  ``where``: what data it was found on (said in the
    docstring)."""
    sensor, axis = proposal.channel.split()
    name = plugin_name(proposal)
    specs, lines, needs = [], [], []
    unit_out = "m/s^2" if sensor == "acc" else "nT"
    for k, t in enumerate(proposal.terms, start=1):
        if t.feature.startswith("temperature felt"):
            code, need = f"(fx.over_sequence(ctx, lambda t, T: fx.felt_temperature(t, T, {t.lag_s:g})) - fx.T_REF_C)", \
                ("temperature", "time", "history")
        elif t.feature in _FEATURE_CODE:
            code, need = _FEATURE_CODE[t.feature]
        else:
            raise ValueError(f"no plug-in code for the feature {t.feature!r}")
        needs += [n for n in need if n not in needs]
        typical = max(abs(t.coef), t.std, 1e-12)
        specs.append(f'        fx.ParamSpec("k{k}", {{"{sensor}": "{unit_out}/({t.unit})"}}, {{"{sensor}": {typical:.6g}}},\n'
                     f'                     "coefficient of {t.feature} (found: {t.coef:.6g} ± {t.std:.2g})"),')
        lines.append(f'        v[:, i] += self.values["k{k}"][0] * {code}')
    full_scale = 9.80665 if sensor == "acc" else 50000.0
    return f'''"""A term outside the catalogue, found by `inclinometer-calib lab diagnose`{(" on " + where) if where else ""}:

    {proposal.formula()}
    (cross-validated R² {proposal.cv_r2:.2f} over {proposal.stations} stations)

Written as a plug-in effect to read, edit and fit:

    inclinometer-calib lab fit --cal CAL.csv --val VAL.csv --plugin THIS_FILE.py --effects {name}

Its parameters start at zero (the fit finds them; the values found are in the specs' docs); the
features are the lab's own (:mod:`inclinometer_calib.lab.discover`), evaluated on the stations the
effect acts on.  A record written with it names this file and its SHA-256: a changed file is refused
until it is named again.
"""
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from inclinometer_calib.core import effects as fx
from inclinometer_calib.lab.discover import rate  # noqa: F401  (a feature may use it)

FULL_SCALE = {full_scale!r}   # {unit_out}: the scale of the input² feature


def PREVIOUS(ctx):
    """The previous hold's true input of the sensor (the station sequence)."""
    return ctx.history.previous_{"g" if sensor == "acc" else "b"}


@dataclass
class Discovered(fx.Effect):
    """{proposal.formula()}"""

    name: ClassVar[str] = "{name}"
    sensors: ClassVar[tuple] = ("{sensor}",)
    default_axes: ClassVar[str] = "{axis}"
    stage: ClassVar[str] = "output"
    needs: ClassVar[tuple] = {tuple(needs)!r}
    signature: ClassVar[str] = "residuals following {", ".join(t.feature for t in proposal.terms)}"
    specs: ClassVar[tuple] = (
{chr(10).join(specs)}
    )

    def _apply(self, v, ctx):
        i = fx.AXIS_INDEX[self.axes[0]]
{chr(10).join(lines)}
'''

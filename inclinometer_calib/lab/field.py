"""The field monitor: does the applied model still explain the survey?  The lab's diagnosis, live.

In the field there is usually no reference attitude, but every station's corrected |G|, |B| and
dip can be compared with the site reference (their differences ΔG, ΔB, Δdip are the survey's QC
residuals).  A correct model leaves them as scatter; a missing effect leaves a trend that follows
what the effect follows.  Over the last ``window`` stations the monitor tests, for each residual
channel (ΔG, ΔB, Δdip):

* **trends** against temperature, time and orientation (sin/cos of drift, azimuth and toolface,
  sin(drift)·sin/cos(azimuth)) — the lab's regression F-test (:func:`stats.regress`);
* **candidate effects** — every effect the lab would try (:func:`diagnose.candidate_effects`:
  catalogue and plug-ins, metadata on the classes) whose span condition the window meets
  (:meth:`effects.Effect.identifiability`): its signature on the three invariants, the
  derivative of the corrected |G|, |B| and dip with respect to its parameters through the
  package's correction path (:meth:`model.ProbeModel.correct`) at the window's raw stations, is
  regressed on the residuals.  The candidate that explains most (summed R² over the channels it
  significantly explains) is the likely missing effect, with its parameters' estimate.

A finding counts when it is significant (p below ``alpha``, Bonferroni-corrected over all tests)
**and** material: the part it explains has an RMS of at least ``materiality`` × the channel's QC
tolerance (a trend of 3 nT over a window is real but does not matter).  Then the verdict is a
misfit, said in words: which residual follows what, and the likely missing effect with what it
would take to fit it.  The window starts again whenever another record is applied.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from ..core import effects as fx
from ..core.frames import angles_from_vectors, rotate
from ..core.survey import Tolerances
from .stats import regress, regress_channels

#: The residual channels: (field of a SurveyStation, name in words, unit, tolerance attribute).
CHANNELS = (("delta_g_mps2", "ΔG", "m/s²", "gravity_mps2"), ("delta_b_nt", "ΔB", "nT", "field_nt"),
            ("delta_dip_deg", "Δdip", "°", "dip_deg"))


#: Where a verdict's text names the likely missing effect (:func:`headline` reads it back).
MISSING_EFFECT = ". Likely missing effect: "


@dataclass
class Verdict:
    """The monitor's verdict after a station: ``misfit`` and the text saying it (empty while the
    model explains the data); ``trends`` and ``candidates``: what was found (dicts, strongest first)."""

    misfit: bool = False
    text: str = ""
    trends: list = field(default_factory=list)
    candidates: list = field(default_factory=list)
    stations: int = 0


class FieldMonitor:
    """Tests the latest stations' residuals against the site for what a missing effect leaves.

    ``window``: stations kept; ``min_stations``: none tested before; ``alpha``: the family-wise
    significance; ``materiality``: the smallest explained RMS that counts, as a fraction of each
    channel's tolerance (``tolerances``)."""

    def __init__(self, window: int = 30, min_stations: int = 12, alpha: float = 1e-3, materiality: float = 0.1,
                 tolerances: Tolerances = Tolerances()):
        if window < min_stations:
            min_stations = window
        self.window = int(window)
        self.min_stations = max(int(min_stations), 6)
        self.alpha = float(alpha)
        self.materiality = float(materiality)
        self.tolerances = tolerances
        self.calibration = None
        self._rows = collections.deque(maxlen=self.window)
        self.last = Verdict()

    def reset(self, calibration) -> None:
        """Another record applies from now on: the window starts again."""
        self.calibration = calibration
        self._rows.clear()
        self.last = Verdict()

    def add(self, st, fields: dict, g, b) -> Verdict:
        """One processed station (its raw means in ``st``, its message fields, its corrected vectors
        ``g``, ``b``).  Stations that moved, or whose residuals are not finite, are not used."""
        deltas = [fields[c[0]] for c in CHANNELS]
        if not st.moved and all(map(math.isfinite, deltas)):
            self._rows.append({"g_raw": np.asarray(st.g, float), "b_raw": np.asarray(st.b, float),
                               "temp": float(st.temp_c), "time": float(st.time_s), "deltas": deltas,
                               "g": np.asarray(g, float), "b": np.asarray(b, float)})
        if len(self._rows) >= self.min_stations:
            self.last = self.check()
        else:
            self.last = Verdict(stations=len(self._rows))
        return self.last

    # ---- the tests -------------------------------------------------------------------------------
    def check(self) -> Verdict:
        rows = list(self._rows)
        n = len(rows)
        y = {c[0]: np.array([r["deltas"][k] for r in rows]) for k, c in enumerate(CHANNELS)}
        regs = self._regressors(rows)
        cands = self._candidates(rows)
        n_tests = len(CHANNELS) * (len(regs) + len(cands)) or 1
        # each regressor against the three channels at once (its SVD shared: regress_channels)
        tested = {rname: dict(zip(y, regress_channels(list(y.values()), x))) for rname, x in regs.items()}
        trends = []
        for key, name, unit, tol_attr in CHANNELS:
            floor = self.materiality * getattr(self.tolerances, tol_attr)
            for rname in regs:
                tr = tested[rname][key]
                if tr is not None and tr.p * n_tests < self.alpha and tr.explained_rms >= floor:
                    trends.append({"channel": name, "regressor": rname, "r2": tr.r2, "p": tr.p * n_tests,
                                   "explained_rms": tr.explained_rms, "unit": unit})
        trends.sort(key=lambda e: -e["r2"])
        found = []
        for eff, cols in cands:
            chans, score, sigma = [], 0.0, {}
            for key, name, unit, tol_attr in CHANNELS:
                tr = regress(y[key], cols[key])
                floor = self.materiality * getattr(self.tolerances, tol_attr)
                if tr is not None:
                    sigma[key] = max(tr.residual_rms, 1e-3 * getattr(self.tolerances, tol_attr))
                if tr is not None and tr.p * n_tests < self.alpha and tr.explained_rms >= floor:
                    chans.append({"channel": name, "r2": tr.r2, "p": tr.p * n_tests, "explained_rms": tr.explained_rms,
                                  "unit": unit})
                    score += tr.r2
            if chans:
                found.append({"effect": eff.key, "label": eff.key, "score": score, "channels": chans,
                              "estimate": [float(v) for v in _joint_estimate(y, cols, sigma)],
                              "units": eff.param_units(), "names": eff.param_names(), "cls": type(eff)})
        found.sort(key=lambda e: -e["score"])
        misfit = bool(trends or found)
        return Verdict(misfit=misfit, text=self._text(n, trends, found) if misfit else "", trends=trends,
                       candidates=[{k: v for k, v in f.items() if k != "cls"} for f in found], stations=n)

    def _regressors(self, rows) -> dict:
        temp = np.array([r["temp"] for r in rows])
        time = np.array([r["time"] for r in rows])
        ang = angles_from_vectors(np.array([r["g"] for r in rows]), np.array([r["b"] for r in rows]))
        i, a, t = (np.radians(ang[k]) for k in ("drift_deg", "azimuth_deg", "gravity_toolface_deg"))
        out = {}
        if np.all(np.isfinite(temp)) and np.ptp(temp) >= fx.MIN_SPAN["temperature"][0]:
            out["temperature"] = temp
        if np.ptp(time) >= fx.MIN_SPAN["time"][0]:
            out["time"] = time
        out.update({"cos(drift)": np.cos(i), "sin(azimuth)·sin(drift)": np.sin(i) * np.sin(a),
                    "cos(azimuth)·sin(drift)": np.sin(i) * np.cos(a), "sin(toolface)": np.sin(t),
                    "cos(toolface)": np.cos(t)})
        return out

    def _candidates(self, rows) -> list:
        """(effect, {channel: (N, k) signature}) for each candidate the window can test.

        The signature of parameter j: what adding the effect at its typical size does to the
        corrected |G|, |B| and dip, per unit of the parameter — to first order, the change of the
        model's output at the corrected vectors, taken back through the base correction matrix
        (a Newton step of :meth:`model.ProbeModel.correct`, which is what the full correction
        would add up to for an effect this small)."""
        from .diagnose import candidate_effects
        from ..calibrate.labmodel import LabModel

        cal = self.calibration
        if cal is None or "history" in cal.needs:
            # a model that depends on the sequence of holds (a settling) cannot be evaluated on the
            # window's rows, which keep no hold timing: its trends are still tested, no candidate
            return []
        x = {"acc": np.array([r["g"] for r in rows]), "mag": np.array([r["b"] for r in rows])}
        temp = np.array([r["temp"] for r in rows])
        time = np.array([r["time"] for r in rows])
        known_t = bool(np.all(np.isfinite(temp)))
        ctx = fx.Context(temperature_c=temp if known_t else np.full(len(rows), fx.T_REF_C), time_s=time)
        t_span = float(np.ptp(temp)) if known_t else 0.0
        norms = {s: np.linalg.norm(x[s], axis=1) for s in ("acc", "mag")}
        base_inv = _invariants(x["acc"], x["mag"], norms["acc"], norms["mag"])
        base_out = {s: fx.apply_chain(x[s], cal.model.chain(s, "val"), ctx) for s in ("acc", "mag")}
        # the record's chain up to a candidate's stage, the same for each of its parameters and for
        # every candidate of that sensor and stage: applied once (apply_chain stage by stage, the
        # same operations on the same numbers) — unless an effect changes the context the chain
        # sees (a thermal lag), which then depends on the candidate's parameters
        before = {}

        def chained(chain, sensor, stage):
            if any(type(e).chain_context is not fx.Effect.chain_context for e in chain):
                return fx.apply_chain(x[sensor], chain, ctx)
            k = fx.STAGES.index(stage)
            if (sensor, stage) not in before:
                before[sensor, stage] = fx.apply_chain(x[sensor], chain, ctx, stages=fx.STAGES[:k], prepared=True)
            return fx.apply_chain(before[sensor, stage], chain, ctx, stages=fx.STAGES[k:], prepared=True)

        out = []
        seen = set()
        for eff, _ in candidate_effects(LabModel(site=cal.site, probe=cal.model)):
            if eff.key in seen or eff.identifiability(t_span, float(np.ptp(time)), frozenset({"free"})):
                continue
            if "history" in type(eff).context_needs():   # the window's rows carry no station sequence
                continue
            seen.add(eff.key)
            term = eff                     # a fresh effect of the lab's list, its parameters zero
            sensor = term.sensor
            chain = cal.model.chain(sensor, "val") + [term]   # apply_chain orders by stage
            mt = cal.plan.matrix_t[sensor]
            typ = np.where(term.param_typical() > 0, term.param_typical(), 1.0)
            cols = {c[0]: np.empty((len(rows), term.n_params)) for c in CHANNELS}
            for j in range(term.n_params):
                v = np.zeros(term.n_params)
                v[j] = typ[j]
                term.set_vector(v)
                dx = -rotate(mt, chained(chain, sensor, term.stage) - base_out[sensor])
                inv = (_invariants(x["acc"] + dx, x["mag"], bn=norms["mag"]) if sensor == "acc" else
                       _invariants(x["acc"], x["mag"] + dx, gn=norms["acc"]))
                for k, c in enumerate(CHANNELS):
                    cols[c[0]][:, j] = (inv[k] - base_inv[k]) / typ[j]
            term.set_vector(np.zeros(term.n_params))
            out.append((term, cols))
        return out

    def _text(self, n, trends, found) -> str:
        cal = self.calibration
        head = (f"the model of record {cal.id if cal is not None else '(none)'} no longer explains the survey: over "
                f"the last {n} stations ")
        parts = []
        shown = set()
        for t in trends[:3]:
            key = (t["channel"], t["regressor"])
            if key in shown:
                continue
            shown.add(key)
            parts.append(f"{t['channel']} follows {t['regressor']} (R² {t['r2']:.2f}, ±{_fmt(t['explained_rms'])} "
                         f"{t['unit']})")
        if not parts and found:   # no plain trend: the residuals follow the candidate's signature
            parts = [f"{c['channel']} follows the signature of {found[0]['label']} (R² {c['r2']:.2f}, "
                     f"±{_fmt(c['explained_rms'])} {c['unit']})" for c in found[0]["channels"]]
        text = head + ("; ".join(parts) if parts else "the residuals against the site have structure")
        if found:
            best = found[0]
            cls = best["cls"]
            follows = " and ".join(cls.field_regressors) or "the data"
            est = ", ".join(f"{n.split('.')[-1]} {_fmt(v)} {u}" for n, v, u in
                            zip(best["names"], best["estimate"], best["units"]))
            chans = ", ".join(f"{c['channel']} (R² {c['r2']:.2f})" for c in best["channels"])
            text += (f"{MISSING_EFFECT}{best['label']} — {cls.summary().rstrip('.')} (its residuals follow "
                     f"{follows}; it explains {chans}; estimated {est}). Fit it in the lab "
                     f"(inclinometer-calib lab fit --effects {cls.name}:{best['label'].split(':')[1]} -o model.yaml) "
                     "and apply that record")
            if len(found) > 1:
                text += f"; runner-up {found[1]['label']}"
        else:
            text += ". No catalogue effect explains it: a plug-in effect, or interference"
        return text + "."


def headline(text: str) -> str:
    """The verdict's text (:meth:`FieldMonitor._text`, a station's ``model_diagnosis``) cut to what a
    summary says: that the model no longer explains the survey, and the likely missing effect."""
    head = text.split(": over the last", 1)[0]
    if MISSING_EFFECT in text:
        head += "; likely missing: " + text.split(MISSING_EFFECT, 1)[1].split(" ", 1)[0]
    return head


def _joint_estimate(y, cols, sigma):
    """The candidate's parameters from all channels at once: weighted least squares of the stacked
    residuals (each channel over its own scatter, with its own offset) on the stacked signatures.
    The signature is what adding the effect to the model does to the corrected invariants, so the
    model needs the parameters that cancel the residuals: minus the regression coefficients."""
    keys = [k for k in sigma if k in cols]
    n = len(next(iter(y.values())))
    k = cols[keys[0]].shape[1]
    rows, rhs = [], []
    for j, key in enumerate(keys):
        off = np.zeros((n, len(keys)))
        off[:, j] = 1.0
        rows.append(np.hstack([cols[key], off]) / sigma[key])
        rhs.append(y[key] / sigma[key])
    a, b = np.vstack(rows), np.concatenate(rhs)
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(b)
    coef, *_ = np.linalg.lstsq(a[ok], b[ok], rcond=None)
    return -coef[:k]


def _invariants(g, b, gn=None, bn=None):
    """|g| (m/s²), |B| (nT) and dip (deg) of corrected vectors (N, 3) — the order of CHANNELS
    (``gn``, ``bn``: the norms of ``g``, ``b`` when the caller has them)."""
    gn = np.linalg.norm(g, axis=1) if gn is None else gn
    bn = np.linalg.norm(b, axis=1) if bn is None else bn
    dip = np.degrees(np.arcsin(np.clip(np.sum(g * b, axis=1) / (gn * bn), -1.0, 1.0)))
    return gn, bn, dip


def _fmt(v) -> str:
    return f"{v:.3g}"

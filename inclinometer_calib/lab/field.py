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
from ..core.formulas import dip_of
from ..core.frames import angles_from_vectors, rotate
from ..core.survey import Tolerances
from .stats import regress_many

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
        self._effects = None                # (record, catalogue, its candidate effects): _candidate_effects
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
        # every test of the window at once (regress_many: each one's figures as alone), in the order
        # they are read below: per channel each regressor, then per candidate each channel
        fits = iter(regress_many([(y[c[0]], x) for c in CHANNELS for x in regs.values()]
                                 + [(y[c[0]], cols[c[0]]) for _, cols in cands for c in CHANNELS]))
        trends = []
        for key, name, unit, tol_attr in CHANNELS:
            floor = self.materiality * getattr(self.tolerances, tol_attr)
            for rname in regs:
                tr = next(fits)
                # material first: a trend too small to matter needs no p-value (Trend.p: computed when read)
                if tr is not None and tr.explained_rms >= floor and tr.p * n_tests < self.alpha:
                    trends.append({"channel": name, "regressor": rname, "r2": tr.r2, "p": tr.p * n_tests,
                                   "explained_rms": tr.explained_rms, "unit": unit})
        trends.sort(key=lambda e: -e["r2"])
        found = []
        for eff, cols in cands:
            chans, score, sigma = [], 0.0, {}
            for key, name, unit, tol_attr in CHANNELS:
                tr = next(fits)
                floor = self.materiality * getattr(self.tolerances, tol_attr)
                if tr is not None:
                    sigma[key] = max(tr.residual_rms, 1e-3 * getattr(self.tolerances, tol_attr))
                if tr is not None and tr.explained_rms >= floor and tr.p * n_tests < self.alpha:
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
        would add up to for an effect this small).

        The arithmetic is that of ``apply_chain(x, chain + [effect])`` per parameter, then
        :func:`frames.rotate` and :func:`_invariants`, element by element; it is only arranged
        for fewer numpy calls: the record's chain is applied once, stage by stage, and an effect
        starts from its stage's output (the effects of the stages before, and of its own stage
        before it in the chain, are the record's); the parameters of all candidates go through
        the rotation and the invariants in one stacked array (elementwise operations: the same
        bits as one at a time)."""
        cal = self.calibration
        if cal is None or "history" in cal.needs:
            # a model that depends on the sequence of holds (a settling) cannot be evaluated on the
            # window's rows, which keep no hold timing: its trends are still tested, no candidate
            return []
        x = {"acc": np.array([r["g"] for r in rows]), "mag": np.array([r["b"] for r in rows])}
        n = len(rows)
        temp = np.array([r["temp"] for r in rows])
        time = np.array([r["time"] for r in rows])
        known_t = bool(np.all(np.isfinite(temp)))
        ctx = fx.Context(temperature_c=temp if known_t else np.full(n, fx.T_REF_C), time_s=time)
        t_span = float(np.ptp(temp)) if known_t else 0.0
        time_span = float(np.ptp(time))
        base_inv = _invariants(x["acc"], x["mag"])
        chains = {s: cal.model.chain(s, "val") for s in ("acc", "mag")}
        pctx = {s: fx.chain_context(chains[s], ctx) for s in chains}
        after = {}                           # sensor -> the record's output after each stage
        for s, chain in chains.items():
            v, after[s] = x[s], []
            for stage in fx.STAGES:
                v = fx.apply_chain(v, chain, pctx[s], stages=(stage,), prepared=True)
                after[s].append(v)
        base_out = {s: after[s][-1] for s in chains}
        terms, diffs, typs = [], {"acc": [], "mag": []}, {"acc": [], "mag": []}
        for term in self._candidate_effects():
            if term.identifiability(t_span, time_span, frozenset({"free"})):
                continue
            sensor = term.sensor
            chain = chains[sensor]
            typ = np.where(term.param_typical() > 0, term.param_typical(), 1.0)
            own_context = type(term).chain_context is not fx.Effect.chain_context
            for j in range(term.n_params):
                v = np.zeros(term.n_params)
                v[j] = typ[j]
                term.set_vector(v)
                if own_context or term.stage not in fx.STAGES:   # it changes what the others see
                    out = fx.apply_chain(x[sensor], chain + [term], ctx)   # apply_chain orders by stage
                else:
                    i = fx.STAGES.index(term.stage)
                    out = fx.apply_chain(term.apply(after[sensor][i], pctx[sensor]), chain, pctx[sensor],
                                         stages=fx.STAGES[i + 1:], prepared=True)
                diffs[sensor].append(out - base_out[sensor])
            typs[sensor].append(typ)
            term.set_vector(np.zeros(term.n_params))
            terms.append(term)
        # every parameter's change of the corrected vectors, then of the invariants, stacked
        inv = {}
        for sensor, d in diffs.items():
            if not d:
                continue
            m = len(d)
            dx = -rotate(cal.plan.matrix_t[sensor], np.concatenate(d))
            g = np.tile(x["acc"], (m, 1))
            b = np.tile(x["mag"], (m, 1))
            if sensor == "acc":
                g += dx
            else:
                b += dx
            typ = np.concatenate(typs[sensor])[:, None]
            inv[sensor] = [((v.reshape(m, n) - base_inv[k]) / typ) for k, v in enumerate(_invariants(g, b))]
        out, used = [], {"acc": 0, "mag": 0}
        for term in terms:
            j0, j1 = used[term.sensor], used[term.sensor] + term.n_params
            used[term.sensor] = j1
            out.append((term, {c[0]: np.ascontiguousarray(inv[term.sensor][k][j0:j1].T) if j1 > j0
                               else np.empty((n, 0)) for k, c in enumerate(CHANNELS)}))
        return out

    def _candidate_effects(self) -> list:
        """The effects the lab would try on the record in force (:func:`diagnose.candidate_effects`),
        one per key, without those that need the hold sequence (the window's rows carry none):
        made once per record, their parameters zero between checks."""
        cal = self.calibration
        catalogue = tuple(fx.CATALOGUE.items())          # a plug-in registered since: made again
        if self._effects is None or self._effects[0] is not cal or self._effects[1] != catalogue:
            from ..calibrate.labmodel import LabModel
            from .diagnose import candidate_effects

            effects, seen = [], set()
            for eff, _ in candidate_effects(LabModel(site=cal.site, probe=cal.model)):
                if eff.key in seen or "history" in type(eff).context_needs():
                    continue
                seen.add(eff.key)
                effects.append(eff)
            self._effects = (cal, catalogue, effects)
        return self._effects[2]

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


def _invariants(g, b):
    """|g| (m/s²), |B| (nT) and dip (deg) of corrected vectors (N, 3) — the order of CHANNELS."""
    gn = np.linalg.norm(g, axis=1)
    bn = np.linalg.norm(b, axis=1)
    dip = dip_of(np.sum(g * b, axis=1), gn, bn)
    return gn, bn, dip


def _fmt(v) -> str:
    return f"{v:.3g}"

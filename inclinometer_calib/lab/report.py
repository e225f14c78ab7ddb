"""One self-contained HTML report of a model-lab run (plots embedded as PNG data URIs).

Sections: first a summary in words and a small table (:func:`summary`), then the full verdict —
the diagnosis text (with the data left out); the effect ladder (the field validation
error after each added effect, as each rung's diagnosis labels it); the noise model (Allan
deviation per axis and its IEEE figures); residuals of the base and final models against orientation, temperature and time; the
paper-style before/after tables (Tables 4 and 5 layout); the fitted parameters with uncertainties.
"""
from __future__ import annotations

import base64
import html
import io

import numpy as np

from ..core.deps import require


def figure_png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def pyplot():
    matplotlib = require("matplotlib", "report", "lab report")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


_PLAIN_LOG_FORMATTER = None


def plain_log_ticks(axis) -> None:
    """The tick labels of a log-scaled ``axis`` (``ax.xaxis``, ``ax.yaxis``) as plain numbers —
    0.02, 3e-05, 10 — where matplotlib writes math text (2×10⁻², 3×10⁻⁵, 10¹): the same ticks, and
    the same choice of the minor ones that carry a label (:class:`matplotlib.ticker.LogFormatter`'s).
    Why: every math-text label is a parse by pyparsing, measured at a quarter of ``reprocess
    --compare``'s CPU time with its one log axis."""
    global _PLAIN_LOG_FORMATTER
    if _PLAIN_LOG_FORMATTER is None:
        from matplotlib.ticker import LogFormatter

        class PlainLogFormatter(LogFormatter):
            def _num_to_string(self, x, vmin, vmax):
                return f"{x:g}"

        _PLAIN_LOG_FORMATTER = PlainLogFormatter
    axis.set_major_formatter(_PLAIN_LOG_FORMATTER(labelOnlyBase=False))
    axis.set_minor_formatter(_PLAIN_LOG_FORMATTER(labelOnlyBase=False))


def ladder_figure(steps, uncorrected: dict) -> str:
    """Validation error after each rung, on a linear scale from the paper's base model down, with
    the noise floor (what a perfect model would still show) drawn; the uncorrected error is
    written in the title (on this scale it would flatten everything else)."""
    plt = pyplot()
    labels = ["base (paper)"] + ["+ " + s.recommended.label for s in steps[:-1] if s.recommended]
    labels = labels[:len(steps)]
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    x = np.arange(len(steps))
    for a, key, t in ((ax[0], "drift_rms_deg", "drift RMS (deg)"), (ax[1], "azimuth_rms_deg", "azimuth RMS (deg)")):
        y = [s.base_val.get(key, np.nan) for s in steps]
        a.plot(x, y, "o-", color="#1f5fa8", label="model")
        floor = steps[-1].floor.get(key, np.nan) if steps[-1].floor else np.nan
        if np.isfinite(floor):
            a.axhline(floor, color="#b5452a", ls="--", lw=1, label=f"noise floor {floor:.3g}°")
        a.set_ylim(0, max(np.nanmax(y) if np.isfinite(np.nanmax(y)) else 1, floor if np.isfinite(floor) else 0) * 1.15)
        a.set_xticks(x)
        a.set_xticklabels(labels, rotation=25, ha="right", fontsize=8)
        unc = uncorrected.get(key, float("nan"))
        a.set_title(f"{t} — uncorrected " + (f"{unc:.3g}°" if np.isfinite(unc) else "not known"), fontsize=10)
        a.grid(True, alpha=0.3)
        a.legend(fontsize=8)
        for xi, yi in zip(x, y):
            a.annotate(f"{yi:.3g}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    fig.suptitle(f"Effect ladder — {steps[0].base_val.get('label', 'validation')}", fontsize=10)
    fig.tight_layout()
    return figure_png(fig)


def sensor_drift_figure(steps, data) -> str:
    """Each triad's residual (measured minus model, oriented stations) against temperature and
    time, for the base and the final model: what a temperature or time effect leaves."""
    plt = pyplot()
    d = data.subset(data.oriented)
    fig, axs = plt.subplots(2, 2, figsize=(12, 6.5))
    for col, (model, name) in enumerate(((steps[0].model, "base"), (steps[-1].model, "final"))):
        g_t, b_t = model.true_vectors(d)
        h_g, h_b = model.forward(d, g_t, b_t)
        for row, (x, xl) in enumerate(((d.temp_c, "temperature (°C)"), (d.time_s / 60.0, "time (min)"))):
            a = axs[row, col]
            for j, c in enumerate(("#1f5fa8", "#b5452a", "#3a7d44")):
                a.scatter(x, (d.b - h_b)[:, j], s=8, color=c, label=f"mag {'xyz'[j]} (nT)")
            a2 = a.twinx()
            for j, c in enumerate(("#1f5fa8", "#b5452a", "#3a7d44")):
                a2.scatter(x, 1e3 * (d.g - h_g)[:, j], s=8, marker="x", color=c, alpha=0.6)
            a.set_xlabel(xl)
            a.set_ylabel("magnetometer residual (nT, dots)")
            a2.set_ylabel("accelerometer residual (mm/s², crosses)")
            a.set_title(f"{name} model: residual vs {xl.split(' ')[0]}", fontsize=10)
            a.grid(alpha=0.3)
            if row == 0 and col == 0:
                a.legend(fontsize=7)
    fig.tight_layout()
    return figure_png(fig)


def residual_figure(model, data, title) -> str:
    plt = pyplot()
    has = np.all(np.isfinite(data.ref), axis=1)
    d = data.subset(has)
    r = model.angle_errors(d)
    fig, axs = plt.subplots(2, 3, figsize=(13, 6.5))
    items = [("drift_err", "drift error (deg)"), ("azimuth_err", "azimuth error (deg)")]
    for row, (key, lab) in enumerate(items):
        y = r[key]
        axs[row, 0].scatter(d.ref[:, 1], y, c=d.ref[:, 0], s=10, cmap="viridis")
        axs[row, 0].set_xlabel("set azimuth (deg), colour = drift")
        axs[row, 1].scatter(d.temp_c, y, s=10, color="#b5452a")
        axs[row, 1].set_xlabel("temperature (°C)")
        axs[row, 2].scatter(d.time_s, y, s=10, color="#3a7d44")
        axs[row, 2].set_xlabel("time (s)")
        for a in axs[row]:
            a.set_ylabel(lab)
            a.axhline(0, color="k", lw=0.5)
            a.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return figure_png(fig)


def sensor_residual_figure(model, data, title) -> str:
    plt = pyplot()
    d = data.subset(data.oriented)
    g_t, b_t = model.true_vectors(d)
    h_g, h_b = model.forward(d, g_t, b_t)
    fig, axs = plt.subplots(1, 2, figsize=(12, 3.6))
    for a, res, true, unit, name in ((axs[0], d.g - h_g, g_t, "m/s²", "accelerometer"),
                                     (axs[1], d.b - h_b, b_t, "nT", "magnetometer")):
        for j, c in enumerate(("#1f5fa8", "#b5452a", "#3a7d44")):
            a.scatter(true[:, j], res[:, j], s=8, color=c, label=f"{'xyz'[j]}")
        a.set_xlabel(f"true input ({unit})")
        a.set_ylabel(f"residual ({unit})")
        a.set_title(f"{name}: residual vs input")
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return figure_png(fig)


def table_html(title, header, rows) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return (f"<h3>{html.escape(title)}</h3>" if title else "") + f"<table><tr>{h}</tr>{body}</table>"


def summary_html(sentences, header, rows, extra=()) -> str:
    """The report's first section: the verdict in a few sentences (``extra`` first), and a small table."""
    text = "".join(f"<p>{html.escape(t)}</p>" for t in [*extra, *sentences])
    return (f"<section class='summary'><h2>Summary</h2>{text}"
            + table_html("", header, [[html.escape(c) for c in r] for r in rows]) + "</section>")


def _fmt(v, p=3):
    return "–" if v is None or not np.isfinite(v) else f"{v:.{p}f}"


#: A validation set with more distinct set values than this is not a grid: its tables use bins.
MAX_GRID_VALUES = 12
DRIFT_BINS = (0.0, 5.0, 15.0, 35.0, 65.0, 95.0, 180.0)


def _axis(values, bins=None):
    """The rows (or columns) of a table: the distinct set values of a grid, or bins when the data
    are not a grid.  Returns (labels, index per station, -1 where NaN)."""
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v)
    uniq = np.unique(np.round(v[ok], 3))
    if len(uniq) <= MAX_GRID_VALUES:
        idx = np.where(ok, np.searchsorted(uniq, np.round(np.nan_to_num(v), 3)), -1)
        return [f"{u:g}" for u in uniq], idx
    edges = np.asarray(bins if bins is not None else np.linspace(0, 360, 9))
    idx = np.where(ok, np.clip(np.digitize(np.nan_to_num(v), edges) - 1, 0, len(edges) - 2), -1)
    return [f"{edges[k]:g}–{edges[k + 1]:g}" for k in range(len(edges) - 1)], idx


def grid_tables_html(before: dict, after: dict, ref) -> str:
    """Tables 4 and 5 of the paper, laid out on the grid the validation data actually have: drift
    error RMS by set drift; azimuth error RMS by set drift × set azimuth over every toolface
    (stations with an undefined azimuth counted apart).  A set of stations that is not a grid is
    binned (drift in bands, azimuth in 45° sectors)."""
    ref = np.asarray(ref, dtype=float)
    rows, ri = _axis(ref[:, 0], DRIFT_BINS)
    cols, ci = _axis(ref[:, 1])

    def rms(x):
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")

    t4 = []
    for k, lab in enumerate(rows):
        m = ri == k
        t4.append([lab, str(int(m.sum())), _fmt(rms(before["drift_err"][m]), 4), _fmt(rms(after["drift_err"][m]), 4)])
    out = table_html("Drift error RMS (deg) by set drift (Table 4 layout)", ["set drift", "stations", "before",
                                                                               "after"], t4)
    ab, aa = np.asarray(before["azimuth_err"], float), np.asarray(after["azimuth_err"], float)
    t5 = []
    for k, lab in enumerate(rows):
        cells = []
        for j in range(len(cols)):
            m = (ri == k) & (ci == j)
            cells.append(_fmt(rms(aa[m]), 4) if m.any() else "")
        m = ri == k
        t5.append([lab] + cells + [_fmt(rms(ab[m]), 3), _fmt(rms(aa[m]), 4)])
    out += table_html("Azimuth error RMS (deg) after, by set drift × set azimuth, all toolfaces (Table 5 layout)",
                      ["set drift"] + cols + ["row RMS before", "row RMS after"], t5)
    undefined = int(np.sum(~np.isfinite(ref[:, 1])))
    if undefined:
        out += f"<p>{undefined} station(s) without a set azimuth (vertical): drift and toolface only.</p>"
    return out


def losses_html(losses) -> str:
    if not losses:
        return "<p>Nothing was left out.</p>"
    rows = [[html.escape(x.source), html.escape(x.what), str(x.count), html.escape(x.reason)] for x in losses]
    return table_html("Left out of the data", ["source", "what", "count", "why"], rows)


def noise_figure(noise: dict) -> str:
    """The pooled Allan deviation per axis of each sensor (log–log), with the fitted IEEE model."""
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    from ..detect.allan import FLICKER

    plt = pyplot()
    fig, axes = plt.subplots(1, len(noise), figsize=(5.5 * len(noise), 3.8))
    for ax, (sensor, m) in zip(np.atleast_1d(axes), noise.items()):
        c = m.curve
        for j, a in enumerate("xyz"):
            if not len(c.tau):
                continue
            line, = ax.loglog(c.tau, c.adev[:, j], "o", ms=3, label=f"{a}")
            t = m.terms[j]
            n2, b2, k2 = (t[k].value ** 2 if t[k].resolved else 0.0 for k in "NBK")
            tau = np.geomspace(c.tau[0], c.tau[-1], 50)
            ax.loglog(tau, np.sqrt(n2 / tau + FLICKER * b2 + k2 * tau / 3.0), "-", color=line.get_color(), lw=0.8)
        ax.set_xlabel("τ (s)")
        ax.set_ylabel(f"Allan deviation ({m.unit})")
        ax.set_title(f"{sensor}: {c.n_segments} holds at {c.rate_hz:.0f} Hz")
        ax.legend(fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        # τ spans about a decade: 1-2-5 ticks in plain numbers (the minor 2×10⁻², 3×10⁻², … collide)
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        plain_log_ticks(ax.yaxis)
    fig.tight_layout()
    return figure_png(fig)


def noise_html(noise: dict) -> str:
    """The IEEE-style noise figures per axis (white noise, bias instability, random walk)."""
    if not noise:
        return ""

    def cell(t):
        if not np.isfinite(t["upper95"]):
            return "n/a"
        txt = f"{t['value']:.3g} ± {t['std']:.2g}" if t["resolved"] else f"&lt; {t['upper95']:.2g}"
        return txt + (" (stations)" if t["source"] == "stations" else "")

    rows = []
    for m in noise.values():
        for r in m.table():
            rows.append([r["axis"], cell(r["white_noise"]) + " " + html.escape(r["white_noise"]["unit"]),
                         cell(r["bias_instability"]) + " " + html.escape(r["bias_instability"]["unit"]),
                         cell(r["random_walk"]) + " " + html.escape(r["random_walk"]["unit"])])
    return table_html("Noise model (IEEE Std 952 figures from the Allan deviation of the holds; '<': not resolved, "
                      "one-sided 95 % bound; '(stations)': the random walk across the station sequence, which short "
                      "holds cannot see)", ["axis", "white noise N", "bias instability B", "random walk K"], rows)


def uncertainty_html(dg) -> str:
    if not dg.uncertainty:
        return ""
    rows = [[k, str(v["stations"]), _fmt(v["rms"], 2), _fmt(100 * v["within_1"], 0) + " %",
             _fmt(100 * v["within_2"], 0) + " %", _fmt(v["median_sigma_deg"], 4)] for k, v in dg.uncertainty.items()]
    return table_html("Errors over their predicted 1σ (noise and the fit's covariance): RMS 1, 68 % within 1σ and "
                      "95 % within 2σ when the uncertainty holds",
                      ["angle", "stations", "RMS of error/σ", "within 1σ", "within 2σ", "median σ (deg)"], rows)


CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px;margin:0.5em 0 1.5em}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
td:first-child,th:first-child{text-align:left}
pre{background:#f4f4f4;padding:0.8em;white-space:pre-wrap;overflow-wrap:anywhere}
img{max-width:100%;display:block;margin:0.5em 0}
h2{border-bottom:1px solid #ddd}li{overflow-wrap:anywhere}
section.summary{background:#f3f7fb;border:1px solid #c9d8e8;padding:0.2em 1em 0.5em;margin-bottom:1.5em}
section.summary p{font-size:15px;margin:0.5em 0}section.summary table{font-size:13px}"""


def page_head(title) -> str:
    """The start of a report page: its head (the CSS) and its title."""
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>")


def in_words(v, unit="°") -> str:
    """A figure in a summary's sentence: three significant digits, "not known" where there is none."""
    return f"{v:.3g}{unit}" if v is not None and np.isfinite(v) else "not known"


def summary(steps, uncorrected: dict, methods=None) -> tuple:
    """What the lab report says first: (sentences, header, rows) — what the lab added and what it
    gained on the validation data, the candidates tried, what the last rung finds, whether the
    predicted uncertainty holds; a table of the rungs."""
    from .diagnose import FINDING_SUMMARY

    base, final = steps[0], steps[-1]
    kind = {"field": "the references never fitted", "in-sample": "in-sample"}.get(base.validation_kind,
                                                                                   base.validation_kind or "")
    added = [s.recommended.label for s in steps[:-1] if s.recommended]
    figures = (f"azimuth RMS {in_words(base.base_val.get('azimuth_rms_deg'))} → "
               f"{in_words(final.base_val.get('azimuth_rms_deg'))}, drift RMS "
               f"{in_words(base.base_val.get('drift_rms_deg'))} → {in_words(final.base_val.get('drift_rms_deg'))}")
    where = f"on the validation data{f', {kind}' if kind else ''}"
    if not base.base_val.get("stations"):
        head = (f"The lab adds {', '.join(added) or 'nothing'} to the paper's model; the validation data have no "
                "station with a reference attitude, so there are no angle errors to show")
    elif added:
        head = f"The lab adds {', '.join(added)} to the paper's model: {figures} {where}"
    else:
        head = (f"The lab adds nothing to {base.model.describe()}: azimuth RMS "
                f"{in_words(base.base_val.get('azimuth_rms_deg'))}, drift RMS "
                f"{in_words(base.base_val.get('drift_rms_deg'))} {where}")
    if uncorrected.get("stations"):
        head += (f" (uncorrected: azimuth {in_words(uncorrected.get('azimuth_rms_deg'))}, drift "
                 f"{in_words(uncorrected.get('drift_rms_deg'))})")
    sentences = [head + "."]
    tried = [len(s.ranked) for s in steps]
    sig = [sum(1 for c in s.ranked if c.significant) for s in steps]
    sentences.append("Candidates tried round by round: " + ", ".join(map(str, tried)) + "; significant: "
                     + ", ".join(map(str, sig)) + "." if len(steps) > 1 else
                     f"{tried[0]} candidates tried, {sig[0]} significant.")
    rec = final.recommended
    sentences.append("After the last rung " + FINDING_SUMMARY.get(final.finding, final.finding).format(
        effect=rec.label if rec is not None else "", refused=final.refused) + ".")
    unc = {k: v for k, v in (final.uncertainty or {}).items() if v.get("stations")}
    if unc:
        # 1 and 95 % within 2σ when it holds exactly; an RMS up to 1.5 with 90 % within 2σ still
        # bounds the errors usefully (a σ too large holds, conservatively)
        holds = all(v["rms"] <= 1.5 and v["within_2"] >= 0.9 for v in unc.values())
        sentences.append("Errors over their predicted 1σ, RMS: "
                         + ", ".join(f"{k} {v['rms']:.2f}" for k, v in unc.items())
                         + (" — the predicted uncertainty holds." if holds else
                            " — the predicted uncertainty does not hold (RMS 1 and 95 % within 2σ when it does)."))
    real = [r for r in methods or () if r["method"] != "truth" and np.isfinite(r["azimuth_rms_deg"])]
    if real:
        best = min(real, key=lambda r: r["azimuth_rms_deg"])
        truth = [r for r in methods if r["method"] == "truth"]
        sentences.append("Calibration methods on the validation log, azimuth RMS: "
                         + ", ".join(f"{r['method']} {in_words(r['azimuth_rms_deg'])}" for r in real)
                         + f"; lowest: {best['method']}"
                         + (f" (the simulator's true model: {in_words(truth[0]['azimuth_rms_deg'])})." if truth
                            else "."))
    header = ["model", "drift RMS °", "azimuth RMS °", "finding"]
    rows = [["uncorrected", _fmt(uncorrected.get("drift_rms_deg"), 4), _fmt(uncorrected.get("azimuth_rms_deg"), 4),
             "raw sensors"]] if uncorrected.get("stations") else []
    labels = ["base (paper)"] + ["+ " + a for a in added]
    for label, s in zip(labels, steps):
        rows.append([label, _fmt(s.base_val.get("drift_rms_deg"), 4), _fmt(s.base_val.get("azimuth_rms_deg"), 4),
                     s.finding])
    return sentences, header, rows


def render(steps, data, uncorrected: dict, final_fit, title="inclinometer_calib model lab", methods=None) -> str:
    """HTML for a ladder of diagnoses (``diagnose.ladder``) on ``data``."""
    base, final = steps[0], steps[-1]
    parts = [page_head(title), summary_html(*summary(steps, uncorrected, methods)), "<h2>The full verdict</h2>",
             f"<p>Data: {html.escape(data.describe())}</p>",
             "<h2>Diagnosis</h2>"]
    for k, s in enumerate(steps):
        parts.append(f"<h3>Round {k + 1}</h3><pre>{html.escape(s.verdict)}</pre>")
        rows = [[html.escape(c.label), _fmt(c.val.get('drift_rms_deg'), 4), _fmt(c.val.get('azimuth_rms_deg'), 4),
                 _fmt(c.score, 4), f"{c.p:.1e}", f"{c.delta_bic:.0f}", "yes" if c.significant else "",
                 html.escape(c.note)] for c in s.ranked]        # every candidate tried, ranked
        parts.append(table_html(f"Candidates ({len(s.ranked)} tried) — errors {s.base_val.get('label', '')}",
                                ["effect", "drift RMS", "azimuth RMS", "pointing RMS", "Wald p", "ΔBIC", "significant",
                                 "note"], rows))
        for n in s.notes:
            parts.append(f"<p>{html.escape(n)}</p>")
        if s.structure:
            rows = [[html.escape(e["channel"]), html.escape(e["regressor"]), f"{e['r2']:.2f}", f"{e['p']:.1e}"]
                    for e in s.structure]
            parts.append(table_html("Residual structure (F-test vs regressors, Bonferroni)",
                                     ["residual", "regressor", "R²", "p"], rows))
    parts.append("<h2>Data left out</h2>" + losses_html(data.losses))
    parts.append("<h2>Effect ladder</h2>")
    parts.append(f"<img src='{ladder_figure(steps, uncorrected)}'>")
    for k, s in enumerate(steps):
        for n in s.notes:
            parts.append(f"<p>Rung {k}: {html.escape(n)}</p>")
    parts.append("<h2>Predicted uncertainty</h2>" + uncertainty_html(final))
    if methods:
        from .methods import compare_html
        parts.append("<h2>Calibration methods compared</h2><p>The same probe calibrated by the twelve positions, by "
                     "the turntable (its accelerometer from the twelve positions) and by the lab with both logs; "
                     "each record corrects the validation log.</p>" + compare_html(methods))
    if base.noise and any(len(m.curve.tau) for m in base.noise.values()):
        parts.append("<h2>Noise model</h2>" + noise_html(base.noise) + f"<img src='{noise_figure(base.noise)}'>")
    parts.append("<h2>Residuals</h2>")
    parts.append(f"<img src='{sensor_drift_figure(steps, data)}'>")
    parts.append(f"<img src='{residual_figure(base.model, data, 'Base model (the paper): validation angle errors')}'>")
    parts.append(f"<img src='{sensor_residual_figure(base.model, data, 'Base model: sensor residuals')}'>")
    if len(steps) > 1:
        parts.append(f"<img src='{residual_figure(final.model, data, 'Final model: ' + final.model.describe())}'>")
        parts.append(f"<img src='{sensor_residual_figure(final.model, data, 'Final model: sensor residuals')}'>")
    has = np.isfinite(data.ref[:, 0]) & (data.role == "val") if (data.role == "val").any() else np.isfinite(data.ref[:, 0])
    if has.any():
        d = data.subset(has)
        parts.append("<h2>Before / after on the validation grid</h2><p>before: uncorrected sensors; after: the final "
                     f"model ({html.escape(final.base_val.get('label', ''))}).</p>")
        from ..core.survey import evaluate
        before = evaluate(d.g, d.b, final.model.site, ref=d.ref)
        parts.append(grid_tables_html(before, final.model.angle_errors(d), d.ref))
    if final_fit is not None:
        rows = [[html.escape(r["name"]), f"{r['value']:.6g}", f"{r['std']:.2g}", html.escape(r["unit"])]
                for r in final_fit.parameter_table()]
        parts.append("<h2>Final model parameters</h2>" + table_html("", ["parameter", "value", "1σ", "unit"], rows))
        if final_fit.not_identifiable:
            parts.append("<ul>" + "".join(f"<li>{html.escape(n.parameter)}: {html.escape(n.reason)}</li>"
                                          for n in final_fit.not_identifiable) + "</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)

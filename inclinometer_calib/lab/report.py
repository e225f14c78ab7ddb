"""One self-contained HTML report of a model-lab run (plots embedded as PNG data URIs).

Sections: the diagnosis text (with the data left out); the effect ladder (the field validation
error after each added effect, as each rung's diagnosis labels it); residuals of the base and final models against orientation, temperature and time; the
paper-style before/after tables (Tables 4 and 5 layout); the fitted parameters with uncertainties.
"""
from __future__ import annotations

import base64
import html
import io

import numpy as np

from ..deps import require
from ..survey import table4, table5


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


def ladder_figure(steps, uncorrected: dict) -> str:
    """Validation error after each rung: uncorrected, the paper's base model, then each added effect."""
    plt = pyplot()
    labels = ["uncorrected", "base (paper)"] + ["+ " + s.recommended.label for s in steps if s.recommended]
    drift = [uncorrected["drift_rms_deg"]] + [s.base_val.get("drift_rms_deg", np.nan) for s in steps]
    az = [uncorrected["azimuth_rms_deg"]] + [s.base_val.get("azimuth_rms_deg", np.nan) for s in steps]
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
    x = np.arange(len(drift))
    for a, y, t in ((ax[0], drift, "drift RMS (deg)"), (ax[1], az, "azimuth RMS (deg)")):
        a.plot(x, y, "o-", color="#1f5fa8")
        a.set_yscale("log")
        a.set_xticks(x)
        a.set_xticklabels(labels[:len(x)], rotation=25, ha="right", fontsize=8)
        a.set_title(f"{steps[0].base_val.get('kind', 'validation')} {t}")
        a.grid(True, which="both", alpha=0.3)
        for xi, yi in zip(x, y):
            a.annotate(f"{yi:.3g}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    fig.suptitle("Effect ladder: validation error after each added effect")
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
    return figure_png(fig)


def table_html(title, header, rows) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<h3>{html.escape(title)}</h3><table><tr>{h}</tr>{body}</table>"


def _fmt(v, p=3):
    return "–" if v is None or not np.isfinite(v) else f"{v:.{p}f}"


def paper_tables_html(before: dict, after: dict, ref) -> str:
    t4b, t4a = table4(before, ref), table4(after, ref)
    rows = [["before"] + [_fmt(v) for v in t4b["mean_err"]] + [_fmt(t4b["overall_rms"])],
            ["after"] + [_fmt(v) for v in t4a["mean_err"]] + [_fmt(t4a["overall_rms"])]]
    out = table_html("Table 4 layout — drift error (deg) by set drift", ["state"] + [f"{d:g}" for d in t4a["drifts"]] + ["RMS"], rows)
    t5b, t5a = table5(before, ref), table5(after, ref)
    rows = []
    for i, dr in enumerate(t5a["drifts"]):
        for name, t in (("before", t5b), ("after", t5a)):
            rows.append([f"{dr:g}", name] + [_fmt(v, 2) for v in t["cells"][i]] + [_fmt(t["rms_err"][i], 2)])
    out += table_html(f"Table 5 layout — azimuth error (deg) at toolface {t5a['toolface_deg']:g}",
                       ["drift", "state"] + [f"{a:g}" for a in t5a["azimuths"]] + ["RMS"], rows)
    return out


CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;color:#222}
table{border-collapse:collapse;font-size:12px;margin:0.5em 0 1.5em}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
pre{background:#f4f4f4;padding:0.8em;white-space:pre-wrap}img{max-width:100%}h2{border-bottom:1px solid #ddd}"""


def render(steps, data, uncorrected: dict, final_fit, title="inclinometer_calib model lab") -> str:
    """HTML for a ladder of diagnoses (``diagnose.ladder``) on ``data``."""
    base, final = steps[0], steps[-1]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>",
             f"<p>Data: {html.escape(data.describe())}</p>",
             "<h2>Diagnosis</h2>"]
    for k, s in enumerate(steps):
        parts.append(f"<h3>Round {k + 1}</h3><pre>{html.escape(s.verdict)}</pre>")
        rows = [[html.escape(c.label), _fmt(c.val.get('drift_rms_deg'), 4), _fmt(c.val.get('azimuth_rms_deg'), 4),
                 _fmt(c.score, 4), f"{c.p:.1e}", f"{c.delta_bic:.0f}", "yes" if c.significant else "",
                 html.escape(c.note)] for c in s.ranked[:8]]
        parts.append(table_html(f"Candidates — errors {s.base_val.get('label', '')}",
                                ["effect", "drift RMS", "azimuth RMS", "pointing RMS", "Wald p", "ΔBIC", "significant",
                                 "note"], rows))
        for n in s.notes:
            parts.append(f"<p>{html.escape(n)}</p>")
        if s.structure:
            rows = [[html.escape(e["channel"]), html.escape(e["regressor"]), f"{e['r2']:.2f}", f"{e['p']:.1e}"]
                    for e in s.structure]
            parts.append(table_html("Residual structure (F-test vs regressors, Bonferroni)",
                                     ["residual", "regressor", "R²", "p"], rows))
    parts.append("<h2>Effect ladder</h2>")
    parts.append(f"<img src='{ladder_figure(steps, uncorrected)}'>")
    parts.append("<h2>Residuals</h2>")
    parts.append(f"<img src='{residual_figure(base.model, data, 'Base model (the paper): validation angle errors')}'>")
    parts.append(f"<img src='{sensor_residual_figure(base.model, data, 'Base model: sensor residuals')}'>")
    if len(steps) > 1:
        parts.append(f"<img src='{residual_figure(final.model, data, 'Final model: ' + final.model.describe())}'>")
        parts.append(f"<img src='{sensor_residual_figure(final.model, data, 'Final model: sensor residuals')}'>")
    has = np.all(np.isfinite(data.ref), axis=1)
    if has.any():
        d = data.subset(has)
        parts.append("<h2>Before / after (paper layout)</h2><p>before: uncorrected sensors; after: the final model "
                     "(fitted as in the ladder: the calibration logs and the survey's invariants).</p>")
        from ..survey import evaluate
        before = evaluate(d.g, d.b, final.model.site, ref=d.ref)
        parts.append(paper_tables_html(before, final.model.angle_errors(d), d.ref))
    if final_fit is not None:
        rows = [[html.escape(r["name"]), f"{r['value']:.6g}", f"{r['std']:.2g}", html.escape(r["unit"])]
                for r in final_fit.parameter_table()]
        parts.append("<h2>Final model parameters</h2>" + table_html("", ["parameter", "value", "1σ", "unit"], rows))
        if final_fit.not_identifiable:
            parts.append("<ul>" + "".join(f"<li>{html.escape(n.parameter)}: {html.escape(n.reason)}</li>"
                                          for n in final_fit.not_identifiable) + "</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)

"""The field effect ladder: one recorded bag replayed through several calibration records.

``inclinometer-calib reprocess BAG --compare base.yaml model.yaml ... -o DIR`` runs the live
graph's steps offline (:func:`reprocess.reprocess`: the same detector, the same pipeline) once per
record, so the stations are the same and only the model differs, and writes ``DIR/<name>.mcap``
per record plus ``DIR/compare.md`` and ``DIR/compare.html`` (plots).  The figure of merit is

* with a reference attitude in the bag (``/probe/reference``: a stand, a check shot, a simulated
  survey): the stations' drift and azimuth RMS against it;
* without one: the QC residuals' RMS against the site reference — ΔG, ΔB and Δdip, what a survey
  crew checks every station by.

Every record is compared against the same site reference (a ``--site`` given, else each record's
own: said when the records' sites differ, since the QC residuals then measure different things).
"""
from __future__ import annotations

import html
import math
import os
from dataclasses import dataclass, field

import numpy as np

from ..core.frames import wrap180


@dataclass
class ModelRun:
    """One record's replay: its name, the record (None: uncorrected), the reprocess report and the
    figures of :func:`metrics`."""

    name: str
    calibration: object
    report: object
    metrics: dict = field(default_factory=dict)
    bag: str = ""


def _rms(x) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def _max(x) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.max(np.abs(x))) if len(x) else float("nan")


def station_errors(stations) -> dict:
    """Per-station arrays of a run's ``SurveyStation`` fields: errors against the reference (NaN
    where none), QC residuals, temperature, status flags."""
    def col(key):
        return np.array([s[key] for s in stations], dtype=float)

    ref_i, ref_a = col("reference_drift_deg"), col("reference_azimuth_deg")
    drift_err = col("drift_deg") - ref_i
    az_err = np.where(np.isfinite(ref_a), wrap180(col("azimuth_deg") - ref_a), np.nan)
    return {"drift_err": drift_err, "azimuth_err": az_err, "delta_g": col("delta_g_mps2"),
            "delta_b": col("delta_b_nt"), "delta_dip": col("delta_dip_deg"), "temperature": col("temperature_c"),
            "ref_drift": ref_i, "index": np.arange(len(stations), dtype=float),
            "moved": np.array([bool(s["moved_during_capture"]) for s in stations]),
            "misfit": np.array([bool(s.get("model_misfit", False)) for s in stations]),
            "interference": np.array([bool(s["interference_suspected"]) for s in stations])}


def metrics(stations) -> dict:
    """The run's figures over its stations (those in which the probe moved left out)."""
    e = station_errors(stations)
    use = ~e["moved"] if len(stations) else np.zeros(0, bool)
    has_ref = use & np.isfinite(e["drift_err"])
    out = {"stations": int(use.sum()), "with_reference": int(has_ref.sum()),
           "delta_g_rms_mps2": _rms(e["delta_g"][use]), "delta_b_rms_nt": _rms(e["delta_b"][use]),
           "delta_dip_rms_deg": _rms(e["delta_dip"][use]),
           "interference_flagged": int(e["interference"][use].sum()), "model_misfit_flagged": int(e["misfit"][use].sum())}
    if has_ref.any():
        out.update(drift_rms_deg=_rms(e["drift_err"][has_ref]), drift_max_abs_deg=_max(e["drift_err"][has_ref]),
                   azimuth_rms_deg=_rms(e["azimuth_err"][has_ref]), azimuth_max_abs_deg=_max(e["azimuth_err"][has_ref]),
                   azimuth_stations=int(np.isfinite(e["azimuth_err"][has_ref]).sum()))
    return out


def compare(bag, models, outdir, *, site=None, tolerances=None, make_detector=None, warn=None,
            monitor_window: int = 30) -> list:
    """Replay ``bag`` through each ``(name, calibration or None)`` of ``models`` into
    ``outdir/<name>.mcap`` (the directory is created; existing files are never overwritten): that
    record's stations and diagnostics only — the inputs, the same for every record, stay in ``bag``
    (copied into each, they were two thirds of a three-record ladder's time).
    ``make_detector()``: a fresh configured static detector per run (default: from the data)."""
    from .field import FieldMonitor
    from ..correct.reprocess import reprocess
    from ..core.survey import Tolerances

    tol = tolerances or Tolerances()
    os.makedirs(outdir, exist_ok=True)
    runs = []
    for name, cal in models:
        dst = os.path.join(outdir, f"{name}.mcap")
        monitor = FieldMonitor(window=monitor_window, tolerances=tol) if monitor_window else None
        rep = reprocess(bag, dst, cal, site, tol, make_detector() if make_detector else None, warn=warn,
                        copy_input=False, monitor=monitor)
        runs.append(ModelRun(name, cal, rep, metrics(rep.stations), dst))
    sites = {r.calibration.site.to_dict().__repr__() for r in runs if r.calibration is not None}
    if site is None and len(sites) > 1 and warn:
        warn("the records own different site references: their QC residuals are against different sites "
             "(give --site to compare them against one)")
    return runs


def has_reference(runs) -> bool:
    return any(r.metrics.get("with_reference") for r in runs)


def _f(v, spec) -> str:
    return format(v, spec) if v is not None and isinstance(v, (int, float)) and math.isfinite(v) else "—"


def table_rows(runs) -> tuple:
    """(header, rows) of the ladder table, reference figures first when the bag has a reference."""
    ref = has_reference(runs)
    header = ["model", "record", "stations"]
    if ref:
        header += ["drift RMS °", "drift max °", "azimuth RMS °", "azimuth max °"]
    header += ["ΔG RMS m/s²", "ΔB RMS nT", "Δdip RMS °", "interference", "model misfit"]
    rows = []
    for r in runs:
        m = r.metrics
        row = [r.name, r.calibration.id if r.calibration is not None else "none (raw)", str(m["stations"])]
        if ref:
            row += [_f(m.get("drift_rms_deg"), ".4f"), _f(m.get("drift_max_abs_deg"), ".4f"),
                    _f(m.get("azimuth_rms_deg"), ".4f"), _f(m.get("azimuth_max_abs_deg"), ".4f")]
        row += [_f(m["delta_g_rms_mps2"], ".5f"), _f(m["delta_b_rms_nt"], ".1f"), _f(m["delta_dip_rms_deg"], ".4f"),
                str(m["interference_flagged"]), str(m["model_misfit_flagged"])]
        rows.append(row)
    return header, rows


def describe(runs, bag) -> list:
    """Plain-text lines of the ladder (what the CLI prints)."""
    header, rows = table_rows(runs)
    widths = [max(len(header[k]), *(len(r[k]) for r in rows)) for k in range(len(header))]
    basis = ("errors against the bag's reference attitudes" if has_reference(runs) else
             "no reference attitude in the bag: QC residuals against the site reference")
    lines = [f"field effect ladder of {bag} ({basis})",
             "  ".join(h.rjust(w) if k else h.ljust(w) for k, (h, w) in enumerate(zip(header, widths)))]
    for r in rows:
        lines.append("  ".join(c.rjust(w) if k else c.ljust(w) for k, (c, w) in enumerate(zip(r, widths))))
    for r in runs:
        if r.calibration is not None:
            lines.append(f"  {r.name}: {r.calibration.model.describe()}")
    return lines


def to_markdown(runs, bag, title: str = "Field effect ladder") -> str:
    header, rows = table_rows(runs)
    basis = ("Errors against the bag's reference attitudes." if has_reference(runs) else
             "The bag has no reference attitude: QC residuals (corrected |G|, |B| and dip minus the site reference).")
    out = [f"# {title}", "", f"Bag: `{bag}`. The same stations (the same detector), one run per record. {basis}", "",
           "| " + " | ".join(header) + " |", "|" + "|".join("---" if k == 0 else "---:" for k in range(len(header))) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    out += ["", "Models:", ""]
    for r in runs:
        model = r.calibration.model.describe() if r.calibration is not None else "uncorrected"
        out.append(f"- **{r.name}**: {model}; bag `{os.path.basename(r.bag)}`")
    verdicts = [(r.name, s["model_diagnosis"]) for r in runs for s in r.report.stations[-1:] if s.get("model_diagnosis")]
    if verdicts:
        out += ["", "Field monitor at the last station:", ""]
        out += [f"- **{n}**: {html.escape(t)}" for n, t in verdicts]
    return "\n".join(out) + "\n"


def ladder_figure(runs) -> str:
    """The ladder plot (PNG data URI): the figures of merit model by model."""
    from .report import figure_png, pyplot

    plt = pyplot()
    ref = has_reference(runs)
    keys = ([("drift_rms_deg", "drift RMS (deg)"), ("azimuth_rms_deg", "azimuth RMS (deg)")] if ref else
            [("delta_b_rms_nt", "ΔB RMS (nT)"), ("delta_dip_rms_deg", "Δdip RMS (deg)")])
    fig, ax = plt.subplots(1, len(keys), figsize=(11, 3.6))
    x = np.arange(len(runs))
    for a, (key, label) in zip(np.atleast_1d(ax), keys):
        y = [r.metrics.get(key, np.nan) for r in runs]
        a.plot(x, y, "o-", color="#1f5fa8")
        if all(v > 0 for v in y if np.isfinite(v)):
            a.set_yscale("log")
        a.set_xticks(x)
        a.set_xticklabels([r.name for r in runs], rotation=20, ha="right", fontsize=8)
        a.set_title(label)
        a.grid(True, which="both", alpha=0.3)
        for xi, yi in zip(x, y):
            if np.isfinite(yi):
                a.annotate(f"{yi:.3g}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    fig.suptitle("Field effect ladder: the same stations through each record")
    return figure_png(fig)


def residual_limits(values) -> tuple:
    """Symmetric y-limits that show ``values`` (arrays of the corrected models' residuals): the
    largest |value| among them, 8 % of margin; (-1, 1) when there is none."""
    finite = np.concatenate([np.abs(np.asarray(v, float))[np.isfinite(v)] for v in values]) if values else np.zeros(0)
    top = float(finite.max()) * 1.08 if len(finite) and finite.max() > 0 else 1.0
    return -top, top


def residual_figure(runs) -> str:
    """Per-station errors (or QC residuals) against temperature and station order, model by model.

    Each panel is scaled to the corrected models it compares (their residuals are the point of
    the page); the uncorrected run, degrees where the others are hundredths, is drawn on an axis
    of its own (right, grey) rather than flattening them."""
    from .report import figure_png, pyplot

    plt = pyplot()
    ref = has_reference(runs)
    items = ([("azimuth_err", "azimuth error (deg)"), ("drift_err", "drift error (deg)")] if ref else
             [("delta_b", "ΔB (nT)"), ("delta_dip", "Δdip (deg)")])
    fig, axs = plt.subplots(len(items), 2, figsize=(12, 3.2 * len(items)), squeeze=False)
    colours = ("#b5452a", "#1f5fa8", "#3a7d44", "#7a3a9d", "#c08a00", "#555555")
    errors = [(r, station_errors(r.report.stations)) for r in runs]
    corrected = [(r, e) for r, e in errors if r.calibration is not None]
    raw = [(r, e) for r, e in errors if r.calibration is None]
    for row, (key, label) in enumerate(items):
        lim = residual_limits([e[key][~e["moved"]] for _, e in corrected])
        for col, (xkey, xlabel) in enumerate((("temperature", "temperature (°C)"), ("index", "station"))):
            a = axs[row, col]
            for k, (r, e) in enumerate(corrected):
                keep = ~e["moved"]
                a.scatter(e[xkey][keep], e[key][keep], s=9, color=colours[k % len(colours)], label=r.name, alpha=0.8)
            if corrected:
                a.set_ylim(*lim)
            if raw:
                side = a.twinx() if corrected else a
                for r, e in raw:
                    keep = ~e["moved"]
                    side.scatter(e[xkey][keep], e[key][keep], s=7, color="#aaaaaa", marker="x", alpha=0.6,
                                 label=f"{r.name} (right axis)" if corrected else r.name)
                if corrected:
                    side.set_ylabel(f"{r.name} (right)", color="#888888", fontsize=8)
                    side.tick_params(axis="y", colors="#888888", labelsize=7)
            a.set_xlabel(xlabel)
            a.set_ylabel(label)
            a.axhline(0, color="k", lw=0.5)
            a.grid(alpha=0.3)
    axs[0, 0].legend(fontsize=8)
    fig.suptitle("Residuals model by model" + (" (each panel scaled to the corrected models; uncorrected on the "
                                               "right axis)" if raw and corrected else ""))
    fig.tight_layout()
    return figure_png(fig)


def to_html(runs, bag, title: str = "Field effect ladder", intro=()) -> str:
    """A self-contained HTML page of the ladder (plots embedded); ``intro``: text lines put first."""
    from .report import CSS, table_html

    header, rows = table_rows(runs)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    if intro:
        parts.append("<pre>" + html.escape("\n".join(intro)) + "</pre>")
    parts += [f"<p>Bag: <code>{html.escape(str(bag))}</code>. The same stations, one run per record.</p>",
             table_html("Model by model", header, [[html.escape(c) for c in r] for r in rows]),
             f"<img src='{ladder_figure(runs)}'>", f"<img src='{residual_figure(runs)}'>", "<h2>Models</h2><ul>"]
    for r in runs:
        model = r.calibration.model.describe() if r.calibration is not None else "uncorrected"
        diag = r.report.stations[-1].get("model_diagnosis") if r.report.stations else ""
        parts.append(f"<li><b>{html.escape(r.name)}</b>: {html.escape(model)}"
                     + (f"<br><i>field monitor:</i> {html.escape(diag)}" if diag else "") + "</li>")
    parts.append("</ul></body></html>")
    return "\n".join(parts)

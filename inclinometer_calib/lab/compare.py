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
    where none), QC residuals, temperature, time (min from the first station, by the stations'
    ``stamp``, s; NaN without), the orientation (the reference azimuth and toolface where the
    station has one, else the measured), status flags."""
    def col(key):
        return np.array([s.get(key, np.nan) for s in stations], dtype=float)

    ref_i, ref_a = col("reference_drift_deg"), col("reference_azimuth_deg")
    drift_err = col("drift_deg") - ref_i
    az_err = np.where(np.isfinite(ref_a), wrap180(col("azimuth_deg") - ref_a), np.nan)
    stamp = col("stamp")
    t0 = stamp[np.isfinite(stamp)].min() if np.isfinite(stamp).any() else np.nan
    ref_t = col("reference_toolface_deg")
    return {"drift_err": drift_err, "azimuth_err": az_err, "delta_g": col("delta_g_mps2"),
            "delta_b": col("delta_b_nt"), "delta_dip": col("delta_dip_deg"), "temperature": col("temperature_c"),
            "ref_drift": ref_i, "index": np.arange(len(stations), dtype=float), "time_min": (stamp - t0) / 60.0,
            "azimuth": np.where(np.isfinite(ref_a), ref_a, col("azimuth_deg")) % 360.0,
            "toolface": np.where(np.isfinite(ref_t), ref_t, col("toolface_deg")) % 360.0,
            "moved": np.array([bool(s["moved_during_capture"]) for s in stations], dtype=bool),
            "misfit": np.array([bool(s.get("model_misfit", False)) for s in stations], dtype=bool),
            "interference": np.array([bool(s["interference_suspected"]) for s in stations], dtype=bool),
            "out_of_tolerance": np.array([bool(s["interference_suspected"] or s.get("gravity_out_of_tolerance"))
                                          for s in stations], dtype=bool)}


def metrics(stations) -> dict:
    """The run's figures over its stations (those in which the probe moved left out).
    ``out_of_tolerance``: stations outside the QC tolerances (|ΔG|, |ΔB| or Δdip), None when the
    run has no QC residuals (an uncorrected run without a site reference)."""
    e = station_errors(stations)
    use = ~e["moved"] if len(stations) else np.zeros(0, bool)
    has_ref = use & np.isfinite(e["drift_err"])
    qc = use & np.isfinite(e["delta_b"])
    out = {"stations": int(use.sum()), "with_reference": int(has_ref.sum()), "moved": int(e["moved"].sum()),
           "delta_g_rms_mps2": _rms(e["delta_g"][use]), "delta_b_rms_nt": _rms(e["delta_b"][use]),
           "delta_dip_rms_deg": _rms(e["delta_dip"][use]),
           "out_of_tolerance": int(e["out_of_tolerance"][qc].sum()) if qc.any() else None,
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
        runs.append(ModelRun(name, cal, rep, metrics(rep.stamped_stations()), dst))
    sites = {r.calibration.site.to_dict().__repr__() for r in runs if r.calibration is not None}
    if site is None and len(sites) > 1 and warn:
        warn("the records own different site references: their QC residuals are against different sites "
             "(give --site to compare them against one)")
    return runs


def has_reference(runs) -> bool:
    return any(r.metrics.get("with_reference") for r in runs)


def _f(v, spec) -> str:
    return format(v, spec) if v is not None and isinstance(v, (int, float)) and math.isfinite(v) else "—"


def _finite(v) -> bool:
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def missing(run) -> str:
    """Why a run has no QC residuals or no errors ("" when it has them): what the report says in
    place of a figure."""
    m = run.metrics
    if not m["stations"]:
        moved = m.get("moved")
        return f"{run.name}: no station" + (f" ({moved} where the probe moved, left out)" if moved else "")
    if not _finite(m["delta_b_rms_nt"]):
        return (f"{run.name}: no QC residuals (ΔG, ΔB, Δdip) — " +
                ("the uncorrected values have no site reference to be compared with (give --site)"
                 if run.calibration is None else "the record has no site reference"))
    return ""


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


def _diagnosis(run) -> str:
    """The field monitor's verdict at the run's last flagged station, cut to its headline."""
    from .field import headline

    said = [s["model_diagnosis"] for s in run.report.stations if s.get("model_misfit") and s.get("model_diagnosis")]
    return headline(said[-1]) if said else ""


def summary(runs) -> tuple:
    """What the report says first: (sentences, header, rows) — the ladder's figure of merit model
    by model in one sentence, the best record's stations outside the QC tolerances, what the field
    monitor says of each record; a small table of the same.  A figure that is missing is said why."""
    from .report import in_words

    ref = has_reference(runs)
    corrected = [r for r in runs if r.calibration is not None]
    if ref:
        key, words, unit = "azimuth_rms_deg", "Azimuth RMS", "°"
        second, words2 = "drift_rms_deg", "drift RMS"
        basis = f"over {max(r.metrics.get('with_reference', 0) for r in runs)} stations with a reference attitude"
    else:
        key, words, unit = "delta_b_rms_nt", "ΔB RMS", " nT"
        second, words2 = "delta_dip_rms_deg", "Δdip RMS"
        basis = "the QC residuals against the site reference (the bag has no reference attitude)"
    shown = [r for r in runs if _finite(r.metrics.get(key))]
    sentences = []
    if shown:
        sentences.append(f"{words} " + " → ".join(f"{in_words(r.metrics[key], unit)} {r.name}" for r in shown)
                         + f"; {words2} " + " → ".join(in_words(r.metrics.get(second)) for r in shown)
                         + f", {basis}.")
    sentences += [m + "." for m in map(missing, runs) if m]
    best = min((r for r in corrected if _finite(r.metrics.get(key))), key=lambda r: r.metrics[key], default=None)
    if best is not None:
        m = best.metrics
        out = m["out_of_tolerance"]
        text = (f"Lowest: {best.name} — {out} of {m['stations']} stations outside the QC tolerances (|ΔG|, |ΔB|, "
                "Δdip)" if out is not None else f"Lowest: {best.name}")
        diag = _diagnosis(best)
        sentences.append(text + (f"; its field monitor flags {m['model_misfit_flagged']} of {m['stations']} "
                                 f"stations: {diag}." if diag else
                                 "; its field monitor flags no station: the model explains the survey."))
    for r in corrected:
        if r is not best and r.metrics["model_misfit_flagged"]:
            sentences.append(f"With {r.name} the field monitor flags {r.metrics['model_misfit_flagged']} of "
                             f"{r.metrics['stations']} stations: {_diagnosis(r)}.")
    moved = max((r.metrics.get("moved", 0) for r in runs), default=0)
    if moved:
        sentences.append(f"{moved} station(s) left out: the probe moved during the hold.")
    header = ["model", f"{words[0].lower() + words[1:] if ref else words} {unit.strip()}", f"{words2} °",
              "outside QC tolerance", "field monitor"]
    rows = []
    for r in runs:
        m = r.metrics
        out = m["out_of_tolerance"]
        monitor = ("— (no model to check)" if r.calibration is None else
                   f"flags {m['model_misfit_flagged']}" if m["model_misfit_flagged"] else "explains the survey")
        rows.append([r.name, _f(m.get(key), ".4g"), _f(m.get(second), ".4g"),
                     f"{out} of {m['stations']}" if out is not None else "— (no QC residuals)", monitor])
    return sentences, header, rows


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
    out = [f"# {title}", "", " ".join(summary(runs)[0]), "",
           f"Bag: `{bag}`. The same stations (the same detector), one run per record. {basis}", "",
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
    from .report import figure_png, plain_log_ticks, pyplot

    plt = pyplot()
    ref = has_reference(runs)
    keys = ([("drift_rms_deg", "drift RMS (deg)"), ("azimuth_rms_deg", "azimuth RMS (deg)")] if ref else
            [("delta_b_rms_nt", "ΔB RMS (nT)"), ("delta_dip_rms_deg", "Δdip RMS (deg)")])
    fig, ax = plt.subplots(1, len(keys), figsize=(11, 3.8))
    x = np.arange(len(runs))
    for a, (key, label) in zip(np.atleast_1d(ax), keys):
        y = np.array([r.metrics.get(key, np.nan) for r in runs], dtype=float)
        a.plot(x, y, "o-", color="#1f5fa8")
        ok = np.isfinite(y)
        if ok.any() and (y[ok] > 0).all():
            a.set_yscale("log")
            plain_log_ticks(a.yaxis)
        a.margins(x=0.12, y=0.18)      # room for the values written above the points
        a.set_xticks(x)
        a.set_xticklabels([r.name for r in runs], rotation=20, ha="right", fontsize=8)
        a.set_title(label)
        a.grid(True, which="both", alpha=0.3)
        for xi, yi in zip(x, y):
            if np.isfinite(yi):
                a.annotate(f"{yi:.3g}", (xi, yi), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
            else:
                a.annotate("no figure", (xi, 0.5), xycoords=("data", "axes fraction"), ha="center", fontsize=8,
                           color="#888888")
    fig.suptitle("Field effect ladder: the same stations through each record")
    fig.tight_layout()
    return figure_png(fig)


def residual_limits(values) -> tuple:
    """Symmetric y-limits that show ``values`` (arrays of the corrected models' residuals): the
    largest |value| among them, 8 % of margin; (-1, 1) when there is none."""
    finite = np.concatenate([np.abs(np.asarray(v, float))[np.isfinite(v)] for v in values]) if values else np.zeros(0)
    top = float(finite.max()) * 1.08 if len(finite) and finite.max() > 0 else 1.0
    return -top, top


COLOURS = ("#b5452a", "#1f5fa8", "#3a7d44", "#7a3a9d", "#c08a00", "#555555")


def _residual_panels(runs, columns, title) -> str:
    """Per-station errors (or QC residuals, without a reference) of each run against the x of each
    of ``columns`` ((key of :func:`station_errors`, label)), one row per residual.

    Each panel is scaled to the corrected models it compares (their residuals are the point of
    the page); the uncorrected run, degrees where the others are hundredths, is drawn on an axis
    of its own (right, grey) rather than flattening them."""
    from .report import figure_png, pyplot

    plt = pyplot()
    ref = has_reference(runs)
    items = ([("azimuth_err", "azimuth error (deg)"), ("drift_err", "drift error (deg)")] if ref else
             [("delta_b", "ΔB (nT)"), ("delta_dip", "Δdip (deg)")])
    fig, axs = plt.subplots(len(items), len(columns), figsize=(12, 3.3 * len(items)), squeeze=False)
    errors = [(r, station_errors(r.report.stamped_stations())) for r in runs]
    corrected = [(r, e) for r, e in errors if r.calibration is not None]
    raw = [(r, e) for r, e in errors if r.calibration is None]
    for row, (key, label) in enumerate(items):
        lim = residual_limits([e[key][~e["moved"]] for _, e in corrected])
        for col, (xkey, xlabel) in enumerate(columns):
            a = axs[row, col]
            for k, (r, e) in enumerate(corrected):
                keep = ~e["moved"]
                a.scatter(e[xkey][keep], e[key][keep], s=9, color=COLOURS[k % len(COLOURS)], label=r.name, alpha=0.8)
            if corrected:
                a.set_ylim(*lim)
            if raw:
                side = a.twinx() if corrected else a
                for r, e in raw:
                    keep = ~e["moved"]
                    side.scatter(e[xkey][keep], e[key][keep], s=7, color="#aaaaaa", marker="x", alpha=0.6,
                                 label=f"{r.name} (right axis)" if corrected else r.name)
                if corrected:
                    side.set_ylabel(f"{raw[0][0].name} (right)", color="#888888", fontsize=8)
                    side.tick_params(axis="y", colors="#888888", labelsize=7)
            if xkey in ("azimuth", "toolface"):
                a.set_xlim(-12, 372)          # a pose at 0° is not drawn on the frame
                a.set_xticks(np.arange(0, 361, 60))
            a.set_xlabel(xlabel)
            a.set_ylabel(label)
            a.axhline(0, color="k", lw=0.5)
            a.grid(alpha=0.3)
    handles = [h for a in fig.axes for h in a.get_legend_handles_labels()[0]]
    names = [n for a in fig.axes for n in a.get_legend_handles_labels()[1]]
    seen = {}
    for h, n in zip(handles, names):
        seen.setdefault(n, h)
    fig.suptitle(title + (" — each panel scaled to the corrected models, the uncorrected on the right axis"
                          if raw and corrected else ""), fontsize=10)
    fig.legend(list(seen.values()), list(seen), loc="lower center", ncol=len(seen), fontsize=8, frameon=False)
    # a fixed layout (the labels are the same every time; a tight_layout of the twin axes measured
    # every tick label and took half the figure's time): room for the twin axis and the legend,
    # checked by test/report_layout.figure_collisions
    fig.subplots_adjust(left=0.07, right=0.93, bottom=0.14 if len(items) > 1 else 0.2, top=0.91, wspace=0.4,
                        hspace=0.32)
    return figure_png(fig)


def residual_figure(runs) -> str:
    """The residuals against temperature and time (a temperature or time effect the model misses);
    time from the stations' stamps, the station order without them."""
    times = [station_errors(r.report.stamped_stations())["time_min"] for r in runs]
    timed = all(np.isfinite(t).all() and len(t) for t in times)
    return _residual_panels(runs, [("temperature", "temperature (°C)"),
                                   ("time_min", "time (min)") if timed else ("index", "station")],
                            "Residuals against temperature and time")


def orientation_figure(runs) -> str:
    """The residuals against azimuth and toolface (the reference attitude where known): a
    misalignment, a cross-axial bias or a heading-dependent interference leaves a sinusoid in the
    orientation — one cycle per turn for a bias or misalignment, two for a scale or soft-iron error."""
    ref = has_reference(runs)
    return _residual_panels(runs, [("azimuth", "set azimuth (deg)" if ref else "azimuth (deg)"),
                                   ("toolface", "set toolface (deg)" if ref else "toolface (deg)")],
                            "Residuals against orientation")


def to_html(runs, bag, title: str = "Field effect ladder", intro=(), findings=()) -> str:
    """A self-contained HTML page of the ladder (plots embedded): the summary first
    (:func:`summary`, after ``findings``: sentences of the caller's), then the full verdict —
    ``intro`` (text lines), the ladder's table, its plots, the models and what the field monitor said."""
    from .report import page_head, summary_html, table_html

    header, rows = table_rows(runs)
    parts = [page_head(title), summary_html(*summary(runs), extra=findings), "<h2>The full verdict</h2>"]
    if intro:
        parts.append("<pre>" + html.escape("\n".join(intro)) + "</pre>")
    notes = [m for m in map(missing, runs) if m]
    parts += [(f"<p>Bag: <code>{html.escape(str(bag))}</code>. " if bag else "<p>")
              + "The same stations, one run per record.</p>",
              table_html("Model by model", header, [[html.escape(c) for c in r] for r in rows])
              + ("<p>— : " + html.escape("; ".join(notes)) + ".</p>" if notes else ""),
              f"<img alt='the field effect ladder' src='{ladder_figure(runs)}'>",
              f"<img alt='residuals against temperature and time' src='{residual_figure(runs)}'>",
              f"<img alt='residuals against orientation' src='{orientation_figure(runs)}'>", "<h2>Models</h2><ul>"]
    for r in runs:
        model = r.calibration.model.describe() if r.calibration is not None else "uncorrected"
        diag = r.report.stations[-1].get("model_diagnosis") if r.report.stations else ""
        parts.append(f"<li><b>{html.escape(r.name)}</b>: {html.escape(model)}"
                     + (f"<br><i>field monitor:</i> {html.escape(diag)}" if diag else "") + "</li>")
    parts.append("</ul></body></html>")
    return "\n".join(parts)

"""A probe's calibration history: each parameter over time with its 1σ, what moved, what is overdue.

For the calibrations of one probe (:meth:`registry.Registry.history`, oldest first) this module
lays out every parameter of the paper's model of both triads — bias (m/s² or nT), scale (1) and
the six non-orthogonality terms e_ij (1) — with the 1σ the calibrator recorded
(:attr:`coeffs.Calibration.uncertainty`: biases and scales of a twelve-position fit; the
non-orthogonality terms have none recorded, and are shown without a band and never tested, rather
than given an invented σ).

**Moved** (:func:`analyse`): calibration *n* differs from calibration *n−1* in parameter *p* when

    |p_n − p_{n−1}| > k · sqrt(σ_n² + σ_{n−1}²)           (k = 3 by default)

i.e. beyond their combined uncertainty: sensor ageing, a knock (a bias jump of the magnetometer
when the probe got magnetised), a stand problem (both triads at once).  A parameter without a σ in
either record is listed as not tested.

**Overdue**: the last calibration is older, at the date asked (default now), than the probe's
calibration interval (the same rule as :meth:`registry.Registry.valid_record`); a probe never
calibrated is overdue too.
"""
from __future__ import annotations

import datetime as _dt
import html
import math
from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np

from ..core.coeffs import UNITS
from ..core.errormodel import E_TERMS
from .registry import HistoryEntry, ProbeInfo, aware

#: Default threshold of :func:`analyse`, in combined 1σ.
K_SIGMA = 3.0
TRIADS = (("acc", "accelerometer"), ("mag", "magnetometer"))
KINDS = ("bias", "scale", "nonorthogonality")


@dataclass(frozen=True)
class Parameter:
    """One parameter of a triad: ``sensor`` (acc/mag), ``name`` (bias_x, scale_y, e_zx ...), its
    ``kind`` (bias, scale, nonorthogonality), ``unit`` and the uncertainty entry that holds its 1σ
    (``("bias", 0)``: ``uncertainty[sensor]["bias"][0]``; None: no 1σ is recorded for it)."""
    sensor: str
    name: str
    kind: str
    unit: str
    sigma_key: Optional[tuple]

    @property
    def label(self) -> str:
        return f"{self.sensor} {self.name}"


def parameters() -> List[Parameter]:
    """Every parameter of the paper's model of both triads, in display order."""
    out = []
    for sensor, _ in TRIADS:
        for i, a in enumerate("xyz"):
            out.append(Parameter(sensor, f"bias_{a}", "bias", UNITS[sensor], ("bias", i)))
        for i, a in enumerate("xyz"):
            out.append(Parameter(sensor, f"scale_{a}", "scale", "1", ("scale", i)))
        for e in E_TERMS:
            out.append(Parameter(sensor, e, "nonorthogonality", "1", None))
    return out


def value_and_sigma(entry: HistoryEntry, p: Parameter) -> tuple:
    """The parameter's value in a calibration and its recorded 1σ (NaN when none is recorded)."""
    value = float(entry.record.triad(p.sensor).parameters()[p.name])
    sigma = math.nan
    unc = entry.record.uncertainty.get(p.sensor) or {}
    if p.sigma_key is not None and p.sigma_key[0] in unc:
        sigma = float(unc[p.sigma_key[0]][p.sigma_key[1]])
    return value, sigma


@dataclass(frozen=True)
class Move:
    """A parameter that moved between two calibrations: values, their difference, the combined 1σ
    ``sqrt(σ_before² + σ_after²)`` and ``z = |Δ| / combined``."""
    parameter: Parameter
    before: float
    after: float
    sigma: float

    @property
    def delta(self) -> float:
        return self.after - self.before

    @property
    def z(self) -> float:
        return abs(self.delta) / self.sigma if self.sigma > 0 else math.inf

    def describe(self) -> str:
        return (f"{self.parameter.label} {self.delta:+.4g} {self.parameter.unit} ({self.z:.1f}σ; "
                f"{self.before:.6g} → {self.after:.6g} ± {self.sigma:.2g} combined)")


@dataclass
class Change:
    """Calibration ``index`` (0-based in the history) compared with the one before it."""
    index: int
    id: str
    date: _dt.datetime
    previous_id: str
    moves: List[Move] = field(default_factory=list)
    untested: List[str] = field(default_factory=list)   # parameters without a 1σ in either record

    @property
    def flagged(self) -> bool:
        return bool(self.moves)

    def reading(self) -> str:
        """What the parameters that moved suggest (a hint for the lab, not a diagnosis)."""
        by = {(m.parameter.sensor, m.parameter.kind) for m in self.moves}
        hints = []
        if {s for s, _ in by} == {"acc", "mag"}:
            hints.append("both triads moved at once: check the stand (a pose held off, a different stand) before "
                         "the probe")
        for sensor, name in TRIADS:
            if (sensor, "bias") in by:
                hints.append(f"{name} bias shift: " + ("the probe magnetised (a knock, a magnet nearby) or sensor "
                                                       "ageing" if sensor == "mag" else "a knock or sensor ageing"))
            if (sensor, "scale") in by:
                hints.append(f"{name} scale change: sensor ageing, or the stand's temperature or reference field")
        return "; ".join(hints)


@dataclass(frozen=True)
class Overdue:
    """The probe is overdue at ``at``: its last calibration (None: never calibrated) is
    ``age_days`` old, beyond ``interval_days``."""
    at: _dt.datetime
    last: Optional[_dt.datetime]
    age_days: float
    interval_days: float

    def describe(self) -> str:
        if self.last is None:
            return f"OVERDUE at {self.at:%Y-%m-%d}: never calibrated"
        return (f"OVERDUE at {self.at:%Y-%m-%d}: last calibrated {self.last:%Y-%m-%d}, {self.age_days:.0f} days ago, "
                f"beyond the calibration interval of {self.interval_days:g} days "
                f"(due {self.last + _dt.timedelta(days=self.interval_days):%Y-%m-%d})")


@dataclass
class History:
    """A probe's history analysed (:func:`analyse`): its entries, the change of each calibration
    from the one before (``changes[n-1]`` compares entries n−1 and n), and whether it is overdue."""
    probe: ProbeInfo
    entries: List[HistoryEntry]
    changes: List[Change]
    overdue: Optional[Overdue]
    at: _dt.datetime
    k: float

    @property
    def flagged(self) -> List[Change]:
        return [c for c in self.changes if c.flagged]


def analyse(probe: ProbeInfo, entries: List[HistoryEntry], at: Optional[_dt.datetime] = None,
            k: float = K_SIGMA) -> History:
    """Compare each calibration with the one before (|Δ| > k·sqrt(σ1² + σ2²): moved) and check
    the interval at ``at`` (aware; default now)."""
    if not (k > 0 and math.isfinite(k)):
        raise ValueError(f"k must be a positive number of σ, got {k}")
    at = aware(at, "history date") if at is not None else _dt.datetime.now(_dt.timezone.utc)
    params = parameters()
    changes = []
    for n in range(1, len(entries)):
        a, b = entries[n - 1], entries[n]
        ch = Change(index=n, id=b.id, date=b.date, previous_id=a.id)
        for p in params:
            va, sa = value_and_sigma(a, p)
            vb, sb = value_and_sigma(b, p)
            if not (math.isfinite(sa) and math.isfinite(sb)):
                ch.untested.append(p.label)
                continue
            mv = Move(p, va, vb, math.hypot(sa, sb))
            if abs(mv.delta) > k * mv.sigma:
                ch.moves.append(mv)
        changes.append(ch)
    overdue = None
    last = entries[-1].date if entries else None
    if last is None:
        overdue = Overdue(at, None, math.inf, probe.calibration_interval_days)
    else:
        age = (at - last).total_seconds() / 86400.0
        if age > probe.calibration_interval_days:
            overdue = Overdue(at, last, age, probe.calibration_interval_days)
    return History(probe, list(entries), changes, overdue, at, float(k))


# ---------------------------------------------------------------------------------------------
# Text
# ---------------------------------------------------------------------------------------------
def _fmt(value: float, sigma: float) -> str:
    """``value±σ`` to the σ's second significant digit; the value alone (6 digits) without σ."""
    if not math.isfinite(sigma) or sigma <= 0:
        return f"{value:.6g}"
    dec = max(0, 1 - int(math.floor(math.log10(sigma))))
    return f"{value:.{dec}f}±{sigma:.{dec}f}"


def format_history(h: History) -> str:
    """The history as text: the probe, one row per parameter with a column per calibration
    (value ± 1σ), what moved, and the overdue flag."""
    p = h.probe
    lines = [f"probe {p.serial}" + (f" ({p.model})" if p.model else "") + (f" — {p.note}" if p.note else ""),
             f"calibration interval {p.calibration_interval_days:g} days; {len(h.entries)} calibration(s)"]
    if not h.entries:
        lines.append(h.overdue.describe() if h.overdue else "")
        return "\n".join(lines)
    lines.append("")
    for n, e in enumerate(h.entries):
        extra = [x for x in (e.operator_note, f"raw log sha256 {e.raw_log_sha256[:12]}…" if e.raw_log_sha256 else "")
                 if x]
        lines.append(f"  #{n + 1} {e.date:%Y-%m-%d %H:%M} UTC  record {e.id}  {e.method.split(' (')[0]}"
                     + (f"  — {'; '.join(extra)}" if extra else ""))
    lines.append("")
    moved = {(c.index, m.parameter) for c in h.changes for m in c.moves}
    head = ["parameter", "unit"] + [f"#{n + 1} {e.date:%Y-%m-%d}" for n, e in enumerate(h.entries)]
    rows = []
    for par in parameters():
        row = [par.label, par.unit]
        for n, e in enumerate(h.entries):
            v, s = value_and_sigma(e, par)
            row.append(_fmt(v, s) + (" *" if (n, par) in moved else ""))
        rows.append(row)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    lines.append("  ".join(x.ljust(w) if i < 2 else x.rjust(w) for i, (x, w) in enumerate(zip(head, widths))))
    for r in rows:
        lines.append("  ".join(x.ljust(w) if i < 2 else x.rjust(w) for i, (x, w) in enumerate(zip(r, widths))))
    lines.append(f"value±1σ as recorded by the calibrator; no σ is recorded for the non-orthogonality terms "
                 f"(not tested). * moved: |Δ| > {h.k:g}·sqrt(σ_prev² + σ²)")
    lines.append("")
    for c in h.changes:
        if c.flagged:
            lines.append(f"FLAG #{c.index + 1} {c.date:%Y-%m-%d} (record {c.id}) differs from #{c.index} "
                         f"(record {c.previous_id}) beyond {h.k:g}σ combined in {len(c.moves)} parameter(s): "
                         + ", ".join(m.parameter.label for m in c.moves))
            for m in c.moves:
                lines.append(f"    {m.describe()}")
            lines.append(f"    may mean: {c.reading()}")
    if h.changes and not h.flagged:
        lines.append(f"no calibration differs from the one before beyond {h.k:g}σ combined")
    lines.append(h.overdue.describe() if h.overdue else
                 f"not overdue at {h.at:%Y-%m-%d}: last calibrated {h.entries[-1].date:%Y-%m-%d}, due "
                 f"{h.entries[-1].date + _dt.timedelta(days=h.probe.calibration_interval_days):%Y-%m-%d}")
    return "\n".join(lines)


def to_json(h: History) -> dict:
    """The history as plain JSON types (``fleet history --json``)."""
    return {
        "serial": h.probe.serial, "at": h.at.isoformat(), "k_sigma": h.k,
        "calibration_interval_days": h.probe.calibration_interval_days,
        "calibrations": [{"date": e.date.isoformat(), "id": e.id, "method": e.method,
                          "operator_note": e.operator_note, "raw_log_sha256": e.raw_log_sha256,
                          "parameters": {p.label: dict(zip(("value", "sigma"), [None if not math.isfinite(x) else x
                                                                                 for x in value_and_sigma(e, p)]))
                                         for p in parameters()}}
                         for e in h.entries],
        "flags": [{"index": c.index, "id": c.id, "previous_id": c.previous_id, "date": c.date.isoformat(),
                   "moved": [{"parameter": m.parameter.label, "delta": m.delta, "sigma": m.sigma, "z": m.z}
                             for m in c.moves]} for c in h.flagged],
        "overdue": None if h.overdue is None else {
            "last": None if h.overdue.last is None else h.overdue.last.isoformat(),
            "age_days": None if not math.isfinite(h.overdue.age_days) else h.overdue.age_days,
            "interval_days": h.overdue.interval_days},
    }


# ---------------------------------------------------------------------------------------------
# HTML with plots
# ---------------------------------------------------------------------------------------------
def _triad_figure(h: History, sensor: str, name: str) -> str:
    """One triad's parameters against date: the value, its 1σ band where recorded, the
    calibrations where that parameter moved ringed in red, and the overdue span shaded."""
    from ..lab.report import figure_png, pyplot

    plt = pyplot()
    pars = [p for p in parameters() if p.sensor == sensor]
    fig, axs = plt.subplots(4, 3, figsize=(13, 10), sharex=True)
    dates = [e.date for e in h.entries]
    moved = {(c.index, m.parameter) for c in h.changes for m in c.moves}
    for ax, p in zip(axs.flat, pars):
        vs = np.array([value_and_sigma(e, p) for e in h.entries], dtype=float)
        v, s = vs[:, 0], vs[:, 1]
        ax.plot(dates, v, "o-", color="#1f5fa8", ms=4, lw=1)
        if np.all(np.isfinite(s)):
            ax.fill_between(dates, v - s, v + s, color="#1f5fa8", alpha=0.2, lw=0, step=None, label="1σ")
            ax.errorbar(dates, v, yerr=s, fmt="none", ecolor="#1f5fa8", elinewidth=0.8, capsize=2)
            ttl = f"{p.name} ({p.unit}), 1σ band"
        else:
            ttl = f"{p.name} ({p.unit}) — no 1σ recorded"
        for n, d in enumerate(dates):
            if (n, p) in moved:
                ax.plot([d], [v[n]], "o", ms=11, mfc="none", mec="#c0392b", mew=2)
        if h.overdue is not None and h.overdue.last is not None:
            ax.axvspan(h.overdue.last + _dt.timedelta(days=h.overdue.interval_days), h.at, color="#c0392b",
                       alpha=0.08)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_title(ttl, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
    for ax in axs.flat[len(pars):]:
        ax.set_visible(False)
    # every panel shows the same dates (shared x): matplotlib's date ticks, found once and fixed;
    # left to each panel, its date-rule search ran at each of the layout's and the PNG's passes,
    # for every panel: a third of the page's time
    from matplotlib.dates import AutoDateFormatter, AutoDateLocator
    from matplotlib.ticker import FixedLocator

    dates_axis = axs.flat[0].xaxis
    auto = AutoDateLocator()
    auto.set_axis(dates_axis)
    ticks = auto()
    dates_axis.set_major_locator(FixedLocator(ticks))        # sharex: one locator for all
    dates_axis.set_major_formatter(AutoDateFormatter(auto))
    fig.autofmt_xdate()
    fig.suptitle(f"probe {h.probe.serial}: {name} parameters by calibration date (red ring: moved beyond "
                 f"{h.k:g}σ combined from the calibration before; red span: overdue)", fontsize=10)
    fig.tight_layout()
    return figure_png(fig)


def to_html(h: History) -> str:
    """A self-contained HTML page (plots as PNG data URIs, like the lab report): the flags, the
    table of :func:`format_history` and each triad's parameters over time."""
    esc = html.escape
    flags = [f"<li class='flag'>#{c.index + 1} {c.date:%Y-%m-%d} (record {esc(c.id)}): moved beyond {h.k:g}σ "
             f"combined — {esc(', '.join(m.describe() for m in c.moves))}. <em>{esc(c.reading())}</em></li>"
             for c in h.flagged]
    if h.overdue is not None:
        flags.append(f"<li class='flag'>{esc(h.overdue.describe())}</li>")
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>Calibration history of probe {esc(h.probe.serial)}</title>",
        "<style>body{font-family:sans-serif;max-width:1300px;margin:1em auto;color:#222}"
        "pre{background:#f6f6f6;padding:.6em;overflow-x:auto;font-size:12px}.flag{color:#c0392b}"
        "img{max-width:100%}</style></head><body>",
        f"<h1>Calibration history of probe {esc(h.probe.serial)}</h1>",
        f"<p>{len(h.entries)} calibration(s); interval {h.probe.calibration_interval_days:g} days; "
        f"checked at {h.at:%Y-%m-%d %H:%M} UTC.</p>",
        "<h2>Flags</h2>",
        "<ul>" + "".join(flags) + "</ul>" if flags else "<p>none</p>",
        "<h2>Parameters</h2>", f"<pre>{esc(format_history(h))}</pre>",
    ]
    if h.entries:
        for sensor, name in TRIADS:
            parts += [f"<h2>{name.capitalize()}</h2>", f"<img alt='{name} parameters over time' "
                      f"src='{_triad_figure(h, sensor, name)}'>"]
        parts.append("<p>The 1σ bands are the calibrator's (the twelve-position fit's covariance of biases and "
                     "scales); the non-orthogonality terms carry no recorded σ, so they are drawn without a band "
                     "and not tested.</p>")
    parts.append("</body></html>")
    return "\n".join(parts)

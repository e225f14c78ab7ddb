"""A report page read back from a real browser: headless Chromium lays the HTML out, a script
injected into a copy of the page measures what a reader sees, and the measurements come back
in the dumped DOM (``--dump-dom``: one Chromium start per page, no driver, no extra package).

What is measured (CSS pixels, in a window ``WIDTH`` wide):

* the blocks a reader reads — headings, paragraphs, ``pre``, tables, list items, images, the
  summary — each with its box; a block inside another measured block is left to its container;
* which pairs of those boxes overlap (by more than 1 px each way: borders may touch);
* each image: its natural size (0: it did not decode) and its laid-out size;
* whether the page is wider than the window (a table or a picture running off the page);
* the visible text (``innerText``) and the order of the blocks.

:func:`check` asserts what the issue asks of every report; a test without Chromium is skipped by
:func:`layout` with the reason (``scripts/setup.sh`` installs Debian's ``chromium`` as root).
"""
from __future__ import annotations

import html
import json
import os
import re
import resource
import shutil
import subprocess
import tempfile

import pytest

WIDTH, HEIGHT = 1280, 900
BINARIES = ("chromium", "chromium-browser", "google-chrome", "chrome")
#: What a report never prints where a figure is missing (it says why instead).
#: (``nan`` in any case; ``None`` as Python prints it — "none" is a word of the reports.)
MISSING_WORDS = re.compile(r"\b(?i:nan)\b|\bNone\b|\b0 holds\b")

_PROBE = r"""<script>
window.addEventListener('load', () => {
  const SEL = 'h1,h2,h3,h4,p,pre,table,li,img,section.summary';
  const all = Array.from(document.querySelectorAll(SEL));
  // a block inside another measured block is part of it (a table's cells, a list item's text)
  const blocks = all.filter(e => !all.some(o => o !== e && o.contains(e) && !o.matches('section.summary')));
  const box = e => { const r = e.getBoundingClientRect();
    return {x: r.left + scrollX, y: r.top + scrollY, w: r.width, h: r.height}; };
  const name = e => e.tagName.toLowerCase() + (e.id ? '#' + e.id : '') +
    (e.className ? '.' + e.className : '') + ': ' + (e.alt || e.innerText || '').slice(0, 60).replace(/\s+/g, ' ');
  const out = {blocks: [], overlaps: [], images: [], width: innerWidth,
               scroll_width: document.documentElement.scrollWidth, text: document.body.innerText};
  const leaf = blocks.filter(e => !e.matches('section.summary'));
  const b = leaf.map(box);
  leaf.forEach((e, i) => out.blocks.push({name: name(e), box: b[i],
                                          in_summary: !!e.closest('section.summary')}));
  for (let i = 0; i < b.length; i++) for (let j = i + 1; j < b.length; j++) {
    const dx = Math.min(b[i].x + b[i].w, b[j].x + b[j].w) - Math.max(b[i].x, b[j].x);
    const dy = Math.min(b[i].y + b[i].h, b[j].y + b[j].h) - Math.max(b[i].y, b[j].y);
    if (dx > 1 && dy > 1) out.overlaps.push([name(leaf[i]), name(leaf[j]), dx, dy]);
  }
  document.querySelectorAll('img').forEach(e => out.images.push(
    {name: name(e), natural: [e.naturalWidth, e.naturalHeight], box: box(e)}));
  const s = document.querySelector('section.summary');
  out.summary = s ? {box: box(s), text: s.innerText, tables: s.querySelectorAll('table').length} : null;
  const pre = document.createElement('pre');
  pre.id = '__layout__';
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>"""


def chromium() -> str | None:
    for name in BINARIES:
        path = shutil.which(name)
        if path:
            return path
    return None


def layout(page) -> dict:
    """Lay ``page`` (a path) out in headless Chromium and return the measurements of the module
    docstring, plus ``cpu_s``: the CPU seconds the browser took (all its processes)."""
    exe = chromium()
    if exe is None:
        pytest.skip("no Chromium to lay the report out (apt-get install chromium; scripts/setup.sh does as root)")
    with tempfile.TemporaryDirectory(prefix="report-layout-") as tmp:
        with open(page, encoding="utf-8") as fh:
            text = fh.read()
        at = text.rfind("</body>")
        copy = os.path.join(tmp, "page.html")
        with open(copy, "w", encoding="utf-8") as fh:
            fh.write(text[:at] + _PROBE + text[at:] if at >= 0 else text + _PROBE)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        proc = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                               "--no-first-run", "--disable-extensions", "--disable-dev-shm-usage",
                               f"--user-data-dir={os.path.join(tmp, 'profile')}", f"--window-size={WIDTH},{HEIGHT}",
                               "--virtual-time-budget=10000", "--dump-dom", "file://" + copy],
                              capture_output=True, text=True, timeout=120, check=False)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    m = re.search(r'<pre id="__layout__">(.*?)</pre>', proc.stdout, re.DOTALL)
    assert m, f"Chromium gave no layout of {page} (exit {proc.returncode}): {proc.stderr[-2000:]}"
    out = json.loads(html.unescape(m.group(1)))
    out["cpu_s"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return out


def check(lay: dict, images: int) -> None:
    """What every report must give a reader: the summary first (words and a table), ``images``
    figures drawn with a size, no two blocks on top of each other, nothing off the page, and no
    ``nan``, ``None`` or "0 holds" where a figure is missing."""
    s = lay["summary"]
    assert s is not None, "the report has no summary (section.summary)"
    assert s["tables"] >= 1 and len(s["text"].split()) >= 12, s["text"]
    first = [b for b in lay["blocks"] if not b["name"].startswith("h1")]
    assert first and first[0]["in_summary"], f"the first block after the title is not the summary: {first[:1]}"
    assert all(b["box"]["y"] >= s["box"]["y"] + s["box"]["h"] - 1 for b in first if not b["in_summary"]), \
        "a block stands above the summary's end"
    assert len(lay["images"]) == images, [i["name"] for i in lay["images"]]
    for im in lay["images"]:
        assert min(im["natural"]) > 0 and im["box"]["w"] > 100 and im["box"]["h"] > 50, im
        assert im["box"]["x"] >= 0 and im["box"]["x"] + im["box"]["w"] <= lay["width"] + 0.5, im
    assert not lay["overlaps"], lay["overlaps"]
    assert lay["scroll_width"] <= lay["width"], f"the page is {lay['scroll_width']} px wide in a {lay['width']} px window"
    bad = sorted({m.group(0) for m in MISSING_WORDS.finditer(lay["text"])})
    assert not bad, [lay["text"][max(0, m.start() - 80):m.end() + 40] for m in MISSING_WORDS.finditer(lay["text"])]


# ---- inside the figures: the PNGs of a report are matplotlib's, so matplotlib measures them ----
def figure_collisions(fig) -> list:
    """Texts of ``fig`` that collide, as words: any two of its titles, axis labels, tick labels
    (those in view), annotations and legends whose boxes overlap by more than 1 px each way, and a
    title, label or tick label over the plot area of another panel (a twin axis is the same panel)."""
    from matplotlib.transforms import Bbox

    fig.draw_without_rendering()                 # the layout and the ticks, no pixels: a tenth of a draw
    r = fig.canvas.get_renderer()
    items = []                                   # (words, box, panel or None, is inside its panel)

    def add(t, ax, kind, inside=False):
        if t.get_visible() and t.get_text().strip():
            bb = t.get_window_extent(r)
            if bb.width > 0 and bb.height > 0:
                items.append((f"{kind} {t.get_text()[:40]!r}", bb, ax, inside))

    def panel(ax):
        return tuple(round(v, 1) for v in ax.bbox.extents)

    if fig._suptitle is not None:
        add(fig._suptitle, None, "suptitle")
    for t in fig.texts:
        if t is not fig._suptitle:
            add(t, None, "text")
    for leg in fig.legends:
        items.append(("figure legend", leg.get_window_extent(r), None, False))
    for ax in fig.axes:
        for t in (ax.title, ax._left_title, ax._right_title):
            add(t, ax, "title")
        add(ax.xaxis.label, ax, "x label")
        add(ax.yaxis.label, ax, "y label")
        for axis, kind in ((ax.xaxis, "x tick"), (ax.yaxis, "y tick")):
            lo, hi = sorted(axis.get_view_interval())
            slack = 1e-9 * max(abs(lo), abs(hi), 1.0)
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if lo - slack <= tick.get_loc() <= hi + slack:
                    add(tick.label1, ax, kind)
                    add(tick.label2, ax, kind)
        for t in ax.texts:
            add(t, ax, "annotation", inside=True)
        if ax.get_legend() is not None:
            items.append(("legend", ax.get_legend().get_window_extent(r), ax, True))

    def overlap(a, b):
        i = Bbox.intersection(a, b)
        return i is not None and i.width > 1 and i.height > 1

    out = []
    for k, (na, a, pa, _) in enumerate(items):
        for nb, b, pb, _ in items[k + 1:]:
            if overlap(a, b):
                out.append(f"{na} and {nb}")
    for name, bb, ax, inside in items:
        if inside:
            continue
        for other in fig.axes:
            if other is ax or (ax is not None and panel(other) == panel(ax)):
                continue
            if overlap(bb, other.bbox):
                out.append(f"{name} over another panel's plot")
    title = fig._suptitle.get_text() if fig._suptitle is not None else fig.axes[0].get_title() if fig.axes else ""
    return [f"{title[:50]!r}: {c}" for c in dict.fromkeys(out)]


class FiguresChecked:
    """Within ``with FiguresChecked() as found:``, every figure a report makes (through
    :func:`lab.report.figure_png`) is checked by :func:`figure_collisions` before it is saved;
    ``found.collisions`` lists what collided, ``found.figures`` counts them."""

    def __enter__(self):
        from inclinometer_calib.lab import report

        self._report, self._png = report, report.figure_png
        self.collisions, self.figures = [], 0

        def checked(fig):
            self.figures += 1
            self.collisions += figure_collisions(fig)
            return self._png(fig)

        report.figure_png = checked
        return self

    def __exit__(self, *exc):
        self._report.figure_png = self._png
        return False

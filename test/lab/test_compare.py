"""The field effect ladder: one bag replayed through several records (``reprocess --compare``)."""
import contextlib
import io
import re

import numpy as np
import pytest
import report_layout

from inclinometer_calib.lab import compare
from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.io.probelog import read_csv
from inclinometer_calib.correct.reprocess import write_probe_bag

# one worker runs the whole module (scripts/test.sh: --dist loadgroup), so that its module
# fixtures, which build the data every test reads, run once, not once per worker
pytestmark = [pytest.mark.xdist_group("compare"), pytest.mark.long(10)]

pytest.importorskip("matplotlib")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("compare")
    sim = d / "sim"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(["simulate", "--out", str(sim), "--seed", "41", "--effect", "temperature_bias:mag=3",
                     "--val-temp", "25:60", "--rate", "50"]) == 0
        assert main(["twelve-position", str(sim / "cal.csv"), "--site", str(sim / "site.yaml"),
                     "-o", str(d / "base.yaml")]) == 0
        assert main(["lab", "fit", "--cal", str(sim / "cal.csv"), "--val", str(sim / "val.csv"), "--site",
                     str(sim / "site.yaml"), "--effects", "temperature_bias:mag", "-o", str(d / "model.yaml"),
                     "--quiet"]) == 0
        assert main(["bag", "from-csv", str(sim / "val.csv"), "-o", str(d / "val.mcap")]) == 0
    return d


class RunsKept:
    """Within ``with RunsKept() as kept:``, what every :func:`compare.compare` the command line calls
    returns (``kept.runs``, one list per call): the tests read the runs the command computed and
    wrote out, instead of replaying the bag through the same records a second time."""

    def __enter__(self):
        self._compare, self.runs = compare.compare, []

        def kept(*args, **kwargs):
            self.runs.append(self._compare(*args, **kwargs))
            return self.runs[-1]

        compare.compare = kept
        return self

    def __exit__(self, *exc):
        compare.compare = self._compare
        return False


@pytest.fixture(scope="module")
def ladder(run):
    """``reprocess --compare none base model``: its output, the collisions inside its figures, and
    the runs it computed (by name)."""
    d = run
    out = io.StringIO()
    with contextlib.redirect_stdout(out), report_layout.FiguresChecked() as figures, RunsKept() as kept:
        assert main(["reprocess", str(d / "val.mcap"), "--compare", "none", str(d / "base.yaml"),
                     str(d / "model.yaml"), "-o", str(d / "cmp")]) == 0
    (runs,) = kept.runs
    return d / "cmp", out.getvalue(), figures, {r.name: r for r in runs}


def test_the_ladder_is_written_as_markdown_and_html_and_falls_with_the_labs_model(run, ladder):
    d = run
    cmp, out, _, runs = ladder
    assert "errors against the bag's reference attitudes" in out
    for name in ("compare.md", "compare.html", "uncorrected.mcap", "base.mcap", "model.mcap"):
        assert (cmp / name).is_file(), name
    md = (cmp / "compare.md").read_text()
    rows = [ln for ln in md.splitlines() if ln.startswith("| ")][1:]     # after the header
    assert [r.split("|")[1].strip() for r in rows] == ["uncorrected", "base", "model"]
    html = (cmp / "compare.html").read_text()
    assert html.count("<img alt=") == 3 and html.count("src='data:image/png;base64,") == 3
    # the runs the command wrote (compare.compare's, the same records from the same files)
    base, model = runs["base"], runs["model"]
    assert base.calibration.id == Calibration.load(d / "base.yaml").id and base.bag == str(cmp / "base.mcap")
    assert model.calibration.id == Calibration.load(d / "model.yaml").id and model.bag == str(cmp / "model.mcap")
    assert model.metrics["azimuth_rms_deg"] < 0.5 * base.metrics["azimuth_rms_deg"]
    assert base.metrics["model_misfit_flagged"] > 0 == model.metrics["model_misfit_flagged"]


def test_the_compare_report_reads_at_a_glance_in_a_browser(ladder):
    """Laid out by Chromium and read back: the summary first, in words and a table (the ladder's
    azimuth RMS model by model, the lowest record, what the field monitor says of the one that
    misses the effect), every plot drawn, nothing on top of anything, no nan — the uncorrected
    run's missing QC residuals (no site given) said why."""
    cmp, _, _, _ = ladder
    lay = report_layout.layout(cmp / "compare.html")
    report_layout.check(lay, images=3)
    said = lay["summary"]["text"]
    md = (cmp / "compare.md").read_text()
    rows = [ln.split("|") for ln in md.splitlines() if ln.startswith("| ")][1:]     # after the header
    az = {r[1].strip(): float(r[6]) for r in rows}
    said_az = re.search(r"Azimuth RMS (\S+)° uncorrected → (\S+)° base → (\S+)° model", said)
    assert said_az, said
    for name, value in zip(("uncorrected", "base", "model"), map(float, said_az.groups())):
        assert value == pytest.approx(az[name], rel=5e-3, abs=1e-4), name      # 3 digits against the table's 4
    assert "Lowest: model — 0 of 198 stations outside the QC tolerances" in said
    assert "With base the field monitor flags" in said and "likely missing: temperature_bias:mag" in said
    assert "uncorrected: no QC residuals" in said and "give --site" in said
    print(f"Chromium: {lay['cpu_s']:.2f} CPU-s")


def test_no_text_collides_inside_the_compare_reports_figures(ladder):
    """The ladder, the residuals against temperature and time, the residuals against azimuth and
    toolface: matplotlib's own text boxes, none over another or over another panel."""
    _, _, figures, _ = ladder
    assert figures.figures == 3 and figures.collisions == []


def test_without_a_reference_the_ladder_is_the_qc_residuals(run, capsys):
    d = run
    log, _ = read_csv(d / "sim" / "val.csv")
    write_probe_bag(log, d / "noref.mcap", reference=False)
    with RunsKept() as kept:
        assert main(["reprocess", str(d / "noref.mcap"), "--compare", str(d / "base.yaml"), str(d / "model.yaml"),
                     "-o", str(d / "cmp2")]) == 0
    out = capsys.readouterr().out
    assert "no reference attitude in the bag: QC residuals against the site reference" in out
    lay = report_layout.layout(d / "cmp2" / "compare.html")       # the page in the QC residuals' words
    report_layout.check(lay, images=3)
    said = lay["summary"]["text"]
    assert re.search(r"ΔB RMS \S+ nT base → \S+ nT model; Δdip RMS \S+° → \S+°, the QC residuals", said), said
    (runs,) = kept.runs             # what the command computed and wrote: base, then model
    assert [r.name for r in runs] == ["base", "model"]
    assert "drift_rms_deg" not in runs[0].metrics
    assert runs[1].metrics["delta_b_rms_nt"] < 0.5 * runs[0].metrics["delta_b_rms_nt"]
    assert runs[1].metrics["delta_dip_rms_deg"] < 0.5 * runs[0].metrics["delta_dip_rms_deg"]


def test_an_existing_output_is_never_overwritten(run, capsys):
    d = run
    (d / "cmp3").mkdir()
    (d / "cmp3" / "base.mcap").write_text("good data")
    assert main(["reprocess", str(d / "val.mcap"), "--compare", str(d / "base.yaml"), "-o", str(d / "cmp3")]) == 2
    assert "exists" in capsys.readouterr().err
    assert (d / "cmp3" / "base.mcap").read_text() == "good data"


def test_residual_panels_are_scaled_to_the_corrected_models_not_to_the_uncorrected_degrees():
    """The demo's residual plots were scaled to the uncorrected ±30°, the corrected residuals a flat
    line: the limits come from the corrected models' values only."""
    from inclinometer_calib.lab.compare import residual_limits

    lo, hi = residual_limits([np.array([0.01, -0.02, np.nan]), np.array([0.015])])
    assert lo == -hi and 0.02 < hi < 0.025
    assert residual_limits([]) == (-1.0, 1.0) and residual_limits([np.array([np.nan])]) == (-1.0, 1.0)

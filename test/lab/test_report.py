"""The lab report's pieces (lab/report.py) and the checks the report tests read them with
(test/report_layout.py): the summary in words when a figure is missing, and collisions inside a figure."""
from types import SimpleNamespace

import pytest
import report_layout

from inclinometer_calib.lab.report import summary, summary_html

pytest.importorskip("matplotlib")


def _step(val, finding="explained", ranked=(), recommended=None):
    return SimpleNamespace(base_val=val, finding=finding, ranked=list(ranked), recommended=recommended, refused="",
                           uncertainty={}, validation_kind=val.get("kind", ""),
                           model=SimpleNamespace(describe=lambda: "base (bias, scale, nonorthogonality) + [none]"))


def test_without_reference_stations_the_lab_summary_says_why_there_are_no_angle_errors():
    """Calibration logs only: no validation angles — said in words, never nan or None."""
    steps = [_step({"stations": 0}, ranked=[SimpleNamespace(significant=False, label="axial_interference:mag:z")])]
    sentences, header, rows = summary(steps, {"stations": 0})
    text = " ".join(sentences) + " " + " ".join(" ".join(r) for r in rows)
    assert "no station with a reference attitude, so there are no angle errors to show" in text
    assert "1 candidates tried, 0 significant" in text and "explains the data to the noise" in text
    assert not report_layout.MISSING_WORDS.search(text), text
    assert [r[0] for r in rows] == ["base (paper)"]            # no uncorrected row without its figures
    page = summary_html(sentences, header, rows)
    assert page.startswith("<section class='summary'><h2>Summary</h2><p>") and "<h3>" not in page


def test_a_rung_that_adds_an_effect_is_said_with_what_it_gained():
    rec = SimpleNamespace(label="temperature_bias:mag:xyz", significant=True)
    steps = [_step({"stations": 198, "kind": "field", "azimuth_rms_deg": 0.41, "drift_rms_deg": 0.02},
                   "recommended", [rec], rec),
             _step({"stations": 198, "kind": "field", "azimuth_rms_deg": 0.05, "drift_rms_deg": 0.002})]
    sentences, _, rows = summary(steps, {"stations": 198, "azimuth_rms_deg": 8.1, "drift_rms_deg": 1.5})
    assert sentences[0] == ("The lab adds temperature_bias:mag:xyz to the paper's model: azimuth RMS 0.41° → 0.05°, "
                            "drift RMS 0.02° → 0.002° on the validation data, the references never fitted "
                            "(uncorrected: azimuth 8.1°, drift 1.5°).")
    assert "Candidates tried round by round: 1, 0; significant: 1, 0." in sentences
    assert [r[0] for r in rows] == ["uncorrected", "base (paper)", "+ temperature_bias:mag:xyz"]


def test_a_collision_inside_a_figure_is_found_and_a_tight_layout_clears_it():
    """The check the report tests run on every figure can fail: two panels whose long tick labels
    and y labels run into the panel beside them, until the layout makes room."""
    from inclinometer_calib.lab.report import pyplot

    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(6, 3))
    for a in axs:
        a.plot([0, 1], [123456789.0, 987654321.0])
        a.ticklabel_format(style="plain")
        a.set_ylabel("a y label as long as a magnetometer's")
        a.set_title("a title as long as the panel is wide and longer")
    found = report_layout.figure_collisions(fig)
    assert any("over another panel's plot" in c for c in found), found
    assert any("title" in c and " and title" in c for c in found), found
    fig.tight_layout()
    axs[0].set_title("a short title")
    axs[1].set_title("another")
    assert report_layout.figure_collisions(fig) == []
    plt.close(fig)


def test_a_log_axis_is_labelled_in_plain_numbers_at_matplotlibs_ticks():
    """plain_log_ticks: the ticks, and the minor ones labelled on a short span, are matplotlib's
    own; the labels are 0.001, 0.02, 0.1 — not math text (each of which pyparsing parses)."""
    from inclinometer_calib.lab.report import plain_log_ticks, pyplot

    plt = pyplot()
    fig, axes = plt.subplots(2, 2)
    for row, y in zip(axes, ([0.0015, 0.015, 0.35], [0.012, 0.03, 0.05])):    # three decades; under one
        for ax in row:
            ax.plot([0, 1, 2], y)
            ax.set_yscale("log")
        plain_log_ticks(row[1].yaxis)
    fig.canvas.draw()

    def labels(ax, minor):
        return [(t.get_position()[1], t.get_text()) for t in ax.yaxis.get_ticklabels(minor=minor) if t.get_text()]

    for (mathtext, plain), minor in ((axes[0], False), (axes[1], True)):
        mathtext, plain = labels(mathtext, minor), labels(plain, minor)
        assert plain and [p for p, _ in plain] == [p for p, _ in mathtext]     # the same ticks labelled
        assert all("$" in s for _, s in mathtext)
        assert [s for _, s in plain] == [f"{p:g}" for p, _ in plain]
    assert [s for _, s in labels(axes[0][1], False)][:3] == ["0.001", "0.01", "0.1"]
    assert "0.02" in [s for _, s in labels(axes[1][1], True)]
    plt.close(fig)

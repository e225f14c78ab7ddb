"""The field monitor: the lab's diagnosis on a survey's residuals against the site, station by station."""
import contextlib
import io

import numpy as np
import pytest

from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.lab.field import FieldMonitor, headline
from inclinometer_calib.correct.pipeline import SurveyProcessor
from inclinometer_calib.io.probelog import read_csv, segment_stations


_SURVEYS = {}


def _survey(tmp_path, effects=(), val_temp="25:60:40"):
    """The stand's record (twelve poses at 25 °C) and the survey's stations of a simulated probe
    (made once per module for the same effects and temperatures: the tests only read them)."""
    key = (tuple(effects), val_temp)
    if key not in _SURVEYS:
        _SURVEYS[key] = _simulated_survey(tmp_path, effects, val_temp)
    return _SURVEYS[key]


def _simulated_survey(tmp_path, effects, val_temp):
    args = ["simulate", "--out", str(tmp_path), "--seed", "31", "--val-temp", val_temp]
    for e in effects:
        args += ["--effect", e]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(args) == 0
        assert main(["twelve-position", str(tmp_path / "cal.csv"), "--site", str(tmp_path / "site.yaml"),
                     "-o", str(tmp_path / "base.yaml")]) == 0
    log, _ = read_csv(tmp_path / "val.csv")
    stations, _ = segment_stations(log)
    return Calibration.load(tmp_path / "base.yaml"), Calibration.load(tmp_path / "truth_coeffs.yaml"), stations


def _run(cal, stations, window=30):
    proc = SurveyProcessor(calibration=cal, monitor=FieldMonitor(window=window))
    return [proc.process(st) for st in stations], proc.monitor


def test_a_model_that_explains_the_survey_raises_no_alarm(tmp_path):
    base, _, stations = _survey(tmp_path)
    fields, _ = _run(base, stations)
    assert not any(f["model_misfit"] for f in fields)


# the temperature-bias survey serves two tests: one xdist group, so that they share it under scripts/test.sh
@pytest.mark.xdist_group("lab-field-temperature")
def test_a_missing_temperature_effect_is_named_with_its_size(tmp_path):
    base, truth, stations = _survey(tmp_path, ["temperature_bias:mag=3"])
    fields, monitor = _run(base, stations)
    flagged = [f for f in fields if f["model_misfit"]]
    assert len(flagged) > len(fields) // 2
    v = monitor.last
    assert v.candidates[0]["label"] == "temperature_bias:mag:xyz", v.text
    assert "no longer explains the survey" in v.text and "temperature" in v.text
    # a report's summary says it in one line: the record, and the effect the candidates name
    assert headline(v.text) == (f"the model of record {base.id} no longer explains the survey; likely missing: "
                                f"{v.candidates[0]['label']}")
    est = np.array(v.candidates[0]["estimate"])
    np.testing.assert_allclose(est, 3.0, rtol=0.35)      # a window's estimate of the 3 nT/°C
    # the true model explains the same survey: no alarm
    fields, _ = _run(truth, stations)
    assert not any(f["model_misfit"] for f in fields)


def test_axial_interference_is_told_from_a_temperature_effect(tmp_path):
    base, _, stations = _survey(tmp_path, ["axial_interference=300"], val_temp="25:25")
    fields, monitor = _run(base, stations)
    assert any(f["model_misfit"] for f in fields)
    assert monitor.last.candidates[0]["label"] == "axial_interference:mag:z", monitor.last.text


@pytest.mark.xdist_group("lab-field-temperature")
def test_the_window_starts_again_with_another_record(tmp_path):
    base, truth, stations = _survey(tmp_path, ["temperature_bias:mag=3"])
    proc = SurveyProcessor(calibration=base, monitor=FieldMonitor(window=20))
    for st in stations[:60]:
        proc.process(st)
    assert proc.monitor.last.misfit
    proc.set_calibration(truth)
    f = proc.process(stations[60])
    assert not f["model_misfit"] and proc.monitor.last.stations == 1

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


def test_each_candidate_signature_has_the_bits_of_its_parameter_alone():
    """The monitor applies the record's chain once, stage by stage, and stacks every parameter
    (FieldMonitor._candidates): each signature column is still, bit for bit, the plain derivation
    — the chain with the effect at its typical size, back through the correction matrix, the
    invariants' change per unit of the parameter."""
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core.frames import Site, rotate
    from inclinometer_calib.lab.field import CHANNELS, _invariants

    probe = sim.build_probe(3)
    cal = Calibration(acc=probe.acc, mag=probe.mag, site=Site())
    rng = np.random.default_rng(4)
    n = 30
    g = rng.normal(size=(n, 3))
    g *= 9.80665 / np.linalg.norm(g, axis=1)[:, None]
    b = rng.normal(size=(n, 3))
    b *= 50000.0 / np.linalg.norm(b, axis=1)[:, None]
    temp, time = np.linspace(20.0, 45.0, n), np.linspace(0.0, 3600.0, n)
    monitor = FieldMonitor()
    monitor.reset(cal)
    cands = monitor._candidates([{"g": g[i], "b": b[i], "temp": temp[i], "time": time[i]} for i in range(n)])
    stages = {eff.stage for eff, _ in cands}
    assert {"tool", "gain", "output"} <= stages and any(eff.n_params == 9 for eff, _ in cands)
    ctx = fx.Context(temperature_c=temp, time_s=time)
    x = {"acc": g, "mag": b}
    base_inv = _invariants(g, b)
    for eff, cols in cands:
        chain = cal.model.chain(eff.sensor, "val")
        base = fx.apply_chain(x[eff.sensor], chain, ctx)
        typ = np.where(eff.param_typical() > 0, eff.param_typical(), 1.0)
        for j in range(eff.n_params):
            v = np.zeros(eff.n_params)
            v[j] = typ[j]
            eff.set_vector(v)
            dx = -rotate(cal.plan.matrix_t[eff.sensor], fx.apply_chain(x[eff.sensor], chain + [eff], ctx) - base)
            inv = _invariants(g + dx, b) if eff.sensor == "acc" else _invariants(g, b + dx)
            for k, c in enumerate(CHANNELS):
                assert np.array_equal(cols[c[0]][:, j], (inv[k] - base_inv[k]) / typ[j]), (eff.key, j, c[1])
        eff.set_vector(np.zeros(eff.n_params))

"""model.CorrectionPlan.correct_sample — the correction node's per-sample path in plain floats —
gives correct_triad's numbers bit for bit: the base model written out, a lab model through
correct_triad itself (and its errors)."""
import math

import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site


def _inputs(seed=0, n=3000):
    """Triads of m/s² and nT scale, with the values that trip arithmetic: NaN, ±inf, signed zeros,
    huge and tiny magnitudes."""
    rng = np.random.default_rng(seed)
    h = np.concatenate([rng.normal(0.0, 10.0, (n // 2, 3)), rng.normal(0.0, 50_000.0, (n - n // 2, 3))])
    h[3] = (np.nan, 1.0, 2.0)
    h[4] = (np.inf, -np.inf, 0.0)
    h[5] = (0.0, -0.0, -0.0)
    h[6] = (1e300, -1e300, 1e-300)
    h[7] = (5e-324, -5e-324, 0.0)
    return h


def _same_bits(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return (np.array_equal(np.isnan(a), np.isnan(b))
            and np.array_equal(np.nan_to_num(a, nan=0.0).view(np.int64), np.nan_to_num(b, nan=0.0).view(np.int64)))


@pytest.mark.parametrize("sensor", ["acc", "mag"])
def test_base_model_samples_equal_correct_triad_bit_for_bit(sensor):
    plan = Calibration(acc=sim.build_probe(3).acc, mag=sim.build_probe(3).mag, site=Site()).plan
    assert not plan.extra[sensor]
    h = _inputs()
    got = [plan.correct_sample(sensor, tuple(row)) for row in h.tolist()]
    assert all(type(v) is tuple and len(v) == 3 and all(type(x) is float for x in v) for v in got)
    with np.errstate(invalid="ignore"):   # inf − inf in the rows with infinities: NaN, as in plain floats
        one_by_one = np.array([plan.correct_triad(sensor, row) for row in h])
        block = plan.correct_triad(sensor, h)
    assert _same_bits(got, one_by_one)
    assert _same_bits(got, block)          # and in a block of samples
    # the base model is exact: v = C·(h − B) recovers the true vector the triad measured
    triad = plan.triads[sensor]
    true = np.array([0.3, -9.7, 1.2]) if sensor == "acc" else np.array([20_000.0, -3_000.0, 45_000.0])
    v = plan.correct_sample(sensor, tuple(triad.forward(true).tolist()))
    assert np.allclose(v, true, rtol=0, atol=1e-9 * np.abs(true).max())
    # temperature and time do not enter a base-only triad
    assert plan.correct_sample(sensor, tuple(h[10]), 60.0, 12.5) == got[10]


def test_a_lab_model_goes_through_correct_triad_with_its_temperature_and_time_and_errors():
    probe = sim.build_probe(4, ["temperature_bias:mag=3", "nonlinearity:acc=1e-3", "bias_drift:mag=40"])
    plan = Calibration(probe.model, site=Site()).plan
    assert plan.extra["acc"] and plan.extra["mag"]
    h = _inputs(1, 400)
    for sensor in ("acc", "mag"):
        for k, row in enumerate(h.tolist()):
            temp, t = 20.0 + 0.1 * k, 0.01 * k
            with np.errstate(all="ignore"):   # the inf and huge rows overflow in the effects, alike
                got = plan.correct_sample(sensor, tuple(row), temp, t)
                ref = plan.correct_triad(sensor, np.array(row), temp, t)
            assert type(got) is tuple and _same_bits(got, ref), (sensor, k)
    with pytest.raises(ValueError, match="depend on temperature"):
        plan.correct_sample("mag", (20_000.0, 0.0, 45_000.0), None, 1.0)
    assert all(math.isfinite(x) for x in plan.correct_sample("acc", (0.1, 0.2, 9.8), 25.0, 0.0))

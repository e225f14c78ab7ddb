"""survey.correct_samples agrees with the station path: bit for bit on the numpy backend (the kernel's
agreement within 1e-9 deg: test_batch_kernel.py)."""
import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site, tool_vectors
from inclinometer_calib.core.survey import (BATCH_KEYS, FLAG_AZIMUTH_UNDEFINED, FLAG_GRAVITY_OUT_OF_TOLERANCE,
                                       FLAG_INTERFERENCE, FLAG_NOT_FINITE, FLAG_TOOLFACE_IS_GRAVITY, Tolerances,
                                       correct_samples, evaluate)

PROBE = sim.build_probe(3)
CAL = Calibration(acc=PROBE.acc, mag=PROBE.mag)


def _samples(site, n=20000, seed=0):
    rng = np.random.default_rng(seed)
    drift = rng.uniform(0, 180, n)
    drift[:500] = rng.uniform(0, 4, 500)            # near vertical: magnetic toolface, azimuth undefined
    g, b = tool_vectors(site, drift, rng.uniform(0, 360, n), rng.uniform(0, 360, n))
    h = PROBE.acc.forward(g) - rng.normal(0, 0.05, (n, 3))    # raw gravity; noisy enough to trip every QC flag
    m = PROBE.mag.forward(b) + rng.normal(0, 300, (n, 3))
    h[5] = np.nan
    m[7, 2] = np.inf
    return h, m


@pytest.mark.parametrize("declination", [0.0, -7.3, 12.0])
@pytest.mark.parametrize("calibrated", [False, True])
def test_batch_equals_station_path_bitwise(declination, calibrated):
    site = Site(declination_deg=declination)
    h, m = _samples(site)
    cal = CAL if calibrated else None
    tol = Tolerances()
    out = correct_samples(h, m, cal, site, tol, block=3000, backend="numpy")   # several blocks and a partial one
    g, b = (h, m) if cal is None else cal.correct(h, m)
    with np.errstate(invalid="ignore"):
        ref = evaluate(g, b, site, tol)
    for k in BATCH_KEYS:
        np.testing.assert_array_equal(out[k], ref[k], err_msg=k)
    np.testing.assert_array_equal(out["status"], ref["status"])
    fl = out["flags"]
    for bit, key in ((FLAG_AZIMUTH_UNDEFINED, "azimuth_undefined"), (FLAG_INTERFERENCE, "interference_suspected"),
                     (FLAG_GRAVITY_OUT_OF_TOLERANCE, "gravity_out_of_tolerance"),
                     (FLAG_TOOLFACE_IS_GRAVITY, "toolface_is_gravity")):
        np.testing.assert_array_equal((fl & bit) > 0, ref[key], err_msg=key)
        assert ref[key].any() and not ref[key].all(), key          # the data exercises both cases
    assert fl[5] & FLAG_NOT_FINITE and fl[7] & FLAG_NOT_FINITE and out["status"][5] == 2


def test_batch_shapes_are_checked():
    with pytest.raises(ValueError, match="must both be \\(N, 3\\)"):
        correct_samples(np.zeros((4, 3)), np.zeros((4, 2)), site=Site())
    with pytest.raises(ValueError, match="no site reference"):
        correct_samples(np.zeros((4, 3)), np.zeros((4, 3)))   # no record owns one: never a default
    out = correct_samples(np.zeros((0, 3)), np.zeros((0, 3)), site=Site())
    assert all(len(v) == 0 for v in out.values())


def test_a_lab_model_gives_the_same_bits_sample_by_sample_and_in_blocks():
    """The one correction path with effects beyond the paper's (Newton steps, temperature and time
    of each sample): a node's sample-by-sample correction equals the batch path's, bit for bit."""
    probe = sim.build_probe(4, ["temperature_bias:mag=3", "nonlinearity:acc=1e-3", "bias_drift:mag=40"])
    site = Site()
    cal = Calibration(probe.model, site=site)
    h, m = _samples(site, n=6000)
    temp = np.linspace(20.0, 60.0, len(h))
    t = np.arange(len(h)) * 0.01
    out = correct_samples(h, m, cal, temperature_c=temp, time_s=t, block=777, backend="numpy")
    idx = np.arange(0, len(h), 97)
    one = [cal.correct(h[i], m[i], temp[i], t[i]) for i in idx]
    with np.errstate(invalid="ignore"):
        ref = evaluate(np.array([g for g, _ in one]), np.array([b for _, b in one]), site)
    for k in BATCH_KEYS:
        np.testing.assert_array_equal(out[k][idx], ref[k], err_msg=k)
    with pytest.raises(ValueError, match="depend on temperature"):
        correct_samples(h, m, cal, time_s=t)          # the model needs a temperature: said, not defaulted

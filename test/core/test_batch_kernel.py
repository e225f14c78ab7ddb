"""survey.correct_samples on the fused kernel (batchkernel): the fused numba kernel and its numpy fallback give the station
path's numbers (angles within 1e-9°, |G| and |B| and every flag exactly)."""
import math

import numpy as np
import pytest

from inclinometer_calib.core import batchkernel, survey
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site, tool_vectors, wrap180
from inclinometer_calib.core.survey import BATCH_KEYS, Tolerances, evaluate

PROBE = sim.build_probe(3)
CAL = Calibration(acc=PROBE.acc, mag=PROBE.mag)
ANGLES = ("drift_deg", "azimuth_deg", "toolface_deg", "dip_deg")
TOL_DEG = 1e-9

has_numba = pytest.mark.skipif(not batchkernel.numba_available(), reason="numba not installed")


def _samples(site, n=20000, seed=0):
    rng = np.random.default_rng(seed)
    drift = rng.uniform(0, 180, n)
    drift[:500] = rng.uniform(0, 4, 500)             # near vertical: azimuth undefined, magnetic toolface
    drift[500:700] = rng.uniform(176, 180, 200)      # near vertical, pointing up
    drift[700:720] = 0.0                             # exactly vertical
    g, b = tool_vectors(site, drift, rng.uniform(0, 360, n), rng.uniform(0, 360, n))
    h = PROBE.acc.forward(g) - rng.normal(0, 0.05, (n, 3))    # raw gravity; noisy enough to trip every QC flag
    m = PROBE.mag.forward(b) + rng.normal(0, 300, (n, 3))
    h[5] = np.nan
    m[7, 2] = np.inf
    h[9] = -0.0                                      # signed zeros into atan2
    m[9] = 0.0
    return h, m


def _station_path(h, m, cal, site, tol, temp=None, tim=None):
    with np.errstate(invalid="ignore", divide="ignore"):
        g, b = (h, m) if cal is None else cal.correct(h, m, temp, tim)
        return evaluate(g, b, site, tol)


def _assert_same(out, ref, what):
    for k in ANGLES:
        d = out[k] - ref[k]
        if k in ("azimuth_deg", "toolface_deg"):      # 359.99999999999997 and 0.0 are the same angle
            d = wrap180(d)
        both_nan = np.isnan(out[k]) & np.isnan(ref[k])
        assert np.array_equal(np.isnan(out[k]), np.isnan(ref[k])), f"{what}: {k} NaN where the station path is not"
        worst = np.max(np.abs(d[~both_nan]), initial=0.0)
        assert worst <= TOL_DEG, f"{what}: {k} differs by {worst:.3g}°"
    for k in ("total_gravity", "total_field"):
        np.testing.assert_array_equal(out[k], ref[k], err_msg=f"{what}: {k}")
    np.testing.assert_array_equal(out["status"], ref["status"], err_msg=f"{what}: status")
    fl = out["flags"]
    for bit, key in ((survey.FLAG_AZIMUTH_UNDEFINED, "azimuth_undefined"),
                     (survey.FLAG_INTERFERENCE, "interference_suspected"),
                     (survey.FLAG_GRAVITY_OUT_OF_TOLERANCE, "gravity_out_of_tolerance"),
                     (survey.FLAG_TOOLFACE_IS_GRAVITY, "toolface_is_gravity")):
        np.testing.assert_array_equal((fl & bit) > 0, ref[key], err_msg=f"{what}: {key}")
        assert ref[key].any() and not ref[key].all(), key          # the data exercise both cases


@has_numba
def test_kernel_atan2_is_within_an_ulp_of_numpy_with_its_special_values():
    _atan2 = batchkernel._kernels()._atan2          # through batchkernel: its cache directory

    rng = np.random.default_rng(3)
    y = rng.normal(size=3000) * 10.0 ** rng.uniform(-6, 6, 3000)
    x = rng.normal(size=3000) * 10.0 ** rng.uniform(-6, 6, 3000)
    got = np.array([_atan2(a, b) for a, b in zip(y, x)])
    ref = np.arctan2(y, x)
    assert np.all(np.abs(got - ref) <= np.spacing(np.abs(ref)))
    inf, nan = math.inf, math.nan
    for a, b in [(0.0, 0.0), (0.0, -0.0), (-0.0, -0.0), (-0.0, 0.0), (1.0, 0.0), (-1.0, -0.0), (0.0, -1.0),
                 (-0.0, -1.0), (inf, inf), (inf, -inf), (-inf, -inf), (-inf, 1.0), (1.0, inf), (1.0, -inf),
                 (-1.0, -inf), (nan, 1.0), (1.0, nan), (3.0, 3.0), (-2.0, 2.0), (1e-300, 1e300), (5e-324, -1.0)]:
        want = math.atan2(a, b)
        got = _atan2(a, b)
        same = got == want and math.copysign(1, got) == math.copysign(1, want)
        assert same or (math.isnan(got) and math.isnan(want)), (a, b, got, want)


@has_numba
def test_the_fast_arc_tangent_is_the_careful_one_bit_for_bit_or_nan_where_a_special_value_decides():
    _atan2_core = batchkernel._kernels()._atan2_core

    rng = np.random.default_rng(4)
    y = rng.normal(size=3000) * 10.0 ** rng.uniform(-6, 6, 3000)
    x = rng.normal(size=3000) * 10.0 ** rng.uniform(-6, 6, 3000)
    y[:40], x[40:80] = 0.0, -0.0                                  # on an axis: the signs decide
    for a, b in zip(y, x):
        fast, careful = _atan2_core(a, b, False), _atan2_core(a, b, True)
        assert fast == careful and math.copysign(1, fast) == math.copysign(1, careful), (a, b)
    inf, nan = math.inf, math.nan
    for a, b in [(1.0, inf), (-2.0, -inf), (inf, 3.0)]:           # finite against infinite: still exact
        assert _atan2_core(a, b, False) == math.atan2(a, b), (a, b)
    for a, b in [(0.0, 0.0), (-0.0, -0.0), (inf, inf), (-inf, inf), (nan, 1.0), (1.0, nan)]:
        assert math.isnan(_atan2_core(a, b, False)), (a, b)        # the kernel redoes these samples


@has_numba
def test_threads_split_the_samples_without_changing_a_bit(monkeypatch):
    site = Site(declination_deg=-3.0)
    n = 5 * batchkernel.MIN_SLICE + 17                               # five slices on two threads
    h, m = _samples(site, n=n, seed=5)
    h[n - 3] = np.nan                                                # special values in a later slice too
    h[batchkernel.MIN_SLICE + 1], m[batchkernel.MIN_SLICE + 1] = -0.0, 0.0
    assert len(batchkernel._slices(n, 2)) == 5 and len(batchkernel._slices(n, 1)) == 1
    one = survey.correct_samples(h, m, CAL, site, backend="numba", threads=1)
    two = survey.correct_samples(h, m, CAL, site, backend="numba", threads=2)
    for k in BATCH_KEYS + ("flags", "status"):
        np.testing.assert_array_equal(two[k], one[k], err_msg=k)
    _assert_same(two, _station_path(h, m, CAL, site, Tolerances()), "two threads")
    monkeypatch.setenv(batchkernel.THREADS_ENV, "3")
    assert batchkernel.resolve_threads() == 3 and batchkernel.resolve_threads(1) == 1
    monkeypatch.delenv(batchkernel.THREADS_ENV)
    assert batchkernel.resolve_threads() >= 1
    for bad in (0, -1, 1.5, True, "two"):
        with pytest.raises(ValueError, match="threads must be a whole number of threads"):
            batchkernel.resolve_threads(bad)
    monkeypatch.setenv(batchkernel.THREADS_ENV, "0")
    with pytest.raises(ValueError, match=r"\$INCLINOMETER_CALIB_BATCH_THREADS must be a whole number"):
        survey.correct_samples(h[:10], m[:10], CAL, site, backend="numba")


@has_numba
@pytest.mark.parametrize("declination", [0.0, -7.3, 12.0, 400.0])
@pytest.mark.parametrize("calibrated", [False, True])
def test_kernel_and_fallback_equal_the_station_path(declination, calibrated):
    site = Site(declination_deg=declination)
    h, m = _samples(site)
    cal = CAL if calibrated else None
    tol = Tolerances()
    ref = _station_path(h, m, cal, site, tol)
    fused = survey.correct_samples(h, m, cal, site, tol, backend="numba")
    fallback = survey.correct_samples(h, m, cal, site, tol, backend="numpy", block=3000)
    _assert_same(fused, ref, "numba")
    _assert_same(fallback, ref, "numpy")
    assert fused["flags"][5] & survey.FLAG_NOT_FINITE and fused["flags"][7] & survey.FLAG_NOT_FINITE
    assert fused["status"][5] == 2


@has_numba
def test_a_lab_model_goes_through_the_one_correction_path_then_the_kernel():
    probe = sim.build_probe(4, ["temperature_bias:mag=3", "nonlinearity:acc=1e-3", "bias_drift:mag=40"])
    site = Site(declination_deg=2.0)
    cal = Calibration(probe.model, site=site)
    h, m = _samples(site, n=6000)
    temp = np.linspace(20.0, 60.0, len(h))
    t = np.arange(len(h)) * 0.01
    out = survey.correct_samples(h, m, cal, temperature_c=temp, time_s=t, block=777, backend="numba")
    _assert_same(out, _station_path(h, m, cal, site, Tolerances(), temp, t), "lab model")
    with pytest.raises(ValueError, match="depend on temperature"):
        survey.correct_samples(h, m, cal, time_s=t, backend="numba")


def test_backend_choice(monkeypatch):
    monkeypatch.setenv(batchkernel.BACKEND_ENV, "numpy")
    assert batchkernel.resolve_backend() == "numpy"
    site = Site(declination_deg=3.0)
    h, m = _samples(site, n=2000)
    out = survey.correct_samples(h, m, CAL, site)      # forced fallback: survey.correct_samples, bit for bit
    ref = survey.correct_samples(h, m, CAL, site)
    for k in BATCH_KEYS + ("flags", "status"):
        np.testing.assert_array_equal(out[k], ref[k], err_msg=k)
    monkeypatch.setenv(batchkernel.BACKEND_ENV, "fast")
    with pytest.raises(ValueError, match=r"\$INCLINOMETER_CALIB_BATCH_BACKEND must be one of auto, numba, numpy"):
        batchkernel.resolve_backend()
    with pytest.raises(ValueError, match="backend must be one of"):
        batchkernel.resolve_backend("gpu")
    monkeypatch.delenv(batchkernel.BACKEND_ENV)
    monkeypatch.setattr(batchkernel, "numba_available", lambda: False)   # as on a machine without numba
    assert batchkernel.resolve_backend() == "numpy"
    with pytest.raises(ImportError, match="the numba backend needs numba"):
        batchkernel.resolve_backend("numba")


@has_numba
def test_bad_input_is_named():
    with pytest.raises(ValueError, match="must both be \\(N, 3\\)"):
        survey.correct_samples(np.zeros((4, 3)), np.zeros((4, 2)), site=Site(), backend="numba")
    with pytest.raises(ValueError, match="no site reference"):
        survey.correct_samples(np.zeros((4, 3)), np.zeros((4, 3)), backend="numba")
    out = survey.correct_samples(np.zeros((0, 3)), np.zeros((0, 3)), site=Site(), backend="numba")
    assert all(len(v) == 0 for v in out.values())
    bad = {k: np.empty(4) for k in BATCH_KEYS}
    bad["flags"] = np.empty(4, dtype=np.uint8)
    bad["status"] = np.empty(4)                       # wrong dtype
    with pytest.raises(ValueError, match=r"out\['status'\] must be a writeable C-contiguous \(4,\) uint8"):
        survey.correct_samples(np.zeros((4, 3)), np.zeros((4, 3)), site=Site(), out=bad, backend="numba")


def test_cache_dir_is_the_users(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "given"))
    assert batchkernel.cache_dir() == str(tmp_path / "given")
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert batchkernel.cache_dir() == str(tmp_path / "xdg" / "inclinometer_calib" / "numba")


@has_numba
def test_the_kernel_is_cached_apart_for_each_text_of_the_formulas():
    """numba checks the kernel's own file for changes, not formulas.py, whose functions it inlines:
    the cache directory carries that file's hash, so an edited formula is compiled afresh."""
    import hashlib
    import os

    from inclinometer_calib.core import formulas

    kernels = batchkernel._kernels()
    with open(formulas.__file__, "rb") as fh:
        want = "formulas-" + hashlib.sha256(fh.read()).hexdigest()[:16]
    assert want in kernels.fused._cache._cache_path.split(os.sep)

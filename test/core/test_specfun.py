"""core.specfun against scipy.special (a maintained implementation that shares no code with it):
the detector's χ² quantiles, the lab's χ², F and t tail probabilities — and that the processes
that find stations no longer import scipy.special."""
import subprocess
import sys

import numpy as np
import pytest
import scipy.special as sc

from inclinometer_calib.core import specfun as sf
from inclinometer_calib.detect.noise import LOW_QUANTILE, STATIC_QUANTILE, chi_quantile


def _rel(got, want):
    got, want = np.asarray(got, float), np.asarray(want, float)
    same = (got == want) | (np.isnan(got) & np.isnan(want))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(same, 0.0, np.abs(got - want) / np.maximum(np.abs(want), 1e-300))


SHAPES = [0.05, 0.1, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.5, 10.0, 12.0, 49.5, 124.5, 500.0, 2000.0]


@pytest.mark.parametrize("a", SHAPES)
def test_the_incomplete_gamma_functions_are_scipys_to_1e_12(a):
    xs = [1e-6, 0.01, 0.5, 1.0, 2.0, 0.5 * a, a, a + 1.0, 1.5 * a, 3.0 * a + 10.0, 50.0, 300.0]
    assert max(_rel(sf.gammainc(a, x), sc.gammainc(a, x)) for x in xs) < 1e-12
    assert max(_rel(sf.gammaincc(a, x), sc.gammaincc(a, x)) for x in xs) < 1e-12
    ps = [1e-12, 1e-6, 1e-3, 0.01, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 0.999, 0.999999, 1 - 1e-9]
    assert max(_rel(sf.gammaincinv(a, p), sc.gammaincinv(a, p)) for p in ps) < 1e-12


def test_the_detectors_quantiles_are_scipys_for_every_block_size():
    """``s/σ`` quantiles of blocks of 3 to 5000 samples (a 0.25 s block at 20 kHz)."""
    for n in range(3, 5001):
        for q in (LOW_QUANTILE, STATIC_QUANTILE):
            want = np.sqrt(2.0 * sc.gammaincinv(0.5 * (n - 1), q) / (n - 1))
            assert _rel(chi_quantile(n, q), want) < 1e-13, (n, q)


def test_the_tail_probabilities_are_scipys_to_1e_10():
    for k in [0.1, 0.5, 1, 2, 3, 6, 10, 30, 100, 1000]:
        for x in [0, 1e-3, 0.5, 1, 3, 10, 30, 100, 1000, 1e4, np.inf]:
            assert _rel(sf.chdtrc(k, x), sc.chdtrc(k, x)) < 1e-12, (k, x)
    d1, d2, f = np.meshgrid([1, 2, 3, 6, 10], [1, 2, 5, 20, 25, 100, 200, 2000, 20000],
                            [0, 1e-4, 0.1, 0.5, 1, 2, 5, 20, 100, 1e4, np.inf])
    assert np.max(_rel(sf.fdtrc(d1, d2, f), sc.fdtrc(d1, d2, f))) < 1e-10
    for df in [1, 2, 3, 5, 9, 29, 199, 2000]:
        for t in [-1e3, -30, -5, -2, -1, -0.1, 0, 0.1, 1, 2, 5, 30, np.inf, -np.inf, np.nan]:
            assert _rel(sf.stdtr(df, t), sc.stdtr(df, t)) < 1e-11, (df, t)


def test_outside_the_domain_is_nan_and_the_edges_are_exact():
    assert np.isnan(sf.gammainc(-1.0, 1.0)) and np.isnan(sf.gammaincinv(1.0, 1.5)) and np.isnan(sf.chdtrc(0, 1.0))
    assert np.isnan(sf.fdtrc(1, 0, 1.0)) and np.isnan(sf.stdtr(0, 1.0)) and np.isnan(sf.betainc(1, 1, 2.0))
    assert sf.gammaincinv(2.0, 0.0) == 0.0 and sf.gammaincinv(2.0, 1.0) == np.inf
    assert sf.chdtrc(3, 0.0) == 1.0 and sf.fdtrc(2, 5, 0.0) == 1.0 and sf.betainc(2, 3, 1.0) == 1.0
    assert sf.fdtrc([1, 2], [5, 6], [1.0, 2.0]).shape == (2,)


def test_finding_stations_and_checking_the_field_do_not_import_scipy_special():
    code = ("import sys; from inclinometer_calib.detect.streaming import StaticDetector; "
            "from inclinometer_calib.lab.field import FieldMonitor; from inclinometer_calib.lab.stats import regress; "
            "d = StaticDetector(); d.noise.force(); FieldMonitor(); "
            "print(sorted(m for m in sys.modules if m.startswith('scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out

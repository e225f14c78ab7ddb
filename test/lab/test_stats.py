"""The regression F-test of the lab's diagnosis and the field monitor (:mod:`lab.stats`)."""
import numpy as np
from scipy import stats as sps

from inclinometer_calib.lab.stats import mean_above_zero_p, regress, regress_many


def _designs(rng):
    """(y, x) pairs as the field monitor makes them: windows of 12 to 30 stations, 1 to 9 regressors,
    some that do not vary or repeat another, some with NaN rows."""
    out = []
    for n in (12, 17, 30):
        for k in (1, 3, 6, 9):
            for kind in ("plain", "zero column", "repeated column", "nan row", "constant"):
                x = rng.normal(size=(n, k))
                y = x @ rng.normal(size=k) * 0.3 + rng.normal(size=n)
                if kind == "zero column":
                    x[:, 0] = 0.0
                elif kind == "repeated column" and k > 1:
                    x[:, 1] = 2.0 * x[:, 0]
                elif kind == "nan row":
                    x[3, 0] = np.nan
                    y[7] = np.nan
                elif kind == "constant":
                    x[:] = 1.5
                out.append((y, x[:, 0] if k == 1 and kind == "plain" else x))
    return out


def test_regress_is_the_textbook_f_test_of_nested_least_squares_fits():
    rng = np.random.default_rng(5)
    for y, x in _designs(rng):
        tr = regress(y, x)
        x2 = x[:, None] if x.ndim == 1 else x
        ok = np.isfinite(y) & np.all(np.isfinite(x2), axis=1)
        yy, xx = y[ok], x2[ok]
        n = len(yy)
        a = np.column_stack([np.ones(n), xx])
        coef, *_ = np.linalg.lstsq(a, yy, rcond=None)
        k = np.linalg.matrix_rank(a) - 1
        ss_tot = float(np.sum((yy - yy.mean()) ** 2))
        ss_res = float(np.sum((yy - a @ coef) ** 2))
        dof = n - k - 1
        if k == 0 or dof < 2:      # nothing varies, or too few points left for the scatter
            assert tr is None
            continue
        f = ((ss_tot - ss_res) / k) / (ss_res / dof)
        assert tr is not None and tr.n == n
        np.testing.assert_allclose([tr.f, tr.r2, tr.explained_rms, tr.residual_rms],
                                   [f, 1 - ss_res / ss_tot, np.sqrt((ss_tot - ss_res) / n), np.sqrt(ss_res / dof)],
                                   rtol=1e-9)
        np.testing.assert_allclose(tr.p, sps.f.sf(f, k, dof), rtol=1e-9)
        if k == xx.shape[1]:   # full rank: the slopes are the fit's (else the minimum-norm ones)
            np.testing.assert_allclose(tr.coef, coef[1:], rtol=1e-9, atol=1e-12)


def test_regress_many_gives_each_pair_the_bits_it_gets_alone():
    rng = np.random.default_rng(11)
    pairs = _designs(rng)
    order = rng.permutation(len(pairs))
    pairs = [pairs[i] for i in order] + pairs[:7]          # mixed shapes, some pairs twice
    together = regress_many(pairs)
    for (y, x), tr in zip(pairs, together):
        alone = regress(y, x)
        assert (tr is None) == (alone is None)
        if tr is None:
            continue
        assert (tr.f, tr.p, tr.r2, tr.explained_rms, tr.residual_rms, tr.n) == \
            (alone.f, alone.p, alone.r2, alone.explained_rms, alone.residual_rms, alone.n)
        assert np.array_equal(tr.coef, alone.coef)


def test_a_trends_p_value_is_computed_when_first_read_and_is_the_f_tests():
    """The field monitor reads p only for a trend large enough to matter: a regression leaves it
    uncomputed until read; then it is P(F(k, dof) > f) of the trend's own figures, kept."""
    from inclinometer_calib.core.specfun import fdtrc

    rng = np.random.default_rng(3)
    x = rng.normal(size=(40, 2))
    tr = regress(0.3 * x[:, 0] + rng.normal(size=40), x)
    assert tr._p is None and (tr.k, tr.dof) == (2, 37)
    p = tr.p
    assert p == fdtrc(2, 37, tr.f) == tr._p
    np.testing.assert_allclose(p, sps.f.sf(tr.f, 2, 37), rtol=1e-9)


def test_nothing_to_test_gives_none():
    y = np.arange(10.0)
    assert regress(y, np.ones(10)) is None                    # the regressor does not vary
    assert regress(y[:3], np.arange(3.0)) is None             # too few points for the degrees of freedom
    assert regress(y, np.empty((10, 0))) is None              # no regressor
    assert regress(2.0 * np.arange(10.0) + 1.0, np.arange(10.0)) is None   # a perfect fit: no scatter to test against
    assert regress_many([]) == []


def test_mean_above_zero_p_is_scipys_one_sided_one_sample_t_test():
    rng = np.random.default_rng(9)
    for n in (2, 3, 5, 17, 200):
        for shift in (-1.0, 0.0, 0.3, 2.0):
            x = rng.normal(shift, 1.5, n)
            want = sps.ttest_1samp(x, 0.0, alternative="greater").pvalue
            assert np.isclose(mean_above_zero_p(x), want, rtol=1e-12, atol=1e-300), (n, shift)
    assert mean_above_zero_p([0.5, 0.5, 0.5]) == 0.0 and mean_above_zero_p([-0.5, -0.5]) == 1.0

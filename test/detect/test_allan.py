"""The noise model from static data: Allan deviation per axis, its IEEE figures, and the random
walk across a sequence of stations — checked against series of known noise."""
import numpy as np
import pytest

from inclinometer_calib.detect.allan import (allan_curve, edf_simple, fit_terms, oadev_octaves, sensor_noise,
                                             sequence_walk)

RATE = 50.0


def _series(seconds, sigma, walk, seed):
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE)
    t = np.arange(n) / RATE
    x = rng.normal(0.0, sigma, (n, 3)) + np.cumsum(rng.normal(0.0, walk / np.sqrt(RATE), (n, 3)), axis=0)
    return t, x


def test_white_noise_density_is_the_sample_sigma_over_the_root_of_the_rate():
    t, x = _series(600, 25.0, 0.0, 1)
    curve = allan_curve([np.column_stack([t, x])])
    assert curve.rate_hz == pytest.approx(RATE)
    # the τ^-1/2 line: σ(τ) = N/√τ
    n_true = 25.0 / np.sqrt(RATE)
    assert np.allclose(curve.adev[0], n_true / np.sqrt(curve.tau[0]), rtol=0.03)
    for axis in fit_terms(curve):
        assert axis["N"].resolved and axis["N"].value == pytest.approx(n_true, rel=0.02)
        assert not axis["K"].resolved and not axis["B"].resolved


def test_a_random_walk_is_resolved_on_a_long_hold_and_only_bounded_on_short_ones():
    t, x = _series(1200, 25.0, 0.5, 2)
    long = sensor_noise("mag", [np.column_stack([t, x])])
    for axis in long.terms:
        k = axis["K"]
        assert k.resolved and abs(k.value - 0.5) < 3 * k.std + 0.05, k
    # the same data cut into 4 s holds: the walk is below the white noise at τ ≤ 1.3 s
    holds = [np.column_stack([t[i:i + 200], x[i:i + 200]]) for i in range(0, len(t) - 200, 275)]
    short = sensor_noise("mag", holds)
    assert short.curve.tau[-1] < 2.0 and short.curve.n_segments == len(holds)
    for axis in short.terms:
        assert not axis["K"].resolved and axis["K"].upper > 0.5


def test_the_station_sequence_finds_the_walk_the_short_holds_cannot_see():
    sig = 25.0 / np.sqrt(200)
    for walk, seed in ((0.5, 3), (0.2, 4)):
        t, x = _series(1200, 25.0, walk, seed)
        idx = range(0, len(t) - 200, 275)
        tm = np.array([t[i:i + 200].mean() for i in idx])
        r = np.array([x[i:i + 200].mean(axis=0) for i in idx])[:80] + 40.0     # any level: it drops out
        ks = sequence_walk(tm[:80], r, np.full_like(r, sig))
        for k in ks:
            assert k.resolved and k.source == "stations"
            assert abs(k.value - walk) < 3.5 * k.std, (walk, k)
    # white noise alone: nothing resolved, an upper bound near zero
    for seed in (5, 6, 7):
        t, x = _series(1200, 25.0, 0.0, seed)
        idx = range(0, len(t) - 200, 275)
        tm = np.array([t[i:i + 200].mean() for i in idx])[:80]
        r = np.array([x[i:i + 200].mean(axis=0) for i in idx])[:80]
        assert not any(k.resolved for k in sequence_walk(tm, r, np.full_like(r, sig)))


def test_the_noise_model_takes_the_walk_from_the_sequence_when_the_holds_cannot_resolve_it():
    t, x = _series(1200, 25.0, 0.5, 8)
    idx = list(range(0, len(t) - 200, 275))[:80]
    holds = [np.column_stack([t[i:i + 200], x[i:i + 200]]) for i in idx]
    tm = np.array([h[:, 0].mean() for h in holds])
    r = np.array([h[:, 1:].mean(axis=0) for h in holds])
    m = sensor_noise("mag", holds, sequence=(tm, r, np.full_like(r, 25.0 / np.sqrt(200))))
    assert all(a["K"].source == "stations" and a["K"].resolved for a in m.terms)
    assert np.all(m.walk_density() > 0.25) and np.all(m.walk_density() < 0.9)
    rows = m.table()
    assert rows[0]["random_walk"]["unit"] == "nT/sqrt(s)" and rows[0]["white_noise"]["unit"] == "nT/sqrt(Hz)"


def test_a_flat_axis_says_nothing_and_is_left_out():
    t, x = _series(200, 0.004, 0.0, 9)
    x[:, 2] = 9.81                       # a stuck axis
    curve = allan_curve([np.column_stack([t, x])])
    terms = fit_terms(curve)
    assert terms[0]["N"].resolved
    assert len(curve.tau) == 0 or not np.isfinite(terms[2]["N"].upper) or not terms[2]["N"].resolved


def test_the_degrees_of_freedom_are_allantools_edf_simple_bit_for_bit():
    """:func:`edf_simple` gives NIST SP 1065 Table 5's white- and random-walk-FM degrees of freedom
    as ``allantools.edf_simple`` does, to the last bit, over the holds' lengths and octaves; any
    other noise type is refused, not defaulted; at three samples the random walk's is +∞ (allantools
    divides by zero there), so a three-sample hold is weighted by its white noise's."""
    allantools = pytest.importorskip("allantools")
    assert edf_simple(3, 1, -2) == np.inf and edf_simple(3, 1, 0) == float(allantools.edf_simple(3, 1, 0))
    t = np.arange(3) / RATE
    curve = allan_curve([np.column_stack([t, [[0.0, 1.0, 2.0], [1.0, 0.0, 2.0], [2.0, 1.0, 0.0]]])])
    assert curve.edf[0] == pytest.approx([edf_simple(3, 1, 0)] * 3)
    for n in (4, 7, 37, 200, 1000, 30001):
        for m in 2 ** np.arange(0, int(np.log2(max(n // 3, 1))) + 1):
            for alpha in (0, -2):
                assert edf_simple(n, int(m), alpha) == float(allantools.edf_simple(n, int(m), alpha)), (n, m, alpha)
    # a hand value: 1000 samples at m = 1, white FM: (3·999/2 − 2·998/1000)·4/9
    assert edf_simple(1000, 1, 0) == pytest.approx((1498.5 - 1.996) * 4 / 9, rel=1e-15)
    with pytest.raises(ValueError, match="alpha"):
        edf_simple(100, 1, -1)


def test_the_octave_deviations_are_allantools_oadev_bit_for_bit():
    """:func:`oadev_octaves` does what ``allantools.oadev`` does for rate data at octave averaging
    factors (without its τ-list preparation): the same numbers to the last bit, on holds of a
    random walk and of white noise, long and short, at an offset."""
    allantools = pytest.importorskip("allantools")
    t, x = _series(20, 25.0, 0.5, 10)
    for n, col, offset in ((1000, 0, 0.0), (200, 1, 48000.0), (37, 2, -9.8), (3, 0, 1.0)):
        y = x[:n, col] + offset
        ms = 2 ** np.arange(0, int(np.log2(n // 3)) + 1)
        _, ad, _, _ = allantools.oadev(y, rate=RATE, data_type="freq", taus=ms / RATE)
        assert np.array_equal(oadev_octaves(y, RATE, ms), ad), n
    # a hold's three axes at once, each as alone
    ms = 2 ** np.arange(0, int(np.log2(300 // 3)) + 1)
    rows = oadev_octaves(np.ascontiguousarray(x[:300].T) + [[0.0], [4.8e4], [-9.8]], RATE, ms)
    for j, offset in enumerate((0.0, 4.8e4, -9.8)):
        _, ad, _, _ = allantools.oadev(x[:300, j] + offset, rate=RATE, data_type="freq", taus=ms / RATE)
        assert np.array_equal(rows[j], ad), j

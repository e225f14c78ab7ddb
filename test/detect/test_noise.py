"""Noise measured from the data: robust to motion, to flat axes, priors and overrides."""
import math

import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.frames import Site
from inclinometer_calib.detect.noise import (LONG_HISTORY, NoiseEstimator, chi_quantile, estimate_from_blocks,
                                          estimate_noise)


def _feed(est, t, x):
    for ti, xi in zip(t.tolist(), x.tolist()):
        est.add(ti, xi)


def test_chi_quantile_is_the_distribution_of_the_sample_std_of_white_noise():
    rng = np.random.default_rng(0)
    s = rng.normal(0, 1, (200_000, 25)).std(axis=1, ddof=1)
    for q in (0.1, 0.5, 0.999):
        assert chi_quantile(25, q) == pytest.approx(np.quantile(s, q), rel=0.01)


@pytest.mark.parametrize("moving", [0.0, 0.5, 0.85])
def test_the_estimate_is_the_white_noise_even_when_most_blocks_move(moving):
    # blocks of 25 samples: static (σ = 1) or moving (a ramp of random slope on top)
    rng = np.random.default_rng(1)
    n_blocks = 400
    s = []
    for k in range(n_blocks):
        x = rng.normal(0, 1.0, 25)
        if k < moving * n_blocks:
            x = x + np.linspace(0, rng.uniform(5, 50), 25)
        s.append(x.std(ddof=1))
    est = estimate_from_blocks(np.array(s)[:, None], 25)
    assert est[0] == pytest.approx(1.0, rel=0.06)


def test_a_flat_axis_is_left_out_of_the_estimate_and_one_flat_everywhere_is_zero():
    rng = np.random.default_rng(2)
    s = rng.normal(0, 1, (300, 25)).std(axis=1, ddof=1)
    clipped = s.copy()
    clipped[:60] = 0.0                    # 20 % of the blocks: the axis sat at its clip level
    est = estimate_from_blocks(np.c_[s, clipped, np.zeros(300)], 25)
    assert est[0] == pytest.approx(1.0, rel=0.06) and est[1] == pytest.approx(1.0, rel=0.06)
    assert est[2] == 0.0                  # stuck: known to be 0, not NaN


def test_the_stream_estimate_of_a_simulated_session_is_its_noise():
    probe = sim.build_probe(3, noise_acc=0.005, noise_mag=50.0)
    log = sim.run_session(probe, Site(), sim.twelve_pose_session(duration_s=3.0), np.random.default_rng(3),
                          move_s=1.5)
    est = NoiseEstimator()
    _feed(est, log.t_s, np.c_[-log.acc, log.mag])
    assert est.ready
    lvl = est.level
    assert lvl.acc_source == "data" and np.allclose(lvl.acc, 0.005, rtol=0.08)
    assert np.allclose(lvl.mag, 50.0, rtol=0.08)
    batch = estimate_noise(log.t_s, log.acc, log.mag)
    assert np.allclose(batch.acc, 0.005, rtol=0.08) and np.allclose(batch.mag, 50.0, rtol=0.08)


def test_prior_until_the_data_speak_override_always_and_a_contradicted_prior_is_said():
    est = NoiseEstimator(override_mag=25.0)
    est.set_prior(acc=0.002)
    lvl = est.level
    assert (lvl.acc_source, lvl.acc) == ("prior", (0.002,) * 3)
    assert (lvl.mag_source, lvl.mag) == ("override", (25.0,) * 3)
    rng = np.random.default_rng(4)
    t = np.arange(2000) * 0.01
    _feed(est, t, np.c_[rng.normal(0, 0.006, (2000, 3)), rng.normal(0, 60.0, (2000, 3))])
    lvl = est.level
    assert lvl.acc_source == "data" and np.allclose(lvl.acc, 0.006, rtol=0.1)
    assert lvl.mag == (25.0,) * 3
    assert est.measured[3] == pytest.approx(60.0, rel=0.1)      # what the gates judge with
    msgs = est.check_prior()
    assert len(msgs) == 1 and "messages state a noise of 0.002 m/s^2" in msgs[0] and "data show 0.00" in msgs[0]


def test_a_gap_drops_the_open_block_and_nothing_before_the_blocks_are_in_is_ready():
    est = NoiseEstimator(ready_blocks=8)
    assert not est.ready and math.isnan(est.level.acc[0]) and est.level.acc_source == "none"
    _feed(est, np.arange(10) * 0.01, np.zeros((10, 6)) + np.arange(10)[:, None])
    est.gap()
    assert est.blocks == 0                # 10 samples over 0.09 s: no block closed, and the gap dropped it


def test_the_estimate_follows_each_fourth_block_then_each_sixteenth_once_the_history_is_long():
    est = NoiseEstimator(block_s=0.25, history_s=600.0)
    rng = np.random.default_rng(5)
    changed_at, last = [], None
    for b in range(600):
        est.add_block(25, 0.002 * (1.0 + 0.1 * rng.standard_normal(6)))
        sigma = np.array(est.level.sigma6)
        if last is None or not np.array_equal(sigma, last, equal_nan=True):
            changed_at.append(b + 1)   # blocks closed when the estimate moved (the first: unknown)
            last = sigma
    early = [c for c in changed_at[1:] if c <= 4 * est.ready_blocks]
    assert early == list(range(est.ready_blocks, 4 * est.ready_blocks + 1))     # every block at first
    mid = [c for c in changed_at if 4 * est.ready_blocks < c < LONG_HISTORY]
    assert mid and all(c % 4 == 0 for c in mid) and len(mid) == (LONG_HISTORY - 1) // 4 - est.ready_blocks
    late = [c for c in changed_at if c >= LONG_HISTORY]
    assert late and all(c % 16 == 0 for c in late) and len(late) == 600 // 16 - (LONG_HISTORY - 1) // 16

"""Live static detection and station correction (ROS-free parts of the nodes)."""
import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.probelog import ProbeLog
from inclinometer_calib.detect.streaming import StaticDetector


def _stations(log, **kw):
    det = StaticDetector(**kw)
    out = []
    g = log.gravity
    for i in range(len(log)):
        out.extend(det.update(log.t_s[i], g[i], log.mag[i], log.temp_c[i]))
    out.extend(det.flush())
    return out, det


def _twelve(noise_scale=1.0, duration_s=2.0, rate_hz=100.0, seed=1, move_s=1.0):
    probe = sim.build_probe(seed, noise_acc=0.002 * noise_scale, noise_mag=20.0 * noise_scale)
    return sim.run_session(probe, Site(), sim.twelve_pose_session(duration_s=duration_s), np.random.default_rng(0),
                           rate_hz=rate_hz, move_s=move_s)


def test_detector_finds_each_station_of_a_session_and_nothing_during_moves():
    log = _twelve()
    segs, det = _stations(log)
    full = [s for s in segs if not s.short]
    assert len(full) == 12
    # each station lies inside one labelled station (it may take in the first, still nearly
    # unrotated, sample of the following move: deviation below the threshold by construction)
    for s in full:
        rows = (log.t_s >= s.t_start) & (log.t_s <= s.t_end)
        poses, counts = np.unique(log.pose[rows], return_counts=True)
        main = poses[np.argmax(counts)]
        assert main > 0 and counts.max() >= rows.sum() - 2
        assert s.duration_s > 1.5 and s.ended_by in ("motion", "end")
    assert det.pop_events() == []


@pytest.mark.parametrize("noise_scale", [0.5, 2.5, 5.0])
def test_thresholds_follow_the_noise_the_data_show_so_every_hold_is_one_station(noise_scale):
    # the fixed 0.002 m/s² / 20 nT of the past cut a 2.5× noisier probe's holds into pieces
    log = _twelve(noise_scale, duration_s=3.0)
    segs, det = _stations(log)
    assert len([s for s in segs if not s.short]) == 12 and det.too_short == 0
    lvl = det.noise_level
    assert lvl.acc_source == lvl.mag_source == "data"
    np.testing.assert_allclose(lvl.acc, 0.002 * noise_scale, rtol=0.1)
    np.testing.assert_allclose(lvl.mag, 20.0 * noise_scale, rtol=0.1)
    for s in segs:                                 # the station carries the noise it was cut with
        np.testing.assert_allclose(s.g_noise, lvl.acc, rtol=0.1)


def test_a_given_noise_overrides_the_data_and_too_low_a_value_cuts_holds_into_pieces_that_are_explained():
    log = _twelve(2.5, duration_s=3.0)
    segs, det = _stations(log, noise_acc=0.002, noise_mag=20.0)
    assert det.noise_level.acc_source == "override"
    events = det.pop_events()
    assert len([s for s in segs if not s.short]) > 12 or det.too_short > 0
    assert any("cut at" in e and "both pieces point the same way" in e and "detector.k_sigma" in e for e in events)


def test_stated_noise_that_the_data_contradict_is_reported_and_the_data_win():
    log = _twelve(2.5)
    det = StaticDetector()
    det.set_prior(noise_acc=0.002, noise_mag=20.0)
    g = log.gravity
    for i in range(len(log)):
        det.update(log.t_s[i], g[i], log.mag[i])
    events = det.pop_events()
    assert any("the messages state a noise of 0.002 m/s^2" in e and "using the data" in e for e in events)
    assert det.noise_level.acc_source == "data"


def test_the_first_stations_wait_for_the_noise_estimate_then_come_out_in_order():
    log = _twelve(2.5)
    det = StaticDetector()
    first, g = None, log.gravity
    for i in range(len(log)):
        got = det.update(log.t_s[i], g[i], log.mag[i])
        if got and first is None:
            first = (i, got)
    i, got = first
    assert det.warming_up is False
    assert log.t_s[i] - got[0].t_end > 0.0          # closed late: replayed from the warm-up buffer
    assert [s.t_start for s in got] == sorted(s.t_start for s in got)


def test_isolated_spikes_are_left_out_of_the_hold_not_allowed_to_end_it():
    probe = sim.build_probe(1)
    log = sim.run_session(probe, Site(), sim.stand_grid_session(drifts=(10,), azimuths=(0,), toolfaces=(0,),
                                                                 duration_s=6.0), np.random.default_rng(0))
    clean = log.acc[300].copy()
    log.acc[300, 0] += 0.5                          # one electrical spike, 250σ
    log.acc[420, 2] -= 0.5
    segs, _ = _stations(log)
    full = [s for s in segs if not s.short]
    assert len(full) == 1 and full[0].outliers == 2
    ref = -np.mean(np.delete(log.acc, [300, 420], axis=0), axis=0)
    assert np.max(np.abs(full[0].g - ref)) < 0.002 and np.isfinite(clean).all()


def test_short_stop_is_reported_as_short():
    probe = sim.build_probe(1)
    stations = sim.stand_grid_session(drifts=(10, 20, 30), azimuths=(0,), toolfaces=(0,), duration_s=2.0)
    stations[1].duration_s = 0.6
    log = sim.run_session(probe, Site(), stations, np.random.default_rng(0))
    segs, det = _stations(log, min_duration_s=1.0)
    assert [s.short for s in segs] == [False, True, False]
    assert det.too_short == 1


def test_nan_sample_breaks_a_station_without_poisoning_it():
    probe = sim.build_probe(1)
    log = sim.run_session(probe, Site(), sim.stand_grid_session(drifts=(10,), azimuths=(0,), toolfaces=(0,),
                                                                 duration_s=6.0), np.random.default_rng(0))
    log.acc[400, 1] = np.nan
    segs, _ = _stations(log)
    assert len([s for s in segs if not s.short]) == 2
    assert all(np.all(np.isfinite(s.g)) for s in segs)
    assert segs[0].ended_by == "gap"


def test_a_creep_during_the_hold_is_measured_as_a_trend():
    probe = sim.build_probe(1, noise_acc=0.005, noise_mag=30.0)
    log = sim.run_session(probe, Site(), sim.stand_grid_session(drifts=(30,), azimuths=(0,), toolfaces=(0,),
                                                                 duration_s=4.0), np.random.default_rng(0))
    rows = np.flatnonzero(np.isfinite(log.ref[:, 0]))
    k = np.arange(len(rows)) / len(rows)
    log.acc[rows, 0] += 0.02 * k                    # 0.02 m/s² over the hold (0.12°)
    segs, _ = _stations(log)
    s = max(segs, key=lambda x: x.n)
    assert s.g_rate[0] == pytest.approx(-0.02 / 4.0, rel=0.15)     # gravity vector = -f
    assert abs(s.g_rate[1]) < 0.002


def test_a_consumer_that_holds_stations_back_still_finds_their_temperatures():
    """The correction node publishes a station only when its reference is in: the temperatures
    stamped within a held-back station must outlive the closing of later stations (a loaded
    machine once lost them, and the stations' temperature-dependent corrections with them)."""
    log = _twelve(duration_s=3.0)
    for retain, expect_all in ((True, True), (False, False)):
        det = StaticDetector()
        det.retain_temperatures = retain
        held = []
        g = log.gravity
        for i in range(len(log)):
            det.add_temperature(log.t_s[i], 20.0 + 0.01 * i)       # on a topic of its own
            held.extend(det.update(log.t_s[i], g[i], log.mag[i]))
        held.extend(det.flush())
        temps = [det.temps.mean(s.t_start, s.t_end) for s in held if not s.short]
        assert len(temps) == 12
        assert all(np.isfinite(temps)) == expect_all


# ---- the batch path (StaticDetector.run) against the per-sample one ----------------------------------
def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, float):
        return a == b or (a != a and b != b)
    return a == b


def _assert_same_detectors(da, db, sa, sb):
    """Same stations (every field, bit for bit), messages and detector state after them."""
    assert len(sa) == len(sb)
    for p, q in zip(sa, sb):
        diff = [k for k, v in vars(p).items() if not _same(v, vars(q)[k])]
        assert not diff, (p.where, diff)
    assert da.events == db.events
    for k in ("too_short", "gaps", "samples_missing", "_dt", "_t_prev", "t_first", "_n", "_s1", "_s2", "_tol"):
        assert _same(getattr(da, k), getattr(db, k)), k
    na, nb = da.noise, db.noise
    assert na.level == nb.level and na.measured == nb.measured and na.blocks == nb.blocks
    assert np.array_equal(na._std, nb._std, equal_nan=True) and (na._b1, na._b2, na._bn) == (nb._b1, nb._b2, nb._bn)
    assert (da.temps._t, da.temps._v) == (db.temps._t, db.temps._v)


def _both_ways(log, split=None, **kw):
    """The log row by row through update(), and through run() (up to ``split``, then row by row)."""
    temp, g = log.temp_c, log.gravity
    a, sa = StaticDetector(**kw), []
    for i in range(len(log)):
        sa.extend(a.update(log.t_s[i], g[i], log.mag[i], temp[i]))
    sa.extend(a.flush())
    b = StaticDetector(**kw)
    k = len(log) if split is None else split
    sb = list(b.run(log.t_s[:k], g[:k], log.mag[:k], temp[:k]))
    for i in range(k, len(log)):
        sb.extend(b.update(log.t_s[i], g[i], log.mag[i], temp[i]))
    sb.extend(b.flush())
    _assert_same_detectors(a, b, sa, sb)
    return sa, a


def _long_hold_log():
    probe = sim.build_probe(3)
    stations = sim.stand_grid_session(drifts=(10, 40), azimuths=(0,), toolfaces=(0,), duration_s=70.0)
    return sim.run_session(probe, Site(), stations, np.random.default_rng(4), rate_hz=200.0)


def test_the_batch_path_gives_the_per_sample_stations_on_a_clean_session_at_two_rates():
    for rate in (100.0, 1000.0):
        segs, _ = _both_ways(_twelve(rate_hz=rate))
        assert len([s for s in segs if not s.short]) == 12


def test_the_batch_path_gives_the_per_sample_stations_on_a_long_hold_cut_by_max_duration():
    segs, _ = _both_ways(_long_hold_log())
    assert sum(s.ended_by == "max_duration" for s in segs) >= 4       # 70 s holds, 30 s pieces


def test_the_batch_path_gives_the_per_sample_stations_on_noisy_spiky_data_with_gaps_and_nans():
    log = _twelve(noise_scale=3.0, rate_hz=400.0, seed=5)
    rng = np.random.default_rng(11)
    # spikes: single ones (outliers), pairs, and bursts of break_samples (they end a hold)
    for start in rng.choice(len(log) - 5, size=120, replace=False):
        width = int(rng.choice([1, 1, 2, 3]))
        log.acc[start:start + width, int(rng.integers(3))] += rng.choice([-1, 1]) * 0.08
    log.mag[rng.choice(len(log), size=40, replace=False), 2] += 2000.0
    log.acc[1500, 1] = np.nan                                 # a non-finite sample
    log.temp_c[rng.choice(len(log), size=300, replace=False)] = np.nan
    keep = np.ones(len(log), bool)
    keep[3000:3150] = False                                   # samples lost: a time gap
    keep[int(0.7 * len(log)):int(0.7 * len(log)) + 40] = False
    sub = ProbeLog(**{k: getattr(log, k)[keep] for k in ProbeLog.__dataclass_fields__})
    segs, det = _both_ways(sub)
    assert det.gaps >= 2 and any(s.outliers for s in segs) and any(s.ended_by == "gap" for s in segs)
    assert any("cut" in e for e in det.events) or det.too_short


def test_the_batch_path_continues_exactly_where_the_per_sample_path_takes_over_and_with_given_noise():
    log = _twelve(noise_scale=1.5, rate_hz=500.0, seed=2)
    _both_ways(log, split=len(log) // 3)
    _both_ways(log, noise_acc=0.002, noise_mag=20.0)          # no warm-up: the noise is given
    segs, det = _both_ways(log, k_sigma=2.5)                  # too tight: holds cut into pieces, said so
    assert det.events


def test_the_batch_path_gives_the_per_sample_temperatures_when_stamps_repeat():
    """run() takes a log's temperatures at once only where every row is stamped after the one
    before it (by more than TIME_EPS); stamps that repeat (a logger's coarse clock) go row by row,
    as update() takes them: a hold that a non-finite sample ends, whose next rows share its last
    stamp, must not take their temperatures into its mean."""
    log = _long_hold_log()
    log.t_s[:] = np.floor(log.t_s * 50.0) / 50.0          # 200 Hz rows, 50 Hz stamps: four rows a stamp
    log.temp_c[:] = 20.0 + np.arange(len(log)) * 1e-3       # every row's own temperature
    ends = np.arange(2000, len(log) - 2000, 1501)           # mid-hold; most share their stamp with the next row
    log.acc[ends, 0] = np.nan
    segs, _ = _both_ways(log)
    assert sum(s.ended_by == "gap" for s in segs) >= 10

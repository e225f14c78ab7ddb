"""Live static detection and station correction (ROS-free parts of the nodes)."""
import numpy as np
import pytest

from inclinometer_calib import simulate as sim
from inclinometer_calib.frames import Site
from inclinometer_calib.streaming import StaticDetector


def _stations(log, **kw):
    det = StaticDetector(**kw)
    out = []
    for i in range(len(log)):
        out.extend(det.update(log.t_s[i], log.acc[i], log.mag[i], log.temp_c[i]))
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
    for i in range(len(log)):
        det.update(log.t_s[i], log.acc[i], log.mag[i])
    events = det.pop_events()
    assert any("the messages state a noise of 0.002 m/s^2" in e and "using the data" in e for e in events)
    assert det.noise_level.acc_source == "data"


def test_the_first_stations_wait_for_the_noise_estimate_then_come_out_in_order():
    log = _twelve(2.5)
    det = StaticDetector()
    first = None
    for i in range(len(log)):
        got = det.update(log.t_s[i], log.acc[i], log.mag[i])
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
        for i in range(len(log)):
            det.add_temperature(log.t_s[i], 20.0 + 0.01 * i)       # on a topic of its own
            held.extend(det.update(log.t_s[i], log.acc[i], log.mag[i]))
        held.extend(det.flush())
        temps = [det.temps.mean(s.t_start, s.t_end) for s in held if not s.short]
        assert len(temps) == 12
        assert all(np.isfinite(temps)) == expect_all

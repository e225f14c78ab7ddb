"""Probe simulator: determinism, physical units, effects where they belong."""
import numpy as np
import pytest

from inclinometer_calib.core import effects as fx
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.frames import Site, drift_deg, total_field, total_gravity
from inclinometer_calib.io.probelog import segment_stations


def _run(probe, stations, seed=0, survey=False):
    return sim.run_session(probe, Site(), stations, np.random.default_rng(seed), rate_hz=50, survey=survey)


def test_same_seed_gives_identical_samples():
    a = _run(sim.build_probe(3), sim.twelve_pose_session(duration_s=0.5))
    b = _run(sim.build_probe(3), sim.twelve_pose_session(duration_s=0.5))
    np.testing.assert_array_equal(a.acc, b.acc)
    np.testing.assert_array_equal(a.mag, b.mag)


def test_ideal_probe_reads_minus_gravity_and_the_site_field():
    probe = sim.SimulatedProbe(sim.ProbeModel.base(), noise_acc=0, noise_mag=0)
    log = _run(probe, sim.stand_grid_session(drifts=(30,), azimuths=(60,), toolfaces=(0,)))
    st = log.pose == 0
    assert total_gravity(log.acc[st]) == pytest.approx(9.80665)
    assert total_field(log.mag[st]) == pytest.approx(50000.0)
    assert drift_deg(-log.acc[st][0]) == pytest.approx(30.0)   # REP-145: g = -f


def test_noise_has_the_configured_sigma():
    probe = sim.SimulatedProbe(sim.ProbeModel.base(), noise_acc=0.01, noise_mag=50)
    log = _run(probe, sim.stand_grid_session(drifts=(10,), azimuths=(0,), toolfaces=(0,), duration_s=40))
    assert np.std(log.acc[:, 0]) == pytest.approx(0.01, rel=0.05)
    assert np.std(log.mag[:, 2]) == pytest.approx(50, rel=0.05)


def test_axial_interference_is_present_in_survey_logs_only():
    probe = sim.build_probe(2, ["axial_interference=400"], noise_acc=0, noise_mag=0)
    grid = sim.stand_grid_session(drifts=(40,), azimuths=(90,), toolfaces=(0,))
    clean = _run(probe, grid, survey=False)
    dirty = _run(probe, grid, survey=True)
    d = dirty.mag - clean.mag
    # +400 nT along tool Z, passed through the probe's scale/non-orthogonality (column z of K·E)
    np.testing.assert_allclose(d[0], probe.mag.A[:, 2] * 400.0, rtol=1e-9)


def test_temperature_bias_follows_temperature():
    probe = sim.build_probe(2, ["temperature_bias:acc:x=0.001"], noise_acc=0, noise_mag=0)
    base = sim.build_probe(2, noise_acc=0, noise_mag=0)
    grid = sim.stand_grid_session(drifts=(20,), azimuths=(0, 60), toolfaces=(0,), temp_profile_c=(25, 45))
    d = _run(probe, grid).acc - _run(base, grid).acc
    # REP-145 output is -g: a +c·ΔT gravity-vector bias appears as -c·ΔT in specific force
    np.testing.assert_allclose(d[:, 0], -0.001 * (_run(base, grid).temp_c - 25.0), atol=1e-12)
    assert np.all(d[:, 1:] == 0)


def test_a_wandering_bias_is_a_random_walk_that_continues_from_session_to_session():
    probe = sim.build_probe(2, ["bias_wander:mag:x=2.0"], noise_acc=0, noise_mag=0)
    base = sim.build_probe(2, noise_acc=0, noise_mag=0)
    grid = sim.stand_grid_session(drifts=(20,), azimuths=(0,), toolfaces=(0,), duration_s=20.0)
    rng = np.random.default_rng(5)
    site = Site()
    a = sim.run_session(probe, site, grid, rng)
    b = sim.run_session(probe, site, grid, rng, t0=float(a.t_s[-1]) + 0.01)
    ref = sim.run_session(base, site, grid, np.random.default_rng(5))
    wa, wb = a.mag[:, 0] - ref.mag[:, 0], b.mag[:, 0] - ref.mag[:, 0]
    assert np.all(a.mag[:, 1:] == ref.mag[:, 1:])             # one axis only
    steps = np.diff(wa)
    # increments of K·√Δt: 2 nT/√s at 100 Hz gives 0.2 nT per sample
    assert np.std(steps) == pytest.approx(2.0 * np.sqrt(0.01), rel=0.06)
    assert abs(wb[0] - wa[-1]) < 1.0                            # the walk goes on where it stood


def test_stand_pose_error_moves_the_real_orientation_but_not_the_labels():
    probe = sim.build_probe(4, ["stand_pose_error=0.2"], noise_acc=0, noise_mag=0)
    grid = sim.stand_grid_session(drifts=(30,), azimuths=(0,), toolfaces=(0, 120, 240))
    log = _run(probe, grid)
    stations, _ = segment_stations(log)
    g_true = probe.model.correct(np.array([s.g for s in stations]), np.array([s.b for s in stations]))[0]
    err = drift_deg(g_true) - 30.0
    assert 0.01 < np.max(np.abs(err)) < 1.0
    assert all(s.ref[0] == 30.0 for s in stations)


def test_time_skew_only_shows_while_moving():
    base = sim.build_probe(6, noise_acc=0, noise_mag=0)
    skew = sim.build_probe(6, ["time_skew=0.05"], noise_acc=0, noise_mag=0)
    sess = sim.twelve_pose_session(duration_s=1.0)
    a, b = _run(base, sess), _run(skew, sess)
    moving = a.pose == 0
    assert np.max(np.abs(a.mag[moving] - b.mag[moving])) > 100
    static = ~moving
    inner = static & np.r_[static[5:], [False] * 5]  # away from the end of each station
    np.testing.assert_allclose(a.mag[inner], b.mag[inner], atol=1e-6)


@pytest.mark.parametrize("text,expected", [
    ("axial_interference=300", [("axial_interference", ("mag",), None, "val", (300.0,))]),
    ("temperature_bias:mag:xy=2,3", [("temperature_bias", ("mag",), "xy", "all", (2.0, 3.0))]),
    ("bias:acc:xyz=1,2,3,nonlinearity@cal", [("bias", ("acc",), "xyz", "all", (1.0, 2.0, 3.0)),
                                             ("nonlinearity", ("acc", "mag"), None, "cal", ())]),
])
def test_one_grammar_names_effects_everywhere(text, expected):
    got = [(e.name, e.sensors, e.axes, e.scope, e.values) for e in fx.parse_effects(text)]
    assert got == expected


@pytest.mark.parametrize("text,msg", [("foo=1", "unknown effect 'foo'"), ("cross_coupling:mag=1", "acts on acc"),
                                      ("bias@somewhere", "scope must be"), ("temperature_bias", "give its size"),
                                      ("3,bias=1", "without an effect before it")])
def test_unknown_or_misapplied_effect_is_refused(text, msg):
    with pytest.raises(ValueError, match=msg):
        sim.build_probe(1, [text])


def test_a_simulated_probe_round_trips_through_its_truth():
    probe = sim.build_probe(3, ["temperature_bias:mag=2", "axial_interference=300", "stand_pose_error=0.1"])
    again = sim.SimulatedProbe.from_dict(probe.to_dict())
    assert again.model.labels() == probe.model.labels() == ["temperature_bias:mag:xyz", "axial_interference:mag:z@val"]
    np.testing.assert_array_equal(again.model.get_vector(), probe.model.get_vector())
    assert again.stand_pose_error_deg == 0.1


_LOG_FIELDS = ("t_s", "acc", "mag", "temp_c", "pose", "ref", "station", "md_m")


@pytest.mark.parametrize("effects", [[], ["bias_wander:mag=5", "stand_pose_error=0.05", "temperature_bias:mag=2",
                                          "time_skew=0.01", "axial_interference=300"]])
@pytest.mark.parametrize("chunk", [1, 7, 250])
def test_a_session_simulated_in_chunks_is_the_whole_session_bit_for_bit(effects, chunk):
    """The probe node simulates its script in pieces (bounded memory): the same RNG stream, the
    same numbers as the whole simulation, a calibration then a survey continuing from it (one
    walk, one generator), whatever the piece size — also one sample, or a piece across a move."""
    def two_sessions(chunked):
        probe, rng = sim.build_probe(3, effects), np.random.default_rng(11)
        cal = sim.SessionPlan(probe, Site(), sim.twelve_pose_session((25.0, 40.0), duration_s=0.9), rng, rate_hz=97.0)
        pieces = cal.chunks(chunk) if chunked else [cal.log()]
        # the survey is planned before the calibration's pieces are taken (as the probe node does)
        well = sim.SessionPlan(probe, Site(), sim.well_path_session(4, duration_s=1.1), rng, rate_hz=97.0,
                               t0=cal.t_last + 1.0 / 97.0, survey=True, lead_in=(np.eye(3), 0.7))
        pieces2 = well.chunks(chunk) if chunked else None
        pieces = list(pieces)
        pieces2 = list(pieces2) if chunked else [well.log()]
        assert max(len(p) for p in pieces + pieces2) <= (chunk if chunked else cal.n + well.n)
        assert sum(map(len, pieces)) == cal.n and pieces[-1].t_s[-1] == cal.t_last
        return [pieces, pieces2], rng.normal()

    whole, after_whole = two_sessions(False)
    chunked, after_chunked = two_sessions(True)
    assert after_whole == after_chunked      # the generator is left where the whole simulation leaves it
    for w, c in zip(whole, chunked):
        for f in _LOG_FIELDS:
            np.testing.assert_array_equal(getattr(w[0], f), np.concatenate([getattr(p, f) for p in c]), err_msg=f)

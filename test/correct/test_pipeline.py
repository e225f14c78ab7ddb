"""The survey pipeline: gates, the record's correction, QC against the site the record owns."""
import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site
from inclinometer_calib.correct.pipeline import NO_SITE, SurveyProcessor, site_override_note
from inclinometer_calib.detect.streaming import StaticDetector
from inclinometer_calib.io import surveystation


def _stations(log):
    det = StaticDetector()
    out = []
    g = log.gravity
    for i in range(len(log)):
        out.extend(det.update(log.t_s[i], g[i], log.mag[i], log.temp_c[i]))
    return out + list(det.flush())


def _one(probe, site, drift, azimuth, toolface, survey=False):
    log = sim.run_session(probe, site, sim.stand_grid_session(drifts=(drift,), azimuths=(azimuth,),
                                                               toolfaces=(toolface,), duration_s=3.0),
                          np.random.default_rng(0), survey=survey)
    return _stations(log)[0]


def test_a_station_is_corrected_by_the_record_and_checked_against_the_records_site():
    probe = sim.build_probe(2)
    site = Site()
    proc = SurveyProcessor(calibration=Calibration(probe.model, site=site))
    f = proc.process(_one(probe, site, 45, 120, 30), ref=(45.0, 120.0, 30.0))
    assert f["drift_deg"] == pytest.approx(45.0, abs=0.01)
    assert abs(f["azimuth_deg"] - 120.0) < 0.05
    assert f["status"] == 0 and abs(f["delta_b_nt"]) < 30
    assert f["coefficients_id"] == proc.calibration.id
    assert sorted(f) == sorted(surveystation.NAMES)        # every field of the message, none other


def test_a_given_site_overrides_the_records_and_says_so():
    probe = sim.build_probe(2)
    cal = Calibration(probe.model, site=Site())
    other = Site(total_field_nt=48000.0, dip_deg=60.0)
    proc = SurveyProcessor(site=other)
    notes = proc.set_calibration(cal)
    assert len(notes) == 1 and "overrides" in notes[0] and "48000" in notes[0] and cal.id in notes[0]
    f = proc.process(_one(probe, Site(), 45, 120, 30))
    assert f["delta_b_nt"] == pytest.approx(50000 - 48000, abs=40)   # checked against the given site
    assert site_override_note(cal, Site()) == ""                      # the same site: nothing to say


def test_without_a_record_and_without_a_site_there_is_no_qc_and_the_station_says_why():
    probe = sim.build_probe(2)
    f = SurveyProcessor().process(_one(probe, Site(), 45, 120, 30))
    assert np.isnan(f["delta_b_nt"]) and np.isnan(f["delta_dip_deg"]) and np.isnan(f["delta_g_mps2"])
    assert not f["interference_suspected"] and f["status"] >= 1
    assert NO_SITE in f["warnings"] and f["azimuth_reference"] == "magnetic" and f["coefficients_id"] == ""


def test_station_fields_carry_a_partial_reference_and_the_gates_outcome():
    probe = sim.build_probe(2)
    site = Site()
    ref = (0.0, float("nan"), 40.0)                 # a vertical stand pose: no azimuth
    f = SurveyProcessor(calibration=Calibration(probe.model, site=site)).process(_one(probe, site, 0, 0, 40), ref=ref)
    assert f["reference_drift_deg"] == 0.0 and np.isnan(f["reference_azimuth_deg"])
    assert f["reference_toolface_deg"] == 40.0
    assert f["azimuth_undefined"] and f["moved_during_capture"] is False and f["warnings"] == []


def test_station_fields_carry_the_short_collar_azimuth_when_enabled():
    probe = sim.build_probe(2, ["axial_interference=400"])
    site = Site()
    cal = Calibration(acc=probe.acc, mag=probe.mag, site=site)   # the base model: the interference stays
    st = _one(probe, site, 60, 30, 0, survey=True)
    ref = (60.0, 30.0, 0.0)
    plain = SurveyProcessor(calibration=cal).process(st, ref=ref)
    fixed = SurveyProcessor(calibration=cal, axial=True).process(st, ref=ref)
    assert plain["azimuth_method"] == "standard" and np.isnan(plain["axial_field_nt"])
    assert plain["interference_suspected"] and fixed["interference_suspected"]  # QC on the measured field
    assert fixed["azimuth_method"] == "short_collar"
    assert fixed["axial_field_nt"] == pytest.approx(400.0, abs=15.0)
    assert abs(fixed["azimuth_deg"] - 30.0) < 0.05 < abs(plain["azimuth_deg"] - 30.0)


def test_a_temperature_model_without_a_temperature_is_said_not_defaulted():
    probe = sim.build_probe(3, ["temperature_bias:mag=3"])
    site = Site()
    st = _one(probe, site, 45, 120, 30)
    st.temp_c = float("nan")
    f = SurveyProcessor(calibration=Calibration(probe.model, site=site)).process(st)
    assert any("no temperature" in w for w in f["warnings"])
    assert np.isnan(f["azimuth_deg"]) and f["status"] == 2


def test_stations_with_a_depth_get_the_trajectory_by_minimum_curvature_and_a_resurvey_replaces():
    from inclinometer_calib.io.probelog import segment_stations
    from inclinometer_calib.correct.trajectory import minimum_curvature

    probe = sim.build_probe(2)
    site = Site(declination_deg=2.0)
    log = sim.run_session(probe, site, sim.well_path_session(10, md_start_m=800.0, md_step_m=30.0),
                          np.random.default_rng(1), rate_hz=50.0)
    stations, _ = segment_stations(log)
    assert [round(s.md_m, 3) for s in stations] == [800.0 + 30 * k for k in range(10)]
    proc = SurveyProcessor(calibration=Calibration(probe.model, site=site))
    fields = [proc.process(st, ref=tuple(st.ref)) for st in stations]
    ref = np.array([s.ref for s in stations])
    true = minimum_curvature(np.r_[0.0, [s.md_m for s in stations]], np.r_[0.0, ref[:, 0]],
                             np.r_[0.0, np.nan_to_num(ref[:, 1])])
    for k, f in enumerate(fields):
        assert f["measured_depth_m"] == 800.0 + 30 * k
        # the measured angles' trajectory: within what their errors (0.01°) make over 1 km
        assert abs(f["tvd_m"] - true.tvd[k + 1]) < 0.05 and abs(f["north_m"] - true.north[k + 1]) < 0.1
        assert abs(f["east_m"] - true.east[k + 1]) < 0.1 and abs(f["dls_deg_per_30m"] - true.dls[k + 1]) < 0.05
        if np.isfinite(f["azimuth_deg"]):
            assert f["azimuth_magnetic_deg"] == pytest.approx((f["azimuth_deg"] - 2.0) % 360, abs=1e-9)
        assert np.isnan(f["azimuth_grid_deg"])            # the site has no grid
    # a re-survey at a depth already passed replaces what lies below it
    again = proc.process(stations[5], ref=tuple(stations[5].ref))
    assert again["tvd_m"] == pytest.approx(fields[5]["tvd_m"], abs=1e-6)
    nxt = proc.process(stations[6], ref=tuple(stations[6].ref))
    assert nxt["north_m"] == pytest.approx(fields[6]["north_m"], abs=1e-6)
    # without a depth: no position
    st = _one(probe, site, 30, 40, 0)
    f = SurveyProcessor(calibration=Calibration(probe.model, site=site)).process(st)
    assert np.isnan(f["measured_depth_m"]) and np.isnan(f["tvd_m"]) and np.isnan(f["north_m"])


def test_each_placed_station_carries_its_iscwsa_covariance_and_its_raw_means():
    from inclinometer_calib.correct import iscwsa
    from inclinometer_calib.io.probelog import segment_stations

    probe = sim.build_probe(4)
    site = Site(declination_deg=3.0)
    log = sim.run_session(probe, site, sim.well_path_session(8, md_start_m=600.0, md_step_m=30.0),
                          np.random.default_rng(2), rate_hz=50.0)
    stations, _ = segment_stations(log)
    unc = {"acc": {"bias": [2e-4, 2e-4, 3e-4], "scale": [1e-4, 1e-4, 1e-4]},
           "mag": {"bias": [5.0, 5.0, 8.0], "scale": [3e-4, 3e-4, 4e-4]}}
    cal = Calibration(probe.model, site=site, uncertainty=unc)
    proc = SurveyProcessor(calibration=cal)
    fields = [proc.process(st) for st in stations]
    for st, f in zip(stations, fields):
        np.testing.assert_array_equal(f["raw_gravity_mps2"], st.g)
        np.testing.assert_array_equal(f["raw_field_nt"], st.b)
    # the same as the model over the whole path at once, with the record's sensor terms
    md = np.r_[0.0, [f["measured_depth_m"] for f in fields]]
    inc = np.r_[0.0, [f["drift_deg"] for f in fields]]
    azi = np.r_[0.0, [f["azimuth_deg"] for f in fields]]
    whole = iscwsa.position_covariance(md, inc, azi, total_gravity_mps2=site.gravity_mps2,
                                       total_field_nt=site.total_field_nt, dip_deg=site.dip_deg,
                                       declination_deg=3.0, terms=iscwsa.terms_from_calibration(cal, site))
    for k, f in enumerate(fields):
        np.testing.assert_allclose(np.reshape(f["position_covariance_ned_m2"], (3, 3)), whole.cov[k + 1],
                                   rtol=0, atol=1e-6 * np.max(whole.cov[k + 1]))
    sig = [np.sqrt(np.trace(np.reshape(f["position_covariance_ned_m2"], (3, 3)))) for f in fields]
    assert all(b > a for a, b in zip(sig, sig[1:]))        # uncertainty grows with depth
    # without a site there is no field to weigh the magnetic terms: NaN, not a guess
    bare = SurveyProcessor(calibration=None).process(stations[0])
    assert np.all(np.isnan(bare["position_covariance_ned_m2"]))


def test_a_record_of_another_probe_is_refused_and_a_later_serial_drops_it_saying_why():
    from inclinometer_calib.correct.pipeline import ProbeMismatch, probe_mismatch

    probe = sim.build_probe(2)
    site = Site()
    st = _one(probe, site, 30, 40, 0)
    mine = Calibration(probe.model, site=site, probe_id="SN-1")
    theirs = Calibration(probe.model, site=site, probe_id="SN-2")
    assert probe_mismatch(theirs, "SN-1") and probe_mismatch(mine, "SN-1") is None
    assert probe_mismatch(Calibration(probe.model, site=site), "SN-1") is None    # a record naming no probe
    proc = SurveyProcessor(calibration=mine, probe_serial="SN-1")
    with pytest.raises(ProbeMismatch, match="SN-2"):
        proc.set_calibration(theirs)
    assert proc.calibration is mine                                  # the record in force stays
    f = proc.process(st)
    assert f["probe_serial"] == "SN-1" and f["coefficients_id"] == mine.id
    # the data turn out to be another probe's: the record is dropped, the stations say why
    with pytest.raises(ProbeMismatch):
        proc.set_probe_serial("SN-3")
    f = proc.process(_one(probe, site, 30, 40, 0))
    assert f["coefficients_id"] == "" and any("uncorrected: record" in w for w in f["warnings"])
    # forced: applied, and every station says so
    forced = SurveyProcessor(calibration=theirs, probe_serial="SN-1", force_probe=True)
    f = forced.process(_one(probe, site, 30, 40, 0))
    assert f["coefficients_id"] == theirs.id and any(w.startswith("FORCED") for w in f["warnings"])


def test_every_azimuth_and_position_of_a_station_is_along_the_one_north_asked_for_and_says_which():
    from north_well import CONVERGENCE, DECLINATION, projected_well, receiver_positions

    from inclinometer_calib.core.frames import wrap180

    runs = {n: projected_well(n)[2] for n in ("auto", "grid", "true", "magnetic")}
    assert repr(runs["auto"]) == repr(runs["grid"])           # a projected site: grid north by default
    for north in ("grid", "true", "magnetic"):
        fields = runs[north]
        for f in fields:
            assert f["azimuth_reference"] == north
            if np.isfinite(f["azimuth_deg"]):
                assert f["azimuth_deg"] == f[f"azimuth_{north}_deg"]
                assert wrap180(f["azimuth_true_deg"] - f["azimuth_magnetic_deg"]) == pytest.approx(DECLINATION)
                assert wrap180(f["azimuth_true_deg"] - f["azimuth_grid_deg"]) == pytest.approx(CONVERGENCE)
                # the reference attitude (the simulator's, true) along the same north: errors stay errors
                assert abs(wrap180(f["azimuth_deg"] - f["reference_azimuth_deg"])) < 0.1
        # a receiver's own minimum curvature from MD, drift and azimuth_deg lands on north/east
        rx = receiver_positions([f["measured_depth_m"] for f in fields], [f["drift_deg"] for f in fields],
                                [np.nan_to_num(f["azimuth_deg"]) for f in fields])
        for f, (n, e) in zip(fields, rx):
            assert (f["north_m"], f["east_m"]) == pytest.approx((n, e), abs=1e-6)
    # the same well along each north: a leg between stations with an azimuth is the true one turned by γ
    # (a vertical station's undefined azimuth counts as 0 from whichever north: those legs are not turned)
    g = np.radians(CONVERGENCE)
    t, gr = runs["true"], runs["grid"]
    legs = [k for k in range(1, len(t)) if np.isfinite(t[k - 1]["azimuth_deg"]) and np.isfinite(t[k]["azimuth_deg"])]
    assert len(legs) >= 5
    for k in legs:
        n, e = t[k]["north_m"] - t[k - 1]["north_m"], t[k]["east_m"] - t[k - 1]["east_m"]
        assert (gr[k]["north_m"] - gr[k - 1]["north_m"], gr[k]["east_m"] - gr[k - 1]["east_m"]) == pytest.approx(
            (n * np.cos(g) + e * np.sin(g), -n * np.sin(g) + e * np.cos(g)), abs=1e-6)
        assert gr[k]["tvd_m"] - gr[k - 1]["tvd_m"] == pytest.approx(t[k]["tvd_m"] - t[k - 1]["tvd_m"], abs=1e-9)
    assert abs(runs["grid"][-1]["east_m"] - runs["true"][-1]["east_m"]) > 0.1     # the norths do differ here


def test_a_north_the_site_cannot_give_is_refused_at_once_or_said_at_every_station():
    probe = sim.build_probe(2)
    plain = Site(declination_deg=2.0)                               # no grid
    with pytest.raises(ValueError, match="no grid"):
        SurveyProcessor(site=plain, north="grid")
    with pytest.raises(ValueError, match="north 'geographic'"):
        SurveyProcessor(north="geographic")
    # the record's site (known only when the record comes): the station falls back and says so
    f = SurveyProcessor(calibration=Calibration(probe.model, site=plain), north="grid").process(
        _one(probe, plain, 45, 120, 30))
    assert f["azimuth_reference"] == "true" and np.isnan(f["azimuth_grid_deg"])
    assert any("grid north asked for" in w and "along true north" in w for w in f["warnings"])

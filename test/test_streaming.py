"""Live static detection and station correction (ROS-free parts of the nodes)."""
import numpy as np
import pytest

from inclinometer_calib import simulate as sim
from inclinometer_calib.frames import Site
from inclinometer_calib.streaming import StaticDetector, SurveyProcessor


def _segments(log, **kw):
    det = StaticDetector(**kw)
    segs = []
    for i in range(len(log)):
        s = det.update(log.t_s[i], log.acc[i], log.mag[i], log.temp_c[i])
        if s is not None:
            segs.append(s)
    s = det.flush()
    if s is not None:
        segs.append(s)
    return segs, det


def test_detector_finds_each_station_of_a_session_and_nothing_during_moves():
    probe = sim.build_probe(1)
    log = sim.run_session(probe, Site(), sim.twelve_pose_session(duration_s=2.0), np.random.default_rng(0))
    segs, det = _segments(log)
    full = [s for s in segs if not s.short]
    assert len(full) == 12
    # each segment lies inside one labelled station (it may take in the first, still nearly
    # unrotated, sample of the following move: deviation below the threshold by construction)
    for s in full:
        rows = (log.t_s >= s.t_start) & (log.t_s <= s.t_end)
        poses, counts = np.unique(log.pose[rows], return_counts=True)
        main = poses[np.argmax(counts)]
        assert main > 0 and counts.max() >= rows.sum() - 2
        assert s.duration_s > 1.5


def test_short_stop_is_reported_as_short():
    probe = sim.build_probe(1)
    stations = sim.stand_grid_session(drifts=(10, 20, 30), azimuths=(0,), toolfaces=(0,), duration_s=2.0)
    stations[1].duration_s = 0.6
    log = sim.run_session(probe, Site(), stations, np.random.default_rng(0))
    segs, det = _segments(log, min_duration_s=1.0)
    assert [s.short for s in segs] == [False, True, False]
    assert det.too_short == 1


def test_nan_sample_breaks_a_station_without_poisoning_it():
    probe = sim.build_probe(1)
    log = sim.run_session(probe, Site(), sim.stand_grid_session(drifts=(10,), azimuths=(0,), toolfaces=(0,),
                                                                 duration_s=4.0), np.random.default_rng(0))
    log.acc[200, 1] = np.nan
    segs, _ = _segments(log)
    assert len([s for s in segs if not s.short]) == 2
    assert all(np.all(np.isfinite(s.g)) for s in segs)


def test_processor_corrects_and_evaluates_a_segment():
    probe = sim.build_probe(2)
    site = Site()
    log = sim.run_session(probe, site, sim.stand_grid_session(drifts=(45,), azimuths=(120,), toolfaces=(30,),
                                                               duration_s=3.0), np.random.default_rng(0))
    segs, _ = _segments(log)
    from inclinometer_calib.coeffs import Calibration
    proc = SurveyProcessor(site, calibration=Calibration(acc=probe.acc, mag=probe.mag))
    rec = proc.process(segs[0], ref=(45.0, 120.0, 30.0))
    assert rec.values["drift_deg"] == pytest.approx(45.0, abs=0.01)
    assert abs(rec.values["azimuth_err"]) < 0.05
    assert rec.values["status"] == 0
    assert rec.coefficients_id == proc.calibration.id


def test_station_fields_carry_the_short_collar_azimuth_when_enabled():
    from inclinometer_calib.coeffs import Calibration
    from inclinometer_calib.streaming import station_fields

    probe = sim.build_probe(2, [("axial_interference", None, None, [400.0])])
    site = Site()
    log = sim.run_session(probe, site, sim.stand_grid_session(drifts=(60,), azimuths=(30,), toolfaces=(0,),
                                                               duration_s=3.0), np.random.default_rng(0),
                          survey=True)
    segs, _ = _segments(log)
    cal = Calibration(acc=probe.acc, mag=probe.mag)
    ref = (60.0, 30.0, 0.0)
    plain = station_fields(SurveyProcessor(site, calibration=cal).process(segs[0], ref=ref), ref, "magnetic",
                           True, True)
    fixed = station_fields(SurveyProcessor(site, calibration=cal, axial=True).process(segs[0], ref=ref), ref,
                           "magnetic", True, True)
    assert plain["azimuth_method"] == "standard" and np.isnan(plain["axial_field_nt"])
    assert plain["interference_suspected"] and fixed["interference_suspected"]  # QC on the measured field
    assert fixed["azimuth_method"] == "short_collar"
    assert fixed["axial_field_nt"] == pytest.approx(400.0, abs=15.0)
    assert abs(fixed["azimuth_deg"] - 30.0) < 0.05 < abs(plain["azimuth_deg"] - 30.0)

"""Live twelve-pose capture: pose identification, warnings, solve when complete."""
import numpy as np
import pytest

from inclinometer_calib import simulate as sim
from inclinometer_calib.capture import CaptureSession
from inclinometer_calib.frames import Site
from inclinometer_calib.streaming import StaticDetector


def _feed(session, log):
    det = StaticDetector()
    out = []
    for i in range(len(log)):
        s = det.update(log.t_s[i], log.acc[i], log.mag[i], log.temp_c[i])
        if s is not None:
            out.append(session.offer(s))
    s = det.flush()
    if s is not None:
        out.append(session.offer(s))
    return out


def _log(stations, seed=1, probe=None):
    probe = probe or sim.build_probe(seed)
    return probe, sim.run_session(probe, Site(), stations, np.random.default_rng(seed))


def test_full_session_identifies_every_pose_and_solves_to_the_truth():
    probe, log = _log(sim.twelve_pose_session(duration_s=2.0))
    s = CaptureSession(site=Site())
    results = _feed(s, log)
    assert results[-1] == "solved" and s.state == "done"
    assert s.captured == list(range(1, 13))
    np.testing.assert_allclose(s.calibration.mag.A, probe.mag.A, atol=2e-3)
    np.testing.assert_allclose(s.calibration.acc.bias, probe.acc.bias, atol=2e-3)
    assert s.warnings == []


def test_repeated_and_out_of_order_poses_warn():
    stations = sim.twelve_pose_session(duration_s=2.0)
    order = [0, 1, 3, 1, 2] + list(range(4, 12))  # 4 before 3, then pose 2 again
    _, log = _log([stations[i] for i in order])
    s = CaptureSession(site=Site())
    _feed(s, log)
    text = "\n".join(s.warnings)
    assert "pose 2" in text and "repeated pose" in text
    assert "pose 4" in text and "out of order (expected pose 3" in text
    assert s.state == "done"


def test_too_short_capture_is_rejected_and_pose_stays_pending():
    stations = sim.twelve_pose_session(duration_s=2.0)
    stations[6].duration_s = 0.5
    _, log = _log(stations)
    s = CaptureSession(site=Site())
    _feed(s, log)
    assert s.pending == [7]
    assert any("pose 7" in w and "too short" in w for w in s.warnings)


def test_recapture_replaces_a_pose():
    stations = sim.twelve_pose_session(duration_s=2.0)
    probe, log = _log(stations)
    s = CaptureSession(site=Site())
    _feed(s, log)
    first = s.captures[5][0].g.copy()
    s.request_recapture(5)
    _, log2 = _log([stations[4]], seed=9, probe=probe)
    assert _feed(s, log2)[-1] == "solved"
    assert len(s.captures[5]) == 1 and not np.array_equal(s.captures[5][0].g, first)
    with pytest.raises(ValueError):
        s.request_recapture(13)


def test_off_pose_static_is_ignored_with_a_warning():
    _, log = _log(sim.stand_grid_session(drifts=(45,), azimuths=(0,), toolfaces=(0,), duration_s=2.0))
    s = CaptureSession(site=Site())
    assert _feed(s, log) == ["ignored"]
    assert "not one of the twelve poses" in s.warnings[0]

"""Probe-log CSV: exact format, rejections that name row and reason, static-station segmentation."""
import numpy as np
import pytest

from inclinometer_calib import simulate as sim
from inclinometer_calib.frames import Site
from inclinometer_calib.probelog import HEADER, ProbeLog, format_csv, parse_csv, segment_stations

GOOD = "0.00,0.1,0.2,-9.8,20000,1000,40000,25,1,,,\n"


def _csv(*rows):
    return ",".join(HEADER) + "\n" + "".join(rows)


def test_header_line_is_literal():
    assert ",".join(HEADER) == ("t_s,ax,ay,az,mx,my,mz,temp_c,pose,ref_drift_deg,ref_azimuth_deg,"
                                "ref_toolface_deg")


def test_wrong_header_is_refused_with_line_1():
    with pytest.raises(ValueError, match="line 1: header"):
        parse_csv("t,ax,ay,az,mx,my,mz,temp,pose,a,b,c\n" + GOOD)


def test_round_trip_through_csv_text():
    log = sim.run_session(sim.build_probe(1), Site(), sim.twelve_pose_session(duration_s=0.2),
                          np.random.default_rng(0), rate_hz=50)
    back, rej = parse_csv(format_csv(log))
    assert rej == []
    np.testing.assert_allclose(back.acc, log.acc, atol=5e-7)
    np.testing.assert_allclose(back.mag, log.mag, atol=5e-4)
    np.testing.assert_array_equal(back.pose, log.pose)


@pytest.mark.parametrize("row,reason", [
    ("0.01,nan,0.2,-9.8,20000,1000,40000,25,1,,,\n", "ax not finite"),
    ("0.01,0.1,inf,-9.8,20000,1000,40000,25,1,,,\n", "ay not finite"),
    ("0.01,0.1,0.2,abc,20000,1000,40000,25,1,,,\n", "az='abc' is not a number"),
    ("0.01,0.1,0.2,-19.6,20000,1000,40000,25,1,,,\n", "az=-19.6 m/s² is saturated"),
    ("0.01,0.1,0.2,-9.8,99999,1000,40000,25,1,,,\n", "mx=99999 nT is saturated"),
    ("0.01,0.1,0.2,-9.8,2e-5,1e-6,4e-5,25,1,,,\n", "look like tesla"),
    ("0.01,0.1,0.2,-9.8,0,0,0,25,1,,,\n", "total field 0 nT is implausible"),
    ("0.01,0.1,0.2,-0.98,20000,1000,40000,25,1,,,\n", "total acceleration"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,13,,,\n", "pose='13' is not one of 1..12"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,,10,,\n", "all three or none"),
    ("0.00,0.1,0.2,-9.8,20000,1000,40000,25,1,,,\n", "non-monotonic timestamp"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,1,,\n", "11 fields, expected 12"),
])
def test_bad_row_is_rejected_naming_row_line_and_reason_and_the_rest_kept(row, reason):
    text = _csv(GOOD, row, "0.02,0.1,0.2,-9.8,20000,1000,40000,25,1,,,\n")
    log, rej = parse_csv(text)
    assert len(log) == 2
    assert len(rej) == 1
    assert rej[0].row == 2 and rej[0].line == 3
    assert reason in str(rej[0])
    assert str(rej[0]).startswith("row 2 (line 3): ")


def test_file_with_no_usable_rows_is_an_error_naming_the_first_rejection():
    with pytest.raises(ValueError, match="no usable rows.*row 1"):
        parse_csv(_csv("0,nan,0,0,0,0,0,25,,,,\n"))


def _labelled_log(n_per, labels, noise=0.001, seed=0):
    rng = np.random.default_rng(seed)
    n = n_per * len(labels)
    pose = np.repeat([p for p, _ in labels], n_per)
    ref = np.repeat([r for _, r in labels], n_per, axis=0).astype(float)
    acc = np.tile([0.0, 0.0, -9.8], (n, 1)) + rng.normal(0, noise, (n, 3))
    mag = np.tile([20000.0, 0.0, 40000.0], (n, 1)) + rng.normal(0, 10, (n, 3))
    return ProbeLog(np.arange(n) * 0.01, acc, mag, np.full(n, 25.0), pose, ref)


NAN3 = (np.nan, np.nan, np.nan)


def test_consecutive_rows_with_same_label_form_one_station_and_repeats_are_new_stations():
    labels = [(1, NAN3), (0, NAN3), (2, NAN3), (0, (10, 20, 30)), (0, (10, 20, 40)), (1, NAN3)]
    stations, problems = segment_stations(_labelled_log(20, labels))
    assert problems == []
    assert [s.pose for s in stations] == [1, 2, 0, 0, 1]
    assert [tuple(s.ref) for s in stations[2:4]] == [(10, 20, 30), (10, 20, 40)]
    assert all(s.n == 20 for s in stations)
    # the reader converts REP-145 specific force to the gravity vector, once
    assert stations[0].g[2] == pytest.approx(9.8, abs=0.01)


def test_too_short_station_is_dropped_with_a_message():
    log = _labelled_log(20, [(1, NAN3), (2, NAN3), (3, NAN3)])
    log.pose[20:37] = 0  # pose 2 keeps 3 samples
    stations, problems = segment_stations(log, min_samples=5)
    assert [s.pose for s in stations] == [1, 3]
    assert any("pose 2" in p and "too short" in p for p in problems)


def test_probe_moving_during_capture_is_flagged():
    log = _labelled_log(50, [(p, NAN3) for p in range(1, 7)])
    log.acc[100:150, 0] += np.linspace(0, 3, 50)  # pose 3 rolls while captured
    stations, problems = segment_stations(log)
    assert stations[2].warnings and "moved during the capture" in stations[2].warnings[0]
    assert sum(bool(s.warnings) for s in stations) == 1


def test_empty_temperature_is_unknown_not_a_bad_row():
    log, rej = parse_csv(_csv(GOOD, "0.01,0.1,0.2,-9.8,20000,1000,40000,,1,,,\n"))
    assert rej == [] and len(log) == 2
    assert np.isnan(log.temp_c[1])
    stations, _ = segment_stations(log, min_samples=2)
    assert stations[0].temp_c == 25.0  # the mean of the known temperatures
    log.temp_c[:] = np.nan
    stations, _ = segment_stations(log, min_samples=2)
    assert np.isnan(stations[0].temp_c)

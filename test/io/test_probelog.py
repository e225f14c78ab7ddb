"""Probe-log CSV: exact format, rejections that name row and reason, static-station segmentation."""
import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.frames import Site, drift_deg
from inclinometer_calib.io.probelog import HEADER, ProbeLog, format_csv, parse_csv, segment_stations

GOOD = "0.00,0.1,0.2,-9.8,20000,1000,40000,25,1,,,\n"


def _csv(*rows):
    return ",".join(HEADER) + "\n" + "".join(rows)


def test_header_line_is_literal():
    assert ",".join(HEADER) == ("t_s,ax,ay,az,mx,my,mz,temp_c,pose,ref_drift_deg,ref_azimuth_deg,"
                                "ref_toolface_deg")


def test_wrong_header_is_refused_with_line_1_naming_what_is_missing_and_unknown():
    with pytest.raises(ValueError, match=r"line 1: the columns are .* \(missing t_s; unknown 't', 'temp', 'a', 'b', "
                                         r"'c'\)"):
        parse_csv("t,ax,ay,az,mx,my,mz,temp,pose,a,b,c\n" + GOOD)
    with pytest.raises(ValueError, match=r"\(given twice: ax\)"):
        parse_csv("t_s,ax,ay,az,mx,my,mz,ax\n1,0,0,-9.8,1,2,3,0\n")


@pytest.mark.parametrize("engine", ["rows", "arrow"])
def test_columns_are_read_by_name_in_any_order_and_optional_ones_may_be_absent(engine):
    canonical = HEADER[:]
    text = ",".join(canonical) + "\n" + GOOD
    order = [3, 0, 11, 2, 1, 8, 4, 10, 5, 6, 7, 9]
    rows = [line.split(",") for line in text.splitlines()]
    shuffled = "\n".join(",".join(r[k] for k in order) for r in rows) + "\n"
    a, ra = parse_csv(text, engine=engine)
    b, rb = parse_csv(shuffled, engine=engine)
    for name in ("t_s", "acc", "mag", "temp_c", "pose", "ref"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert [str(x) for x in ra] == [str(x) for x in rb]
    # the columns a turntable rig writes: no pose, no stand reference (it used to be refused)
    tt = ("t_s,ax,ay,az,mx,my,mz,temp_c,mount,table_deg\n"
          "0.00,0.1,0.2,-9.8,20000,100,40000,25.0,xy,0\n"
          "0.01,0.1,0.2,-9.8,20000,100,40000,25.0,xy,0\n"
          "0.02,0.1,0.2,-9.8,20000,100,40000,,xy,\n")
    log, rej = parse_csv(tt, engine=engine)
    assert not rej and len(log) == 3 and list(log.mount) == ["xy"] * 3
    assert np.array_equal(log.table_deg[:2], [0.0, 0.0]) and np.isnan(log.table_deg[2]) and np.isnan(log.temp_c[2])
    assert not log.pose.any() and np.isnan(log.ref).all()


def test_round_trip_through_csv_text():
    log = sim.run_session(sim.build_probe(1), Site(), sim.twelve_pose_session(duration_s=0.2),
                          np.random.default_rng(0), rate_hz=50)
    back, rej = parse_csv(format_csv(log))
    assert rej == []
    np.testing.assert_allclose(back.acc, log.acc, atol=5e-7)
    np.testing.assert_allclose(back.mag, log.mag, atol=5e-4)
    np.testing.assert_array_equal(back.pose, log.pose)


def test_a_resting_vertical_probe_enters_the_core_as_gravity_down_positive():
    # REP-145: at rest the accelerometer reads the reaction to gravity, up: -9.8 on a down-hole Z
    log, rej = parse_csv(",".join(HEADER[:7]) + "\n0.0,0.1,0.0,-9.8,20000,1000,40000\n")
    assert rej == []
    np.testing.assert_array_equal(log.gravity, [[-0.1, 0.0, 9.8]])
    assert drift_deg(log.gravity[0]) < 1.0                  # vertical: the paper's eq. (1) on g, not on f
    log.gravity[0, 2] = 0.0                                 # a new array each time: the record stays as read
    assert log.acc[0, 2] == -9.8


@pytest.mark.parametrize("row,reason", [
    ("0.01,nan,0.2,-9.8,20000,1000,40000,25,1,,,\n", "ax not finite"),
    ("0.01,0.1,inf,-9.8,20000,1000,40000,25,1,,,\n", "ay not finite"),
    ("0.01,0.1,0.2,abc,20000,1000,40000,25,1,,,\n", "az='abc' is not a number"),
    ("0.01,0.1,0.2,-19.6,20000,1000,40000,25,1,,,\n", "az=-19.6 m/s² is saturated"),
    ("0.01,0.1,0.2,-9.8,99999,1000,40000,25,1,,,\n", "mx=99999 nT is saturated"),
    ("0.01,0.1,0.2,-9.8,2e-5,1e-6,4e-5,25,1,,,\n", "look like tesla: give the unit (--mag-unit T)"),
    ("0.01,0.1,0.2,-9.8,0.2,0.01,0.4,25,1,,,\n", "look like gauss"),
    ("0.01,0.1,0.2,-9.8,0,0,0,25,1,,,\n", "total field 0 nT is implausible"),
    ("0.01,0.1,0.2,-0.98,20000,1000,40000,25,1,,,\n", "total acceleration"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,13,,,\n", "pose='13' is not one of 1..12"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,inf,,,\n", "pose='inf' is not one of 1..12"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,nan,,,\n", "pose='nan' is not a number"),
    ("0.01,0.1,0.2,-9.8,20000,1000,40000,25,,190,,\n", "ref_drift_deg=190 outside 0..180"),
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


def test_a_reference_is_read_for_what_it_gives_and_no_row_is_lost_for_a_blank_column():
    # a stand's log gives drift and toolface of its vertical poses, no azimuth
    log, rej = parse_csv(_csv("0.00,0.1,0.2,-9.8,20000,1000,40000,25,9,0.0,,0.0\n",
                              "0.01,0.1,0.2,-9.8,20000,1000,40000,25,,45.0,,\n",
                              "0.02,0.1,0.2,-9.8,20000,1000,40000,25,,,,\n"))
    assert rej == [] and len(log) == 3
    np.testing.assert_array_equal(log.ref[0], [0.0, np.nan, 0.0])
    np.testing.assert_array_equal(log.ref[1], [45.0, np.nan, np.nan])
    assert np.all(np.isnan(log.ref[2]))


@pytest.mark.parametrize("unit,scale", [("T", 1e-9), ("uT", 1e-3), ("G", 1e-5)])
def test_a_magnetometer_in_another_unit_is_read_in_nT_when_the_unit_is_given(unit, scale):
    row = f"0.00,0.1,0.2,-9.8,{20000 * scale:.9g},{1000 * scale:.9g},{40000 * scale:.9g},25,,,,\n"
    log, rej = parse_csv(_csv(row), mag_unit=unit)
    assert rej == []
    np.testing.assert_allclose(log.mag[0], [20000, 1000, 40000], rtol=1e-9)
    with pytest.raises(ValueError, match="unit 'Oe' unknown"):
        parse_csv(_csv(row), mag_unit="Oe")


def test_a_compressed_log_is_read(tmp_path):
    import gzip

    from inclinometer_calib.io.probelog import read_csv

    p = tmp_path / "log.csv.gz"
    with gzip.open(p, "wt") as fh:
        fh.write(_csv(GOOD))
    log, rej = read_csv(p)
    assert len(log) == 1 and rej == []


def _session_log(stations, noise_acc=0.002, seed=0, rate_hz=100.0):
    probe = sim.build_probe(1, noise_acc=noise_acc)
    return sim.run_session(probe, Site(), stations, np.random.default_rng(seed), rate_hz=rate_hz)


def test_stations_are_found_by_the_live_detector_and_named_by_their_rows_labels():
    poses = sim.twelve_pose_session(duration_s=2.0)[:2]
    grid = sim.stand_grid_session(drifts=(10,), azimuths=(20,), toolfaces=(30, 40), duration_s=2.0)
    log = _session_log(poses + grid + poses[:1])
    stations, problems = segment_stations(log)
    assert problems == []
    assert [s.pose for s in stations] == [1, 2, 0, 0, 1]
    assert [tuple(s.ref) for s in stations[2:4]] == [(10, 20, 30), (10, 20, 40)]
    for s in stations:        # the detector's window lies inside the labelled rows (it may take in the
        rows = slice(s.first_row - 1, s.last_row)   # first, still unrotated, sample of the next move)
        assert np.sum(log.pose[rows] == s.pose) >= s.n - 1 and 170 <= s.n <= 201
    # the detector converts REP-145 specific force to the gravity vector, once
    assert stations[0].g[0] == pytest.approx(9.8, abs=0.1)   # pose 1: tool X down


def test_a_labelled_hold_with_no_station_is_named_with_the_reason():
    stations = sim.twelve_pose_session(duration_s=2.0)[:3]
    stations[1].duration_s = 0.3
    log = _session_log(stations)
    found, problems = segment_stations(log)
    assert [s.pose for s in found] == [1, 3]
    assert problems == ["pose 2 at rows 301-330 (t=3.00-3.29 s): no static station found: the hold lasts 0.29 s, "
                        "less than the detector needs (0.5 s after 0.2 s settling)"]


def test_a_probe_moving_during_a_capture_is_found_by_the_gates():
    from inclinometer_calib.detect.gates import apply_gates

    log = _session_log(sim.twelve_pose_session(duration_s=3.0)[:4], noise_acc=0.005)
    rows = np.flatnonzero(log.pose == 3)
    log.acc[rows, 1] += np.linspace(0, 0.03, len(rows))   # pose 3 creeps 0.18° while captured
    stations, _ = segment_stations(log)
    moved = [s for s in stations if apply_gates(s) and s.moved]
    assert [s.pose for s in moved] == [3]
    assert "turned" in moved[0].warnings[0] and "pose 3" in moved[0].warnings[0]


def test_empty_temperature_is_unknown_not_a_bad_row():
    log, rej = parse_csv(_csv(GOOD, "0.01,0.1,0.2,-9.8,20000,1000,40000,,1,,,\n"))
    assert rej == [] and len(log) == 2
    assert np.isnan(log.temp_c[1])
    log = _session_log(sim.twelve_pose_session(duration_s=2.0)[:1])
    log.temp_c[::2] = np.nan
    stations, _ = segment_stations(log)
    rows = slice(stations[0].first_row - 1, stations[0].last_row)
    assert stations[0].temp_c == pytest.approx(np.nanmean(log.temp_c[rows]))  # the mean of the known ones
    log.temp_c[:] = np.nan
    stations, _ = segment_stations(log)
    assert np.isnan(stations[0].temp_c)


def test_stations_name_the_files_rows_though_rows_before_them_were_rejected():
    log = _session_log(sim.twelve_pose_session(duration_s=2.0)[:2])
    text = format_csv(log).splitlines()
    for k in range(5, 55):                            # 50 unusable rows before the second hold
        fields = text[k].split(",")
        fields[1] = "nan"
        text[k] = ",".join(fields)
    back, rej = parse_csv("\n".join(text) + "\n")
    assert len(rej) == 50
    stations, _ = segment_stations(back)
    rows = [r for r in range(1, len(log) + 1) if log.pose[r - 1] == 2]
    assert stations[1].pose == 2 and rows[0] <= stations[1].first_row and stations[1].last_row <= rows[-1] + 1


@pytest.mark.parametrize("engine", ["rows", "arrow"])
def test_a_log_file_with_its_columns_in_another_order_is_read_as_its_text_is(tmp_path, engine):
    from inclinometer_calib.io.probelog import read_csv

    text = "mz,my,mx,t_s,az,ay,ax,pose\n40000,1000,20000,0.00,-9.8,0.2,0.1,1\n40000,1000,20000,0.01,-9.8,0.2,0.1,1\n"
    (tmp_path / "p.csv").write_text(text)
    log, rej = read_csv(tmp_path / "p.csv", engine=engine)
    ref, _ = parse_csv(text, engine=engine)
    assert not rej and len(log) == 2 and np.array_equal(log.acc, ref.acc) and np.array_equal(log.mag, ref.mag)
    assert np.array_equal(log.acc[0], [0.1, 0.2, -9.8]) and list(log.pose) == [1, 1]
    assert np.isnan(log.temp_c).all()

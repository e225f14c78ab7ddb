"""Bad input fed to the CLI: a clear error or flag naming what and where, no crash, and the good
data around it still used.

Parse-level rejections are pinned in test_probelog.py, record checks in test_coeffs.py, and a
NaN calibration row / a missing pose / an edited offset in test_cli.py; here each remaining case
goes through ``inclinometer_calib.apps.cli.main`` in-process.
"""
import json

import numpy as np
import pytest
import yaml

from inclinometer_calib.apps.cli import main

N_VAL = 198      # stand-grid stations of the simulated validation log


@pytest.fixture(scope="module")
def simdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    assert main(["simulate", "--out", str(d), "--seed", "4", "--station-seconds", "1.5",
                 "--cal-temps", "25,30"]) == 0          # two rounds of the twelve poses
    return d


class Log:
    """A probe-log CSV as editable rows of fields (row k = data row k, file line k + 1)."""

    def __init__(self, path):
        lines = path.read_text().splitlines()
        self.header, self.rows = lines[0], [ln.split(",") for ln in lines[1:]]

    def write(self, path):
        path.write_text("\n".join([self.header] + [",".join(r) for r in self.rows]) + "\n")
        return str(path)

    def station_rows(self, pose=None, ref=None, nth=0):
        """Indices of the nth run of consecutive rows with this pose label (or ref_drift)."""
        runs, cur = [], []
        for i, r in enumerate(self.rows):
            hit = (r[8] == str(pose)) if pose is not None else (r[9] != "" and float(r[9]) == ref)
            if hit:
                cur.append(i)
            elif cur:
                runs.append(cur)
                cur = []
        if cur:
            runs.append(cur)
        return runs[nth]


def _run(capsys, argv):
    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def _twelve(capsys, cal, tmp_path):
    out = tmp_path / "c.yaml"
    code, stdout, err = _run(capsys, ["twelve-position", cal, "-o", str(out), "--site", str(out.parent / "site.yaml")])
    return code, stdout, err, out


def _correct_json(capsys, log, simdir, *extra):
    code, stdout, err = _run(capsys, ["correct", log, "--coeffs", str(simdir / "truth_coeffs.yaml"), "--json", *extra])
    return code, (json.loads(stdout) if code == 0 else None), err


@pytest.fixture
def site(simdir, tmp_path):
    (tmp_path / "site.yaml").write_text((simdir / "site.yaml").read_text())


# ---- samples ---------------------------------------------------------------------------------
def test_inf_and_nan_samples_in_a_survey_log_are_rejected_by_row_and_every_station_still_comes_out(simdir, tmp_path,
                                                                                                   capsys):
    log = Log(simdir / "val.csv")
    i = log.station_rows(ref=30.0)[10]
    log.rows[i][6] = "inf"
    log.rows[i + 1][2] = "NaN"
    code, summ, err = _correct_json(capsys, log.write(tmp_path / "v.csv"), simdir)
    assert code == 0
    assert f"row {i + 1} (line {i + 2}): mz not finite (NaN/inf)" in err
    assert f"row {i + 2} (line {i + 3}): ay not finite (NaN/inf)" in err
    assert summ["stations"] == N_VAL and summ["drift_rms_deg"] < 0.05


def test_saturated_axis_is_rejected_naming_axis_and_row_and_the_calibration_still_solves(simdir, tmp_path, site,
                                                                                        capsys):
    log = Log(simdir / "cal.csv")
    i = log.station_rows(pose=3)[2]
    log.rows[i][3] = "-19.6"                      # az at the accelerometer's 2 g full scale
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 0 and out.exists()
    assert f"row {i + 1} (line {i + 2}): az=-19.6 m/s² is saturated" in err


@pytest.mark.parametrize("value,reason", [("0", "total field 0 nT is implausible"),
                                          ("", "is not a number")])
def test_zero_or_absent_field_is_rejected_and_the_calibration_still_solves(simdir, tmp_path, site, capsys, value,
                                                                          reason):
    log = Log(simdir / "cal.csv")
    i = log.station_rows(pose=9)[3]
    log.rows[i][4:7] = [value] * 3
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 0 and out.exists()
    assert f"row {i + 1} (line {i + 2}): " in err and reason in err


def test_magnetometer_in_tesla_is_refused_with_the_unit_hint(simdir, tmp_path, site, capsys):
    log = Log(simdir / "cal.csv")
    for r in log.rows:
        r[4:7] = [f"{float(v) * 1e-9:.6e}" for v in r[4:7]]
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 2 and not out.exists()
    assert "no usable rows" in err and "row 1 (line 2)" in err
    assert "look like tesla: give the unit (--mag-unit T)" in err
    code, _, err = _run(capsys, ["twelve-position", str(tmp_path / "cal.csv"), "-o", str(out), "--site",
                                 str(tmp_path / "site.yaml"), "--mag-unit", "T"])
    assert code == 0 and out.exists()                 # told the unit, the same log calibrates


def test_non_monotonic_timestamp_is_rejected_naming_the_row_and_the_rest_is_used(simdir, tmp_path, capsys):
    log = Log(simdir / "val.csv")
    i = log.station_rows(ref=50.0)[20]
    log.rows[i][0] = log.rows[i - 5][0]
    code, summ, err = _correct_json(capsys, log.write(tmp_path / "v.csv"), simdir)
    assert code == 0 and summ["stations"] == N_VAL
    assert f"row {i + 1} (line {i + 2}): time t_s=" in err and "non-monotonic timestamp" in err


# ---- poses -----------------------------------------------------------------------------------
def test_duplicated_pose_is_used_and_warned(simdir, tmp_path, site, capsys):
    log = Log(simdir / "cal.csv")
    idx = log.station_rows(pose=6, nth=0)
    t_end = float(log.rows[-1][0])
    extra = [list(log.rows[i]) for i in idx]
    for k, r in enumerate(extra):                  # pose 6 captured a third time, at the end
        r[0] = f"{t_end + 1.0 + 0.01 * k:.4f}"
    log.rows += extra
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 0 and out.exists()
    assert "pose(s) 6 ×3 captured more often than the others (×2)" in err


def test_mislabelled_pose_is_refused_naming_rows_label_and_gravity_and_the_rest_solves(simdir, tmp_path, site,
                                                                                      capsys):
    log = Log(simdir / "cal.csv")
    idx = log.station_rows(pose=7, nth=1)          # second round: pose 7 labelled as 5
    for i in idx:
        log.rows[i][8] = "5"
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 0 and out.exists()              # round 1 still has pose 7
    # the detector's station lies inside the labelled rows (it starts after the settling time)
    hit = [ln for ln in err.splitlines() if "labelled pose 5 but its gravity says pose 7 or 8" in ln]
    assert len(hit) == 1 and "refused (mislabelled pose)" in hit[0]
    first, last = (int(x) for x in hit[0].split("station at rows ")[1].split(" ")[0].split("-"))
    assert idx[0] + 1 <= first < last <= idx[-1] + 2


def test_mislabelled_pose_that_leaves_a_pose_missing_is_solved_without_it_naming_both(simdir, tmp_path, site,
                                                                                     capsys):
    log = Log(simdir / "cal.csv")
    runs = [log.station_rows(pose=7, nth=nth) for nth in (0, 1)]
    for i in runs[0] + runs[1]:
        log.rows[i][8] = "5"
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 0 and out.exists()              # 11 poses determine both triads (least squares)
    assert err.count("labelled pose 5 but its gravity says pose 7 or 8") == 2
    assert "solved without pose(s) [7] (never captured), by least squares over the others" in err
    rec = yaml.safe_load(out.read_text())
    assert "least squares" in rec["method"] and rec["notes"]


def test_probe_moved_during_a_capture_is_refused_and_the_rest_solves(simdir, tmp_path, site, capsys):
    log = Log(simdir / "cal.csv")
    idx = log.station_rows(pose=10, nth=0)
    for k, i in enumerate(idx):                    # the probe rolls while pose 10 is captured
        log.rows[i][1] = f"{float(log.rows[i][1]) + 2.0 * k / len(idx):.6f}"
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 0 and out.exists()              # round 2 still has pose 10
    assert f"pose 10 at rows {idx[0] + 1}-{idx[-1] + 1}" in err and "no static station found" in err
    assert "the probe was never still there" in err


def test_static_window_too_short_is_dropped_naming_the_station_and_the_others_come_out(simdir, tmp_path, capsys):
    log = Log(simdir / "val.csv")
    idx = log.station_rows(ref=60.0)
    for i in idx[3:]:                              # only 3 rows keep their labels
        log.rows[i][9:12] = ["", "", ""]
    code, summ, err = _correct_json(capsys, log.write(tmp_path / "v.csv"), simdir)
    assert code == 0 and summ["stations"] == N_VAL - 1           # the hold is found, without its label
    assert f"ref (60, 0, 0) at rows {idx[0] + 1}-{idx[0] + 3}" in err and "no static station found" in err


# ---- survey QC ---------------------------------------------------------------------------------
def test_near_vertical_station_is_flagged_azimuth_undefined_and_left_out_of_azimuth_stats(simdir, tmp_path, capsys):
    # a vertical station: the stand grid's first drift set to 0 (the data are those of drift 2°
    # stations, so take the simulator's true vertical vectors instead)
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.coeffs import Calibration
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.io.probelog import write_csv

    truth = Calibration.load(simdir / "truth_coeffs.yaml")
    probe = sim.build_probe(4)
    sess = sim.stand_grid_session(drifts=(0, 0.2, 20), azimuths=(0, 120), toolfaces=(0,), duration_s=1.5)
    log = sim.run_session(probe, Site(**yaml.safe_load((simdir / "site.yaml").read_text())["site"]), sess,
                          np.random.default_rng(0))
    p = tmp_path / "vertical.csv"
    write_csv(p, log)
    st = tmp_path / "st.csv"
    code, stdout, err = _run(capsys, ["correct", str(p), "--coeffs", str(simdir / "truth_coeffs.yaml"),
                                      "--json", "-o", str(st)])
    assert code == 0 and truth.id
    summ = json.loads(stdout)
    assert summ["flagged"]["azimuth_undefined"] == 4
    assert summ["azimuth_stations"] == 2 and summ["azimuth_rms_deg"] < 0.5   # only the 20° stations
    rows = [r.split(",") for r in st.read_text().splitlines()]
    head = rows[0]
    for r in rows[1:]:
        if float(r[head.index("ref_drift_deg")]) < 0.5:
            assert "azimuth_undefined" in r[head.index("flags")] and r[head.index("status")] == "warn"
            assert r[head.index("azimuth_err_deg")] == ""           # no azimuth error computed
            assert r[head.index("toolface_type")] == "magnetic"


def test_magnetic_interference_is_flagged_on_that_station_only(simdir, tmp_path, capsys):
    log = Log(simdir / "val.csv")
    idx = log.station_rows(ref=40.0, nth=0)
    for i in idx:
        log.rows[i][6] = f"{float(log.rows[i][6]) + 800.0:.3f}"   # a steel object near the probe
    st = tmp_path / "st.csv"
    code, summ, err = _correct_json(capsys, log.write(tmp_path / "v.csv"), simdir, "-o", str(st))
    assert code == 0 and summ["stations"] == N_VAL
    assert summ["flagged"]["interference_suspected"] == 1
    rows = [r.split(",") for r in st.read_text().splitlines()]
    head = rows[0]
    hit = [r for r in rows[1:] if "interference_suspected" in r[head.index("flags")]]
    assert len(hit) == 1
    assert float(log.rows[idx[0]][0]) <= float(hit[0][head.index("t_start_s")]) < float(log.rows[idx[-1]][0])
    assert abs(float(hit[0][head.index("delta_b_nt")])) > 300 and hit[0][head.index("status")] == "warn"


# ---- singular / ill-conditioned fit -----------------------------------------------------------
def test_dead_axis_is_refused_naming_the_axis_and_no_coefficients_are_written(simdir, tmp_path, site, capsys):
    log = Log(simdir / "cal.csv")
    for r in log.rows:
        r[5] = "21000.000"                          # my stuck at a constant
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    assert code == 2 and not out.exists()
    assert "magnetometer y reads a constant 21000.0000 nT" in err and "stuck" in err
    assert "magnetometer y was flat in 24 captures" in err
    assert "error: " in err and "magnetometer: 0 usable capture(s)" in err


def test_two_physically_identical_poses_are_named_and_the_pose_solved_without(simdir, tmp_path, site, capsys):
    # pose 2 (X down, rolled 180°) recorded in pose 1's orientation in both rounds: gravity cannot
    # tell (X is down in both), the field's horizontal part can
    log = Log(simdir / "cal.csv")
    for nth in (0, 1):
        src, dst = log.station_rows(pose=1, nth=nth), log.station_rows(pose=2, nth=nth)
        for k, i in enumerate(dst):
            log.rows[i][1:7] = log.rows[src[k % len(src)]][1:7]
    code, _, err, out = _twelve(capsys, log.write(tmp_path / "cal.csv"), tmp_path)
    # the labels say pose 2, gravity agrees (X down in both): taken as labelled, then the solve finds
    # that the field of "pose 2" is pose 1's and leaves pose 2 out of the magnetometer's solve
    assert code == 0 and out.exists()
    assert "magnetometer: pose 2 (all 2 captures) does not fit the twelve-pose model" in err and "left out" in err
    assert "magnetometer by least squares" in out.read_text()


# ---- coefficient files -----------------------------------------------------------------------
@pytest.mark.parametrize("edit,msg", [
    (lambda r: r["accelerometer"].update(correction_matrix=[[1, 0, 0], [0, 1, 0]]),
     "accelerometer.correction_matrix has shape (2, 3), expected 3×3"),
    (lambda r: r["magnetometer"]["units"].update(input="uT"), "magnetometer.units.input is 'uT', expected 'nT'"),
    (lambda r: r.update(format_version=99), "format_version 99 is not supported"),
])
def test_malformed_coefficient_file_is_refused_by_correct_naming_file_and_field(simdir, tmp_path, capsys, edit, msg):
    rec = yaml.safe_load((simdir / "truth_coeffs.yaml").read_text())
    edit(rec)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(rec))
    code, stdout, err = _run(capsys, ["correct", str(simdir / "val.csv"), "--coeffs", str(p), "--json"])
    assert code == 2 and stdout == ""
    assert f"error: {p}: " in err and msg in err


def test_coefficient_file_that_is_not_yaml_is_refused(simdir, tmp_path, capsys):
    p = tmp_path / "garbage.yaml"
    p.write_text("format: [inclinometer_calib\n  : :")
    code, _, err = _run(capsys, ["correct", str(simdir / "val.csv"), "--coeffs", str(p)])
    assert code == 2 and f"{p}: not valid YAML" in err


MARKED_PLUGIN = """import pathlib

pathlib.Path(__file__).with_name("executed.marker").write_text("this plug-in ran")

from inclinometer_calib.core.effects import T_REF_C, Effect, ParamSpec


class CliCubeBias(Effect):
    name = "cube_bias_cli"
    stage = "output"
    specs = (ParamSpec("c3", {"acc": "m/s^2/degC^3", "mag": "nT/degC^3"}, {"acc": 1e-6, "mag": 0.01}),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["c3"] * ((ctx.temperature_c - T_REF_C) ** 3)[:, None]
"""


@pytest.fixture
def plugin_record(simdir, tmp_path, monkeypatch):
    """(record, plug-in file, the record's --json summary while its plug-in was loaded): the
    simulated probe's record plus a plug-in effect; then, as for a new process, the effect
    unregistered, its module gone, nothing named, no marker."""
    import sys

    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core import plugins
    from inclinometer_calib.core.coeffs import Calibration

    monkeypatch.setattr(plugins, "_NAMED", {}, raising=False)
    plug = tmp_path / "plug" / "cube.py"
    plug.parent.mkdir()
    plug.write_text(MARKED_PLUGIN)
    assert plugins.load_plugin(plug) == ["cube_bias_cli"]
    truth = Calibration.load(simdir / "truth_coeffs.yaml")
    eff = fx.make_effect("cube_bias_cli", "mag", c3=[2e-3, -1e-3, 1e-3])
    rec = tmp_path / "rec.yaml"
    Calibration(truth.model.with_effect(eff), probe_id=truth.probe_id, site=truth.site).save(rec)
    code, before, err = _correct_json_with(rec, simdir)
    assert code == 0, err
    fx.CATALOGUE.pop("cube_bias_cli")
    for m in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(plug)]:
        del sys.modules[m]
    plugins._NAMED.clear()
    plug.with_name("executed.marker").unlink()
    yield rec, plug, before
    fx.CATALOGUE.pop("cube_bias_cli", None)


def _correct_json_with(rec, simdir, *extra):
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["correct", str(simdir / "val.csv"), "--coeffs", str(rec), "--json", *extra])
    return code, (json.loads(out.getvalue()) if code == 0 else out.getvalue()), err.getvalue()


def test_correct_refuses_a_record_whose_plugin_was_not_named_in_one_line_without_running_it(plugin_record, simdir):
    rec, plug, _ = plugin_record
    code, stdout, err = _correct_json_with(rec, simdir)
    assert code == 2 and stdout == ""
    assert err.count("\n") == 1 and err.startswith(f"error: {rec}: effect 'cube_bias_cli' comes from the plug-in "
                                                     f"file '{plug}' (sha256 ")
    assert "which is not named" in err and "--plugin PATH" in err
    assert not plug.with_name("executed.marker").exists()


def test_correct_refuses_a_named_plugin_that_changed_since_the_record_without_running_it(plugin_record, simdir):
    rec, plug, _ = plugin_record
    plug.write_text(plug.read_text() + "\n# edited\n")
    code, stdout, err = _correct_json_with(rec, simdir, "--plugin", str(plug))
    assert code == 2 and stdout == ""
    assert err.count("\n") == 1 and "changed since the record was written" in err and "cube_bias_cli" in err
    assert not plug.with_name("executed.marker").exists()


def test_correct_with_the_named_matching_plugin_corrects_as_before(plugin_record, simdir):
    rec, plug, before = plugin_record
    code, after, err = _correct_json_with(rec, simdir, "--plugin", str(plug))
    assert code == 0, err
    assert plug.with_name("executed.marker").exists()
    assert after == before


# ---- bags --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bag(simdir, tmp_path_factory):
    pytest.importorskip("mcap")
    pytest.importorskip("rosbags")
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.correct.reprocess import write_probe_bag

    d = tmp_path_factory.mktemp("badbag")
    site = Site(**yaml.safe_load((simdir / "site.yaml").read_text())["site"])
    sess = sim.stand_grid_session(drifts=(10, 45), azimuths=(0, 90, 180, 270), toolfaces=(0,), duration_s=2.0)
    log = sim.run_session(sim.build_probe(4), site, sess, np.random.default_rng(0))
    p = d / "in.mcap"
    write_probe_bag(log, p, compression="")
    return p, log


def test_corrupt_mcap_chunk_is_an_error_naming_the_offset_and_the_other_stations_come_out(simdir, bag, tmp_path,
                                                                                          capsys):
    from inclinometer_calib.io.bag import open_bag

    src, _ = bag
    data = bytearray(src.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(64)                 # zero a stretch inside a chunk
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(data))
    out = tmp_path / "out.mcap"
    code, stdout, err = _run(capsys, ["reprocess", str(bad), "--coeffs", str(simdir / "truth_coeffs.yaml"),
                                      "-o", str(out)])
    assert code == 1
    assert f"error: {bad}: " in err and "byte offset" in err and "were processed and written" in err
    res = open_bag(out)
    n = sum(1 for _ in res.messages(["/survey/station"]))
    assert 4 <= n <= 8                              # a chunk (≤ 1 s of log) is lost, not the stations
    assert 0 < sum(1 for _ in res.messages(["/probe/imu"])) < len(bag[1])


def test_field_in_nT_written_as_tesla_in_a_bag_is_refused_with_the_unit_hint(simdir, bag, tmp_path, capsys):
    from inclinometer_calib.correct.reprocess import write_probe_bag

    _, log = bag
    wrong = type(log)(log.t_s, log.acc, log.mag * 1e9, log.temp_c, log.pose, log.ref)   # nT ×1e9 → "tesla" = nT
    p = tmp_path / "nt.mcap"
    write_probe_bag(wrong, p, compression="")
    code, _, err = _run(capsys, ["reprocess", str(p), "--coeffs", "none", "-o", str(tmp_path / "o.mcap")])
    assert code == 2
    assert "no usable /probe/imu + /probe/mag sample pairs" in err and "holds the copied input" not in err
    assert "looks like nT written into a tesla field" in err and "/probe/mag at log time" in err


def test_a_survey_recorded_before_its_calibration_is_not_a_clean_reprocess(simdir, tmp_path, capsys):
    """The survey first, the stand's poses after: every station goes out raw "before calibration",
    which for the stand's poses alone is expected: the survey's, outside the stand's span the
    record gives (a survey station taken for pose 9 long before the stand is not in it), said,
    exit 1, as the live graph's summary does (io/accounting.py); the stand alone (all raw, all
    captures), exit 0 (the usual order, exit 0: test_stranger_probe, test/correct/test_engine.py)."""
    pytest.importorskip("mcap")
    rev = tmp_path / "rev.mcap"
    assert _run(capsys, ["bag", "from-csv", str(simdir / "val.csv"), str(simdir / "cal.csv"), "-o", str(rev)])[0] == 0
    code, out, err = _run(capsys, ["reprocess", str(rev), "--calibrate", "-o", str(tmp_path / "r.mcap")])
    assert code == 1, err
    assert "error: 198 survey station(s) raw: not the stand's poses (those lie at t=1700000600.980–1700000695.970 " \
           "s), they went out before the calibration solved — 198 before the stand's first pose (the survey came " \
           "first?)" in err, err
    stand = tmp_path / "stand.mcap"           # the stand alone: every station raw, all of them captures
    assert _run(capsys, ["bag", "from-csv", str(simdir / "cal.csv"), "-o", str(stand)])[0] == 0
    code, out, err = _run(capsys, ["reprocess", str(stand), "--calibrate", "-o", str(tmp_path / "s.mcap"),
                                   "--coeffs-out", str(tmp_path / "s.yaml")])
    assert code == 0 and "was corrected" not in err, err


def test_a_bag_without_magnetometer_messages_says_so_and_leaves_no_output(bag, tmp_path, capsys):
    """Not thousands of samples "without a partner", nor an output file said to hold the copied
    input (the CLI removes it): the stream that is missing, in words."""
    from inclinometer_calib.io.bag import BagWriter, open_bag

    src, _ = bag
    for name, mag_type in (("nomag.mcap", None), ("wrongmag.mcap", "std_msgs/msg/String")):
        p = tmp_path / name
        w = BagWriter(p, compression="none")
        channels = {}
        for m in open_bag(src).messages():
            if m.topic == "/probe/mag" and mag_type is None:
                continue
            if m.topic not in channels:
                channels[m.topic] = w.add_topic(m.topic, mag_type if m.topic == "/probe/mag" else m.type)
            w.write(channels[m.topic], m.data, m.log_time, m.publish_time)
        w.close()
        out = tmp_path / f"o-{name}"
        code, _, err = _run(capsys, ["reprocess", str(p), "--coeffs", "none", "-o", str(out)])
        assert code == 2
        if mag_type is None:
            assert "no /probe/mag messages in the bag" in err and "partner" not in err, err
        else:   # there are messages, of another type: said as such, not as none
            assert "no /probe/mag messages" not in err and "skipped topic /probe/mag" in err, err
        assert "holds the copied input" not in err and not out.exists()
        assert sum(line.startswith("error:") for line in err.splitlines()) == 1, err


def test_a_killed_recorders_bag_is_recovered_by_the_cli_into_one_any_reader_opens(bag, tmp_path, capsys):
    from rosbags.highlevel import AnyReader, AnyReaderError

    src, _ = bag
    data = src.read_bytes()
    killed = tmp_path / "killed.mcap"
    killed.write_bytes(data[:int(len(data) * 0.6)])        # no summary, a chunk cut in half
    with pytest.raises(AnyReaderError):                     # what a user meets without us
        with AnyReader([killed]) as r:
            sum(1 for _ in r.messages())
    fixed = tmp_path / "fixed.mcap"
    code, stdout, err = _run(capsys, ["bag", "recover", str(killed), "-o", str(fixed)])
    assert code == 0, err
    assert "recovered" in stdout or "saved" in stdout
    with AnyReader([fixed]) as r:
        n = sum(1 for _ in r.messages())
    assert 0 < n
    code, _, err = _run(capsys, ["bag", "recover", str(killed), "-o", str(fixed)])   # never overwritten
    assert code == 2 and "exists" in err


def test_reprocess_takes_the_detectors_noise_from_the_data_or_from_an_option(simdir, bag, tmp_path, capsys):
    src, _ = bag
    code, stdout, _ = _run(capsys, ["reprocess", str(src), "--coeffs", "none", "-o", str(tmp_path / "a.mcap")])
    assert code == 0 and "(data)" in stdout and "8 stations" in stdout
    code, stdout, _ = _run(capsys, ["reprocess", str(src), "--coeffs", "none", "-o", str(tmp_path / "b.mcap"),
                                    "--noise-acc", "0.004", "--noise-mag", "30"])
    assert code == 0 and "0.004/0.004/0.004 m/s^2 (override)" in stdout and "30/30/30 nT (override)" in stdout


def test_a_crept_and_a_clipped_station_are_errors_in_correct_and_reprocess_alike_and_left_out_of_the_figures(
        simdir, tmp_path, capsys):
    """One status rule (pipeline.station_status) on every path: a station whose probe crept during
    the hold, and one whose magnetometer z is clipped (flat), are status 2 in ``correct -o`` and in
    ``reprocess`` both, and neither counts in ``correct``'s error figures."""
    from inclinometer_calib.io.bag import read_bag

    log = Log(simdir / "val.csv")
    crept, clipped = log.station_rows(ref=30.0), log.station_rows(ref=60.0)
    for k, i in enumerate(crept):                  # a slow roll: 0.1° over the hold, below the detector's break
        log.rows[i][1] = f"{float(log.rows[i][1]) + 0.017 * k / len(crept):.6f}"
    for i in clipped:                              # the magnetometer's z stuck at its first value
        log.rows[i][6] = log.rows[clipped[0]][6]
    path = log.write(tmp_path / "v.csv")
    out_csv = tmp_path / "stations.csv"
    code, summ, err = _correct_json(capsys, path, simdir, "-o", str(out_csv))
    assert code == 0 and summ["stations"] == N_VAL - 2          # the two are out of the figures
    rows = [r.split(",") for r in out_csv.read_text().splitlines()]
    col = {n: k for k, n in enumerate(rows[0])}
    by_ref = {(r[col["ref_drift_deg"]], r[col["ref_azimuth_deg"]], r[col["ref_toolface_deg"]]): r for r in rows[1:]}
    crept_row = next(r for k, r in by_ref.items() if k[0] == "30.0000" and k[1:] == ("0.0000", "0.0000"))
    clipped_row = next(r for k, r in by_ref.items() if k[0] == "60.0000" and k[1:] == ("0.0000", "0.0000"))
    assert crept_row[col["status"]] == "error" and "moved_during_capture" in crept_row[col["flags"]]
    assert crept_row[col["drift_err_deg"]] == ""
    assert clipped_row[col["status"]] == "error" and "mag_unusable" in clipped_row[col["flags"]]
    assert clipped_row[col["drift_err_deg"]] == ""
    # reprocess of the same data: the same verdicts
    bag, re_bag = tmp_path / "v.mcap", tmp_path / "re.mcap"
    assert main(["bag", "from-csv", path, "-o", str(bag)]) == 0
    assert main(["reprocess", str(bag), "--coeffs", str(simdir / "truth_coeffs.yaml"), "-o", str(re_bag)]) == 0
    st = {(s["reference_drift_deg"], s["reference_azimuth_deg"], s["reference_toolface_deg"]): s
          for s in read_bag(re_bag)[0]}
    assert st[(30.0, 0.0, 0.0)]["status"] == 2 and st[(30.0, 0.0, 0.0)]["moved_during_capture"]
    assert st[(60.0, 0.0, 0.0)]["status"] == 2
    assert sum(s["status"] == 2 for s in st.values()) == 2


@pytest.mark.parametrize("command", [["wits"], ["witsml", "-o", "w.xml"]])
def test_the_rig_exports_of_a_file_that_is_not_a_bag_are_one_line(tmp_path, capsys, command):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(np.random.default_rng(0).bytes(5000))
    assert main([command[0], str(junk), *command[1:]]) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"error: {junk}: not a readable bag (not an MCAP file (bad or missing magic bytes) "
                           "at byte offset 0)"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mcap"]

"""CLI end to end: simulate -> twelve-position -> correct, and clear errors for bad input."""
import json
import os
import re
import subprocess
import sys

import pytest
import yaml

from inclinometer_calib.apps.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def simdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--out", str(d), "--seed", "3", "--station-seconds", "1.5"]) == 0
    return d


def _json(capsys, argv):
    capsys.readouterr()
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_calibration_lowers_validation_errors_to_the_noise_level(simdir, capsys, tmp_path):
    coeffs = tmp_path / "coeffs.yaml"
    assert main(["twelve-position", str(simdir / "cal.csv"), "-o", str(coeffs)]) == 0
    out = capsys.readouterr().out
    assert "Table 2" in out and "Table 3" in out
    val = str(simdir / "val.csv")
    before = _json(capsys, ["correct", val, "--coeffs", "none", "--json"])
    after = _json(capsys, ["correct", val, "--coeffs", str(coeffs), "--json", "-o", str(tmp_path / "st.csv")])
    truth = _json(capsys, ["correct", val, "--coeffs", str(simdir / "truth_coeffs.yaml"), "--json"])
    for key in ("stations", "drift_rms_deg", "drift_max_abs_deg", "azimuth_rms_deg", "azimuth_max_abs_deg"):
        assert key in after
    assert after["stations"] == 198
    assert before["azimuth_rms_deg"] > 1.0 and before["drift_rms_deg"] > 0.05
    # the truth model's errors are the noise level of this data; the twelve-position fit
    # (from noisy poses) must come within a small factor of it, in absolute terms tiny
    assert after["drift_rms_deg"] < max(3 * truth["drift_rms_deg"], 0.005)
    assert after["azimuth_rms_deg"] < max(3 * truth["azimuth_rms_deg"], 0.03)
    assert (tmp_path / "st.csv").read_text().startswith("station,pose,")


def test_correct_prints_paper_style_tables(simdir, capsys):
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", str(simdir / "truth_coeffs.yaml")]) == 0
    out = capsys.readouterr().out
    assert "Table 4" in out and "Table 5" in out and "RMS" in out


def test_a_missing_pose_is_solved_without_by_least_squares_and_said(simdir, tmp_path, capsys):
    lines = (simdir / "cal.csv").read_text().splitlines()
    kept = [ln for ln in lines if ln.split(",")[8] != "5"]
    bad = tmp_path / "cal_missing5.csv"
    bad.write_text("\n".join(kept) + "\n")
    assert main(["twelve-position", str(bad), "-o", str(tmp_path / "c.yaml")]) == 0
    captured = capsys.readouterr()
    assert "solved without pose(s) [5] (never captured), by least squares over the others" in captured.err
    assert "least squares over 11 captures" in captured.out


def test_too_few_poses_are_a_clear_error_with_exit_2(simdir, tmp_path, capsys):
    lines = (simdir / "cal.csv").read_text().splitlines()
    kept = [ln for ln in lines if ln.split(",")[8] not in ("9", "10", "11", "12")]
    bad = tmp_path / "cal_no_z.csv"
    bad.write_text("\n".join(kept) + "\n")
    assert main(["twelve-position", str(bad), "-o", str(tmp_path / "c.yaml")]) == 2
    err = capsys.readouterr().err
    assert "accelerometer: the captures left" in err and "none in pose(s) [9, 10, 11, 12]" in err
    assert "poses never captured: [9, 10, 11, 12]" in err
    assert not (tmp_path / "c.yaml").exists()


def test_bad_rows_are_warned_and_the_rest_used(simdir, tmp_path, capsys):
    lines = (simdir / "cal.csv").read_text().splitlines()
    lines[10] = lines[10].replace(lines[10].split(",")[1], "nan", 1)
    bad = tmp_path / "cal_nan.csv"
    bad.write_text("\n".join(lines) + "\n")
    assert main(["twelve-position", str(bad), "-o", str(tmp_path / "c.yaml")]) == 0
    err = capsys.readouterr().err
    assert "row 10 (line 11): ax not finite" in err


def test_hand_edited_coefficients_are_refused(simdir, tmp_path, capsys):
    rec = yaml.safe_load((simdir / "truth_coeffs.yaml").read_text())
    rec["magnetometer"]["offset"][0] += 50
    p = tmp_path / "edited.yaml"
    p.write_text(yaml.safe_dump(rec))
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", str(p)]) == 2
    assert "disagree with the parameters" in capsys.readouterr().err


def test_module_runs_as_a_program(simdir):
    r = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.cli", "correct", str(simdir / "val.csv"),
                        "--coeffs", "none", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["coefficients"] == "none"


def test_axial_correction_removes_survey_interference(tmp_path, capsys):
    d = tmp_path / "ai"
    assert main(["simulate", "--out", str(d), "--seed", "5", "--effect", "axial_interference=400"]) == 0
    # the stand's calibration (the interference acts on the survey only; the simulator's full truth
    # in truth_coeffs.yaml would remove it)
    base = str(d / "base.yaml")
    assert main(["twelve-position", str(d / "cal.csv"), "--site", str(d / "site.yaml"), "-o", base]) == 0
    capsys.readouterr()
    # most stations out of |B|/dip tolerance: said, and not a clean exit, corrected or not
    assert main(["correct", str(d / "val.csv"), "--coeffs", base, "--json"]) == 1
    plain = json.loads(capsys.readouterr().out)
    assert main(["correct", str(d / "val.csv"), "--coeffs", base, "--json", "--axial-correction"]) == 1
    cap = capsys.readouterr()
    fixed = json.loads(cap.out)
    assert "or magnetic interference" in cap.err
    assert plain["flagged"]["interference_suspected"] > 0
    assert fixed["azimuth_method"] == "short_collar"
    assert fixed["azimuth_rms_deg"] < 0.3 * plain["azimuth_rms_deg"]
    assert fixed["flagged"]["axial_degenerate"] < fixed["stations"] // 2  # the stand grid avoids east-west at 90°


def test_without_a_site_file_the_site_is_taken_from_the_calibration_data(tmp_path, capsys):
    """A site with another dip and a declination, calibrated and corrected without --site: the
    azimuths come out in the stand's frame and no station is falsely flagged."""
    d = tmp_path / "decl"
    assert main(["simulate", "--out", str(d), "--seed", "9", "--declination", "3", "--dip", "62",
                 "--total-field", "47000"]) == 0
    coeffs = tmp_path / "c.yaml"
    assert main(["twelve-position", str(d / "cal.csv"), "-o", str(coeffs)]) == 0
    assert "no --site given" in capsys.readouterr().err
    rec = yaml.safe_load(coeffs.read_text())
    assert abs(rec["site"]["dip_deg"] - 62.0) < 0.01 and abs(rec["site"]["declination_deg"] - 3.0) < 0.01
    out = _json(capsys, ["correct", str(d / "val.csv"), "--coeffs", str(coeffs), "--json"])
    assert out["azimuth_rms_deg"] < 0.05
    assert out["flagged"]["interference_suspected"] == 0


def test_a_site_given_later_that_contradicts_a_record_solved_without_one_is_said(simdir, tmp_path, capsys):
    coeffs = tmp_path / "nosite.yaml"
    assert main(["twelve-position", str(simdir / "cal.csv"), "-o", str(coeffs)]) == 0
    assert yaml.safe_load(coeffs.read_text())["site_source"] == "measured"
    other = tmp_path / "site.yaml"
    site = yaml.safe_load((simdir / "site.yaml").read_text())["site"]
    site["total_field_nt"] += 800.0
    other.write_text(yaml.safe_dump({"site": site}))
    capsys.readouterr()
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", str(coeffs), "--site", str(other), "--json"]) == 0
    err = capsys.readouterr().err
    assert "the coefficients were solved without a site" in err and "calibrate with --site" in err


def test_the_version_is_printed():
    from inclinometer_calib import __version__
    r = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.cli", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == f"inclinometer-calib {__version__}"


def test_correct_says_its_qc_counts_and_fails_when_most_stations_fail_against_the_records_site(simdir, tmp_path,
                                                                                             capsys):
    """Another probe's record on this probe's log: most stations out of |B|/dip tolerance.  It used
    to exit 0 with an azimuth RMS of degrees and no word about its QC errors."""
    assert main(["twelve-position", str(simdir / "cal.csv"), "-o", str(tmp_path / "own.yaml")]) == 0
    other = tmp_path / "other"
    assert main(["simulate", "--out", str(other), "--seed", "9"]) == 0
    assert main(["twelve-position", str(other / "cal.csv"), "-o", str(tmp_path / "other.yaml")]) == 0
    capsys.readouterr()
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", str(tmp_path / "own.yaml")]) == 0
    out = capsys.readouterr().out
    assert "QC against the site (|B| 300 nT, dip 0.25°, |G| 0.0981 m/s²): " in out and "|B| off at 0, dip off at 0" in out
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", str(tmp_path / "other.yaml")]) == 1
    cap = capsys.readouterr()
    n = re.search(r": (\d+) of (\d+) stations within, \|B\| off at (\d+)", cap.out)
    within, total, b_off = map(int, n.groups())
    assert total - within > total / 2 and b_off > 0, cap.out
    assert cap.err.strip().splitlines()[-1].startswith(f"error: {total - within} of the {total} stations are out of "
                                                       "tolerance against the site of record "), cap.err
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", str(tmp_path / "other.yaml"), "--json"]) == 1
    js = json.loads(capsys.readouterr().out)
    assert js["qc"]["out_of_tolerance"]["|B|"] == b_off and sum(js["qc"][k] for k in ("ok", "warn", "error")) == total
    # uncorrected figures (no record) are not held to the site
    assert main(["correct", str(simdir / "val.csv"), "--coeffs", "none", "--json"]) == 0


def test_every_option_of_every_command_says_what_it_does():
    import argparse

    from inclinometer_calib.apps.cli import build_parser

    missing = []

    def walk(parser, path):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    walk(sub, path + [name])
            elif not isinstance(a, argparse._HelpAction) and not a.help:
                missing.append(" ".join(path + [a.option_strings[0] if a.option_strings else a.dest]))

    walk(build_parser(), [])
    assert not missing, missing

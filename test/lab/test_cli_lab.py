"""`inclinometer-calib lab fit|diagnose|report` on data with a hidden effect."""
import json

import pytest

from inclinometer_calib.apps.cli import main


def _run(capsys, argv):
    capsys.readouterr()
    code = main(argv)
    return code, capsys.readouterr()


@pytest.mark.long(8)
def test_lab_cli_names_fits_and_reports_the_hidden_effect(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), "--seed", "61", "--effect", "axial_interference=300"]) == 0
    cal, val = str(out / "cal.csv"), str(out / "val.csv")
    code, r = _run(capsys, ["lab", "diagnose", "--cal", cal, "--val", val, "--json"])
    assert code == 0
    dg = json.loads(r.out)
    assert dg["ranked"][0]["effect"] == "axial_interference" and dg["ranked"][0]["sensor"] == "mag"
    assert dg["significant_structure_left"] is True
    assert {"drift_rms_deg", "azimuth_rms_deg"} <= set(dg["base"]["val"])
    assert {"effect", "sensor", "axes", "val", "score"} <= set(dg["ranked"][0])

    code, r = _run(capsys, ["lab", "fit", "--cal", cal, "--val", val, "--effects", "axial_interference", "--json"])
    assert code == 0
    fit = json.loads(r.out)
    assert fit["effects"] == ["axial_interference:mag:z@val"]
    base_code, rb = _run(capsys, ["lab", "fit", "--cal", cal, "--val", val, "--json"])
    base = json.loads(rb.out)
    assert fit["val"]["azimuth_rms_deg"] < 0.5 * base["val"]["azimuth_rms_deg"]
    p = {q["name"]: q for q in fit["parameters"]}["axial_interference:mag:z.field_z"]
    assert abs(p["value"] - 300) < 5 * p["std"]

    html = tmp_path / "report.html"
    code, r = _run(capsys, ["lab", "report", "--cal", cal, "--val", val, "-o", str(html), "--quiet", "--max-steps", "1"])
    assert code == 0
    text = html.read_text()
    assert text.startswith("<!doctype html>") and "Effect ladder" in text and "axial_interference" in text
    assert text.count("data:image/png;base64,") >= 4
    assert "Table 4 layout" in text and "Table 5 layout" in text


def test_lab_unknown_effect_is_a_clear_error(tmp_path, capsys):
    out = tmp_path / "sim"
    main(["simulate", "--out", str(out), "--seed", "62"])
    code, r = _run(capsys, ["lab", "fit", "--cal", str(out / "cal.csv"), "--effects", "wobble"])
    assert code == 2 and "unknown effect 'wobble'" in r.err

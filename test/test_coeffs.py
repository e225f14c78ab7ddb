"""Coefficient record: YAML round trip, and refusal of malformed or hand-edited records."""
import numpy as np
import pytest
import yaml

from inclinometer_calib import simulate as sim
from inclinometer_calib.coeffs import Calibration, CoefficientError


@pytest.fixture
def cal():
    probe = sim.build_probe(7)
    return Calibration(acc=probe.acc, mag=probe.mag, probe_id="P-7", created="2026-11-22T00:00:00+00:00")


def test_yaml_round_trip_is_exact(tmp_path, cal):
    path = tmp_path / "c.yaml"
    cal.save(path)
    back = Calibration.load(path)
    assert back.id == cal.id
    np.testing.assert_array_equal(back.mag.correction_matrix, cal.mag.correction_matrix)
    rec = yaml.safe_load(path.read_text())
    assert rec["format_version"] == 2
    assert rec["accelerometer"]["units"]["offset"] == "m/s^2"
    assert rec["magnetometer"]["units"]["offset"] == "nT"


def _edit(cal, fn):
    rec = cal.to_record()
    fn(rec)
    return yaml.safe_dump(rec)


@pytest.mark.parametrize("edit,msg", [
    (lambda r: r.update(format_version=99), "format_version 99 is not supported"),
    (lambda r: r.update(format="something"), "format is 'something'"),
    (lambda r: r["magnetometer"]["units"].update(offset="T"), "magnetometer.units.offset is 'T'"),
    (lambda r: r["accelerometer"].update(correction_matrix=[[1, 0], [0, 1]]), "shape"),
    (lambda r: r["accelerometer"].update(offset=[1, 2]), "offset has shape"),
    (lambda r: r["magnetometer"]["parameters"].pop("e_zy"), "lacks \\['e_zy'\\]"),
    (lambda r: r["magnetometer"]["parameters"].update(bias_x="abc"), "must all be numbers"),
    (lambda r: r["magnetometer"]["parameters"].update(bias_x=123.0), "disagree with the parameters"),
    (lambda r: r["magnetometer"]["parameters"].update(scale_x=0.0, scale_y=0.0), "singular"),
    (lambda r: r.update(id="0123456789ab"), "does not match the content"),
])
def test_malformed_record_is_refused_naming_the_field(cal, edit, msg):
    with pytest.raises(CoefficientError, match=msg):
        Calibration.from_yaml(_edit(cal, edit))


def test_not_yaml_is_refused():
    with pytest.raises(CoefficientError, match="not valid YAML"):
        Calibration.from_yaml("a: [1, 2")


def test_save_never_leaves_a_half_file(tmp_path, cal, monkeypatch):
    path = tmp_path / "c.yaml"
    cal.save(path)
    good = path.read_text()

    def boom(*a, **k):
        raise OSError("disk full")
    monkeypatch.setattr("os.replace", boom)
    with pytest.raises(OSError):
        cal.save(path)
    assert path.read_text() == good
    assert [p.name for p in tmp_path.iterdir()] == ["c.yaml"]

"""Coefficient record: YAML round trip, and refusal of malformed or hand-edited records."""
import numpy as np
import pytest
import yaml

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration, CoefficientError


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


def test_the_stands_span_travels_with_the_record_outside_its_id(tmp_path, cal):
    """Where the stand's poses lie in the data's time (a capture session's solve): written, read
    back exactly, and not part of the id (the same model from another session is the same record)."""
    path = tmp_path / "c.yaml"
    cal.diagnostics["stand"] = {"t_start": 1700000001.56, "t_end": 1700000107.98}
    cal.save(path)
    back = Calibration.load(path)
    assert back.diagnostics["stand"] == {"t_start": 1700000001.56, "t_end": 1700000107.98} and back.id == cal.id
    assert yaml.safe_load(path.read_text())["stand"] == {"t_start": 1700000001.56, "t_end": 1700000107.98}


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
    (lambda r: r.update(stand={"t_start": 5.0}), "stand must be a mapping of t_start and t_end"),
    (lambda r: r.update(stand={"t_start": 5.0, "t_end": 1.0}), "is not a span of data time"),
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


DATA = __import__("pathlib").Path(__file__).resolve().parents[1] / "data" / "records"


def test_a_version_1_record_written_by_the_earlier_release_still_loads_and_corrects_as_it_did(tmp_path, capsys):
    """test/data/records/v1_twelve_position.yaml was written by the release before format 2
    (``simulate --seed 8``, ``twelve-position --site``); that release's ``correct`` of the
    simulation's val.csv gave drift RMS 0.0012960682 and azimuth RMS 0.0138948685 deg."""
    import json

    from inclinometer_calib.apps.cli import main

    v1 = Calibration.load(DATA / "v1_twelve_position.yaml")
    assert v1.model.extra_terms == [] and v1.probe_id == "legacy-8"
    assert yaml.safe_load((DATA / "v1_twelve_position.yaml").read_text())["id"] == "f9a991e4132e"
    assert main(["simulate", "--out", str(tmp_path / "sim"), "--seed", "8"]) == 0
    capsys.readouterr()
    assert main(["correct", str(tmp_path / "sim" / "val.csv"), "--coeffs", str(DATA / "v1_twelve_position.yaml"),
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["drift_rms_deg"] == pytest.approx(0.0012960682050696165, abs=1e-12)
    assert out["azimuth_rms_deg"] == pytest.approx(0.013894868484056654, abs=1e-12)
    # saved again, it is a version 2 record (its id now covers the site too) that loads the same
    v1.save(tmp_path / "again.yaml")
    v2 = Calibration.load(tmp_path / "again.yaml")
    assert yaml.safe_load((tmp_path / "again.yaml").read_text())["format_version"] == 2
    assert v2.id == v1.id != "f9a991e4132e"
    np.testing.assert_array_equal(v2.mag.correction_matrix, v1.mag.correction_matrix)


def test_a_version_1_record_cannot_claim_effects_beyond_the_base_model():
    rec = yaml.safe_load((DATA / "v1_twelve_position.yaml").read_text())
    rec["model"]["effects"].append("temperature_bias")
    with pytest.raises(CoefficientError, match="version 1 record cannot carry effects"):
        Calibration.from_record(rec)


def test_a_record_carries_any_lab_model_and_applies_it_with_each_samples_temperature_and_time(tmp_path):
    probe = sim.build_probe(9, ["temperature_bias:mag=2", "nonlinearity:acc:z=1e-3", "bias_drift:mag:x=30",
                                "axial_interference=250"])
    cal = Calibration(probe.model, probe_id="P-9", site=sim.Site(dip_deg=60.0))
    cal.save(tmp_path / "m.yaml")
    rec = yaml.safe_load((tmp_path / "m.yaml").read_text())
    assert [e["name"] for e in rec["model"]["effects"]] == ["temperature_bias", "nonlinearity", "bias_drift",
                                                             "axial_interference"]
    assert rec["model"]["effects"][0]["units"] == {"c": "nT/degC"} and rec["model"]["effects"][3]["scope"] == "val"
    back = Calibration.load(tmp_path / "m.yaml")
    assert back.id == cal.id and back.model.labels() == cal.model.labels()
    assert back.needs == ("temperature", "time")
    rng = np.random.default_rng(1)
    g, b = rng.normal(0, 5, (50, 3)), rng.normal(0, 3e4, (50, 3))
    temp, t = rng.uniform(0, 80, 50), rng.uniform(0, 7200, 50)
    a = cal.correct(g, b, temp, t)
    z = back.correct(g, b, temp, t)
    np.testing.assert_array_equal(a[0], z[0])
    np.testing.assert_array_equal(a[1], z[1])
    # it inverts the model: forward then correct gives the true vectors back
    g_true, b_true = rng.normal(0, 5, (50, 3)), rng.normal(0, 3e4, (50, 3))
    h_g, h_b = probe.model.forward(g_true, b_true, temp, t)
    np.testing.assert_allclose(cal.correct(h_g, h_b, temp, t)[0], g_true, atol=1e-9)
    np.testing.assert_allclose(cal.correct(h_g, h_b, temp, t)[1], b_true, atol=1e-6)
    # a different site is a different record
    other = Calibration(probe.model, probe_id="P-9", site=sim.Site(dip_deg=61.0))
    assert other.id != cal.id


PLUGIN = """from inclinometer_calib.core.effects import T_REF_C, Effect, ParamSpec


class CubeTemperatureBias(Effect):
    \"\"\"Bias growing with the cube of the temperature offset (a test plug-in).\"\"\"

    name = "temperature_bias_cube_{tag}"
    stage = "output"
    specs = (ParamSpec("c3", {{"acc": "m/s^2/degC^3", "mag": "nT/degC^3"}}, {{"acc": 1e-6, "mag": 0.01}}),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["c3"] * ((ctx.temperature_c - T_REF_C) ** 3)[:, None]
"""


def test_a_plugin_effect_travels_with_its_file_and_hash_and_loads_only_from_the_named_matching_source(
        tmp_path, monkeypatch):
    import re
    import sys

    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core import plugins

    monkeypatch.setattr(plugins, "_NAMED", {}, raising=False)     # this test's own named plug-ins

    def new_process():
        """The effect not registered, its module not imported, nothing named."""
        del fx.CATALOGUE[name]
        for m in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(plug)]:
            del sys.modules[m]
        plugins._NAMED.clear()

    plug = tmp_path / "plug" / "cube.py"
    plug.parent.mkdir()
    plug.write_text(PLUGIN.format(tag="a"))
    (name,) = plugins.load_plugin(plug)
    model = sim.ProbeModel.base().with_effect(fx.make_effect(name, "mag", c3=[0.01, 0.02, 0.03]))
    cal = Calibration(model, probe_id="P")
    cal.save(tmp_path / "rec.yaml")
    item = yaml.safe_load((tmp_path / "rec.yaml").read_text())["model"]["effects"][0]
    assert item["plugin"]["file"] == str(plug) and len(item["plugin"]["sha256"]) == 64
    assert Calibration.load(tmp_path / "rec.yaml").id == cal.id     # registered, same source: fine
    # another process: the record alone does not load its plug-in ...
    new_process()
    refusal = f"effect '{name}' comes from the plug-in file '{plug}' (sha256 {item['plugin']['sha256'][:12]}…)"
    with pytest.raises(CoefficientError, match=re.escape(refusal + ", which is not named")):
        Calibration.load(tmp_path / "rec.yaml")
    assert name not in fx.CATALOGUE
    # ... the user names it, and the record loads it
    plugins.name_plugin(plug)
    back = Calibration.load(tmp_path / "rec.yaml")
    assert back.model.labels() == [f"{name}:mag:xyz"] and name in fx.CATALOGUE and back.id == cal.id
    # changed since: refused, naming the plug-in and both hashes
    new_process()
    plug.write_text(PLUGIN.format(tag="a") + "\n# edited\n")
    plugins.name_plugin(plug)
    with pytest.raises(CoefficientError, match="changed since the record was written"):
        Calibration.load(tmp_path / "rec.yaml")
    assert name not in fx.CATALOGUE
    # loaded from the edited source (e.g. for a fit): the record is refused too
    plugins.load_plugin(plug)
    with pytest.raises(CoefficientError, match="changed since the record was written"):
        Calibration.load(tmp_path / "rec.yaml")
    # missing, nothing named: refused, saying how to allow it
    new_process()
    plug.unlink()
    with pytest.raises(CoefficientError, match="which is not named.*--plugin PATH"):
        Calibration.load(tmp_path / "rec.yaml")


def test_a_record_given_as_text_never_runs_the_plugin_it_names_even_from_the_working_folder(tmp_path, monkeypatch):
    """A record from the topic or a registry (``from_yaml``, no folder of its own): the plug-in it
    names relative to the working folder is not executed; named, with the record's hash, it is."""
    import sys

    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core import plugins

    monkeypatch.setattr(plugins, "_NAMED", {}, raising=False)
    monkeypatch.chdir(tmp_path)
    plug = tmp_path / "cube.py"
    plug.write_text("open(__file__ + '.ran', 'w').close()\n" + PLUGIN.format(tag="text"))
    (name,) = plugins.load_plugin(plug)
    cal = Calibration(sim.ProbeModel.base().with_effect(fx.make_effect(name, "acc", c3=[1e-6, 0, 0])), probe_id="T")
    rec = cal.to_record()
    rec["model"]["effects"][0]["plugin"]["file"] = "cube.py"
    del rec["id"]
    text = yaml.safe_dump(rec)
    del fx.CATALOGUE[name]
    for m in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(plug)]:
        del sys.modules[m]
    plugins._NAMED.clear()
    (tmp_path / "cube.py.ran").unlink()
    with pytest.raises(CoefficientError, match=f"<yaml>: effect '{name}' comes from the plug-in file 'cube.py'"):
        Calibration.from_yaml(text)
    assert not (tmp_path / "cube.py.ran").exists() and name not in fx.CATALOGUE
    plugins.name_plugin("cube.py")
    try:
        assert Calibration.from_yaml(text).model.labels() == [f"{name}:acc:xyz"]
        assert (tmp_path / "cube.py.ran").exists()
    finally:
        fx.CATALOGUE.pop(name, None)

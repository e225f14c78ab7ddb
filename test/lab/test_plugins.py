"""User-defined effects: loaded from the user's file, simulated, ranked and fitted like built-ins; executed only
from a source the user named, never because a record names it."""
import os
import sys

import numpy as np
import pytest
import yaml

from inclinometer_calib.core import effects as fx
from inclinometer_calib import lab
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration, CoefficientError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EXAMPLE = os.path.join(ROOT, "examples", "plugins", "quadratic_temperature.py")


def test_plugin_effect_outside_the_catalogue_is_found_through_the_plugin_interface(sim_factory):
    assert lab.load_plugin(EXAMPLE) == ["temperature_bias_quadratic"]
    data, truth, site = sim_factory(51, ["temperature_bias_quadratic:mag=0.3"], plugins=[EXAMPLE])
    dg = lab.diagnose(data, site=site)
    top = dg.ranked[0]
    assert (top.effect, top.sensor) == ("temperature_bias_quadratic", "mag"), dg.verdict
    assert top.significant
    true_val = lab.val_metrics(lab.model_from_truth(truth), data.subset(data.role == "val"))
    assert top.val["azimuth_rms_deg"] <= 1.2 * true_val["azimuth_rms_deg"]


def test_a_plugin_without_effects_is_refused(tmp_path):
    p = tmp_path / "empty.py"
    p.write_text("x = 1\n")
    with pytest.raises(lab.PluginError, match="defines no subclass"):
        lab.load_plugin(p)


def test_a_plugin_that_fails_to_import_names_the_error(tmp_path):
    p = tmp_path / "broken.py"
    p.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(lab.PluginError, match="RuntimeError: boom"):
        lab.load_plugin(p)


def test_a_plugin_may_not_take_a_catalogue_name(tmp_path):
    p = tmp_path / "clash.py"
    p.write_text("from inclinometer_calib.core.effects import Effect\n"
                 "class Bias2(Effect):\n    name = 'bias'\n    stage = 'output'\n")
    with pytest.raises(lab.PluginError, match="already taken"):
        lab.load_plugin(p)
    assert fx.CATALOGUE["bias"] is fx.Bias


# ---- no code from data: a record never makes anything execute -------------------------------------------------
MARKED = '''import pathlib

pathlib.Path(__file__).with_name("executed.marker").write_text("this plug-in ran")

from inclinometer_calib.core.effects import T_REF_C, Effect, ParamSpec


class MarkedCubeBias(Effect):
    """Bias growing with the cube of the temperature offset; executing the file leaves a marker."""

    name = "{name}"
    stage = "output"
    specs = (ParamSpec("c3", {{"acc": "m/s^2/degC^3", "mag": "nT/degC^3"}}, {{"acc": 1e-6, "mag": 0.01}}),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["c3"] * ((ctx.temperature_c - T_REF_C) ** 3)[:, None]
'''


@pytest.fixture
def fresh(monkeypatch):
    """This test's own registry of named plug-ins; its effects leave the catalogue afterwards."""
    from inclinometer_calib.core import plugins

    monkeypatch.setattr(plugins, "_NAMED", {}, raising=False)
    before = set(fx.CATALOGUE)
    yield plugins
    for name in set(fx.CATALOGUE) - before:
        del fx.CATALOGUE[name]


def _forget(path, name):
    """As in a new process: the effect not registered, its module not imported, nothing named."""
    from inclinometer_calib.core import plugins

    fx.CATALOGUE.pop(name, None)
    for m in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(path)]:
        del sys.modules[m]
    plugins._NAMED.clear()
    marker = path.with_name("executed.marker")
    if marker.exists():
        marker.unlink()


def _record(tmp_path, plug, name, ref=None):
    """A record (rec.yaml in tmp_path) using the plug-in ``plug``, written as the lab writes it; the
    plug-in then forgotten.  ``ref`` edits the record's plug-in reference (the id then dropped)."""
    plug.write_text(MARKED.format(name=name))
    spec = plug.stem if ref and "module" in ref else plug
    assert lab.load_plugin(spec) == [name]
    cal = Calibration(sim.ProbeModel.base().with_effect(fx.make_effect(name, "mag", c3=[0.01, 0.02, 0.03])),
                      probe_id="P")
    rec = cal.to_record()
    if ref:
        rec["model"]["effects"][0]["plugin"] = dict(ref, sha256=rec["model"]["effects"][0]["plugin"]["sha256"])
        del rec["id"]
    path = tmp_path / "rec.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    _forget(plug, name)
    return path, rec["model"]["effects"][0]["plugin"], cal


def _refused(path, name, ref):
    """Loading ``path`` is refused in one line naming the effect, the record's plug-in and its hash
    prefix, and how to allow it; the plug-in did not run."""
    with pytest.raises(CoefficientError) as info:
        Calibration.load(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert repr(name) in msg and repr(ref.get("file") or ref.get("module")) in msg
    assert f"sha256 {ref['sha256'][:12]}" in msg
    assert "--plugin PATH" in msg and "plugins" in msg
    return msg


def test_a_record_naming_a_file_the_user_did_not_name_is_refused_without_running_it(tmp_path, fresh):
    plug = tmp_path / "plug" / "cube.py"
    plug.parent.mkdir()
    path, ref, _ = _record(tmp_path, plug, "cube_marked_abs")
    msg = _refused(path, "cube_marked_abs", ref)
    assert "not named" in msg
    assert not plug.with_name("executed.marker").exists()
    assert "cube_marked_abs" not in fx.CATALOGUE


def test_a_record_naming_a_relative_file_is_refused_without_running_it(tmp_path, fresh):
    plug = tmp_path / "plug" / "cube.py"
    plug.parent.mkdir()
    path, ref, _ = _record(tmp_path, plug, "cube_marked_rel", ref={"file": "plug/cube.py"})  # beside the record
    _refused(path, "cube_marked_rel", ref)
    assert not plug.with_name("executed.marker").exists()


def test_a_record_naming_a_module_is_refused_without_importing_it(tmp_path, fresh, monkeypatch):
    mods = tmp_path / "mods"
    mods.mkdir()
    monkeypatch.syspath_prepend(str(mods))
    plug = mods / "marked_cube_plugin.py"
    path, ref, _ = _record(tmp_path, plug, "cube_marked_mod", ref={"module": "marked_cube_plugin"})
    _refused(path, "cube_marked_mod", ref)
    assert not plug.with_name("executed.marker").exists()
    assert "marked_cube_plugin" not in sys.modules


def test_a_named_plugin_whose_source_is_not_the_records_is_refused_without_running_it(tmp_path, fresh):
    plug = tmp_path / "plug" / "cube.py"
    plug.parent.mkdir()
    path, ref, _ = _record(tmp_path, plug, "cube_marked_changed")
    plug.write_text(plug.read_text() + "\n# edited since the record was written\n")
    fresh.name_plugin(plug)
    msg = _refused(path, "cube_marked_changed", ref)
    assert "changed since the record was written" in msg
    assert not plug.with_name("executed.marker").exists()


def test_naming_a_plugin_executes_nothing_and_the_named_matching_file_loads_and_corrects_as_before(tmp_path, fresh):
    plug = tmp_path / "plug" / "cube.py"
    plug.parent.mkdir()
    path, ref, cal = _record(tmp_path, plug, "cube_marked_ok")
    assert fresh.name_plugin(plug) == ref                     # the reference the record keeps, read now
    assert not plug.with_name("executed.marker").exists()     # naming only hashes
    back = Calibration.load(path)
    assert plug.with_name("executed.marker").exists()         # executed: named, and the record's SHA-256
    assert back.id == cal.id and back.model.labels() == ["cube_marked_ok:mag:xyz"]
    rng = np.random.default_rng(3)
    g, b = rng.normal(0, 5, (20, 3)), rng.normal(0, 3e4, (20, 3))
    temp, t = rng.uniform(0, 80, 20), rng.uniform(0, 7200, 20)
    for x, y in zip(cal.correct(g, b, temp, t), back.correct(g, b, temp, t)):
        np.testing.assert_array_equal(x, y)


def test_a_fit_runs_the_plugins_the_user_named_for_it(tmp_path, fresh):
    """Naming plug-ins for a simulation or fit (no record) executes them: the user's intent."""
    plug = tmp_path / "cube.py"
    plug.write_text(MARKED.format(name="cube_marked_fit"))
    assert lab.load_plugin(plug) == ["cube_marked_fit"]
    assert plug.with_name("executed.marker").exists()
    assert fx.CATALOGUE["cube_marked_fit"].plugin == fresh.name_plugin(plug)

"""User-defined effects: loaded from the user's file, simulated, ranked and fitted like built-ins."""
import os

import pytest

from inclinometer_calib import effects as fx
from inclinometer_calib import lab

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
    p.write_text("from inclinometer_calib.effects import Effect\n"
                 "class Bias2(Effect):\n    name = 'bias'\n    stage = 'output'\n")
    with pytest.raises(lab.PluginError, match="already taken"):
        lab.load_plugin(p)
    assert fx.CATALOGUE["bias"] is fx.Bias

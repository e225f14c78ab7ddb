"""One site file, one Site: the CLI's reader, the calibration record and the nodes' parameters
(built by the launcher, read back as the nodes read them) all go through geomag.site_from_config."""
import os

import pytest
import yaml

from inclinometer_calib.apps import launcher
from inclinometer_calib.apps.common import UserError, load_site
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.geomag import site_from_parameters, site_parameter_defaults

RIG_SITE = os.path.join(os.path.dirname(__file__), "..", "..", "config", "rig_site.yaml")


def _site_files(tmp_path):
    with open(RIG_SITE, encoding="utf-8") as fh:
        rig = yaml.safe_load(fh)["site"]
    ifr = tmp_path / "ifr.yaml"           # a location with measured values that win, no wrapper
    ifr.write_text(yaml.safe_dump({**rig, "model": "IGRF-14", "total_field_nt": 50321.5, "declination_deg": -0.75}))
    typed = tmp_path / "typed.yaml"       # values typed in, no location
    typed.write_text("site:\n  total_field_nt: 49876.0\n  dip_deg: 71.25\n  declination_deg: 1.5\n")
    return [RIG_SITE, str(ifr), str(typed)]


def _node_parameters(path):
    # what a node declares: its defaults (nodes.common.declare_site) overridden by the launcher's
    defaults = site_parameter_defaults()
    given = launcher.site_node_parameters(path)
    assert set(given) <= {f"site.{k}" for k in defaults}
    return {**defaults, **{k[len("site."):]: v for k, v in given.items()}}


def test_one_site_file_gives_the_same_site_to_the_cli_the_record_and_the_nodes(tmp_path):
    for path in _site_files(tmp_path):
        cli = load_site(path)
        record = Calibration.from_yaml(Calibration(site=cli).to_yaml()).site
        node = site_from_parameters(_node_parameters(path))
        assert record.to_dict() == cli.to_dict(), path
        assert node.to_dict() == cli.to_dict(), path
    assert cli.reference == {} and cli.dip_deg == 71.25
    assert load_site(RIG_SITE).reference["crs"] == "EPSG:23031"


def test_a_bad_site_file_is_refused_in_the_same_words_by_the_cli_and_the_launcher(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("site:\n  latitude_deg: 57.48\n  longitude_deg: 1.72\n  date: 2026-11-23\n  dip: 70\n")
    with pytest.raises(UserError) as cli:
        load_site(str(bad))
    with pytest.raises(ValueError) as launch:
        launcher.site_node_parameters(str(bad))
    assert str(cli.value) == str(launch.value)
    assert str(cli.value).startswith(f"{bad}: cannot read site reference: site: unknown key(s) ['dip']")
    assert "\n" not in str(cli.value)

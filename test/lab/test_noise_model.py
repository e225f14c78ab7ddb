"""The lab's noise model on logs from the independent generator (``independent.py``): holds the
detector cut joined again, the walk read from the Allan deviation of a long hold, abutting logs at
different attitudes kept apart."""
import json

import numpy as np
import pytest

from inclinometer_calib import lab
from inclinometer_calib.core.frames import Site
from inclinometer_calib.lab.noise import holds, noise_model

import independent as ind


def _site(gen):
    s = gen.site
    return Site(total_field_nt=s.field_nt, dip_deg=s.dip_deg, declination_deg=s.declination_deg, gravity_mps2=s.gravity)


def test_a_long_hold_cut_by_the_detector_is_one_hold_whose_allan_deviation_resolves_the_walk(tmp_path):
    probe = ind.random_probe(21)
    probe["mag"].walk, probe["acc"].walk = 0.5, 5e-5
    gen = ind.Generator(probe, seed=21)
    gen.write(tmp_path / "static.csv", ind.twelve_pose_rounds(1, hold_s=900.0)[:1])
    data = lab.load_logs(tmp_path / "static.csv")
    assert len(data) > 10                              # the detector cuts a long hold at its maximum duration
    assert len(holds(data)) == 1                       # ... the noise model joins it again
    nm = noise_model(lab.LabModel.base(_site(gen)), data)
    assert nm["mag"].curve.tau[-1] > 100.0                 # a few s per station alone
    for sensor, noise, walk in (("mag", probe["mag"].noise, 0.5), ("acc", probe["acc"].noise, 5e-5)):
        for axis in nm[sensor].terms:
            assert axis["N"].value == pytest.approx(noise / np.sqrt(50.0), rel=0.03)   # σ/√rate
            k = axis["K"]
            assert k.resolved and abs(k.value - walk) < 3.5 * k.std, (sensor, k)
    rows = nm["mag"].table()
    assert {r["random_walk"]["source"] for r in rows} == {"holds"}


def test_abutting_logs_at_different_attitudes_are_not_one_hold(tmp_path):
    probe = ind.random_probe(22)
    gen = ind.Generator(probe, seed=22)
    # the second log starts in the sample after the first one's last, at another attitude
    gen.write(tmp_path / "a.csv", ind.twelve_pose_rounds(1, hold_s=4.0)[:3])
    gen.write(tmp_path / "b.csv", ind.twelve_pose_rounds(1, hold_s=4.0)[3:6])
    data = lab.load_logs([tmp_path / "a.csv", tmp_path / "b.csv"])
    assert len(holds(data)) == len(data) == 6
    nm = noise_model(lab.LabModel.base(_site(gen)), data)
    assert nm["mag"].curve.tau[-1] < 2.0                # no Allan point across the jump
    for axis in nm["mag"].terms:
        assert axis["N"].value == pytest.approx(probe["mag"].noise / np.sqrt(50.0), rel=0.05)


def test_the_cli_prints_the_ieee_figures_of_static_logs_and_names_a_missing_file(tmp_path, capsys):
    from inclinometer_calib.apps.cli import main

    probe = ind.random_probe(23)
    gen = ind.Generator(probe, seed=23)
    gen.write(tmp_path / "static.csv", ind.twelve_pose_rounds(1, hold_s=120.0)[:2], labels=False)
    assert main(["lab", "noise", str(tmp_path / "static.csv")]) == 0
    out = capsys.readouterr().out
    assert "2 holds" in out and "white noise N" in out and "nT/√Hz" in out
    assert main(["lab", "noise", "--json", str(tmp_path / "static.csv")]) == 0
    doc = json.loads(capsys.readouterr().out)
    wn = doc["mag"]["figures"][0]["white_noise"]
    assert wn["resolved"] and wn["value"] == pytest.approx(probe["mag"].noise / np.sqrt(50.0), rel=0.05)
    assert main(["lab", "noise", str(tmp_path / "nowhere.csv")]) != 0
    assert "nowhere.csv" in capsys.readouterr().err


def test_a_noise_model_without_holds_says_why_instead_of_zero_holds_and_nan():
    """A recorded run keeps the stations' means only: no Allan deviation (it read "Allan deviation
    of 0 holds, τ up to nan s")."""
    from types import SimpleNamespace

    import numpy as np

    from inclinometer_calib.lab.diagnose import noise_line

    empty = SimpleNamespace(terms=[], unit="m/s^2", curve=SimpleNamespace(n_segments=0, tau=np.zeros(0)))
    line = noise_line({"acc": empty, "mag": empty})
    assert "nan" not in line and "0 holds" not in line
    assert line.startswith("Noise model: no Allan deviation — the data hold no samples of the holds")

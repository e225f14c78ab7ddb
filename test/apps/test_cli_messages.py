"""What the CLI says when an input or an output is wrong: one line, in plain words, about the thing
that is wrong — a missing input bag as the input's error (not the output's), an existing output as
existing (no errno text), a record's plug-in named at another path than the record's as that (not as
an edited record).

The commands with input problems run in-process (``main``); the plug-in ones in a subprocess each, as
a user runs them: a plug-in, once executed, stays registered in its process.
"""
import subprocess
import sys

import pytest

from inclinometer_calib.apps.cli import main

ROOT = __file__.rsplit("/test/", 1)[0]
EXAMPLE_PLUGIN = f"{ROOT}/examples/plugins/quadratic_temperature.py"
EXISTS = "already exists; refusing to overwrite it (choose another output name)"


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    """The user trial's setup: a simulated run, its validation log as a bag, a twelve-position record."""
    d = tmp_path_factory.mktemp("trial")
    assert main(["simulate", "--out", str(d / "sim"), "--seed", "1", "--station-seconds", "0.6", "--rate", "25"]) == 0
    assert main(["bag", "from-csv", str(d / "sim" / "val.csv"), "-o", str(d / "val.mcap")]) == 0
    assert main(["twelve-position", str(d / "sim" / "cal.csv"), "-o", str(d / "coeffs.yaml")]) == 0
    return d


def _err(capsys, argv):
    capsys.readouterr()
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("how", ["--calibrate", "--coeffs"])
def test_a_missing_input_bag_is_said_of_the_input_not_of_the_output(trial, tmp_path, capsys, how):
    missing, out = tmp_path / "missing.mcap", tmp_path / "r.mcap"
    argv = ["reprocess", missing, "--calibrate"] if how == "--calibrate" else \
        ["reprocess", missing, "--coeffs", trial / "coeffs.yaml"]
    rc, err = _err(capsys, argv + ["-o", out])
    assert rc == 2
    assert err == f"error: {missing}: no such bag file or directory\n"
    assert list(tmp_path.iterdir()) == []          # nothing written, no temporary left


@pytest.mark.parametrize("command", ["reprocess", "bag from-csv"])
def test_an_existing_output_is_refused_in_plain_words_and_kept(trial, tmp_path, capsys, command):
    out = tmp_path / "out.mcap"
    out.write_bytes(b"an earlier run")
    argv = ["reprocess", trial / "val.mcap", "--coeffs", trial / "coeffs.yaml"] if command == "reprocess" else \
        ["bag", "from-csv", trial / "sim" / "val.csv"]
    rc, err = _err(capsys, argv + ["-o", out])
    assert rc == 2
    assert err == f"error: {out} {EXISTS}\n"
    assert out.read_bytes() == b"an earlier run" and list(tmp_path.iterdir()) == [out]


MAKE_RECORD = """
import sys
from inclinometer_calib import lab
from inclinometer_calib.core import effects as fx
from inclinometer_calib.core.coeffs import Calibration

plugin, base, out = sys.argv[1:]
assert lab.load_plugin(plugin) == ["temperature_bias_quadratic"]
cal = Calibration.load(base)
model = cal.model.with_effect(fx.make_effect("temperature_bias_quadratic", "mag", c2=[0.01, 0.02, 0.03]))
Calibration(model, probe_id=cal.probe_id, method="lab_fit", site=cal.site, site_source=cal.site_source).save(out)
"""


def _cli(*argv, cwd):
    return subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.cli", *map(str, argv)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def plugin_record(trial):
    """A record fitted with the example plug-in at plug/qt.py, and an identical copy at plug/qt2.py."""
    plug = trial / "plug"
    plug.mkdir()
    text = open(EXAMPLE_PLUGIN, encoding="utf-8").read()
    (plug / "qt.py").write_text(text)
    (plug / "qt2.py").write_text(text)
    rec = trial / "plugrec.yaml"
    r = subprocess.run([sys.executable, "-c", MAKE_RECORD, str(plug / "qt.py"), str(trial / "coeffs.yaml"), str(rec)],
                       cwd=trial, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return rec, plug


def test_a_records_plugin_named_at_another_path_is_refused_saying_which_paths_differ(trial, plugin_record):
    rec, plug = plugin_record
    r = _cli("reprocess", "val.mcap", "--coeffs", rec, "--plugin", "plug/qt2.py", "-o", "p.mcap", cwd=trial)
    assert r.returncode == 2
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {rec}: id "), r.stderr
    said = lines[0]
    assert "edited without re-issuing" not in said
    assert f"at {plug / 'qt.py'}" in said and f"named here at {plug / 'qt2.py'}" in said and "the same content" in said
    assert f"--plugin {plug / 'qt.py'}" in said
    assert not (trial / "p.mcap").exists()
    # the plug-in at the record's path: the record is accepted (the id differed by the path alone)
    r = _cli("reprocess", "val.mcap", "--coeffs", rec, "--plugin", "plug/qt.py", "-o", "p.mcap", cwd=trial)
    assert r.returncode == 0, r.stderr
    assert (trial / "p.mcap").exists()


def test_a_record_edited_and_named_with_a_plugin_elsewhere_is_still_said_to_be_edited(trial, plugin_record, tmp_path):
    rec, _ = plugin_record
    edited = tmp_path / "edited.yaml"
    text = rec.read_text()
    assert "\nprobe_id: probe\n" in text
    edited.write_text(text.replace("\nprobe_id: probe\n", "\nprobe_id: another\n", 1))   # the id kept
    r = _cli("reprocess", "val.mcap", "--coeffs", edited, "--plugin", "plug/qt2.py", "-o", tmp_path / "p.mcap",
             cwd=trial)
    assert r.returncode == 2
    assert len(r.stderr.splitlines()) == 1 and "edited without re-issuing" in r.stderr, r.stderr


def test_an_input_bag_the_os_refuses_is_said_of_the_input_in_one_line(tmp_path, capsys, monkeypatch):
    """An input the OS will not open (permission denied; faked: root reads anything) is one line
    about the input, not a traceback and not "cannot write" the output."""
    from inclinometer_calib.apps.cli import main
    from inclinometer_calib.io import bag

    src = tmp_path / "in.mcap"
    src.write_bytes(b"x")

    def refuse(path):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(bag, "open_bag", refuse)
    monkeypatch.setattr(bag.BagReader, "__init__", lambda self, path, *a, **k: refuse(path))
    out = tmp_path / "r.mcap"
    code = main(["reprocess", str(src), "--coeffs", "none", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"error: cannot read {src}: permission denied (EACCES)" in err and "Traceback" not in err, err
    assert not out.exists()

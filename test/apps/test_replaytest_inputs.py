"""``replay-test``'s input, checked before the replay: a usage error is one ``error:`` line and exit
2, costs no replay and leaves nothing behind; a record's plug-in named with ``--plugin`` is loaded
for the expected set too; the diff table and the JUnit report say what differs and by how much.

No ROS graph: the replay (the launcher's process) is replaced by a stand-in that only records that
it was reached."""
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from inclinometer_calib.apps import replaytest
from inclinometer_calib.apps.cli import main
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core import effects as fx
from inclinometer_calib.core import plugins
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site
from inclinometer_calib.correct.reprocess import reprocess, write_probe_bag

EXAMPLE_PLUGIN = Path(__file__).resolve().parents[2] / "examples" / "plugins" / "quadratic_temperature.py"
#: The example plug-in's effect under a name no other test registers (this process may hold the example's).
EFFECT = "replaytest_quadratic_temperature"
SERIAL = "RT-1"


class ReplayStarted(Exception):
    """Raised by the stand-in for the launcher: the replay was reached, every input accepted."""


@pytest.fixture
def no_replay(monkeypatch):
    """The launcher's process replaced: reaching it raises :class:`ReplayStarted`; the calls, kept."""
    calls = []

    def run(cmd, **kwargs):
        calls.append(cmd)
        raise ReplayStarted(cmd)

    monkeypatch.setattr(replaytest, "subprocess", types.SimpleNamespace(run=run))
    return calls


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """A short simulated session (6 stations) as a probe bag, and reprocess's stations of it as a
    golden bag."""
    d = tmp_path_factory.mktemp("replaytest_inputs")
    probe = sim.build_probe(3)
    log = sim.run_session(probe, Site(), sim.stand_grid_session(drifts=(10, 40), azimuths=(0, 120, 240),
                                                                toolfaces=(0,), duration_s=1.5),
                          np.random.default_rng(3), rate_hz=100)
    bag = d / "session.mcap"
    write_probe_bag(log, bag, serial=SERIAL)
    rec = d / "probe.yaml"
    Calibration(acc=probe.acc, mag=probe.mag, probe_id=SERIAL, site=Site()).save(rec)
    golden = d / "golden.mcap"
    reprocess(bag, golden, Calibration.load(rec))
    return {"bag": bag, "record": rec, "golden": golden}


def _run(capsys, *argv):
    code = main(["replay-test", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err):
    assert err.count("\n") == 1 and err.startswith("error: ") and "Traceback" not in err, err
    return err.strip()


# --- defect: --plugin ignored for the expected set --------------------------------------------------

@pytest.fixture
def plugin_record(tmp_path, bags, monkeypatch):
    """A record whose model uses the example plug-in (under the name :data:`EFFECT`), written as the
    lab writes it; then the plug-in forgotten, as in a new process (not named, not registered)."""
    monkeypatch.setattr(plugins, "_NAMED", {})
    plug = tmp_path / "plug" / "qt.py"
    plug.parent.mkdir()
    plug.write_text(EXAMPLE_PLUGIN.read_text().replace('"temperature_bias_quadratic"', f'"{EFFECT}"'))
    assert plugins.load_plugin(plug) == [EFFECT]
    base = Calibration.load(bags["record"])
    rec = tmp_path / "plugrec.yaml"
    Calibration(base.model.with_effect(fx.make_effect(EFFECT, "mag", c2=0.05)), probe_id=SERIAL,
                site=Site()).save(rec)
    fx.CATALOGUE.pop(EFFECT)
    for name in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(plug)]:
        del sys.modules[name]
    plugins._NAMED.clear()
    yield rec, plug
    fx.CATALOGUE.pop(EFFECT, None)
    for name in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(plug)]:
        del sys.modules[name]


def test_expect_reprocess_loads_a_plugin_record_whose_plugin_is_named_and_reaches_the_replay(
        plugin_record, bags, tmp_path, capsys, no_replay):
    rec, plug = plugin_record
    with pytest.raises(ReplayStarted):
        _run(capsys, bags["bag"], "--expect", "reprocess", "--coeffs", rec, "--plugin", plug,
             "--out", tmp_path / "run")
    out, err = capsys.readouterr()
    assert "expected: reprocess of" in out and "6 stations" in out, out + err
    assert no_replay and ["--plugin", str(plug)] == no_replay[0][no_replay[0].index("--plugin"):][:2]


def test_expect_reprocess_still_refuses_a_plugin_record_whose_plugin_is_not_named(
        plugin_record, bags, tmp_path, capsys, no_replay):
    rec, _ = plugin_record
    code, _, err = _run(capsys, bags["bag"], "--expect", "reprocess", "--coeffs", rec, "--out", tmp_path / "run")
    assert code == 2 and "which is not named" in _one_error_line(err) and not no_replay


# --- defect: bad input as tracebacks (exit 1), or found after the replay -----------------------------

def _listing(d):
    return sorted(str(p.relative_to(d)) for p in Path(d).rglob("*"))


@pytest.mark.parametrize("kind", ["empty file", "folder without a bag"])
def test_a_bag_to_replay_that_is_not_a_bag_is_one_error_line_exit_2_before_any_work(kind, tmp_path, capsys,
                                                                                      no_replay):
    if kind == "empty file":
        bad = tmp_path / "empty.mcap"
        bad.write_bytes(b"")
    else:
        bad = tmp_path / "folder"
        bad.mkdir()
    before = _listing(tmp_path)
    code, out, err = _run(capsys, bad, "--expect", "reprocess", "--calibrate")
    line = _one_error_line(err)
    assert code == 2 and f"error: {bad}: not a bag to replay: " in line, line
    assert not no_replay and out == "" and _listing(tmp_path) == before


@pytest.mark.parametrize("kind", ["empty file", "folder without a bag", "truncated golden bag"])
def test_an_expected_bag_that_is_not_readable_is_one_error_line_exit_2_before_the_replay(kind, bags, tmp_path,
                                                                                         capsys, no_replay):
    if kind == "empty file":
        bad = tmp_path / "empty.mcap"
        bad.write_bytes(b"")
    elif kind == "folder without a bag":
        bad = tmp_path / "folder"
        bad.mkdir()
    else:
        bad = tmp_path / "cut.mcap"
        data = bags["golden"].read_bytes()
        bad.write_bytes(data[:len(data) // 2])
    before = _listing(tmp_path)
    code, out, err = _run(capsys, bags["bag"], "--expect", bad, "--out", tmp_path / "run")
    line = _one_error_line(err)
    assert code == 2 and line.startswith(f"error: --expect {bad}: not a readable bag ("), line
    assert not no_replay and _listing(tmp_path) == before


@pytest.mark.parametrize("where", ["a file", "under a file"])
def test_an_out_that_cannot_be_the_runs_folder_is_one_error_line_exit_2_before_the_replay(where, bags, tmp_path,
                                                                                         capsys, no_replay):
    f = tmp_path / "existing_file"
    f.write_text("mine\n")
    out_dir = f if where == "a file" else f / "run"
    before = _listing(tmp_path)
    code, out, err = _run(capsys, bags["bag"], "--expect", bags["golden"], "--out", out_dir)
    line = _one_error_line(err)
    assert code == 2 and line.startswith(f"error: --out {out_dir}: "), line
    assert ("a file of that name exists" if where == "a file" else f"{f} is a file, not a folder") in line, line
    assert not no_replay and _listing(tmp_path) == before and f.read_text() == "mine\n"


def test_a_junit_file_in_a_missing_folder_is_refused_before_the_replay(bags, tmp_path, capsys, no_replay):
    junit = tmp_path / "missing" / "replay.xml"
    code, out, err = _run(capsys, bags["bag"], "--expect", bags["golden"], "--out", tmp_path / "run",
                          "--junit", junit)
    line = _one_error_line(err)
    assert code == 2 and line == f"error: cannot write {junit}: the folder {junit.parent} does not exist", line
    assert not no_replay and not (tmp_path / "run").exists()


def test_coeffs_none_is_refused_before_the_replay_as_the_graph_has_no_uncorrected_mode(bags, tmp_path, capsys,
                                                                                       no_replay):
    """It used to reach the launcher, which took "none" for a file name (now refused there too)."""
    code, out, err = _run(capsys, bags["bag"], "--expect", bags["golden"], "--coeffs", "none", "--out",
                          tmp_path / "run")
    line = _one_error_line(err)
    assert code == 2 and line.startswith("error: --coeffs none: the live graph has no uncorrected mode"), line
    assert not no_replay and not (tmp_path / "run").exists()


def test_a_golden_bag_and_good_options_reach_the_replay(bags, tmp_path, capsys, no_replay):
    """The checks above refuse only what is wrong: the same command with good input replays."""
    with pytest.raises(ReplayStarted):
        _run(capsys, bags["bag"], "--expect", bags["golden"], "--coeffs", bags["record"], "--out",
             tmp_path / "run", "--junit", tmp_path / "replay.xml")
    assert len(no_replay) == 1


# --- cosmetic: the diff table's stamp column, the JUnit report's delta ---------------------------

def _comparison():
    c = replaytest.Comparison(expected=2, got=2)
    c.differences = [replaytest.Difference(1700000123.456, 7, "azimuth_deg", 123.4, 123.4000025, 2.5e-6),
                     replaytest.Difference(1700000456.789, 12, "status", "ok", "warn")]
    return c


def test_the_difference_table_keeps_its_columns_aligned_for_epoch_stamps():
    lines = replaytest.format_comparison(_comparison(), 1e-6)
    header = next(i for i, line in enumerate(lines) if "t (s)" in line)
    table = lines[header:header + 3]
    assert len({len(line) for line in table}) == 1, "\n".join(table)
    right = table[0].index("id") + 2          # the id column's right edge, as the header has it
    assert table[1][right - 1:right] == "7" and table[2][right - 2:right] == "12", "\n".join(table)


def test_the_junit_report_gives_the_delta_replayed_minus_expected_of_a_differing_number():
    xml = replaytest.junit_xml(_comparison(), [], "replay-test x")
    assert "azimuth_deg: expected 123.4, replayed 123.4000025 (delta +2.5e-06 deg)" in xml
    assert "status: expected ok, replayed warn" in xml and "replayed warn (delta" not in xml

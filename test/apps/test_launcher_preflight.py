"""The launcher's pre-flight checks: bad arguments are refused before anything starts — one line
``error: ...`` on stderr, exit status 2, no node started, no domain reserved, ``--out`` untouched —
and a node that refuses its parameters anyway is not restarted, its own reason in the last line.

The launcher runs as a subprocess (:data:`LAUNCHER`) whose nodes are stand-ins (:data:`STAND_IN`):
each start is written to a file, so a check that let a bad argument through shows as a node
started, and no test here ever starts ROS."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PLUGIN = os.path.join(ROOT, "examples", "plugins", "quadratic_temperature.py")

#: A node stand-in (argv: the file it notes its start in, its name): notes its start; the node
#: named by STAND_IN_REFUSE says what nodes.common.run says of a refused parameter and exits 2;
#: any other runs until SIGINT.
STAND_IN = r"""
import os, signal, sys, time
starts, name = sys.argv[1], sys.argv[2]
with open(starts, "a") as f:
    f.write(name + "\n")
if os.environ.get("STAND_IN_RUNERR") == name and open(starts).read().split().count(name) == 1:
    print(f"{name.capitalize()}Node: error while running: a callback raised", file=sys.stderr)
    sys.exit(2)
if os.environ.get("STAND_IN_REFUSE") == name:
    print(f"{name.capitalize()}Node: error: Invalid parameter value (/x/nothere.yaml) for parameter. Reason: "
          "parameter coeffs_file: cannot use '/x/nothere.yaml': No such file or directory", file=sys.stderr)
    sys.exit(2)
signal.signal(signal.SIGINT, lambda *_: sys.exit(0))
if os.environ.get("STAND_IN_END") == name:      # ends once the others named have started (as often as named)
    wait = os.environ.get("STAND_IN_WAIT", "").split(",")
    while any(open(starts).read().split().count(w) < wait.count(w) for w in wait):
        time.sleep(0.05)
    sys.exit(0)
while True:
    time.sleep(0.05)
"""

#: ``python -m inclinometer_calib.apps.launcher ARGS`` with the stand-in nodes (argv[1]: where they
#: note their starts).
LAUNCHER = r"""
import sys
from inclinometer_calib.apps import launcher
starts, stand_in = sys.argv[1], sys.argv[2]
launcher.node_command = lambda name, params, cfg: [sys.executable, "-c", stand_in, starts, name]
sys.exit(launcher.main(sys.argv[3:]))
"""


def _launch(tmp_path, *argv, env=None, timeout=120):
    """Run the launcher (stand-in nodes) in ``tmp_path``: ``(rc, stdout, stderr, nodes started)``."""
    starts = tmp_path / "starts.txt"
    env = dict(os.environ if env is None else env, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env.pop("ROS_DOMAIN_ID", None)
    proc = subprocess.run([sys.executable, "-c", LAUNCHER, str(starts), STAND_IN, *map(str, argv)], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=timeout)
    started = starts.read_text().split() if starts.exists() else []
    return proc.returncode, proc.stdout, proc.stderr, started


def _refused(tmp_path, *argv):
    """The launcher refuses ``argv`` before anything starts: exit status 2, one line ``error: ...``
    on stderr and nothing on stdout, no node started, no ``--out`` folder made.  The line."""
    out = tmp_path / "run"
    rc, stdout, stderr, started = _launch(tmp_path, "--out", out, "--no-loop", "--timeout", "5", *argv)
    assert started == [], f"nodes started: {started}\n{stdout[-3000:]}\n{stderr[-2000:]}"
    assert rc == 2, f"exit status {rc}\n{stdout[-3000:]}\n{stderr[-2000:]}"
    assert stdout == ""
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert "Traceback" not in stderr
    assert not out.exists(), sorted(os.listdir(out))
    return lines[0]


@pytest.fixture(scope="module")
def val_bag(tmp_path_factory):
    """The user trial's replay input: a simulated validation log as a bag (``bag from-csv``)."""
    from inclinometer_calib.apps.cli import main

    d = tmp_path_factory.mktemp("trial")
    assert main(["simulate", "--out", str(d / "sim"), "--seed", "1"]) == 0
    assert main(["bag", "from-csv", str(d / "sim" / "val.csv"), "-o", str(d / "val.mcap")]) == 0
    return d / "val.mcap"


def _bag_with(path, topics):
    """A finalized bag with these topics (and no messages on them)."""
    from inclinometer_calib.io.bag import BagWriter
    from inclinometer_calib.io.topics import PROBE_TOPICS

    with BagWriter(path) as w:
        for t in topics:
            w.add_topic(t, PROBE_TOPICS[t])
    return path


# ---- --coeffs: loaded before the graph starts, by the nodes' loader and plug-in rule ---------------------------
def test_a_missing_coeffs_file_is_refused_before_any_node_starts(tmp_path, val_bag):
    line = _refused(tmp_path, "--source", "mcap", "--input", val_bag, "--no-calibration", "--coeffs", "nothere.yaml",
                    "--speed", "50")
    assert line == "error: --coeffs nothere.yaml: No such file or directory"


def test_a_file_that_is_not_a_coefficient_record_is_refused_before_any_node_starts(tmp_path):
    (tmp_path / "notes.yaml").write_text("just: notes\n")
    line = _refused(tmp_path, "--no-calibration", "--coeffs", "notes.yaml")
    assert line.startswith("error: --coeffs notes.yaml: ") and "format" in line


def test_a_binary_file_given_as_the_record_is_one_line_not_a_traceback(tmp_path):
    """A bag given for --coeffs: YAML's reader raised UnicodeDecodeError, past the pre-flight."""
    _bag_with(tmp_path / "run.mcap", ["/probe/imu"])
    line = _refused(tmp_path, "--no-calibration", "--coeffs", "run.mcap")
    assert line == "error: --coeffs run.mcap: not a calibration record (not UTF-8 text)", line


def test_coeffs_none_is_not_taken_for_a_file_name(tmp_path):
    """``reprocess --coeffs none`` means no record; the launcher has no such mode: said, not passed on
    to the correction node as a file called none."""
    assert _refused(tmp_path, "--coeffs", "none").startswith("error: --coeffs none: the launcher takes a coefficient")


def _plugin_record(tmp_path):
    """A record (rec.yaml) whose model uses the example plug-in (copied to plug/q.py), written in a
    process of its own so that this one names nothing."""
    (tmp_path / "plug").mkdir()
    (tmp_path / "plug" / "q.py").write_bytes(open(PLUGIN, "rb").read())
    subprocess.run([sys.executable, "-c", """
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core import effects as fx
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.plugins import load_plugin
load_plugin("plug/q.py")
effect = fx.make_effect("temperature_bias_quadratic", "mag", c2=[0.01, 0.02, 0.03])
Calibration(sim.ProbeModel.base().with_effect(effect), probe_id="P").save("rec.yaml")
"""], cwd=tmp_path, check=True)
    return "rec.yaml"


def test_a_record_needing_a_plugin_not_named_is_refused_before_any_node_starts(tmp_path, val_bag):
    rec = _plugin_record(tmp_path)
    line = _refused(tmp_path, "--source", "mcap", "--input", val_bag, "--no-calibration", "--coeffs", rec)
    assert line.startswith("error: --coeffs rec.yaml: effect 'temperature_bias_quadratic' comes from the plug-in")
    assert "not named" in line and "--plugin PATH" in line


def test_a_record_whose_plugin_is_named_passes_the_checks_and_the_graph_starts(tmp_path, val_bag):
    """The same rule as the nodes': the plug-in named with --plugin, the record loads (and the
    stand-in graph runs: its probe ends once the correction has started, whatever the machine's speed)."""
    rec = _plugin_record(tmp_path)
    env = dict(os.environ, STAND_IN_END="probe", STAND_IN_WAIT="correction")
    rc, stdout, stderr, started = _launch(tmp_path, "--out", tmp_path / "run", "--source", "mcap", "--input", val_bag,
                                          "--no-calibration", "--no-recorder", "--no-loop", "--coeffs", rec,
                                          "--plugin", "plug/q.py", "--timeout", "60", env=env)
    assert sorted(started) == ["correction", "probe"], f"{stdout[-3000:]}\n{stderr[-2000:]}"
    assert "error:" not in stderr


def test_a_usage_error_in_the_node_parameters_exits_2_before_any_node_starts(tmp_path):
    """--plugin, --param (build_params) refused as usage errors: exit status 2, not 1."""
    assert _refused(tmp_path, "--plugin", "nope.py").startswith("error: --plugin: plug-in file ")
    assert _refused(tmp_path, "--param", "nonode:x:=1").startswith("error: --param 'nonode:x:=1': expected")


# ---- --input: the replay's file checked before the graph starts ------------------------------------------------
@pytest.mark.parametrize("source, name, make, said", [
    ("mcap", "nothere.mcap", None, "no such bag file or directory"),
    ("mcap", "empty.mcap", lambda p: p.write_bytes(b""), "empty file"),
    ("mcap", "notes.mcap", lambda p: p.write_text("not a bag\n"), "not an MCAP file"),
    ("mcap", "nomag.mcap", lambda p: _bag_with(p, ["/probe/imu", "/probe/temperature"]), "no /probe/mag messages"),
    ("mcap", "noimu.mcap", lambda p: _bag_with(p, ["/probe/mag"]), "no /probe/imu and no /probe/mag messages"),
    ("mcap", "folder", lambda p: p.mkdir(), "bag directory holds no .mcap file"),
    ("csv", "nothere.csv", None, "No such file or directory"),
    ("csv", "empty.csv", lambda p: p.write_text(""), "empty file"),
    ("csv", "folder", lambda p: p.mkdir(), "Is a directory"),
    ("csv", "notes.csv", lambda p: p.write_text("a,b,c\n1,2,3\n"), "line 1: the columns are"),
    ("csv", "probe.mcap", lambda p: _bag_with(p, ["/probe/imu"]), "not text"),
    ("csv", "notgzip.csv.gz", lambda p: p.write_text("t_s,ax\n"), "gzip"),
])
def test_a_bad_input_is_refused_naming_the_file_before_any_node_starts(tmp_path, source, name, make, said):
    if make is not None:
        make(tmp_path / name)
    line = _refused(tmp_path, "--source", source, "--input", name)
    assert line.startswith(f"error: --input {name}") and said in line, line


def test_a_bag_without_probe_samples_names_what_it_holds(tmp_path):
    from inclinometer_calib.io.bag import BagWriter, message_encoder

    enc = message_encoder()
    with BagWriter(tmp_path / "temp.mcap") as w:
        ch = w.add_topic("/probe/temperature", "sensor_msgs/msg/Temperature")
        for k in range(3):
            data = enc.encode("sensor_msgs/msg/Temperature", k * 10**9, "probe", {"temperature": 25.0, "variance": 0.0})
            w.write(ch, data, k * 10**9, k * 10**9)
    line = _refused(tmp_path, "--source", "mcap", "--input", "temp.mcap")
    assert "no /probe/imu and no /probe/mag messages" in line and "3 on /probe/temperature" in line, line


def test_an_unreadable_csv_input_is_refused_before_any_node_starts(tmp_path, monkeypatch):
    """The OS's refusal to open the file, one line.  Root reads any file: there the refusal is made
    by the open the check calls (the same OSError the OS would raise); elsewhere by chmod, through
    the whole launcher too."""
    import builtins

    from inclinometer_calib.apps import launcher
    from inclinometer_calib.apps.common import UserError

    p = tmp_path / "locked.csv"
    p.write_text("t_s,ax,ay,az,mx,my,mz\n")
    if os.geteuid() != 0:
        p.chmod(0)
        assert "Permission denied" in _refused(tmp_path, "--source", "csv", "--input", "locked.csv")
    real_open = builtins.open

    def refusing(f, *a, **k):
        if os.fspath(f) == str(p):
            raise PermissionError(13, "Permission denied", str(p))
        return real_open(f, *a, **k)

    monkeypatch.setattr(builtins, "open", refusing)
    with pytest.raises(UserError) as exc:
        launcher.check_csv_input(str(p))
    assert str(exc.value) == f"--input {p}: Permission denied"


def test_the_user_trials_command_with_a_missing_coeffs_file_exits_2_in_one_line(tmp_path, val_bag):
    """The trial's own command line, through the real entry point (``-m``): refused before the
    graph starts.  (``--timeout`` only bounds a launcher that would start it anyway.)"""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_DOMAIN_ID", None)
    proc = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--source", "mcap", "--input",
                           str(val_bag), "--no-calibration", "--coeffs", "nothere.yaml", "--speed", "50", "--no-loop",
                           "--out", "run4", "--timeout", "30"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=180)
    assert proc.returncode == 2, proc.stdout[-3000:]
    assert proc.stdout == "" and proc.stderr == "error: --coeffs nothere.yaml: No such file or directory\n"
    assert not (tmp_path / "run4").exists()


# ---- defence in depth: a node that refuses its parameters anyway ----------------------------------------------
def test_a_node_refusing_its_parameters_is_not_restarted_and_the_last_line_gives_its_reason(tmp_path):
    """A node that exits 2 (nodes.common.run: its parameters or input refused) would fail the same
    way again: not restarted; the last line carries the node's own error, said once."""
    env = dict(os.environ, STAND_IN_REFUSE="correction")
    rc, stdout, stderr, started = _launch(tmp_path, "--out", tmp_path / "run", "--no-calibration", "--no-recorder",
                                          "--no-loop", "--timeout", "60", env=env)
    assert started.count("correction") == 1, stdout[-3000:]
    assert rc == 1, stdout[-3000:]
    last = stdout.splitlines()[-1]
    assert last == ("[launch] exit status 1: the run is not clean: correction refused its parameters or input "
                    "(exit status 2): Invalid parameter value (/x/nothere.yaml) for parameter. Reason: parameter "
                    "coeffs_file: cannot use '/x/nothere.yaml': No such file or directory; not restarted: it would "
                    "fail the same way"), last
    assert "restarting" not in stdout and "died unexpectedly" not in stdout


def test_a_node_whose_callback_failed_mid_run_is_restarted_as_a_node_that_died(tmp_path):
    """Exit status 2 with "error while running" (nodes.common.run: a callback raised, not its
    parameters refused at the start): restarted after the lease as any node that died."""
    env = dict(os.environ, STAND_IN_RUNERR="correction", STAND_IN_END="probe", STAND_IN_WAIT="correction,correction")
    rc, stdout, stderr, started = _launch(tmp_path, "--out", tmp_path / "run", "--no-calibration", "--no-recorder",
                                          "--no-loop", "--timeout", "60", env=env)
    assert started.count("correction") == 2, stdout[-3000:]
    assert "correction died unexpectedly (exit status 2)" in stdout and "refused its parameters" not in stdout

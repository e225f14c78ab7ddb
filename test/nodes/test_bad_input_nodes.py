"""Bad input fed to the nodes: each is flagged or reported (naming what and where), no node
crashes, and the good data around it still comes out.

In-process (callbacks called directly, rclpy initialised in the test's own domain) where DDS adds
nothing; over DDS, with the correction node as a separate process, for NaN samples, magnetic
interference and a near-vertical station; the probe's CSV and MCAP replay as separate processes.
"""
import math
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from rclpy.exceptions import InvalidParameterValueException  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField, Temperature  # noqa: E402

from inclinometer_calib.core.station import Station
from inclinometer_calib.io import bag  # noqa: E402
from inclinometer_calib.calibrate import simulate as sim  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.core.frames import Site  # noqa: E402
from inclinometer_calib.nodes import common as c  # noqa: E402
from inclinometer_calib.nodes.calibration import CalibrationNode  # noqa: E402
from inclinometer_calib.nodes.correction import CorrectionNode  # noqa: E402
from inclinometer_calib.io.probelog import write_csv  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(10)

SITE = Site()
SEED = 5


class Collect:
    """Stands in for a publisher: keeps what is published."""

    def __init__(self):
        self.msgs = []

    def publish(self, msg):
        self.msgs.append(msg)


@pytest.fixture(scope="module")
def coeffs_file(tmp_path_factory):
    probe = sim.build_probe(SEED)
    path = tmp_path_factory.mktemp("coeffs") / "truth.yaml"
    Calibration(acc=probe.acc, mag=probe.mag, probe_id="bad-input", site=SITE).save(path)
    return path


def _grid_log(refs, seed=SEED, duration_s=2.0, move_s=0.5, rate_hz=100.0):
    stations = [Station.planned(sim.orientation_matrix(*r), duration_s, ref=r) for r in refs]
    return sim.run_session(sim.build_probe(seed), SITE, stations, np.random.default_rng(1), rate_hz=rate_hz,
                           move_s=move_s, survey=True)


def _rows(log, ref):
    return np.flatnonzero(np.all(np.isclose(log.ref, ref), axis=1))


def _correction(ros, coeffs_file, *params):
    node = CorrectionNode(parameter_overrides=[Parameter("coeffs_file", value=str(coeffs_file)), *params])
    ros.append(node)
    node.pub_station, node.pub_diag = Collect(), Collect()
    return node


def _feed(node, log):
    for t, g, m in zip(log.t_s.tolist(), log.gravity.tolist(), log.mag.tolist()):
        node.stream.feed(t, tuple(g), tuple(m))
    node.stream.close_hold()    # the end of the data: the open hold closes (no solve with what there is)


# ---- correction node, in-process ------------------------------------------------------------
def test_saturated_and_zero_field_samples_are_dropped_and_named_off_tolerance_stations_flagged(ros, coeffs_file,
                                                                                             capfd):
    refs = [(30.0, 60.0, 0.0), (40.0, 120.0, 0.0), (50.0, 200.0, 120.0), (20.0, 300.0, 240.0),
            (35.0, 10.0, 0.0), (25.0, 90.0, 60.0)]
    log = _grid_log(refs)
    sat = _rows(log, refs[1])
    log.acc[sat, 0] = 2.0 * 9.80665       # x axis stuck at full scale (2 g): implausible, as the CSV reader says
    zero = _rows(log, refs[2])
    log.mag[zero] = 0.0                   # magnetometer reads nothing
    log.acc[_rows(log, refs[4])] *= 1.05  # an accelerometer 5 % off: plausible samples, |G| out of tolerance
    log.mag[_rows(log, refs[5]), 2] += 800.0   # a steel object near the probe
    node = _correction(ros, coeffs_file)
    _feed(node, log)
    st = node.pub_station.msgs
    assert len(st) == 4, [s.drift_deg for s in st]   # no station from the dropped samples
    assert node.engine.counts.implausible == len(sat) + len(zero)
    err = capfd.readouterr().err
    assert "dropped: ax=19.6133 m/s² is saturated (full scale ±19.6133)" in err
    assert "dropped: total field 0 nT is implausible" in err
    for s, r in zip(st[:2], (refs[0], refs[3])):
        assert s.status == 0 and not (s.interference_suspected or s.gravity_out_of_tolerance)
        assert abs(s.drift_deg - r[0]) < 0.1 and abs(s.azimuth_deg - r[1]) < 0.5
    assert st[2].gravity_out_of_tolerance and st[2].status == 2
    assert st[3].interference_suspected and st[3].status == 1 and st[3].delta_b_nt > 300
    # diagnostics name what is wrong, per station
    diag = node.pub_diag.msgs
    g_diag = {s.name: s for s in diag[2].status}
    assert g_diag["inclinometer_calib: total gravity"].level == DiagnosticStatus.ERROR
    assert "total gravity" in g_diag["inclinometer_calib: total gravity"].message
    assert f"station {st[2].station_id}" in g_diag["inclinometer_calib: station"].message
    b_diag = {s.name: s for s in diag[3].status}
    assert b_diag["inclinometer_calib: total field"].level == DiagnosticStatus.WARN
    assert max(s.level for s in diag[0].status) == DiagnosticStatus.OK


def test_non_monotonic_stamps_and_absent_field_are_reported(ros, coeffs_file, capfd):
    refs = [(30.0, 60.0, 0.0), (45.0, 150.0, 0.0)]
    log = _grid_log(refs)
    node = _correction(ros, coeffs_file)

    def send(k, imu=True, mag=True, t=None):
        t = log.t_s[k] if t is None else t
        mi, mm = Imu(), MagneticField()
        c.set_stamp(mi.header.stamp, t)
        mm.header.stamp = mi.header.stamp
        mi.linear_acceleration.x, mi.linear_acceleration.y, mi.linear_acceleration.z = log.acc[k].tolist()
        mm.magnetic_field.x, mm.magnetic_field.y, mm.magnetic_field.z = (log.mag[k] * 1e-9).tolist()
        if imu:
            node.stream._on_imu(serialize_message(mi), None)
        if mag:
            node.stream._on_mag(serialize_message(mm))

    n = len(log)
    for k in range(n // 2):
        send(k)
    for k in range(10, 20):          # a burst of old stamps (a clock that jumped back)
        send(k)
    for k in range(n // 2, n):
        send(k)
    assert node.engine.pairer.out_of_order == 10 and node.engine.counts.out_of_order == 10
    node.stream.close_hold()
    st = node.pub_station.msgs
    assert len(st) == 2 and all(s.status == 0 for s in st)
    assert [round(s.drift_deg) for s in st] == [30, 45]
    err = capfd.readouterr().err
    assert "non-monotonic timestamps, dropped" in err and "/probe/mag: sample stamped t=0.100 s" in err

    # absent field: imu keeps coming, no magnetometer sample pairs with it
    node.stream._on_timer()  # the 1 Hz check (on the stream driver's timer): pairs have been coming
    assert "without a /probe/mag partner" not in capfd.readouterr().err
    waiting = node.engine.pairer.waiting
    for k in range(200):
        send(0, mag=False, t=log.t_s[-1] + 1.0 + 0.01 * k)
    node.stream._on_timer()          # within the second: not checked again yet
    assert "without a /probe/mag partner" not in capfd.readouterr().err
    node.stream._pairing_checked -= 1.0   # a second later
    node.stream._on_timer()
    assert node.engine.pairer.waiting == waiting + 200      # said within a second, not after the buffer fills
    err = capfd.readouterr().err
    assert "without a /probe/mag partner" in err
    assert len(node.pub_station.msgs) == 2  # nothing made up from the imu alone


def test_nan_samples_counted_and_named(ros, coeffs_file, capfd):
    refs = [(30.0, 60.0, 0.0), (45.0, 150.0, 0.0)]
    log = _grid_log(refs, duration_s=3.0)
    rows = _rows(log, refs[0])
    log.acc[rows[150], 2] = np.nan
    log.mag[rows[151], 0] = np.inf
    node = _correction(ros, coeffs_file)
    _feed(node, log)
    assert node.engine.counts.nonfinite == 2
    err = capfd.readouterr().err
    assert "non-finite sample at t=" in err and "/probe/imu" in err
    st = node.pub_station.msgs
    # the NaN split the first station in two halves (each > 1 s); none carries a NaN
    assert len(st) == 3
    assert all(s.status == 0 and math.isfinite(s.drift_deg) for s in st)


# ---- coefficient YAML given to the correction node ----------------------------------------
def _edited(src, tmp_path, name, edit):
    rec = yaml.safe_load(open(src).read())
    edit(rec)
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(rec, sort_keys=False))
    return p


BAD_YAML = {
    "wrong_shape": (lambda r: r["accelerometer"].__setitem__("correction_matrix", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
                    "shape"),
    "wrong_units": (lambda r: r["magnetometer"]["units"].__setitem__("bias", "T"), "units"),
    "unknown_version": (lambda r: r.__setitem__("format_version", 99), "format_version 99"),
    "hand_edited": (lambda r: r["accelerometer"]["offset"].__setitem__(0, 0.5), "hand-edited"),
    "ill_conditioned": (lambda r: r["magnetometer"]["parameters"].update(scale_x=1e-9), "ill-conditioned"),
    "not_yaml": (None, "not valid YAML"),
}


@pytest.mark.parametrize("case", sorted(BAD_YAML))
def test_malformed_coefficient_yaml_is_refused(ros, coeffs_file, tmp_path, case):
    edit, needle = BAD_YAML[case]
    if edit is None:
        bad = tmp_path / "bad.yaml"
        bad.write_text("format: [unclosed\n")
    else:
        keys = yaml.safe_load(open(coeffs_file).read())
        assert "accelerometer" in keys and "magnetometer" in keys, list(keys)
        bad = _edited(coeffs_file, tmp_path, case, edit)
    with pytest.raises(InvalidParameterValueException, match="cannot use") as info:
        CorrectionNode(parameter_overrides=[Parameter("coeffs_file", value=str(bad))])
    assert needle in str(info.value) and str(bad) in str(info.value)
    # a running node refuses it too, and keeps its coefficients
    node = _correction(ros, coeffs_file)
    before = node.calibration.id
    res = node.set_parameters([Parameter("coeffs_file", value=str(bad))])[0]
    assert not res.successful and needle in res.reason
    assert node.calibration.id == before and node.engine.counts.records == 1   # nothing else was taken


def test_malformed_coefficient_yaml_exits_2(ros_env, coeffs_file, tmp_path):
    bad = _edited(coeffs_file, tmp_path, "v99", BAD_YAML["unknown_version"][0])
    proc = subprocess.run([sys.executable, "-m", "inclinometer_calib.nodes.correction", "--ros-args",
                           "-p", f"coeffs_file:={bad}"], env=ros_env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "error:" in last and "format_version 99" in last and str(bad) in last


# ---- a record's plug-in: loaded only from the node's plugins parameter ---------------------
MARKED_PLUGIN = """import pathlib

pathlib.Path(__file__).with_name("executed.marker").write_text("this plug-in ran")

from inclinometer_calib.core.effects import T_REF_C, Effect, ParamSpec


class NodeCubeBias(Effect):
    name = "cube_bias_node"
    stage = "output"
    specs = (ParamSpec("c3", {"acc": "m/s^2/degC^3", "mag": "nT/degC^3"}, {"acc": 1e-6, "mag": 0.01}),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["c3"] * ((ctx.temperature_c - T_REF_C) ** 3)[:, None]
"""


@pytest.fixture
def plugin_record(coeffs_file, tmp_path, monkeypatch):
    """(record file, its Calibration, plug-in file): the test probe's record plus a plug-in effect;
    then, as in a new process, nothing registered, imported or named, no marker."""
    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core import plugins

    monkeypatch.setattr(plugins, "_NAMED", {}, raising=False)
    plug = tmp_path / "cube.py"
    plug.write_text(MARKED_PLUGIN)
    assert plugins.load_plugin(plug) == ["cube_bias_node"]
    base = Calibration.load(coeffs_file)
    cal = Calibration(base.model.with_effect(fx.make_effect("cube_bias_node", "mag", c3=[1e-3, 0, 0])),
                      probe_id=base.probe_id, site=base.site)
    rec = tmp_path / "rec.yaml"
    cal.save(rec)
    fx.CATALOGUE.pop("cube_bias_node")
    for m in [m for m, mod in list(sys.modules.items()) if getattr(mod, "__file__", None) == str(plug)]:
        del sys.modules[m]
    plugins._NAMED.clear()
    plug.with_name("executed.marker").unlink()
    yield rec, cal, plug
    fx.CATALOGUE.pop("cube_bias_node", None)


def test_a_record_whose_plugin_the_node_was_not_given_is_refused_from_file_and_topic_without_running_it(
        ros, coeffs_file, plugin_record, capfd):
    from inclinometer_calib.msg import CalibrationCoefficients

    rec, cal, plug = plugin_record
    with pytest.raises(InvalidParameterValueException, match="cannot use") as info:
        CorrectionNode(parameter_overrides=[Parameter("coeffs_file", value=str(rec))])
    assert "effect 'cube_bias_node' comes from the plug-in" in str(info.value) and "plugins" in str(info.value)
    # on the topic: reported as any record that fails its checks, the node keeps the record it had
    node = _correction(ros, coeffs_file)
    before = node.calibration.id
    capfd.readouterr()
    node._on_coefficients(c.coefficients_to_msg(cal, CalibrationCoefficients))
    err = capfd.readouterr().err
    assert "coefficients rejected, keeping the previous ones" in err and "which is not named" in err
    assert node.calibration.id == before
    assert not plug.with_name("executed.marker").exists()


def test_a_record_whose_plugin_the_node_was_given_with_its_hash_is_applied(ros, plugin_record):
    rec, cal, plug = plugin_record
    node = _correction(ros, rec, Parameter("plugins", value=[str(plug)]))
    assert node.calibration.id == cal.id
    assert plug.with_name("executed.marker").exists()


# ---- calibration node, in-process -----------------------------------------------------------
def _cal_log(pieces, rate_hz=100.0):
    """pieces: (pose or (drift, azimuth, toolface), duration_s, wobble_mps2)"""
    probe = sim.build_probe(SEED)
    stations = []
    for what, dur, _ in pieces:
        rot = sim.pose_matrix(what) if isinstance(what, int) else sim.orientation_matrix(*what)
        stations.append(Station.planned(rot, dur, pose=what if isinstance(what, int) else 0))
    log = sim.run_session(probe, SITE, stations, np.random.default_rng(2), rate_hz=rate_hz, move_s=1.0)
    # wobble: the probe moved during a capture (slow sway, within the detector's band)
    starts = np.flatnonzero(np.diff(np.r_[0, (log.pose > 0).astype(int)]) == 1)
    k = 0
    for what, dur, wobble in pieces:
        if not isinstance(what, int):
            continue
        i0 = starts[k]
        k += 1
        if wobble:
            n = int(dur * rate_hz)
            log.acc[i0:i0 + n, 0] += wobble * np.sin(2 * np.pi * 1.0 * np.arange(n) / rate_hz)
    return log


def _cal_node(ros):
    node = CalibrationNode(parameter_overrides=[Parameter("detector.noise_acc", value=0.01)])
    ros.append(node)
    node.pub_status, node.pub_coeffs = Collect(), Collect()
    return node


def test_calibration_warns_and_still_solves(ros, capfd):
    poses = list(range(1, 13))
    pieces = ([(1, 2.0, 0), (2, 2.0, 0), (1, 2.0, 0),           # repeated
               (3, 0.6, 0),                                      # too short
               ((45.0, 30.0, 0.0), 2.0, 0), (3, 2.0, 0),         # not one of the twelve
               (4, 2.0, 0.04),                                   # moved during the capture
               (6, 2.0, 0)]                                      # out of order (4 expected)
              + [(p, 2.0, 0) for p in poses[3:] if p != 6])
    node = _cal_node(ros)
    _feed(node, _cal_log(pieces))
    w = "\n".join(node.session.warnings)
    assert "pose 1 again, out of sequence" in w and "ignored" in w
    assert "pose 3" in w and "capture too short" in w
    assert "is not one of the twelve poses" in w
    assert "pose 4 at" in w and "vibration or motion during the hold" in w and "station not used" in w
    assert "pose 6 at" in w and "out of order (expected pose 4 next)" in w
    assert node.session.state == "done" and len(node.pub_coeffs.msgs) == 1
    status = node.pub_status.msgs[-1]
    assert status.state == "done" and list(status.pending) == []
    assert any("out of sequence" in x for x in status.warnings)
    err = capfd.readouterr().err
    assert "vibration or motion during the hold" in err and "[WARN]" in err   # logged, at WARNING


def test_calibration_missing_pose_keeps_waiting(ros):
    node = _cal_node(ros)
    _feed(node, _cal_log([(p, 2.0, 0) for p in range(1, 13) if p != 7]))
    node._publish_status()
    st = node.pub_status.msgs[-1]
    assert st.state == "collecting" and list(st.pending) == [7] and not node.pub_coeffs.msgs
    assert "11 of 12 poses captured" in st.message


# ---- over DDS: NaN, interference and near-vertical through a correction process -------------
def test_nan_interference_near_vertical_over_dds(ros_env, coeffs_file, tmp_path):
    from inclinometer_calib.msg import SurveyStation

    refs = [(30.0, 60.0, 0.0), (40.0, 100.0, 0.0), (0.1, 200.0, 0.0), (35.0, 250.0, 120.0), (25.0, 320.0, 0.0)]
    log = _grid_log(refs, duration_s=2.5)
    nan_rows = _rows(log, refs[0])
    log.acc[nan_rows[120], 1] = np.nan
    interf = _rows(log, refs[3])
    log.mag[interf] += np.array([0.0, 0.0, 1500.0])  # a steel collar: +1500 nT along the tool axis

    out = open(tmp_path / "correction.log", "w+")
    proc = subprocess.Popen([sys.executable, "-m", "inclinometer_calib.nodes.correction", "--ros-args",
                             "-p", f"coeffs_file:={coeffs_file}", "-p", "use_topic:=false",
                             "-p", "qos.reliability:=reliable", "-p", "qos.depth:=10000", "-p", "idle_flush_s:=0.5"],
                            env=ros_env, stdout=out, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node("bad_input_feeder")
    stations = []
    try:
        # reliable, and histories deeper than the log's 1 500 samples: none is dropped however far the
        # node falls behind (the verdict must not depend on the machine's speed)
        qos = c.sensor_qos(10000, "reliable")
        pub_imu = node.create_publisher(Imu, c.TOPIC_IMU, qos)
        pub_mag = node.create_publisher(MagneticField, c.TOPIC_MAG, qos)
        pub_temp = node.create_publisher(Temperature, c.TOPIC_TEMPERATURE, qos)
        node.create_subscription(SurveyStation, c.TOPIC_STATION, stations.append, c.reliable_qos(100))
        stop = threading.Event()
        th = threading.Thread(target=lambda: [rclpy.spin_once(node, timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                              daemon=True)
        th.start()
        end = time.monotonic() + 20
        while time.monotonic() < end and (pub_imu.get_subscription_count() < 1 or pub_mag.get_subscription_count() < 1
                                          or node.count_publishers(c.TOPIC_STATION) < 1):
            assert proc.poll() is None, open(out.name).read()
            time.sleep(0.05)
        time.sleep(0.5)
        mi, mm, mt = Imu(), MagneticField(), Temperature()
        for k, (t, f, m) in enumerate(zip(log.t_s.tolist(), log.acc.tolist(), (log.mag * 1e-9).tolist())):
            c.set_stamp(mi.header.stamp, t)
            mm.header.stamp = mt.header.stamp = mi.header.stamp
            mi.linear_acceleration.x, mi.linear_acceleration.y, mi.linear_acceleration.z = f
            mm.magnetic_field.x, mm.magnetic_field.y, mm.magnetic_field.z = m
            mt.temperature = 25.0
            pub_imu.publish(mi)
            pub_mag.publish(mm)
            pub_temp.publish(mt)
            if k % 100 == 99:
                time.sleep(0.02)  # about 5x real time: a loaded CI machine must keep up
        end = time.monotonic() + 30
        while time.monotonic() < end and len(stations) < 6:
            time.sleep(0.05)
        time.sleep(0.3)
        stop.set()
        th.join(2)
        assert proc.poll() is None, "the correction node died"
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        if proc.poll() is None:
            proc.send_signal(2)
        proc.wait(15)
    text = open(out.name).read()
    assert proc.returncode == 0, text
    assert "non-finite sample at t=" in text and "/probe/imu" in text
    # station 0 is split by the NaN; then 40 deg, near-vertical, interference, 25 deg
    drifts = [round(s.drift_deg, 1) for s in stations]
    assert len(stations) == 6, drifts
    by_ref = {}  # by set drift (no /probe/reference here)
    for s in stations:
        by_ref.setdefault(min((30.0, 40.0, 0.1, 35.0, 25.0), key=lambda r: abs(r - s.drift_deg)), []).append(s)
    assert len(by_ref[30.0]) == 2 and all(s.status == 0 for s in by_ref[30.0])
    for r in (40.0, 25.0):
        (s,) = by_ref[r]
        assert s.status == 0 and abs(s.drift_deg - r) < 0.1 and not s.interference_suspected
    (v,) = by_ref[0.1]
    assert v.azimuth_undefined and math.isnan(v.azimuth_deg) and v.toolface_type == SurveyStation.TOOLFACE_MAGNETIC
    (i,) = by_ref[35.0]
    assert i.interference_suspected and (abs(i.delta_b_nt) > 300 or abs(i.delta_dip_deg) > 0.25)
    assert math.isfinite(i.azimuth_deg)  # reported, but flagged


# ---- probe replay: CSV with bad rows, truncated MCAP with foreign topics --------------------
def _run_probe(env, *params, timeout=60):
    args = [sys.executable, "-m", "inclinometer_calib.nodes.probe", "--ros-args", "-p", "speed:=100.0",
            "-p", "start_delay_s:=0.0"]
    for p in params:
        args += ["-p", p]
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=timeout)


def test_probe_csv_replay_reports_rejected_rows(ros_env, tmp_path):
    log = _grid_log([(30.0, 60.0, 0.0), (45.0, 150.0, 0.0)], duration_s=1.5)
    path = tmp_path / "log.csv"
    write_csv(path, log)
    lines = path.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    cols = header.split(",")
    ax, t_col = cols.index("ax"), cols.index("t_s")

    def edit(i, col, value):
        parts = rows[i].split(",")
        parts[col] = value
        rows[i] = ",".join(parts)

    edit(10, ax, "nan")
    edit(20, ax, "abc")
    edit(30, t_col, "0.0")  # time goes back
    path.write_text("\n".join([header] + rows) + "\n")
    proc = _run_probe(ros_env, "source:=csv", f"path:={path}")
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout + proc.stderr
    assert f"{path}: row" in text and "(line 12)" in text and "(line 22)" in text and "(line 32)" in text
    assert "3 rows rejected" in text
    assert f"end of script: {len(rows) - 3} samples published" in text


def test_probe_mcap_replay_truncated_with_unknown_topics(ros_env, tmp_path):
    from std_msgs.msg import String

    src = tmp_path / "rec.mcap"
    w = bag.BagWriter(src, max_chunk_s=0.25, compression="none")
    ch_imu = w.add_topic(c.TOPIC_IMU, "sensor_msgs/msg/Imu")
    ch_mag = w.add_topic(c.TOPIC_MAG, "sensor_msgs/msg/MagneticField")
    ch_foo = w.add_topic("/foo/chatter", "std_msgs/msg/String")
    ch_ref = w.add_topic(c.TOPIC_REFERENCE, "std_msgs/msg/String")  # mislabelled: not a Vector3Stamped
    n = 400
    for k in range(n):
        t = 1.0 + 0.01 * k
        ns = int(round(t * 1e9))
        mi, mm = Imu(), MagneticField()
        c.set_stamp(mi.header.stamp, t)
        mm.header.stamp = mi.header.stamp
        mi.linear_acceleration.z = -9.80665
        mm.magnetic_field.x, mm.magnetic_field.z = 35e-6, 35e-6
        w.write(ch_imu, serialize_message(mi), ns, ns)
        w.write(ch_mag, serialize_message(mm), ns, ns)
        if k % 50 == 0:
            w.write(ch_foo, serialize_message(String(data="hello")), ns, ns)
            w.write(ch_ref, serialize_message(String(data="not a vector")), ns, ns)
    w.close()
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * 0.6)])  # the recorder was killed mid-chunk

    proc = _run_probe(ros_env, "source:=mcap", f"path:={cut}")
    text = proc.stdout + proc.stderr
    assert proc.returncode == 3, text  # replayed what it could, and says the input was damaged
    assert f"{cut}: the input was damaged" in text and "exit status 3" in text
    assert "/foo/chatter (std_msgs/msg/String) is not replayed" in text
    assert f"{c.TOPIC_REFERENCE} has type std_msgs/msg/String, expected geometry_msgs/msg/Vector3Stamped" in text
    assert str(cut) in text and "truncated or corrupt" in text and "byte offset" in text
    got = [int(x) for x in re.findall(r"end of script: (\d+) samples published", text)]
    assert got and 0.3 * n < got[0] < 0.7 * n, text  # the readable part, and only that

    # an intact bag replays completely
    proc = _run_probe(ros_env, "source:=mcap", f"path:={src}")
    assert proc.returncode == 0 and f"end of script: {n} samples published" in proc.stdout + proc.stderr

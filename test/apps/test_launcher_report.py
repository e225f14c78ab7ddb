"""The launcher's ROS-free parts: honest labels in the run report and summary, the choice of the
run's ROS_DOMAIN_ID (a free one, or exactly the one asked for and refused while another run holds
it), the restart delay read from the nodes' Fast DDS profile, the watch loop's restarts that
fall due at the end of a run, and the stacks of a node that hangs at its stop (on stand-in
processes).  Nothing here starts ROS."""
import math
import os
import signal
import sys
import threading
import time

import pytest

from inclinometer_calib.apps import launcher, rosenv
from inclinometer_calib.io import surveystation
from inclinometer_calib.io.bag import read_bag

NAN = float("nan")


def _station(station_id, coefficients_id, **kw):
    s = {"station_id": station_id, "coefficients_id": coefficients_id, "drift_deg": 30.2, "azimuth_deg": 61.0,
         "reference_drift_deg": 30.0, "reference_azimuth_deg": 60.0, "delta_b_nt": -850.0, "delta_dip_deg": 1.2,
         "status": 1, "interference_suspected": True, "azimuth_undefined": False}
    s.update(kw)
    return s


def _rows(report):
    return [ln for ln in report.splitlines() if ln.startswith("| ") and not ln.startswith("| id")]


def test_stations_before_the_calibration_are_labelled_uncorrected_without_qc_flags():
    stations = [_station(0, ""),                                             # a stand pose, raw
                _station(1, "abc123", status=0, interference_suspected=False),
                _station(2, "abc123", status=1)]                              # corrected and off: flagged
    raw, good, flagged = _rows(launcher.format_report({}, [], None, stations))
    assert raw.endswith("| uncorrected (before calibration) |") and "interference" not in raw
    assert raw.split("|")[2].strip() == launcher.DASH  # no coefficients
    assert good.endswith("| ok |")
    assert flagged.endswith("| warn (interference_suspected) |")


def test_missing_values_print_as_a_dash_not_nan():
    stations = [_station(0, "", reference_drift_deg=NAN, reference_azimuth_deg=NAN, azimuth_deg=NAN)]
    summary = {"stations_recorded": 1, "raw_stations": {"before calibration": 1}, "coefficient_messages": 1, "coefficients_id": "abc123",
               "survey": {"stations": 1, "drift_rms_deg": 0.001, "drift_max_abs_deg": 0.001,
                          "azimuth_rms_deg": NAN, "azimuth_max_abs_deg": NAN, "azimuth_stations": 0,
                          "toolface_rms_deg": NAN, "status_counts": {"0": 0, "1": 1, "2": 0},
                          "max_abs_delta_b_nt": 3.0, "max_abs_delta_dip_deg": 0.01, "max_abs_delta_g_mps2": 0.0}}
    lines = launcher.format_summary(summary)
    report = launcher.format_report(summary, lines, None, stations)
    for text in ("\n".join(lines), report):
        assert "nan" not in text.lower(), text
    assert f"azimuth RMS {launcher.DASH} max {launcher.DASH} deg" in "\n".join(lines)
    (row,) = _rows(report)
    cells = [x.strip() for x in row.strip("|").split("|")]
    assert cells[2:4] == [launcher.DASH, launcher.DASH] and cells[5] == launcher.DASH and cells[7] == launcher.DASH
    assert launcher._num(math.inf, ".3f") == launcher.DASH and launcher._num(None, ".3f") == launcher.DASH


@pytest.fixture
def no_domain(monkeypatch):
    for key in ("ROS_DOMAIN_ID", rosenv.RESERVED_BY_PARENT):
        monkeypatch.delenv(key, raising=False)


def test_without_a_domain_the_launcher_reserves_a_free_one(no_domain):
    args = launcher.parse_args([])
    a_id, a_lock, how = launcher.reserve_run_domain(args, {})
    b_id, b_lock, _ = launcher.reserve_run_domain(args, {})
    try:
        assert a_id != b_id and rosenv.DOMAIN_ID_MIN <= a_id <= rosenv.DOMAIN_ID_MAX
        assert "free domain" in how
    finally:
        a_lock.close()
        b_lock.close()


def test_an_explicit_domain_held_by_another_run_is_refused_with_status_2(no_domain, tmp_path, capsys):
    domain_id, lock = rosenv.reserve_domain_id()  # "another run" holds it
    try:
        out = tmp_path / "run"
        assert launcher.main(["--out", str(out), "--domain-id", str(domain_id)]) == 2
        err = capsys.readouterr().err
        assert f"ROS_DOMAIN_ID {domain_id} is in use by another inclinometer_calib run" in err
        assert "Give another --domain-id" in err and not out.exists()
        # the same id from the environment is refused the same way ...
        with pytest.raises(rosenv.DomainInUse):
            launcher.reserve_run_domain(launcher.parse_args([]), {"ROS_DOMAIN_ID": str(domain_id)})
        # ... unless the environment says the parent holds it for us (tests, benchmarks)
        env = {"ROS_DOMAIN_ID": str(domain_id), rosenv.RESERVED_BY_PARENT: str(domain_id)}
        assert launcher.reserve_run_domain(launcher.parse_args([]), env)[:2] == (domain_id, None)
    finally:
        lock.close()
    free_again = rosenv.reserve_this_domain_id(domain_id)  # released with its holder
    free_again.close()


def test_a_bag_without_stations_coefficients_or_status_gives_an_empty_summary(tmp_path):
    """Only /probe/* topics (a replayed probe log) and /clock: nothing for the summary to read —
    rosbags reads an empty connection list as every connection, which made it decode a Clock or an
    Imu as a coefficient record."""
    pytest.importorskip("rosbags")
    pytest.importorskip("mcap")
    import numpy as np
    from rosbags.typesys import Stores, get_typestore

    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.io.bag import BagWriter
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.correct.reprocess import write_probe_bag

    out = tmp_path / "run"
    out.mkdir()
    log = sim.run_session(sim.build_probe(1), Site(), sim.stand_grid_session(duration_s=1.0),
                          np.random.default_rng(0), rate_hz=50)
    write_probe_bag(log, out / "survey.mcap")                          # /probe/imu, mag, temperature, reference
    ts = get_typestore(Stores.ROS2_JAZZY)
    Clock, Time = ts.types["rosgraph_msgs/msg/Clock"], ts.types["builtin_interfaces/msg/Time"]
    with BagWriter(out / "survey_1.mcap") as w:                        # a second part with only /clock
        cid = w.add_topic("/clock", "rosgraph_msgs/msg/Clock")
        for k in range(5):
            w.write(cid, bytes(ts.serialize_cdr(Clock(clock=Time(sec=k, nanosec=0)), "rosgraph_msgs/msg/Clock")),
                    1_700_000_000_000_000_000 + k)
    assert read_bag(out / "survey.mcap") == ([], [], None)
    assert read_bag(out / "survey_1.mcap") == ([], [], None)
    said = []
    summary = launcher.summarize_run(str(out), print_fn=said.append, loop=False)
    assert summary["stations_recorded"] == 0 and summary["coefficient_messages"] == 0
    assert "calibration_status" not in summary and "coefficients_id" not in summary
    assert [p["file"] for p in summary["bag_parts"]] == ["survey.mcap", "survey_1.mcap"]
    assert "bag: 0 survey stations, 0 coefficient message(s)" in said
    assert (out / "summary.json").is_file() and (out / "report.md").is_file()


def _recorded_station(**fields):
    """A SurveyStation as rosbags reads it from a bag recorded before azimuth_true_deg existed: the
    fields surveystation.from_msg reads, no azimuth_true_deg."""
    from types import SimpleNamespace

    names = ("station_id", "drift_deg", "azimuth_deg", "toolface_deg", "gravity_toolface_deg", "magnetic_toolface_deg",
             "total_gravity_mps2", "total_field_nt", "dip_deg", "delta_g_mps2", "delta_b_nt", "delta_dip_deg",
             "status", "azimuth_undefined", "interference_suspected", "coefficients_id", "reference_drift_deg",
             "reference_azimuth_deg", "reference_toolface_deg", "samples_averaged", "duration_s", "temperature_c",
             "moved_during_capture", "model_misfit", "model_diagnosis", "measured_depth_m", "tvd_m", "north_m",
             "east_m", "dls_deg_per_30m", "azimuth_magnetic_deg", "azimuth_grid_deg", "azimuth_reference")
    values = {k: 0 for k in names}
    values.update(fields)
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=0)), warnings=[], **values)


def test_a_station_recorded_before_the_one_north_is_read_along_its_positions_north():
    # then: azimuth true, north/east along grid north (the site had a grid)
    old = surveystation.from_msg(_recorded_station(azimuth_deg=40.0, azimuth_magnetic_deg=37.5, azimuth_grid_deg=39.2,
                                                  azimuth_reference="true", reference_azimuth_deg=40.25))
    assert old["azimuth_reference"] == "grid" and old["azimuth_deg"] == 39.2 and old["azimuth_true_deg"] == 40.0
    assert old["reference_azimuth_deg"] == pytest.approx(40.25 - 0.8)      # the reference along grid north too
    # no grid: true (or magnetic) as recorded
    plain = surveystation.from_msg(_recorded_station(azimuth_deg=40.0, azimuth_magnetic_deg=37.5, azimuth_grid_deg=NAN,
                                                    azimuth_reference="true", reference_azimuth_deg=40.25))
    assert plain["azimuth_reference"] == "true" and plain["azimuth_deg"] == 40.0 and plain["azimuth_true_deg"] == 40.0
    mag = surveystation.from_msg(_recorded_station(azimuth_deg=37.5, azimuth_magnetic_deg=37.5, azimuth_grid_deg=NAN,
                                                  azimuth_reference="magnetic"))
    assert mag["azimuth_reference"] == "magnetic" and math.isnan(mag["azimuth_true_deg"])


def test_the_nodes_get_the_packages_fast_dds_profile_unless_the_user_names_one(tmp_path):
    """The launcher's nodes read config/fastdds.xml (reliable writers' heartbeat 0.1 s, participant
    announcements 0.5 s) through both variables Fast DDS 2 and 3 read; a profiles file the user's
    environment names is kept, and a config directory without one leaves Fast DDS's defaults."""
    import xml.etree.ElementTree as ET

    cfg = launcher.config_dir()
    env = {}
    said = launcher.dds_profile_env(env, cfg)
    path = os.path.join(cfg, launcher.DDS_PROFILE)
    assert all(env[v] == path for v in launcher.DDS_PROFILE_VARS) and path in said
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(path).getroot()
    hb = root.find("p:data_writer[@is_default_profile='true']/p:times/p:heartbeatPeriod", ns)
    lease = root.find("p:participant[@is_default_profile='true']/p:rtps/p:builtin/p:discovery_config/"
                      "p:leaseAnnouncement", ns)
    assert (int(hb.find("p:sec", ns).text), int(hb.find("p:nanosec", ns).text)) == (0, 100_000_000)
    assert (int(lease.find("p:sec", ns).text), int(lease.find("p:nanosec", ns).text)) == (0, 500_000_000)
    mine = {"FASTDDS_DEFAULT_PROFILES_FILE": "/rig/dds.xml"}
    assert "/rig/dds.xml (from FASTDDS_DEFAULT_PROFILES_FILE)" in launcher.dds_profile_env(mine, cfg)
    assert mine == {"FASTDDS_DEFAULT_PROFILES_FILE": "/rig/dds.xml"}
    bare = {}
    assert launcher.dds_profile_env(bare, str(tmp_path)) == "Fast DDS defaults" and bare == {}


def test_a_node_that_died_is_restarted_once_the_graph_has_forgotten_it(tmp_path):
    """The restart waits for the dead participant's lease (and a second): the lease of the default
    participant profile in the profiles file the nodes read (ours: 5 s; a rig's own), Fast DDS's
    20 s without one; no wait under another RMW or with an infinite lease."""
    env = {}
    launcher.dds_profile_env(env, launcher.config_dir())
    assert launcher.participant_lease_s(env) == 5.0 and launcher.restart_delay_s(env) == 6.0
    assert launcher.participant_lease_s({}) == launcher.FASTDDS_DEFAULT_LEASE_S == 20.0
    assert launcher.restart_delay_s(dict(env, RMW_IMPLEMENTATION="rmw_cyclonedds_cpp")) == 0.0

    def rig(lease_xml):
        path = tmp_path / f"rig{len(list(tmp_path.iterdir()))}.xml"
        path.write_text(
            '<?xml version="1.0"?><dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"><profiles>'
            '<participant profile_name="other"><rtps><builtin><discovery_config><leaseDuration><sec>99</sec>'
            '</leaseDuration></discovery_config></builtin></rtps></participant>'
            '<participant profile_name="rig" is_default_profile="true"><rtps><builtin><discovery_config>'
            f'{lease_xml}</discovery_config></builtin></rtps></participant></profiles></dds>')
        rig.path = str(path)
        return launcher.participant_lease_s({"FASTRTPS_DEFAULT_PROFILES_FILE": str(path)})

    assert rig("<leaseDuration><sec>3</sec><nanosec>250000000</nanosec></leaseDuration>") == 3.25
    for infinite in ("<sec>DURATION_INFINITY</sec>", "<sec>DURATION_INFINITE_SEC</sec>",
                     "<sec>5</sec><nanosec>DURATION_INFINITE_NSEC</nanosec>", "DURATION_INFINITY"):
        assert rig(f"<leaseDuration>{infinite}</leaseDuration>") is None, infinite
    assert rig("") == 20.0                         # the default profile sets none: Fast DDS's
    rig("<leaseDuration><sec>3</sec></leaseDuration>")
    assert launcher.participant_lease_s({"FASTRTPS_DEFAULT_PROFILES_FILE": rig.path,
                                         "RMW_IMPLEMENTATION": "rmw_fastrtps_dynamic_cpp"}) == 3.0
    # named only where Fast DDS 3 looks: Jazzy's Fast DDS 2 may run on its default, 20 s
    assert launcher.participant_lease_s({"FASTDDS_DEFAULT_PROFILES_FILE": rig.path}) == 20.0
    bad = tmp_path / "bad.xml"
    bad.write_text("<dds><profiles>")
    assert launcher.participant_lease_s({"FASTDDS_DEFAULT_PROFILES_FILE": str(bad)}) == 20.0


#: A stand-in for a node process (argv: its name, the folder it reports to): it writes the
#: monotonic time of its start to ``<name>.starts``; the correction dies (exit 1) at its first
#: start, writing ``correction.died``; the probe ends (exit 0) once the correction has died, or
#: runs like the others until SIGINT.  CLOCK_MONOTONIC is the machine's: the launcher's and the
#: stand-ins' times compare.
STAND_IN = r"""
import os, signal, sys, time
name, d = sys.argv[1], sys.argv[2]
first = not os.path.exists(os.path.join(d, name + ".starts"))
with open(os.path.join(d, name + ".starts"), "a") as f:
    f.write(f"{time.monotonic()}\n")
if name == "correction" and first:
    with open(os.path.join(d, "correction.died"), "w") as f:
        f.write(f"{time.monotonic()}\n")
    sys.exit(1)
signal.signal(signal.SIGINT, lambda *_: sys.exit(0))
while True:
    if name == "probe" and os.environ.get("STAND_IN_PROBE_ENDS") and os.path.exists(os.path.join(d, "correction.died")):
        time.sleep(0.2)
        sys.exit(0)
    time.sleep(0.05)
"""


def _stand_in_graph(tmp_path, monkeypatch, lease_s, *argv):
    """``run_graph`` on stand-in processes (:data:`STAND_IN`), no ROS: a probe and a correction
    node, the nodes' Fast DDS profile giving ``lease_s``."""
    profile = tmp_path / "dds.xml"
    profile.write_text(
        '<?xml version="1.0"?><profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">'
        '<participant profile_name="p" is_default_profile="true"><rtps><builtin><discovery_config>'
        f'<leaseDuration><sec>{lease_s}</sec></leaseDuration></discovery_config></builtin></rtps></participant>'
        '</profiles>')
    monkeypatch.setattr(launcher, "node_command",
                        lambda name, params, cfg: [sys.executable, "-c", STAND_IN, name, str(tmp_path)])
    out = tmp_path / "run"
    out.mkdir()
    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(profile))
    env.pop("RMW_IMPLEMENTATION", None)
    args = launcher.parse_args(["--no-calibration", "--no-recorder", "--drain", "0.5", *argv])
    result = launcher.run_graph(args, str(out), env)
    starts = {n: [float(x) for x in (tmp_path / f"{n}.starts").read_text().split()] for n in ("probe", "correction")}
    return result, starts, (out / "launch.log").read_text()


def test_a_restart_due_after_the_probe_has_ended_is_made_and_the_drain_waits_for_it(tmp_path, monkeypatch):
    """The correction dies, then the probe ends before the restart is due (the lease: 1 s, and a
    second): the restart is still made, counted, and the drain waits for the restarted node
    (RESTART_DRAIN_S: here 1 s) before the graph stops."""
    monkeypatch.setattr(launcher, "RESTART_DRAIN_S", 1.0)
    monkeypatch.setenv("STAND_IN_PROBE_ENDS", "1")
    result, starts, log = _stand_in_graph(tmp_path, monkeypatch, 1)
    died = float((tmp_path / "correction.died").read_text())
    assert len(starts["correction"]) == 2, log
    assert starts["correction"][1] - died >= 2.0, log            # not before the lease and a second
    assert result.restarts["correction"] == 1
    assert any(p.startswith("correction died unexpectedly") and p.endswith("; restarted") for p in result.problems), \
        result.problems
    assert not any("not restarted" in p for p in result.problems), result.problems
    assert "restarting it in 2 s, once the graph has forgotten the process that died" in log
    assert "probe finished and the graph drained; stopping the graph" in log
    assert "correction stopped (exit status 0)" in log   # the restarted one, stopped by the launcher
    assert log.index("probe finished\n") < log.index("starting correction (pid", log.index("probe finished\n"))


def test_a_restart_still_due_when_the_run_times_out_is_said_undone(tmp_path, monkeypatch):
    """The correction dies at once; the run's --timeout (3 s) comes before its restart (lease 30 s):
    it is not restarted, not counted as restarted, and the summary's problems say so."""
    result, starts, log = _stand_in_graph(tmp_path, monkeypatch, 30, "--timeout", "3")
    assert len(starts["correction"]) == 1, log
    assert result.restarts.get("correction", 0) == 0
    assert "the run timed out after 3 s" in result.problems
    assert any(p.startswith("correction died unexpectedly")
               and p.endswith("; not restarted: the run ended before its restart was due") for p in result.problems), \
        result.problems
    assert "correction: not restarted: the run ended before its restart was due" in log
    assert "restarting it in 31 s" in log


#: A node that does not stop on SIGINT (it hangs in a wait), set up as every node's ``main`` sets
#: itself up (``nodes.executor.install_stop_hook``).
HANGING_NODE = r"""
import signal, sys, threading
from inclinometer_calib.nodes.executor import install_stop_hook
install_stop_hook()
signal.signal(signal.SIGINT, signal.SIG_IGN)

def stuck_in_a_wait_for_ever():
    open(sys.argv[1], "w").close()
    threading.Event().wait()

stuck_in_a_wait_for_ever()
"""


def test_a_node_still_running_after_sigint_says_where_it_hangs_before_it_is_killed(tmp_path):
    """The launcher asks a node that did not stop on SIGINT for its threads' stacks (faulthandler,
    registered by every node's main), and the run's log has them, then SIGTERM ends it."""
    ready = tmp_path / "ready"
    log = launcher.RunLog(str(tmp_path / "launch.log"))
    child = launcher.Child("probe", [sys.executable, "-c", HANGING_NODE, str(ready)], dict(os.environ),
                           threading.Lock(), log)
    for _ in range(600):                      # up to a minute for its start on a loaded machine
        if ready.exists() or child.poll() is not None:
            break
        time.sleep(0.1)
    assert ready.exists(), "the stand-in node never started"
    rc = child.stop(sigint_s=0.5, sigterm_s=5.0)
    log.close()
    text = (tmp_path / "launch.log").read_text()
    assert rc == -signal.SIGTERM, text
    assert "[launch] probe still running 0.5 s after SIGINT: its threads' stacks follow" in text
    assert "[probe] Current thread" in text and "in stuck_in_a_wait_for_ever" in text, text
    assert "still running" not in text.split("stuck_in_a_wait_for_ever", 2)[-1], text   # SIGTERM was enough


def test_the_nodes_get_a_loopback_udp_profile_without_shared_memory(tmp_path):
    """Under LOCALHOST rmw_fastrtps adds shared memory whatever FASTDDS_BUILTIN_TRANSPORTS says: the
    nodes get a copy of the graph's profile (its lease and heartbeats kept) with a UDPv4 transport
    on 127.0.0.1 only, the built-in transports off, peers on 127.0.0.1, and the range left to that
    profile; a rig's own profile, another RMW or another range are left alone."""
    import xml.etree.ElementTree as ET

    cfg = launcher.config_dir()
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "7"}
    launcher.dds_profile_env(env, cfg)
    new, path = launcher.loopback_profile(env, cfg)
    try:
        assert path and new["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT" and new["ROS_DOMAIN_ID"] == "7"
        assert all(new[v] == path for v in launcher.DDS_PROFILE_VARS)
        assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"          # the graph's own untouched
        ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
        root = ET.parse(path).getroot()
        (desc,) = root.findall("p:transport_descriptors/p:transport_descriptor", ns)
        assert desc.findtext("p:type", namespaces=ns) == "UDPv4"
        assert [a.text for a in desc.findall("p:interfaceWhiteList/p:address", ns)] == ["127.0.0.1"]
        rtps = root.find("p:participant[@is_default_profile='true']/p:rtps", ns)
        assert rtps.findtext("p:useBuiltinTransports", namespaces=ns) == "false"
        assert rtps.findtext("p:userTransports/p:transport_id", namespaces=ns) == desc.findtext("p:transport_id",
                                                                                               namespaces=ns)
        for where in ("initialPeersList", "metatrafficUnicastLocatorList"):
            assert rtps.findtext(f"p:builtin/p:{where}/p:locator/p:udpv4/p:address", namespaces=ns) == "127.0.0.1"
        assert launcher.participant_lease_s(new) == launcher.participant_lease_s(env) == 5.0
        assert root.find("p:data_writer/p:times/p:heartbeatPeriod/p:nanosec", ns).text == "100000000"
    finally:
        os.remove(path)
    rig = dict(env, FASTRTPS_DEFAULT_PROFILES_FILE=str(tmp_path / "rig.xml"))
    for other in (rig, dict(env, RMW_IMPLEMENTATION="rmw_cyclonedds_cpp"),
                  dict(env, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")):
        assert launcher.loopback_profile(other, cfg) == (other, None)

"""The ``wits`` node over real DDS: SurveyStation messages published in this process reach the
node (a separate process) and leave it as WITS0 record 07 to a TCP client on loopback and to a
file, read back by the tests' own parser; raw and error stations are not sent, a station received again (a restarted correction node) is sent once.  The same node
rewrites a WITSML 2.1 Trajectory after every station: it validates against the Energistics schema
and parses back to the numbers published (error stations as ``rejected``), and is marked inactive
when the node stops."""
import signal
import socket
import subprocess
import sys
import time

import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

from inclinometer_calib.rig import witsml  # noqa: E402
from wits_parser import parse_wits0  # noqa: E402


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_stations_leave_the_node_as_wits0_records_over_tcp_and_to_a_file(ros, ros_env, tmp_path):
    import rclpy
    from inclinometer_calib.msg import SurveyStation
    from inclinometer_calib.nodes import common as c

    port = _free_port()
    out = tmp_path / "wits.dat"
    traj = tmp_path / "trajectory.xml"
    proc = subprocess.Popen([sys.executable, "-m", "inclinometer_calib.nodes.wits", "--ros-args", "-p",
                             f"port:={port}", "-p", f"output:={out}", "-p", "well_id:=TEST-1",
                             "-p", f"witsml_file:={traj}", "-p", "wellbore:=TEST-1 A"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        client = None
        t0 = time.monotonic()
        while client is None and time.monotonic() - t0 < 20:
            try:
                client = socket.create_connection(("127.0.0.1", port), timeout=1)
            except OSError:
                time.sleep(0.2)
        assert client is not None, "the node's WITS server did not come up"
        node = rclpy.create_node("wits_test_publisher")
        ros.append(node)
        pub = node.create_publisher(SurveyStation, c.TOPIC_STATION, c.reliable_qos(100))
        t0 = time.monotonic()
        while pub.get_subscription_count() < 1 and time.monotonic() - t0 < 20:
            rclpy.spin_once(node, timeout_sec=0.1)
        sent, published = [], []
        for k in range(6):
            m = SurveyStation()
            m.header.stamp.sec = 1_795_000_000 + 30 * k
            m.station_id = k
            m.coefficients_id = "" if k == 0 else "abc123"      # the first: raw, not a survey
            m.status = 2 if k == 3 else 0                        # the fourth: the probe moved
            m.measured_depth_m, m.tvd_m = 500.0 + 30 * k, 499.0 + 29 * k
            m.drift_deg, m.azimuth_deg, m.azimuth_magnetic_deg = 3.0 * k, 40.0 + k, 38.5 + k
            m.magnetic_toolface_deg = m.gravity_toolface_deg = 10.0 * k
            m.north_m, m.east_m, m.dls_deg_per_30m = 1.5 * k, 2.5 * k, 3.0
            m.azimuth_reference, m.azimuth_method = "true", "standard"
            m.azimuth_grid_deg = m.axial_field_nt = float("nan")                # no grid, no short collar
            m.azimuth_true_deg = m.azimuth_deg
            m.total_gravity_mps2, m.total_field_nt, m.dip_deg = 9.81 + 0.001 * k, 50_000.0 + k, 60.0 + 0.01 * k
            m.raw_gravity_mps2 = [0.1 * k, -0.2, 9.8]
            m.raw_field_nt = [1000.0 + k, -2000.0, 40_000.5]
            pub.publish(m)
            published.append(m)
            if k not in (0, 3):
                sent.append(m)
        pub.publish(published[2])        # the same station again (a correction node restarted mid-run): sent once
        buf = b""
        client.settimeout(0.5)
        t0 = time.monotonic()
        while buf.count(b"!!\r\n") < len(sent) and time.monotonic() - t0 < 20:
            rclpy.spin_once(node, timeout_sec=0.05)
            try:
                buf += client.recv(65536)
            except socket.timeout:
                pass
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:       # a record sent twice would come now
            rclpy.spin_once(node, timeout_sec=0.05)
            try:
                buf += client.recv(65536)
            except socket.timeout:
                pass
        recs = parse_wits0(buf)
        assert [float(r[(7, 8)]) for r in recs] == [m.measured_depth_m for m in sent]
        assert [r[(7, 4)] for r in recs] == ["1", "2", "3", "4"] and all(r[(7, 1)] == "TEST-1" for r in recs)
        for r, m in zip(recs, sent):
            assert float(r[(7, 13)]) == pytest.approx(m.drift_deg, abs=0.005)
            assert float(r[(7, 14)]) == pytest.approx(m.azimuth_magnetic_deg, abs=0.005)
            assert float(r[(7, 15)]) == pytest.approx(m.azimuth_deg, abs=0.005)
            assert float(r[(7, 9)]) == pytest.approx(m.tvd_m, abs=0.005)
        assert parse_wits0(out.read_bytes()) == recs                      # the same bytes to the file
        client.close()
        # WITSML: every calibrated station (the error one rejected), rewritten after each station
        t0 = time.monotonic()
        while time.monotonic() - t0 < 20 and not (traj.exists() and b"station-5" in traj.read_bytes()):
            time.sleep(0.1)
        xml = traj.read_bytes()
        witsml.validate(xml)
        assert b"<eml:ActiveStatus>active<" in xml
        back = witsml.read_trajectory(xml)
        survey = published[1:]
        assert [b["uid"] for b in back] == [f"station-{m.station_id}" for m in survey]
        for b, m in zip(back, survey):
            assert b["station_status"] == ("rejected" if m.status == 2 else "position")
            for k in ("measured_depth_m", "tvd_m", "drift_deg", "azimuth_deg", "north_m", "east_m",
                      "dls_deg_per_30m", "total_gravity_mps2", "total_field_nt", "dip_deg"):
                assert b[k] == getattr(m, k), (m.station_id, k)
            assert b["raw_gravity_mps2"] == list(m.raw_gravity_mps2) and b["raw_field_nt"] == list(m.raw_field_nt)
            assert b["coefficients_id"] == "abc123" and b["azimuth_reference"] == "true"
    finally:
        proc.terminate()
        try:
            log = proc.communicate(timeout=20)[0]
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)              # PYTHONFAULTHANDLER: every thread's stack
            log = proc.communicate(timeout=20)[0]
            pytest.fail(f"the node did not end within 20 s of SIGTERM; its log and stacks:\n{log[-8000:]}")
    assert "station 3: status error" in log and "Traceback" not in log, log
    # record 07 cannot say its north and units: the node says them
    assert "azimuth 0715 and north/east 0718/0719 along true north" in log and "units M, DEG, dogleg DGHM" in log
    final = traj.read_bytes()                                 # the node's last rewrite: the survey is over
    witsml.validate(final)
    assert b"<eml:ActiveStatus>inactive<" in final and len(witsml.read_trajectory(final)) == 5

"""The ``live`` node over real DDS and a real WebSocket: the node (a separate process, a free
loopback port) receives SurveyStation and DiagnosticArray messages published in this process and
sends them to a client speaking the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``,
the one foxglove-sdk 0.30.3 accepts): serverInfo, advertise of every channel the layout reads,
subscribe, then binary message data (opcode 0x01, u32 subscription id, u64 log time ns, payload)
whose JSON the test decodes and checks number by number."""
import json
import os
import queue
import re
import signal
import struct
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")
pytest.importorskip("foxglove", reason="the live node needs foxglove-sdk (requirements/core.txt)")
ws_client = pytest.importorskip("websockets.sync.client", reason="the test client needs websockets (test.txt)")

from inclinometer_calib.rig import liveview as lv  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _layout_topics():
    with open(os.path.join(ROOT, "config", "foxglove_layout.json"), encoding="utf-8") as fh:
        text = json.dumps(json.load(fh)["configById"])
    return set(re.findall(r'"(/live/\w+)', text))


def test_stations_reach_a_foxglove_client_over_loopback(ros, ros_env):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from inclinometer_calib.msg import SurveyStation
    from inclinometer_calib.nodes import common as c

    proc = subprocess.Popen([sys.executable, "-m", "inclinometer_calib.nodes.live", "--ros-args", "-p", "port:=0",
                             "-p", "republish_s:=60.0"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True).start()
    log = []
    try:
        url = None
        t0 = time.monotonic()
        while url is None and time.monotonic() - t0 < 20 and proc.poll() is None:
            try:
                log.append(lines.get(timeout=0.2))
            except queue.Empty:
                continue
            m = re.search(r"(ws://127\.0\.0\.1:\d+)", log[-1])
            url = m.group(1) if m else None
        assert url, "the node did not say its URL:\n" + "".join(log)

        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10, close_timeout=1) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            info = json.loads(ws.recv(timeout=5))
            assert info["op"] == "serverInfo"
            channels = {}
            while set(channels) != set(lv.CHANNELS):
                msg = json.loads(ws.recv(timeout=5))
                if msg["op"] == "advertise":
                    channels.update({ch["topic"]: ch for ch in msg["channels"]})
            assert _layout_topics() <= set(channels), "the layout reads topics the node does not advertise"
            assert channels[lv.TOPIC_STATION]["encoding"] == "json"
            assert channels[lv.TOPIC_TRAJECTORY]["schemaName"] == "foxglove.SceneUpdate"
            schema = json.loads(channels[lv.TOPIC_STATION]["schema"])
            assert set(schema["properties"]) == set(SurveyStation.get_fields_and_field_types()) - {"header"} | {"stamp"}
            subs = {1: lv.TOPIC_STATION, 2: lv.TOPIC_RESIDUALS, 3: lv.TOPIC_DIAGNOSTICS}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": k, "channelId": channels[t]["id"]} for k, t in subs.items()]}))

            node = rclpy.create_node("live_test_publisher")
            ros.append(node)
            pub = node.create_publisher(SurveyStation, c.TOPIC_STATION, c.reliable_qos(100))
            pub_diag = node.create_publisher(DiagnosticArray, c.TOPIC_DIAGNOSTICS, c.reliable_qos(10))
            t0 = time.monotonic()
            while (pub.get_subscription_count() < 1 or pub_diag.get_subscription_count() < 1) \
                    and time.monotonic() - t0 < 20:
                rclpy.spin_once(node, timeout_sec=0.1)
            sent = []
            for k in range(2):
                m = SurveyStation()
                m.header.stamp.sec, m.header.stamp.nanosec = 1_795_000_000 + 30 * k, 500_000_000
                m.station_id, m.coefficients_id, m.status = 10 + k, "abc123", k
                m.drift_deg, m.azimuth_deg, m.toolface_deg = 12.345 + k, 231.5 - k, 47.25
                m.delta_g_mps2, m.delta_b_nt, m.delta_dip_deg = 0.0012 * (k + 1), -37.5 + 400 * k, 0.021
                m.measured_depth_m, m.tvd_m, m.north_m, m.east_m = 500.0 + 30 * k, 499.0 + 29 * k, 1.5 * k, -2.5 * k
                m.azimuth_sigma_deg = float("nan")
                m.warnings = ["the probe crept"] if k else []
                pub.publish(m)
                sent.append(m)
            diag = DiagnosticArray()
            diag.status = [DiagnosticStatus(level=DiagnosticStatus.WARN, name="inclinometer_calib: total field",
                                            hardware_id="probe-1", values=[KeyValue(key="delta", value="412")])]
            pub_diag.publish(diag)

            got = {t: [] for t in subs.values()}
            t0 = time.monotonic()
            while (len(got[lv.TOPIC_STATION]) < 2 or not got[lv.TOPIC_DIAGNOSTICS]
                   or len(got[lv.TOPIC_RESIDUALS]) < 2) and time.monotonic() - t0 < 20:
                try:
                    data = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(data, bytes):
                    opcode, sub_id, log_time = struct.unpack_from("<BIQ", data)
                    assert opcode == 0x01 and sub_id in subs and log_time > 0
                    got[subs[sub_id]].append(json.loads(data[13:]))

        stations = got[lv.TOPIC_STATION]
        assert [s["station_id"] for s in stations] == [10, 11]
        for s, m in zip(stations, sent):
            for k in ("drift_deg", "azimuth_deg", "toolface_deg", "delta_g_mps2", "delta_b_nt", "delta_dip_deg",
                      "measured_depth_m", "tvd_m", "north_m", "east_m"):
                assert s[k] == getattr(m, k), k
            assert s["stamp"] == pytest.approx(m.header.stamp.sec + 0.5, abs=1e-6)
            assert s["azimuth_sigma_deg"] is None                      # NaN -> null
            assert s["coefficients_id"] == "abc123" and s["status"] == m.status
        assert stations[1]["warnings"] == ["the probe crept"]
        series = got[lv.TOPIC_RESIDUALS][-1]
        assert series["station_id"] == [10, 11] and series["delta_b_nt"] == [-37.5, 362.5]
        status = got[lv.TOPIC_DIAGNOSTICS][0]["status"][0]
        assert (status["level"], status["name"], status["values"]) == (
            1, "inclinometer_calib: total field", [{"key": "delta", "value": "412"}])
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)              # PYTHONFAULTHANDLER: every thread's stack
            proc.wait(timeout=20)
            time.sleep(0.5)
            while not lines.empty():
                log.append(lines.get())
            pytest.fail("the node did not end within 20 s of SIGTERM; its log and stacks:\n" + "".join(log)[-8000:])
        finally:
            while not lines.empty():
                log.append(lines.get())
    assert "Traceback" not in "".join(log), "".join(log)

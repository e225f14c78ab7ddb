"""The demo's rig run end to end: the launcher with the rig site given by latitude, longitude and
date (config/rig_site.yaml: WMM2025 and a grid), a WITS0 client on its TCP port, a Foxglove client
on its WebSocket, and the WITSML trajectory it writes.  Every node is a separate process over real
DDS (own ROS_DOMAIN_ID, localhost discovery); both servers on loopback.  The stations must carry
the model's reference field (declination, grid convergence), depth, position and its ISCWSA
covariance; the rig's clients must get every one of them, all along one north (grid: the site has
a grid), so that each client's own minimum curvature lands on the positions it was given and the
three agree to the centimetre."""
import json
import math
import os
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")
pytest.importorskip("foxglove", reason="the live node needs foxglove-sdk (requirements/core.txt)")
ws_client = pytest.importorskip("websockets.sync.client", reason="the test client needs websockets (test.txt)")

from inclinometer_calib.rig import liveview as lv  # noqa: E402
from north_well import receiver_positions  # noqa: E402
from rig_clients import wits_client  # noqa: E402
from inclinometer_calib.apps.common import load_site  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(14)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SITE_FILE = os.path.join(ROOT, "config", "rig_site.yaml")
N_STATIONS = 4


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _foxglove_client(port, got, stop):
    """Connects as soon as the live node listens, subscribes to the station channel and keeps every
    station (the JSON payload of binary message frames: opcode 0x01, u32 subscription, u64 time)."""
    url = f"ws://127.0.0.1:{port}"
    while not stop.is_set():
        try:
            ws = ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=2, close_timeout=1)
            break
        except OSError:
            time.sleep(0.2)
    else:
        return
    with ws:
        channels = {}
        subscribed = False
        while True:
            try:
                msg = ws.recv(timeout=0.5)
            except TimeoutError:
                if stop.is_set():
                    break
                continue
            except Exception:       # the server closed with the graph
                break
            if isinstance(msg, str):
                m = json.loads(msg)
                if m.get("op") == "advertise":
                    channels.update({ch["topic"]: ch for ch in m["channels"]})
                if not subscribed and lv.TOPIC_STATION in channels:
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": 1, "channelId": channels[lv.TOPIC_STATION]["id"]}]}))
                    subscribed = True
            elif msg[0] == 0x01 and struct.unpack_from("<I", msg, 1)[0] == 1:
                got.append(json.loads(msg[13:]))


@pytest.fixture(scope="module")
def rig_run(domain_env, tmp_path_factory):
    env, _ = domain_env
    out = tmp_path_factory.mktemp("rig") / "run"
    wits_port, fox_port = _free_port(), _free_port()
    wits, fox, stop = [], [], threading.Event()
    threads = [threading.Thread(target=wits_client, args=(wits_port, wits, stop), daemon=True),
               threading.Thread(target=_foxglove_client, args=(fox_port, fox, stop), daemon=True)]
    for t in threads:
        t.start()
    cmd = [sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--speed", "30",
           "--stations", str(N_STATIONS), "--seed", "5", "--reliable", "--timeout", "120", "--no-loop",
           "--param", "probe:rate_hz:=50.0",
           "--site", SITE_FILE, "--witsml", "--wits-port", str(wits_port), "--foxglove-port", str(fox_port)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=180)
    stop.set()
    for t in threads:
        t.join(5)
    if proc.returncode != 0:
        pytest.fail(f"launcher exit status {proc.returncode}\n{proc.stdout[-6000:]}\n{proc.stderr[-3000:]}")
    return out, proc, b"".join(wits), fox


def test_the_rig_run_stations_carry_the_models_field_depth_position_and_its_uncertainty(rig_run):
    from inclinometer_calib.io.bag import read_bag

    out, proc, _, _ = rig_run
    site = load_site(SITE_FILE)
    assert site.reference["model"] == "WMM2025" and abs(site.declination_deg) > 0.5
    stations = [s for s in read_bag(str(out / "survey.mcap"))[0] if s["coefficients_id"]]
    assert len(stations) == N_STATIONS
    sig = []
    for s in stations:
        # QC against the model's field: the node looked the site up as the launcher did
        assert abs(s["total_field_nt"] - site.total_field_nt) < 300 and abs(s["delta_b_nt"]) < 300
        assert s["azimuth_reference"] == "grid"                 # the site has a grid: grid north by default
        if math.isfinite(s["azimuth_deg"]):
            assert s["azimuth_deg"] == s["azimuth_grid_deg"]
            assert (s["azimuth_true_deg"] - s["azimuth_magnetic_deg"]) % 360 == pytest.approx(
                site.declination_deg % 360, abs=1e-6)
            assert (s["azimuth_true_deg"] - s["azimuth_grid_deg"]) % 360 == pytest.approx(
                site.grid_convergence_deg % 360, abs=1e-6)
        assert math.isfinite(s["measured_depth_m"]) and math.isfinite(s["tvd_m"])
        cov = np.reshape(s["position_covariance_ned_m2"], (3, 3))
        assert np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
        sig.append(math.sqrt(np.trace(cov)))
        assert np.all(np.isfinite(s["raw_gravity_mps2"])) and np.all(np.isfinite(s["raw_field_nt"]))
    assert all(b > a for a, b in zip(sig, sig[1:]))
    assert "ISCWSA 1σ" in proc.stdout and "trajectory:" in proc.stdout


def test_the_rigs_wits_and_foxglove_clients_get_every_station_and_the_witsml_validates(rig_run):
    from wits_parser import parse_wits0

    from inclinometer_calib.rig import witsml
    from inclinometer_calib.io.bag import read_bag

    out, _, wits_bytes, fox = rig_run
    stations = [s for s in read_bag(str(out / "survey.mcap"))[0] if s["coefficients_id"] and s["status"] != 2]
    records = parse_wits0(wits_bytes)
    assert [round(float(r[(7, 8)]), 2) for r in records] == [round(s["measured_depth_m"], 2) for s in stations]
    got = {m["station_id"]: m for m in fox}
    for s in stations:
        assert s["station_id"] in got, (sorted(got), s["station_id"])
        assert got[s["station_id"]]["tvd_m"] == pytest.approx(s["tvd_m"], abs=1e-9)
    xml = (out / "trajectory.xml").read_bytes()
    witsml.validate(xml)
    back = witsml.read_trajectory(xml)
    assert [round(b["measured_depth_m"], 3) for b in back] == [round(s["measured_depth_m"], 3) for s in stations]
    # one north everywhere: each client's own minimum curvature from MD, inclination and azimuth lands on the
    # north/east it was given, and the three give the same position, to the centimetre
    live = [got[s["station_id"]] for s in stations]
    assert {m["azimuth_reference"] for m in live} == {"grid"} and {b["azimuth_reference"] for b in back} == {"grid"}
    # and the recorded run exported as WITSML 1.4.1.1 in feet (read back in metres), validated against its schema
    doc = witsml.trajectory_document(read_bag(str(out / "survey.mcap"))[0], version="1.4.1.1", units="ft")
    assert witsml.validate(doc.xml) == "1.4.1.1"
    v1411 = witsml.read_trajectory(doc.xml)
    assert {b["azimuth_reference"] for b in v1411} == {"grid"} and len(v1411) == len(back)
    given = {"wits0": (float(records[-1][(7, 18)]), float(records[-1][(7, 19)])),
             "live": (live[-1]["north_m"], live[-1]["east_m"]), "witsml": (back[-1]["north_m"], back[-1]["east_m"]),
             "witsml 1.4.1.1 ft": (v1411[-1]["north_m"], v1411[-1]["east_m"])}
    recomputed = {
        "wits0": receiver_positions([float(r[(7, 8)]) for r in records], [float(r[(7, 13)]) for r in records],
                                    [float(r.get((7, 15), "0")) for r in records])[-1],
        "live": receiver_positions([m["measured_depth_m"] for m in live], [m["drift_deg"] for m in live],
                                   [m["azimuth_deg"] or 0.0 for m in live])[-1],
        "witsml": receiver_positions([b["measured_depth_m"] for b in back], [b["drift_deg"] for b in back],
                                     [np.nan_to_num(b["azimuth_deg"]) for b in back])[-1],
        "witsml 1.4.1.1 ft": receiver_positions([b["measured_depth_m"] for b in v1411], [b["drift_deg"] for b in v1411],
                                                [np.nan_to_num(b["azimuth_deg"]) for b in v1411])[-1]}
    for k in given:
        assert given[k] == pytest.approx(recomputed[k], abs=0.01), k
        assert given[k] == pytest.approx((stations[-1]["north_m"], stations[-1]["east_m"]), abs=0.01), k

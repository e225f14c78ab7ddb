"""The live view's payloads (inclinometer_calib/rig/liveview.py), without ROS: the station as JSON with
every field of msg/SurveyStation.msg (NaN -> null) and its JSON Schema, the residual series, the
station table, the trajectory's SceneUpdate and frame, and the SDK server's handling of a client
that stops reading (the node must never wait for one)."""
import json
import math
import os
import re
import struct
import time
from types import SimpleNamespace

import pytest

foxglove = pytest.importorskip("foxglove", reason="the live view needs foxglove-sdk (requirements/core.txt)")

from inclinometer_calib.io import surveystation  # noqa: E402
from inclinometer_calib.rig import liveview as lv  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
NAN = float("nan")


def msg_fields(name):
    """name -> ROS 2 IDL type of a message of msg/, read from its .msg file (as rclpy names them)."""
    idl = {"float64": "double", "float32": "float", "bool": "boolean", "byte": "octet"}
    out = {}
    with open(os.path.join(ROOT, "msg", f"{name}.msg"), encoding="utf-8") as fh:
        for line in fh:
            line = line.split("#")[0].strip()
            m = re.fullmatch(r"([\w/]+)(\[(\d*)\])?\s+(\w+)", line)     # constants have "=": not fields
            if not m:
                continue
            base = idl.get(m.group(1), m.group(1))
            base = "std_msgs/Header" if base in ("Header", "std_msgs/Header") else base
            out[m.group(4)] = (f"{base}[{m.group(3)}]" if m.group(3) else f"sequence<{base}>") if m.group(2) else base
    return out


NESTED = {"std_msgs/Header": {"stamp": "builtin_interfaces/Time", "frame_id": "string"},
          "builtin_interfaces/Time": {"sec": "int32", "nanosec": "uint32"}}


def station_msg(**values):
    """A SurveyStation-like message (attributes as rclpy/rosbags give them) with every field of the
    .msg file: distinct finite values unless given."""
    fields = msg_fields("SurveyStation")
    attrs = {}
    for k, (name, t) in enumerate(fields.items()):
        if name == "header":
            continue
        if t == "double":
            attrs[name] = 1.25 + k
        elif t == "boolean":
            attrs[name] = k % 2 == 0
        elif t == "string":
            attrs[name] = f"text{k}"
        elif t.startswith("sequence<string"):
            attrs[name] = [f"warning {k}"]
        elif t.startswith("double["):
            attrs[name] = [0.5 * k + i for i in range(int(t[7:-1]))]
        else:
            attrs[name] = k
    attrs.update(values)
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=1_795_000_000, nanosec=250_000_000),
                                                  frame_id="probe"), **attrs)


def check_schema(value, schema, where="$"):
    """The subset of JSON Schema json_schema writes: type (one or a list), properties, required,
    items, minItems/maxItems."""
    types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
    py = {"number": (int, float), "integer": int, "boolean": bool, "string": str, "null": type(None),
          "array": list, "object": dict}
    assert any(isinstance(value, py[t]) and not (t in ("number", "integer") and isinstance(value, bool))
               for t in types), f"{where}: {value!r} is not {types}"
    if isinstance(value, dict):
        for k in schema.get("required", ()):
            assert k in value, f"{where}: {k} missing"
        for k, v in value.items():
            assert k in schema["properties"], f"{where}.{k}: not in the schema"
            check_schema(v, schema["properties"][k], f"{where}.{k}")
    if isinstance(value, list):
        assert schema.get("minItems", 0) <= len(value) <= schema.get("maxItems", math.inf), where
        for i, v in enumerate(value):
            check_schema(v, schema["items"], f"{where}[{i}]")


# ---------------------------------------------------------------------------------------------
# the station as JSON

def test_station_json_has_every_field_of_the_message_with_nan_as_null():
    fields = msg_fields("SurveyStation")
    msg = station_msg(azimuth_deg=NAN, raw_field_nt=[NAN, 2.0, 3.0], station_id=7, drift_deg=12.5)
    s = surveystation.from_msg(msg)
    assert set(s) == set(fields) - {"header"} | {"stamp"}
    payload = json.loads(json.dumps(lv.jsonable(s), allow_nan=False))
    assert payload["azimuth_deg"] is None and payload["raw_field_nt"] == [None, 2.0, 3.0]
    assert payload["station_id"] == 7 and payload["drift_deg"] == 12.5
    assert payload["stamp"] == pytest.approx(1_795_000_000.25, abs=1e-6)
    for name in fields:
        if name not in ("header", "azimuth_deg", "raw_field_nt", "station_id", "drift_deg"):
            assert payload[name] == getattr(msg, name), name
    check_schema(payload, lv.json_schema(lv.station_fields(fields), NESTED.__getitem__))


def test_json_schema_of_nested_messages_and_fixed_arrays():
    diag = {"header": "std_msgs/Header", "status": "sequence<diagnostic_msgs/DiagnosticStatus>"}
    nested = {**NESTED, "diagnostic_msgs/DiagnosticStatus": {"level": "octet", "name": "string", "message": "string",
                                                             "hardware_id": "string",
                                                             "values": "sequence<diagnostic_msgs/KeyValue>"},
              "diagnostic_msgs/KeyValue": {"key": "string", "value": "string"}}
    schema = lv.json_schema(diag, nested.__getitem__)
    good = {"header": {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": ""},
            "status": [{"level": 1, "name": "inclinometer_calib: dip", "message": "m", "hardware_id": "p",
                        "values": [{"key": "delta", "value": "0.1"}]}]}
    check_schema(good, schema)
    with pytest.raises(AssertionError):
        check_schema({**good, "status": [{**good["status"][0], "level": "1"}]}, schema)
    fixed = lv.json_schema({"v": "double[3]"}, NESTED.__getitem__)["properties"]["v"]
    assert fixed == {"type": "array", "items": {"type": ["number", "null"]}, "minItems": 3, "maxItems": 3}


def test_message_dict_turns_bytes_arrays_and_nested_messages_into_plain_values():
    import array

    import numpy as np

    @__import__("dataclasses").dataclass
    class KeyValue:
        key: str
        value: str

    @__import__("dataclasses").dataclass
    class Status:
        level: bytes
        values: list
        fixed: object
        seq: object

    d = lv.message_dict(Status(level=b"\x02", values=[KeyValue("a", "b")], fixed=np.array([1.0, NAN]),
                               seq=array.array("d", [0.5])))
    assert d["level"] == 2 and d["values"] == [{"key": "a", "value": "b"}] and d["seq"] == [0.5]
    assert d["fixed"][0] == 1.0 and math.isnan(d["fixed"][1])
    assert lv.jsonable(d)["fixed"] == [1.0, None]


# ---------------------------------------------------------------------------------------------
# the survey so far

def _station(sid, md, n, e, tvd, status=0, coefficients_id="abc", **kw):
    return surveystation.from_msg(station_msg(station_id=sid, measured_depth_m=md, north_m=n, east_m=e, tvd_m=tvd,
                                       status=status, coefficients_id=coefficients_id, **{"warnings": [], **kw}))


def test_residual_series_hold_the_corrected_stations_only():
    view = lv.LiveView()
    view.add(_station(0, NAN, NAN, NAN, NAN, coefficients_id="", delta_b_nt=900.0,     # raw: before calibration
                      uncorrected_reason="before calibration: the calibration has not solved yet"))
    view.add(_station(1, 500.0, 1.0, 2.0, 499.0, delta_g_mps2=0.001, delta_b_nt=-35.0, delta_dip_deg=0.02))
    view.add(_station(2, 530.0, 2.0, 4.0, 528.0, status=1, delta_g_mps2=-0.002, delta_b_nt=410.0,
                      delta_dip_deg=NAN))
    r = view.residuals()
    assert r["station_id"] == [1, 2] and r["status"] == [0, 1] and r["measured_depth_m"] == [500.0, 530.0]
    assert r["delta_g_mps2"] == [0.001, -0.002] and r["delta_b_nt"] == [-35.0, 410.0]
    assert lv.jsonable(r)["delta_dip_deg"] == [0.02, None]
    rows = view.table()["rows"]
    assert [row["station"] for row in rows] == [2, 1, 0]                                # newest first
    assert rows[2]["status"] == "uncorrected (before calibration)" and rows[1]["status"].startswith("ok")
    assert rows[0]["dB_nT"] == 410.0 and rows[0]["md_m"] == 530.0


def test_trajectory_in_depth_order_a_resurvey_replaces_what_lies_below():
    view = lv.LiveView(max_stations=10)
    for k, md in enumerate((500.0, 530.0, 560.0)):
        view.add(_station(k, md, 0.1 * k, 0.2 * k, md - 1.0 - k, status=2 if k == 1 else 0))
    view.add(_station(3, NAN, NAN, NAN, NAN))                      # no depth: not on the trajectory
    assert [p["station_id"] for p in view.trajectory()] == [0, 1, 2]
    assert view.trajectory()[1]["color"] == lv.STATUS_COLORS[2]
    view.add(_station(4, 530.0, 0.15, 0.25, 528.5))                # re-survey at 530 m: replaces 530 and 560
    pts = view.trajectory()
    assert [p["station_id"] for p in pts] == [0, 4] and pts[1]["ned"] == (0.15, 0.25, 528.5)
    for k in range(20):
        view.add(_station(10 + k, 600.0 + k, 0.0, 0.0, 600.0 + k))
    assert len(view.stations) == 10 and len(view.trajectory()) == 10


def test_scene_update_carries_every_point_in_the_ned_frame():
    view = lv.LiveView()
    view.add(_station(0, 0.0, 0.0, 0.0, 0.0))
    view.add(_station(1, 530.0, 12.75, -3.5, 527.25, status=1))
    view.add(_station(2, 560.0, 25.125, -7.0, 555.5))
    data = lv.scene_update(view.trajectory(), 1_795_000_000.5).encode()
    # protobuf doubles are little-endian 64-bit: every non-zero coordinate is in the message
    for p in view.trajectory():
        for x in p["ned"]:
            if x:
                assert struct.pack("<d", x) in data, x
    assert lv.FRAME_NED.encode() in data and b"trajectory" in data
    empty = lv.scene_update([]).encode()
    assert b"trajectory" in empty and lv.FRAME_NED.encode() not in empty          # a deletion


@pytest.mark.parametrize("north", ["grid", "true", "magnetic"])
def test_the_live_station_declares_the_one_north_of_its_azimuth_and_north_east_and_names_the_others(north):
    from north_well import CONVERGENCE, projected_well, receiver_positions

    _, _, stations = projected_well(north)
    view = lv.LiveView()
    sent = []
    for s in stations:
        d = surveystation.from_msg(station_msg(**{k: v for k, v in s.items() if k != "stamp"}))
        view.add(d)
        sent.append(json.loads(json.dumps(lv.jsonable(d), allow_nan=False)))     # what /live/station carries
    last = sent[-1]
    assert {p["azimuth_reference"] for p in sent} == {north} and last["azimuth_deg"] == last[f"azimuth_{north}_deg"]
    assert (last["azimuth_true_deg"] - last["azimuth_grid_deg"]) % 360 == pytest.approx(CONVERGENCE)
    rx = receiver_positions([p["measured_depth_m"] for p in sent], [p["drift_deg"] for p in sent],
                            [p["azimuth_deg"] or 0.0 for p in sent])                # null: a vertical station
    assert (last["north_m"], last["east_m"]) == pytest.approx(rx[-1], abs=0.01)
    assert {r["azimuth_reference"] for r in view.table()["rows"]} == {north}
    # the trajectory entity's metadata north = <north> (protobuf KeyValuePair: key field 1, value field 2)
    assert b"\x05north\x12" + bytes([len(north)]) + north.encode() in lv.scene_update(view.trajectory()).encode()


def test_the_ned_frame_is_drawn_z_up():
    """The rotation of survey_ned in survey_enu maps (north, east, down) to (east, north, up)."""
    x, y, z, w = lv.NED_IN_ENU
    r = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    n, e, d = 3.0, 5.0, 7.0
    assert [sum(r[i][j] * v for j, v in enumerate((n, e, d))) for i in range(3)] == pytest.approx([e, n, -d])
    data = lv.frame_transforms().encode()
    assert lv.FRAME_NED.encode() in data and lv.FRAME_DISPLAY.encode() in data
    assert struct.pack("<d", math.sqrt(0.5)) in data


def test_log_entries_say_errors_warnings_and_misfit():
    s = _station(5, 700.0, 0, 0, 700.0, status=2, warnings=["the probe crept 0.1 deg"], model_misfit=True,
                 model_diagnosis="temperature_bias:mag")
    levels = [lvl for lvl, _ in lv.log_entries(s)]
    assert levels == ["error", "warning", "warning"]
    assert "temperature_bias:mag" in lv.log_entries(s)[2][1]
    assert lv.log_message("warning", "x", 1.0).encode()


# ---------------------------------------------------------------------------------------------
# a slow client does not hold up the sender (what the live node relies on)

def test_a_client_that_stops_reading_does_not_block_the_sender():
    from websockets.sync.client import connect

    ctx = foxglove.Context()
    ch = foxglove.Channel("/big", message_encoding="json", context=ctx)
    server = foxglove.start_server(host="127.0.0.1", port=0, context=ctx, message_backlog_size=64)
    try:
        # max_queue=1: the client's reader stops taking frames off the socket after one: a stalled client
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=["foxglove.sdk.v1"], max_queue=1,
                     open_timeout=5, close_timeout=0.2) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            ws.recv(timeout=5)                                                         # serverInfo
            ws.recv(timeout=5)                                                         # advertise
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": ch.id()}]}))
            t0 = time.monotonic()
            while not ch.has_sinks() and time.monotonic() - t0 < 5:
                time.sleep(0.01)
            assert ch.has_sinks(), "the client's subscription did not reach the server"
            payload = b'{"x":"' + b"a" * 100_000 + b'"}'
            t0 = time.perf_counter()
            for _ in range(2000):                                                     # 200 MB
                ch.log(payload)
            elapsed = time.perf_counter() - t0
    finally:
        server.stop()
    assert elapsed < 2.0, f"2000 x 100 kB to a stalled client took {elapsed:.2f} s"

"""inclinometer_calib.io.bag without ROS: definitions, hashes, writer, damaged-file reading, recovery.

CDR bytes come from rosbags' serializer (no rclpy needed). Needs the mcap / rosbags packages
(installed by scripts/setup.sh); skipped without them.
"""
import json
import os
import re
import shutil
import struct
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("mcap_ros2")
pytest.importorskip("rosbags")

from mcap.reader import NonSeekingReader, make_reader  # noqa: E402
from mcap_ros2.reader import read_ros2_messages  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from inclinometer_calib.io import bag  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
TS = get_typestore(Stores.ROS2_JAZZY)
IMU = "sensor_msgs/msg/Imu"
STATION = "inclinometer_calib/msg/SurveyStation"
SEP = "=" * 80
T0 = 1_700_000_000_000_000_000


def _station_store():
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(bag.message_definition(STATION), STATION))
    return store


def imu_cdr(i: int) -> bytes:
    t = TS.types
    msg = t[IMU](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=i, nanosec=7), frame_id="probe"),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=t["geometry_msgs/msg/Vector3"](x=0.1, y=0.2, z=float(i)),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.arange(9, dtype=np.float64))
    return bytes(TS.serialize_cdr(msg, IMU))


def station_cdr(store, i: int) -> bytes:
    cls = store.types[STATION]
    t = store.types
    kwargs = {}
    fields = {
        "header": t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=i, nanosec=0), frame_id="probe"),
        "station_id": i, "azimuth_reference": "true", "toolface_type": "gravity",
        "coefficients_id": "cal-1", "status": 0, "azimuth_method": "standard", "axial_degenerate": False,
        "moved_during_capture": False, "warnings": ["a hold cut into pieces"], "model_misfit": False,
        "model_diagnosis": "", "probe_serial": "SN-1", "uncorrected_reason": "",
    }
    for name in cls.__dataclass_fields__:
        if name in fields:
            kwargs[name] = fields[name]
        elif name.startswith(("is_", "interference", "azimuth_undefined", "gravity_out")):
            kwargs[name] = False
        elif name == "samples_averaged":
            kwargs[name] = 100
        elif name in ("raw_gravity_mps2", "raw_field_nt"):
            kwargs[name] = np.full(3, float(i))
        elif name == "position_covariance_ned_m2":
            kwargs[name] = np.eye(3).ravel() * (i + 1)
        else:
            kwargs[name] = float(i) + 0.5
    return bytes(store.serialize_cdr(cls(**kwargs), STATION))


def write_imu_bag(path, n=500, dt_ns=10_000_000, **kw):
    with bag.BagWriter(path, **kw) as w:
        cid = w.add_topic("/probe/imu", IMU, qos_profiles=[{"reliability": "best_effort"}])
        for i in range(n):
            w.write(cid, imu_cdr(i), T0 + i * dt_ns, T0 + i * dt_ns - 1000)
    return w


# ---------------------------------------------------------------------------------------------
# definitions and hashes


def installed_type_hashes():
    """type -> RIHS01 hash of every type description rosidl installed (share/<pkg>/msg/<T>.json)
    under AMENT_PREFIX_PATH and the venv: what rclpy reports for live publishers."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    out = {}
    for prefix in prefixes + [sys.prefix]:
        for path in sorted(Path(prefix).glob("share/*/msg/*.json")):
            data = json.loads(path.read_text())
            name = data["type_description_msg"]["type_description"]["type_name"]
            for entry in data["type_hashes"]:
                if entry["type_name"] == name:
                    out.setdefault(name, entry["hash_string"])
    return out


def _split_definition(text):
    """(own part, [nested type names]) of a ros2msg definition; checks the separators."""
    for line in text.splitlines():
        if set(line) == {"="}:
            assert len(line) == 80
    parts = text.split(f"\n{SEP}\n")
    nested = [p.split("\n", 1)[0] for p in parts[1:]]
    assert all(n.startswith("MSG: ") for n in nested)
    assert len(nested) == len(set(nested))  # each nested type once
    return parts[0], [n[5:] for n in nested]


@pytest.mark.parametrize("type_name", [IMU, "sensor_msgs/msg/MagneticField",
                                       "diagnostic_msgs/msg/DiagnosticArray"])
def test_standard_definitions_parse_to_the_jazzy_types(type_name):
    text = bag.message_definition(type_name)
    _own, nested = _split_definition(text)
    if type_name == IMU:
        assert sorted(nested) == ["builtin_interfaces/Time", "geometry_msgs/Quaternion",
                                  "geometry_msgs/Vector3", "std_msgs/Header"]
    types = get_types_from_msg(text, type_name)
    assert set(types) == {type_name} | {n.replace("/", "/msg/") for n in nested}
    for name, (consts, fields) in types.items():
        assert (consts, fields) == tuple(TS.fielddefs[name]), name


@pytest.mark.parametrize("name", ["SurveyStation", "CalibrationCoefficients", "CalibrationStatus"])
def test_own_definitions_parse_to_the_msg_files(name):
    full = f"inclinometer_calib/msg/{name}"
    defs = bag.MessageDefinitions()
    text = defs.definition(full)
    _own, nested = _split_definition(text)
    assert sorted(nested) == ["builtin_interfaces/Time", "std_msgs/Header"]
    expected = get_types_from_msg(defs.text(full), full)[full]  # the .msg it was made from
    assert get_types_from_msg(text, full)[full] == expected  # fields and constants kept
    if name == "SurveyStation":
        consts, fields = expected
        assert [f[0] for f in fields][:3] == ["header", "station_id", "drift_deg"]
        assert ("STATUS_WARN", "uint8", 1) in consts
        assert ("AZIMUTH_REFERENCE_TRUE", "string", "true") in consts


def test_hashes_equal_the_installed_type_descriptions():
    installed = installed_type_hashes()
    recorded = [IMU, "sensor_msgs/msg/MagneticField", "sensor_msgs/msg/Temperature",
                "geometry_msgs/msg/Vector3Stamped", "diagnostic_msgs/msg/DiagnosticArray"]
    own = [f"inclinometer_calib/msg/{p.stem}" for p in sorted((REPO / "msg").glob("*.msg"))]
    for name in recorded + own:
        if name not in installed and name in own:
            pytest.skip("our messages are not built (scripts/setup.sh): no .json to compare")
        assert bag.type_hash(name) == installed[name], name
    # every installed type rosbags' Jazzy store knows: rosbags 0.11 hashes `char` as char where
    # rosidl hashes it as uint8; apart from types with a char field, all agree
    differ = sorted(n for n in installed if n in TS.fielddefs and bag.type_hash(n) != installed[n])
    assert all(re.search(r"^char\b", bag.message_definition(n), re.M) for n in differ), differ
    assert len(installed) > 100 and len(differ) < 10


def test_own_messages_without_an_install(tmp_path):
    defs = bag.MessageDefinitions(prefixes=[tmp_path])
    defs.prefixes = [tmp_path]  # not even the venv: this repository's msg/ directory
    assert defs.text(STATION) == (REPO / "msg" / "SurveyStation.msg").read_text()
    assert defs.definition(STATION) == bag.message_definition(STATION)
    assert defs.type_hash(STATION) == bag.type_hash(STATION)
    with pytest.raises(bag.UnknownTypeError):
        defs.definition("nopkg/msg/Nothing")
    assert defs.type_hash("nopkg/msg/Nothing") == ""
    assert "no .msg file" in defs.hash_errors["nopkg/msg/Nothing"]


def test_definition_syntax_cases_decoded_by_both_readers(tmp_path):
    share = tmp_path / "share" / "testpkg" / "msg"
    share.mkdir(parents=True)
    (share / "Outer.msg").write_text(
        "# comment line with a type-looking word: Inner thing\n"
        "uint8 MODE_A=1  # trailing comment\n"
        'string GREETING="hello # not a comment"\n'
        "string<=10 bounded_name\n"
        "int32[<=5] bounded_ints\n"
        "float64[9] fixed\n"
        "Inner[] inners\n"
        "testpkg/Inner[2] two_inners\n"
        "Header header\n"
        "int32 with_default 5\n")
    (share / "Inner.msg").write_text("builtin_interfaces/Time stamp\nbool flag\n")
    defs = bag.MessageDefinitions(prefixes=[tmp_path])
    text = defs.definition("testpkg/Outer")
    _own, nested = _split_definition(text)
    # `Header` is std_msgs/Header; package-local `Inner` resolved once
    assert sorted(nested) == ["builtin_interfaces/Time", "std_msgs/Header", "testpkg/Inner"]
    consts, _fields = get_types_from_msg(text, "testpkg/msg/Outer")["testpkg/msg/Outer"]
    assert consts == [("MODE_A", "uint8", 1), ("GREETING", "string", "hello # not a comment")]
    assert defs.type_hash("testpkg/msg/Outer").startswith("RIHS01_")

    # a message of it, written with that definition, decodes in mcap_ros2 and rosbags
    t = defs.typestore.types
    inner = t["testpkg/msg/Inner"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=2),
                                   flag=True)
    msg = t["testpkg/msg/Outer"](
        bounded_name="abc", bounded_ints=np.array([1, 2], dtype=np.int32), fixed=np.arange(9.0),
        inners=[inner], two_inners=[inner, inner],
        header=t["std_msgs/msg/Header"](stamp=inner.stamp, frame_id="f"), with_default=7)
    cdr = bytes(defs.typestore.serialize_cdr(msg, "testpkg/msg/Outer"))
    d = tmp_path / "outer"
    with bag.BagWriter(d, definitions=defs) as w:
        w.write(w.add_topic("/outer", "testpkg/Outer"), cdr, T0)
    (m,) = read_ros2_messages(str(d / "outer_0.mcap"))
    assert m.ros_msg.two_inners[1].stamp.nanosec == 2 and list(m.ros_msg.bounded_ints) == [1, 2]
    with AnyReader([d]) as r:  # checks the recorded hash against the definition, too
        ((conn, _t, raw),) = list(r.messages())
        assert r.deserialize(raw, conn.msgtype).with_default == 7

    # types that cannot be resolved: said, not guessed
    with pytest.raises(bag.UnknownTypeError):
        defs.definition("testpkg/msg/Missing")
    (share / "Broken.msg").write_text("Missing thing\n")
    with pytest.raises(bag.UnknownTypeError, match="referenced by testpkg/msg/Broken"):
        defs.definition("testpkg/Broken")
    (share / "Wide.msg").write_text("wstring wide\n")  # rosbags has no wstring
    with pytest.raises(bag.UnknownTypeError):
        defs.definition("testpkg/Wide")
    assert defs.type_hash("testpkg/Wide") == ""
    with pytest.raises(ValueError):
        bag.normalize_type("notatype")


def test_qos_yaml_roundtrip():
    prof = {"reliability": "best_effort", "durability": "transient_local", "depth": 5,
            "deadline_ns": 1_500_000_000}
    text = bag.qos_profiles_yaml([prof])
    assert "deadline:\n    sec: 1\n    nsec: 500000000" in text
    back = bag.parse_qos_profiles(text)[0]
    for k, v in prof.items():
        assert back[k] == v
    assert bag.qos_profiles_yaml([]) == ""
    # rosbag2's older integer enums
    assert bag.parse_qos_profiles([{"reliability": 2, "durability": 1}])[0]["reliability"] == \
        "best_effort"


# ---------------------------------------------------------------------------------------------
# writer -> both readers


def test_writer_decoded_by_mcap_ros2_and_rosbags(tmp_path):
    store = _station_store()
    p = tmp_path / "run.mcap"
    with bag.BagWriter(p) as w:
        ci = w.add_topic("/probe/imu", IMU, qos_profiles=[{"reliability": "best_effort"}])
        cs = w.add_topic("/survey/station", STATION,
                         qos_profiles=[{"durability": "transient_local", "depth": 1}])
        for i in range(300):
            w.write(ci, imu_cdr(i), T0 + i * 5_000_000, T0 + i * 5_000_000 - 10)
            if i % 100 == 0:
                w.write(cs, station_cdr(store, i // 100), T0 + i * 5_000_000 + 1)
    assert w.message_counts() == {"/probe/imu": 300, "/survey/station": 3}

    with open(p, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        assert header.profile == "ros2"
        assert summary.statistics.message_count == 303
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {s.name for s in summary.schemas.values()} == {IMU, STATION}
        for ch in summary.channels.values():
            assert ch.message_encoding == "cdr"
            assert ch.metadata["topic_type_hash"].startswith("RIHS01_")
            assert ch.metadata["offered_qos_profiles"].startswith("- history:")
        meta = list(reader.iter_metadata())
        assert meta and meta[0].name == "rosbag2" and "serialized_metadata" in meta[0].metadata

    decoded = list(read_ros2_messages(str(p)))
    imu = [m for m in decoded if m.channel.topic == "/probe/imu"]
    st = [m for m in decoded if m.channel.topic == "/survey/station"]
    assert [m.ros_msg.angular_velocity.z for m in imu] == [float(i) for i in range(300)]
    assert [m.ros_msg.station_id for m in st] == [0, 1, 2]
    assert st[1].ros_msg.azimuth_reference == "true"
    assert imu[3].log_time_ns - imu[3].publish_time_ns == 10

    with AnyReader([p]) as r:
        got = {}
        for conn, _t, raw in r.messages():
            got.setdefault(conn.topic, []).append(r.deserialize(raw, conn.msgtype))
        assert len(got["/probe/imu"]) == 300 and len(got["/survey/station"]) == 3
        assert got["/survey/station"][2].station_id == 2
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in r.connections}
        assert qos["/probe/imu"].reliability.name == "BEST_EFFORT"
        assert qos["/survey/station"].durability.name == "TRANSIENT_LOCAL"

    # our own reader
    rd = bag.open_bag(p)
    msgs = list(rd.messages())
    assert rd.finalized and not rd.errors and len(msgs) == 303
    assert rd.topics["/survey/station"].count == 3


def test_read_messages_gives_the_probe_types_by_the_fast_path_and_the_same_values_as_rosbags(tmp_path):
    store = _station_store()
    p = tmp_path / "run.mcap"
    with bag.BagWriter(p, compression="") as w:
        ci = w.add_topic("/probe/imu", IMU)
        cs = w.add_topic("/survey/station", STATION)
        for i in range(20):
            w.write(ci, imu_cdr(i), T0 + i)
        w.write(cs, station_cdr(store, 4), T0 + 20)
    fast = list(bag.read_messages(p))
    slow = list(bag.read_messages(p, fast=False))
    with AnyReader([p]) as r:
        theirs = [r.deserialize(raw, c.msgtype) for c, _t, raw in r.messages()]
    assert [m.topic for m, _ in fast] == ["/probe/imu"] * 20 + ["/survey/station"]
    for (_, (stamp, f)), (_, mine), ref in zip(fast[:20], slow[:20], theirs[:20]):
        a = ref.linear_acceleration
        assert stamp == (ref.header.stamp.sec, ref.header.stamp.nanosec) and f == (a.x, a.y, a.z)
        b = mine.linear_acceleration
        assert (b.x, b.y, b.z) == f
    assert slow[-1][1].station_id == fast[-1][1].station_id == theirs[-1].station_id == 4
    assert fast[-1][1].warnings == theirs[-1].warnings
    assert [v for _, v in bag.read_messages(p, ["/survey/station"], decode=False)] == [None]


def test_a_station_recorded_with_an_older_definition_is_read_with_the_bags_own(tmp_path):
    from inclinometer_calib.io import surveystation

    # the definition before the stations had one north: no azimuth_true_deg (its positions were
    # along grid north, its azimuth true)
    old = bag.message_definition(STATION).replace("float64 azimuth_true_deg\n", "", 1)
    assert old != bag.message_definition(STATION)
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(old, STATION))
    data = station_cdr(store, 3)          # azimuth 0.5 + k, grid azimuth 0.5 + k' along the field list
    p = tmp_path / "old.mcap"
    with bag.BagWriter(p, compression="") as w:
        w.write(w.add_topic("/survey/station", STATION, definition=old, type_hash=""), data, T0)
    (_, msg), = bag.read_messages(p)
    assert not hasattr(msg, "azimuth_true_deg")
    d = surveystation.from_msg(msg)
    assert d["azimuth_reference"] == "grid" and d["azimuth_true_deg"] == msg.azimuth_deg
    assert d["azimuth_deg"] == msg.azimuth_grid_deg


def test_directory_layout_rosbags_checks_hashes(tmp_path):
    d = tmp_path / "survey1"
    write_imu_bag(d, n=50)
    assert (d / "metadata.yaml").is_file() and (d / "survey1_0.mcap").is_file()
    with AnyReader([d]) as r:  # verifies type_description_hash against the embedded schema
        conn = r.connections[0]
        assert conn.digest == bag.type_hash(IMU)
        assert sum(1 for _ in r.messages()) == 50
    # a wrong hash in metadata.yaml is caught by rosbags: proves the check is live
    bad = tmp_path / "bad"
    shutil.copytree(d, bad)
    (bad / "survey1_0.mcap").rename(bad / "bad_0.mcap")
    text = (d / "metadata.yaml").read_text().replace(bag.type_hash(IMU), "RIHS01_" + "0" * 64)
    (bad / "metadata.yaml").write_text(text.replace("survey1_0.mcap", "bad_0.mcap"))
    with pytest.raises(Exception, match="hash mismatch"):
        with AnyReader([bad]):
            pass
    assert sum(1 for _ in bag.open_bag(d).messages()) == 50


def test_chunks_bounded_by_time_and_tick(tmp_path):
    p = tmp_path / "t.mcap"
    with bag.BagWriter(p, max_chunk_s=0.25, chunk_size=1 << 30) as w:
        cid = w.add_topic("/probe/imu", IMU)
        for i in range(200):  # 2 s of log time at 100 Hz
            w.write(cid, imu_cdr(i), T0 + i * 10_000_000)
        size_before = p.stat().st_size
        w.write(cid, imu_cdr(999), time.time_ns())  # arms a chunk at "now"
        assert not w.tick(time.time_ns())
        assert w.tick(time.time_ns() + 300_000_000)  # idle: the timer closes it
        assert p.stat().st_size > size_before  # ... and it is on disk already
    with open(p, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 8
    for c in chunks:
        assert c.message_end_time - c.message_start_time < 250_000_000


def test_the_writers_message_path_gives_the_files_mcap_add_message_gives_byte_for_byte(tmp_path, monkeypatch):
    """BagWriter adds messages to the mcap writer's open chunk itself (bag._fast_message_add); the
    file is the one the library's ``Writer.add_message`` writes: several channels, times out of
    order, chunks closed by size (a 4 kB chunk) and by time, message indexes and statistics."""
    def write(folder):
        folder.mkdir()
        with bag.BagWriter(folder / "same.mcap", chunk_size=4096, max_chunk_s=0.5) as w:
            a = w.add_topic("/probe/imu", IMU)
            b = w.add_topic("/probe/temperature", "sensor_msgs/msg/Temperature")
            for i in range(300):
                w.write(a, imu_cdr(i), T0 + i * 10_000_000 + (7_000_000 if i % 5 == 0 else 0), T0 + i)
                if i % 3 == 0:
                    w.write(b, bytes(range(i % 40)), T0 + i * 10_000_000 - 3_000_000)
        return (folder / "same.mcap").read_bytes()

    fast = write(tmp_path / "fast")
    monkeypatch.setattr(bag, "_fast_message_add", lambda writer, chunk_size: None)
    library = write(tmp_path / "library")
    assert fast == library
    with open(tmp_path / "fast" / "same.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.message_count == 400 and len(summary.chunk_indexes) > 10


def test_compressions(tmp_path):
    assert "zstd" in bag.available_compressions()
    for comp in bag.available_compressions():
        p = tmp_path / f"c_{comp or 'none'}.mcap"
        write_imu_bag(p, n=20, compression=comp or "none")
        assert len(list(read_ros2_messages(str(p)))) == 20
        assert len(list(bag.open_bag(p).messages())) == 20
    with pytest.raises(ValueError):
        bag.BagWriter(tmp_path / "x.mcap", compression="brotli")


def test_never_overwrites(tmp_path):
    p = tmp_path / "good.mcap"
    write_imu_bag(p, n=10)
    before = p.read_bytes()
    with pytest.raises(FileExistsError):
        bag.BagWriter(p)
    assert p.read_bytes() == before
    d = tmp_path / "dirbag"
    write_imu_bag(d, n=10)
    with pytest.raises(FileExistsError):
        bag.BagWriter(d)
    with pytest.raises(FileExistsError):
        bag.recover(p, d)
    assert len(list(bag.open_bag(d).messages())) == 10


def test_unknown_type_recorded_without_definition(tmp_path):
    p = tmp_path / "u.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with bag.BagWriter(p) as w:
            cid = w.add_topic("/strange", "nopkg/msg/Nothing")
            w.write(cid, b"\x00\x01\x00\x00abcd", T0)
    assert any("nopkg/msg/Nothing" in str(c.message) for c in caught)
    rd = bag.open_bag(p)
    (m,) = list(rd.messages())
    assert m.type == "nopkg/msg/Nothing" and m.data == b"\x00\x01\x00\x00abcd"
    assert rd.topics["/strange"].definition == ""


# ---------------------------------------------------------------------------------------------
# damaged files


def _chunk_layout(p):
    with open(p, "rb") as f:
        summary = make_reader(f).get_summary()
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def _msgs_in(chunks, n, dt_ns):
    times = [T0 + i * dt_ns for i in range(n)]
    return sum(1 for t in times for c in chunks if c.message_start_time <= t <= c.message_end_time)


def test_truncated_file_clear_error_and_recover(tmp_path):
    n, dt = 600, 10_000_000
    good = tmp_path / "good.mcap"
    write_imu_bag(good, n=n, dt_ns=dt, max_chunk_s=0.5)
    chunks = _chunk_layout(good)
    assert len(chunks) >= 10
    cut_chunk = chunks[6]
    cut = cut_chunk.chunk_start_offset + cut_chunk.chunk_length // 2
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(good.read_bytes()[:cut])
    expected = _msgs_in(chunks[:6], n, dt)
    assert 0 < expected < n

    rd = bag.open_bag(damaged)
    got = []
    with pytest.raises(bag.BagError) as exc:
        for m in rd.messages():
            got.append(m)
    err = exc.value
    assert err.path == str(damaged) and err.offset == cut_chunk.chunk_start_offset
    assert "truncated CHUNK record" in str(err) and str(cut_chunk.chunk_start_offset) in str(err)
    assert len(got) == expected  # everything before the damage was delivered
    assert [TS.deserialize_cdr(m.data, IMU).angular_velocity.z for m in got] == \
        [float(i) for i in range(expected)]

    fixed = tmp_path / "fixed.mcap"
    report = bag.recover(damaged, fixed)
    assert report.saved == expected and report.errors and not report.finalized_source
    assert report.per_topic == {"/probe/imu": expected}
    assert len(list(read_ros2_messages(str(fixed)))) == expected
    with AnyReader([fixed]) as r:
        assert sum(1 for _ in r.messages()) == expected
    rd2 = bag.open_bag(fixed)
    assert len(list(rd2.messages())) == expected and rd2.finalized
    # recovered into a directory: rosbags opens it through metadata.yaml (hash check too)
    fixed_dir = tmp_path / "fixed_dir"
    bag.recover(damaged, fixed_dir)
    with AnyReader([fixed_dir]) as r:
        assert sum(1 for _ in r.messages()) == expected


def test_unfinalized_file_keeps_everything(tmp_path):
    # a crash right after a chunk: no data-end, no summary
    good = tmp_path / "good.mcap"
    write_imu_bag(good, n=300, max_chunk_s=0.5)
    chunks = _chunk_layout(good)
    last = chunks[-1]
    with open(good, "rb") as f:
        data = f.read()
    # end of the last chunk's message indexes = start of the next record after them
    end = last.chunk_start_offset + last.chunk_length + last.message_index_length
    crashed = tmp_path / "crashed.mcap"
    crashed.write_bytes(data[:end])
    rd = bag.open_bag(crashed)
    got = list(rd.messages(strict=False))
    assert len(got) == 300
    assert rd.errors and "not finalized" in str(rd.errors[0])
    with pytest.raises(bag.BagError, match="not finalized"):
        list(bag.open_bag(crashed).messages())
    assert bag.recover(crashed, tmp_path / "ok.mcap").saved == 300


def _library_read_count(path):
    """Messages mcap's own sequential reader yields before it gives up (it stops at damage)."""
    n = 0
    try:
        with open(path, "rb") as f:
            for _ in NonSeekingReader(f, validate_crcs=True).iter_messages(log_time_order=False):
                n += 1
    except Exception:  # noqa: BLE001 - the library's reaction to the damage, whatever it is
        pass
    return n


# damage in one chunk record: (offset from the chunk's start, bytes written there or None for a
# flipped byte, whether the chunk's messages are lost)
CHUNK_DAMAGE = {
    "compressed data": (lambda c: c.chunk_length - 20, None, True),
    "compression string length": (lambda c: 9 + 28, struct.pack("<I", 10**6), True),
    # runs past the record: the record's own length bounds the data, which passes its CRC
    "compressed data length": (lambda c: 9 + 28 + 4 + 4, struct.pack("<Q", 10**9), False),
}


@pytest.mark.parametrize("where", sorted(CHUNK_DAMAGE))
def test_corrupt_chunk_skipped_rest_kept(tmp_path, where):
    n, dt = 400, 10_000_000
    good = tmp_path / "good.mcap"
    write_imu_bag(good, n=n, dt_ns=dt, max_chunk_s=0.5)
    chunks = _chunk_layout(good)
    bad_chunk = chunks[3]
    data = bytearray(good.read_bytes())
    offset, patch, lost = CHUNK_DAMAGE[where]
    pos = bad_chunk.chunk_start_offset + offset(bad_chunk)
    if patch is None:
        data[pos] ^= 0xFF
    else:
        data[pos:pos + len(patch)] = patch
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(bytes(data))
    expected = n - _msgs_in([bad_chunk], n, dt) if lost else n
    rd = bag.open_bag(corrupt)
    got = list(rd.messages(strict=False))
    assert len(got) == expected  # every other chunk, also those after the damaged one
    assert rd.finalized  # the summary after the data section is intact
    if lost:
        assert len(rd.errors) == 1 and rd.errors[0].offset == bad_chunk.chunk_start_offset
        assert "damaged chunk" in str(rd.errors[0])
    else:
        assert not rd.errors
    # mcap's own reader gets no further (a damaged length inside a chunk ends its stream)
    assert _library_read_count(corrupt) <= expected
    report = bag.recover(corrupt, tmp_path / "r.mcap")
    assert report.saved == expected


def test_not_an_mcap(tmp_path):
    p = tmp_path / "junk.mcap"
    p.write_bytes(b"hello world, definitely not mcap")
    with pytest.raises(bag.BagError, match="not an MCAP file") as exc:
        bag.open_bag(p)
    assert exc.value.offset == 0
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(bag.BagError):
        bag.open_bag(empty)


# ---------------------------------------------------------------------------------------------
# a write the operating system refuses (a full disk)


def _refusing_writes_past(limit):
    """Context: the kernel refuses every write of this process past ``limit`` bytes of a file
    (RLIMIT_FSIZE: EFBIG, after writing what fits — a torn write, as a disk that fills leaves it)."""
    import contextlib
    import resource
    import signal

    @contextlib.contextmanager
    def ctx():
        old_sig = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # EFBIG instead of the signal
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
        try:
            yield
        finally:   # nothing else of this process writes in between (no output, no logging)
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            signal.signal(signal.SIGXFSZ, old_sig)
    return ctx()


def test_a_refused_write_ends_the_file_where_readers_read_it_whole(tmp_path):
    """A write refused at any byte of the file (the header, a chunk, its message indexes, the
    summary while finalizing): the writer raises the OSError, keeps it, cuts the file back to its
    last whole record and writes nothing more; the file then reads as an unfinalized bag holding
    exactly ``committed_counts()``, and ``recover`` rewrites it.  A header that does not fit leaves
    no file at all."""
    import errno

    n, dt = 120, 10_000_000
    data = [imu_cdr(i) for i in range(n)]

    def record(path):
        w = bag.BagWriter(path, compression="none", max_chunk_s=0.1)   # a chunk every 10 messages
        cid = w.add_topic("/probe/imu", IMU)
        for i in range(n):
            w.write(cid, data[i], T0 + i * dt)
        w.close()
        return w

    size = os.path.getsize(record(tmp_path / "whole.mcap").path)
    cases = {"header": 0, "chunk": 0, "finalizing": 0}
    for limit in range(0, size, 37):
        path = tmp_path / f"cut{limit}.mcap"
        refused = None
        with _refusing_writes_past(limit):
            try:
                record(path)
            except OSError as exc:
                refused = exc
        assert refused is not None and refused.errno == errno.EFBIG, limit
        if not path.exists():      # the header did not fit: nothing left behind
            cases["header"] += 1
            continue
        rd = bag.open_bag(path)
        got = list(rd.messages(strict=False))
        assert len(rd.errors) == 1, (limit, rd.errors)
        reason = rd.errors[0].reason
        assert reason.startswith(("file ends without a data-end record", "summary section or footer")), reason
        cases["finalizing" if len(got) == n else "chunk"] += 1
        assert [TS.deserialize_cdr(m.data, IMU).angular_velocity.z for m in got] == \
            [float(i) for i in range(len(got))]
        assert len(got) % 10 == 0 or len(got) == n          # whole chunks only
        assert bag.recover(path, tmp_path / f"rec{limit}.mcap").saved == len(got)
    assert all(cases.values()), cases

    # the writer's account of what the file holds, and nothing written after a refusal
    path = tmp_path / "account.mcap"
    w = bag.BagWriter(path, compression="none", max_chunk_s=0.1)
    cid = w.add_topic("/probe/imu", IMU)
    for i in range(35):
        w.write(cid, data[i], T0 + i * dt)
    with _refusing_writes_past(os.path.getsize(path) + 100):   # less than the next chunk
        with pytest.raises(OSError) as exc:
            for i in range(35, n):
                w.write(cid, data[i], T0 + i * dt)
    assert w.error is exc.value and w.closed
    held = len(list(bag.open_bag(path).messages(strict=False)))
    assert w.committed_counts() == {"/probe/imu": held} and held == 30   # the chunk that tore is not counted
    topic, last, log_time = w.last_committed()
    assert topic == "/probe/imu" and last == data[held - 1] and log_time == T0 + (held - 1) * dt
    size = os.path.getsize(path)
    with pytest.raises(OSError, match="nothing more is written"):
        w.write(cid, data[0], T0 + n * dt)
    w.close()                                                 # no finalizing after a refusal
    assert os.path.getsize(path) == size


def test_a_bag_written_under_a_temporary_name_records_the_name_it_ends_with(tmp_path):
    """``output_path`` writes ``.x.part-<pid>.mcap`` and renames it ``x.mcap``: the bag's rosbag2
    metadata names ``x.mcap`` (it named the temporary file)."""
    import yaml

    from inclinometer_calib.core.output import final_name, output_path

    assert final_name(tmp_path / ".run.part-123.mcap") == tmp_path / "run.mcap"
    assert final_name(tmp_path / "run.mcap") == tmp_path / "run.mcap"
    with output_path(tmp_path / "x.mcap") as tmp:
        assert tmp.name != "x.mcap"
        write_imu_bag(tmp, n=3)
    with open(tmp_path / "x.mcap", "rb") as f:
        meta = [m for m in make_reader(f).iter_metadata() if m.name == "rosbag2"]
    info = yaml.safe_load(meta[0].metadata["serialized_metadata"])
    assert info["relative_file_paths"] == ["x.mcap"] and info["files"][0]["path"] == "x.mcap"

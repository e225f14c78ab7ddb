"""The output station's one field table (inclinometer_calib/io/surveystation.py) against the message
definition as ``rosbags`` parses msg/SurveyStation.msg, and its forms: a message read back through
CDR, a recording that predates fields, the Parquet types, the CSV columns."""
import math
import pathlib

import numpy as np
import pytest

from inclinometer_calib.io import surveystation
from inclinometer_calib.io.topics import STATION_TYPE

pytest.importorskip("rosbags.typesys")
MSG = pathlib.Path(__file__).resolve().parents[2] / "msg" / "SurveyStation.msg"


@pytest.fixture(scope="module")
def store():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    st = get_typestore(Stores.ROS2_JAZZY)
    st.register(get_types_from_msg(MSG.read_text(), STATION_TYPE))
    return st


def _spelled(kind, rest) -> str:
    """A rosbags field definition spelled as a .msg line spells its type."""
    from rosbags.typesys.base import Nodetype

    if kind == Nodetype.BASE:
        return rest[0]
    (ek, er), n = rest
    return f"{_spelled(ek, er)}[{n or ''}]"


def test_the_field_table_is_the_message_definition_field_for_field_in_order(store):
    fields = [(name, _spelled(kind, rest)) for name, (kind, rest) in store.fielddefs[STATION_TYPE][1]
              if name != "header"]
    assert [(f.name, f.ros_type) for f in surveystation.FIELDS] == fields


def _message(store, **overrides):
    """A rosbags SurveyStation with a distinct value in every field, serialized and read back."""
    cls = store.types[STATION_TYPE]
    values = {}
    for k, f in enumerate(surveystation.FIELDS):
        base = f.ros_type.partition("[")[0]
        v = {"float64": 0.5 + k, "uint32": k, "uint8": k % 3, "bool": k % 2 == 0, "string": f"s{k}"}[base]
        if f.ros_type == "string[]":
            v = ["a warning", "another"]
        elif f.ros_type.endswith("]"):
            v = np.arange(int(f.ros_type[8:-1]), dtype=float) + k
        values[f.name] = v
    values.update(overrides)
    T = store.types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=250_000_000),
                                   frame_id="probe")
    msg = cls(header=hdr, **values)
    return store.deserialize_cdr(store.serialize_cdr(msg, STATION_TYPE), STATION_TYPE), values


def test_a_message_becomes_the_dict_of_every_field_and_back(store):
    msg, values = _message(store)
    d = surveystation.from_msg(msg)
    assert list(d) == list(surveystation.DICT_KEYS)
    assert d["stamp"] == 1_700_000_000 + 0.25
    for f in surveystation.FIELDS:
        want = values[f.name]
        assert d[f.name] == (list(want) if f.ros_type.endswith("]") else want), f.name
        assert type(d[f.name]) in (int, float, bool, str, list), f.name      # plain Python, not numpy
    back = surveystation.to_msg(d, type("Msg", (), {})())
    assert {f.name: getattr(back, f.name) for f in surveystation.FIELDS} == {k: d[k] for k in surveystation.NAMES}
    with pytest.raises(KeyError, match="not a SurveyStation field"):
        surveystation.to_msg({"drift": 1.0}, back)


def test_a_recording_that_predates_a_field_reads_it_as_its_missing_value():
    class Old:                      # the fields a recording of the first release held, no trajectory
        header = type("H", (), {"stamp": type("T", (), {"sec": 5, "nanosec": 0})})()
        warnings = ()

    required = [f for f in surveystation.FIELDS if f.missing is None]
    for f in required:
        setattr(Old, f.name, [] if f.ros_type.endswith("]") else 0)
    d = surveystation.from_msg(Old())
    for f in surveystation.FIELDS:
        if f.missing is not None:
            want = list(f.missing) if isinstance(f.missing, tuple) else f.missing
            assert d[f.name] == want or (isinstance(want, float) and math.isnan(d[f.name])), f.name


def test_the_parquet_row_and_types_cover_the_fields_and_refuse_another():
    pa = pytest.importorskip("pyarrow")
    types = dict(surveystation.arrow_types(pa))
    assert list(types) == list(surveystation.NAMES)
    assert types["raw_gravity_mps2"] == pa.list_(pa.float64(), 3) and types["warnings"] == pa.list_(pa.string())
    assert types["station_id"] == pa.uint32() and types["status"] == pa.uint8()
    with pytest.raises(ValueError, match="not SurveyStation fields"):
        surveystation.to_row({"station_id": 1, "drift": 2.0})


def test_the_csv_names_a_column_for_fields_of_the_table_only_and_each_once():
    assert set(surveystation.CSV_NAMES) <= set(surveystation.NAMES)
    assert len(set(surveystation.CSV_COLUMNS)) == len(surveystation.CSV_COLUMNS)
    assert set(surveystation.CSV_NAMES.values()) <= set(surveystation.CSV_COLUMNS)

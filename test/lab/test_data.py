"""Reading the lab's logs (:mod:`inclinometer_calib.lab.data`)."""
import contextlib
import io

import numpy as np
import pytest

from inclinometer_calib.apps.cli import main
from inclinometer_calib.lab import data


@pytest.fixture
def logs(tmp_path):
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", "--out", str(tmp_path), "--seed", "7",
                     "--rate", "25"]) == 0
    with open(tmp_path / "val.csv", "a") as fh:        # a row the reader rejects: a line said each time
        fh.write("not-a-time,0,0,9.8,20000,0,45000,25,,,,\n")
    return tmp_path / "cal.csv", tmp_path / "val.csv"


def _fields(st):
    return {k: v for k, v in vars(st).items() if isinstance(v, np.ndarray) and v.dtype != object}


def test_the_same_logs_read_again_are_a_copy_of_the_first_reading_and_say_the_same(logs, monkeypatch):
    cal, val = logs
    reads = []
    read = data._read_logs
    monkeypatch.setattr(data, "_read_logs", lambda *a: reads.append(a) or read(*a))
    said_first, said_again = [], []
    first = data.load_logs(cal, val, warn=said_first.append)
    again = data.load_logs(cal, val, warn=said_again.append)
    assert len(reads) == 1                                          # read once, then taken again
    assert said_first and said_again == said_first                  # the rejected row is said both times
    assert any("not-a-time" in s or "row" in s for s in said_first), said_first
    for k, v in _fields(first).items():
        np.testing.assert_array_equal(getattr(again, k), v, err_msg=k)
    assert [str(x) for x in again.losses] == [str(x) for x in first.losses]
    # a copy: what one caller changes, the next reading does not see
    again.g[:] = 0.0
    third = data.load_logs(cal, val)
    assert len(reads) == 1 and np.array_equal(third.g, first.g)
    # another role or other bytes under the same name: read anew
    data.load_logs(cal)
    assert len(reads) == 2
    text = val.read_text().splitlines(keepends=True)
    val.write_text("".join(text[:len(text) // 2]))
    half = data.load_logs(cal, val)
    assert len(reads) == 3 and len(half.g) < len(first.g)


def test_a_set_of_logs_longer_than_the_cache_holds_is_read_each_time(logs, monkeypatch):
    cal, val = logs
    reads = []
    read = data._read_logs
    monkeypatch.setattr(data, "_read_logs", lambda *a: reads.append(a) or read(*a))
    monkeypatch.setattr(data, "LOAD_CACHE_MAX_SAMPLES", 10)
    data._loaded.clear()
    data.load_logs(cal, val)
    data.load_logs(cal, val)
    assert len(reads) == 2 and not data._loaded


def test_a_log_that_cannot_be_read_fails_as_it_did_and_is_not_kept(tmp_path, logs):
    cal, _ = logs
    missing = tmp_path / "nowhere.csv"
    with pytest.raises(OSError):
        data.load_logs(cal, missing)
    assert all(str(missing) not in str(k) for k in data._loaded.keys())

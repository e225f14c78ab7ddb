"""The package's one memo (:mod:`inclinometer_calib.core.memo`)."""
import numpy as np

from inclinometer_calib.core.memo import CopyMemo


def test_values_go_in_and_come_out_as_copies():
    memo = CopyMemo(2)
    value = {"a": np.arange(3.0)}
    memo.put("k", value)
    value["a"][0] = 99.0                      # the caller's change after putting it
    got = memo.get("k")
    assert got["a"][0] == 0.0
    got["a"][1] = -1.0                        # a getter's change to what it got
    assert memo.get("k")["a"].tolist() == [0.0, 1.0, 2.0]
    assert memo.get("missing") is None and memo.get("missing", 7) == 7


def test_the_least_recently_used_goes_first():
    memo = CopyMemo(2)
    memo.put("a", 1)
    memo.put("b", 2)
    assert memo.get("a") == 1                 # "a" used last: "b" is the oldest now
    memo.put("c", 3)
    assert "b" not in memo and memo.keys() == ["a", "c"] and len(memo) == 2
    memo.put("a", 4)                          # put again: the newest, with its new value
    memo.put("d", 5)
    assert memo.keys() == ["a", "d"] and memo.get("a") == 4
    memo.clear()
    assert len(memo) == 0

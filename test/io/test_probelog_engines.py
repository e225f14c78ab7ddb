"""The vectorised probe-log reader (pyarrow + numpy) against the row reader, the reference.

Every case is read by both (``engine="arrow"``, ``engine="rows"``) and must give the same log —
array for array, dtype and NaN for NaN — and the same rejections, message, row and line for
message; a file that is unusable as a whole must give the same error.  The cases: the test data
files, simulated logs of every layout (plain, depth, turntable + depth), a file in which every
column of some row holds each of a catalogue of odd values (empty, blank, NaN, inf, overflow,
underscores, padded, quoted, ``nan(1)``, non-ASCII digits, labels out of range, ...), rows with the
wrong number of fields, blank and comment lines, every line ending, a BOM, non-monotonic times
around rejected rows, and seeded random edits of all of these.
"""
import gzip
import pathlib

import numpy as np
import pytest

from inclinometer_calib.io import probelog
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.probelog import HEADER, format_csv, parse_csv, read_csv

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"
FIELDS = ("t_s", "acc", "mag", "temp_c", "pose", "ref", "row", "mount", "table_deg", "md_m", "station")

#: Field values the two readers must judge alike wherever they stand.
ODD = ["", " ", "  ", "nan", "NaN", "-nan", "+nan", "inf", "-inf", "Infinity", "INF", "1e400", "-1e400", "1e-400",
       "abc", "1_0", "1__0", " 1.5", "1.5 ", "\t2", "nan(1)", "inf(", "0x10", "+.5", ".", "-", "1.",
       "1.5e+", "00.5", "1e0001", "13", "12", "1.0", "1.5", "0", "-0", "190", "-1", "180", "xy", " xy", "yz ", "zz",
       "XY", "\u0661", "\uff11", "\u00a01", "1e5", "99999", "-99999", "0.0001", "9.9", "-9.8", "19.6", "-19.6",
       "20000", "2e-5", "0.2", "1.5\x1f", "é", "250", "-50", "2.4703282292062327e-324",
       "123456789012345678901234567890", "0.1000000000000000055511151231257827", "# note"]


def _no_row_reader(*a, **kw):
    raise AssertionError("the whole file went to the row reader")


def assert_same(text, vectorised=False, **kw):
    """Both readers on ``text``: the same outcome.  ``vectorised``: the arrow reader must not hand
    the whole file to the row reader."""
    out = {}
    for engine in probelog.ENGINES:
        real = probelog._parse_rows
        if engine == "arrow" and vectorised:
            probelog._parse_rows = _no_row_reader
        try:
            out[engine] = parse_csv(text, engine=engine, **kw)
        except ValueError as exc:
            out[engine] = exc
        finally:
            probelog._parse_rows = real
    rows, arrow = out["rows"], out["arrow"]
    if isinstance(rows, Exception) or isinstance(arrow, Exception):
        assert type(arrow) is type(rows) and str(arrow) == str(rows)
        return None
    assert [str(r) for r in arrow[1]] == [str(r) for r in rows[1]]
    assert arrow[1] == rows[1]
    for f in FIELDS:
        a, r = getattr(arrow[0], f), getattr(rows[0], f)
        assert a.dtype == r.dtype and a.shape == r.shape, f
        if a.dtype == object:
            assert a.tolist() == r.tolist(), f
        else:
            np.testing.assert_array_equal(a, r, err_msg=f)
            if a.dtype.kind == "f":
                np.testing.assert_array_equal(np.signbit(a), np.signbit(r), err_msg=f)
    return rows


def _log(kind, seed=0, rate_hz=20.0):
    log = sim.run_session(sim.build_probe(1), Site(), sim.twelve_pose_session(duration_s=0.5)[:3],
                          np.random.default_rng(seed), rate_hz=rate_hz)
    i = np.arange(len(log))
    if kind in ("depth", "turntable"):
        log.md_m = np.where(i % 3 == 0, 500.0 + 0.5 * i, np.nan)
    if kind == "turntable":
        log.mount = np.array([("", "xy", "xz", "yz")[k % 4] for k in i], dtype=object)
        log.table_deg = np.where(i % 2 == 0, 1.0 * i, np.nan)
    log.ref[i % 5 == 0, 1] = 30.0          # references of every kind, incl. an azimuth
    return log


def _rows(kind, **kw):
    lines = format_csv(_log(kind, **kw)).splitlines()
    return lines[0], lines[1:]


@pytest.mark.parametrize("paren", [False, True], ids=["numbers", "numbers as text"])
@pytest.mark.parametrize("kind", ["plain", "depth", "turntable"])
def test_every_odd_value_in_every_column_is_judged_alike(kind, paren):
    # with a "(" in the file (nan(1), which pyarrow's CSV parser reads and float refuses) the
    # numeric columns are read as text and checked for the plain form; without, as float64
    head, rows = _rows(kind, rate_hz=400.0)
    n_cols = len(head.split(","))
    odd = [v for v in ODD if paren or "(" not in v]
    cases = [(c, v) for c in list(range(1, n_cols)) + [0] for v in odd]      # t_s last: a time far ahead
    assert len(rows) >= len(cases)
    for i, (c, v) in enumerate(cases):
        fields = rows[i].split(",")
        fields[c] = v
        rows[i] = ",".join(fields)
    text = "\n".join([head] + rows) + "\n"
    rows_result = assert_same(text, vectorised=True)
    # the catalogue does reach every kind of outcome: rows kept as written unusually, rejections of each step
    rej = " | ".join(str(r) for r in rows_result[1])
    for what in ("is not a number", "not finite (NaN/inf)", "is saturated", "is implausible", "is not one of 1..12",
                 "outside 0..180", "non-monotonic timestamp", "ref_azimuth_deg not finite"):
        assert what in rej
    kept = int(np.sum(rows_result[0].row <= len(cases)))        # edited rows that are still usable
    assert 0 < kept < len(cases) / 2
    if kind == "turntable":
        assert "mount='zz' is not one of" in rej and "xy" in rows_result[0].mount[:len(cases)].tolist()
    if kind != "plain":
        assert "md_m not finite" in rej


@pytest.mark.parametrize("unit", ["nT", "uT", "T"])
def test_each_magnetometer_unit_alike(unit):
    log = _log("plain")
    text = format_csv(log, mag_unit=unit)
    lines = text.splitlines()
    lines[3] = lines[3].replace(lines[3].split(",")[4], "0.2", 1)        # a field in gauss among the rest
    assert assert_same("\n".join(lines), mag_unit=unit) is not None
    assert_same(text, mag_unit="nT" if unit != "nT" else "T")               # the wrong unit: every row refused


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r"])
@pytest.mark.parametrize("extra", ["", "\n", "\n\n", " \n"])
def test_blank_comment_and_short_lines_and_every_line_ending(newline, extra):
    head, rows = _rows("depth")
    rows[2:2] = ["", "   ", ",,,,,,,,,,,,", "# comment", ",,", "\t", rows[1] + ",", ",".join(rows[4].split(",")[:-2])]
    rows[9:9] = [""] * 3
    assert_same(newline.join([head] + rows) + extra.replace("\n", newline))
    assert_same(newline.join([head] + rows))                         # no final line break
    assert_same("\ufeff" + newline.join([head] + rows) + newline)     # a BOM before the header


def test_the_time_check_counts_only_rows_kept():
    g = "0.1,0.2,-9.8,20000,1000,40000,25"
    text = "\n".join([",".join(HEADER),
                      f"1.0,{g},1,,,",
                      f"5.0,{g},13,,,",          # kept but for its pose: does not move the clock
                      f"3.0,{g},1,,,",
                      f"9.0,0.1,0.2,-19.6,20000,1000,40000,25,1,,,",   # saturated: neither
                      f"4.0,{g},1,,,",
                      f"4.0,{g},1,,,",           # repeated
                      f"3.5,{g},,190,,",         # back in time and a bad reference: the time is named
                      f"6.0,{g},,,,"])
    rows = assert_same(text)
    np.testing.assert_array_equal(rows[0].t_s, [1.0, 3.0, 4.0, 6.0])
    assert [r.row for r in rows[1]] == [2, 4, 6, 7]
    assert "does not increase (previous 4)" in str(rows[1][2]) and "previous 4" in str(rows[1][3])


@pytest.mark.parametrize("odd", ['"', "\x0b", "\x0c", "\x1c", "\u2028", "\x85", "\x00", "é", "nan(7)"])
def test_characters_that_split_lines_or_fields_differently_are_read_alike(odd):
    head, rows = _rows("plain")
    rows[3] = rows[3][:5] + odd + rows[3][5:]
    rows[6] = '"' + rows[6].replace(",", '","') + '"' if odd == '"' else rows[6] + odd
    assert_same("\n".join([head] + rows) + "\n")


def test_files_unusable_as_a_whole_give_the_same_error():
    for text in ["", "\n", "\ufeff", "t,ax\n1,2\n", ",".join(HEADER) + "\n", ",".join(HEADER),
                 ",".join(HEADER + ["mount"]) + "\n", ",".join(HEADER) + "\n0,nan,0,0,0,0,0,25,,,,\n",
                 ",".join(HEADER) + "\n\n\n", ",".join(HEADER) + "\r\n1,2\r\n"]:
        assert_same(text)
    with pytest.raises(ValueError, match="reader 'pandas' unknown"):
        parse_csv(",".join(HEADER) + "\n", engine="pandas")


def test_seeded_random_edits_are_read_alike():
    rng = np.random.default_rng(20261124)
    for it in range(60):
        head, rows = _rows(("plain", "depth", "turntable")[it % 3], seed=it)
        n_cols = len(head.split(","))
        for _ in range(int(rng.integers(1, 12))):
            i = int(rng.integers(len(rows)))
            op = int(rng.integers(6))
            fields = rows[i].split(",")
            if op <= 2:
                fields[int(rng.integers(n_cols))] = ODD[int(rng.integers(len(ODD)))]
            elif op == 3:
                fields[0] = rows[max(0, i - int(rng.integers(1, 5)))].split(",")[0]     # back in time
            elif op == 4:
                del fields[int(rng.integers(n_cols))]
            else:
                fields.insert(0, "")
            rows[i] = ",".join(fields)
        nl = ("\n", "\r\n", "\r")[int(rng.integers(3))]
        assert_same(nl.join([head] + rows) + nl, mag_unit="nT")


def test_the_shipped_logs_and_a_stranger_in_tesla_are_read_alike(tmp_path):
    import strangers as S

    for name in ("calibration.csv.gz", "validation.csv.gz"):
        path = DATA / "stranger-probe" / name
        arrow, rows = read_csv(path), read_csv(path, engine="rows")
        assert arrow[1] == rows[1] and len(arrow[0]) == len(rows[0]) > 10000
        with gzip.open(path, "rt") as fh:
            assert_same(fh.read())
    p = S.make(S.Case("tesla", mag_unit="T", hold_s=1.0, move_s=0.5), tmp_path)
    text = p["both"].read_text()
    assert assert_same(text, mag_unit="T") is not None
    assert read_csv(p["both"], mag_unit="T")[1] == read_csv(p["both"], mag_unit="T", engine="rows")[1] == []


def test_only_the_lines_that_fail_a_check_go_through_the_row_code(monkeypatch):
    head, rows = _rows("turntable", rate_hz=200.0)
    rows[10] = rows[10].replace(rows[10].split(",")[1], "nan", 1)
    rows[20] = rows[20] + ",1"
    rows[30] = ",".join(rows[30].split(",")[:12] + [" xy"] + rows[30].split(",")[13:])   # valid, written oddly
    seen = []
    real = probelog._parse_row
    monkeypatch.setattr(probelog, "_parse_row", lambda fields, *a: seen.append(fields) or real(fields, *a))
    log, rej = parse_csv("\n".join([head] + rows) + "\n")
    assert len(seen) == 3 and len(rows) > 300
    assert [r.row for r in rej] == [11, 21] and 31 in log.row and log.mount[log.row == 31][0] == "xy"


def test_a_file_that_is_not_utf8_is_refused_alike(tmp_path):
    head, rows = _rows("plain")
    rows[4] = rows[4].replace(",", ",\xff", 1)
    p = tmp_path / "latin.csv"
    p.write_bytes(("\n".join([head] + rows) + "\n").encode("latin-1"))
    for engine in probelog.ENGINES:
        with pytest.raises(UnicodeDecodeError):
            read_csv(p, engine=engine)


def test_a_header_holding_a_line_break_of_splitlines_is_read_alike():
    head, rows = _rows("plain")
    assert_same("\n".join([head + "\x0bjunk"] + rows) + "\n")
    assert_same("\n".join([head + "\x0b"] + rows) + "\n")


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r", "\n\r"])
def test_lines_are_found_across_block_edges(newline):
    text = newline.join(f"{k}," + "x" * (k % 7) for k in range(200))
    body = memoryview(text.encode())
    which = np.arange(0, len(text.splitlines()), 3)
    for block in (5, 7, 64, 1 << 20):
        got = list(probelog._lines(body, which, "\r" in newline, block=block))
        assert got == [text.splitlines()[k] for k in which]


def test_the_arrow_readers_columns_are_pyarrows_own_conversion_without_importing_pandas(tmp_path):
    """``probelog._numpy`` reads a column from its buffers: float64 (nulls as NaN), boolean and
    int32, chunked and sliced, equal to pyarrow's ``to_numpy``; a process that reads a log never
    imports pandas (pyarrow's conversion did: a quarter of a CPU-second each)."""
    import subprocess
    import sys

    pa = pytest.importorskip("pyarrow")
    pc = pytest.importorskip("pyarrow.compute")
    rng = np.random.default_rng(5)
    for _ in range(60):
        n = int(rng.integers(0, 40))
        values = [None if rng.random() < 0.2 else float(rng.normal()) for _ in range(n)]
        col = pa.chunked_array([pa.array(values[:n // 3], pa.float64()), pa.array(values[n // 3:], pa.float64())],
                               type=pa.float64()).slice(int(rng.integers(0, 4)))
        for arr in (col, col.is_null(), pc.fill_null(pc.cast(col, pa.int32(), safe=False), -1)):
            got, want = probelog._numpy(arr), arr.to_numpy()
            assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
            assert got.flags.writeable
    path = tmp_path / "log.csv"
    path.write_text(format_csv(sim.run_session(sim.build_probe(3), Site(), sim.twelve_pose_session(),
                                               np.random.default_rng(3))))
    code = ("import sys; from inclinometer_calib.io.probelog import read_csv; "
            f"log = read_csv({str(path)!r}, engine='arrow')[0]; assert len(log) > 1000; "
            "print('pandas' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"

"""WITS level 0 out (:mod:`inclinometer_calib.rig.wits`), read back by a parser written here from the
WITS0 framing rules (``&&`` CR LF, lines ``RRII`` + value, ``!!`` CR LF), not with our encoder:
every item of record 07 in the WITS dictionary's metric and FPS units, items without a value left
out, the corrected azimuth and north/east along one north (a receiver's own minimum curvature lands
on 0718/0719), several TCP clients served at once, a stalled or vanished client dropped without the
others losing a record.

The units are the WITS dictionary's for record 7 (as vendored in mwdstd/mwdstdwits,
src/wits-dictionary.ts): depths and positions M / F, angles DEG, dogleg severity (0720 SDLS) DGHM /
DGHF — degrees per hundred metres / feet."""
import datetime as dt
import io
import math
import socket
import time

import pytest

from inclinometer_calib.rig import wits
from wits_parser import parse_wits0


STATION = {"measured_depth_m": 1523.4, "tvd_m": 1402.18, "drift_deg": 34.567, "azimuth_magnetic_deg": 120.1,
           "azimuth_deg": 121.75, "magnetic_toolface_deg": 45.0, "gravity_toolface_deg": 310.25, "north_m": -250.5,
           "east_m": 433.12, "dls_deg_per_30m": 2.5}


def test_a_station_is_one_record_07_with_every_item():
    when = dt.datetime(2026, 11, 23, 14, 5, 9, tzinfo=dt.timezone.utc)
    raw = wits.encode(STATION, 17, well_id="NO 15/9-F-12", hole_section=2, when=when)
    assert raw.startswith(b"&&\r\n") and raw.endswith(b"!!\r\n")
    (rec,) = parse_wits0(raw)
    assert rec[(7, 1)] == "NO 15/9-F-12" and rec[(7, 2)] == "2" and rec[(7, 3)] == "7" and rec[(7, 4)] == "17"
    assert rec[(7, 5)] == "261123" and rec[(7, 6)] == "140509" and rec[(7, 12)] == "MWD"
    expect = {8: 1523.4, 9: 1402.18, 11: 1523.4, 13: 34.567, 14: 120.1, 15: 121.75, 16: 45.0, 17: 310.25,
              18: -250.5, 19: 433.12, 20: 2.5 * 100 / 30}          # the dictionary's DGHM: deg per 100 m
    for item, v in expect.items():
        assert float(rec[(7, item)]) == pytest.approx(v, abs=0.005), item
    assert rec[(7, 13)] == "34.567"                                # angles to 0.001°
    # an undefined value (a vertical station's azimuth) is left out, not sent as a number
    (rec2,) = parse_wits0(wits.encode({**STATION, "azimuth_deg": math.nan, "north_m": None}, 18))
    assert (7, 15) not in rec2 and (7, 18) not in rec2 and (7, 13) in rec2


def test_fps_units_are_feet_and_degrees_per_100_ft_and_convert_back_to_the_metres_to_the_centimetre():
    (rec,) = parse_wits0(wits.encode(STATION, 1, units="ft"))
    for item, key in ((8, "measured_depth_m"), (9, "tvd_m"), (11, "measured_depth_m"), (18, "north_m"),
                      (19, "east_m")):
        assert float(rec[(7, item)]) * 0.3048 == pytest.approx(STATION[key], abs=0.005), item
    assert float(rec[(7, 20)]) == pytest.approx(2.5 * 30.48 / 30, abs=0.0005)   # DGHF: deg per 100 ft
    assert float(rec[(7, 15)]) == STATION["azimuth_deg"] and float(rec[(7, 13)]) == STATION["drift_deg"]
    with pytest.raises(ValueError, match="units 'yd'"):
        wits.encode(STATION, 1, units="yd")
    assert "units F, DEG, dogleg DGHF" in wits.describe([STATION], "ft")


@pytest.mark.parametrize("north", ["grid", "true", "magnetic"])
def test_a_wits_client_recomputing_positions_lands_on_0718_0719_along_the_north_declared(north):
    from north_well import projected_well, receiver_positions

    _, _, stations = projected_well(north)
    for units, to_m in (("m", 1.0), ("ft", 0.3048)):
        recs = parse_wits0(b"".join(wits.encode(s, k + 1, units=units) for k, s in enumerate(stations)))
        rx = receiver_positions([float(r[(7, 8)]) * to_m for r in recs], [float(r[(7, 13)]) for r in recs],
                                [float(r.get((7, 15), "0")) for r in recs])     # a vertical station: azimuth 0
        last = recs[-1]
        assert (float(last[(7, 18)]) * to_m, float(last[(7, 19)]) * to_m) == pytest.approx(rx[-1], abs=0.01)
        assert (float(last[(7, 18)]) * to_m, float(last[(7, 19)]) * to_m) == pytest.approx(
            (stations[-1]["north_m"], stations[-1]["east_m"]), abs=0.005)
    # 0715 is the azimuth from that north, 0714 the magnetic one; the record cannot say the north: describe does
    assert float(last[(7, 15)]) == pytest.approx(stations[-1][f"azimuth_{north}_deg"], abs=0.0005)
    assert float(last[(7, 14)]) == pytest.approx(stations[-1]["azimuth_magnetic_deg"], abs=0.0005)
    assert f"along {north} north" in wits.describe(stations)


def test_records_go_to_a_file_or_device_as_a_byte_stream(tmp_path):
    dev = io.BytesIO()
    for k in range(5):
        dev.write(wits.encode({**STATION, "measured_depth_m": 1500 + 30 * k}, k + 1))
    recs = parse_wits0(dev.getvalue())
    assert [float(r[(7, 8)]) for r in recs] == [1500, 1530, 1560, 1590, 1620]


def _connect(port):
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    return s


def _read_all(s, want_records, timeout=10.0):
    buf = b""
    t0 = time.monotonic()
    s.settimeout(0.5)
    while buf.count(b"!!\r\n") < want_records and time.monotonic() - t0 < timeout:
        try:
            chunk = s.recv(65536)
        except socket.timeout:
            continue
        if not chunk:
            break
        buf += chunk
    return buf


def _wait(cond, timeout=5.0):
    t0 = time.monotonic()
    while not cond() and time.monotonic() - t0 < timeout:
        time.sleep(0.01)
    return cond()


def test_several_tcp_clients_get_every_station_and_a_stalled_one_is_dropped_alone():
    import threading

    said = []
    srv = wits.WitsServer(port=0, max_buffer=256 * 1024, say=said.append, sndbuf=16 * 1024)
    n = 3000                                     # about 0.8 MB: far beyond what a stalled client may hold
    try:
        a, b, stall = _connect(srv.port), _connect(srv.port), _connect(srv.port)
        stall.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)   # it never reads
        assert _wait(lambda: srv.clients == 3)
        got = {}
        readers = [threading.Thread(target=lambda s=s, k=k: got.__setitem__(k, _read_all(s, n, timeout=30)))
                   for k, s in (("a", a), ("b", b))]
        for t in readers:
            t.start()
        for k in range(n):
            srv.send(wits.encode({**STATION, "measured_depth_m": 1000.0 + k}, k + 1))
            if k % 20 == 0:
                time.sleep(0.002)     # a survey comes station by station; the readers keep up
        for t in readers:
            t.join()
        for k in ("a", "b"):
            recs = parse_wits0(got[k])
            assert [int(r[(7, 4)]) for r in recs] == list(range(1, n + 1)), k
            assert float(recs[-1][(7, 8)]) == 1000.0 + n - 1
        assert _wait(lambda: any("stalled" in why for _, why in srv.dropped)), srv.dropped
        assert any("dropped: stalled" in m for m in said) and srv.clients == 2
        # a client that goes away is dropped; the other goes on
        b.close()
        srv.send(wits.encode(STATION, n + 1))
        assert parse_wits0(_read_all(a, 1))[-1][(7, 4)] == str(n + 1)
        assert _wait(lambda: any(why == "disconnected" for _, why in srv.dropped))
        a.close()
        stall.close()
    finally:
        srv.close()


def test_the_cli_exports_a_recorded_runs_survey_stations(tmp_path, capsys):
    from north_well import projected_survey, receiver_positions

    from inclinometer_calib.apps.cli import main
    from inclinometer_calib.io.bag import read_bag
    from inclinometer_calib.correct.reprocess import reprocess, write_probe_bag

    _, log, _, cal = projected_survey()                      # a projected site: grid north by default
    write_probe_bag(log, tmp_path / "well.mcap")
    reprocess(tmp_path / "well.mcap", tmp_path / "re.mcap", cal)
    assert main(["wits", str(tmp_path / "re.mcap"), "-o", str(tmp_path / "w.dat"), "--well-id", "X-1"]) == 0
    assert "along grid north" in capsys.readouterr().out
    recs = parse_wits0((tmp_path / "w.dat").read_bytes())
    stations = read_bag(tmp_path / "re.mcap")[0]
    assert len(recs) == len(stations) == 8 and all(r[(7, 1)] == "X-1" for r in recs)
    for r, s in zip(recs, stations):
        assert float(r[(7, 8)]) == s["measured_depth_m"] and float(r[(7, 9)]) == pytest.approx(s["tvd_m"], abs=0.005)
        assert float(r[(7, 18)]) == pytest.approx(s["north_m"], abs=0.005)
        assert s["azimuth_reference"] == "grid"
    rx = receiver_positions([float(r[(7, 8)]) for r in recs], [float(r[(7, 13)]) for r in recs],
                            [float(r.get((7, 15), "0")) for r in recs])
    assert (float(recs[-1][(7, 18)]), float(recs[-1][(7, 19)])) == pytest.approx(rx[-1], abs=0.01)
    # FPS: the same positions in feet
    assert main(["wits", str(tmp_path / "re.mcap"), "-o", str(tmp_path / "f.dat"), "--units", "ft"]) == 0
    assert "units F, DEG, dogleg DGHF" in capsys.readouterr().out
    for r, s in zip(parse_wits0((tmp_path / "f.dat").read_bytes()), stations):
        assert float(r[(7, 19)]) * 0.3048 == pytest.approx(s["east_m"], abs=0.005)
    assert main(["wits", str(tmp_path / "nowhere.mcap")]) != 0
    assert "nowhere.mcap" in capsys.readouterr().err

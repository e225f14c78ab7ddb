"""The stream engine (ROS-free): the one path from samples to stations that the nodes, reprocess and
the CLI drive — its stations do not depend on the order the topics arrive in, a record applies from
the data time it was solved at, and a calibration session that ends is solved and applied."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from inclinometer_calib.calibrate import simulate as sim  # noqa: E402
from inclinometer_calib.io.bag import open_bag, read_bag  # noqa: E402
from inclinometer_calib.calibrate.capture import CaptureSession  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.correct.engine import Expect, RecordOut, StationOut, StreamEngine  # noqa: E402
from inclinometer_calib.core.frames import Site  # noqa: E402
from inclinometer_calib.lab.field import FieldMonitor  # noqa: E402
from inclinometer_calib.correct.pipeline import SurveyProcessor  # noqa: E402
from inclinometer_calib.io.probelog import ProbeLog  # noqa: E402
from inclinometer_calib.correct.reprocess import BagFeeder, reprocess, write_probe_bag  # noqa: E402
from inclinometer_calib.io.topics import TOPIC_IMU, TOPIC_MAG  # noqa: E402

SITE = Site(total_field_nt=51000.0, dip_deg=60.0, declination_deg=2.0)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Twelve poses then a 10-station well path with depths, temperatures and references, as a bag."""
    d = tmp_path_factory.mktemp("engine")
    probe = sim.build_probe(21, ["temperature_bias:mag=2"])
    rng = np.random.default_rng(4)
    cal = sim.run_session(probe, SITE, sim.twelve_pose_session(duration_s=2.0), rng, rate_hz=100, move_s=1.0)
    well = sim.run_session(probe, SITE, sim.well_path_session(10, build_deg_per_station=4.0, duration_s=2.0, seed=3),
                           rng, rate_hz=100, move_s=1.0, t0=cal.t_s[-1] + 2.0)
    log = ProbeLog.concatenate([cal, well])
    log.pose[:] = 0                                      # a stream has no labels
    bag = d / "run.mcap"
    write_probe_bag(log, bag, serial="SN-9")
    return {"dir": d, "bag": bag, "log": log, "probe": probe}


def _messages(path):
    return list(open_bag(path).messages(strict=False))


def _engine(calibrate=True, sync=False):
    proc = SurveyProcessor(monitor=FieldMonitor(window=30))
    session = CaptureSession(site=None, probe_id="SN-9") if calibrate else None
    return StreamEngine(None, proc, session, sync_calibration=sync, expect=Expect(True, True, True))


def _stations(engine, messages):
    feeder = BagFeeder(engine)
    out = []
    for m in messages:
        feeder.feed(m)
        out += [e for e in engine.pop() if isinstance(e, (StationOut, RecordOut))]
    engine.end()
    out += [e for e in engine.pop() if isinstance(e, (StationOut, RecordOut))]
    return out


def _same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert type(x) is type(y)
        if isinstance(x, RecordOut):
            assert x.calibration.id == y.calibration.id and x.stamp == y.stamp
            continue
        for k, v in x.fields.items():
            w = y.fields[k]
            if isinstance(v, float) and math.isnan(v):
                assert isinstance(w, float) and math.isnan(w), k
            else:
                assert v == w, (x.fields["station_id"], k, v, w)


def test_stations_do_not_depend_on_the_order_the_topics_arrive(run):
    """Each topic in its own order, but the side streams (reference, temperature, depth) and the
    mag stream arriving late against the imu — as separate DDS readers deliver them under load —
    give the same stations and records, bit for bit, as the bag's own order."""
    msgs = _messages(run["bag"])
    expected = _stations(_engine(), msgs)
    assert sum(isinstance(e, StationOut) for e in expected) == 22 and any(isinstance(e, RecordOut) for e in expected)
    rng = np.random.default_rng(0)
    for lag in ({"/probe/reference": 300, "/probe/temperature": 900, "/probe/depth": 200, TOPIC_MAG: 50},
                {"/probe/reference": 2000, "/probe/depth": 5000, TOPIC_IMU: 700}):
        # a message's arrival = its place in the bag + a random lag of up to its topic's; within a
        # topic the order stays (reliable, in-order delivery): its messages fill its arrival slots in turn
        order = sorted(range(len(msgs)), key=lambda i: i + rng.uniform(0, lag.get(msgs[i].topic, 0)))
        queues = {}
        for m in msgs:
            queues.setdefault(m.topic, []).append(m)
        taken = {t: iter(q) for t, q in queues.items()}
        shuffled = [next(taken[msgs[i].topic]) for i in order]
        for topic in lag:       # within a topic, the order stays (reliable delivery)
            assert [m.log_time for m in shuffled if m.topic == topic] == sorted(m.log_time for m in msgs
                                                                                 if m.topic == topic)
        _same(_stations(_engine(), shuffled), expected)


def test_the_engine_gives_reprocess_its_stations(run):
    rep = reprocess(run["bag"], None, calibrate=True, monitor=FieldMonitor(window=30))
    mine = [e for e in _stations(_engine(), _messages(run["bag"])) if isinstance(e, StationOut)]
    _same(mine, [SimpleNamespace(fields=f) for f in rep.stations] and
          [StationOut(f, None) for f in rep.stations])
    assert rep.counts["used"] == len(run["log"]) and rep.counts["unpaired"] == 0


def test_a_record_applies_from_the_data_time_it_was_solved_at_however_late_it_arrives(run):
    """Keeping step with a calibration elsewhere: stations wait until it has taken them; a record
    that arrives late still applies to exactly the stations after its stamp."""
    msgs = _messages(run["bag"])
    whole = _stations(_engine(), msgs)
    rec = next(e for e in whole if isinstance(e, RecordOut))
    expected = [e for e in whole if isinstance(e, StationOut)]
    eng = _engine(calibrate=False, sync=True)
    feeder = BagFeeder(eng)
    got = []
    for m in msgs:
        feeder.feed(m)
        got += [e for e in eng.pop() if isinstance(e, StationOut)]
        # the calibration elsewhere is far behind: nothing may go out past what it took
        eng.calibration_progress(min(eng.t_last, rec.stamp - 5.0), 0)
    assert all(e.station.t_end < rec.stamp - 5.0 for e in got)
    eng.calibration_progress(math.inf, 1)        # it took everything and made one record ...
    assert not [e for e in eng.pop() if isinstance(e, StationOut)]   # ... which has not arrived: wait
    eng.record(rec.calibration, rec.stamp)
    eng.end()
    got += [e for e in eng.pop() if isinstance(e, StationOut)]
    assert [e.fields["coefficients_id"] for e in got] == [e.fields["coefficients_id"] for e in expected]
    assert [e.fields["drift_deg"] for e in got] == [e.fields["drift_deg"] for e in expected]
    raw = [e for e in got if not e.fields["coefficients_id"]]
    assert raw and all(e.fields["uncorrected_reason"].startswith("before calibration") for e in raw)


def test_a_record_of_another_probe_is_refused_and_every_station_says_why(run):
    other = Calibration(acc=run["probe"].acc, mag=run["probe"].mag, probe_id="SN-1", site=SITE)
    eng = _engine(calibrate=False)
    eng.set_serial("SN-9")
    assert not eng.record(other)
    out = [e for e in _stations(eng, _messages(run["bag"])) if isinstance(e, StationOut)]
    assert out and all(not e.fields["coefficients_id"] for e in out)
    assert all(e.fields["uncorrected_reason"].startswith("record refused: record ") and "probe SN-1" in
               e.fields["uncorrected_reason"] for e in out)
    assert eng.counts.records_refused == 1 and eng.counts.uncorrected == len(out)


def test_samples_that_never_find_a_partner_and_implausible_ones_are_counted(run):
    eng = _engine(calibrate=False)
    msgs = [m for i, m in enumerate(_messages(run["bag"])) if not (m.topic == TOPIC_MAG and i % 100 == 0)]
    _stations(eng, msgs)
    c = eng.counts
    assert c.imu - c.mag == c.unpaired > 0 and c.pairs == c.mag


# ---- the session that ends -----------------------------------------------------------------
def _cal_log(cut=(), rounds=2, seed=5):
    probe = sim.build_probe(seed, severity=2.0)
    rng = np.random.default_rng(seed)
    temps = tuple(25.0 + 3 * k for k in range(rounds))
    stations = [st for st in sim.twelve_pose_session(temps, duration_s=2.0) if st.pose not in cut]
    cal = sim.run_session(probe, SITE, stations, rng, rate_hz=100, move_s=1.0)
    grid = sim.run_session(probe, SITE, sim.stand_grid_session(drifts=(2, 20, 45), azimuths=(0, 120, 240),
                                                               toolfaces=(0, 150), duration_s=2.0),
                           rng, rate_hz=100, move_s=1.0, t0=cal.t_s[-1] + 2.0)
    log = ProbeLog.concatenate([cal, grid])
    log.pose[:] = 0
    return log, probe, len(stations)


def test_a_pose_missing_ends_the_sequence_when_the_probe_leaves_the_stand_and_the_survey_is_corrected(tmp_path):
    """Pose 7 cut from both rounds: the second round is used too, the two statics that are not
    poses of the sequence end it, it is solved by least squares, and every survey station is
    corrected — the first of the two too: held until the second decided that the probe had left
    the stand, the record applies from its start (it went out raw before).  The record says where
    the stand's stations lie: the captures' span."""
    log, probe, n_cal = _cal_log(cut=(7,))
    bag = tmp_path / "cut.mcap"
    write_probe_bag(log, bag)
    rep = reprocess(bag, None, calibrate=True, site=SITE)
    assert len(rep.calibrations) == 1
    cal = rep.calibrations[0]
    assert "least squares" in cal.method and rep.calibration_state == "done"
    said = " ".join(rep.calibration_warnings)
    assert "the twelve-pose sequence is over (2 statics in a row that are not poses of the sequence" in said
    assert "missing pose 7: never captured" in said
    assert len(rep.captures) == n_cal                           # both rounds, pose 7 absent from each
    survey = rep.stations[n_cal:]
    corrected = [s for s in survey if s["coefficients_id"] == cal.id]
    assert len(survey) == 18 and len(corrected) == 18
    span = cal.diagnostics["stand"]
    assert span == {"t_start": min(c.t_start for c in rep.captures), "t_end": max(c.t_end for c in rep.captures)}
    assert all(not s["coefficients_id"] for s in rep.stations[:n_cal])
    for s in corrected:
        assert abs(s["drift_deg"] - s["reference_drift_deg"]) < 0.02
    # the probe's true errors, within the least-squares solution's reach
    truth = Calibration(acc=probe.acc, mag=probe.mag, site=SITE)
    assert np.allclose(cal.triad("mag").bias, truth.triad("mag").bias, atol=5.0)


def _spliced_log(before=(), between=(), at=6, seed=5):
    """Survey stations ``before`` the stand, statics ``between`` its poses (after the ``at``-th),
    the twelve poses, then a grid of 18 survey stations: one log, unlabelled, from one probe."""
    probe = sim.build_probe(seed, severity=2.0)
    rng = np.random.default_rng(seed)
    poses = sim.twelve_pose_session(duration_s=2.0)
    rest = [st for d, a in between for st in sim.stand_grid_session(drifts=(d,), azimuths=(a,), toolfaces=(0,),
                                                                    duration_s=2.0)]
    first = [st for d, a in before for st in sim.stand_grid_session(drifts=(d,), azimuths=(a,), toolfaces=(0,),
                                                                     duration_s=2.0)]
    cal = sim.run_session(probe, SITE, first + poses[:at] + rest + poses[at:], rng, rate_hz=100, move_s=1.0)
    grid = sim.run_session(probe, SITE, sim.stand_grid_session(drifts=(2, 20, 45), azimuths=(0, 120, 240),
                                                               toolfaces=(0, 150), duration_s=2.0),
                           rng, rate_hz=100, move_s=1.0, t0=cal.t_s[-1] + 2.0)
    log = ProbeLog.concatenate([cal, grid])
    log.pose[:] = 0
    return log


def test_a_rest_on_the_stand_between_poses_is_the_stands_not_a_raw_survey_station(tmp_path):
    """A static at 45° between poses 6 and 7 (the crew paused with the probe off a pose): held —
    the survey's first station or a rest? — until pose 7 says the probe is still on the stand; it
    goes out raw with the poses, inside the stand's span the record gives, and nothing is counted
    against the run.  The whole survey after the stand is corrected."""
    from inclinometer_calib.io.accounting import stand_of, survey_raw

    bag = tmp_path / "rest.mcap"
    write_probe_bag(_spliced_log(between=[(45, 30)]), bag)
    rep = reprocess(bag, None, calibrate=True, site=SITE)
    cal = rep.calibrations[0]
    stations = rep.stamped_stations()
    assert len(rep.captures) == 12 and len(stations) == 13 + 18
    raw = [s for s in stations if not s["coefficients_id"]]
    assert len(raw) == 13 and raw[6]["reference_drift_deg"] == 45.0       # the rest, in its place
    t0, t1 = stand_of(cal)
    assert t0 <= raw[6]["stamp"] - raw[6]["duration_s"] and raw[6]["stamp"] <= t1
    assert all(s["coefficients_id"] == cal.id for s in stations[13:])
    assert survey_raw(stations, 1, 12, (t0, t1)) == ""


def test_survey_stations_before_the_stand_are_counted_raw_while_the_rest_is_corrected(tmp_path):
    """Three survey stations, then the stand, then the survey: the three go out raw "before
    calibration" — not the stand's (before its span) — a raw survey the run counts, while the
    survey after the stand is corrected (none_corrected alone could not tell: most were).
    ``reprocess`` exits 1 with the line, and the launcher's summary of what it wrote (the live
    graph's record and stations) has it as a problem: one rule, both drivers."""
    from inclinometer_calib.apps import launcher
    from inclinometer_calib.apps.cli import main
    from inclinometer_calib.io.accounting import stand_of, survey_raw

    bag = tmp_path / "first.mcap"
    write_probe_bag(_spliced_log(before=[(30, 0), (35, 120), (40, 240)]), bag)
    out = tmp_path / "run"
    out.mkdir()
    assert main(["reprocess", str(bag), "--calibrate", "-o", str(out / "survey.mcap")]) == 1
    summary = launcher.summarize_run(str(out), print_fn=lambda *a: None, loop=False)
    assert [p for p in summary["accounting"]["problems"] if "survey station(s) raw" in p] == [
        survey_raw(read_bag(out / "survey.mcap")[0], 1, 12, summary["accounting"]["stations"]["stand"])]
    rep = reprocess(bag, None, calibrate=True, site=SITE)
    cal = rep.calibrations[0]
    stations = rep.stamped_stations()
    assert [bool(s["coefficients_id"]) for s in stations] == [False] * 15 + [True] * 18
    t0, _ = stand_of(cal)
    assert all(s["stamp"] < t0 for s in stations[:3]) and all(s["stamp"] > t0 for s in stations[3:])
    said = survey_raw(stations, 1, 12, stand_of(cal))
    assert said.startswith("3 survey station(s) raw: not the stand's poses") and "3 before the stand's first" in said


def test_a_single_station_after_an_incomplete_stand_at_the_end_of_the_data_is_corrected():
    """Pose 7 never captured, then one survey station, then the data end: that station did not end
    the sequence (one stray of two), but the end did — the record solved at the end applies from its
    start, and the station, held until then, is corrected; the poses are raw and inside the span."""
    probe = sim.build_probe(5, severity=2.0)
    rng = np.random.default_rng(5)
    poses = [st for st in sim.twelve_pose_session(duration_s=2.0) if st.pose != 7]
    one = sim.stand_grid_session(drifts=(30,), azimuths=(60,), toolfaces=(0,), duration_s=2.0)
    log = sim.run_session(probe, SITE, poses + one, rng, rate_hz=100, move_s=1.0)
    eng = StreamEngine(None, SurveyProcessor(), CaptureSession(site=SITE), expect=Expect(False, True, False))
    eng.samples(log.t_s, log.gravity, log.mag, log.temp_c)
    eng.close_hold()              # the survey station closes: the session has not decided on it yet
    out = [e for e in eng.pop() if isinstance(e, StationOut)]
    assert len(out) == 11 and len(eng._undecided) == 1 and eng.settled < eng._undecided[0].t_close
    eng.end()
    ev = eng.pop()
    (rec,) = [e for e in ev if isinstance(e, RecordOut)]
    (last,) = [e for e in ev if isinstance(e, StationOut)]
    assert last.fields["coefficients_id"] == rec.calibration.id and rec.stamp < last.station.t_start
    assert abs(last.fields["drift_deg"] - 30.0) < 0.05 and eng.done
    t0, t1 = rec.calibration.diagnostics["stand"]["t_start"], rec.calibration.diagnostics["stand"]["t_end"]
    assert t1 < last.station.t_start and t0 < t1


def test_a_session_reset_while_a_station_is_held_lets_it_and_the_progress_go_on():
    """The calibration node's ~/reset while a static after the captures is undecided: the engine no
    longer holds it — its progress (``settled``, what a correction node keeping step waits for)
    moves past it instead of staying capped until the next static."""
    probe = sim.build_probe(5, severity=2.0)
    poses = [st for st in sim.twelve_pose_session(duration_s=2.0) if st.pose != 7]
    one = sim.stand_grid_session(drifts=(30,), azimuths=(60,), toolfaces=(0,), duration_s=2.0)
    log = sim.run_session(probe, SITE, poses + one, np.random.default_rng(5), rate_hz=100, move_s=1.0)
    eng = StreamEngine(None, session=CaptureSession(site=SITE), expect=Expect(False, True, False))
    eng.samples(log.t_s, log.gravity, log.mag, log.temp_c)
    eng.close_hold()
    assert eng._undecided_close is not None and eng.settled < eng._undecided_close <= eng.t_last
    eng.session.reset()
    eng.release_undecided()
    assert eng.settled >= eng.t_last and eng._undecided_close is None


def test_a_recapture_taken_after_a_long_pause_is_solved_from_and_the_record_applies_after_it():
    """The sequence ends on a 200 s pause, and the static after it is the recapture asked for: the
    session solves again with it, so that record applies after it — not from its start, which would
    correct the station with coefficients solved from itself."""
    probe = sim.build_probe(5, severity=2.0)
    rng = np.random.default_rng(5)
    poses = sim.twelve_pose_session(duration_s=2.0)
    first = sim.run_session(probe, SITE, [p for p in poses if p.pose != 12], rng, rate_hz=100, move_s=1.0)
    again = sim.run_session(probe, SITE, [poses[2]], rng, rate_hz=100, move_s=1.0, t0=first.t_s[-1] + 200.0)
    eng = StreamEngine(None, SurveyProcessor(), CaptureSession(site=SITE), expect=Expect(False, True, False))
    eng.samples(first.t_s, first.gravity, first.mag, first.temp_c)
    eng.close_hold()
    eng.session.request_recapture(3)
    eng.samples(again.t_s, again.gravity, again.mag, again.temp_c)
    eng.end()
    ev = eng.pop()
    recs = [e for e in ev if isinstance(e, RecordOut)]
    last = [e for e in ev if isinstance(e, StationOut)][-1]
    assert recs and "s without a capture before the static" in " ".join(e.text for e in ev if hasattr(e, "text"))
    assert recs[-1].stamp >= last.station.t_end and last.station.pose == 3


def test_after_the_sequence_ends_a_survey_station_near_a_missing_pose_is_not_taken(tmp_path):
    """Pose 9 (tool axis vertical) never captured: survey stations at 2° of drift look like it, but
    once the probe has left the stand they are survey stations — never a capture, never a new solve."""
    log, _, n_cal = _cal_log(cut=(9,), rounds=1)
    bag = tmp_path / "cut9.mcap"
    write_probe_bag(log, bag)
    rep = reprocess(bag, None, calibrate=True, site=SITE)
    assert len(rep.calibrations) == 1 and "least squares" in rep.calibrations[0].method
    assert sorted(c.pose for c in rep.captures) == [p for p in range(1, 13) if p != 9]
    near = [s for s in rep.stations[n_cal:] if s["reference_drift_deg"] == 2.0]
    assert len(near) == 6 and all(s["coefficients_id"] == rep.calibrations[0].id for s in near)


def test_the_sequence_ends_after_end_after_s_without_a_capture():
    log, _, n_cal = _cal_log(cut=(12,), rounds=1)
    det_t = log.t_s.copy()
    # a pause of 200 s (probe streaming on the bench) before the survey
    gap = det_t > det_t[0] + (n_cal * 3.0 + 1.0)
    log.t_s = np.where(gap, det_t + 200.0, det_t)
    eng = StreamEngine(None, SurveyProcessor(), CaptureSession(site=SITE, end_after_stations=50, end_after_s=120.0),
                       expect=Expect(False, True, False))
    eng.samples(log.t_s, log.gravity, log.mag, log.temp_c)
    eng.end()
    ev = eng.pop()
    recs = [e for e in ev if isinstance(e, RecordOut)]
    assert recs and any("s without a capture before the static" in e.text for e in ev if hasattr(e, "text"))
    first_survey = [e for e in ev if isinstance(e, StationOut)][n_cal - 1:]
    assert recs[0].stamp < first_survey[1].station.t_end


def test_a_station_the_calibration_elsewhere_still_holds_waits_for_it(tmp_path):
    """Keeping step with a calibration node whose station waits there (its temperatures late) while
    the correction has them all: the correction's station waits too — ``settled`` just before a
    station's close is not that station taken — so the record solved at it (pose 7 cut: the
    sequence ends at a survey station and applies from its start) corrects it, as offline.
    Failed before: the same station went out raw (the replay on one core, 2026-11-26)."""
    log, _, n_cal = _cal_log(cut=(7,), rounds=1)
    bag = tmp_path / "cut.mcap"
    write_probe_bag(log, bag, serial="SN-9")
    msgs = _messages(bag)
    expected = [e for e in _stations(_engine(), msgs) if isinstance(e, StationOut)]
    cal = StreamEngine(None, session=CaptureSession(site=None, probe_id="SN-9"), expect=Expect(False, True, False))
    cor = StreamEngine(None, SurveyProcessor(monitor=FieldMonitor(window=30)), None, sync_calibration=True,
                       expect=Expect(True, True, False))    # the log has no depth: nothing else holds a station
    cal_feed, cor_feed = BagFeeder(cal), BagFeeder(cor)
    temps = [m for m in msgs if m.topic == "/probe/temperature"]
    late, got, records = 0, [], []

    def step():
        # the calibration's progress first, its records on their own topic after (as live)
        cor.calibration_progress(cal.settled, cal.counts.records, cal.done)
        got.extend(e for e in cor.pop() if isinstance(e, StationOut))
        for r in records:
            cor.record(r.calibration, r.stamp)
        records.clear()
        records.extend(e for e in cal.pop() if isinstance(e, RecordOut))
        got.extend(e for e in cor.pop() if isinstance(e, StationOut))

    for i, m in enumerate(msgs):
        cor_feed.feed(m)
        if m.topic != "/probe/temperature":
            cal_feed.feed(m)
        while late < len(temps) and temps[late].log_time <= msgs[max(i - 300, 0)].log_time:
            cal_feed.feed(temps[late])      # the calibration's temperatures 300 messages behind
            late += 1
        step()
    for m in temps[late:]:
        cal_feed.feed(m)
    cal.end()
    step()
    step()
    cor.end()
    got.extend(e for e in cor.pop() if isinstance(e, StationOut))
    assert len(got) == len(expected) and n_cal < len(got)
    assert [e.fields["coefficients_id"] for e in got] == [e.fields["coefficients_id"] for e in expected]
    assert [e.fields["drift_deg"] for e in got] == [e.fields["drift_deg"] for e in expected]
    assert cor.counts.forced == 0
    # the first station after the stand, held by the calibration until the second decided: corrected
    assert got[n_cal].fields["coefficients_id"] and not any(e.fields["coefficients_id"] for e in got[:n_cal])

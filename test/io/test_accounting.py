"""The run's accounting (accounting.py): a reader is said to have taken every sample only when both
sides' final counts are known; a loss is named per reader and topic; the recorder's counts are the
recording's own."""
from inclinometer_calib.io.accounting import account, captures_of, format_account

SENT = {"imu": 1000, "mag": 1000, "temperature": 1000, "reference": 10, "depth": 10}


def progress(node, end, **taken):
    counts = dict(SENT, **taken)
    return dict(node=node, end=end, window=0, stations=0, records=0, forced=0, pairs_used=counts["imu"],
                pairs_dropped=0, **counts)


def lines_of(messages, recorded=None):
    a = account([], messages, paced=False, recorded=recorded)
    return a, format_account(a)


def test_a_reader_that_took_the_end_with_fewer_samples_is_named_with_what_it_lost():
    a, lines = lines_of([progress("probe", True), progress("correction", True, imu=900, mag=899)])
    assert "  correction LOST 100 imu, 101 mag" in lines
    assert any(p.startswith("samples lost: correction 100 imu, 101 mag") and "unpaced" in p for p in a["problems"])


def test_a_reader_that_did_not_take_the_end_is_never_said_to_have_taken_every_one():
    a, lines = lines_of([progress("probe", True), progress("calibration", False)])
    line = next(x for x in lines if x.startswith("  calibration"))
    assert "every one" not in line and "it did not take the end" in line
    assert "calibration did not take the end of the data" in a["problems"]


def test_without_the_probes_end_in_the_recording_no_reader_is_said_complete():
    a, lines = lines_of([progress("probe", False, imu=500, mag=500, temperature=500),
                         progress("correction", True, imu=400)])
    line = next(x for x in lines if x.startswith("  correction"))
    assert line == "  correction took 400 of 500 imu; the probe's end is not in the recording"
    assert any("end of the data is not in the recording" in p for p in a["problems"])


def test_the_recorder_is_counted_by_the_recording_and_its_loss_is_its_one_problem():
    # the recorder never says it ended once it lost a sample: its counts are the recording's, final
    a, lines = lines_of([progress("probe", True), progress("recorder", False, imu=10)],
                        recorded=dict(SENT, imu=990, mag=1000, temperature=997))
    assert "  recorder LOST 10 imu, 3 temperature" in lines
    assert not any("recorder did not take the end" in p for p in a["problems"])
    assert [p for p in a["problems"] if p.startswith("samples lost")] == [
        "samples lost: recorder 10 imu, 3 temperature (an unpaced replay or a live source: a slow reader loses "
        "what its queue cannot hold)"]


def test_every_reader_complete_is_a_clean_account():
    a, lines = lines_of([progress("probe", True), progress("calibration", True), progress("correction", True),
                         progress("recorder", True)], recorded=dict(SENT))
    assert a["problems"] == []
    assert [x for x in lines if x.startswith("  ")] == ["  calibration took every one", "  correction took every one",
                                                          "  recorder took every one"]


def _station(i, cid="", reason=""):
    return {"station_id": i, "coefficients_id": cid, "uncorrected_reason": reason, "drift_deg": 1.0,
            "azimuth_deg": 2.0, "toolface_deg": 3.0, "stamp": float(i)}


BEFORE = "before calibration: the calibration has not solved yet"


def test_a_calibration_that_solved_after_every_station_leaves_a_raw_survey_and_no_clean_run():
    """The survey before the calibration (a bag of the survey, then the stand): every station raw
    "before calibration" although a record was solved from 12 of them — not a clean run, said; the
    stand alone (12 stations, 12 captures: its record applies after them) and the stand's poses
    raw before a corrected survey are expected; no record, captures not known, stations raw for
    another reason: nothing said here."""
    class Record:   # what captures_of reads of a record solved from captures (two left out)
        diagnostics = {"acc": {"per_pose": {p: {"rounds": 1} for p in range(1, 11)}, "left_out": ["a", "b"]}}

    assert captures_of(Record()) == 12
    assert captures_of(type("Turntable", (), {"diagnostics": {"acc": {}}})()) is None
    survey_first = [_station(i, reason=BEFORE) for i in range(210)]
    a = account(survey_first, [], records=1, captures=12)
    assert [p for p in a["problems"] if "was corrected" in p] == [
        "none of the 210 stations was corrected: the calibration solved from 12 of them after the last (the survey "
        "came before the stand's poses?), so the survey is raw"]
    assert account(survey_first[:12], [], records=1, captures=12)["problems"] == []          # the stand alone
    stand_first = [_station(i, reason=BEFORE) for i in range(12)] + [_station(i, "abc") for i in range(12, 210)]
    assert account(stand_first, [], records=1, captures=12)["problems"] == []
    assert account(survey_first, [], records=0, captures=12)["problems"] == []   # did not solve: said elsewhere
    assert account(survey_first, [], records=1, captures=None)["problems"] == []
    refused = survey_first[:11] + [_station(11, reason="record refused: another probe's")]
    assert not any("was corrected" in p for p in account(refused, [], records=1, captures=5)["problems"])


def test_samples_of_the_input_bag_the_probe_did_not_send_are_counted_and_said():
    """A replayed bag with 300 imu samples whose mag partner is missing: the probe sends the pairs
    only; the summary says how many of the input's it did not send (they were in the probe's
    warnings only), as reprocess warns of them — the input's defect, not a loss of the run."""
    held = {"/probe/imu": 1300, "/probe/mag": 1000, "/probe/temperature": 1000, "/probe/serial": 1}
    a = account([], [progress("probe", True)], paced=True, input_counts=held)
    assert a["input"] == {"held": {"imu": 1300, "mag": 1000, "temperature": 1000}, "not_sent": {"imu": 300}}
    assert "  of the input bag's 1300 imu, 1000 mag, 1000 temperature, not sent: 300 imu (without a partner of " \
           "the same stamp on the other stream, or not decodable: the probe's warnings say which)" in format_account(a)
    assert a["problems"] == []
    whole = account([], [progress("probe", True)], input_counts={"/probe/imu": 1000, "/probe/mag": 1000})
    assert whole["input"]["not_sent"] == {} and not any("not sent" in x for x in format_account(whole))


def test_stations_raw_before_the_calibration_beyond_its_captures_are_said_not_hidden():
    """23 stations raw before a record solved from 22 captures (a sequence missing a pose ended on
    a survey station): the summary says the one more — only the calibration knows which it was, so
    it is said, not counted against the run."""
    stations = [_station(i, reason=BEFORE) for i in range(23)] + [_station(i, "abc") for i in range(23, 60)]
    a = account(stations, [], records=1, captures=22)
    assert a["problems"] == [] and a["stations"]["captures"] == 22
    line = next(x for x in format_account(a) if x.startswith("stations:"))
    assert "; uncorrected: 23 before calibration (1 more than the 22 stand captures the record was solved from: " \
           "stations that were not the stand's poses went out raw" in line, line
    exact = account(stations[:22] + stations[23:], [], records=1, captures=22)
    assert "more than the" not in next(x for x in format_account(exact) if x.startswith("stations:"))


def test_with_the_stand_span_raw_survey_stations_are_counted_and_the_stands_own_are_not():
    """The record says where the stand's poses lie (t 100–160 s): raw stations inside it — captures,
    a retake, a rest — are the stand's; raw ones before it (the survey began first) or after it are
    a raw survey, counted against the run; the "more than the captures" note is for records that
    do not say.  A station spans ``stamp`` − ``duration_s`` to ``stamp``."""
    def st(i, t, cid=""):
        return dict(_station(i, cid, "" if cid else BEFORE), stamp=float(t), duration_s=3.0)

    def run(*parts):      # one recording: ids in order
        return [dict(x, station_id=i) for i, x in enumerate(x for part in parts for x in part)]

    stand = (100.0, 160.0)
    inside = [st(i, 103 + 4 * i) for i in range(14)]                  # 12 captures, a retake, a rest
    survey = [st(20 + i, 200 + 10 * i, "abc") for i in range(30)]
    a = account(run(inside, survey), [], records=1, captures=12, stand=stand)
    assert a["problems"] == [] and a["stations"]["stand"] == [100.0, 160.0]
    assert "more than the" not in next(x for x in format_account(a) if x.startswith("stations:"))
    early = [st(90 + i, 50 + 10 * i) for i in range(3)] + [st(97, 100.5)]    # the last ends inside: the stand's
    a = account(run(early, inside, survey), [], records=1, captures=12, stand=stand)
    assert a["problems"] == ["3 survey station(s) raw: not the stand's poses (those lie at t=100.000–160.000 s), "
                             "they went out before the calibration solved — 3 before the stand's first pose (the "
                             "survey came first?)"]
    late = [st(60, 170)]
    a = account(run(inside, late, survey), [], records=1, captures=12, stand=stand)
    assert a["problems"] == ["1 survey station(s) raw: not the stand's poses (those lie at t=100.000–160.000 s), "
                             "they went out before the calibration solved — 1 after its last"]
    every = [st(i, 10 + 5 * i) for i in range(40)]                    # all inside a span that took them all
    assert "none of the 40 stations was corrected" in account(every, [], records=1, captures=12,
                                                              stand=(0.0, 300.0))["problems"][0]

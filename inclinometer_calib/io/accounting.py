"""The run's accounting: what came in, what went out, what was lost — ROS-free.

Every node of the live graph says on ``/graph/progress`` (``StreamProgress``, recorded with the
rest) what it sent or took per topic, how many stations and records it published, how many
stations went out before what they waited for had arrived, and whether it saw the end.  From the
recorded bag (all its parts) this module puts that together with the recorded stations:

* **samples**: per reader and topic, taken against sent by the probe — a loss anywhere is named;
* **stations**: published by the correction node against recorded (one per id: a restarted
  recorder receives the latest stations again), the ids' gaps, an id recorded twice with
  different values;
* **corrections**: the recorded stations without a correction and why
  (``SurveyStation.uncorrected_reason``): before the calibration solved (the stand's poses
  themselves: expected — but a station raw before the calibration outside the stand's span, as
  its record says it, is a survey station left raw, :func:`survey_raw`), a record refused
  (another probe's), no record at all;
* **patience**: stations that went out before their reference, temperatures, depth or the
  calibration's step arrived (a live source's wall-clock patience ran out);
* **restarts** the launcher made.

:func:`account` returns a dict (for ``summary.json``) whose ``problems`` are the reasons the run
is not clean, one sentence each; :func:`format_account` the summary's lines.
"""
from __future__ import annotations

import math

#: Topics a reader takes, by its role (what its counts are compared with the probe's).
SAMPLE_TOPICS = ("imu", "mag", "temperature")
SIDE_TOPICS = ("reference", "depth")
ALL_TOPICS = SAMPLE_TOPICS + SIDE_TOPICS

#: ``uncorrected_reason``'s first words (engine.BEFORE_CALIBRATION, NO_RECORD, RECORD_REFUSED).
REASONS = ("before calibration", "record refused", "no calibration record")


def last_progress(messages) -> dict:
    """The last ``StreamProgress`` of each node (``messages``: dicts in the order recorded; a
    restarted node's later messages win)."""
    out = {}
    for m in messages:
        out[m["node"]] = m
    return out


def _same_station(a: dict, b: dict) -> bool:
    keys = ("drift_deg", "azimuth_deg", "toolface_deg", "coefficients_id", "stamp")
    for k in keys:
        x, y = a.get(k), b.get(k)
        if x != y and not (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)):
            return False
    return True


def unique_stations(stations) -> tuple:
    """``(stations, conflicts)``: one per id in id order (the first recorded; a restarted recorder
    receives the latest ones again), and the ids recorded twice with different values."""
    by_id, conflicts = {}, []
    for s in stations:
        i = s["station_id"]
        if i not in by_id:
            by_id[i] = s
        elif not _same_station(by_id[i], s) and i not in conflicts:
            conflicts.append(i)
    return [by_id[i] for i in sorted(by_id)], sorted(conflicts)


def id_gaps(ids) -> list:
    """Ranges ``(first, last)`` of ids missing between the lowest and the highest recorded."""
    ids = sorted(set(ids))
    gaps = []
    for a, b in zip(ids, ids[1:]):
        if b > a + 1:
            gaps.append((a + 1, b - 1))
    return gaps


def _reason_kind(reason: str) -> str:
    for k in REASONS:
        if reason.startswith(k):
            return k
    return "unknown" if reason else "before calibration"   # a bag recorded before the field existed


def recorded_counts(paths) -> dict:
    """Messages per probe topic held by a recording's parts (``paths``), each counted once: a
    recorder restarted mid-run receives the probe's latest samples again (a stamped message is told
    by its header stamp, the unstamped depth by its publish time — the source's own — and value)."""
    from .bag import BagError, open_bag
    from .topics import TOPIC_DEPTH, TOPIC_IMU, TOPIC_MAG, TOPIC_REFERENCE, TOPIC_TEMPERATURE

    names = {TOPIC_IMU: "imu", TOPIC_MAG: "mag", TOPIC_TEMPERATURE: "temperature", TOPIC_REFERENCE: "reference",
             TOPIC_DEPTH: "depth"}
    seen = {k: set() for k in names.values()}
    for path in paths:
        try:
            for m in open_bag(path).messages(list(names), strict=False):
                key = (m.publish_time, bytes(m.data)) if m.topic == TOPIC_DEPTH else bytes(m.data[4:12])
                seen[names[m.topic]].add(key)
        except BagError:
            continue
    return {k: len(v) for k, v in seen.items()}


def stand_of(calibration):
    """``(t_start, t_end)``, data time (s): where the stations a capture session took as the stand's
    poses (captured, merged or refused) lie (``diagnostics["stand"]``, :class:`capture.CaptureSession`);
    None for a record that does not say (a turntable's, a lab fit's, one made before it was kept)."""
    span = (getattr(calibration, "diagnostics", None) or {}).get("stand") or {}
    try:
        t0, t1 = float(span["t_start"]), float(span["t_end"])
    except (KeyError, TypeError, ValueError):
        return None
    return (t0, t1) if math.isfinite(t0) and math.isfinite(t1) and t0 <= t1 else None


#: Slack (s) on the stand's span: stamps go through a message header (ns) and a record's YAML.
SPAN_SLACK_S = 1e-6


def survey_raw(stations, records: int, captures=None, stand=None) -> str:
    """The problem, one sentence, of a run whose calibration solved (``records`` > 0) but left
    survey stations raw: stations raw "before calibration" that were not the stand's.  With the
    first record's ``stand`` span (:func:`stand_of`) those are the raw ones that lie outside it
    (a station from ``stamp`` − ``duration_s`` to ``stamp``): before the stand's first pose (the
    survey, or part of it, came first) or after its last (a sequence's end the record did not
    cover); a retake or a rest on the stand lies inside and is the stand's.  Without it (an older
    record), or when every station is inside it, the whole survey raw is still told
    (:func:`none_corrected`).  Empty: nothing to say here (no record: said elsewhere, the
    calibration did not solve)."""
    if not records or not stations:
        return ""
    if stand is None:
        return none_corrected(stations, records, captures)
    t0, t1 = stand[0] - SPAN_SLACK_S, stand[1] + SPAN_SLACK_S
    before = after = 0
    for s in stations:
        if s["coefficients_id"] or _reason_kind(s.get("uncorrected_reason", "")) != "before calibration":
            continue
        end = float(s["stamp"])
        start = end - float(s.get("duration_s") or 0.0)
        if end < t0:
            before += 1
        elif start > t1:
            after += 1
    if not before + after:
        return none_corrected(stations, records, captures)
    where = " and ".join(w for w in (f"{before} before the stand's first pose (the survey came first?)" if before
                                     else "", f"{after} after its last" if after else "") if w)
    return (f"{before + after} survey station(s) raw: not the stand's poses (those lie at t={stand[0]:.3f}–"
            f"{stand[1]:.3f} s), they went out before the calibration solved — {where}")


def none_corrected(stations, records: int, captures=None) -> str:
    """The problem of a run whose calibration solved (``records`` > 0) after every one of its
    ``stations`` while some of them were not its captures (survey first, the stand's poses last):
    all went out raw "before calibration", which for the stand's poses alone is expected.
    ``captures``: how many the first record was solved from (:func:`captures_of`; a session of the
    stand alone has as many stations, all raw: its record applies after them); None, not known:
    nothing said.  Empty when a station was corrected, when there are no stations, no record (said
    elsewhere: the calibration did not solve), or stations raw for another reason (said as such)."""
    if not records or not stations or captures is None:
        return ""
    if raw_before_calibration(stations) < len(stations) or len(stations) <= captures:
        return ""
    return (f"none of the {len(stations)} stations was corrected: the calibration solved from {captures} of them "
            "after the last (the survey came before the stand's poses?), so the survey is raw")


def raw_before_calibration(stations) -> int:
    """How many of ``stations`` went out without a correction because no record applied yet
    (``uncorrected_reason`` "before calibration")."""
    return sum(1 for s in stations if not s["coefficients_id"]
               and _reason_kind(s.get("uncorrected_reason", "")) == "before calibration")


def beyond_captures(before: int, captures) -> str:
    """What ``before`` stations raw "before calibration" beyond the record's ``captures`` (None: not
    known) were, in words; empty when there are none.  For a record that does not say where the
    stand's poses lie (:func:`stand_of`; with it, :func:`survey_raw` counts them): said, not counted
    against the run — which raw ones were not the stand's (a retake, a rest, a survey station before
    the record) the record does not tell."""
    if captures is None or before <= captures:
        return ""
    return (f"{before - captures} more than the {captures} stand captures the record was solved from: stations "
            "that were not the stand's poses went out raw — a retake, a rest on the stand, or survey stations "
            "before the calibration solved")


def captures_of(calibration) -> int | None:
    """How many stand captures a calibration record was solved from: per pose the rounds the solve
    used, plus the captures it left out (:func:`twelve_position.solve_captures`'s diagnostics);
    None for a record that does not say (not solved from captures: a turntable's, a lab fit's)."""
    diag = (getattr(calibration, "diagnostics", None) or {}).get("acc") or {}
    per_pose = diag.get("per_pose")
    if not per_pose:
        return None
    return int(sum(int(v.get("rounds") or 0) for v in per_pose.values())) + len(diag.get("left_out") or ())


def first_record(calibration) -> tuple:
    """``(captures, stand)`` of a run's first record (None: no record): what :func:`survey_raw`
    and :func:`account` judge the raw stations by — :func:`captures_of`, :func:`stand_of`."""
    if calibration is None:
        return None, None
    return captures_of(calibration), stand_of(calibration)


def account(stations, progress_messages, *, restarts=None, calibration_ran=True, paced=True,
            station_node: str = "correction", source: str = "probe", recorder: str = "recorder",
            recorded=None, records: int = 0, captures=None, stand=None, input_counts=None) -> dict:
    """The run's accounting (see the module docstring).  ``stations``: the recorded station dicts
    (all parts); ``progress_messages``: the recorded ``StreamProgress`` dicts in order;
    ``restarts``: node → count; ``calibration_ran``: stations before the calibration are then
    expected to be raw, the stand's poses — not a survey station (:func:`survey_raw`: ``records``,
    the calibration records the run made, the first solved from ``captures`` over the ``stand``
    span).  ``input_counts``: a replayed
    bag's messages per topic (its summary), set against what the source sent: samples of the input
    it did not send (an imu or mag sample without a partner of the same stamp, one that does not
    decode) are counted and said — the input's own defect, as ``reprocess`` warns of it, not a
    loss of the run."""
    prog = last_progress(progress_messages)
    out: dict = {"problems": [], "readers": {}}
    problems = out["problems"]
    src = prog.get(source)
    if src is not None:
        out["sent"] = {k: int(src[k]) for k in ALL_TOPICS}
        out["source_ended"] = bool(src["end"])
        out["window"] = int(src["window"])
        if input_counts and src["end"]:
            held = {k: int(input_counts.get(f"/probe/{k}", 0)) for k in SAMPLE_TOPICS}
            out["input"] = {"held": held, "not_sent": {k: held[k] - out["sent"][k] for k in SAMPLE_TOPICS
                                                       if held[k] > out["sent"][k]}}
        if not src["end"]:
            problems.append(f"the {source}'s end of the data is not in the recording (the recording stopped "
                            "before it, or the source did not finish)")
    lost_all = []
    for name, m in sorted(prog.items()):
        if name == source:
            continue
        topics = ALL_TOPICS if name not in ("calibration",) else SAMPLE_TOPICS
        r = {"taken": {k: int(m[k]) for k in topics}, "stations": int(m["stations"]), "records": int(m["records"]),
             "forced": int(m["forced"]), "ended": bool(m["end"]), "pairs_used": int(m["pairs_used"]),
             "pairs_dropped": int(m["pairs_dropped"])}
        if name == recorder and recorded is not None:
            r["taken"] = {k: int(recorded[k]) for k in topics}     # what the recording holds, each once
        r["final"] = bool(src is not None and src["end"] and (r["ended"] or name == recorder))
        if r["final"]:
            # final counts on both sides (before the end, each node's last progress is of another moment)
            lost = {k: int(src[k]) - r["taken"][k] for k in topics if r["taken"][k] < int(src[k])}
            if lost:
                r["lost"] = lost
                lost_all.append(f"{name} " + ", ".join(f"{v} {k}" for k, v in lost.items()))
        if r["forced"]:
            problems.append(f"{name}: {r['forced']} station(s) went out before what they waited for had arrived "
                            "(their reference, temperatures, depth or the calibration's step: see its warnings)")
        if src is not None and src["end"] and not r["ended"] and name != recorder:
            # (the recorder's counts are the recording's own: what it lost is its LOST line)
            problems.append(f"{name} did not take the end of the data")
        out["readers"][name] = r
    if lost_all:
        problems.append("samples lost: " + "; ".join(lost_all) + (" (an unpaced replay or a live source: a slow "
                                                                   "reader loses what its queue cannot hold)"
                                                                   if not paced else ""))
    uniq, conflicts = unique_stations(stations)
    ids = [s["station_id"] for s in uniq]
    st = {"recorded": len(uniq), "messages": len(stations), "conflicting_ids": conflicts, "id_gaps": id_gaps(ids)}
    pub = prog.get(station_node)
    if pub is not None:
        st["published"] = int(pub["stations"])
        # ids continue across restarts: the ids the publisher gave are first..first+published-1 at most
        if st["published"] > len(uniq):
            problems.append(f"{st['published'] - len(uniq)} of the {st['published']} stations {station_node} "
                            "published were not recorded")
    if conflicts:
        problems.append(f"station id(s) {conflicts} recorded twice with different values: a restarted node "
                        "numbered stations again")
    if st["id_gaps"]:
        text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in st["id_gaps"])
        problems.append(f"station ids missing from the record: {text}")
    raw = {}
    for s in uniq:
        if not s["coefficients_id"]:
            k = _reason_kind(s.get("uncorrected_reason", ""))
            raw[k] = raw.get(k, 0) + 1
    st["uncorrected"] = raw
    out["stations"] = st
    bad = {k: v for k, v in raw.items() if k != "before calibration" or not calibration_ran}
    for k, v in bad.items():
        example = next((s.get("uncorrected_reason") for s in uniq if not s["coefficients_id"]
                        and _reason_kind(s.get("uncorrected_reason", "")) == k), "")
        problems.append(f"{v} station(s) uncorrected: {example or k}")
    if calibration_ran and captures is not None:
        st["captures"] = int(captures)      # the stand's captures the first record was solved from
    if calibration_ran and stand is not None:
        st["stand"] = [float(stand[0]), float(stand[1])]
    late = survey_raw(uniq, records, captures, stand) if calibration_ran else ""
    if late:
        problems.append(late)
    out["restarts"] = dict(restarts or {})
    return out


def format_account(a: dict) -> list:
    """The summary's lines for an :func:`account`."""
    lines = []
    if "sent" in a:
        sent = a["sent"]
        lines.append("samples: the probe sent " + ", ".join(f"{sent[k]} {k}" for k in ALL_TOPICS if sent[k]) +
                     (f" (paced: at most {a['window']} ahead of its slowest reader)" if a.get("window") else
                      " (not paced)"))
        if a.get("input", {}).get("not_sent"):
            held, not_sent = a["input"]["held"], a["input"]["not_sent"]
            lines.append("  of the input bag's " + ", ".join(f"{held[k]} {k}" for k in SAMPLE_TOPICS if held[k]) +
                         ", not sent: " + ", ".join(f"{v} {k}" for k, v in not_sent.items()) +
                         " (without a partner of the same stamp on the other stream, or not decodable: the "
                         "probe's warnings say which)")
        ended = a.get("source_ended")
        for name, r in a["readers"].items():
            if "lost" in r:
                lines.append(f"  {name} LOST " + ", ".join(f"{v} {k}" for k, v in r["lost"].items()))
            elif not r.get("final"):
                # no final counts on one side: what it took is not known to be all
                short = {k: v for k, v in r["taken"].items() if v < sent[k]}
                lines.append(f"  {name} took " + (", ".join(f"{r['taken'][k]} of {sent[k]} {k}" for k in short)
                                                   if short else "as many as the probe had said it sent")
                             + ("; it did not take the end" if ended and not r["ended"] else
                                "; the probe's end is not in the recording" if not ended else ""))
            else:
                lines.append(f"  {name} took every one" + (f"; {r['forced']} station(s) did not wait for their data"
                                                           if r["forced"] else ""))
    st = a.get("stations", {})
    if st:
        pub = st.get("published")
        line = f"stations: {st['recorded']} recorded" + (f" of {pub} published" if pub is not None else "")
        raw = st.get("uncorrected") or {}
        if raw:
            line += "; uncorrected: " + ", ".join(f"{v} {k}" for k, v in raw.items())
            note = "" if st.get("stand") else beyond_captures(raw.get("before calibration", 0), st.get("captures"))
            if note:
                line += f" ({note})"
        if st["id_gaps"]:
            line += "; ids missing: " + ", ".join(f"{x}" if x == y else f"{x}-{y}" for x, y in st["id_gaps"])
        lines.append(line)
    if a.get("restarts"):
        lines.append("restarts: " + ", ".join(f"{n} ×{k}" for n, k in a["restarts"].items() if k))
    return lines

"""Lab data: the static stations of several logs (:class:`station.Stations`), each with what is
known of its orientation.

Three kinds of station, by what constrains them:

* ``pose``  — a twelve-position pose (Table 1): orientation known from the pose, in the stand frame;
* ``ref``   — a stand-grid station with reference drift/azimuth/toolface: orientation known (a
  vertical reference without azimuth is known too: its rotation about the vertical is the
  toolface, as for azimuth 0);
* ``free``  — orientation unknown: constrained only by the site invariants |g|, |B| and dip.

Each log has a *role*: ``"cal"`` (the non-magnetic lab stand) or ``"val"`` (validation / survey
data, where survey-only effects such as axial drill-string interference may act).
Measured vectors are in the gravity-vector convention (m/s², down positive) and nT.  The station
type is the package's one (:mod:`station`); this module only reads logs into it.
"""
from __future__ import annotations

import hashlib
import re

import numpy as np

from ..detect.gates import SettlingTally, apply_gates
from ..io.probelog import read_csv, report, segment_stations
from ..core.memo import CopyMemo
from ..core.station import Loss, Stations


#: The last logs read (:func:`load_logs`), by their paths, roles and contents: a process that
#: works on one probe's logs reads them again and again — a diagnosis, the fit it recommends and the
#: report of both, each round of the model loop — and reading a log (parsing it, finding its
#: stations with the live detector, gating them) is most of what a fit on it costs after that.
LOAD_CACHE_SIZE = 4
#: A set whose stations keep more samples than this (rows of time and six channels, 56 bytes each)
#: is not kept: a process reading long logs one after the other does not hold them all.
LOAD_CACHE_MAX_SAMPLES = 2_000_000
_loaded = CopyMemo(LOAD_CACHE_SIZE)


def _content_key(items) -> tuple | None:
    """``(kind, path, blake2b of its bytes)`` of each log, or None when one cannot be read (the
    reading then fails as it would, and says why)."""
    key = []
    for kind, path in items:
        try:
            with open(path, "rb") as fh:
                digest = hashlib.file_digest(fh, "blake2b").hexdigest() if hasattr(hashlib, "file_digest") \
                    else hashlib.blake2b(fh.read()).hexdigest()
        except (OSError, TypeError, ValueError):
            return None
        key.append((kind, str(path), digest))
    return tuple(key)


def load_logs(cal_path=None, val_path=None, warn=None, free_paths=()) -> Stations:
    """Read CAL and VAL probe logs (CSV) into one :class:`station.Stations`; what is left out goes
    to ``warn`` (callable) and into the data's ledger (:attr:`Stations.losses`).

    Stations are found by the live nodes' detector (:func:`probelog.segment_stations`) and
    checked by the gates (:mod:`gates`).  Left out, each counted with its reason: rejected rows;
    labelled holds in which no station was found; stations in which the probe moved; stations in
    which a gate refused a sensor's data (saturated, flat); a log with no usable station (the
    other logs are still read; no usable station at all is an error).  ``cal_path`` may be a list
    of logs (e.g. two temperature runs).  ``free_paths``: logs without labels (the probe turned by
    hand through many attitudes); their stations enter as ``free`` (role ``cal``), constrained by
    the site invariants only.  Time-dependent effects count from the earliest first sample of the
    logs (read together, they are one probe's data since power-on).

    The same logs (the same paths, roles and bytes) read again in one process give a copy of the
    stations read the first time, and ``warn`` hears the same lines again (:data:`LOAD_CACHE_SIZE`
    sets of logs are kept, none whose stations hold more than :data:`LOAD_CACHE_MAX_SAMPLES`
    samples).
    """
    cal_paths = [] if cal_path is None else ([cal_path] if isinstance(cal_path, (str, bytes)) or
                                             not hasattr(cal_path, "__iter__") else list(cal_path))
    items = ([("free", p) for p in (free_paths or ())] + [("cal", p) for p in cal_paths]
             + ([("val", val_path)] if val_path is not None else []))
    key = _content_key(items)
    if key is not None and key in _loaded:
        stations, said = _loaded.get(key)
        for msg in said if warn else ():
            warn(msg)
        return stations
    said = []

    def say(msg):
        said.append(msg)
        if warn:
            warn(msg)

    out = _read_logs(cal_paths, val_path, say, free_paths)
    kept = sum(len(x) for x in (out.samples if out.samples is not None else ()) if x is not None)
    if key is not None and kept <= LOAD_CACHE_MAX_SAMPLES:
        _loaded.put(key, (out, said))
    return out


def _read_logs(cal_paths, val_path, say, free_paths) -> Stations:
    """:func:`load_logs`, read."""
    parts, losses = [], []
    t_origin = None
    for path, role, labels in ([(p, "cal", False) for p in (free_paths or ())]
                               + [(p, "cal", True) for p in cal_paths] + [(val_path, "val", True)]):
        if path is None:
            continue
        log, rejections = read_csv(path)
        if len(log):
            t_origin = float(log.t_s[0]) if t_origin is None else min(t_origin, float(log.t_s[0]))
        stations, problems = segment_stations(log, use_labels=labels)
        report(path, rejections, problems, say)
        losses += _row_losses(str(path), rejections)
        losses += [Loss(str(path), "poses" if p.startswith("pose") else "holds", 1, p.split(": no static station "
                                                                                         "found: ")[-1])
                   for p in problems if ": no static station found: " in p]
        kept = []
        tally = SettlingTally()
        for st in stations:
            findings = apply_gates(st)
            for msg in tally.add(findings):
                say(f"{path}: {msg}")
            if st.moved:
                losses.append(Loss(str(path), "stations", 1, f"{st.label} at {st.where}: the probe moved during "
                                                             "the hold"))
            elif st.unusable:
                losses.append(Loss(str(path), "stations", 1, f"{st.label} at {st.where}: a gate refused the "
                                   f"{' and '.join(st.unusable)} data (" + "; ".join(f.message for f in findings) + ")"))
            else:
                kept.append(st)
        settled = tally.summary(len(stations), str(path))
        if settled:
            say(settled)
        if len(kept) < len(stations):
            say(f"{path}: {len(stations) - len(kept)} station(s) left out (the probe moved, or a sensor's data "
                "refused by a gate)")
        if not kept:
            why = "no usable static stations" + ("" if labels else " (need ≥ 0.5 s still at each attitude)")
            losses.append(Loss(str(path), "log", 1, why))
            say(f"{path}: {why}: the whole log is left out")
            continue
        parts.append((kept, role, str(path), labels, _samples(log, kept)))
    if not parts:
        raise ValueError("no usable static stations in any log" if losses else "no logs given")
    return Stations.concatenate([Stations.from_list(st, role, source=src, use_ref=labels, t_origin=t_origin,
                                                    samples=smp)
                                 for st, role, src, labels, smp in parts], losses=losses)


def _samples(log, stations):
    """Each station's samples: (n, 7) time (s), gravity vector (m/s², ``ProbeLog.gravity``) and
    field (nT)."""
    g = log.gravity
    out = []
    for st in stations:
        i0, i1 = np.searchsorted(log.t_s, [st.t_start, st.t_end], side="left")
        i1 = min(i1 + 1, len(log))
        out.append(np.column_stack([log.t_s[i0:i1], g[i0:i1], np.asarray(log.mag[i0:i1])]))
    return out


def _row_losses(source: str, rejections) -> list:
    """Rejected rows, one ledger entry per kind of reason (the first reason of each kind quoted)."""
    kinds = {}
    for r in rejections:
        kind = re.sub(r"[-+]?\d[\d.eE+-]*|'[^']*'", "#", r.reason)
        n, first = kinds.get(kind, (0, r))
        kinds[kind] = (n + 1, first)
    return [Loss(source, "rows", n, f"{first.reason} (first at row {first.row})") for n, first in kinds.values()]


def load_bag(path, warn=None):
    """The stations of a recorded run (a bag of the probe's streams) as lab data, and the
    calibration record its twelve-position captures solve to (None when they do not).

    The bag is replayed through the live graph's own steps (:func:`reprocess.reprocess` with the
    calibration session, writing nothing): the twelve-position captures the session accepted are
    the ``cal`` stations (kind ``pose``); every other station with a reference attitude on
    ``/probe/reference`` (a survey with a stand or a check shot) is a ``val`` station (kind
    ``ref``), and one without a reference a ``val`` station of kind ``free``, constrained by the
    site invariants.  Time-dependent effects count from the stream's first sample.  Returns
    ``(stations, calibration)``.
    """
    from ..correct.reprocess import reprocess

    rep = reprocess(path, None, calibrate=True, copy_input=False)
    for w in rep.warnings():
        if warn:
            warn(f"{path}: {w}")
    for e in rep.bag_errors:
        if warn:
            warn(f"{path}: {e}")
    captured = {(c.t_start, c.t_end) for c in rep.captures}
    cal = [c for c in rep.captures if not c.moved]
    val = [s for s in rep.raw_stations if not s.moved and not s.short and (s.t_start, s.t_end) not in captured
           and not any(c.t_start <= s.t_start and s.t_end <= c.t_end for c in rep.captures)]
    if not cal and not val:
        raise ValueError(f"{path}: no usable static stations")
    losses = [Loss(str(path), "records", 1, str(e)) for e in rep.bag_errors]
    moved = [s for s in list(rep.captures) + list(rep.raw_stations) if s.moved and not s.short]
    losses += [Loss(str(path), "stations", 1, f"{s.label} at {s.where}: the probe moved during the hold") for s in moved]
    parts = [Stations.from_list(cal, "cal", source=f"{path} (captures)")] if cal else []
    if val:
        parts.append(Stations.from_list(val, "val", source=str(path)))
    return Stations.concatenate(parts, losses=losses), (rep.calibrations[-1] if rep.calibrations else None)

"""The stream engine: samples in, corrected and checked stations out — one object, every driver.

ROS-free.  The correction and calibration nodes, ``reprocess``, ``correct`` and the lab drive this
object with the same rules, so a bag replayed through the live graph gives the stations
``reprocess`` gives, bit for bit, whatever the order in which the topics arrive:

1. **samples**: ``/probe/imu`` and ``/probe/mag`` of one stamp are paired
   (:class:`streaming.StreamPairer`); a non-finite pair closes the current hold, an implausible one
   (:func:`implausible`) is dropped and counted, every other goes through the static detector
   (:class:`streaming.StaticDetector`: thresholds from the noise the data show; the messages'
   covariance a prior);
2. **a closed station waits** until what it needs of the other streams is in — the reference
   attitude, the temperatures and the depth current up to it, and, when a calibration runs
   elsewhere (``sync_calibration``), that calibration having taken the same station
   (:meth:`calibration_progress`) — and stations go on in the order they closed.  The waits are
   judged on the data's own time, never on the wall clock: a driver that runs out of patience
   calls :meth:`release` with ``force``, which is counted;
3. **gates** once (:func:`gates.apply_gates`, the same limits and gravity for every role);
4. **the capture session** (calibrate role: :class:`capture.CaptureSession` or the turntable's)
   is offered the station; a solve is a record, stamped with the data time from which it applies
   (:meth:`_stamp_of_solve`); a station the session has not decided on yet (a rest on the stand,
   or the survey's first station: ``undecided_since``) is held from the survey — and the
   calibration role's :attr:`settled` stays before it — until the next station or the end decides;
5. **the survey** (survey role: :class:`pipeline.SurveyProcessor`): the station is corrected by
   the record in force at its end — the latest whose stamp lies before it (:meth:`record_for`) —
   evaluated against the site, placed on the trajectory, and checked by the field monitor; its
   ``SurveyStation`` fields are one :class:`StationOut` event.

What a driver must say or publish comes out as events (:meth:`pop`): :class:`StationOut`,
:class:`RecordOut` and :class:`Say` (a level and one line).  :attr:`counts` accounts for every
message that came in and what became of it.

Time: stamps are float seconds of the data's time base; ``order`` keys (a message's DDS source
timestamp live, a bag's publish or log time offline) place the unstamped depth among the samples.
"""
from __future__ import annotations

import bisect
import collections
import math
import re
from dataclasses import dataclass, field

from ..core.frames import STANDARD_GRAVITY, Site, specific_force_from_gravity
from ..detect.gates import GateLimits, apply_gates
from .pipeline import UNNAMED_PROBE, probe_mismatch
from ..io.probelog import Limits, check_sample
from ..detect.streaming import TIME_EPS, ReferenceTrack, StaticDetector, StreamPairer
from ..io.topics import TOPIC_IMU, TOPIC_MAG

NAN = float("nan")
INF = math.inf
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d*)?(?:e[-+]?\d+)?")
#: Samples whose order keys are kept to place a depth that arrives late (about 20 s at 1 kHz).
SENT_KEPT = 20_000

#: Why a station has no correction (``SurveyStation.uncorrected_reason``), the first words.
BEFORE_CALIBRATION = "before calibration"
NO_RECORD = "no calibration record"
RECORD_REFUSED = "record refused"


# ---------------------------------------------------------------------------------------------
# Plausibility of one sample (the CSV reader's limits, with a cheap pre-check for the hot path)

_LIMITS = Limits()
_ACC2 = (_LIMITS.acc_total_range[0] ** 2, _LIMITS.acc_total_range[1] ** 2)
#: below (99.9 % of full scale)² in total, no axis can be saturated: the fast path is exact
_MAG2 = (_LIMITS.mag_total_range[0] ** 2, (0.999 * _LIMITS.mag_full_scale) ** 2)
assert _ACC2[1] < (0.999 * _LIMITS.acc_full_scale) ** 2   # likewise for the accelerometer


def implausible(g, m) -> str | None:
    """Why a sample (gravity vector m/s², field nT) is unusable, or None: the CSV reader's limits
    (:func:`probelog.check_sample`, said in the values the probe sent: REP-145 specific force),
    the same everywhere; a field that looks like nT written into a tesla field says so."""
    a2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
    b2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    if _ACC2[0] <= a2 <= _ACC2[1] and _MAG2[0] <= b2 <= _MAG2[1]:
        return None
    reason = check_sample(specific_force_from_gravity(tuple(g)), m, NAN, _LIMITS)
    if reason is not None and 1.0 < math.sqrt(b2) * 1e-9 < 1e6:
        reason += " — the field looks like nT written into a tesla field; MagneticField carries tesla"
    return reason


# ---------------------------------------------------------------------------------------------
# Events


@dataclass
class StationOut:
    """A station to publish: its ``SurveyStation`` fields (all but the header, stamped at the
    station's end), the :class:`station.Station` and the reference used (None: none)."""

    fields: dict
    station: object
    ref: tuple | None = None


@dataclass
class RecordOut:
    """A record the capture session solved: publish it, stamped ``stamp`` (the data time from
    which it applies: stations that end after it)."""

    calibration: object
    stamp: float


@dataclass
class Say:
    """One line for the user: ``level`` debug, info, warning or error."""

    level: str
    text: str


@dataclass
class _Pending:
    station: object
    t_close: float          # stamp of the sample that closed it (inf: the end of the data)


@dataclass
class Expect:
    """Which side streams the source keeps current (repeats at least every second of data time),
    so that a station waits for them: ``None`` = not known (a live source that says nothing):
    then a reference is waited for once one was seen, a temperature once one was seen (or when
    the record needs one), a depth never."""

    reference: bool | None = None
    temperature: bool | None = None
    depth: bool | None = None


@dataclass
class Counts:
    """What came in and what became of it."""

    imu: int = 0
    mag: int = 0
    temperature: int = 0
    reference: int = 0
    depth: int = 0
    pairs: int = 0                # imu/mag pairs completed
    used: int = 0                 # pairs fed to the detector
    nonfinite: int = 0            # pairs with a NaN/inf value (each closes the hold)
    implausible: int = 0          # pairs dropped as implausible
    out_of_order: int = 0         # pairs whose stamp is not after the previous one (dropped)
    stations: int = 0             # stations closed (short ones included)
    short: int = 0                # of which shorter than the detector's minimum (not published)
    published: int = 0            # StationOut events
    uncorrected: int = 0          # of which without a record
    forced: int = 0               # stations released before what they waited for was in
    records: int = 0              # records received (external) or solved (session)
    records_refused: int = 0
    lost: dict = field(default_factory=dict)   # messages the source sent that never arrived, per topic

    @property
    def unpaired(self) -> int:
        """imu and mag samples that found no partner (so far)."""
        return self.imu + self.mag - 2 * (self.pairs + self.out_of_order)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["unpaired"] = self.unpaired
        return d


class StreamEngine:
    """The one path from samples to stations (see the module docstring).

    Parameters
    ----------
    detector : the static detector (default: thresholds from the data).
    processor : :class:`pipeline.SurveyProcessor` — the survey role (None: no stations out).
    session : a capture session (:class:`capture.CaptureSession`, :class:`turntable.TurntableSession`)
        — the calibrate role (None: none).
    sync_calibration : a calibration runs elsewhere (the calibration node): its records apply by
        their stamps and a station waits until that calibration has taken it
        (:meth:`calibration_progress`).  False: an external record applies to the stations
        released after it arrives (a file, a record of another run).
    expect : :class:`Expect` — the side streams the source keeps current.
    gate_limits, gravity_mps2 : the gates' limits and the raw |g| they check against (the given
        site's gravity; default the standard gravity — a 10 % gate).
    publish_short : also publish stations shorter than the detector's minimum duration.
    """

    def __init__(self, detector: StaticDetector | None = None, processor=None, session=None, *,
                 sync_calibration: bool = False, expect: Expect | None = None,
                 gate_limits: GateLimits | None = None, gravity_mps2: float | None = None,
                 publish_short: bool = False):
        self.det = detector if detector is not None else StaticDetector()
        self.det.retain_temperatures = True     # stations wait for their temperatures: forgotten once out
        self.proc = processor
        self.session = session
        self.sync = bool(sync_calibration)
        self.expect = expect or Expect()
        self.gate_limits = gate_limits or (getattr(session, "limits", None) or GateLimits())
        self.gravity = float(gravity_mps2) if gravity_mps2 is not None else (
            session.site.gravity_mps2 if getattr(session, "site", None) is not None else Site().gravity_mps2)
        self.publish_short = bool(publish_short)
        self.pairer = StreamPairer()
        self.refs = ReferenceTrack()
        self.depths = ReferenceTrack()          # (depth m,) from the stamp of the sample sent before it
        self.counts = Counts()
        self.have_temp = False
        self.serial = ""
        self.t_last = -INF                      # stamp of the last pair
        self.t_first = NAN
        self.last_pair = None                   # (t, f, m) of the last pair used
        self.settled = -INF                     # every station closed at or before this has gone out
        self.ended = False
        self._out: list = []
        self._implausible_kinds: set = set()    # kinds of implausible sample said (each said when first seen)
        self._pending: collections.deque = collections.deque()
        self._prior = [False, False]
        self._sent: collections.deque = collections.deque(maxlen=SENT_KEPT)   # (order, stamp) of samples
        self._depths_waiting: list = []         # (order, value) of depths sent after the last sample in
        # records by the data time from which they apply: [(stamp, seq, calibration, source)]
        self._records: list = []
        self._seq = 0
        self.released_t = -INF                  # t_end of the last station gone out
        self.refusal = ""                       # why the last record offered was refused
        # the calibration elsewhere (sync): how far it has taken the data, how many records it made
        self.cal_settled = -INF
        self.cal_records = 0
        self.cal_ended = False
        self.cal_gone = False                   # the driver gave up on it (node dead): no more waiting
        self._hold = ""                         # what every station waits for first (set_expect clears it)
        # stations the session has not decided on yet (survey or the stand's: capture.CaptureSession.
        # undecided_since): the survey role holds them, and the calibration role's progress does not
        # pass them (a correction node keeping step waits for the record that may apply to them)
        self._undecided: list = []              # held _Pending (survey role)
        self._undecided_close = None            # t_close of the first of them (either role)

    def hold(self, what: str) -> None:
        """Stations wait for ``what`` (the source's announcement: :meth:`set_expect`) before anything."""
        self._hold = what

    def set_expect(self, expect: Expect) -> None:
        """The side streams the source keeps current (its announcement); ends a :meth:`hold`."""
        self.expect = expect
        self._hold = ""
        if self._pending:
            self.release()

    # ---- events -----------------------------------------------------------------------------
    def pop(self) -> list:
        """The events since the last call, in order."""
        out, self._out = self._out, []
        return out

    def _say(self, level: str, text: str) -> None:
        self._out.append(Say(level, text))

    # ---- the side streams ---------------------------------------------------------------------
    def temperature(self, t: float, temp_c: float) -> None:
        """A temperature (°C) stamped ``t``: a station's temperature is the mean of those within it."""
        self.counts.temperature += 1
        self.det.add_temperature(t, temp_c)
        self.have_temp = True
        if self._pending:
            self.release()

    def reference(self, t: float, v) -> None:
        """The reference attitude (drift, azimuth, toolface deg; NaN: not given) from ``t`` on."""
        self.counts.reference += 1
        self.refs.add(t, v)
        if self._pending:
            self.release()

    def depth(self, value: float, order: int = 0) -> None:
        """The measured depth (m), unstamped: it holds from the last sample *sent* before it
        (``order``: the message's send order key, comparable with the samples'; 0: after the last
        sample taken).  A depth sent after every sample in so far waits for the next one."""
        self.counts.depth += 1
        value = float(value)
        if not order:
            self.depths.add(self.t_last, (value,))
        elif self._sent and self._sent[-1][0] > order:
            self._place_depth(order, value)        # late: samples sent after it are in already
        else:
            self._depths_waiting.append((order, value))
        if self._pending:
            self.release()

    def _place_depth(self, order: int, value: float) -> None:
        k = bisect.bisect_left(self._sent, (order, -INF)) - 1     # the last sample sent before it
        self.depths.add(self._sent[k][1] if k >= 0 else -INF, (value,))

    def _note_sent(self, order: int, t: float) -> None:
        self._sent.append((order, t))
        if self._depths_waiting and self._depths_waiting[0][0] < order:
            ready = [d for d in self._depths_waiting if d[0] < order]
            self._depths_waiting = [d for d in self._depths_waiting if d[0] >= order]
            for d_order, value in ready:
                self._place_depth(d_order, value)

    def set_serial(self, serial: str) -> None:
        """The data's probe (``/probe/serial``): records of another probe are refused (said)."""
        serial = str(serial or "")
        if not serial or serial == self.serial:
            return
        self.serial = serial
        named = getattr(self.session, "probe_id", None)
        if named is not None and named != serial:
            if named not in ("", UNNAMED_PROBE):
                self._say("warning", f"probe_id {named!r} is not the probe on /probe/serial ({serial}): the records "
                                     "are named for the data's probe")
            self.session.probe_id = serial        # the records this session makes are the data's probe's
        if self.proc is not None:
            self.proc.probe_serial = serial
            kept = []
            for rec in self._records:
                why = self._mismatch(rec[2])
                if why:
                    self._refuse(rec[2], why)
                else:
                    kept.append(rec)
            self._records = kept

    # ---- records ---------------------------------------------------------------------------------
    def _mismatch(self, cal) -> str:
        why = probe_mismatch(cal, self.serial)
        if why is None or (self.proc is not None and self.proc.force_probe):
            return ""
        return why

    def _refuse(self, cal, why: str) -> None:
        self.counts.records_refused += 1
        self.refusal = f"{RECORD_REFUSED}: {why}"
        self._say("error", f"{why}: not applied (force it only if the record is known to fit these data); "
                           "the stations go uncorrected until a record of this probe arrives")

    def record(self, cal, stamp: float | None = None, source: str = "") -> bool:
        """A record from outside (a file, the coefficients topic, a bag): it applies to the
        stations ending after ``stamp`` (data time; None: from the start of the data).  Keeping
        step with a calibration node (``sync_calibration``) that is the time it was solved at, its
        header; a record that simply arrives applies from the next station: :attr:`released_t`.
        A record of another probe than the data's is refused and said (False)."""
        if any(r[2] is not None and r[2].id == cal.id for r in self._records):
            return True                           # latched again (a restarted node): the same record
        self.counts.records += 1
        why = self._mismatch(cal)
        if why:
            self._refuse(cal, why)
            return False
        self._add_record(cal, -INF if stamp is None else stamp, source)
        if self._pending:
            self.release()
        return True

    def _add_record(self, cal, stamp: float, source: str) -> None:
        self._seq += 1
        bisect.insort(self._records, (float(stamp), self._seq, cal, source))
        self.refusal = ""

    def record_for(self, t_end: float):
        """The record in force for a station ending at ``t_end``: the latest whose stamp lies
        before it (None: none yet)."""
        cal = None
        for stamp, _, c, _ in self._records:
            if stamp < t_end - TIME_EPS:
                cal = c
            else:
                break
        return cal

    @property
    def calibration(self):
        """The newest record (None: none)."""
        return self._records[-1][2] if self._records else None

    def calibration_progress(self, settled: float, records: int, ended: bool = False) -> None:
        """The calibration elsewhere has taken every station closed up to ``settled`` (data time)
        and made ``records`` records so far (``ended``: it has seen the end of the data)."""
        self.cal_settled = max(self.cal_settled, float(settled))
        self.cal_records = max(self.cal_records, int(records))
        self.cal_ended = self.cal_ended or bool(ended)
        if self._pending:
            self.release()

    def calibration_gone(self, gone: bool = True) -> None:
        """The calibration elsewhere is gone (its node died): stations stop waiting for it."""
        self.cal_gone = gone
        if self._pending:
            self.release()

    # ---- samples ---------------------------------------------------------------------------
    def imu(self, key, g, order: int = 0, sigma: float = NAN) -> tuple:
        """A ``/probe/imu`` sample: header stamp ``key`` (sec, nanosec), its gravity vector ``g``
        (m/s², down positive: :func:`io.cdr.decode_imu_gravity`), ``order`` its send-order key
        (placing depths), ``sigma`` the per-axis noise its
        covariance states (m/s², NaN: none; the first one is the detector's prior)."""
        self.counts.imu += 1
        if not self._prior[0]:
            self._prior[0] = True
            if sigma > 0:
                self.det.set_prior(noise_acc=sigma)
        if order:
            self._note_sent(order, key[0] + 1e-9 * key[1])
        got = self.pairer.add_imu(key, g)
        if got is None:
            return self._dropped(TOPIC_IMU, key)
        return self._pair(*got)

    def mag(self, key, b, sigma: float = NAN) -> tuple:
        """A ``/probe/mag`` sample: stamp ``key``, field ``b`` in nT, ``sigma`` its stated noise (nT)."""
        self.counts.mag += 1
        if not self._prior[1]:
            self._prior[1] = True
            if sigma > 0:
                self.det.set_prior(noise_mag=sigma)
        got = self.pairer.add_mag(key, b)
        if got is None:
            return self._dropped(TOPIC_MAG, key)
        return self._pair(*got)

    def _dropped(self, topic: str, key) -> tuple:
        """No pair came of a sample on ``topic`` stamped ``key``: it waits for its partner, or it
        completed a pair stamped not after the previous one (dropped, counted; said at the 1st, 2nd,
        4th ... one: bounded)."""
        n = self.pairer.out_of_order
        if n != self.counts.out_of_order:
            self.counts.out_of_order = n
            if n & (n - 1) == 0:
                self._say("warning", f"a sample pair stamped not after the previous one ({topic}: sample stamped "
                                     f"t={key[0] + 1e-9 * key[1]:.3f} s, the previous pair t={self.pairer.last_t:.3f} "
                                     f"s): non-monotonic timestamps, dropped; {n} so far")
        return ()

    def _pair(self, t, g, m) -> tuple:
        """A complete pair at ``t``: through the detector.  Returns the stations it closed (they
        wait, go out, or both: see :meth:`pop`)."""
        c = self.counts
        c.pairs += 1
        if self.t_first != self.t_first:
            self.t_first = t
        if not math.isfinite(g[0] + g[1] + g[2] + m[0] + m[1] + m[2]):
            c.nonfinite += 1
            if c.nonfinite & (c.nonfinite - 1) == 0:   # said at the 1st, 2nd, 4th ... one: bounded
                which = [n for n, v in ((TOPIC_IMU, g), (TOPIC_MAG, m)) if not all(map(math.isfinite, v))]
                self._say("warning", f"non-finite sample at t={t:.3f} s on {' and '.join(which)} (gravity {tuple(g)} "
                                     f"m/s^2, mag {tuple(m)} nT): it ends the current static interval; "
                                     f"{c.nonfinite} so far")
        elif implausible(g, m) is not None:
            c.implausible += 1
            reason = implausible(g, m)
            kind = _NUMBER.sub("#", reason)       # the reason without its numbers: a few kinds at most
            if c.implausible & (c.implausible - 1) == 0 or kind not in self._implausible_kinds:
                self._implausible_kinds.add(kind)  # the first of each kind too: one does not hide another
                self._say("warning", f"sample at t={t:.3f} s dropped: {reason}; {c.implausible} dropped so far")
            return ()
        c.used += 1
        self.t_last = t
        self.last_pair = (t, g, m)
        closed = self.det.update(t, g, m)
        if self.det.events:
            for e in self.det.pop_events():
                self._say("warning", e)
        for st in closed:
            self._closed(st, t)
        if not self._pending:
            self.settled = t if self._undecided_close is None else min(t, self._undecided_close - TIME_EPS)
        return closed

    def samples(self, t, g, m, temp_c=None) -> None:
        """A block of samples at once (a log): the detector's bulk path (:meth:`StaticDetector.run`,
        the same stations as sample by sample); rows that are not plausible are left out first,
        counted.  Only for a source with no side streams waiting (a log's own temperature column)."""
        import numpy as np

        t = np.asarray(t, float)
        g = np.asarray(g, float)
        m = np.asarray(m, float)
        n = len(t)
        self.counts.imu += n
        self.counts.mag += n
        self.counts.pairs += n
        if n and self.t_first != self.t_first:
            self.t_first = float(t[0])
        temp = None if temp_c is None else np.asarray(temp_c, float)
        if temp is not None:
            self.have_temp = bool(np.any(np.isfinite(temp))) or self.have_temp
        finite = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(m), axis=1)
        keep = np.ones(n, bool)
        for i in np.flatnonzero(finite):
            if implausible(g[i], m[i]) is not None:
                keep[i] = False
        self.counts.nonfinite += int(np.sum(~finite))
        self.counts.implausible += int(np.sum(~keep))
        self.counts.used += int(np.sum(keep & finite))
        closed = self.det.run(t[keep], g[keep], m[keep], None if temp is None else temp[keep])
        for e in self.det.pop_events():
            self._say("warning", e)
        for st in closed:
            self._closed(st, st.t_end)
        if n:
            self.t_last = float(t[keep][-1]) if keep.any() else self.t_last

    def _closed(self, st, t_close: float) -> None:
        self.counts.stations += 1
        if st.short:
            self.counts.short += 1
            if self.session is None and not self.publish_short:
                return
        self._pending.append(_Pending(st, t_close))
        self.release()

    # ---- waiting and going out -----------------------------------------------------------------
    def _missing(self, p: _Pending) -> list:
        """What station ``p`` still waits for (empty: it can go)."""
        miss = []
        if self.sync and not self.cal_gone:
            # settled is "every station closed at or before it has gone out" there: a station waiting
            # there says t_close − TIME_EPS, so the same station here waits until it reaches t_close
            if not self.cal_ended and self.cal_settled < p.t_close:
                miss.append("calibration")
            elif self.counts.records < self.cal_records:
                miss.append("record")
        if self.ended:           # nothing more of the side streams will come
            return miss
        if self._hold:
            return [self._hold] + miss
        st = p.station
        t = st.t_end
        exp = self.expect
        if exp.reference or (exp.reference is None and self.refs.seen):
            if self.refs.latest < t - TIME_EPS:
                miss.append("reference")
        temps = self.det.temps
        if exp.temperature or (exp.temperature is None and self.have_temp):
            if temps.latest < t - TIME_EPS:
                miss.append("temperature")
        elif exp.temperature is None and self.proc is not None:
            cal = self.record_for(t)
            if cal is not None and "temperature" in cal.needs:
                miss.append("temperature")      # the model needs one, none came yet: it may be late
        if exp.depth and self.depths.latest < st.t_mid - TIME_EPS:
            miss.append("depth")
        return miss

    def waiting(self) -> list:
        """``(station, t_close, what it waits for)`` of the stations waiting, oldest first."""
        return [(p.station, p.t_close, self._missing(p)) for p in self._pending]

    def release(self, force: bool = False, why: str = "") -> None:
        """Send on the waiting stations that can go, in order; with ``force`` all of them (the
        driver's patience ran out — ``why`` says how long — or the data ended): what they did not
        get is said on each and counted."""
        pending = self._pending
        while pending:
            p = pending[0]
            miss = self._missing(p)
            if miss and not force:
                break
            pending.popleft()
            if miss:
                self.counts.forced += 1
                text = (f"station at t={p.station.t_start:.2f}-{p.station.t_end:.2f} s went out without waiting "
                        f"longer for its {', '.join(miss)}{' (' + why + ')' if why else ''}: "
                        f"{', '.join(_CONSEQUENCE[m] for m in miss)}")
                p.station.warnings.append(text)
                self._say("warning", text)
            self._go(p)
        self._settle()

    def _settle(self) -> None:
        """:attr:`settled`: every station closed at or before it has gone out and been decided."""
        pending = self._pending
        self.settled = (pending[0].t_close - TIME_EPS) if pending else (INF if self.ended else
                                                                          max(self.settled, self.t_last))
        if self._undecided_close is not None:
            self.settled = min(self.settled, self._undecided_close - TIME_EPS)

    def _go(self, p: _Pending) -> None:
        st = p.station
        if not math.isfinite(st.md_m):          # the depth it was held at (in effect at its middle)
            d = self.depths.at(st.t_mid)
            st.md_m = d[0] if d is not None else NAN
        if self.have_temp:   # the temperatures stamped within it, now that they are in (they may come late)
            st.temp_c = self.det.temps.mean(st.t_start, st.t_end)
            self.det.temps.forget_before(st.t_start)   # in time order: no earlier one will ask
        apply_gates(st, self.gate_limits, self.gravity)
        self.released_t = max(self.released_t, st.t_end)
        if self.session is not None:
            self._offer(st)
            if getattr(self.session, "undecided_since", None) is not None:
                # the survey's first station or a rest on the stand: the next static (or the end) says
                if self._undecided_close is None:
                    self._undecided_close = p.t_close
                if self.proc is not None:
                    self._undecided.append(p)
                return
            self._decided()
        self._survey(p)

    def release_undecided(self) -> None:
        """The session has decided, or can no longer decide (it finished; the driver reset it): the
        stations held go on to the survey with the records in force, and :attr:`settled` moves on."""
        if self._undecided_close is not None:
            self._decided()
            self._settle()

    def _decided(self) -> None:
        """The session has decided on the stations it held (the record of a sequence that ended at
        them applies to them): they go on to the survey, in order."""
        self._undecided_close = None
        held, self._undecided = self._undecided, []
        for q in held:
            self._survey(q)

    def _survey(self, p: _Pending) -> None:
        st = p.station
        if self.proc is None or (st.short and not self.publish_short):
            return
        cal = self.record_for(st.t_end)
        if cal is not self.proc.calibration:
            for note in self.proc.set_calibration(cal) if cal is not None else self._no_record():
                self._say("warning", note)
        ref = self.refs.at(st.t_mid)
        fields = self.proc.process(st, ref=ref, have_temperature=self.have_temp)
        if cal is None:
            fields["uncorrected_reason"] = self._uncorrected_reason()
            if fields["uncorrected_reason"].startswith(RECORD_REFUSED) and \
                    fields["uncorrected_reason"] not in fields["warnings"]:
                fields["warnings"].append(fields["uncorrected_reason"])
            self.counts.uncorrected += 1
        else:
            fields["uncorrected_reason"] = ""
        self.counts.published += 1
        self._out.append(StationOut(fields, st, ref))

    def _no_record(self) -> list:
        self.proc.calibration = None
        self.proc.forced = ""
        return []

    def _uncorrected_reason(self) -> str:
        if self.refusal:
            return self.refusal
        if self.session is not None or self.sync:
            return f"{BEFORE_CALIBRATION}: the calibration has not solved yet"
        return f"{NO_RECORD}: none given and none received"

    # ---- the capture session ------------------------------------------------------------------
    def _offer(self, st) -> None:
        s = self.session
        n_warn, n_info, n_solves = len(s.warnings), len(getattr(s, "infos", ())), s.solves
        before = (s.state, s.message)
        result = s.offer(st)
        for w in s.warnings[n_warn:]:
            if not (s.state == "error" and w == s.message):   # the failure itself: at ERROR, below
                self._say("warning", w)
        for i in getattr(s, "infos", ())[n_info:]:
            self._say("info", i)
        if result == "accepted" and hasattr(s, "pending"):
            self._say("info", f"captured pose {s.current_pose}; pending {s.pending}")
        self._solved(n_solves, before, self._stamp_of_solve(st))

    def _stamp_of_solve(self, st) -> float:
        """From when a record solved while ``st`` was offered applies: after the station when it
        was one of the captures solved from (a station is never corrected by coefficients solved
        from itself); when the sequence ended there, from the start of the first station that was
        not the stand's (``session.applies_from``: that one, or the first of the strays before it,
        held until then — the survey's first stations)."""
        since = getattr(self.session, "applies_from", None)
        return st.t_end if since is None else since - TIME_EPS

    def _solved(self, n_solves: int, before: tuple, stamp: float) -> None:
        s = self.session
        if s.solves != n_solves and s.calibration is not None:
            last = self.calibration
            if last is None or last.id != s.calibration.id:      # the same record again: not again
                self.counts.records += 1
                self._add_record(s.calibration, stamp, "session")
                self._out.append(RecordOut(s.calibration, stamp))
        elif s.state == "error" and s.message and (s.state, s.message) != before:
            self._say("error", s.message)

    # ---- the end ---------------------------------------------------------------------------------
    def close_hold(self) -> None:
        """Close the open hold now (its station waits or goes out as any other)."""
        for st in self.det.flush():
            self._closed(st, self.t_last)
        for e in self.det.pop_events():
            self._say("warning", e)

    def idle(self) -> None:
        """The data paused (a live source said nothing for a while): close the open hold, send
        every station out with what arrived, and let the session solve with what it has — data
        that come later continue."""
        self.close_hold()
        self.release(force=True, why="no sample for a while")
        self._finish_session()

    def _finish_session(self) -> None:
        s = self.session
        if s is None:
            return
        n_solves, before = s.solves, (s.state, s.message)
        n_warn = len(s.warnings)
        s.finish()
        for w in s.warnings[n_warn:]:
            if not (s.state == "error" and w == s.message):
                self._say("warning", w)
        since = getattr(s, "applies_from", None)
        self._solved(n_solves, before, self.t_last if since is None else since - TIME_EPS)
        self.release_undecided()

    def end(self) -> None:
        """The end of the data: the open hold closes and every station goes out with what arrived
        of the side streams — except that, keeping step with a calibration elsewhere, they still
        wait for it to take them (:attr:`done` then says when all are out) — and the session
        solves with what it has (and says what is missing)."""
        if self.ended:
            return
        for st in self.det.flush():
            self._closed(st, INF)
        for e in self.det.pop_events():
            self._say("warning", e)
        self.ended = True
        self.release()
        self._finish_session()
        if self.pairer.waiting:
            self._say("warning", f"{self.pairer.waiting} imu/mag sample(s) never found their partner (same stamp)")

    @property
    def done(self) -> bool:
        """The data ended and every station has gone out."""
        return self.ended and not self._pending and self._undecided_close is None


_CONSEQUENCE = {
    "reference": "its reference is the last one received (possibly the previous station's)",
    "temperature": "its temperature is the mean of those received so far",
    "depth": "its depth is the last one received",
    "calibration": "the calibration had not taken it yet: a record solved from it or before it may not apply",
    "record": "a record the calibration announced had not arrived",
}

__all__ = ["StreamEngine", "StationOut", "RecordOut", "Say", "Expect", "Counts", "implausible",
           "BEFORE_CALIBRATION", "NO_RECORD", "RECORD_REFUSED", "STANDARD_GRAVITY"]

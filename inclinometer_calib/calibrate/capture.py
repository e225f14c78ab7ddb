"""Twelve-pose capture: which pose the probe is in, what is captured, when to solve — ROS-free.

One session for every path: the calibration node offers each station its detector closes, the
CLI (``twelve-position``) and offline reprocessing offer the stations of a log or a bag found by
the same detector.  The session

* **gates** each station (:mod:`gates`: in-hold motion, a flat/saturated axis, an implausible
  |g|): a moved station is rejected, a sensor that failed is left out of that sensor's solve;
* **identifies** the pose from the measured gravity direction (which tool axis is vertical, and
  its sign: a pair of poses) and the field's heading on the stand (which member of the pair),
  the heading measured from the captures — a stand need not be set up against magnetic north as
  in the paper — and checks it against the log's pose label when there is one;
* follows **the sequence**: before the first solve any pending pose is accepted (out of order
  with a warning), the pose just captured again is the same hold cut into pieces (merged) or a
  retake, any other repeat is refused; after the first solve a new round must start at pose 1
  and follow Table 1's order, otherwise the statics are survey stations, not poses (labelled
  captures, from a stand's log, are used whatever their order);
* **solves** when all twelve poses are in, again after every complete round, when **the sequence
  is over** with poses missing or refused — the probe has left the stand's poses for survey
  stations (``end_after_stations`` statics in a row that are not poses of the sequence) or
  ``end_after_s`` of data time passed without a capture — and at the end of the data
  (:meth:`finish`); it screens out captures that do not fit and solves by least squares when a
  pose is left without one (:func:`twelve_position.solve_captures`), and says which poses are
  missing and why.  Such a record applies from the first of the statics that ended the sequence
  (:attr:`CaptureSession.applies_from`): until the next static or the end decides, a static that
  is not a pose may be a rest on the stand or the survey's first station
  (:attr:`CaptureSession.undecided_since`: the engine holds it), and the record says where the
  stand's stations lie in the data's time (:meth:`CaptureSession.stand_span`).  A sequence that is over is closed: only a new round from pose 1 in Table 1's
  order (or a recapture) is taken after it, never a survey station near a pose that is missing;
* with a **model** named (``effects``, the package's effect grammar, e.g.
  ``temperature_bias:mag``), fits the paper's model plus those effects to the captures with the
  lab's fit, starting from the twelve-position solution, and says which parameters the captures
  could not identify (e.g. a temperature effect from captures at one temperature);
* owns the **site** of its record: the one given, or — without one — the one the stand measures
  (dip and the horizontal field's direction; ``site_source`` "measured"), never a default;
* says every failure aloud: each gate, refusal and left-out capture is a message in
  :attr:`warnings` (the node logs them at WARNING, the CLI prints them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.frames import Site, angle_between_deg
from ..detect.gates import GateLimits, SaturationMonitor, SettlingTally, apply_gates
from ..core.station import Station, merge_stations
from .twelve_position import (POSES, CaptureSet, field_heading_deg, identify_pose, pose_reference, solve_captures,
                              to_calibration, _gravity_candidates)

#: Statics of the same pose closer in time than this (s) are pieces of one hold, merged.
MERGE_GAP_S = 1.0
#: After the first solve, a further round's capture, corrected, must be this close to its pose of
#: Table 1 (deg: the stand's accuracy, with room) and its field this close to the first round's
#: capture of the pose; survey stations near a pose are not.
ROUND_GRAVITY_TOL_DEG = 2.0
ROUND_FIELD_TOL_DEG = 5.0
#: Before any solve, a pose captured again must point like its earlier capture (raw gravity and
#: raw field directions, deg): the same sensor errors in the same pose give the same readings.
REPEAT_TOL_DEG = 3.0
#: Before any solve, the two poses of a pair (turned 180° about the vertical from each other) read
#: gravity alike in the tool frame: at least this close (deg), or 5 times what the other pairs show.
PAIR_MIN_TOL_DEG = 0.5


def position(pose: int) -> int:
    """Place in Table 1's sequence of a pose, the two poses of a pair (turned 180° about the
    vertical from each other: 1–2, 3–4, …) sharing it — which member of a pair a capture is
    depends on the stand's heading, the sequence does not."""
    return (int(pose) - 1) // 2


@dataclass
class CaptureSession:
    """State of a twelve-pose calibration.

    Parameters
    ----------
    site : Site or None — reference field (gravity, and M_d: the vertical field that scales the
        magnetometer) and the site the record owns; None: measured by the stand (the solve assumes
        the default gravity and M_d, which only set the triads' scale).
    effects : effects to fit beyond the paper's model (the package's grammar), "" for none.
    min_capture_s : a capture shorter than this is rejected ("too short").
    pose_tolerance_deg : how far from a Table 1 pose the measured gravity may be (uncalibrated
        sensors may be several degrees off).
    rounds : after the first solve, accept further complete rounds in Table 1 order and solve
        again with all of them (False: the first solve is final).  Before any solve, a pose
        missing from the first round does not stop a second one: once the sequence has reached
        its last pair, a pose of the first pair that reads as its earlier capture starts it.
    limits : the gates' limits (:class:`gates.GateLimits`).
    end_after_stations : before any solve, this many statics in a row that are not poses of the
        sequence (not a pose; a pose that does not read as its earlier capture; a repeat out of
        order) end it: the probe has left the stand.
    end_after_s : before any solve, a static that starts this long (data time, s) after the last
        capture ends the sequence too.
    """

    site: Site | None = None
    min_capture_s: float = 0.5
    pose_tolerance_deg: float = 15.0
    rounds: bool = True
    probe_id: str = "probe"
    limits: GateLimits = field(default_factory=GateLimits)
    effects: str = ""
    end_after_stations: int = 2
    end_after_s: float = 120.0

    captures: list = field(default_factory=list)      # accepted Stations (pose = the identified pose)
    warnings: list = field(default_factory=list)      # every message for the user, in order
    infos: list = field(default_factory=list)         # progress messages (not failures)
    current_pose: int = -1
    recapture: set = field(default_factory=set)
    result: object = None
    calibration: object = None
    state: str = "collecting"                         # collecting | solving | done | error
    message: str = ""
    solves: int = 0

    def __post_init__(self):
        from ..core.effects import parse_effects, split_model_options
        rest, self._options = split_model_options(self.effects)   # the stand's pose errors, a heading offset
        self._specs = parse_effects(rest)   # a bad name is an error now, not at the first solve
        self.fit = None                   # the lab fit of the named effects (model.FitResult), if any
        self._round: list = []            # captures of a round in progress after the first solve
        self._dirty = False               # captures added since the last solve
        self._saturation = SaturationMonitor()
        self._settled = SettlingTally()
        self._flat_seen = {}              # "accelerometer x" -> stations in which it was flat
        self._flat_reported = {}
        self._h2 = [0.0, 0.0]             # sums of cos, sin of twice the captures' field headings
        self._heading = 0.0
        self._heading_said = False
        self.solve_notes: list = []       # what the last solve said (left-out captures, residuals)
        self._solve_texts: set = set()    # everything any solve said
        if self.end_after_stations < 1 or not self.end_after_s > 0:
            raise ValueError("CaptureSession: end_after_stations must be >= 1 and end_after_s > 0")
        self.ended = False                # the sequence is over (left the stand): closed to pending poses
        self._strays = 0                  # statics in a row that are not poses of the sequence
        self._refused: dict = {}          # pose -> why its last capture was refused
        self._pre_round = False           # a second round under way before any solve
        self._stray_t0 = math.nan         # start (data time, s) of the first of those strays
        #: (t_start, t_end) of every station taken as a pose (captured, merged or refused): where the
        #: stand's stations lie (:meth:`stand_span`)
        self._poses_seen: list = []
        #: data time (s) from which the record of a solve in the last :meth:`offer` or
        #: :meth:`finish` applies, when the sequence ended there: the start of the first station that
        #: was not the stand's (the first stray — it is the survey's first station); None: the solve
        #: came with a capture (the record applies after it) or none came
        self.applies_from = None

    # ---- views -----------------------------------------------------------------------------
    @property
    def captured(self) -> list:
        have = {c.pose for c in self.captures}
        return [p for p in POSES if p in have]

    @property
    def pending(self) -> list:
        have = {c.pose for c in self.captures}
        return [p for p in POSES if p not in have]

    @property
    def expected_next(self) -> int:
        """The pose the sequence expects next: in a round after the first solve, the one after the
        last; before, the first pending pose from the last one captured on (Table 1 order by pair,
        wrapping)."""
        if self.state == "done" and self._round:
            last = self._round[-1].pose
            return last + 1 if last < 12 else -1
        pending = self.pending
        if not pending:
            return -1
        last = self.captures[-1].pose if self.captures else 1
        after = [p for p in pending if position(p) >= position(last)]   # the last one's partner counts as next
        return after[0] if after else pending[0]

    @property
    def heading(self) -> float:
        """The field's heading in the stand frame (deg), measured from the captures so far: 0 for a
        stand set up against magnetic north as in the paper.  A pose and its pair partner give
        headings 180° apart, so the mean is taken of the doubled angles; the branch is the one
        nearest the previous estimate (the first: nearest magnetic north)."""
        c, s = self._h2
        if c == 0.0 and s == 0.0:
            return self._heading
        half = math.degrees(math.atan2(s, c)) / 2.0
        return half + 180.0 * round((self._heading - half) / 180.0)

    def identify(self, g, b):
        """Pose (1..12) and heading misfit (deg) for a mean gravity vector ``g`` and raw field ``b``
        (:func:`twelve_position.identify_pose` at the stand's measured heading)."""
        cands = _gravity_candidates(g, self.pose_tolerance_deg)
        if not cands:
            return None, float("nan")
        # the heading with this capture counted in (either member of the pair: doubled angles)
        psi = math.radians(field_heading_deg(cands[0], b))
        c, s = self._h2
        c, s = c + math.cos(2 * psi), s + math.sin(2 * psi)
        half = math.degrees(math.atan2(s, c)) / 2.0
        heading = half + 180.0 * round((self._heading - half) / 180.0)
        return identify_pose(g, b, heading, self.pose_tolerance_deg)

    def _count_heading(self, st):
        psi = math.radians(field_heading_deg(st.pose, st.b))
        self._h2[0] += math.cos(2 * psi)
        self._h2[1] += math.sin(2 * psi)
        self._heading = self.heading
        if not self._heading_said and len(self.captures) >= 4 and abs(self._heading) > 20.0:
            self._heading_said = True
            self._info(f"the field points {self._heading:+.0f}° from the stand's north: the stand is turned about "
                       f"{-self._heading:+.0f}° from magnetic north (the solve does not need it; the poses are told "
                       "apart by it)")

    def _warn(self, msg):
        self.warnings.append(msg)
        del self.warnings[:-200]  # bounded history
        return msg

    def _info(self, msg):
        self.infos.append(msg)
        del self.infos[:-200]
        return msg

    # ---- offering stations -----------------------------------------------------------------
    @property
    def _open(self) -> bool:
        """The first sequence is under way: captures, no solve yet, not ended."""
        return bool(self.captures) and self.solves == 0 and not self.ended and self.state != "done"

    def offer(self, st: Station) -> str:
        """Consider a closed station.  Returns 'accepted', 'merged', 'rejected', 'ignored' or 'solved'.

        Everything refused is said in :attr:`warnings`.  A station carrying a pose label (from a
        log) must agree with the pose its gravity shows; a station after the calibration that
        does not continue a new round in order is a survey station: 'ignored' without a warning.
        Before any solve, a static long after the last capture, or ``end_after_stations`` statics
        in a row that are not poses of the sequence, end it (:meth:`end_sequence`).
        """
        self.applies_from = None
        if self._open:
            gap = st.t_start - self.captures[-1].t_end
            if gap > self.end_after_s:
                self.end_sequence(f"{gap:.0f} s without a capture before the static at {st.where} (end_after_s "
                                  f"{self.end_after_s:g})", at=st.t_start)
        result = self._offer(st)
        if result in ("accepted", "merged", "rejected", "solved"):   # a pose: the probe on the stand?
            self._poses_seen.append((st.t_start, st.t_end))
            del self._poses_seen[:-1000]     # bounded (a stand's poses and retakes are far fewer)
        if self._open:
            if result == "ignored":
                if not self._strays:
                    self._stray_t0 = st.t_start
                self._strays += 1
                if self._strays >= self.end_after_stations:
                    self.end_sequence(f"{self._strays} statics in a row that are not poses of the sequence, the "
                                      f"last at {st.where}: the probe has left the stand")
            else:   # a capture, or a pose the gates refused: the probe is still on the stand
                self._strays = 0
        return result

    @property
    def undecided_since(self):
        """Start (data time, s) of the first of the statics in a row, after captures, that are not
        poses of the open sequence — whether they are the survey's first stations (the sequence
        ends at the ``end_after_stations``-th: its record applies from the first) or a rest on the
        stand (a capture follows: they stay the stand's) is not decided yet; None: nothing is
        undecided.  A driver holds the survey's use of those stations until it is."""
        return self._stray_t0 if self._open and self._strays else None

    def end_sequence(self, why: str = "the sequence is over", at=None):
        """The twelve-pose sequence is over (the probe left the stand, or the time ran out) with
        poses missing or refused: solve with the captures there are (least squares), say which
        poses are missing and why, and close the session to them (a new round from pose 1, or a
        recapture, is still taken).  The record applies (:attr:`applies_from`) from the first
        stray's start, else from ``at`` (data time, s: the station that ended it).  Returns the
        calibration or None."""
        self.applies_from = self._stray_t0 if self._strays else at
        self.ended = True
        self._strays = 0
        missing = self.pending
        if not missing and self.state == "done":
            return self.calibration
        why_missing = "; ".join(f"pose {p}: " + (f"refused ({self._refused[p]})" if p in self._refused
                                                    else "never captured") for p in missing)
        self._warn(f"the twelve-pose sequence is over ({why}) with {len(self.captured)} of 12 poses: solving with "
                   f"the {len(self.captures)} capture(s) there are — missing {why_missing}")
        if not self.captures:
            self.state, self.message = "error", "no twelve-position captures: nothing to calibrate"
            return None
        return self.solve(final=True)

    def _reject(self, pose, why: str) -> str:
        if pose is not None:
            self._refused[pose] = why
        return "rejected"

    def _offer(self, st: Station) -> str:
        pose, _ = self.identify(st.g, st.b)
        # solved from every pose: later statics are new rounds or survey stations; solved without some
        # poses (at the end of the data, least squares): those poses are still welcome — unless the
        # sequence ended (the probe left the stand): then a survey station near a missing pose is not one
        after_solve = (self.state == "done" and not self.recapture and not self.pending) or \
            (self.ended and not self.recapture)
        self.current_pose = pose if pose is not None else -1
        where = f"pose {pose} at {st.where}" if pose is not None else f"static at {st.where}"
        if pose is None:
            if not after_solve and st.duration_s >= self.min_capture_s:
                self._warn(f"{where} is not one of the twelve poses (no tool axis within "
                           f"{self.pose_tolerance_deg:g}° of vertical): ignored")
            return "ignored"
        if after_solve and not self._continues_round(pose, st):
            return "ignored"
        if st.short or st.duration_s < self.min_capture_s:
            self._warn(f"{where}: capture too short ({st.duration_s:.2f} s < {self.min_capture_s:g} s): rejected")
            return self._reject(pose, "capture too short")
        apply_gates(st, self.limits, self._solve_site.gravity_mps2)   # a no-op when the caller gated it
        findings = st.findings
        said = set(self._settled.add(findings))      # a settling at every hold: said twice, then counted
        for f in findings:
            if f.code == "flat":   # the same stuck/clipped axis in every station: said twice, then counted
                self._flat_seen[f.axis] = self._flat_seen.get(f.axis, 0) + 1
                if self._flat_seen[f.axis] > 2:
                    continue
            if f.code == "settled" and f.message not in said:
                continue
            self._warn(f.message)
        for msg in self._saturation.add(st, findings):
            self._warn(msg)
        if st.moved:
            return self._reject(pose, "the probe moved during the hold")
        if len(st.unusable) == 2:
            self._warn(f"{where}: neither sensor usable: rejected")
            return self._reject(pose, "neither sensor usable")
        if st.pose and st.pose != pose:
            cands = _gravity_candidates(st.g, self.pose_tolerance_deg)
            if st.pose not in cands:
                self._warn(f"station at {st.where}: labelled pose {st.pose} but its gravity says pose "
                           f"{' or '.join(map(str, cands))}: refused (mislabelled pose)")
                return self._reject(st.pose, "mislabelled")
            pose = st.pose   # the label tells the pair's members apart where the heading guessed wrong
        labelled = bool(st.pose)
        st.pose = pose
        if not self._same_as_before(st):
            return "ignored"
        result = self._accept(st, labelled, after_solve)
        if result not in ("ignored", "rejected"):
            self._count_heading(st)
        return result

    def _same_as_before(self, st) -> bool:
        """Before any solve, a pose captured again must read as its first capture did (the same
        sensor errors in the same pose): a survey station near a pose does not.  A pose whose pair
        partner is captured must read gravity as the partner does (the two differ by a turn about
        the vertical only, which leaves gravity in the tool frame as it is: they differ by twice
        the stand's tilt) — within 5 times what the other complete pairs show, at least
        :data:`PAIR_MIN_TOL_DEG`: a survey station a degree or two off a missing pose is not it."""
        if self.state == "done":
            return True     # calibrated: checked against the pose itself (_looks_like_pose)
        first = next((c for c in self.captures if c.pose == st.pose), None)
        if first is None:
            partner = st.pose + 1 if st.pose % 2 else st.pose - 1
            mate = next((c for c in self.captures if c.pose == partner), None)
            if mate is None:
                return True
            tol = self._pair_tolerance(exclude=position(st.pose))
            dg = angle_between_deg(st.g, mate.g)
            if dg <= tol:
                return True
            self._warn(f"pose {st.pose} at {st.where}: its gravity is {dg:.2f}° from its pair partner's (pose "
                       f"{partner} at {mate.where}; the stand's other pairs agree within {tol / 5.0:.2g}°): not pose "
                       f"{st.pose} (a survey station near it?) — ignored")
            return False
        dg, db = angle_between_deg(st.g, first.g), angle_between_deg(st.b, first.b)
        if dg <= REPEAT_TOL_DEG and db <= REPEAT_TOL_DEG:
            return True
        self._warn(f"pose {st.pose} at {st.where}: its gravity is {dg:.1f}° and its field {db:.1f}° from pose "
                   f"{st.pose}'s earlier capture at {first.where}: not the same pose (a survey station, or the "
                   "stand moved?) — ignored")
        return False

    def _pair_tolerance(self, exclude: int) -> float:
        """How far a pose's gravity may be from its pair partner's: 5 times the largest difference
        the other complete pairs show (at least PAIR_MIN_TOL_DEG); REPEAT_TOL_DEG until two are in."""
        firsts = {}
        for c in self.captures:
            firsts.setdefault(c.pose, c)
        diffs = [angle_between_deg(firsts[p].g, firsts[p + 1].g) for p in range(1, 13, 2)
                 if p in firsts and p + 1 in firsts and position(p) != exclude]
        if len(diffs) < 2:
            return REPEAT_TOL_DEG
        return max(PAIR_MIN_TOL_DEG, 5.0 * max(diffs))

    def _continues_round(self, pose, st) -> bool:
        """After the first solve: does this station start or continue a new round in order?

        Calibrated, a stand pose is exactly one of Table 1 (within the stand's accuracy) and its
        field points as in the first round's capture of it; a survey station a few degrees off a
        pose is neither, and is left alone silently."""
        if not self.rounds:
            return False
        if st.pose:                      # a stand's log says it is a calibration pose (label checked next)
            return True
        if not self._looks_like_pose(pose, st):
            return False
        if not self._round:
            return position(pose) == 0
        last = self._round[-1]
        if position(pose) in (position(last.pose), position(last.pose) + 1):
            return True
        self._warn(f"round {self.solves + 1} abandoned after pose {last.pose}: the next static ({st.where}) is "
                   f"pose {pose}, out of Table 1's order — the survey started? Its {len(self._round)} capture(s) "
                   "are not used; the coefficients stay those of the complete rounds")
        self._drop_round()
        return position(pose) == 0

    def _looks_like_pose(self, pose, st) -> bool:
        cal = self.calibration
        if cal is None:
            return True
        from ..core.station import correct_stations   # the one correction path, with the station's temperature

        g, b = (v[0] for v in correct_stations([st], cal))
        if not angle_between_deg(g, pose_reference(pose, [0.0, 0.0, 1.0])) <= ROUND_GRAVITY_TOL_DEG:
            return False
        first = next((c for c in self.captures if c.pose == pose and "mag" not in c.unusable), None)
        if first is not None:
            b0 = correct_stations([first], cal)[1][0]
            if not angle_between_deg(b, b0) <= ROUND_FIELD_TOL_DEG:
                return False
        return True

    def _drop_round(self):
        ids = {id(c) for c in self._round}
        self.captures = [c for c in self.captures if id(c) not in ids]
        self._round = []

    def _accept(self, st, labelled, after_solve) -> str:
        last = self.captures[-1] if self.captures else None
        had_pending = bool(self.pending)
        # the same pose again right after: the hold was cut into pieces (or retaken) — one capture
        if (last is not None and last.pose == st.pose and st.pose not in self.recapture
                and st.t_start - last.t_end <= MERGE_GAP_S and set(last.unusable) == set(st.unusable)):
            merged = merge_stations(last, st)
            self.captures[-1] = merged
            if self._round and self._round[-1] is last:
                self._round[-1] = merged
            self._info(f"pose {st.pose}: pieces of one hold merged ({last.where} + {st.where})")
            self._dirty = True
            return "merged"
        where = f"pose {st.pose} at {st.where}"
        if st.pose in self.recapture:
            self.recapture.discard(st.pose)
            self.captures = [c for c in self.captures if c.pose != st.pose]
            self.captures.append(st)
            self._info(f"{where}: replaces the earlier capture(s) (recapture)")
            self._dirty = True
            return self._maybe_solve(not self.recapture)
        if after_solve:
            self.captures.append(st)
            self._dirty = True
            if labelled:
                return "accepted"        # a stand's labelled capture: used by the next solve (finish)
            self._round.append(st)
            if len({c.pose for c in self._round}) == 12:
                self._info(f"round {self.solves + 1} complete: solving again with every round")
                self._round = []
                return self._maybe_solve(True)
            return "accepted"
        if st.pose in {c.pose for c in self.captures}:
            if last is not None and last.pose == st.pose:
                self._warn(f"{where}: pose {st.pose} captured again (retake): both captures are used")
            elif labelled:
                self._info(f"{where}: another capture of pose {st.pose} (labelled): used")
            elif self.state == "done":
                self._info(f"{where}: pose {st.pose} again after a solve without pose(s) {self.pending}: not used")
                return "ignored"
            elif self._next_round(st, last):
                pass
            else:
                self._pre_round = False
                self._warn(f"{where}: pose {st.pose} again, out of sequence (expected pose {self.expected_next}): "
                           "ignored — call recapture to replace a pose")
                return "ignored"
        elif position(st.pose) != position(self.expected_next):
            if labelled:   # a stand's labels: its order is its own
                self._info(f"{where}: out of Table 1's order (labelled); accepted")
            else:
                self._warn(f"{where}: out of order (expected pose {self.expected_next} next); accepted")
        self.captures.append(st)
        self._dirty = True
        # solve when this capture completes the twelve (later captures wait for a round or the end)
        return self._maybe_solve(had_pending and not self.pending and not self.recapture)

    def _next_round(self, st, last) -> bool:
        """Before any solve, with a pose still missing: does ``st`` start or continue a further
        round?  It starts when the sequence has reached its last pair (11–12) and ``st`` is of the
        first (1–2); it continues in Table 1's order (a missing pair skipped).  ``st`` already reads
        as its earlier capture (:meth:`_same_as_before`)."""
        if last is None:
            return False
        if position(st.pose) == 0 and position(last.pose) == position(POSES[-1]):
            self._pre_round = True
            self._info(f"pose {st.pose} at {st.where}: a further round before any solve (pose(s) {self.pending} "
                       "missing): its captures are used")
            return True
        return self._pre_round and position(st.pose) >= position(last.pose)

    def _maybe_solve(self, now: bool) -> str:
        if now:
            self.applies_from = None      # solved from this capture: the record applies after it
            return "solved" if self.solve() is not None else "rejected"
        return "accepted"

    # ---- control ---------------------------------------------------------------------------
    def request_recapture(self, pose: int) -> str:
        if pose not in POSES:
            raise ValueError(f"pose {pose} is not one of 1..12")
        self.recapture.add(pose)
        self.state = "collecting"
        return f"pose {pose} will be replaced by its next capture"

    def reset(self):
        self.captures.clear()
        self.warnings.clear()
        self.infos.clear()
        self.recapture.clear()
        self._round = []
        self._dirty = False
        self._saturation = SaturationMonitor()
        self._settled = SettlingTally()
        self._flat_seen, self._flat_reported = {}, {}
        self._h2, self._heading, self._heading_said, self.solve_notes = [0.0, 0.0], 0.0, False, []
        self._solve_texts = set()
        self.ended, self._strays, self._refused, self._pre_round = False, 0, {}, False
        self._stray_t0, self._poses_seen, self.applies_from = math.nan, [], None
        self.result = self.calibration = None
        self.state, self.message, self.current_pose, self.solves = "collecting", "", -1, 0

    def finish(self):
        """End of the data: solve with what there is if anything changed since the last solve.

        A round in progress after the first solve is not used (incomplete); labelled captures are.
        Before any solve, the captures there are are solved if they determine the model (least
        squares, poses missing) — else the session ends in 'error' with a message naming the
        poses never captured.  Statics after the last capture that had not ended the sequence
        yet (:attr:`undecided_since`) were the survey's: the record applies from the first of them.
        Returns the calibration or None.
        """
        self.applies_from = self.undecided_since
        if self.state == "done" and self._round:
            self._warn(f"round {self.solves + 1} incomplete at the end of the data (poses "
                       f"{[c.pose for c in self._round]}): not used")
            self._drop_round()
            return self.calibration
        if not self._dirty and self.state in ("done", "error"):
            return self.calibration
        if not self.captures:
            self.state = "error"
            self.message = "no twelve-position captures in the data: nothing to calibrate"
            self._warn(self.message)
            return None
        return self.solve(final=True)

    def capture_sets(self):
        """The captures each triad may use, as :class:`twelve_position.CaptureSet` (acc, mag)."""
        sets = []
        for sensor in ("acc", "mag"):
            use = [c for c in self.captures if sensor not in c.unusable]
            means = [c.g if sensor == "acc" else c.b for c in use]
            noise = [c.g_noise if sensor == "acc" else c.b_noise for c in use]
            sig = [np.maximum(np.where(np.isfinite(nz), nz, sd), 1e-12) / math.sqrt(c.n)
                   for c, nz, sd in zip(use, noise, [c.g_std if sensor == "acc" else c.b_std for c in use])]
            sets.append(CaptureSet([c.pose for c in use], means, sig, [f"pose {c.pose} at {c.where}" for c in use]))
        return sets

    def solve(self, final: bool = False):
        """Solve from the captures (see the module docstring).  Sets :attr:`state` and :attr:`message`;
        what the solve says goes to :attr:`warnings` (as it happens) and :attr:`solve_notes` (the
        last solve's only).  ``final``: the end of the data — poses captured more often than the
        others are named then (a duplicated label?), not while a round is still coming in."""
        self.state = "solving"
        self._dirty = False
        notes = []
        for axis, k in self._flat_seen.items():
            if k > 2:
                notes.append(f"{axis} was flat in {k} captures (the first two are named above); those captures' "
                             f"{axis.split()[0]} data are not used")
        settled = self._settled.summary(len(self.captures))
        if settled:
            notes.append(settled)
        acc, mag = self.capture_sets()
        missing = self.pending
        try:
            self.result = solve_captures(acc, mag, self._solve_site)
            if missing:
                self.result.notes.append(f"solved without pose(s) {missing} (never captured), by least squares "
                                         "over the others")
            cal = to_calibration(self.result, self._solve_site, self.probe_id)
            if self.site is None:   # the site the stand measures is the record's (said by the caller)
                cal.site = self.result.site_estimate(self._solve_site.gravity_mps2)
                cal.site_source = "measured"
            if self._specs or self._options:
                cal = self._fit_model(cal, notes)
            span = self.stand_span()
            if span is not None:   # in the record: a run's accounting tells the stand's raw stations from a survey's
                cal.diagnostics["stand"] = {"t_start": float(span[0]), "t_end": float(span[1])}
            self.calibration = cal
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.state = "error"
            self.message = (f"solve failed: {exc}" + (f" (poses never captured: {missing})" if missing else ""))
            self._say_solve(notes + [self.message])
            return None
        notes.extend(self.result.notes)
        counts = {p: sum(1 for c in self.captures if c.pose == p) for p in self.captured}
        usual = int(np.median(list(counts.values())))
        extra = sorted(p for p, k in counts.items() if k > usual)
        if final and extra:
            notes.append("pose(s) " + ", ".join(f"{p} ×{counts[p]}" for p in extra) + f" captured more often than "
                         f"the others (×{usual}): their means average every capture; check for a duplicated pose label")
        self._say_solve(notes)
        self.state = "done"
        self.solves += 1
        n = len(self.captures)
        self.message = (f"solved from {n} captures ({self.result.acc.method}); RMS residual acc "
                        f"{self.result.acc.rms_residual:.5f} m/s², mag {self.result.mag.rms_residual:.2f} nT "
                        f"({self.result.acc.z_rms:.1f}× and {self.result.mag.z_rms:.1f}× the noise)")
        return self.calibration

    def stand_span(self):
        """``(t_start, t_end)`` (data time, s) of the stand after a solve: from the first to the last
        capture the solve used (either triad), widened by the stations taken as poses (captured,
        merged, refused, left out) that follow on from it — each within ``end_after_s`` of the next,
        the gap that ends a sequence; None before a solve.  A survey station taken for a pose long
        before or after the stand (a vertical well near pose 9's attitude) is not in it."""
        if self.result is None:
            return None
        used = set(self.result.acc.used) | set(self.result.mag.used)
        caps = [c for c in self.captures if f"pose {c.pose} at {c.where}" in used]   # capture_sets' names
        if not caps:
            return None
        t0, t1 = min(c.t_start for c in caps), max(c.t_end for c in caps)
        # every capture too: the one offered now (solved from) is not among the poses seen yet
        seen = sorted(self._poses_seen + [(c.t_start, c.t_end) for c in self.captures])
        for a, b in reversed(seen):          # back from the first capture used
            if b < t0 and t0 - b > self.end_after_s:
                break
            t0 = min(t0, a)
        for a, b in seen:                    # on from the last
            if a > t1 and a - t1 > self.end_after_s:
                break
            t1 = max(t1, b)
        return t0, t1

    @property
    def _solve_site(self) -> Site:
        """The site the solve assumes: the given one, else the defaults (g_d and M_d only set the
        triads' scale; the record then owns the measured site)."""
        return self.site if self.site is not None else Site()

    def _fit_model(self, cal, notes):
        """The paper's model plus the named effects, fitted to the captures by the lab's fit from
        the twelve-position solution; the stand's heading is fitted too (its north is not known).
        Parameters the captures cannot determine are named in the record and in ``notes``."""
        from .fit import fit
        from .labmodel import N_POSES, POSES_LABEL, LabModel
        from ..core.station import Stations

        imp = self.result.implied_site()
        lm = LabModel.from_calibration(cal, fit_heading=True)   # the stand's north is not known: always fitted
        lm.heading_deg = float(((imp["field_heading_deg"] - cal.site.declination_deg) + 180.0) % 360.0 - 180.0)
        lm = lm.with_named(self.effects)
        named = lm.probe.labels() + ([POSES_LABEL] if lm.fit_poses else [])
        data = Stations.from_list(self.captures, "cal", source="captures")
        fixed = None
        if lm.fit_poses:
            # twelve poses alone do not separate every pose's rotation from the base model: the
            # poses that are right (not left out of both triads alike) define the frame, held at
            # zero; the rotations of those the stand holds off are fitted
            off = list(self.result.poses_off)
            idx = lm.param_index(POSES_LABEL)
            fixed = np.zeros(len(lm.get_vector()), bool)
            fixed[idx] = True
            for q in off:
                fixed[idx[3 * (q - 1):3 * q]] = False
            lm.gauge_poses = np.array([q not in off for q in range(1, N_POSES + 1)])
            notes.append("stand_pose_error: " + (f"the rotation of pose(s) {off} fitted, the other poses defining the "
                                                 "frame" if off else "no pose is held off by these captures (none was "
                                                 "left out of both triads alike): nothing to fit"))
        res = fit(lm, data, fixed=fixed)
        if not res.success:
            raise ValueError(f"the fit of {', '.join(named)} did not converge: {res.message}")
        for n in res.not_identifiable:
            notes.append(f"model [{', '.join(named) or 'base'}]: {n.parameter} is not identifiable from these captures: "
                         f"{n.reason}")
        self.fit = res
        out = lm.record(probe_id=self.probe_id, site_source=cal.site_source, not_identifiable=res.not_identifiable,
                        fit_stats={"chi2": res.chi2, "dof": res.dof, "z_rms": res.z_rms, "stations": len(data)},
                        method=f"{cal.method}; then the lab's fit of {', '.join(named)} to the captures")
        out.diagnostics.update({k: v for k, v in cal.diagnostics.items() if k not in out.diagnostics})
        notes.append(f"model fitted to the {len(data)} captures: base (bias, scale, nonorthogonality) + "
                     f"[{', '.join(named) or 'none'}]; noise-normalised residual RMS "
                     f"{res.z_rms:.2f} (the twelve-position model alone: {self.result.mag.z_rms:.2f} mag, "
                     f"{self.result.acc.z_rms:.2f} acc)")
        return out

    def _say_solve(self, notes):
        self.solve_notes = list(notes)
        for note in notes:
            if note not in self._solve_texts:   # the same words again at a later solve: said once
                self._warn(note)
            self._solve_texts.add(note)

    @property
    def capture_warnings(self) -> list:
        """The warnings about captures (gates, identification, sequence), without what the solves
        said: with :attr:`solve_notes` what a whole log gives, when only the last solve matters."""
        return [w for w in self.warnings if w not in self._solve_texts]

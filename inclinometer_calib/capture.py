"""Live twelve-pose capture: which pose the probe is in, what is captured, when to solve — ROS-free.

The calibration node feeds every closed static segment (from :class:`streaming.StaticDetector`)
to :meth:`CaptureSession.offer`.  The session identifies the pose from the measured gravity
direction (which tool axis is vertical, and its sign) and the field's horizontal direction (which
of the two rolls about that axis: the stand is set up against magnetic north, as in the paper),
keeps captures, warns on wrong/repeated/short/moving captures, and solves when all twelve are in.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .frames import Site
from .twelve_position import POSES, identify_pose_with_field, solve_stations, to_calibration


@dataclass
class Capture:
    """One accepted capture of a pose (means in the gravity-vector convention and nT)."""

    pose: int
    g: np.ndarray
    b: np.ndarray
    temp_c: float
    t_start: float
    t_end: float
    n: int
    misfit_deg: float


@dataclass
class _StationView:
    """Adapter giving captures the attributes ``twelve_position.solve_stations`` reads."""

    pose: int
    g: np.ndarray
    b: np.ndarray


@dataclass
class CaptureSession:
    """State of a twelve-pose calibration.

    Parameters
    ----------
    site : Site — reference field (the stand is assumed aligned with magnetic north).
    min_capture_s : a capture shorter than this is rejected ("too short").
    max_scatter_acc / max_scatter_mag : per-axis standard deviation above which the probe is
        taken to have moved during the capture (m/s², nT).
    pose_tolerance_deg : how far from a Table 1 pose the measured gravity may be.
    rounds : accept repeated poses as extra rounds (True) or ignore them with a warning (False).
    """

    site: Site = field(default_factory=Site)
    min_capture_s: float = 1.0
    max_scatter_acc: float = 0.02
    max_scatter_mag: float = 150.0
    pose_tolerance_deg: float = 15.0
    rounds: bool = False
    probe_id: str = "probe"

    captures: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    current_pose: int = -1
    recapture: set = field(default_factory=set)
    result: object = None
    calibration: object = None
    state: str = "collecting"
    message: str = ""

    @property
    def captured(self) -> list:
        return [p for p in POSES if self.captures.get(p)]

    @property
    def pending(self) -> list:
        return [p for p in POSES if not self.captures.get(p)]

    @property
    def expected_next(self) -> int:
        return self.pending[0] if self.pending else -1

    def _stand_field(self):
        # Stand frame = magnetic north/east/down (Table 1 is laid out against magnetic north).
        return Site(self.site.total_field_nt, self.site.dip_deg, 0.0, self.site.gravity_mps2).field_ned()

    def identify(self, g, b):
        """Pose (1..12) and misfit (deg) for mean gravity vector ``g`` and raw field ``b``."""
        return identify_pose_with_field(g, b, self._stand_field(), self.pose_tolerance_deg)

    def _warn(self, msg):
        self.warnings.append(msg)
        del self.warnings[:-50]  # bounded history
        return msg

    def offer(self, seg) -> str:
        """Consider a closed static segment.  Returns 'accepted', 'rejected', 'ignored' or 'solved'."""
        pose, misfit = self.identify(seg.g, seg.b)
        self.current_pose = pose if pose is not None else -1
        if pose is None:
            self._warn(f"static at t={seg.t_start:.1f}-{seg.t_end:.1f} s is not one of the twelve poses "
                       f"(no tool axis within {self.pose_tolerance_deg:g}° of vertical): ignored")
            return "ignored"
        where = f"pose {pose} at t={seg.t_start:.1f}-{seg.t_end:.1f} s"
        if getattr(seg, "short", False) or seg.duration_s < self.min_capture_s:
            self._warn(f"{where}: capture too short ({seg.duration_s:.2f} s < {self.min_capture_s:g} s): rejected")
            return "rejected"
        if np.max(seg.g_std) > self.max_scatter_acc or np.max(seg.b_std) > self.max_scatter_mag:
            self._warn(f"{where}: probe moved during the capture (scatter acc {np.max(seg.g_std):.4f} m/s², "
                       f"mag {np.max(seg.b_std):.1f} nT): rejected")
            return "rejected"
        if misfit > 30.0:
            self._warn(f"{where}: field direction {misfit:.0f}° from the expected one — is the stand aligned "
                       f"with magnetic north? accepted on gravity")
        cap = Capture(pose, np.asarray(seg.g), np.asarray(seg.b), seg.temp_c, seg.t_start, seg.t_end, seg.n, misfit)
        if pose in self.recapture:
            self.recapture.discard(pose)
            self.captures[pose] = [cap]
        elif self.captures.get(pose):
            if not self.rounds:
                self._warn(f"{where}: repeated pose (already captured); ignored — call recapture to replace it")
                return "ignored"
            self.captures[pose].append(cap)
        else:
            if pose != self.expected_next and self.state == "collecting":
                self._warn(f"{where}: out of order (expected pose {self.expected_next} next); accepted")
            self.captures[pose] = [cap]
        if not self.pending and not self.recapture:
            self.solve()
            return "solved"
        return "accepted"

    def request_recapture(self, pose: int) -> str:
        if pose not in POSES:
            raise ValueError(f"pose {pose} is not one of 1..12")
        self.recapture.add(pose)
        self.state = "collecting"
        return f"pose {pose} will be replaced by its next capture"

    def reset(self):
        self.captures.clear()
        self.warnings.clear()
        self.recapture.clear()
        self.result = self.calibration = None
        self.state, self.message, self.current_pose = "collecting", "", -1

    def solve(self):
        self.state = "solving"
        views = [_StationView(c.pose, c.g, c.b) for caps in self.captures.values() for c in caps]
        try:
            self.result = solve_stations(views, self.site)
            self.calibration = to_calibration(self.result, self.site, self.probe_id)
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.state, self.message = "error", f"solve failed: {exc}"
            self._warn(self.message)
            return None
        self.state = "done"
        self.message = (f"solved from {sum(len(v) for v in self.captures.values())} captures; RMS residual acc "
                        f"{self.result.acc.rms_residual:.5f} m/s², mag {self.result.mag.rms_residual:.2f} nT")
        return self.calibration

"""Lab data: static stations of several logs, each with what is known of its orientation.

Three kinds of station, by what constrains them:

* ``pose``  — a twelve-position pose (Table 1): orientation known from the pose, in the stand frame;
* ``ref``   — a stand-grid station with reference drift/azimuth/toolface: orientation known (a
  vertical reference without azimuth is known too: its rotation about the vertical is the
  toolface, as for azimuth 0);
* ``free``  — orientation unknown: constrained only by the site invariants |g|, |B| and dip.

Each log has a *role*: ``"cal"`` (the non-magnetic lab stand) or ``"val"`` (validation / survey
data, where survey-only effects such as axial drill-string interference may act).
Measured vectors are in the gravity-vector convention (m/s², down positive) and nT.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..effects import T_REF_C
from ..frames import orientation_matrix
from ..gates import apply_gates
from ..probelog import read_csv, report, segment_stations
from ..survey import Tolerances, in_vertical_cone
from ..twelve_position import pose_matrix

#: Floors of the per-station noise estimate (std/√n): m/s², nT.
SIGMA_FLOOR = {"acc": 2e-6, "mag": 0.05}
KINDS = ("pose", "ref", "free")


@dataclass
class LabData:
    """Station arrays (N stations).

    g, b : (N, 3) measured means (gravity vector m/s², field nT)
    g_sigma, b_sigma : (N, 3) noise of the means (within-station std / √n, floored)
    g_scatter, b_scatter : (N, 3) within-station sample std (the raw noise estimate)
    temp_c, time_s : (N,)
    rotation : (N, 3, 3) tool→NED for pose/ref stations, NaN for free ones
    kind : (N,) 'pose' | 'ref' | 'free';   role : (N,) 'cal' | 'val'
    pose : (N,) 1..12 or 0;   ref : (N, 3) deg or NaN;   n : (N,) samples;  source : (N,) log name
    """

    g: np.ndarray
    b: np.ndarray
    g_sigma: np.ndarray
    b_sigma: np.ndarray
    g_scatter: np.ndarray
    b_scatter: np.ndarray
    temp_c: np.ndarray
    time_s: np.ndarray
    rotation: np.ndarray
    kind: np.ndarray
    role: np.ndarray
    pose: np.ndarray
    ref: np.ndarray
    n: np.ndarray
    source: np.ndarray

    def __len__(self):
        return len(self.g)

    def subset(self, mask) -> "LabData":
        mask = np.asarray(mask)
        return LabData(**{k: getattr(self, k)[mask] for k in self.__dataclass_fields__})

    @classmethod
    def concatenate(cls, parts) -> "LabData":
        parts = [p for p in parts if len(p)]
        return cls(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in cls.__dataclass_fields__})

    @property
    def oriented(self) -> np.ndarray:
        return self.kind != "free"

    def describe(self) -> str:
        parts = []
        for role in ("cal", "val"):
            m = self.role == role
            if m.any():
                kinds = ", ".join(f"{int(np.sum(m & (self.kind == k)))} {k}" for k in KINDS if np.any(m & (self.kind == k)))
                t = self.temp_c[m]
                parts.append(f"{role}: {int(m.sum())} stations ({kinds}), {t.min():.1f}–{t.max():.1f} °C")
        return "; ".join(parts)


def from_stations(stations, role: str, source: str = "", use_ref: bool = True) -> LabData:
    """Build lab data from :class:`probelog.Station` objects."""
    if role not in ("cal", "val"):
        raise ValueError(f"role must be 'cal' or 'val', got {role!r}")
    n = len(stations)
    rot = np.full((n, 3, 3), np.nan)
    kind = np.empty(n, dtype=object)
    for i, st in enumerate(stations):
        if st.pose:
            rot[i] = pose_matrix(st.pose)
            kind[i] = "pose"
        elif use_ref and st.has_ref:
            rot[i] = orientation_matrix(*st.ref)
            kind[i] = "ref"
        elif (use_ref and np.isfinite(st.ref[0]) and np.isfinite(st.ref[2])
              and in_vertical_cone(st.ref[0], Tolerances().min_drift_deg)):
            rot[i] = orientation_matrix(st.ref[0], 0.0, st.ref[2])   # vertical: no azimuth, toolface about it
            kind[i] = "ref"
        else:
            kind[i] = "free"
    cnt = np.array([max(st.n, 1) for st in stations], dtype=float)
    temps = np.array([st.temp_c for st in stations], dtype=float)
    if not np.all(np.isfinite(temps)):
        # unknown temperature: the log's mean, else the effects' reference — temperature effects
        # then see no span and are reported as not identifiable, instead of poisoning the fit
        known = temps[np.isfinite(temps)]
        temps = np.where(np.isfinite(temps), temps, known.mean() if len(known) else T_REF_C)
    g_sc = np.array([st.g_std for st in stations]).reshape(n, 3)
    b_sc = np.array([st.b_std for st in stations]).reshape(n, 3)
    return LabData(
        g=np.array([st.g for st in stations]).reshape(n, 3), b=np.array([st.b for st in stations]).reshape(n, 3),
        g_sigma=np.maximum(np.nan_to_num(g_sc) / np.sqrt(cnt)[:, None], SIGMA_FLOOR["acc"]),
        b_sigma=np.maximum(np.nan_to_num(b_sc) / np.sqrt(cnt)[:, None], SIGMA_FLOOR["mag"]),
        g_scatter=g_sc, b_scatter=b_sc,
        temp_c=temps,
        time_s=np.array([(st.t_start + st.t_end) / 2 for st in stations], dtype=float),
        rotation=rot, kind=kind.astype(str), role=np.full(n, role), pose=np.array([st.pose for st in stations]),
        ref=np.array([st.ref for st in stations], dtype=float).reshape(n, 3), n=cnt.astype(int),
        source=np.full(n, source))


def load_logs(cal_path=None, val_path=None, warn=None, free_paths=()) -> LabData:
    """Read CAL and VAL probe logs (CSV) into one LabData; rejections go to ``warn`` (callable).

    Stations are found by the live nodes' detector (:func:`probelog.segment_stations`) and
    checked by the gates (:mod:`gates`); a station in which the probe moved is left out, with
    the reason.  ``free_paths``: logs without labels (the probe turned by hand through many
    attitudes); their stations enter as ``free`` (role ``cal``), constrained by the site
    invariants only.
    """
    parts = []
    for path, role, labels in ([(p, "cal", False) for p in (free_paths or ())]
                               + [(cal_path, "cal", True), (val_path, "val", True)]):
        if path is None:
            continue
        log, rejections = read_csv(path)
        stations, problems = segment_stations(log, use_labels=labels)
        if warn:
            report(path, rejections, problems, warn)
        for st in stations:
            for f in apply_gates(st):
                if warn:
                    warn(f"{path}: {f.message}")
        moved = [s for s in stations if s.moved]
        stations = [s for s in stations if not s.moved]  # a capture taken while moving is not used
        if moved and warn:
            warn(f"{path}: {len(moved)} station(s) left out: the probe moved during the capture")
        if not stations:
            raise ValueError(f"{path}: no usable static stations" + ("" if labels else
                             " (need ≥ 0.5 s still at each attitude)"))
        parts.append(from_stations(stations, role, source=str(path), use_ref=labels))
    if not parts:
        raise ValueError("no logs given")
    return LabData.concatenate(parts)

"""A probe generator for the lab's tests that shares no code with the package.

Its own physics, written out here with numpy and scipy only: orientations from scipy's
``Rotation`` (intrinsic Z-Y-Z: azimuth, drift, toolface; tool Z down-hole, NED), each triad's
output ``y = A·x + q·x²/s + b + c·(T - 20 °C) + r·t + w(t) + k·x_prev + h·(x_prev − x)·exp(−t_h/τ_h) + noise``
with a full 3×3 gain
matrix ``A`` (scale and non-orthogonality together), a square-law term ``q`` per axis (``s`` 9.81 m/s²
or 50 000 nT), a temperature coefficient ``c``, a drift rate ``r`` and a
random-walk bias ``w``, a remanence ``k`` (a share of the previous hold's input) and a settling ``h``
(a fluxgate's offset set by the change of field at the move, decaying with ``τ_h`` from the hold's
first sample, ``t_h`` the time since it); in a survey log
the input ``x`` carries the drill string's field, fixed in the tool frame; a stand whose twelve poses may sit off by fixed small rotations (the
same in every round, both triads alike); moves between holds by spherical interpolation.  Logs
are written the way other tools write them: specific force (a resting probe reads -gravity),
temperature per row, pose labels and reference angles on static rows only, a vertical pose with
no azimuth, times continuing from one log to the next (one power-on).

The true model's level on the lab's own stations comes from :func:`true_vectors`: each
station's mean output corrected with the true parameters (what a perfect model would give).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: The stand's twelve poses as (drift, azimuth, toolface) degrees; None: no azimuth (vertical).
POSES = {1: (90, 0, 180), 2: (90, 180, 180), 3: (90, 0, 0), 4: (90, 180, 0), 5: (90, 0, 90), 6: (90, 180, 90),
         7: (90, 180, 270), 8: (90, 0, 270), 9: (0, None, 0), 10: (0, None, 180), 11: (180, None, 0),
         12: (180, None, 180)}
T0_C = 20.0


def attitude(drift, azimuth, toolface) -> Rotation:
    """Tool→NED rotation Rz(azimuth)·Ry(drift)·Rz(toolface) (azimuth None: 0, about the vertical)."""
    return Rotation.from_euler("ZYZ", [azimuth or 0.0, drift, toolface], degrees=True)


@dataclass
class Triad:
    gain: np.ndarray                      # (3, 3) output per input
    bias: np.ndarray                      # (3,)
    noise: float
    temp_coef: np.ndarray = field(default_factory=lambda: np.zeros(3))   # per °C
    drift_rate: np.ndarray = field(default_factory=lambda: np.zeros(3))  # per hour
    walk: float = 0.0                     # random-walk density, unit/√s
    remanence: float = 0.0                # share of the previous hold's true input kept (same log)
    survey_field: np.ndarray = field(default_factory=lambda: np.zeros(3))   # tool-frame field of the drill string
    square: np.ndarray = field(default_factory=lambda: np.zeros(3))   # y_i += square_i·x_i²/scale (scale: 1 g, 50 µT)
    temp_lag_s: float = 0.0               # the sensor's temperature lags the logged one (first order, s)
    settle_share: float = 0.0             # share of the field's change at the move left as an offset
    settle_tau_s: float = 1.0             # ... decaying with this time constant from the hold's start (s)


@dataclass
class Site:
    gravity: float = 9.8101
    field_nt: float = 48700.0
    dip_deg: float = 61.3
    declination_deg: float = 0.0

    def vectors(self):
        d, a = np.radians(self.dip_deg), np.radians(self.declination_deg)
        h = self.field_nt * np.cos(d)
        return np.array([0.0, 0.0, self.gravity]), np.array([h * np.cos(a), h * np.sin(a), self.field_nt * np.sin(d)])

    def as_yaml_dict(self):
        return {"total_field_nt": self.field_nt, "dip_deg": self.dip_deg, "declination_deg": self.declination_deg,
                "gravity_mps2": self.gravity}


def random_probe(seed, noise_acc=0.004, noise_mag=25.0):
    """A probe with errors of the size real ones have (bias ~0.03 m/s² / 300 nT, scale ~1e-3,
    axes off by ~0.2°)."""
    rng = np.random.default_rng(seed)

    def gain(scale_sd, axis_sd):
        return np.eye(3) + np.diag(rng.normal(0, scale_sd, 3)) + (1 - np.eye(3)) * rng.normal(0, axis_sd, (3, 3))

    acc = Triad(gain(1e-3, 3e-3), rng.normal(0, 0.03, 3), noise_acc)
    mag = Triad(gain(2e-3, 3e-3), rng.normal(0, 300.0, 3), noise_mag)
    return {"acc": acc, "mag": mag}


@dataclass
class Hold:
    rot: Rotation
    seconds: float
    pose: int = 0
    ref: tuple = (None, None, None)       # written on the static rows


def twelve_pose_rounds(rounds=2, hold_s=3.0, offsets=None):
    """The stand's poses in order, ``rounds`` times; ``offsets`` {pose: (rx, ry, rz) deg}: where the
    stand really holds a pose (a tool-frame rotation after the set attitude), the same every round."""
    out = []
    for _ in range(rounds):
        for p, (i, a, t) in POSES.items():
            r = attitude(i, a, t)
            if offsets and p in offsets:
                r = r * Rotation.from_rotvec(np.radians(offsets[p]))
            out.append(Hold(r, hold_s, pose=p, ref=(i, a, t)))
    return out


def grid(drifts=(5, 30, 60, 90, 120), azimuths=(20, 140, 260), toolfaces=(0, 135, 250), hold_s=3.0, vertical=True):
    out = [Hold(attitude(i, a, t), hold_s, ref=(i, a, t)) for i in drifts for a in azimuths for t in toolfaces]
    if vertical:
        out += [Hold(attitude(0, None, t), hold_s, ref=(0, None, t)) for t in (0, 120, 240)]
    return out


def _stream(holds, rate_hz, move_s, t0):
    """Sample times, tool→NED rotations, and per-sample hold index (-1 while moving)."""
    ts, rots, idx = [], [], []
    t = t0
    prev = None
    each = Rotation.concatenate([h.rot for h in holds])     # a hold's samples: its rotation, indexed
    for k, h in enumerate(holds):
        if prev is not None:
            n = max(int(round(move_s * rate_hz)), 2)
            s = Slerp([0, 1], Rotation.concatenate([prev.rot, h.rot]))(np.linspace(0, 1, n + 2)[1:-1])
            ts.append(t + np.arange(n) / rate_hz)
            rots.append(s)
            idx.append(np.full(n, -1))
            t += n / rate_hz
        n = int(round(h.seconds * rate_hz))
        ts.append(t + np.arange(n) / rate_hz)
        rots.append(each[np.full(n, k)])
        idx.append(np.full(n, k))
        t += n / rate_hz
        prev = h
    return np.concatenate(ts), Rotation.concatenate(rots), np.concatenate(idx)


class Generator:
    """One probe on one site; logs written one after another from one power-on."""

    def __init__(self, probe, site=None, seed=0, rate_hz=50.0, move_s=1.0):
        self.probe, self.site = probe, site or Site()
        self.rng = np.random.default_rng(seed + 1000)
        self.rate_hz, self.move_s = rate_hz, move_s
        self.t = 0.0
        self.walk_state = {"acc": np.zeros(3), "mag": np.zeros(3)}
        self.walk_track = {"acc": [], "mag": []}   # (t, value) per sample, for the true model
        self.lag_state = {}                         # the temperature each sensor feels, across logs
        self.felt_track = {"acc": [], "mag": []}   # (t, felt temperature), for the true model
        self.hold_starts = []                       # (time of a hold's first sample, its previous hold's rotation or None)

    def _lagged(self, name, t, temp, tau):
        """The temperature the sensor feels: the logged one through a first-order lag of ``tau`` s,
        continuing from the previous log (exact for a temperature linear between samples' ends)."""
        state = self.lag_state.get(name, float(temp[0]))
        out = np.empty_like(temp)
        prev_t = t[0]
        for k in range(len(t)):
            a = math.exp(-max(t[k] - prev_t, 0.0) / tau)
            state = a * state + (1.0 - a) * temp[k]
            out[k] = state
            prev_t = t[k]
        self.lag_state[name] = state
        self.felt_track[name].append((t.copy(), out.copy()))
        return out

    def felt_at(self, name, times, logged):
        """The temperature sensor ``name`` felt at ``times`` (the logged one where it has no lag)."""
        if not self.felt_track[name]:
            return logged
        t = np.concatenate([a for a, _ in self.felt_track[name]])
        f = np.concatenate([b for _, b in self.felt_track[name]])
        return np.interp(times, t, f)

    def outputs(self, t, rot, temp, prev_rot=None, prev_ok=None, survey=False, since=None):
        g_ned, b_ned = self.site.vectors()
        out = {}
        for name, v_ned in (("acc", g_ned), ("mag", b_ned)):
            tr = self.probe[name]
            x = rot.inv().apply(v_ned)                       # true tool-frame vector
            if survey:                                       # the drill string's field moves with the tool
                x = x + tr.survey_field
            y = x @ tr.gain.T + tr.square * x ** 2 / (9.81 if name == "acc" else 5e4)
            felt = self._lagged(name, t, temp, tr.temp_lag_s) if tr.temp_lag_s > 0 else temp
            y = y + tr.bias + np.outer(felt - T0_C, tr.temp_coef) + np.outer(t / 3600.0, tr.drift_rate)
            if tr.remanence and prev_rot is not None:        # the previous hold's input, a little of it kept
                y = y + tr.remanence * np.nan_to_num(prev_rot.inv().apply(v_ned) * prev_ok[:, None])
            if tr.settle_share and since is not None:        # the change at the move, settling away
                step = (prev_rot.inv().apply(v_ned) - rot.inv().apply(v_ned)) * prev_ok[:, None]
                decay = np.where(np.isfinite(since), np.exp(-np.nan_to_num(since) / tr.settle_tau_s), 0.0)
                y = y + tr.settle_share * step * decay[:, None]
            if tr.walk:
                dt = np.diff(t, prepend=t[0] - 1.0 / self.rate_hz)
                steps = self.rng.normal(0, 1, (len(t), 3)) * tr.walk * np.sqrt(dt)[:, None]
                w = self.walk_state[name] + np.cumsum(steps, axis=0)
                self.walk_state[name] = w[-1]
                self.walk_track[name].append((t, w))
                y = y + w
            out[name] = y + self.rng.normal(0, tr.noise, y.shape)
        return out["acc"], out["mag"]

    def write(self, path, holds, temperature=lambda t: np.full_like(t, 25.0), labels=True, survey=False):
        """Write one log; ``temperature(t)`` °C of the session time (s).  Returns the hold intervals."""
        t, rot, idx = _stream(holds, self.rate_hz, self.move_s, self.t)
        self.t = float(t[-1] + 1.0 / self.rate_hz)
        temp = temperature(t)
        # the hold before each sample's (moves belong to the hold they leave); none for the first
        held = np.maximum.accumulate(np.where(idx >= 0, idx, -1))
        prev = np.where(idx >= 0, idx - 1, held)
        prev_ok = (prev >= 0).astype(float)
        prev_rot = Rotation.concatenate([h.rot for h in holds])[np.maximum(prev, 0)]
        first = (idx >= 0) & np.r_[True, idx[1:] != idx[:-1]]          # each hold's first sample
        t_first = np.full(len(holds), np.nan)
        t_first[idx[first]] = t[first]
        since = np.where(idx >= 0, t - t_first[np.maximum(idx, 0)], np.nan)
        self.hold_starts += [(float(t_first[k]), holds[k - 1].rot if k else None) for k in range(len(holds))]
        acc, mag = self.outputs(t, rot, temp, prev_rot, prev_ok, survey, since)
        # the rows as csv.writer writes them (no field needs quoting; "\r\n" ends each), column by column
        f = -acc                                             # specific force: a resting probe reads -gravity
        cols = [[format(v, spec) for v in x.tolist()] for x, spec in
                ((t, ".3f"), (f[:, 0], ".6f"), (f[:, 1], ".6f"), (f[:, 2], ".6f"), (mag[:, 0], ".2f"),
                 (mag[:, 1], ".2f"), (mag[:, 2], ".2f"), (temp, ".3f"))]
        label = [",".join([str(h.pose) if h.pose else ""] + ["" if v is None else f"{v:.1f}" for v in h.ref])
                 if labels else ",,," for h in holds]
        lab = [label[k] if k >= 0 else ",,," for k in idx.tolist()]
        head = "t_s,ax,ay,az,mx,my,mz,temp_c,pose,ref_drift_deg,ref_azimuth_deg,ref_toolface_deg"
        with open(path, "w", newline="") as fh:
            fh.write(head + "\r\n" + "".join(",".join(row) + "\r\n" for row in zip(*cols, lab)))
        return t

    def walk_at(self, sensor, times):
        if not self.walk_track[sensor]:
            return np.zeros((len(times), 3))
        t = np.concatenate([a for a, _ in self.walk_track[sensor]])
        w = np.concatenate([b for _, b in self.walk_track[sensor]])
        return np.stack([np.interp(times, t, w[:, j]) for j in range(3)], axis=1)


def true_vectors(gen: Generator, data):
    """The lab's stations corrected with the true parameters: gravity vector (m/s²) and field (nT).

    ``data``: the lab's :class:`Stations` (times from the first log's first sample, which is this
    generator's t = 0; the validation log written with ``survey=True`` when a drill-string field is set)."""
    out = []
    for name, meas in (("acc", data.g), ("mag", data.b)):
        tr = gen.probe[name]
        felt = gen.felt_at(name, data.time_s, data.temp_c)
        y = meas - tr.bias - np.outer(felt - T0_C, tr.temp_coef) - np.outer(data.time_s / 3600.0, tr.drift_rate)
        y = y - gen.walk_at(name, data.time_s)
        if tr.remanence:
            v_ned = gen.site.vectors()[0 if name == "acc" else 1]
            prev = np.swapaxes(data.prev_rotation, -1, -2) @ v_ned
            y = y - tr.remanence * np.nan_to_num(prev)
        if tr.settle_share:
            y = y - tr.settle_share * _settling_means(gen, data, name, tr.settle_tau_s)
        x = np.linalg.solve(tr.gain, y.T).T
        for _ in range(20):                                  # y = A·x + q·x²/s, by fixed point
            x = np.linalg.solve(tr.gain, (y - tr.square * x ** 2 / (9.81 if name == "acc" else 5e4)).T).T
        if np.any(tr.survey_field):                          # the survey log's inputs carried the drill string's field
            x = x - np.outer(data.role == "val", tr.survey_field)
        out.append(x)
    return out[0], out[1]


def _settling_means(gen: Generator, data, name, tau):
    """Per station, the mean over its samples of the settling's ``(x_prev − x)·exp(−t_h/τ)`` (the
    hold it lies in found by its first sample's time)."""
    v_ned = gen.site.vectors()[0 if name == "acc" else 1]
    starts = np.array([s for s, _ in gen.hold_starts])
    out = np.zeros((len(data), 3))
    for i, smp in enumerate(data.samples):
        ts = np.asarray(smp)[:, 0]
        k = int(np.searchsorted(starts, ts[0] + 1e-9)) - 1
        t0, prev = gen.hold_starts[k]
        if prev is None:
            continue
        x = np.asarray(smp)[:, 1:4] if name == "acc" else np.asarray(smp)[:, 4:7]
        rot = Rotation.from_matrix(data.rotation[i]) if np.all(np.isfinite(data.rotation[i])) else None
        cur = rot.inv().apply(v_ned) if rot is not None else x.mean(axis=0)
        out[i] = (prev.inv().apply(v_ned) - cur) * np.mean(np.exp(-(ts - t0) / tau))
    return out

"""Probe simulator: a probe on a three-axis non-magnetic calibration stand in a site field.

The probe's two triads each follow the seed paper's Poisson model (bias, scale, six
non-orthogonality terms) plus any catalogue effects from :mod:`effects`, plus white noise.  Beyond
the triad signal chain the simulator models two whole-probe effects:

* ``stand_pose_error`` (deg, 1σ): each static station's real orientation is the set orientation
  rotated by a small random rotation (the stand's pose errors); the labels keep the set values.
* ``time_skew`` (s): the magnetometer samples at ``t + skew`` on the same trajectory (visible only
  while the probe moves).

Seeded and deterministic: the same seed and options give the same samples, bit for bit.
Magnitudes are physical: accelerometer in m/s², magnetometer in nT, temperature in °C.
The output accelerometer is REP-145 specific force (``-g``), as a real IMU reports it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from . import effects as fx
from .errormodel import E_TERMS, TriadModel
from .frames import Site, attitude_angles, orientation_matrix, specific_force_from_gravity
from .probelog import ProbeLog
from .twelve_position import POSES, pose_matrix

#: Whole-probe effects handled here rather than in a triad's signal chain.
PROBE_EFFECTS = {"stand_pose_error": "deg", "time_skew": "s"}


@dataclass
class ProbeModel:
    """A simulated probe: the base Poisson model of each triad plus extra effects and noise.

    ``acc`` is in the gravity-vector convention (m/s²), ``mag`` in nT.  ``survey_only`` lists
    effects present in survey/validation logs but not on the non-magnetic calibration stand
    (axial drill-string interference by default).
    """

    acc: TriadModel
    mag: TriadModel
    effects: list = field(default_factory=list)
    noise_acc: float = 0.002   # m/s² per sample, 1σ
    noise_mag: float = 20.0    # nT per sample, 1σ
    stand_pose_error_deg: float = 0.0
    time_skew_s: float = 0.0
    survey_only: tuple = ("axial_interference",)

    def chain(self, sensor: str, survey: bool) -> list:
        """Signal chain of one triad: extra effects around the base model (E, K, B)."""
        base = self.acc if sensor == "acc" else self.mag
        chain = [fx.NonOrthogonality(sensor=sensor, values=_e_values(base)),
                 fx.Scale(sensor=sensor, values={"k": base.scale - 1.0}),
                 fx.Bias(sensor=sensor, values={"b": base.bias})]
        for eff in self.effects:
            if eff.sensor == sensor and (survey or eff.name not in self.survey_only):
                chain.append(eff)
        return chain

    def measure(self, g_tool, b_tool, temp_c, t_s, rng, survey: bool):
        """Raw outputs for true tool-frame gravity (m/s², down) and field (nT), (N, 3) each.

        Returns ``(specific_force_mps2, field_nt)``.
        """
        ctx = fx.Context(temperature_c=np.asarray(temp_c, float), time_s=np.asarray(t_s, float))
        a = fx.apply_chain(g_tool, self.chain("acc", survey), ctx)
        m = fx.apply_chain(b_tool, self.chain("mag", survey), ctx)
        a = a + rng.normal(0.0, self.noise_acc, a.shape)
        m = m + rng.normal(0.0, self.noise_mag, m.shape)
        return specific_force_from_gravity(a), m

    def to_dict(self) -> dict:
        return {
            "acc": self.acc.parameters(), "mag": self.mag.parameters(),
            "effects": [{"name": e.name, "sensor": e.sensor, "axes": e.axes,
                         "values": {k: v.tolist() for k, v in e.values.items()}} for e in self.effects],
            "noise_acc_mps2": self.noise_acc, "noise_mag_nt": self.noise_mag,
            "stand_pose_error_deg": self.stand_pose_error_deg, "time_skew_s": self.time_skew_s,
            "survey_only": list(self.survey_only),
        }


def _e_values(model: TriadModel):
    e1, e2 = [], []
    for a in "xyz":
        n1, n2 = fx.NonOrthogonality.term_names(a)
        e1.append(model.e[n1])
        e2.append(model.e[n2])
    return {"e1": np.array(e1), "e2": np.array(e2)}


def random_probe(rng: np.random.Generator, severity: float = 1.0) -> tuple:
    """Base-model errors of an uncalibrated probe, drawn around the seed paper's Table 2 sizes.

    Accelerometer: bias ~0.05 m/s², scale ~0.3 %, e-terms ~0.02; magnetometer: bias ~300 nT,
    scale ~3 %, e-terms ~0.03 (all 1σ × ``severity``).  Returns ``(acc, mag)`` TriadModels.
    """
    def triad(bias, scale, e):
        return TriadModel(scale=1.0 + severity * rng.normal(0, scale, 3),
                          bias=severity * rng.normal(0, bias, 3),
                          e={k: severity * rng.normal(0, e) for k in E_TERMS})
    return triad(0.05, 0.003, 0.02), triad(300.0, 0.03, 0.03)


# --------------------------------------------------------------------------------------------
# Sessions: static stations joined by moves
# --------------------------------------------------------------------------------------------
@dataclass
class Stationary:
    """A static station of a session: set orientation (tool→NED), labels, duration and temperature."""

    rotation: np.ndarray
    duration_s: float
    pose: int = 0
    ref: tuple = (np.nan, np.nan, np.nan)
    temp_c: float = 25.0


def twelve_pose_session(rounds_temp_c=(25.0,), duration_s: float = 2.0, azimuth_deg: float = 0.0,
                        refs: bool = False):
    """The twelve poses of Table 1, once per round, at each round's temperature.

    ``azimuth_deg`` rotates the whole stand about the vertical (its "north" need not be north).
    ``refs``: also give each pose's set (drift, azimuth, toolface), as a stand's log does — the
    vertical poses 9–12 without azimuth (:func:`frames.attitude_angles`).
    """
    rz = orientation_matrix(0.0, azimuth_deg, 0.0)
    return [Stationary(rz @ pose_matrix(p), duration_s, pose=p, temp_c=t,
                       ref=attitude_angles(rz @ pose_matrix(p)) if refs else (np.nan, np.nan, np.nan))
            for t in rounds_temp_c for p in POSES]


VAL_DRIFTS = (2, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90)
VAL_AZIMUTHS = (0, 60, 120, 180, 240, 300)
VAL_TOOLFACES = (0, 120, 240)


def stand_grid_session(drifts=VAL_DRIFTS, azimuths=VAL_AZIMUTHS, toolfaces=VAL_TOOLFACES,
                       duration_s: float = 1.0, temp_profile_c=(25.0,)):
    """Validation stations on the stand grid.

    ``temp_profile_c``: temperatures (°C) the session passes through, piecewise linear over the
    stations (e.g. (25, 45, 25): heated, then cooled — which keeps temperature and time apart).
    """
    combos = [(i, a, t) for i in drifts for a in azimuths for t in toolfaces]
    prof = np.atleast_1d(np.asarray(temp_profile_c, dtype=float))
    temps = np.interp(np.linspace(0, 1, len(combos)), np.linspace(0, 1, len(prof)), prof) if combos else []
    return [Stationary(orientation_matrix(i, a, t), duration_s, ref=(float(i), float(a), float(t)),
                       temp_c=float(tc)) for (i, a, t), tc in zip(combos, temps)]


def run_session(probe: ProbeModel, site: Site, stations, rng: np.random.Generator, rate_hz: float = 100.0,
                move_s: float = 1.0, t0: float = 0.0, survey: bool = False, lead_in=None) -> ProbeLog:
    """Simulate a session: each station held for its duration, with moves of ``move_s`` between.

    During moves the orientation follows a slerp between the stations (rows carry no labels).
    ``lead_in = (rotation, seconds)``: the session starts with a move of that length from that
    orientation (where an earlier session left the probe), so that sessions run one after the
    other make one continuous stream.
    """
    if rate_hz <= 0:
        raise ValueError("rate_hz must be positive")
    dt = 1.0 / rate_hz
    # Build a time line of key orientations: each station is held constant, moves interpolate.
    actual = []
    for st in stations:
        r = st.rotation
        if probe.stand_pose_error_deg > 0:
            err = Rotation.from_rotvec(np.radians(rng.normal(0, probe.stand_pose_error_deg, 3))).as_matrix()
            r = r @ err
        actual.append(r)
    key_t, key_r = [], []
    segments = []  # (t_start, t_end, station index or -1, temp_start, temp_end)
    t = t0
    prev_temp = stations[0].temp_c if stations else 25.0
    if lead_in is not None and stations and lead_in[1] > 0:
        key_t.append(t)
        key_r.append(np.asarray(lead_in[0], dtype=float))
        segments.append((t, t + lead_in[1], -1, prev_temp, prev_temp))
        t += lead_in[1]
    for k, (st, r) in enumerate(zip(stations, actual)):
        if k > 0 and move_s > 0:
            segments.append((t, t + move_s, -1, prev_temp, st.temp_c))
            t += move_s
        key_t += [t, t + st.duration_s]
        key_r += [r, r]
        segments.append((t, t + st.duration_s, k, st.temp_c, st.temp_c))
        t += st.duration_s
        prev_temp = st.temp_c
    if not segments:
        return ProbeLog.empty()
    key_t = np.array(key_t)
    # Nudge duplicate key times (zero-length moves) so the slerp stays well defined.
    key_t = key_t + np.arange(len(key_t)) * 1e-9
    slerp = Slerp(key_t, Rotation.from_matrix(np.array(key_r)))

    t_all, pose, ref, temp, seg_id = [], [], [], [], []
    for (ts, te, k, t_a, t_b) in segments:
        n = max(int(round((te - ts) * rate_hz)), 1)
        tt = ts + dt * np.arange(n)
        t_all.append(tt)
        seg_id.append(np.full(n, k))
        temp.append(np.interp(tt, [ts, te], [t_a, t_b]))
        if k >= 0:
            pose.append(np.full(n, stations[k].pose, dtype=int))
            ref.append(np.tile(np.asarray(stations[k].ref, float), (n, 1)))
        else:
            pose.append(np.zeros(n, dtype=int))
            ref.append(np.full((n, 3), np.nan))
    t_all = np.concatenate(t_all)
    temp = np.concatenate(temp)
    seg_id = np.concatenate(seg_id)
    actual = np.array(actual)

    def rot_at(times):
        # Static rows use the station's matrix exactly (no quaternion round trip); moves slerp.
        r = slerp(np.clip(times, key_t[0], key_t[-1])).as_matrix()
        static = seg_id >= 0
        hold = static & (times == t_all)
        r[hold] = actual[seg_id[hold]]
        return r

    r_acc = rot_at(t_all)
    r_mag = rot_at(t_all + probe.time_skew_s) if probe.time_skew_s else r_acc
    g_tool = np.einsum("nji,j->ni", r_acc, site.gravity_ned())   # Rᵀ·g_ned
    b_tool = np.einsum("nji,j->ni", r_mag, site.field_ned())     # Rᵀ·b_ned
    f, m = probe.measure(g_tool, b_tool, temp, t_all, rng, survey)
    return ProbeLog(t_all, f, m, temp, np.concatenate(pose), np.concatenate(ref))


def build_probe(seed: int, effects_spec=(), severity: float = 1.0, noise_acc: float = 0.002,
                noise_mag: float = 20.0) -> ProbeModel:
    """A random probe (seeded) with the named extra effects.

    ``effects_spec`` items are ``(name, sensor or None, axes or None, values)`` where values is a
    list of floats (one, or one per axis) for the effect's first parameter; whole-probe effects
    ``stand_pose_error`` (deg) and ``time_skew`` (s) take one value.
    """
    rng = np.random.default_rng(seed)
    acc, mag = random_probe(rng, severity)
    probe = ProbeModel(acc=acc, mag=mag, noise_acc=noise_acc, noise_mag=noise_mag)
    for name, sensor, axes, values in effects_spec:
        if name == "stand_pose_error":
            probe.stand_pose_error_deg = float(values[0])
            continue
        if name == "time_skew":
            probe.time_skew_s = float(values[0])
            continue
        cls = fx.CATALOGUE.get(name)
        if cls is None:
            raise ValueError(f"unknown effect {name!r}; known: "
                             f"{', '.join(sorted(list(fx.CATALOGUE) + list(PROBE_EFFECTS)))}")
        sensors = [sensor] if sensor else list(cls.sensors)
        for s in sensors:
            eff = cls(sensor=s, axes=axes or cls.default_axes)
            first = cls.specs[0].name
            eff.values[first] = np.broadcast_to(np.asarray(values, float), (len(eff.axes),)).copy()
            probe.effects.append(eff)
    return probe


def parse_effect_arg(text: str):
    """Parse ``NAME[:sensor[:axes]]=V[,V,...]`` into ``(name, sensor, axes, [values])``."""
    if "=" not in text:
        raise ValueError(f"--effect {text!r}: expected NAME[:sensor[:axes]]=VALUE[,VALUE...]")
    lhs, rhs = text.split("=", 1)
    parts = lhs.split(":")
    if len(parts) > 3 or not parts[0]:
        raise ValueError(f"--effect {text!r}: expected NAME[:sensor[:axes]]=VALUE")
    name = parts[0]
    sensor = parts[1] if len(parts) > 1 and parts[1] else None
    axes = parts[2] if len(parts) > 2 and parts[2] else None
    try:
        values = [float(v) for v in rhs.split(",")]
    except ValueError:
        raise ValueError(f"--effect {text!r}: values must be numbers") from None
    if sensor not in (None, "acc", "mag"):
        raise ValueError(f"--effect {text!r}: sensor must be 'acc' or 'mag'")
    return name, sensor, axes, values


def well_path_session(n_stations: int = 30, kickoff_deg: float = 0.0, build_deg_per_station: float = 3.0,
                      max_drift_deg: float = 85.0, azimuth_start_deg: float = 40.0,
                      turn_deg_per_station: float = 1.5, duration_s: float = 2.0,
                      temp_start_c: float = 25.0, temp_end_c: float = 60.0, seed: int = 0):
    """Survey stations down a synthetic build-and-turn well path (reference angles known).

    Drift builds from ``kickoff_deg`` by ``build_deg_per_station`` up to ``max_drift_deg``;
    azimuth turns steadily; toolface is random per station (the tool rolls while drilling);
    temperature rises with depth.
    """
    rng = np.random.default_rng(seed)
    out = []
    temps = np.linspace(temp_start_c, temp_end_c, n_stations)
    for k in range(n_stations):
        i = min(kickoff_deg + build_deg_per_station * k, max_drift_deg)
        a = (azimuth_start_deg + turn_deg_per_station * k) % 360.0
        t = float(rng.uniform(0, 360))
        out.append(Stationary(orientation_matrix(i, a, t), duration_s, ref=(float(i), float(a), t),
                              temp_c=float(temps[k])))
    return out

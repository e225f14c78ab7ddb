"""Probe simulator: a probe on a three-axis non-magnetic calibration stand in a site field.

The probe measures with the package's probe model (:class:`model.ProbeModel`: the seed paper's
Poisson model of each triad — bias, scale, six non-orthogonality terms — plus any catalogue or
plug-in effects, each with its scope: survey-only effects such as axial interference act on the
survey, not on the stand), plus white noise, plus the whole-probe effects of :mod:`effects`:

* ``stand_pose_error`` (deg, 1σ): each static station's real orientation is the set orientation
  rotated by a small random rotation (the stand's pose errors); the labels keep the set values.
* ``time_skew`` (s): the magnetometer samples at ``t + skew`` on the same trajectory (visible only
  while the probe moves).

Seeded and deterministic: the same seed and options give the same samples, bit for bit.
Magnitudes are physical: accelerometer in m/s², magnetometer in nT, temperature in °C.
The output accelerometer is REP-145 specific force (``-g``), as a real IMU reports it.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from ..core import effects as fx
from ..core.errormodel import E_TERMS, TriadModel
from ..core.frames import Site, attitude_angles, orientation_matrix, pose_matrix, specific_force_from_gravity
from ..core.model import ProbeModel
from ..io.probelog import ProbeLog
from ..core.station import Station
from .twelve_position import POSES


@dataclass
class SimulatedProbe:
    """A simulated probe: its true model (:class:`model.ProbeModel`), white noise and the
    whole-probe effects.  ``model.acc`` is in the gravity-vector convention (m/s²), ``model.mag``
    in nT."""

    model: ProbeModel
    noise_acc: float = 0.002   # m/s² per sample, 1σ
    noise_mag: float = 20.0    # nT per sample, 1σ
    whole_probe: list = field(default_factory=list)   # effects of stage "probe"
    #: Where each stochastic effect's random walk stands: key -> (time s, value per axis); sessions
    #: simulated one after the other continue one walk (one power-on).
    walks: dict = field(default_factory=dict, repr=False)

    @property
    def acc(self) -> TriadModel:
        return self.model.acc

    @property
    def mag(self) -> TriadModel:
        return self.model.mag

    @property
    def effects(self) -> list:
        """The effects beyond the base model (triad ones, then whole-probe ones)."""
        return [t.effect for t in self.model.extra_terms] + list(self.whole_probe)

    def _whole(self, cls) -> float:
        for e in self.whole_probe:
            if isinstance(e, cls):
                return float(e.get_vector()[0])
        return 0.0

    @property
    def stand_pose_error_deg(self) -> float:
        return self._whole(fx.StandPoseError)

    @property
    def time_skew_s(self) -> float:
        return self._whole(fx.TimeSkew)

    def measure(self, g_tool, b_tool, temp_c, t_s, rng, survey: bool, draws: "SessionDraws | None" = None,
                history=None):
        """What the probe sends: :meth:`measure_gravity`'s accelerometer as REP-145 specific force
        (:func:`frames.specific_force_from_gravity`, as a real IMU reports it), and the field.
        Returns ``(specific_force_mps2, field_nt)``."""
        a, m = self.measure_gravity(g_tool, b_tool, temp_c, t_s, rng, survey, draws, history)
        return specific_force_from_gravity(a), m

    def measure_gravity(self, g_tool, b_tool, temp_c, t_s, rng, survey: bool, draws: SessionDraws | None = None,
                        history=None):
        """Raw outputs for true tool-frame gravity (m/s², down) and field (nT), (N, 3) each, on the
        stand (``survey`` False) or in the survey; ``t_s`` s since the data's first sample.

        The random numbers come from ``rng`` in this order: each stochastic effect's walk
        increments (N × its axes), the accelerometer noise (N × 3), the magnetometer noise (N × 3).
        ``draws`` (:class:`SessionDraws`): the samples are one piece of a longer block, in order,
        and take their numbers from the block's streams instead, the same ones the whole block
        would have taken from ``rng``.  ``history`` (:class:`effects.History`, per sample): for
        effects that depend on the sequence of holds (a sensor settling after the move).

        Returns ``(gravity_mps2, field_nt)``: the raw accelerometer in the core's convention
        (down positive), for a caller that feeds the core directly (:func:`msa.simulate_run`).
        """
        role = "val" if survey else "cal"
        a, m = self.model.forward(g_tool, b_tool, temp_c, t_s, role=role, history=history)
        walk = self._walk(np.asarray(t_s, dtype=float), rng, role, draws)
        a, m = a + walk["acc"], m + walk["mag"]
        a = a + (draws.stream("acc") if draws else rng).normal(0.0, self.noise_acc, a.shape)
        m = m + (draws.stream("mag") if draws else rng).normal(0.0, self.noise_mag, m.shape)
        return a, m

    def walk_widths(self, role: str) -> list:
        """``[(key, axes)]`` of the stochastic effects acting in ``role``, in the order they draw."""
        return [(t.effect.key, len(np.atleast_1d(t.effect.values["density"]))) for t in self.model.terms
                if t.effect.stochastic and t.acts_on(role)]

    def _walk(self, t_s, rng, role, draws=None) -> dict:
        """The stochastic effects' draws at times ``t_s`` (ascending), per sensor (N, 3): a random
        walk ``w(t+Δt) = w(t) + K·√Δt·ε`` per axis (:class:`effects.BiasWander`, output stage: added
        to the output), continuing from where the previous session left it.  In pieces
        (``draws``), the running sum is carried from piece to piece so that every value is the
        whole block's, bit for bit (``np.cumsum`` adds left to right)."""
        out = {"acc": np.zeros((len(t_s), 3)), "mag": np.zeros((len(t_s), 3))}
        for term in self.model.terms:
            e = term.effect
            if not e.stochastic or not term.acts_on(role) or not len(t_s):
                continue
            k = np.asarray(e.values["density"], dtype=float)
            t_last, w_last = self.walks.get(e.key, (float(t_s[0]), np.zeros(len(k))))
            dt = np.maximum(np.diff(np.concatenate([[t_last], t_s])), 0.0)
            z = (draws.stream(e.key) if draws else rng).normal(0.0, 1.0, (len(t_s), len(k)))
            inc = z * k * np.sqrt(dt)[:, None]
            if draws is None:
                w = w_last + np.cumsum(inc, axis=0)
            else:   # w = (w at the block's start) + (running sum of the block's increments)
                base, carry = draws.carry.get(e.key, (w_last, None))
                run = np.cumsum(inc if carry is None else np.vstack([carry, inc]), axis=0)
                run = run if carry is None else run[1:]
                draws.carry[e.key] = (base, run[-1].copy())
                w = base + run
            self.walks[e.key] = (float(t_s[-1]), w[-1].copy())
            out[e.sensor][:, [fx.AXIS_INDEX[a] for a in e.axes]] += w
        return out

    def to_dict(self) -> dict:
        return {
            "acc": self.acc.parameters(), "mag": self.mag.parameters(),
            "effects": [{"name": t.effect.name, "sensor": t.effect.sensor, "axes": t.effect.axes, "scope": t.scope,
                         "values": {k: v.tolist() for k, v in t.effect.values.items()}}
                        for t in self.model.extra_terms],
            "noise_acc_mps2": self.noise_acc, "noise_mag_nt": self.noise_mag,
            "stand_pose_error_deg": self.stand_pose_error_deg, "time_skew_s": self.time_skew_s,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SimulatedProbe":
        """The probe of a ``truth.json`` (:meth:`to_dict`); plug-in effects must be loaded first."""
        model = ProbeModel.base(TriadModel.from_parameters(d["acc"]), TriadModel.from_parameters(d["mag"]))
        for e in d.get("effects", ()):
            ecls = fx.effect_class(e["name"])
            eff = ecls(sensor=e["sensor"], axes=e["axes"], values={k: np.asarray(v) for k, v in e["values"].items()})
            model = model.with_effect(eff, e.get("scope"))
        whole = [cls(sensor="probe", values={cls.specs[0].name: d[key]})
                 for cls, key in ((fx.StandPoseError, "stand_pose_error_deg"), (fx.TimeSkew, "time_skew_s"))
                 if d.get(key)]
        return cls(model, d.get("noise_acc_mps2", 0.002), d.get("noise_mag_nt", 20.0), whole)


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
# Sessions: static stations (:meth:`station.Station.planned`) joined by moves
# --------------------------------------------------------------------------------------------
def twelve_pose_session(rounds_temp_c=(25.0,), duration_s: float = 2.0, azimuth_deg: float = 0.0,
                        refs: bool = False):
    """The twelve poses of Table 1, once per round, at each round's temperature.

    ``azimuth_deg`` rotates the whole stand about the vertical (its "north" need not be north).
    ``refs``: also give each pose's set (drift, azimuth, toolface), as a stand's log does — the
    vertical poses 9–12 without azimuth (:func:`frames.attitude_angles`).
    """
    rz = orientation_matrix(0.0, azimuth_deg, 0.0)
    return [Station.planned(rz @ pose_matrix(p), duration_s, pose=p, temp_c=t,
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
    return [Station.planned(orientation_matrix(i, a, t), duration_s, ref=(float(i), float(a), float(t)),
                            temp_c=float(tc)) for (i, a, t), tc in zip(combos, temps)]


class SessionDraws:
    """The random numbers of one session's samples, drawn piece by piece in order.

    A whole session takes from ``rng``, in this order (:meth:`SimulatedProbe.measure`): for each
    stochastic effect N × its axes standard normals (the walk), then N × 3 for the accelerometer
    noise, then N × 3 for the magnetometer noise.  Here each of these blocks gets its own copy of
    ``rng`` positioned at the block's start (found by drawing and discarding the numbers before
    it, ``SKIP`` at a time), so that pieces of the session taken in order get exactly the numbers
    the whole session would have got — every draw is ``loc + scale·z`` of one standard normal
    per element, in order — and ``rng`` is left where the whole session leaves it.  ``carry``
    holds each walk's running sum from piece to piece.
    """

    SKIP = 1 << 16

    def __init__(self, rng: np.random.Generator, n: int, widths):
        self.carry = {}
        self._streams = {}
        for key, per_sample in list(widths) + [("acc", 3), ("mag", 3)]:
            self._streams[key] = copy.deepcopy(rng)
            left = n * per_sample
            while left > 0:
                k = min(left, self.SKIP)
                rng.normal(0.0, 1.0, k)
                left -= k

    def stream(self, key) -> np.random.Generator:
        return self._streams[key]


class SessionPlan:
    """A session laid out in time: each planned station (:meth:`station.Station.planned`) held for
    its duration, with moves of ``move_s`` between; its samples are simulated on demand, whole
    (:meth:`log`) or in pieces of bounded size (:meth:`chunks`), with the same numbers either way.

    Building the plan takes the stations' stand pose errors from ``rng`` (the first draws of a
    session); the samples' draws follow (:class:`SessionDraws`).  Times (and time-dependent
    effects) are log time.  During moves the orientation follows a slerp between the stations
    (rows carry no labels).  ``lead_in = (rotation, seconds)``: the session starts with a move of
    that length from that orientation (where an earlier session left the probe), so that sessions
    run one after the other make one continuous stream.

    ``n`` is the number of samples and ``t_last`` the time of the last one (s).
    """

    def __init__(self, probe: SimulatedProbe, site: Site, stations, rng: np.random.Generator,
                 rate_hz: float = 100.0, move_s: float = 1.0, t0: float = 0.0, survey: bool = False, lead_in=None):
        if rate_hz <= 0:
            raise ValueError("rate_hz must be positive")
        self.probe, self.site, self.stations, self.rng, self.survey = probe, site, list(stations), rng, survey
        stations = self.stations
        self.rate_hz = rate_hz
        self.dt = dt = 1.0 / rate_hz
        # Build a time line of key orientations: each station is held constant, moves interpolate.
        actual = []
        for st in stations:
            r = st.rotation
            if probe.stand_pose_error_deg > 0:
                from scipy.spatial.transform import Rotation   # lazily: 0.16 s of every process start

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
        self.segments = segments
        self.counts = [max(int(round((te - ts) * rate_hz)), 1) for (ts, te, _, _, _) in segments]
        self.offsets = np.concatenate([[0], np.cumsum(self.counts, dtype=np.int64)]).astype(int).tolist()
        self.n = self.offsets[-1]
        self.t_last = segments[-1][0] + dt * (self.counts[-1] - 1) if segments else t0
        self._draws = None
        if not segments:
            return
        key_t = np.array(key_t)
        # Nudge duplicate key times (zero-length moves) so the slerp stays well defined.
        self._key_t = key_t + np.arange(len(key_t)) * 1e-9
        from scipy.spatial.transform import Rotation, Slerp   # lazily: 0.16 s of every process start

        self._slerp = Slerp(self._key_t, Rotation.from_matrix(np.array(key_r)))
        self._actual = np.array(actual)
        # the measured depth: a station's own while held, between two stations running from one to the next
        md_t = np.array([x for (ts, te, k, _, _) in segments if k >= 0 for x in (ts, te)])
        md = np.array([stations[k].md_m for (_, _, k, _, _) in segments if k >= 0 for _ in (0, 1)])
        ok = np.isfinite(md)
        self._md_keys = (md_t[ok], md[ok]) if ok.any() else None

    def labels(self, a: int = 0, b: int | None = None):
        """``(t_s, station, temp_c, pose, ref)`` of samples ``a`` to ``b`` (exclusive): the time line
        and the labels, without simulating any measurement."""
        b = self.n if b is None else b
        t_all, seg_id, temp, pose, ref = [], [], [], [], []
        for j, (ts, te, k, t_a, t_b) in enumerate(self.segments):
            o, c = self.offsets[j], self.counts[j]
            lo, hi = max(a, o), min(b, o + c)
            if lo >= hi:
                continue
            n = hi - lo
            tt = ts + self.dt * np.arange(lo - o, hi - o)
            t_all.append(tt)
            seg_id.append(np.full(n, k))
            temp.append(np.interp(tt, [ts, te], [t_a, t_b]))
            if k >= 0:
                pose.append(np.full(n, self.stations[k].pose, dtype=int))
                ref.append(np.tile(np.asarray(self.stations[k].ref, float), (n, 1)))
            else:
                pose.append(np.zeros(n, dtype=int))
                ref.append(np.full((n, 3), np.nan))
        if not t_all:
            return (np.zeros(0), np.zeros(0, dtype=int), np.zeros(0), np.zeros(0, dtype=int), np.zeros((0, 3)))
        return tuple(np.concatenate(x) for x in (t_all, seg_id, temp, pose, ref))

    def _rot_at(self, times, t_all, seg_id):
        # Static rows use the station's matrix exactly (no quaternion round trip); moves slerp.
        r = self._slerp(np.clip(times, self._key_t[0], self._key_t[-1])).as_matrix()
        hold = (seg_id >= 0) & (times == t_all)
        r[hold] = self._actual[seg_id[hold]]
        return r

    def _history(self, t_all, seg_id):
        """Each sample's place in the sequence of holds (:class:`effects.History`, one entry per
        sample: its time from its hold's first sample, the previous hold's true inputs; a moving
        sample has no hold), or None when no effect of the probe needs it."""
        if "history" not in self.probe.model.needs("val" if self.survey else "cal"):
            return None
        start = {k: ts for (ts, _, k, _, _) in self.segments if k >= 0}
        held = seg_id >= 0
        since = np.full(len(t_all), np.inf)
        since[held] = t_all[held] - np.array([start[k] for k in seg_id[held]])
        prev = np.full((len(t_all), 3, 3), np.nan)
        after = held & (seg_id >= 1)
        prev[after] = self._actual[seg_id[after] - 1]
        rt = np.swapaxes(prev, -1, -2)
        return fx.History(source=np.zeros(len(t_all), dtype=int), order=np.maximum(seg_id, 0),
                          previous_g=rt @ self.site.gravity_ned(), previous_b=rt @ self.site.field_ned(),
                          settled_s=since, duration_s=np.zeros(len(t_all)), n=np.ones(len(t_all)))

    def _simulate(self, a: int, b: int, draws) -> ProbeLog:
        probe, site = self.probe, self.site
        t_all, seg_id, temp, pose, ref = self.labels(a, b)
        r_acc = self._rot_at(t_all, t_all, seg_id)
        r_mag = self._rot_at(t_all + probe.time_skew_s, t_all, seg_id) if probe.time_skew_s else r_acc
        g_tool = np.einsum("nji,j->ni", r_acc, site.gravity_ned())   # Rᵀ·g_ned
        b_tool = np.einsum("nji,j->ni", r_mag, site.field_ned())     # Rᵀ·b_ned
        f, m = probe.measure(g_tool, b_tool, temp, t_all, self.rng, self.survey, draws=draws,
                             history=self._history(t_all, seg_id))
        md = (np.interp(t_all, *self._md_keys, left=np.nan, right=np.nan) if self._md_keys is not None
              else np.full(len(t_all), np.nan))
        return ProbeLog(t_all, f, m, temp, pose, ref, station=seg_id, md_m=md)

    def log(self) -> ProbeLog:
        """All the samples at once (their draws straight from ``rng``)."""
        if not self.segments:
            return ProbeLog.empty()
        return self._simulate(0, self.n, None)

    def chunks(self, chunk_samples: int):
        """The samples as consecutive logs of at most ``chunk_samples`` rows (``station`` still counts
        the session's stations), equal to :meth:`log` cut into pieces, bit for bit.

        The random numbers are set aside when this is called (``rng`` moves past the session at
        once, so that a session planned after this one starts where a whole simulation would), and
        the pieces must be taken in order: a stochastic effect's walk runs from piece to piece,
        and on into the next session, as in one whole simulation.  Use either this or :meth:`log`
        once per plan.
        """
        if chunk_samples < 1:
            raise ValueError("chunk_samples must be at least 1")
        if not self.segments:
            return iter(())
        draws = SessionDraws(self.rng, self.n, self.probe.walk_widths("val" if self.survey else "cal"))
        return (self._simulate(a, min(a + chunk_samples, self.n), draws) for a in range(0, self.n, chunk_samples))


def run_session(probe: SimulatedProbe, site: Site, stations, rng: np.random.Generator, rate_hz: float = 100.0,
                move_s: float = 1.0, t0: float = 0.0, survey: bool = False, lead_in=None) -> ProbeLog:
    """Simulate a session, all its samples at once (:class:`SessionPlan`; in pieces of bounded
    memory: ``SessionPlan(...).chunks(n)``, the same numbers)."""
    return SessionPlan(probe, site, stations, rng, rate_hz=rate_hz, move_s=move_s, t0=t0, survey=survey,
                       lead_in=lead_in).log()


def turntable_session(steps: int = 12, duration_s: float = 3.0, tilt_deg: float = 0.0, temp_c: float = 25.0,
                      mounts=("xy", "xz", "yz"), angles_deg=None) -> list:
    """The patent's turntable procedure: per mount, the table turned through a full turn in
    ``steps`` equal steps (or at ``angles_deg``), each held ``duration_s``.  ``tilt_deg``: the table
    not level (tilted about north by that much).  Returns ``[(mount, table_deg, planned Station)]``."""
    from .turntable import table_rotation

    out = []
    for m in mounts:
        angles = (360.0 * np.arange(steps) / steps) if angles_deg is None else np.asarray(angles_deg, float)
        for a in angles:
            out.append((m, float(a), Station.planned(table_rotation(m, a, tilt_deg), duration_s, temp_c=temp_c)))
    return out


def run_turntable(probe: "SimulatedProbe", site: Site, plan, rng: np.random.Generator, rate_hz: float = 50.0,
                  move_s: float = 2.0, t0: float = 0.0) -> ProbeLog:
    """Simulate a turntable log (:func:`turntable_session`): the rows of each held step carry its
    ``mount`` and ``table_deg`` (moves between steps, and remountings, carry none)."""
    log = run_session(probe, site, [st for _, _, st in plan], rng, rate_hz=rate_hz, move_s=move_s, t0=t0)
    static = log.station >= 0
    log.mount = np.full(len(log), "", dtype=object)
    log.mount[static] = np.array([plan[k][0] for k in log.station[static]], dtype=object)
    log.table_deg = np.full(len(log), np.nan)
    log.table_deg[static] = [plan[k][1] for k in log.station[static]]
    return log


def build_probe(seed: int, effects=(), severity: float = 1.0, noise_acc: float = 0.002,
                noise_mag: float = 20.0) -> SimulatedProbe:
    """A random probe (seeded) with the named extra effects.

    ``effects``: specifications in the package's grammar (:func:`effects.parse_effects`, a
    string or a list of them, e.g. ``["axial_interference=300", "temperature_bias:mag=2"]``);
    each needs its size, the value(s) of its first parameter (one, or one per axis); without a
    sensor an effect acts on every sensor it can.  Whole-probe effects (``stand_pose_error`` deg,
    ``time_skew`` s) take one value.
    """
    rng = np.random.default_rng(seed)
    acc, mag = random_probe(rng, severity)
    model = ProbeModel.base(acc, mag)
    whole = []
    for spec in fx.parse_effects(effects):
        for eff in spec.build(need_values=True):
            if eff.stage == fx.PROBE_STAGE:
                whole.append(eff)
            else:
                model = model.with_effect(eff, spec.scope)
    return SimulatedProbe(model, noise_acc=noise_acc, noise_mag=noise_mag, whole_probe=whole)


def well_path_session(n_stations: int = 30, kickoff_deg: float = 0.0, build_deg_per_station: float = 3.0,
                      max_drift_deg: float = 85.0, azimuth_start_deg: float = 40.0,
                      turn_deg_per_station: float = 1.5, duration_s: float = 2.0,
                      temp_start_c: float = 25.0, temp_end_c: float = 60.0, seed: int = 0,
                      md_start_m: float = 500.0, md_step_m: float = 30.0):
    """Survey stations down a synthetic build-and-turn well path (reference angles known).

    Drift builds from ``kickoff_deg`` by ``build_deg_per_station`` up to ``max_drift_deg``;
    azimuth turns steadily; toolface is random per station (the tool rolls while drilling);
    temperature rises with depth.  Stations are ``md_step_m`` apart in measured depth (a stand
    of pipe) from ``md_start_m``: the log carries the depth.
    """
    rng = np.random.default_rng(seed)
    out = []
    temps = np.linspace(temp_start_c, temp_end_c, n_stations)
    for k in range(n_stations):
        i = min(kickoff_deg + build_deg_per_station * k, max_drift_deg)
        a = (azimuth_start_deg + turn_deg_per_station * k) % 360.0
        t = float(rng.uniform(0, 360))
        out.append(Station.planned(orientation_matrix(i, a, t), duration_s, ref=(float(i), float(a), t),
                                   temp_c=float(temps[k]), md_m=md_start_m + md_step_m * k))
    return out

"""A probe model in the lab: the package's :class:`model.ProbeModel` plus what a fit needs of the site.

The probe model (the paper's base model of each triad plus any effects, each with a scope ``all``,
``cal`` or ``val``) is the one the simulator measures with and a calibration record carries; the
lab adds the site: gravity and total field are fixed (they only set the overall scale of each
triad, as the paper notes for M_d); the dip is fitted by default, the stand's heading offset
(stand north vs the site's north) optionally.  :meth:`LabModel.record` turns a fitted model into
the calibration record that ``correct``, ``reprocess`` and the nodes apply.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from ..core import effects as fx
from ..core.errormodel import TriadModel
from ..core.frames import Site
from ..core.model import ProbeModel
from ..core.survey import evaluate

SENSORS = ("acc", "mag")
#: The pseudo-term of the stand's systematic pose errors (:class:`effects.StandPoseError`).
POSES_LABEL = fx.StandPoseError.name
N_POSES = 12


@dataclass
class LabModel:
    site: Site
    probe: ProbeModel = field(default_factory=ProbeModel.base)
    fit_dip: bool = True
    fit_heading: bool = False
    dip_deg: float = float("nan")
    heading_deg: float = 0.0
    #: Fit the stand's systematic pose errors: per pose of Table 1, a small rotation (rx, ry, rz,
    #: deg, tool frame) after the set attitude, applied to both triads' true vectors.
    fit_poses: bool = False
    pose_offsets_deg: np.ndarray = field(default_factory=lambda: np.zeros((N_POSES, 3)))
    #: The poses whose mean rotation is held at zero (the gauge): the poses that are right define
    #: the tool frame (:meth:`regauge`).
    gauge_poses: np.ndarray = field(default_factory=lambda: np.ones(N_POSES, bool))

    def __post_init__(self):
        if not np.isfinite(self.dip_deg):
            self.dip_deg = self.site.dip_deg
        self.pose_offsets_deg = np.asarray(self.pose_offsets_deg, dtype=float).reshape(N_POSES, 3)

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def base(cls, site: Site, acc: TriadModel | None = None, mag: TriadModel | None = None, **kw) -> "LabModel":
        return cls(site=site, probe=ProbeModel.base(acc, mag), **kw)

    @classmethod
    def from_calibration(cls, cal, **kw) -> "LabModel":
        """A record's model, with the record's site, as the start of a fit."""
        return cls(site=cal.site, probe=copy.deepcopy(cal.model), **kw)

    def with_named(self, text) -> "LabModel":
        """A copy with the effects named in the package's grammar (:func:`effects.parse_effects`)
        added, the stand's pose errors and the heading offset among them
        (:func:`effects.split_model_options`): whatever ``lab diagnose`` recommends."""
        rest, options = fx.split_model_options(text)
        new = copy.deepcopy(self)
        for key in options:
            setattr(new, key, True)
        for spec in fx.parse_effects(rest):
            for eff in spec.build():
                new = new.with_effect(eff, spec.scope)
        return new

    def with_effect(self, effect: fx.Effect, scope: str | None = None) -> "LabModel":
        """A copy with one more effect (see :meth:`model.ProbeModel.with_effect`)."""
        new = copy.deepcopy(self)
        new.probe = new.probe.with_effect(effect, scope)
        return new

    @property
    def terms(self) -> list:
        return self.probe.terms

    @property
    def extra_terms(self) -> list:
        return self.probe.extra_terms

    def labels(self) -> list:
        return self.probe.labels() + ([fx.HEADING_OFFSET] if self.fit_heading else []) + \
            ([POSES_LABEL] if self.fit_poses else [])

    def _n_site(self) -> int:
        return int(self.fit_dip) + int(self.fit_heading)

    def param_index(self, label: str) -> np.ndarray:
        """Indices in the parameter vector of one term (its :attr:`model.Term.label`), or of the
        stand's heading offset (``heading_offset``)."""
        n_probe = len(self.probe.param_names())
        if label == fx.HEADING_OFFSET:
            return np.array([n_probe + self._n_site() - 1]) if self.fit_heading else np.zeros(0, int)
        if label == POSES_LABEL:
            return np.arange(n_probe + self._n_site(), n_probe + self._n_site() + 3 * N_POSES) if self.fit_poses \
                else np.zeros(0, int)
        i = 0
        for t in self.probe.terms:
            if t.label == label:
                return np.arange(i, i + t.effect.n_params)
            i += t.effect.n_params
        raise KeyError(f"no term {label!r} in {self.describe()}")

    def without(self, label: str) -> "LabModel":
        """A copy without one extra term (or without the fitted heading offset)."""
        new = copy.deepcopy(self)
        if label == fx.HEADING_OFFSET:
            new.fit_heading, new.heading_deg = False, 0.0
            return new
        if label == POSES_LABEL:
            new.fit_poses, new.pose_offsets_deg = False, np.zeros((N_POSES, 3))
            new.gauge_poses = np.ones(N_POSES, bool)
            return new
        new.probe.terms = [t for t in new.probe.terms if t.label != label or t.effect.base]
        return new

    # ---- parameter vector --------------------------------------------------------------------
    def _pose_names(self) -> list:
        return [f"{POSES_LABEL}.r{a}_p{k}" for k in range(1, N_POSES + 1) for a in "xyz"] if self.fit_poses else []

    def param_names(self) -> list:
        return self.probe.param_names() + (["site.dip_deg"] if self.fit_dip else []) + \
            (["site.heading_deg"] if self.fit_heading else []) + self._pose_names()

    def param_units(self) -> list:
        return self.probe.param_units() + ["deg"] * (self._n_site() + len(self._pose_names()))

    def param_scale(self) -> np.ndarray:
        """Typical magnitude of each parameter (for conditioning and priors)."""
        return np.concatenate([self.probe.param_scale(), np.full(self._n_site(), 0.1),
                               np.full(len(self._pose_names()), 0.05)])

    def prior_mask(self) -> np.ndarray:
        """Parameters held by a weak prior: those of the effects beyond the base model, and the
        stand's pose errors (a pose the data do not have stays at zero)."""
        return np.concatenate([self.probe.extra_mask(), np.zeros(self._n_site(), bool),
                               np.ones(len(self._pose_names()), bool)])

    def gauge_residual(self) -> np.ndarray:
        """The mean pose rotation of the gauge poses, per axis, over 0.001°: a rotation of every pose
        alike is the base model's own rotation freedom (inside K·E of both triads), so it is held at
        zero with these stiff prior rows — over the poses that are right (:meth:`regauge`), which
        then define the tool frame."""
        if not self.fit_poses or not self.gauge_poses.any():
            return np.zeros(0)
        return self.pose_offsets_deg[self.gauge_poses].mean(axis=0) / 1e-3

    def regauge(self, data) -> bool:
        """Choose the gauge poses: those the data have whose fitted rotation lies near the median
        of all (within 3 robust σ, at least 0.01°) — the poses that are off leave the gauge.
        Returns True when the set changed (the fit is then repeated)."""
        have = np.zeros(N_POSES, bool)
        have[np.unique(data.pose[(data.kind == "pose") & (data.pose >= 1)]) - 1] = True
        if have.sum() < 3:
            new = have
        else:
            off = self.pose_offsets_deg[have]
            d = np.linalg.norm(off - np.median(off, axis=0), axis=1)
            cut = max(3.0 * 1.4826 * float(np.median(d)), 0.01)
            new = have.copy()
            new[np.flatnonzero(have)[d > cut]] = False
        changed = not np.array_equal(new, self.gauge_poses)
        self.gauge_poses = new
        return changed

    def get_vector(self) -> np.ndarray:
        v = [self.probe.get_vector()]
        if self.fit_dip:
            v.append(np.array([self.dip_deg]))
        if self.fit_heading:
            v.append(np.array([self.heading_deg]))
        if self.fit_poses:
            v.append(self.pose_offsets_deg.ravel())
        return np.concatenate(v)

    def set_vector(self, vec) -> None:
        vec = np.asarray(vec, dtype=float)
        n = sum(t.effect.n_params for t in self.probe.terms)      # len(param_names()), without the names
        self.probe.set_vector(vec[:n])
        i = n
        if self.fit_dip:
            self.dip_deg = float(vec[i])
            i += 1
        if self.fit_heading:
            self.heading_deg = float(vec[i])
            i += 1
        if self.fit_poses:
            self.pose_offsets_deg = vec[i:i + 3 * N_POSES].reshape(N_POSES, 3).copy()

    # ---- physics ------------------------------------------------------------------------------
    def field_ned(self) -> np.ndarray:
        s = Site(self.site.total_field_nt, self.dip_deg, self.site.declination_deg + self.heading_deg,
                 self.site.gravity_mps2)
        return s.field_ned()

    def true_vectors(self, data):
        """True tool-frame gravity and field of oriented stations (NaN for free ones).

        With the stand's pose errors (:attr:`fit_poses`), a pose station's real attitude is
        ``R·Q`` (``Q`` the pose's small rotation, tool frame), so its true vectors are
        ``Qᵀ·Rᵀ·v``."""
        rt = np.swapaxes(data.rotation, -1, -2)
        g, b = rt @ self.site.gravity_ned(), rt @ self.field_ned()
        if self.fit_poses:
            m = (data.kind == "pose") & (data.pose >= 1) & (data.pose <= N_POSES)
            if m.any():
                from scipy.spatial.transform import Rotation   # here: 0.16 s of every process importing the lab

                q = Rotation.from_rotvec(np.radians(self.pose_offsets_deg[data.pose[m] - 1]))
                g[m], b[m] = q.inv().apply(g[m]), q.inv().apply(b[m])
        return g, b

    def chain(self, sensor: str, role: str) -> list:
        return self.probe.chain(sensor, role)

    def base_triad(self, sensor: str) -> TriadModel:
        return self.probe.triad(sensor)

    def history(self, data, mask=None):
        """The stations' :class:`effects.History` (of those in ``mask``), or None when no effect
        of the model needs it.  The previous hold's input is its true vectors where its attitude
        is known (a pose or a reference), else its measured means."""
        # (every term acts on cal or val data: needs("cal") + needs("val") in one pass over the terms)
        if not any("history" in type(t.effect).context_needs() for t in self.probe.terms):
            return None
        m = np.ones(len(data), bool) if mask is None else mask
        rt = np.swapaxes(data.prev_rotation[m], -1, -2)
        g_prev, b_prev = rt @ self.site.gravity_ned(), rt @ self.field_ned()
        known = np.all(np.isfinite(g_prev), axis=1)
        g_prev = np.where(known[:, None], g_prev, data.prev_g[m])
        b_prev = np.where(known[:, None], b_prev, data.prev_b[m])
        return fx.History(source=data.source[m], order=data.order[m], previous_g=g_prev, previous_b=b_prev,
                          samples=data.samples[m], settled_s=data.settled_s[m], duration_s=data.duration_s[m],
                          n=data.n[m])

    def forward(self, data, g_true, b_true):
        """Predicted outputs (gravity-vector m/s², nT) for true vectors, station by station."""
        return self.forward_triad("acc", data, g_true), self.forward_triad("mag", data, b_true)

    def forward_triad(self, sensor: str, data, v_true):
        """One triad's predicted outputs (:meth:`forward`'s, the same bits)."""
        out = np.empty_like(v_true)
        for role in ("cal", "val"):
            m = data.role == role
            if m.any():
                out[m] = self.probe.forward_triad(sensor, v_true[m], data.temp_c[m], data.time_s[m], role,
                                                  history=self.history(data, m))
        return out

    def correct(self, data):
        """Corrected (true) vectors of the stations: :meth:`model.ProbeModel.correct`, role by role."""
        return self.correct_triad("acc", data), self.correct_triad("mag", data)

    def correct_triad(self, sensor: str, data):
        """One triad's corrected vectors (:meth:`correct`'s, the same bits)."""
        h = data.g if sensor == "acc" else data.b
        out = np.empty_like(h)
        for role in ("cal", "val"):
            m = data.role == role
            if m.any():
                out[m] = self.probe.correct_triad(sensor, h[m], data.temp_c[m], data.time_s[m], role,
                                                  history=self.history(data, m))
        return out

    def angle_errors(self, data, tol=None):
        """Corrected angles of the stations and, for those with a reference, their errors."""
        g, b = self.correct(data)
        kw = {} if tol is None else {"tol": tol}
        # azimuths from the stand's north: the site declination plus any fitted heading offset
        site = Site(self.site.total_field_nt, self.site.dip_deg, self.site.declination_deg + self.heading_deg,
                    self.site.gravity_mps2)
        return evaluate(g, b, site, ref=data.ref, **kw)

    def describe(self) -> str:
        extra = ", ".join(self.labels()) or "none"
        return f"base (bias, scale, nonorthogonality) + [{extra}]"

    # ---- the record ---------------------------------------------------------------------------
    def record(self, probe_id: str = "probe", method: str = "lab fit", site_source: str = "given",
               not_identifiable=(), fit_stats: dict | None = None):
        """The fitted model as a calibration record (:class:`coeffs.Calibration`) for ``correct``,
        ``reprocess`` and the nodes.  The site is the lab's (its total field and gravity set the
        triads' scale); a fitted dip and heading offset are kept as diagnostics, not applied: the
        dip of the site reference stays the one given, the heading belongs to the stand.  A wandering
        bias (:class:`effects.BiasWander`) keeps its density; its path, which belongs to these data,
        is left behind (its RMS kept as a diagnostic)."""
        from ..core.coeffs import Calibration

        diags = {"fit": dict(fit_stats or {})}
        diags["fit"].update({"fitted_dip_deg": float(self.dip_deg)})
        if self.fit_poses:     # the stand's, not the probe's: kept as a finding, never applied
            diags["fit"]["stand_pose_errors_deg"] = {int(k + 1): [float(x) for x in self.pose_offsets_deg[k]]
                                                     for k in range(N_POSES) if np.any(self.pose_offsets_deg[k])}
        if self.fit_heading:
            diags["fit"]["stand_heading_offset_deg"] = float(self.heading_deg)
        probe = copy.deepcopy(self.probe)
        wander = [t for t in probe.terms if t.effect.stochastic]
        for t in wander:       # the path belongs to these data; a record carries the density only
            diags["fit"].setdefault("wander_path_rms", {})[t.label] = [
                float(x) for x in np.sqrt(np.mean(t.effect.path ** 2, axis=0))] if len(t.effect.knots_s) else []
            t.effect.clear_path()
        return Calibration(probe, probe_id=probe_id, method=method, site=self.site,
                           site_source=site_source, diagnostics=diags,
                           not_identifiable=[{"parameter": n.parameter, "reason": n.reason} for n in not_identifiable])

"""A probe model for the lab: the paper's base model plus any effects, as one parameter vector.

The base model of each triad is the seed paper's: ``nonorthogonality`` (six e-terms), ``scale``
and ``bias`` (eqs. 3–4).  Extra effects from :mod:`inclinometer_calib.effects` (or plug-ins) are
added to a triad's signal chain; each has a *scope*: ``"all"`` logs, or only ``"cal"`` / ``"val"``
(e.g. axial drill-string interference acts on survey data, not on the non-magnetic stand).

Besides the effects the model holds the site: gravity and total field are fixed (they only set the
overall scale of each triad, as the paper notes for M_d); the dip is fitted by default, the stand's
heading offset (stand north vs the site's north) optionally.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from .. import effects as fx
from ..errormodel import TriadModel
from ..frames import Site
from ..survey import evaluate

SENSORS = ("acc", "mag")
BASE_NAMES = ("nonorthogonality", "scale", "bias")


def base_effects(sensor: str, triad: TriadModel | None = None) -> list:
    """The paper's base model as effects, optionally initialised from a TriadModel."""
    e1 = e2 = np.zeros(3)
    k = b = np.zeros(3)
    if triad is not None:
        e1 = np.array([triad.e[fx.NonOrthogonality.term_names(a)[0]] for a in "xyz"])
        e2 = np.array([triad.e[fx.NonOrthogonality.term_names(a)[1]] for a in "xyz"])
        k, b = triad.scale - 1.0, triad.bias
    return [fx.NonOrthogonality(sensor=sensor, values={"e1": e1, "e2": e2}),
            fx.Scale(sensor=sensor, values={"k": k}),
            fx.Bias(sensor=sensor, values={"b": b})]


@dataclass
class Term:
    """An effect in the model with the logs it acts on."""

    effect: fx.Effect
    scope: str = "all"

    @property
    def label(self) -> str:
        return self.effect.key + ("" if self.scope == "all" else f"@{self.scope}")


@dataclass
class LabModel:
    site: Site
    terms: list = field(default_factory=list)
    fit_dip: bool = True
    fit_heading: bool = False
    dip_deg: float = float("nan")
    heading_deg: float = 0.0

    def __post_init__(self):
        if not np.isfinite(self.dip_deg):
            self.dip_deg = self.site.dip_deg

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def base(cls, site: Site, acc: TriadModel | None = None, mag: TriadModel | None = None, **kw) -> "LabModel":
        terms = [Term(e) for e in base_effects("acc", acc)] + [Term(e) for e in base_effects("mag", mag)]
        return cls(site=site, terms=terms, **kw)

    def with_effect(self, effect: fx.Effect, scope: str = "all") -> "LabModel":
        """A copy with one more effect; adding an effect twice raises."""
        new = copy.deepcopy(self)
        if any(t.effect.key == effect.key for t in new.terms):
            raise ValueError(f"effect {effect.key} is already in the model")
        if scope not in ("all", "cal", "val"):
            raise ValueError(f"scope must be all, cal or val, got {scope!r}")
        new.terms.append(Term(copy.deepcopy(effect), scope))
        return new

    @property
    def extra_terms(self) -> list:
        return [t for t in self.terms if t.effect.name not in BASE_NAMES]

    def labels(self) -> list:
        return [t.label for t in self.extra_terms] + (["heading_offset"] if self.fit_heading else [])

    # ---- parameter vector --------------------------------------------------------------------
    def param_names(self) -> list:
        names = [n for t in self.terms for n in t.effect.param_names()]
        if self.fit_dip:
            names.append("site.dip_deg")
        if self.fit_heading:
            names.append("site.heading_deg")
        return names

    def param_units(self) -> list:
        units = [u for t in self.terms for u in t.effect.param_units()]
        return units + ["deg"] * (int(self.fit_dip) + int(self.fit_heading))

    def param_scale(self) -> np.ndarray:
        """Typical magnitude of each parameter (for conditioning and priors)."""
        s = []
        for t in self.terms:
            typ = t.effect.param_typical()
            s.append(np.where(typ > 0, typ, 1.0))
        return np.concatenate(s + [np.array([0.1] * (int(self.fit_dip) + int(self.fit_heading)))])

    def get_vector(self) -> np.ndarray:
        v = [t.effect.get_vector() for t in self.terms]
        if self.fit_dip:
            v.append(np.array([self.dip_deg]))
        if self.fit_heading:
            v.append(np.array([self.heading_deg]))
        return np.concatenate(v)

    def set_vector(self, vec) -> None:
        vec = np.asarray(vec, dtype=float)
        i = 0
        for t in self.terms:
            n = t.effect.n_params
            t.effect.set_vector(vec[i:i + n])
            i += n
        if self.fit_dip:
            self.dip_deg = float(vec[i])
            i += 1
        if self.fit_heading:
            self.heading_deg = float(vec[i])

    # ---- physics ------------------------------------------------------------------------------
    def field_ned(self) -> np.ndarray:
        s = Site(self.site.total_field_nt, self.dip_deg, self.site.declination_deg + self.heading_deg,
                 self.site.gravity_mps2)
        return s.field_ned()

    def true_vectors(self, data):
        """True tool-frame gravity and field of oriented stations (NaN for free ones)."""
        rt = np.swapaxes(data.rotation, -1, -2)
        return rt @ self.site.gravity_ned(), rt @ self.field_ned()

    def chain(self, sensor: str, role: str) -> list:
        return [t.effect for t in self.terms if t.effect.sensor == sensor and t.scope in ("all", role)]

    def base_triad(self, sensor: str) -> TriadModel:
        ch = {t.effect.name: t.effect for t in self.terms if t.effect.sensor == sensor and t.effect.name in BASE_NAMES}
        e = {}
        for j, a in enumerate("xyz"):
            n1, n2 = fx.NonOrthogonality.term_names(a)
            e[n1] = ch["nonorthogonality"].values["e1"][j]
            e[n2] = ch["nonorthogonality"].values["e2"][j]
        return TriadModel(scale=1.0 + ch["scale"].values["k"], bias=ch["bias"].values["b"], e=e)

    def _ctx(self, data, mask):
        return fx.Context(temperature_c=data.temp_c[mask], time_s=data.time_s[mask])

    def forward(self, data, g_true, b_true):
        """Predicted outputs (gravity-vector m/s², nT) for true vectors, station by station."""
        h_g = np.empty_like(g_true)
        h_b = np.empty_like(b_true)
        for role in ("cal", "val"):
            m = data.role == role
            if not m.any():
                continue
            ctx = self._ctx(data, m)
            h_g[m] = fx.apply_chain(g_true[m], self.chain("acc", role), ctx)
            h_b[m] = fx.apply_chain(b_true[m], self.chain("mag", role), ctx)
        return h_g, h_b

    def correct(self, data, iterations: int = 6):
        """Corrected (true) vectors from the measured ones by Newton iteration on the forward model.

        Starts from the base model's linear inverse; each step solves with the base sensitivity
        ``K·E`` (the extra effects are small), so it converges in a few steps.
        """
        out = []
        for sensor, meas in (("acc", data.g), ("mag", data.b)):
            tri = self.base_triad(sensor)
            a_inv = tri.correction_matrix
            v = np.empty_like(meas)
            for role in ("cal", "val"):
                m = data.role == role
                if not m.any():
                    continue
                ctx = self._ctx(data, m)
                chain = self.chain(sensor, role)
                h = meas[m]
                x = tri.inverse(h)
                if len(chain) > 3:
                    for _ in range(iterations):
                        x = x + (h - fx.apply_chain(x, chain, ctx)) @ a_inv.T
                v[m] = x
            out.append(v)
        return out[0], out[1]

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

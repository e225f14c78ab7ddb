"""The probe model: the seed paper's base model of each triad plus any effects — forward, and the
one correction path of the package.

A :class:`ProbeModel` is a composition of effects (:mod:`effects`): per triad the paper's base
model (``nonorthogonality`` E, ``scale`` K, ``bias`` B: ``h = K·E·v + B``, eqs. 3–4) and any
catalogue or plug-in effect, each with a *scope*: ``all`` data, or only the calibration stand
(``cal``) or the survey (``val``; e.g. axial drill-string interference is absent from the
non-magnetic stand).  The simulator measures with it (:meth:`ProbeModel.forward`), the lab fits
it, a calibration record carries it, and every path that corrects data — the correction node,
``correct``, ``reprocess``, the batch path, the lab — calls :meth:`ProbeModel.correct`:

* the base model alone: ``v = C·(h − B)`` with ``C = (K·E)⁻¹`` (paper eqs. 17–19), exactly;
* with effects beyond it: Newton steps on the forward chain starting from that,
  ``v ← v + C·(h − forward(v))``, a fixed number of them (:data:`CORRECTION_ITERATIONS`), so
  that every path takes the same steps; the effects are small next to ``K·E``, so each step gains
  several digits.

Effects that depend on temperature (°C) or time (s since the data's first sample) get those of
each sample (or station).  Conventions: accelerometer in the seed paper's **gravity-vector**
convention (down positive, m/s²; REP-145 specific force is converted before the core), field in
nT.  All arithmetic is element by element (no BLAS), so one sample corrected alone and the same
sample in a block of a million give the same bits.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from . import effects as fx
from .errormodel import TriadModel
from .formulas import corrected, mat_vec

SENSORS = ("acc", "mag")
#: The data an effect's scope selects: the calibration stand (cal) or the survey (val).
ROLES = ("cal", "val")
#: Newton steps of the correction when the model has effects beyond the paper's.
CORRECTION_ITERATIONS = 6


class ModelContextError(ValueError):
    """The model needs a temperature or time that the data do not give."""


@dataclass
class Term:
    """An effect in the model with the data it acts on (``all``, ``cal`` or ``val``)."""

    effect: fx.Effect
    scope: str = "all"

    def __post_init__(self):
        if self.scope not in fx.SCOPES:
            raise ValueError(f"scope must be one of {', '.join(fx.SCOPES)}, got {self.scope!r}")

    @property
    def label(self) -> str:
        return self.effect.key + ("" if self.scope == "all" else f"@{self.scope}")

    def acts_on(self, role: str) -> bool:
        return self.scope in ("all", role)


def base_effects(sensor: str, triad: TriadModel | None = None) -> list:
    """The paper's base model of one triad as effects (E, K, B), optionally from a TriadModel."""
    e1 = e2 = np.zeros(3)
    k = b = np.zeros(3)
    if triad is not None:
        e1 = np.array([triad.e[fx.NonOrthogonality.term_names(a)[0]] for a in "xyz"])
        e2 = np.array([triad.e[fx.NonOrthogonality.term_names(a)[1]] for a in "xyz"])
        k, b = triad.scale - 1.0, triad.bias
    return [fx.NonOrthogonality(sensor=sensor, values={"e1": e1, "e2": e2}),
            fx.Scale(sensor=sensor, values={"k": k}),
            fx.Bias(sensor=sensor, values={"b": b})]


class ProbeModel:
    """Base model of both triads plus effects, as one list of :class:`Term`.

    Build with :meth:`base` (or :meth:`from_triads`) and :meth:`with_effect`; the parameter vector
    (:meth:`get_vector` / :meth:`set_vector`) is what the lab fits."""

    def __init__(self, terms=()):
        self.terms = list(terms)
        for sensor in SENSORS:
            have = [t.effect.name for t in self.terms if t.effect.sensor == sensor and t.effect.base]
            if sorted(have) != sorted(fx.BASE):
                raise ValueError(f"a probe model needs the base model {', '.join(fx.BASE)} of the {sensor} triad "
                                 f"once each, got {have}")
        keys = [t.effect.key for t in self.terms]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ValueError(f"effect(s) {', '.join(dup)} twice in the model")

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def base(cls, acc: TriadModel | None = None, mag: TriadModel | None = None) -> "ProbeModel":
        """The paper's model of both triads (identity when a triad is not given)."""
        return cls([Term(e) for e in base_effects("acc", acc)] + [Term(e) for e in base_effects("mag", mag)])

    from_triads = base

    def with_effect(self, effect: fx.Effect, scope: str | None = None) -> "ProbeModel":
        """A copy with one more effect (default scope: ``val`` for a survey-only effect, else
        ``all``); adding an effect twice raises."""
        if effect.stage == fx.PROBE_STAGE:
            raise ValueError(f"{effect.name} is a whole-probe effect of the simulator, not part of a triad's model")
        new = copy.deepcopy(self)
        if any(t.effect.key == effect.key for t in new.terms):
            raise ValueError(f"effect {effect.key} is already in the model")
        new.terms.append(Term(copy.deepcopy(effect), scope or ("val" if effect.survey_only else "all")))
        return new

    @property
    def extra_terms(self) -> list:
        """The terms beyond the paper's base model."""
        return [t for t in self.terms if not t.effect.base]

    def labels(self) -> list:
        return [t.label for t in self.extra_terms]

    def describe(self) -> str:
        return f"base (bias, scale, nonorthogonality) + [{', '.join(self.labels()) or 'none'}]"

    def triad(self, sensor: str) -> TriadModel:
        """The base model of one triad as a :class:`TriadModel` (K, B, the six e-terms)."""
        ch = {type(t.effect): t.effect for t in self.terms if t.effect.sensor == sensor and t.effect.base}
        no = ch[fx.NonOrthogonality]
        e = {}
        for j, a in enumerate("xyz"):
            n1, n2 = fx.NonOrthogonality.term_names(a)
            e[n1] = no.values["e1"][j]
            e[n2] = no.values["e2"][j]
        return TriadModel(scale=1.0 + ch[fx.Scale].values["k"], bias=ch[fx.Bias].values["b"], e=e)

    @property
    def acc(self) -> TriadModel:
        return self.triad("acc")

    @property
    def mag(self) -> TriadModel:
        return self.triad("mag")

    def chain(self, sensor: str, role: str = "val") -> list:
        """The effects acting on one triad's data of ``role`` (base model included)."""
        return [t.effect for t in self.terms if t.effect.sensor == sensor and t.acts_on(role)]

    def needs(self, role: str = "val") -> tuple:
        """What the model's effects on data of ``role`` depend on: ``temperature``, ``time``."""
        out = []
        for t in self.terms:
            if t.acts_on(role):
                out += [n for n in type(t.effect).context_needs() if n not in out]
        return tuple(out)

    # ---- parameter vector --------------------------------------------------------------------
    def param_names(self) -> list:
        return [n for t in self.terms for n in t.effect.param_names()]

    def param_units(self) -> list:
        return [u for t in self.terms for u in t.effect.param_units()]

    def param_scale(self) -> np.ndarray:
        """Typical magnitude of each parameter (1 where none is stated): conditioning, priors."""
        if not self.terms:
            return np.zeros(0)
        return np.concatenate([np.where(t.effect.param_typical() > 0, t.effect.param_typical(), 1.0)
                               for t in self.terms])

    def extra_mask(self) -> np.ndarray:
        """True for the parameters of effects beyond the base model."""
        return np.array([not t.effect.base for t in self.terms for _ in range(t.effect.n_params)], dtype=bool)

    def get_vector(self) -> np.ndarray:
        return np.concatenate([t.effect.get_vector() for t in self.terms]) if self.terms else np.zeros(0)

    def set_vector(self, vec) -> None:
        vec = np.asarray(vec, dtype=float)
        i = 0
        for t in self.terms:
            n = t.effect.n_params
            t.effect.set_vector(vec[i:i + n])
            i += n

    # ---- physics ------------------------------------------------------------------------------
    def context(self, n: int, temperature_c=None, time_s=None, role: str = "val", where: str = "",
                history=None, needs=None) -> fx.Context:
        """The per-sample context of ``n`` samples; a temperature, time or history
        (:class:`effects.History`) the model's effects need and that is not given raises
        :class:`ModelContextError` (never a silent default).  NaN entries stay NaN: those samples
        come out NaN (the caller says why).  ``needs``: :meth:`needs` of ``role`` when the caller
        has it (a :class:`CorrectionPlan`)."""
        needs = self.needs(role) if needs is None else needs
        temp = _per_sample(temperature_c, n, fx.T_REF_C)
        tim = _per_sample(time_s, n, 0.0)
        for what, given in (("temperature", temperature_c), ("time", time_s), ("history", history)):
            if what in needs and given is None:
                eff = [t.label for t in self.terms if t.acts_on(role) and what in type(t.effect).context_needs()]
                raise ModelContextError(f"{where}the model's effect(s) {', '.join(eff)} depend on {what} and the data "
                                        f"give no {what}")
        return fx.Context(temperature_c=temp, time_s=tim, history=history)

    def forward(self, g_true, b_true, temperature_c=None, time_s=None, role: str = "val", history=None):
        """Sensor outputs (gravity-vector m/s², nT) for true tool-frame vectors (N, 3) each."""
        return (self.forward_triad("acc", g_true, temperature_c, time_s, role, history),
                self.forward_triad("mag", b_true, temperature_c, time_s, role, history))

    def forward_triad(self, sensor: str, v_true, temperature_c=None, time_s=None, role: str = "val",
                      history=None):
        """One triad's outputs of :meth:`forward` (``sensor`` ``acc``: gravity vector, m/s²;
        ``mag``: nT), the same bits: the lab's finite differences over one triad's parameters
        recompute that triad only."""
        v_true = np.atleast_2d(np.asarray(v_true, dtype=float))
        ctx = self.context(len(v_true), temperature_c, time_s, role, history=history)
        return fx.apply_chain(v_true, self.chain(sensor, role), ctx)

    def correct(self, g, b, temperature_c=None, time_s=None, role: str = "val", history=None):
        """Corrected gravity vector (m/s², down positive) and field (nT) from raw outputs in the
        same conventions — the one correction path (see the module docstring).

        ``g``, ``b``: (N, 3) or (3,); ``temperature_c``, ``time_s``: scalars or (N,) (needed when
        the model has effects that depend on them); ``history`` for effects that depend on the
        sequence of holds.  Returns arrays of the input shapes."""
        return CorrectionPlan(self, role).correct(g, b, temperature_c, time_s, history=history)

    def correct_triad(self, sensor: str, h, temperature_c=None, time_s=None, role: str = "val", history=None):
        """One triad of :meth:`correct` (:meth:`CorrectionPlan.correct_triad`), the same bits."""
        return CorrectionPlan(self, role, (sensor,)).correct_triad(sensor, h, temperature_c, time_s, history)

    # ---- record ---------------------------------------------------------------------------------
    def terms_record(self) -> list:
        """The effects beyond the base model as plain data (a calibration record's ``model.effects``)."""
        from .plugins import reference

        out = []
        for t in self.extra_terms:
            e = t.effect
            cls = type(e)
            item = {"name": e.name, "sensor": e.sensor, "axes": e.axes, "scope": t.scope,
                    "parameters": {s.name: [float(x) for x in e.values[s.name]] for s in cls.specs},
                    "units": {s.name: s.unit[e.sensor] for s in cls.specs}}
            if cls.iscwsa.get(e.sensor):
                item["iscwsa"] = cls.iscwsa[e.sensor]
            ref = reference(cls)
            if ref:
                item["plugin"] = ref
            out.append(item)
        return out

    @classmethod
    def from_record(cls, acc: TriadModel, mag: TriadModel, items, base_dir: str = ".",
                    source: str = "<record>") -> "ProbeModel":
        """The model of a record: base triads plus ``model.effects`` items (:meth:`terms_record`);
        a plug-in effect must come from a source the user named with the record's SHA-256
        (:func:`plugins.require_plugin`: the record itself never makes anything execute)."""
        from .plugins import require_plugin

        model = cls.base(acc, mag)
        for k, item in enumerate(items or ()):
            where = f"{source}: model.effects[{k}]"
            if not isinstance(item, dict) or "name" not in item:
                raise ValueError(f"{where}: expected a mapping with name, sensor, axes, scope, parameters")
            if item.get("plugin"):
                require_plugin(item["name"], item["plugin"], base_dir, source)
            try:
                ecls = fx.effect_class(item["name"])
                params = item.get("parameters") or {}
                unknown = set(params) - {s.name for s in ecls.specs}
                if unknown:
                    raise ValueError(f"unknown parameter(s) {sorted(unknown)}")
                units = item.get("units") or {}
                for s in ecls.specs:
                    if s.name in units and units[s.name] != s.unit[item.get("sensor", "")]:
                        raise ValueError(f"{s.name} is in {units[s.name]!r}, the effect's unit is "
                                         f"{s.unit.get(item.get('sensor', ''))!r} (convert the values, do not just "
                                         "relabel them)")
                vals = {name: np.asarray(v, dtype=float) for name, v in params.items()}
                if any(not np.all(np.isfinite(v)) for v in vals.values()):
                    raise ValueError("parameters contain NaN/inf")
                eff = ecls(sensor=item.get("sensor", ""), axes=item.get("axes", ecls.default_axes), values=vals)
                model = model.with_effect(eff, item.get("scope", "all"))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where} ({item.get('name')}): {exc}") from None
        return model


def _per_sample(x, n, default):
    if x is None:
        return np.full(n, default)
    a = np.asarray(x, dtype=float)
    return np.broadcast_to(a.reshape(-1) if a.ndim else a, (n,)).copy() if a.size in (1, n) else a


class CorrectionPlan:
    """:meth:`ProbeModel.correct` with everything that does not depend on the data worked out once
    (the base triads' correction matrices, the chains): what a node keeps for per-sample use."""

    def __init__(self, model: ProbeModel, role: str = "val", sensors=SENSORS):
        """``sensors``: the triads to prepare (both by default; the lab's fits correct one at a time)."""
        self.model = model
        self.role = role
        self.triads = {s: model.triad(s) for s in sensors}
        c = {s: self.triads[s].correction_matrix for s in sensors}
        self.matrix_t = {s: c[s].T.copy() for s in sensors}
        #: each triad's base model as floats, ``(C's nine entries row by row, B)``: what
        #: :func:`formulas.corrected` takes (here, in :meth:`correct_sample`, and in the batch kernel)
        self.coefficients = {s: (tuple(c[s].ravel().tolist()), tuple(self.triads[s].bias.tolist()))
                             for s in sensors}
        self.chains = {s: model.chain(s, role) for s in sensors}
        self.extra = {s: len(self.chains[s]) > len(fx.BASE) for s in sensors}
        self.needs = model.needs(role)
        # what each triad's own chain needs (a magnetometer-only effect never stops the accelerometer)
        self.triad_needs = {sn: tuple(dict.fromkeys(n for e in self.chains[sn] for n in type(e).context_needs()))
                            for sn in sensors}

    def correct(self, g, b, temperature_c=None, time_s=None, history=None):
        """Both triads (see :meth:`ProbeModel.correct`)."""
        return (self.correct_triad("acc", g, temperature_c, time_s, history),
                self.correct_triad("mag", b, temperature_c, time_s, history))

    def correct_triad(self, sensor: str, h, temperature_c=None, time_s=None, history=None):
        """One triad's corrected vectors (a node corrects each stream as its samples come)."""
        h = np.asarray(h, dtype=float)
        c, b = self.coefficients[sensor]
        return self.correct_triad_rows(sensor, h.reshape(-1, 3), c, b, temperature_c, time_s, history).reshape(h.shape)

    def correct_triad_rows(self, sensor: str, h, c, b, temperature_c=None, time_s=None, history=None):
        """:meth:`correct_triad` of ``h`` (N, 3) with the base model ``c`` (C's nine entries row by
        row) and ``b`` (the bias's three) — numbers, or arrays of one value per row with the chain's
        effects holding one row of values per row too (:attr:`effects.Effect.row_parameters`, set
        by the caller: many parameter vectors corrected in one call, the lab's Jacobians,
        :func:`calibrate.fit.residual_rows`).  ``v = C·(h − B)``, then the Newton steps
        ``v ← v + C·(h − forward(v))``, element by element: each row the bits it gets alone."""
        h2 = np.asarray(h, dtype=float)
        x = self.triads[sensor].inverse(h2, c, b)
        if self.extra[sensor]:
            ctx = self.model.context(len(h2), temperature_c, time_s, self.role, history=history,
                                     needs=self.triad_needs[sensor])
            chain = self.chains[sensor]
            ctx = fx.chain_context(chain, ctx)          # once, not at every Newton step
            for _ in range(CORRECTION_ITERATIONS):
                d = h2 - fx.apply_chain(x, chain, ctx, prepared=True)
                x = x + np.stack(mat_vec(c, d[:, 0], d[:, 1], d[:, 2]), axis=1)
        return x

    def correct_sample(self, sensor: str, h, temperature_c=None, time_s=None) -> tuple:
        """One sample of one triad, ``h`` three floats (m/s² gravity vector or nT, tool frame), as a
        tuple of three floats: :meth:`correct_triad` of that sample, bit for bit.

        A node corrects its streams sample by sample; numpy on one 3-vector costs ≈ 30 µs a call.
        For a triad with nothing beyond the base model this is :func:`formulas.corrected`,
        ``v = C·(h − B)``, in plain floats (≈ 1 µs); a triad with effects goes through
        :meth:`correct_triad` (which raises ValueError as it does)."""
        if self.extra[sensor]:
            v = self.correct_triad(sensor, (h[0], h[1], h[2]), temperature_c, time_s)
            return (float(v[0]), float(v[1]), float(v[2]))
        c, b = self.coefficients[sensor]
        return corrected(c, b, h[0], h[1], h[2])

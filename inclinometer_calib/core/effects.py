"""Catalogue of physical error effects of a sensor triad, composable into a probe model.

Each effect is a small class with its own metadata: a stable ``name``, the ``sensors`` it can act
on (``"acc"``, ``"mag"``, or ``"probe"`` for whole-probe effects), the ``axes`` it acts on (a
subset of ``"xyz"``), its parameters (:class:`ParamSpec`: one value per axis, with unit and
typical 1σ size per sensor), the nearest ISCWSA MWD error-model term (``iscwsa``), whether it acts
on survey data only (``survey_only``), what it depends on (``needs``: temperature, time), when
the data can identify it (:meth:`Effect.identifiability`), the residual signature that betrays it
(``signature``, ``field_regressors``), and one forward function :meth:`Effect.apply`.  Code
elsewhere asks the class; no list of effect names lives anywhere else.

Signal chain of one triad (stages applied in this order)::

    tool     v  = true tool-frame vector (+ tool-fixed disturbances: axial_interference)
    axes     s  = E·v  (non-orthogonality; misalignment; triad_misalignment)
    gain     y  = K(T)·s·(1 + asymmetry·sign s) + nonlinearity(s) + cross_coupling(s)
    output   h  = y + bias(T, t)

Whole-probe effects (stage ``probe``: ``stand_pose_error``, ``time_skew``) act on the probe's
orientation and sampling rather than on one triad's signal; the simulator applies them.

Units: accelerometer in m/s² of the seed paper's gravity vector (down positive, ``g = -f`` of
REP-145); magnetometer in nT.  Temperature in °C relative to ``T_REF_C``; time in s since the
data's first sample (the probe's power-on: the first sample of a log, a stream or the first of
several logs read together).

Effects are named on the command line, in node parameters and in records with one grammar
(:func:`parse_effects`)::

    NAME[:sensor[:axes]][@scope][=V[,V...]]   items separated by commas

e.g. ``temperature_bias:mag``, ``axial_interference@val=300``, ``bias:mag:xy=10,20,nonlinearity``
(a bare number continues the previous item's values).

Adding an effect means adding one class here and registering it in :data:`CATALOGUE`.
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .errormodel import E_TERMS
from .frames import rotate

T_REF_C = 25.0
#: Reference input magnitude per sensor (used to express nonlinearity in dimensionless form).
FULL_SCALE = {"acc": 9.80665, "mag": 50000.0}
AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
#: the two other axes of each axis, in index order (the paper's e-terms: e1 the first, e2 the second)
OTHER_AXES = tuple(tuple(i for i in range(3) if i != b) for b in range(3))
STAGES = ("tool", "axes", "gain", "output")
#: Stage of whole-probe effects (not in a triad's signal chain).
PROBE_STAGE = "probe"
SCOPES = ("all", "cal", "val")
#: Spans of the data an effect that depends on temperature or time needs before it is identifiable,
#: with what to do about it.
MIN_SPAN = {
    "temperature": (3.0, "°C", "calibrate at two or more temperatures at least 10 °C apart"),
    "time": (300.0, "s", "a drift needs stations spread over at least several minutes (repeat poses at the end)"),
}
#: The experiments that tell a temperature effect from a drift in time (they fit a steady warm-up alike).
SEPARATE_TEMPERATURE = ("a temperature cycle that goes up and down, or two runs heated at different rates (a "
                        "temperature effect follows the temperature back down and is the same per degree in both "
                        "runs; a drift in time does neither)")
SEPARATE_TIME = ("a hold at constant temperature (a drift in time goes on, a temperature effect stops), or a "
                 "temperature cycle that goes up and down")


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of an effect: name, unit per sensor and typical 1σ magnitude per sensor."""

    name: str
    unit: dict
    typical: dict
    doc: str = ""


@dataclass
class History:
    """Where each station stands in its sequence, for effects that depend on it (a magnetometer
    that keeps a little of the previous hold's field, a stand that settles): per station (N,)
    ``source`` (its log), ``order`` (its place in the log, time order, from 0), ``previous_g`` and
    ``previous_b`` (N, 3) the true tool-frame input of the previous hold in the same log (gravity
    vector m/s², field nT; the measured means where that hold's attitude is unknown; NaN for a
    log's first hold), where in its hold each station lies, the stations before these (a stream's),
    and ``samples`` (N,) each station's samples as an (n, 7) array of time (s), gravity vector
    (3, m/s²) and field (3, nT), or None where the data keep none (a bag)."""

    source: np.ndarray
    order: np.ndarray
    previous_g: np.ndarray
    previous_b: np.ndarray
    samples: np.ndarray | None = None
    #: The part of its hold each station keeps: seconds left out at the hold's start (a sensor
    #: settling after the move, :mod:`gates`), seconds kept and samples kept, (N,); None: unknown
    #: (taken as a whole hold of unknown length: no settling is modelled).
    settled_s: np.ndarray | None = None
    duration_s: np.ndarray | None = None
    n: np.ndarray | None = None
    #: Stations corrected one at a time (a stream): the times (s) and temperatures (°C) of the
    #: stations before these, in order — the temperature a sensor feels late depends on them
    #: (:class:`ThermalLag`); None: the rows given are the whole sequence.
    earlier_time_s: np.ndarray | None = None
    earlier_temp_c: np.ndarray | None = None


@dataclass
class Context:
    """Per-sample conditions an effect may depend on: temperature (°C) and time (s since the
    data's first sample), each (N,); and ``history`` (:class:`History`) where the data give it
    (the lab's stations) — an effect that needs it declares ``needs = ("history",)``."""

    temperature_c: np.ndarray
    time_s: np.ndarray
    history: History | None = None


@dataclass
class Effect(abc.ABC):
    """Base class.  Subclasses set ``name``, ``stage``, ``sensors``, ``specs`` and ``_apply``.

    ``values`` maps each parameter name to an array with one entry per acted-on axis.
    """

    sensor: str = "mag"
    axes: str = "xyz"
    values: dict = field(default_factory=dict)

    name: ClassVar[str] = ""
    stage: ClassVar[str] = "gain"
    sensors: ClassVar[tuple] = ("acc", "mag")
    specs: ClassVar[tuple] = ()
    default_axes: ClassVar[str] = "xyz"
    #: The nearest ISCWSA MWD error-model terms, per sensor (for users who think in those codes).
    iscwsa: ClassVar[dict] = {}
    #: Part of the seed paper's base model (bias, scale, non-orthogonality).
    base: ClassVar[bool] = False
    #: Acts on survey data only (not on the non-magnetic lab stand): default scope ``val``.
    survey_only: ClassVar[bool] = False
    #: What the effect depends on besides the signal: ``"temperature"``, ``"time"``.  None: found
    #: out by evaluating the effect (:meth:`context_needs`; for plug-ins that do not say).
    needs: ClassVar[tuple | None] = None
    #: Why static stand data can never reveal the effect (empty: they can).
    not_from_static: ClassVar[str] = ""
    #: The residual signature that betrays the effect when it is missing from a model.
    signature: ClassVar[str] = ""
    #: What a survey's residuals against the site (|G|, |B|, dip) follow when the effect is missing
    #: from the model applied in the field: ``"temperature"``, ``"time"``, ``"orientation"``.
    field_regressors: ClassVar[tuple] = ()
    #: The experiment that tells this effect apart from one that fits the same data alike (the lab
    #: says it when two effects are confounded).
    separated_by: ClassVar[str] = ""
    #: Set on plug-in classes by :func:`plugins.load_plugin`: ``{"file" or "module": ..., "sha256": ...}``.
    plugin: ClassVar[dict | None] = None
    #: What the effect stands in for when it is not itself a physical cause (empty: it is one): a
    #: bias drifting with time fits whatever follows time — a temperature lag, a settling, an
    #: ageing.  The lab recommends a proxy over a physical candidate only when it also predicts
    #: held-out data better, and never calls it the physical cause.
    proxy: ClassVar[str] = ""
    #: The features of the lab's search beyond the catalogue (:mod:`lab.discover`) this effect
    #: models: a residual they explain names this effect, not a term outside the catalogue.
    discovery_features: ClassVar[tuple] = ()
    #: Parameters (spec names) the data say nothing of while the effect is absent (a settling's time
    #: constant when nothing settles): the lab's test of the effect holds them at their start and
    #: tests the others, then fits them all when those are significant (:mod:`lab.diagnose`).
    held_in_test: ClassVar[tuple] = ()
    #: What the model must already depend on for this effect to do anything (``"temperature"``:
    #: a temperature effect of the same sensor; empty: nothing) — the lab tries it only then.
    requires: ClassVar[str] = ""
    #: A stochastic effect: its parameters (``specs``) are the roughness of a path the lab
    #: estimates from the data (:mod:`calibrate.wander`), not values a least-squares fit moves.
    stochastic: ClassVar[bool] = False
    #: ``_apply`` also takes ``values`` with one row per sample (arrays (N, axes) instead of
    #: (axes,)) and gives each sample what its own values alone would, bit for bit (element by
    #: element arithmetic): the lab's fits then evaluate many parameter vectors in one call
    #: (:func:`calibrate.fit.forward_jacobian`).  Said by the class itself (:func:`takes_rows`: a
    #: subclass that changes ``_apply`` says it again).
    row_parameters: ClassVar[bool] = False

    def __post_init__(self):
        if self.sensor not in self.sensors:
            raise ValueError(f"effect {self.name!r} does not act on sensor {self.sensor!r} "
                             f"(it acts on {', '.join(self.sensors)})")
        if self.stage == PROBE_STAGE:
            self.axes = ""     # a whole-probe effect has one value, not one per axis
        elif not self.axes or any(a not in AXIS_INDEX for a in self.axes) or len(set(self.axes)) != len(self.axes):
            raise ValueError(f"effect {self.name!r}: axes must be distinct letters of 'xyz', got {self.axes!r}")
        self.axes = "".join(sorted(self.axes, key="xyz".index))
        values = {}
        for spec in self.specs:
            v = np.asarray(self.values.get(spec.name, 0.0), dtype=float)
            try:
                values[spec.name] = np.broadcast_to(v, (self._n_axes,)).astype(float).copy()
            except ValueError:
                raise ValueError(f"effect {self.key}: {spec.name} needs 1 or {self._n_axes} values, got "
                                 f"{v.size}") from None
        unknown = set(self.values) - {s.name for s in self.specs}
        if unknown:
            raise ValueError(f"effect {self.name!r}: unknown parameter(s) {sorted(unknown)}")
        self.values = values

    # ---- parameter vector (for fitting) ----------------------------------------------------
    @property
    def _n_axes(self) -> int:
        return len(self.axes) if self.stage != PROBE_STAGE else 1

    @property
    def key(self) -> str:
        return f"{self.name}:{self.sensor}:{self.axes}" if self.stage != PROBE_STAGE else self.name

    def param_names(self) -> list:
        if self.stage == PROBE_STAGE:
            return [f"{self.key}.{s.name}" for s in self.specs]
        return [f"{self.key}.{s.name}_{a}" for s in self.specs for a in self.axes]

    def param_units(self) -> list:
        return [s.unit[self.sensor] for s in self.specs for _ in range(self._n_axes)]

    def param_typical(self) -> np.ndarray:
        return np.array([s.typical[self.sensor] for s in self.specs for _ in range(self._n_axes)], dtype=float)

    def get_vector(self) -> np.ndarray:
        return np.concatenate([self.values[s.name] for s in self.specs]) if self.specs else np.zeros(0)

    def set_vector(self, vec) -> None:
        vec = np.asarray(vec, dtype=float)
        n = self._n_axes
        for i, s in enumerate(self.specs):
            self.values[s.name] = vec[i * n:(i + 1) * n].copy()

    @property
    def n_params(self) -> int:
        return len(self.specs) * self._n_axes

    def _idx(self):
        return [AXIS_INDEX[a] for a in self.axes]

    def _cols(self):
        """The acted-on columns for ``v[:, ...]``: all three as a slice (the arithmetic in place,
        without the gather and scatter copies of a list index: the same elementwise operations,
        so the same bits, in about half the time), else :meth:`_idx`."""
        return slice(None) if self.axes == "xyz" else self._idx()

    def chain_context(self, ctx: Context) -> Context:
        """The context the effects of this effect's chain see (:func:`apply_chain`): ``ctx`` itself,
        unless the effect changes what the others see (a sensor feeling the temperature late)."""
        return ctx

    def apply(self, v: np.ndarray, ctx: Context) -> np.ndarray:
        """Apply the effect to the (N, 3) signal ``v`` at this effect's stage; returns a new array."""
        out = np.array(v, dtype=float, copy=True)
        self._apply(out, ctx)
        return out

    @abc.abstractmethod
    def _apply(self, v, ctx):
        """Change the (N, 3) signal ``v`` in place (one value per acted-on axis in ``self.values``)."""

    def describe(self) -> str:
        vals = ", ".join(f"{s.name}={np.array2string(self.values[s.name], precision=6)} {s.unit[self.sensor]}"
                         for s in self.specs)
        return f"{self.key} ({vals})"

    # ---- metadata ----------------------------------------------------------------------------
    @classmethod
    def summary(cls) -> str:
        """One line: the first line of the class docstring."""
        return (cls.__doc__ or cls.name).strip().splitlines()[0]

    @classmethod
    def context_needs(cls) -> tuple:
        """``needs`` as declared, else found by evaluating the effect at its typical size with two
        temperatures and two times (a plug-in that does not declare it is still checked)."""
        if cls.needs is not None:
            return tuple(cls.needs)
        if cls.stage == PROBE_STAGE:
            return ()
        out = []
        for sensor in cls.sensors:
            eff = cls(sensor=sensor, axes=cls.default_axes,
                      values={s.name: s.typical[sensor] or 1.0 for s in cls.specs})
            v = np.array([[3.0, -4.0, 8.0]] * 2)
            for what, ctx in (("temperature", Context(np.array([T_REF_C, T_REF_C + 20.0]), np.zeros(2))),
                              ("time", Context(np.full(2, T_REF_C), np.array([0.0, 3600.0])))):
                try:
                    y = eff.apply(v, ctx)
                except (AttributeError, TypeError):   # it reads ctx.history, which this context lacks
                    if "history" not in out:
                        out.append("history")
                    break
                if what not in out and not np.array_equal(y[0], y[1]):
                    out.append(what)
        return tuple(out)

    def identifiability(self, temperature_span_c: float, time_span_s: float, kinds=frozenset()) -> str:
        """Why the data described cannot determine this effect, or "" when they can.

        ``temperature_span_c`` / ``time_span_s``: spans of the stations it acts on; ``kinds``:
        the kinds of station they are (``pose``, ``ref``, ``free``)."""
        if self.not_from_static:
            return self.not_from_static
        spans = {"temperature": temperature_span_c, "time": time_span_s}
        for what in self.context_needs():
            if what not in MIN_SPAN:      # the history: any sequence of holds has one
                continue
            lo, unit, advice = MIN_SPAN[what]
            if spans[what] < lo:
                return f"{what} span {spans[what]:.1f} {unit} is too small: {advice}"
        return ""


def _spec(name, unit_acc, unit_mag, typ_acc, typ_mag, doc=""):
    return ParamSpec(name, {"acc": unit_acc, "mag": unit_mag}, {"acc": typ_acc, "mag": typ_mag}, doc)


# ---------------------------------------------------------------------------------------------
# Base model (the seed paper's): bias, scale, non-orthogonality
# ---------------------------------------------------------------------------------------------
@dataclass
class Bias(Effect):
    """Zero bias B (paper eqs. 3–4)."""

    iscwsa: ClassVar[dict] = {"acc": "ABXY-TI1S/ABZ", "mag": "MBXY/MBZ"}
    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "bias"
    base: ClassVar[bool] = True
    needs: ClassVar[tuple] = ()
    stage: ClassVar[str] = "output"
    specs: ClassVar[tuple] = (_spec("b", "m/s^2", "nT", 0.004, 70.0, "zero bias"),)

    def _apply(self, v, ctx):
        v[:, self._cols()] += self.values["b"]


@dataclass
class Scale(Effect):
    """Scale-factor error: K = 1 + k (paper eqs. 3–4)."""

    iscwsa: ClassVar[dict] = {"acc": "ASXY/ASZ", "mag": "MSXY/MSZ"}
    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "scale"
    base: ClassVar[bool] = True
    needs: ClassVar[tuple] = ()
    stage: ClassVar[str] = "gain"
    specs: ClassVar[tuple] = (_spec("k", "1", "1", 0.0005, 0.0016, "scale-factor error (K-1)"),)

    def _apply(self, v, ctx):
        v[:, self._cols()] *= 1.0 + self.values["k"]


@dataclass
class NonOrthogonality(Effect):
    """The paper's six Poisson e-terms: s_b = v_b + Σ_a e_ab v_a (E[b, a] = e_ab).

    ``axes`` here selects the *output* axes b whose two terms are included.
    """

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "nonorthogonality"
    stage: ClassVar[str] = "axes"
    base: ClassVar[bool] = True
    needs: ClassVar[tuple] = ()
    iscwsa: ClassVar[dict] = {"acc": "XYM", "mag": "XYM"}
    specs: ClassVar[tuple] = (
        _spec("e1", "rad", "rad", 0.0017, 0.0017, "E[b, first other axis]: e_yx, e_xy, e_xz for b=x, y, z"),
        _spec("e2", "rad", "rad", 0.0017, 0.0017, "E[b, second other axis]: e_zx, e_zy, e_yz for b=x, y, z"),
    )

    def _apply(self, v, ctx):
        # every output axis at once from the input as it was: per element the same two products
        # and sums as axis by axis, so the same bits
        first, second = _other_axes(self.axes)
        v[:, self._cols()] += self.values["e1"] * v.take(first, axis=1) + self.values["e2"] * v.take(second, axis=1)

    @staticmethod
    def term_names(axis: str) -> tuple:
        """Paper names of (e1, e2) for output axis ``axis``: e.g. y → (e_xy, e_zy)."""
        return _E_NAMES[axis]


def _e_names(axis: str) -> tuple:
    b = AXIS_INDEX[axis]
    others = [i for i in range(3) if i != b]
    inv = {v: k for k, v in E_TERMS.items()}
    return inv[(b, others[0])], inv[(b, others[1])]


#: :meth:`NonOrthogonality.term_names` of each axis (worked out once: a fit asks thousands of times).
_E_NAMES = {a: _e_names(a) for a in "xyz"}
_OTHER = {}


def _other_axes(axes: str) -> tuple:
    """The columns of the first and of the second other axis of each of ``axes`` (as index arrays
    for ``take``, kept per ``axes``: the non-orthogonality is applied thousands of times a fit, and
    ``take`` with an index array gathers in 60 % of the time of ``v[:, list]``)."""
    if axes not in _OTHER:
        b = [AXIS_INDEX[a] for a in axes]
        _OTHER[axes] = (np.array([OTHER_AXES[i][0] for i in b], dtype=np.intp),
                        np.array([OTHER_AXES[i][1] for i in b], dtype=np.intp))
    return _OTHER[axes]


# ---------------------------------------------------------------------------------------------
# Geometry beyond the paper
# ---------------------------------------------------------------------------------------------
def _small_rotation(rx, ry, rz):
    """Rotation matrix of small angles (rad) about x, y, z (exact, via Rodrigues)."""
    w = np.array([rx, ry, rz], dtype=float)
    th = np.linalg.norm(w)
    if th == 0:
        return np.eye(3)
    k = w / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


@dataclass
class Misalignment(Effect):
    """Sensor axes vs the housing (the patent's α/β angles), as small rotations about each axis.

    A rigid rotation of a triad is a special case of the base model's K·E (9 degrees of freedom),
    so on its own it is absorbed by the base model; it matters when the base model is restricted.
    """

    iscwsa: ClassVar[dict] = {"acc": "XYM1/XYM2", "mag": "XYM1/XYM2"}
    name: ClassVar[str] = "misalignment"
    stage: ClassVar[str] = "axes"
    needs: ClassVar[tuple] = ()
    not_from_static: ClassVar[str] = ("a rigid rotation of a triad is already inside the base model's K·E (9 degrees "
                                      "of freedom): not separable without an external reference of the housing axes")
    specs: ClassVar[tuple] = (_spec("angle", "rad", "rad", 0.0017, 0.0017, "rotation about the axis"),)

    def _rotation(self):
        w = np.zeros(3)
        w[self._idx()] = self.values["angle"]
        return _small_rotation(*w)

    def _apply(self, v, ctx):
        v[:] = rotate(self._rotation(), v)  # sensor axes rotated by R: s = Rᵀ v


@dataclass
class TriadMisalignment(Misalignment):
    """Magnetometer axes rotated against the accelerometer axes (small angles about x, y, z)."""

    iscwsa: ClassVar[dict] = {}
    name: ClassVar[str] = "triad_misalignment"
    sensors: ClassVar[tuple] = ("mag",)
    not_from_static: ClassVar[str] = ("a rotation of the magnetometer against the accelerometer is inside the base "
                                      "model's K·E: not separable from static stations")


@dataclass
class AxialInterference(Effect):
    """Axial drill-string magnetization: a field fixed along tool Z (ISCWSA AMIL, 1σ 220 nT).

    Typically present in survey data only, not in the non-magnetic lab stand.
    """

    iscwsa: ClassVar[dict] = {"mag": "AMIL"}
    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "axial_interference"
    stage: ClassVar[str] = "tool"
    sensors: ClassVar[tuple] = ("mag",)
    default_axes: ClassVar[str] = "z"
    survey_only: ClassVar[bool] = True
    needs: ClassVar[tuple] = ()
    signature: ClassVar[str] = "azimuth error varying with sin(drift)·sin(azimuth), |B| and dip off the reference"
    field_regressors: ClassVar[tuple] = ("orientation",)
    specs: ClassVar[tuple] = (_spec("field", "m/s^2", "nT", 0.0, 220.0, "field along the axis"),)

    def _apply(self, v, ctx):
        v[:, self._cols()] += self.values["field"]

    def identifiability(self, temperature_span_c, time_span_s, kinds=frozenset()) -> str:
        if kinds and set(kinds) <= {"pose"}:
            return ("on twelve-position poses a field fixed along tool Z is indistinguishable from the Z bias: needs "
                    "survey stations of known orientation or the site invariants at several azimuths")
        return super().identifiability(temperature_span_c, time_span_s, kinds)


# ---------------------------------------------------------------------------------------------
# Gain-stage effects
# ---------------------------------------------------------------------------------------------
@dataclass
class TemperatureScale(Effect):
    """Scale factor varying with temperature: K(T) = K·(1 + c·(T - T_ref))."""

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "temperature_scale"
    stage: ClassVar[str] = "gain"
    needs: ClassVar[tuple] = ("temperature",)
    signature: ClassVar[str] = "residuals following temperature in proportion to the input"
    separated_by: ClassVar[str] = SEPARATE_TEMPERATURE
    field_regressors: ClassVar[tuple] = ("temperature",)
    specs: ClassVar[tuple] = (_spec("c", "1/degC", "1/degC", 5e-5, 1e-4, "scale temperature coefficient"),)

    def _apply(self, v, ctx):
        dt = (ctx.temperature_c - T_REF_C)[:, None]
        v[:, self._cols()] *= 1.0 + self.values["c"] * dt


@dataclass
class ScaleAsymmetry(Effect):
    """Different scale for positive and negative input: y = s·(1 + a·sign(s))."""

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "scale_asymmetry"
    discovery_features: ClassVar[tuple] = ("sign(input)",)
    stage: ClassVar[str] = "gain"
    needs: ClassVar[tuple] = ()
    signature: ClassVar[str] = "residuals following the sign of the input (|input|)"
    field_regressors: ClassVar[tuple] = ("orientation",)
    specs: ClassVar[tuple] = (_spec("a", "1", "1", 5e-4, 1e-3, "half the difference of ± scales"),)

    def _apply(self, v, ctx):
        idx = self._cols()
        v[:, idx] *= 1.0 + self.values["a"] * np.sign(v[:, idx])


@dataclass
class Nonlinearity(Effect):
    """Quadratic and cubic terms: y = s + q·s²/FS + c·s³/FS² (FS = 1 g or 50 000 nT).

    ``q`` and ``c`` are dimensionless: the error, as a fraction of full scale, at full-scale input.
    """

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "nonlinearity"
    discovery_features: ClassVar[tuple] = ("input²",)
    stage: ClassVar[str] = "gain"
    needs: ClassVar[tuple] = ()
    signature: ClassVar[str] = "residuals following input² / input³"
    field_regressors: ClassVar[tuple] = ("orientation",)
    specs: ClassVar[tuple] = (
        _spec("q", "1", "1", 5e-4, 1e-3, "quadratic coefficient at full scale"),
        _spec("c", "1", "1", 5e-4, 1e-3, "cubic coefficient at full scale"),
    )

    def _apply(self, v, ctx):
        fs = FULL_SCALE[self.sensor]
        idx = self._cols()
        s = v[:, idx] / fs
        v[:, idx] += fs * (self.values["q"] * s ** 2 + self.values["c"] * s ** 3)


@dataclass
class CrossCoupling(Effect):
    """Accelerometer cross-coupling (the IEEE accelerometer model's K_ip, K_io, K_po terms).

    For output axis i with the other axes j < k:  y_i += (k_ij·s_i·s_j + k_ik·s_i·s_k + k_jk·s_j·s_k) / 1 g.
    Coefficients are dimensionless (error as a fraction of 1 g at 1 g × 1 g).
    """

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "cross_coupling"
    stage: ClassVar[str] = "gain"
    sensors: ClassVar[tuple] = ("acc",)
    needs: ClassVar[tuple] = ()
    signature: ClassVar[str] = "accelerometer residuals following products of the other axes' inputs"
    field_regressors: ClassVar[tuple] = ("orientation",)
    specs: ClassVar[tuple] = (
        _spec("k_ij", "1", "1", 5e-4, 0.0, "s_i·s_j (input × first other axis)"),
        _spec("k_ik", "1", "1", 5e-4, 0.0, "s_i·s_k (input × second other axis)"),
        _spec("k_jk", "1", "1", 5e-4, 0.0, "s_j·s_k (the two other axes)"),
    )

    def _apply(self, v, ctx):
        fs = FULL_SCALE["acc"]
        # every output axis at once from the input as it was: per element the same products and
        # sums as axis by axis, so the same bits
        i = self._idx()
        si, sj, sk = v[:, i], v[:, [OTHER_AXES[a][0] for a in i]], v[:, [OTHER_AXES[a][1] for a in i]]
        val = self.values
        v[:, i] += (val["k_ij"] * si * sj + val["k_ik"] * si * sk + val["k_jk"] * sj * sk) / fs


# ---------------------------------------------------------------------------------------------
# Output-stage effects
# ---------------------------------------------------------------------------------------------
@dataclass
class TemperatureBias(Effect):
    """Bias varying with temperature: b(T) = c·(T - T_ref)."""

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "temperature_bias"
    discovery_features: ClassVar[tuple] = ("temperature",)
    stage: ClassVar[str] = "output"
    needs: ClassVar[tuple] = ("temperature",)
    signature: ClassVar[str] = "residuals following temperature"
    separated_by: ClassVar[str] = SEPARATE_TEMPERATURE
    field_regressors: ClassVar[tuple] = ("temperature",)
    specs: ClassVar[tuple] = (_spec("c", "m/s^2/degC", "nT/degC", 2e-4, 3.0, "bias temperature coefficient"),)

    def _apply(self, v, ctx):
        v[:, self._cols()] += self.values["c"] * (ctx.temperature_c - T_REF_C)[:, None]


@dataclass
class BiasDrift(Effect):
    """Slowly varying bias: b(t) = r·t/3600 (r per hour, t from the start of the log)."""

    row_parameters: ClassVar[bool] = True
    name: ClassVar[str] = "bias_drift"
    discovery_features: ClassVar[tuple] = ("time",)
    stage: ClassVar[str] = "output"
    needs: ClassVar[tuple] = ("time",)
    signature: ClassVar[str] = "residuals following time"
    separated_by: ClassVar[str] = SEPARATE_TIME
    proxy: ClassVar[str] = ("anything that follows time: a temperature the sensor feels late (a thermal lag), a "
                            "settling after power-on, an ageing")
    field_regressors: ClassVar[tuple] = ("time",)
    specs: ClassVar[tuple] = (_spec("rate", "m/s^2/h", "nT/h", 0.002, 30.0, "bias drift per hour"),)

    def _apply(self, v, ctx):
        v[:, self._cols()] += self.values["rate"] * (ctx.time_s / 3600.0)[:, None]


@dataclass
class BiasWander(Effect):
    """A bias that wanders: a random walk ``b(t) = w(t)``, ``E[(w(t+Δt) − w(t))²] = K²·Δt`` per axis.

    Stochastic: its parameter is the walk's density ``K`` (unit/√s, the *rate random walk* of
    IEEE Std 952), which the lab takes from the noise model (:mod:`allan`: the Allan deviation of
    the holds, or the station sequence when the holds are too short to see it).  The path ``w`` is
    estimated from the data by a smoother over the stations (:mod:`calibrate.wander`: the posterior mean
    under that random-walk prior, piecewise linear between the stations' times ``knots_s``); its
    mean over the data is held at zero (the constant bias carries it).  Outside the data the best
    prediction of a random walk is its last value, so the path is held constant beyond its ends;
    a calibration record carries the density only (a new run's path is its own), and applies no
    correction for it.
    """

    name: ClassVar[str] = "bias_wander"
    stage: ClassVar[str] = "output"
    needs: ClassVar[tuple] = ("time",)
    stochastic: ClassVar[bool] = True
    iscwsa: ClassVar[dict] = {}
    signature: ClassVar[str] = ("residuals that wander in time, alike at neighbouring stations whatever their attitude, "
                                "following no regressor")
    separated_by: ClassVar[str] = ("a pose repeated at intervals at constant temperature: a wander changes the repeats "
                                   "irregularly, a drift in proportion to the time between them, a temperature effect "
                                   "not at all")
    field_regressors: ClassVar[tuple] = ("time",)
    specs: ClassVar[tuple] = (_spec("density", "m/s^2/sqrt(s)", "nT/sqrt(s)", 1e-5, 0.3,
                                    "random-walk density K (the roughness of the path)"),)
    #: Times (s) of the path's knots (the stations'), ascending; empty: no path (no correction).
    knots_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: The path at the knots, (n_knots, n_axes), in the sensor's unit; with its 1σ.
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    path_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: Effective degrees of freedom of the path per axis (the smoother's trace), from the last fit.
    edf: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: The path's roughness penalty ``Σ (Δw)²/(K²·Δt)`` at the last fit (its prior's χ²).
    penalty: float = 0.0

    # the density is held (from the noise model), the path is not a least-squares parameter
    def param_names(self) -> list:
        return []

    def param_units(self) -> list:
        return []

    def param_typical(self) -> np.ndarray:
        return np.zeros(0)

    def get_vector(self) -> np.ndarray:
        return np.zeros(0)

    def set_vector(self, vec) -> None:
        pass

    @property
    def n_params(self) -> int:
        return 0

    def clear_path(self) -> None:
        self.knots_s, self.path, self.path_std, self.edf = np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros(0)
        self.penalty = 0.0

    def sigma_at(self, time_s) -> np.ndarray:
        """(N, n_axes) 1σ of the path at ``time_s`` (s): the smoother's between the knots; beyond
        them a random walk's prediction error grows, ``σ² = σ_end² + K²·|t − t_end|``; without a
        path (a record applied to a new run) ``K·√t`` from the data's first sample."""
        t = np.asarray(time_s, dtype=float)
        k = np.asarray(self.values["density"], dtype=float)
        if not len(self.knots_s):
            return np.sqrt(np.maximum(t, 0.0))[:, None] * k
        out = np.empty((len(t), len(k)))
        t0, t1 = self.knots_s[0], self.knots_s[-1]
        for j in range(len(k)):
            sd = np.interp(t, self.knots_s, np.nan_to_num(self.path_std[:, j]))
            out[:, j] = np.sqrt(sd ** 2 + k[j] ** 2 * (np.maximum(t0 - t, 0.0) + np.maximum(t - t1, 0.0)))
        return out

    def _apply(self, v, ctx):
        if not len(self.knots_s):
            return
        for j, i in enumerate(self._idx()):
            v[:, i] += np.interp(ctx.time_s, self.knots_s, self.path[:, j])

    def identifiability(self, temperature_span_c, time_span_s, kinds=frozenset()) -> str:
        if not np.any(self.values["density"] > 0):
            return ("the noise model shows no random walk on these axes (Allan deviation of the holds and the station "
                    "sequence): nothing to smooth")
        return super().identifiability(temperature_span_c, time_span_s, kinds)

    def describe(self) -> str:
        moved = (f", path RMS {np.array2string(np.sqrt(np.mean(self.path ** 2, axis=0)), precision=3)} "
                 f"{self.specs[0].unit[self.sensor].split('/')[0]} over {len(self.knots_s)} stations") \
            if len(self.knots_s) else ""
        return super().describe() + moved


def mean_decay(start_s, n, spacing_s, tau_s):
    """Mean of ``exp(−t/τ)`` over ``n`` samples ``spacing_s`` apart from ``t = start_s``
    (broadcasts): ``exp(−a/τ)·(1 − rⁿ)/(n·(1 − r))``, ``r = exp(−Δt/τ)`` — a decay averaged over
    the samples a station keeps."""
    r = np.exp(-np.asarray(spacing_s, float) / tau_s)
    n = np.asarray(n, float)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        geo = np.where(np.abs(1.0 - r) > 1e-12, (1.0 - r ** n) / (n * (1.0 - r)), 1.0)
    return np.exp(-np.asarray(start_s, float) / tau_s) * geo


@dataclass
class Settling(Effect):
    """A sensor settling after each move: an offset set by the change of its input at the move,
    decaying from the hold's first sample: ``y += h·(x_prev − x)·exp(−t/τ)``, ``τ = exp(ln_tau)``
    seconds, averaged over the samples a station keeps (``t`` from ``settled_s`` to ``settled_s + duration``: a hold whose
    start the gates trimmed keeps the tail, :mod:`gates`).

    A fluxgate's core keeps a little of the field it held before (``h`` of the change, per axis)
    and lets it go with a time constant ``τ`` of about a second; with ``τ`` long against the holds
    it is the remanence of the previous field.  Needs the station sequence and where in its hold
    each station lies (:class:`History`): the lab's stations have them, and stations corrected in
    order get them (:func:`station.correct_stations`); a correction without them (a node's sample
    streams) refuses the model (:class:`model.ModelContextError`), never guesses."""

    name: ClassVar[str] = "settling"
    stage: ClassVar[str] = "tool"
    #: a fluxgate's core (its magnetisation follows the field it held); an accelerometer's proof
    #: mass has no such memory
    sensors: ClassVar[tuple] = ("mag",)
    held_in_test: ClassVar[tuple] = ("ln_tau",)
    needs: ClassVar[tuple] = ("history",)
    signature: ClassVar[str] = ("residuals following the change of input since the previous hold, larger in holds "
                                "kept from early on")
    separated_by: ClassVar[str] = ("holds of different lengths, and the same pose reached from different poses: a "
                                   "settling fades over a long hold, a constant offset does not")
    specs: ClassVar[tuple] = (
        _spec("h", "1", "1", 1e-3, 1e-3, "share of the change of input at the move left as an offset"),
        # ln τ, not τ: with no settling (h = 0) the data say nothing of τ, and the fits' weak prior
        # (100× the typical size: ±3 in ln τ, τ from 0.05 to 20 s at 1σ) then holds it at 0 — τ = 1 s,
        # a fluxgate's — instead of letting it wander (τ = 0 would see nothing)
        _spec("ln_tau", "ln(s)", "ln(s)", 0.03, 0.03, "natural log of the settling's time constant in s"),
    )

    def _apply(self, v, ctx):
        h = ctx.history
        if h is None or h.settled_s is None or h.duration_s is None or h.n is None:
            raise ValueError("settling: the data give no hold timing (the station sequence)")
        prev = h.previous_b                                  # a magnetometer's (``sensors``)
        c = self._cols()
        n = np.maximum(np.asarray(h.n, float), 1.0)
        spacing = np.where(n > 1, np.nan_to_num(h.duration_s) / np.maximum(n - 1, 1), 0.0)
        tau = np.exp(np.clip(self.values["ln_tau"], -7.0, 7.0))
        decay = mean_decay(np.asarray(h.settled_s, float)[:, None], n[:, None], spacing[:, None], tau[None, :])
        change = np.nan_to_num(prev[:, c] - v[:, c])       # a log's first hold: nothing before it
        v[:, c] += self.values["h"] * change * decay


def felt_temperature(time_s, temp_c, tau_s: float) -> np.ndarray:
    """The temperature felt through a first-order lag ``tau_s`` (``dT_f/dt = (T − T_f)/τ``) at each
    of the times given (any order; the temperature linear between them, felt as logged at the
    first): ``y₁ = T₁ − τs + (y₀ − T₀ + τs)·e^(−Δt/τ)``, ``s`` the segment's slope — exact for a
    piecewise-linear input.  An unknown (NaN) temperature is NaN there and skipped: the lag goes on
    from the last known one."""
    time_s, temp_c = np.asarray(time_s, float), np.asarray(temp_c, float)
    order = np.argsort(time_s, kind="stable")
    t, T = time_s[order].tolist(), temp_c[order].tolist()
    y = [math.nan] * len(T)
    last = None                       # (time, logged, felt) of the last known temperature
    for k in range(len(T)):
        if not (T[k] == T[k] and t[k] == t[k]):
            continue                  # unknown here: NaN, and the lag goes on from the last known one
        if last is None:
            y[k] = T[k]
        else:
            dt = t[k] - last[0]
            if not dt > 0:
                y[k] = last[2]
            else:
                sl = (T[k] - last[1]) / dt
                a = math.exp(-dt / tau_s)
                y[k] = T[k] - tau_s * sl + (last[2] - last[1] + tau_s * sl) * a
        last = (t[k], T[k], y[k])
    out = np.empty(len(T))
    out[order] = y
    return out


def over_sequence(ctx: Context, f) -> np.ndarray:
    """``f(times, temperatures)`` at the rows of ``ctx``, over the stations before them too when
    they come in its history (a stream corrects one station at a time: :attr:`History.earlier_time_s`)
    — for what depends on the temperature's course, not on the rows alone."""
    h = ctx.history
    t, temp = np.asarray(ctx.time_s, float), np.asarray(ctx.temperature_c, float)
    if h is None or h.earlier_time_s is None or not len(h.earlier_time_s):
        return f(t, temp)
    n = len(h.earlier_time_s)
    return f(np.concatenate([np.asarray(h.earlier_time_s, float), t]),
             np.concatenate([np.asarray(h.earlier_temp_c, float), temp]))[n:]


@dataclass
class ThermalLag(Effect):
    """The sensor feels the temperature late: its other temperature effects see the logged
    temperature through a first-order lag, ``dT_f/dt = (T − T_f)/τ``, ``τ = exp(ln_tau)`` seconds,
    the temperature linear between stations (:func:`felt_temperature`).  One time constant per
    sensor (its thermal coupling to the thermometer).

    It adds nothing by itself: it is tried on a model that already has a temperature effect of the
    sensor (:attr:`Effect.requires`).  The felt temperature depends on the stations before: a
    correction one station at a time (a stream) passes them (:attr:`History.earlier_time_s`)."""

    name: ClassVar[str] = "thermal_lag"
    stage: ClassVar[str] = "tool"
    needs: ClassVar[tuple] = ("temperature", "time", "history")
    requires: ClassVar[str] = "temperature"
    signature: ClassVar[str] = ("residuals following the temperature's rate (the logged temperature leads the "
                                "sensor's)")
    separated_by: ClassVar[str] = ("heating and cooling at different rates: a lag follows the rate, a drift in time "
                                   "does not change sign when the temperature turns")
    discovery_features: ClassVar[tuple] = ("lag",)       # the temperature's rate, or felt late
    # ln τ: positive by construction; the fits' weak prior (±3 in ln τ) holds it at τ = 1 s while
    # the data say nothing
    specs: ClassVar[tuple] = (_spec("ln_tau", "ln(s)", "ln(s)", 0.03, 0.03,
                                    "natural log of the sensor's thermal time constant in s"),)

    @property
    def _n_axes(self) -> int:
        return 1                                  # one time constant for the sensor, whatever the axes

    def param_names(self) -> list:
        return [f"{self.key}.{s.name}" for s in self.specs]

    def _apply(self, v, ctx):
        pass                                      # it changes what the sensor's other effects see only

    def chain_context(self, ctx: Context) -> Context:
        tau = float(np.exp(np.clip(self.values["ln_tau"][0], -7.0, 12.0)))
        felt = over_sequence(ctx, lambda t, temp: felt_temperature(t, temp, tau))
        return Context(temperature_c=felt, time_s=ctx.time_s, history=ctx.history)


# ---------------------------------------------------------------------------------------------
# Whole-probe effects (the simulator applies them; no triad signal chain)
# ---------------------------------------------------------------------------------------------
@dataclass
class WholeProbeEffect(Effect):
    """An effect on the whole probe's orientation or sampling (the simulator applies it), with
    one value, not one per axis; no triad's signal chain holds it."""

    stage: ClassVar[str] = PROBE_STAGE
    sensors: ClassVar[tuple] = ("probe",)
    default_axes: ClassVar[str] = ""
    needs: ClassVar[tuple] = ()

    def _apply(self, v, ctx):
        raise TypeError(f"{self.name} acts on the whole probe (the simulator), not on a triad's signal")


@dataclass
class StandPoseError(WholeProbeEffect):
    """Orientation errors of the calibration stand's poses (deg).

    Two kinds, both a rotation of the whole probe (both triads alike) after the set attitude:

    * **random**, different at every station (``sigma``, 1σ per axis; the simulator applies it):
      no fittable signature — it shows as unstructured excess scatter, which the lab reports with
      its size as an equivalent pose error;
    * **systematic**, a worn or badly set stand holding some pose a few tenths of a degree off the
      same way in every round: a fittable signature.  The lab fits it per pose (three small
      rotations in the tool frame, :attr:`calibrate.labmodel.LabModel.fit_poses`; their mean over the poses
      is the base model's own rotation freedom and is held at zero) and says which poses are off.
    """

    name: ClassVar[str] = "stand_pose_error"
    signature: ClassVar[str] = ("the same poses off in every round: both triads' residuals at a pose rotated alike "
                                "(residual ≈ measured vector × rotation), repeated across rounds")
    specs: ClassVar[tuple] = (ParamSpec("sigma", {"probe": "deg"}, {"probe": 0.05}, "1σ per axis"),)


@dataclass
class TimeSkew(WholeProbeEffect):
    """The magnetometer samples this much later than the accelerometer (s)."""

    name: ClassVar[str] = "time_skew"
    not_from_static: ClassVar[str] = ("a sampling offset between the triads is invisible in static stations: it needs "
                                      "data recorded while the probe rotates")
    specs: ClassVar[tuple] = (ParamSpec("skew", {"probe": "s"}, {"probe": 0.005}, "magnetometer minus accelerometer "
                                        "sampling time"),)


#: Effects by name (plug-ins are added by :func:`register`).
CATALOGUE = {cls.name: cls for cls in (
    Bias, Scale, NonOrthogonality, Misalignment, TriadMisalignment, AxialInterference,
    TemperatureScale, ScaleAsymmetry, Nonlinearity, CrossCoupling, TemperatureBias, BiasDrift, BiasWander,
    Settling, ThermalLag, StandPoseError, TimeSkew,
)}
#: The seed paper's base model of a triad, in signal-chain order (E, then K, then B).
BASE = ("nonorthogonality", "scale", "bias")
assert set(BASE) == {name for name, cls in CATALOGUE.items() if cls.base}


def effect_class(name: str):
    """The registered class of an effect name; unknown names raise with the known ones."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(sorted(CATALOGUE))} "
                         "(or load a plug-in with --plugin)") from None


def make_effect(name: str, sensor: str | None = None, axes: str | None = None, **values) -> Effect:
    """Build a catalogue (or registered plug-in) effect by name; default sensor: its first."""
    cls = effect_class(name)
    return cls(sensor=sensor or cls.sensors[0], axes=cls.default_axes if axes is None else axes, values=values)


def register(cls):
    """Register a user-defined effect class (plug-in) under its ``name``; collisions raise."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)) or not cls.name:
        raise TypeError("a plug-in effect must subclass inclinometer_calib.core.effects.Effect and set a name")
    if cls.name in CATALOGUE and CATALOGUE[cls.name] is not cls:
        raise ValueError(f"effect name {cls.name!r} is already taken")
    if cls.stage not in STAGES:
        raise ValueError(f"effect {cls.name!r}: stage must be one of {STAGES}")
    CATALOGUE[cls.name] = cls
    return cls


def takes_rows(effect) -> bool:
    """Whether ``effect``'s class itself says its ``_apply`` takes one row of values per sample
    (:attr:`Effect.row_parameters`; inherited, it would claim it for an ``_apply`` it never saw)."""
    return type(effect).__dict__.get("row_parameters", False) is True


def chain_context(effects, ctx: Context) -> Context:
    """The context ``effects`` see (:meth:`Effect.chain_context`: a sensor feeling the temperature
    late changes the temperature the others see)."""
    for eff in effects:
        if type(eff).chain_context is not Effect.chain_context:
            ctx = eff.chain_context(ctx)
    return ctx


def apply_chain(v: np.ndarray, effects, ctx: Context, stages=STAGES, prepared: bool = False) -> np.ndarray:
    """Apply ``effects`` to the (N, 3) signal ``v`` stage by stage (in list order within a stage).
    ``prepared``: ``ctx`` is already :func:`chain_context`'s (a caller that applies the chain again
    and again, the correction's Newton steps, works it out once)."""
    out = np.asarray(v, dtype=float)
    if not prepared:
        ctx = chain_context(effects, ctx)
    own = False     # ``out`` is a copy Effect.apply made in this call: the next effect may change it in place
    for stage in stages:
        for eff in effects:
            if eff.stage == stage:
                plain = type(eff).apply is Effect.apply
                if own and plain:
                    eff._apply(out, ctx)          # what apply() does, without its copy
                else:
                    out = eff.apply(out, ctx)
                    own = plain
    return out


# ---------------------------------------------------------------------------------------------
# The one grammar of effect specifications
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EffectSpec:
    """One item of :func:`parse_effects`: ``NAME[:sensor[:axes]][@scope][=V[,V...]]``.

    ``sensors``: the sensors named, or every sensor the effect acts on; ``axes`` None: the
    effect's default axes; ``scope`` ``all``/``cal``/``val`` (default ``val`` for a survey-only
    effect, else ``all``); ``values`` the first parameter's values (empty: not given)."""

    name: str
    sensors: tuple
    axes: str | None
    scope: str
    values: tuple
    text: str

    def build(self, need_values: bool = False) -> list:
        """One effect per sensor; the values (if given) set its first parameter."""
        cls = effect_class(self.name)
        if need_values and not self.values and cls.specs:
            raise ValueError(f"effect {self.text!r}: give its size, e.g. "
                             f"{self.name}={cls.specs[0].typical[cls.sensors[0]]:g}")
        out = []
        for s in self.sensors:
            vals = {cls.specs[0].name: list(self.values)} if self.values and cls.specs else {}
            try:
                out.append(cls(sensor=s, axes=cls.default_axes if self.axes is None else self.axes, values=vals))
            except ValueError as exc:
                raise ValueError(f"effect {self.text!r}: {exc}") from None
        return out


#: Names the effect grammar also takes that are not a triad's effects but options of the lab's fit
#: (what ``lab diagnose`` recommends is accepted verbatim wherever a model is named): the stand's
#: systematic pose errors (:class:`StandPoseError`'s name: a rotation per pose, the poses that are
#: right defining the frame) and the heading offset between the stand's north and the site's.
HEADING_OFFSET = "heading_offset"
MODEL_OPTIONS = {StandPoseError.name: "fit_poses", HEADING_OFFSET: "fit_heading"}


def split_model_options(text) -> tuple:
    """``(effects_text, options)``: the model options of :data:`MODEL_OPTIONS` named in ``text``
    (a string or list of strings in :func:`parse_effects`' grammar) taken out, as
    ``{"fit_poses": True, ...}``; the rest as a list of strings for :func:`parse_effects`.  An
    option takes no sensor, axes, scope or values (the lab fits what it is)."""
    if text is None:
        return None, {}
    texts = [text] if isinstance(text, str) else list(text)
    kept, options, after_option = [], {}, False
    for tok in (t.strip() for x in texts for t in str(x).split(",")):
        name = tok.split("=")[0].split("@")[0].split(":")[0].strip()
        if name in MODEL_OPTIONS:
            if tok != name:
                raise ValueError(f"effect {tok!r}: {name} takes no sensor, axes, scope or values (the lab fits "
                                 + ("a small rotation per pose of the stand" if name == StandPoseError.name else
                                    "the angle between the stand's north and the site's") + ")")
            options[MODEL_OPTIONS[name]] = True
            after_option = True
            continue
        if after_option and tok:
            try:
                float(tok)
            except ValueError:
                pass
            else:
                raise ValueError(f"effect value {tok!r} after {name or 'a model option'}, which takes no values")
        after_option = False
        kept.append(tok)
    return ",".join(kept), options


def parse_effects(text) -> list:
    """Parse effect specifications (a string, or a list of strings) into :class:`EffectSpec` items.

    Grammar: items ``NAME[:sensor[:axes]][@scope][=V[,V...]]`` separated by commas; a bare number
    continues the values of the item before it.  Names must be registered (catalogue or loaded
    plug-ins); every error names the item."""
    if text is None:
        return []
    texts = [text] if isinstance(text, str) else list(text)
    tokens = [tok.strip() for t in texts for tok in str(t).split(",")]
    items = []
    for tok in tokens:
        if not tok:
            continue
        try:
            float(tok)
            is_number = True
        except ValueError:
            is_number = False
        if is_number:
            if not items or "=" not in items[-1]:
                raise ValueError(f"effect value {tok!r} without an effect before it (NAME=V[,V...])")
            items[-1] += "," + tok
        else:
            items.append(tok)
    return [_parse_item(item) for item in items]


def _parse_item(item: str) -> EffectSpec:
    lhs, eq, rhs = item.partition("=")
    spec, _, scope = lhs.partition("@")
    parts = spec.strip().split(":")
    if len(parts) > 3 or not parts[0]:
        raise ValueError(f"effect {item!r}: expected NAME[:sensor[:axes]][@scope][=V[,V...]]")
    cls = effect_class(parts[0])
    sensor = parts[1] if len(parts) > 1 and parts[1] else None
    if sensor is not None and sensor not in cls.sensors:
        raise ValueError(f"effect {item!r}: {cls.name} acts on {', '.join(cls.sensors)}, not {sensor!r}")
    axes = parts[2] if len(parts) > 2 and parts[2] else None
    scope = scope.strip() or ("val" if cls.survey_only else "all")
    if scope not in SCOPES:
        raise ValueError(f"effect {item!r}: scope must be one of {', '.join(SCOPES)}")
    values = ()
    if eq:
        try:
            values = tuple(float(v) for v in rhs.split(","))
        except ValueError:
            raise ValueError(f"effect {item!r}: values must be numbers") from None
    return EffectSpec(cls.name, (sensor,) if sensor else tuple(cls.sensors), axes, scope, values, item)

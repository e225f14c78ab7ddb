"""Catalogue of physical error effects of a sensor triad, composable into a probe model.

Each effect is a small object with a stable ``name``, the ``sensor`` it acts on (``"acc"`` or
``"mag"``), the ``axes`` it acts on (a subset of ``"xyz"``), its parameters (one value per axis,
with units and a typical magnitude) and one forward function :meth:`Effect.apply`.

Signal chain of one triad (stages applied in this order)::

    tool     v  = true tool-frame vector (+ tool-fixed disturbances: axial_interference)
    axes     s  = E·v  (non-orthogonality; misalignment; triad_misalignment)
    gain     y  = K(T)·s·(1 + asymmetry·sign s) + nonlinearity(s) + cross_coupling(s)
    output   h  = y + bias(T, t)

Units: accelerometer in m/s² of the seed paper's gravity vector (down positive, ``g = -f`` of
REP-145); magnetometer in nT.  Temperature in °C relative to ``T_REF_C``; time in s.

Adding an effect means adding one class here and registering it in :data:`CATALOGUE`.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .errormodel import E_TERMS

T_REF_C = 25.0
#: Reference input magnitude per sensor (used to express nonlinearity in dimensionless form).
FULL_SCALE = {"acc": 9.80665, "mag": 50000.0}
AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
STAGES = ("tool", "axes", "gain", "output")


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of an effect: name, unit per sensor and typical 1σ magnitude per sensor."""

    name: str
    unit: dict
    typical: dict
    doc: str = ""


@dataclass
class Context:
    """Per-sample conditions an effect may depend on: temperature (°C), time (s), all (N,)."""

    temperature_c: np.ndarray
    time_s: np.ndarray


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
    description: ClassVar[str] = ""
    #: The nearest ISCWSA MWD error-model terms, per sensor (for users who think in those codes).
    iscwsa: ClassVar[dict] = {}

    def __post_init__(self):
        if self.sensor not in self.sensors:
            raise ValueError(f"effect {self.name!r} does not act on sensor {self.sensor!r} "
                             f"(it acts on {', '.join(self.sensors)})")
        if not self.axes or any(a not in AXIS_INDEX for a in self.axes) or len(set(self.axes)) != len(self.axes):
            raise ValueError(f"effect {self.name!r}: axes must be distinct letters of 'xyz', got {self.axes!r}")
        self.axes = "".join(sorted(self.axes, key="xyz".index))
        values = {}
        for spec in self.specs:
            v = np.asarray(self.values.get(spec.name, 0.0), dtype=float)
            values[spec.name] = np.broadcast_to(v, (len(self.axes),)).astype(float).copy()
        unknown = set(self.values) - {s.name for s in self.specs}
        if unknown:
            raise ValueError(f"effect {self.name!r}: unknown parameter(s) {sorted(unknown)}")
        self.values = values

    # ---- parameter vector (for fitting) ----------------------------------------------------
    @property
    def key(self) -> str:
        return f"{self.name}:{self.sensor}:{self.axes}"

    def param_names(self) -> list:
        return [f"{self.key}.{s.name}_{a}" for s in self.specs for a in self.axes]

    def param_units(self) -> list:
        return [s.unit[self.sensor] for s in self.specs for _ in self.axes]

    def param_typical(self) -> np.ndarray:
        return np.array([s.typical[self.sensor] for s in self.specs for _ in self.axes], dtype=float)

    def get_vector(self) -> np.ndarray:
        return np.concatenate([self.values[s.name] for s in self.specs]) if self.specs else np.zeros(0)

    def set_vector(self, vec) -> None:
        vec = np.asarray(vec, dtype=float)
        n = len(self.axes)
        for i, s in enumerate(self.specs):
            self.values[s.name] = vec[i * n:(i + 1) * n].copy()

    @property
    def n_params(self) -> int:
        return len(self.specs) * len(self.axes)

    def _idx(self):
        return [AXIS_INDEX[a] for a in self.axes]

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


def _spec(name, unit_acc, unit_mag, typ_acc, typ_mag, doc=""):
    return ParamSpec(name, {"acc": unit_acc, "mag": unit_mag}, {"acc": typ_acc, "mag": typ_mag}, doc)


# ---------------------------------------------------------------------------------------------
# Base model (the seed paper's): bias, scale, non-orthogonality
# ---------------------------------------------------------------------------------------------
@dataclass
class Bias(Effect):
    """Zero bias B (paper eqs. 3–4)."""

    iscwsa: ClassVar[dict] = {"acc": "ABXY-TI1S/ABZ", "mag": "MBXY/MBZ"}
    name: ClassVar[str] = "bias"
    stage: ClassVar[str] = "output"
    specs: ClassVar[tuple] = (_spec("b", "m/s^2", "nT", 0.004, 70.0, "zero bias"),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["b"]


@dataclass
class Scale(Effect):
    """Scale-factor error: K = 1 + k (paper eqs. 3–4)."""

    iscwsa: ClassVar[dict] = {"acc": "ASXY/ASZ", "mag": "MSXY/MSZ"}
    name: ClassVar[str] = "scale"
    stage: ClassVar[str] = "gain"
    specs: ClassVar[tuple] = (_spec("k", "1", "1", 0.0005, 0.0016, "scale-factor error (K-1)"),)

    def _apply(self, v, ctx):
        v[:, self._idx()] *= 1.0 + self.values["k"]


@dataclass
class NonOrthogonality(Effect):
    """The paper's six Poisson e-terms: s_b = v_b + Σ_a e_ab v_a (E[b, a] = e_ab).

    ``axes`` here selects the *output* axes b whose two terms are included.
    """

    name: ClassVar[str] = "nonorthogonality"
    stage: ClassVar[str] = "axes"
    specs: ClassVar[tuple] = (
        _spec("e1", "rad", "rad", 0.0017, 0.0017, "E[b, first other axis]: e_yx, e_xy, e_xz for b=x, y, z"),
        _spec("e2", "rad", "rad", 0.0017, 0.0017, "E[b, second other axis]: e_zx, e_zy, e_yz for b=x, y, z"),
    )

    def _apply(self, v, ctx):
        src = v.copy()
        for j, a in enumerate(self.axes):
            b = AXIS_INDEX[a]
            others = [i for i in range(3) if i != b]
            v[:, b] += self.values["e1"][j] * src[:, others[0]] + self.values["e2"][j] * src[:, others[1]]

    @staticmethod
    def term_names(axis: str) -> tuple:
        """Paper names of (e1, e2) for output axis ``axis``: e.g. y → (e_xy, e_zy)."""
        b = AXIS_INDEX[axis]
        others = [i for i in range(3) if i != b]
        inv = {v: k for k, v in E_TERMS.items()}
        return inv[(b, others[0])], inv[(b, others[1])]


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
    specs: ClassVar[tuple] = (_spec("angle", "rad", "rad", 0.0017, 0.0017, "rotation about the axis"),)

    def _rotation(self):
        w = np.zeros(3)
        w[self._idx()] = self.values["angle"]
        return _small_rotation(*w)

    def _apply(self, v, ctx):
        v[:] = v @ self._rotation()  # sensor axes rotated by R: s = Rᵀ v


@dataclass
class TriadMisalignment(Misalignment):
    """Magnetometer axes rotated against the accelerometer axes (small angles about x, y, z)."""

    iscwsa: ClassVar[dict] = {}
    name: ClassVar[str] = "triad_misalignment"
    sensors: ClassVar[tuple] = ("mag",)


@dataclass
class AxialInterference(Effect):
    """Axial drill-string magnetization: a field fixed along tool Z (ISCWSA AMIL, 1σ 220 nT).

    Typically present in survey data only, not in the non-magnetic lab stand.
    """

    iscwsa: ClassVar[dict] = {"mag": "AMIL"}
    name: ClassVar[str] = "axial_interference"
    stage: ClassVar[str] = "tool"
    sensors: ClassVar[tuple] = ("mag",)
    default_axes: ClassVar[str] = "z"
    specs: ClassVar[tuple] = (_spec("field", "m/s^2", "nT", 0.0, 220.0, "field along the axis"),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["field"]


# ---------------------------------------------------------------------------------------------
# Gain-stage effects
# ---------------------------------------------------------------------------------------------
@dataclass
class TemperatureScale(Effect):
    """Scale factor varying with temperature: K(T) = K·(1 + c·(T - T_ref))."""

    name: ClassVar[str] = "temperature_scale"
    stage: ClassVar[str] = "gain"
    specs: ClassVar[tuple] = (_spec("c", "1/degC", "1/degC", 5e-5, 1e-4, "scale temperature coefficient"),)

    def _apply(self, v, ctx):
        dt = (ctx.temperature_c - T_REF_C)[:, None]
        v[:, self._idx()] *= 1.0 + self.values["c"] * dt


@dataclass
class ScaleAsymmetry(Effect):
    """Different scale for positive and negative input: y = s·(1 + a·sign(s))."""

    name: ClassVar[str] = "scale_asymmetry"
    stage: ClassVar[str] = "gain"
    specs: ClassVar[tuple] = (_spec("a", "1", "1", 5e-4, 1e-3, "half the difference of ± scales"),)

    def _apply(self, v, ctx):
        idx = self._idx()
        v[:, idx] *= 1.0 + self.values["a"] * np.sign(v[:, idx])


@dataclass
class Nonlinearity(Effect):
    """Quadratic and cubic terms: y = s + q·s²/FS + c·s³/FS² (FS = 1 g or 50 000 nT).

    ``q`` and ``c`` are dimensionless: the error, as a fraction of full scale, at full-scale input.
    """

    name: ClassVar[str] = "nonlinearity"
    stage: ClassVar[str] = "gain"
    specs: ClassVar[tuple] = (
        _spec("q", "1", "1", 5e-4, 1e-3, "quadratic coefficient at full scale"),
        _spec("c", "1", "1", 5e-4, 1e-3, "cubic coefficient at full scale"),
    )

    def _apply(self, v, ctx):
        fs = FULL_SCALE[self.sensor]
        idx = self._idx()
        s = v[:, idx] / fs
        v[:, idx] += fs * (self.values["q"] * s ** 2 + self.values["c"] * s ** 3)


@dataclass
class CrossCoupling(Effect):
    """Accelerometer cross-coupling (the IEEE accelerometer model's K_ip, K_io, K_po terms).

    For output axis i with the other axes j < k:  y_i += (k_ij·s_i·s_j + k_ik·s_i·s_k + k_jk·s_j·s_k) / 1 g.
    Coefficients are dimensionless (error as a fraction of 1 g at 1 g × 1 g).
    """

    name: ClassVar[str] = "cross_coupling"
    stage: ClassVar[str] = "gain"
    sensors: ClassVar[tuple] = ("acc",)
    specs: ClassVar[tuple] = (
        _spec("k_ij", "1", "1", 5e-4, 0.0, "s_i·s_j (input × first other axis)"),
        _spec("k_ik", "1", "1", 5e-4, 0.0, "s_i·s_k (input × second other axis)"),
        _spec("k_jk", "1", "1", 5e-4, 0.0, "s_j·s_k (the two other axes)"),
    )

    def _apply(self, v, ctx):
        fs = FULL_SCALE["acc"]
        src = v.copy()
        for n, a in enumerate(self.axes):
            i = AXIS_INDEX[a]
            j, k = [m for m in range(3) if m != i]
            v[:, i] += (self.values["k_ij"][n] * src[:, i] * src[:, j] + self.values["k_ik"][n] * src[:, i] * src[:, k]
                        + self.values["k_jk"][n] * src[:, j] * src[:, k]) / fs


# ---------------------------------------------------------------------------------------------
# Output-stage effects
# ---------------------------------------------------------------------------------------------
@dataclass
class TemperatureBias(Effect):
    """Bias varying with temperature: b(T) = c·(T - T_ref)."""

    name: ClassVar[str] = "temperature_bias"
    stage: ClassVar[str] = "output"
    specs: ClassVar[tuple] = (_spec("c", "m/s^2/degC", "nT/degC", 2e-4, 3.0, "bias temperature coefficient"),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["c"] * (ctx.temperature_c - T_REF_C)[:, None]


@dataclass
class BiasDrift(Effect):
    """Slowly varying bias: b(t) = r·t/3600 (r per hour, t from the start of the log)."""

    name: ClassVar[str] = "bias_drift"
    stage: ClassVar[str] = "output"
    specs: ClassVar[tuple] = (_spec("rate", "m/s^2/h", "nT/h", 0.002, 30.0, "bias drift per hour"),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["rate"] * (ctx.time_s / 3600.0)[:, None]


#: Effects by name.  ``stand_pose_error`` and ``time_skew`` act on the orientation and sampling
#: of the whole probe rather than on one triad's signal, so they live in ``simulate``.
CATALOGUE = {cls.name: cls for cls in (
    Bias, Scale, NonOrthogonality, Misalignment, TriadMisalignment, AxialInterference,
    TemperatureScale, ScaleAsymmetry, Nonlinearity, CrossCoupling, TemperatureBias, BiasDrift,
)}


def make_effect(name: str, sensor: str, axes: str | None = None, **values) -> Effect:
    """Build a catalogue (or registered plug-in) effect by name."""
    try:
        cls = CATALOGUE[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(sorted(CATALOGUE))}") from None
    return cls(sensor=sensor, axes=axes or cls.default_axes, values=values)


def register(cls):
    """Register a user-defined effect class (plug-in) under its ``name``; collisions raise."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)) or not cls.name:
        raise TypeError("a plug-in effect must subclass inclinometer_calib.effects.Effect and set a name")
    if cls.name in CATALOGUE and CATALOGUE[cls.name] is not cls:
        raise ValueError(f"effect name {cls.name!r} is already taken")
    if cls.stage not in STAGES:
        raise ValueError(f"effect {cls.name!r}: stage must be one of {STAGES}")
    CATALOGUE[cls.name] = cls
    return cls


def apply_chain(v: np.ndarray, effects, ctx: Context, stages=STAGES) -> np.ndarray:
    """Apply ``effects`` to the (N, 3) signal ``v`` stage by stage (in list order within a stage)."""
    out = np.asarray(v, dtype=float)
    for stage in stages:
        for eff in effects:
            if eff.stage == stage:
                out = eff.apply(out, ctx)
    return out

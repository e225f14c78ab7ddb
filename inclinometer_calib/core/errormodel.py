"""The seed paper's per-triad error model (eqs. 3–4) in matrix form, forward and inverse.

For one triad (magnetometer: H from M, eq. 3; accelerometer: a from G, eq. 4)::

    H = K · E · M + B          (sensor output from the true tool-frame vector)
    M = C · (H - B) = C·H + D  (correction; C = (K·E)⁻¹, D = -C·B — eqs. 17–19)

with ``K = diag(Kx, Ky, Kz)`` the scale factors, ``B`` the zero biases and the Poisson
non-orthogonality/installation matrix ::

        | 1     e_yx  e_zx |
    E = | e_xy  1     e_zy |
        | e_xz  e_yz  1    |

The paper names ``e_ab`` "axis a of the triad relative to sensor b": it is the coefficient of the
true component ``M_a`` in the output of sensor ``b``, i.e. ``E[b, a]``.  (The accelerometer's
``f_ab`` are the same thing.)  Units: ``K`` and ``E`` are dimensionless ratios of output units to
input units; ``B`` and ``D`` are in output units (nT or A/D counts for the magnetometer; m/s² of the
*gravity vector* or A/D counts for the accelerometer).

The correction's formula itself is written once, in :mod:`formulas` (``corrected``: the text
:meth:`TriadModel.inverse`, a node's per-sample correction and the batch kernel all run).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .formulas import corrected

AXES = "xyz"
#: The six non-orthogonality terms, in the paper's naming, and their (row, col) place in E.
E_TERMS = {
    "e_yx": (0, 1),
    "e_zx": (0, 2),
    "e_xy": (1, 0),
    "e_zy": (1, 2),
    "e_xz": (2, 0),
    "e_yz": (2, 1),
}


@dataclass
class TriadModel:
    """Bias, scale and non-orthogonality of one sensor triad (paper eqs. 3/4).

    Parameters
    ----------
    scale : (3,) array
        Kx, Ky, Kz (output units per input unit).
    bias : (3,) array
        Bx, By, Bz (output units).
    e : dict
        The six Poisson terms by paper name (``e_yx`` ... ``e_yz``), dimensionless.
    """

    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    e: dict = field(default_factory=lambda: {k: 0.0 for k in E_TERMS})

    def __post_init__(self):
        self.scale = np.asarray(self.scale, dtype=float).reshape(3)
        self.bias = np.asarray(self.bias, dtype=float).reshape(3)
        unknown = set(self.e) - set(E_TERMS)
        if unknown:
            raise ValueError(f"unknown non-orthogonality term(s) {sorted(unknown)}")
        self.e = {k: float(self.e.get(k, 0.0)) for k in E_TERMS}

    # ---- matrix form -----------------------------------------------------------------------
    @property
    def E(self) -> np.ndarray:
        m = np.eye(3)
        for name, (r, c) in E_TERMS.items():
            m[r, c] = self.e[name]
        return m

    @property
    def A(self) -> np.ndarray:
        """The full 3×3 sensitivity matrix ``K·E`` (output = A·input + B)."""
        return self.scale[:, None] * self.E

    @property
    def correction_matrix(self) -> np.ndarray:
        """``C = (K·E)⁻¹`` — Table 3's A_i, B_i, C_i (row i = corrected axis i)."""
        return np.linalg.inv(self.A)

    @property
    def correction_offset(self) -> np.ndarray:
        """``D = -C·B`` — Table 3's D_i, in output units."""
        return -self.correction_matrix @ self.bias

    @classmethod
    def from_matrix(cls, a: np.ndarray, bias) -> "TriadModel":
        """Decompose a sensitivity matrix ``A = K·E`` (unit diagonal E) into paper parameters."""
        a = np.asarray(a, dtype=float)
        k = np.diag(a).copy()
        if np.any(np.abs(k) < 1e-12):
            raise np.linalg.LinAlgError("sensitivity matrix has a zero diagonal: scale undefined")
        e_mat = a / k[:, None]
        return cls(scale=k, bias=bias, e={n: e_mat[r, c] for n, (r, c) in E_TERMS.items()})

    # ---- forward / inverse -----------------------------------------------------------------
    def forward(self, m) -> np.ndarray:
        """Sensor output ``H = K·E·M + B`` for true vectors ``m`` of shape (..., 3)."""
        return np.asarray(m, dtype=float) @ self.A.T + self.bias

    def inverse(self, h, c=None, b=None) -> np.ndarray:
        """The linear part of the correction, ``M = C·(H - B)``, for outputs ``h`` (N, 3):
        :func:`formulas.corrected`, element by element, so that every batch size gives the same bits.

        A building block of :meth:`model.ProbeModel.correct`, the one correction path (which
        adds the effects beyond the paper); the twelve-position solver also uses it on its own
        triad before any record exists.  ``c``: C's nine entries row by row, when the caller
        keeps them (:class:`model.CorrectionPlan`: the lab's fits correct a triad thousands of
        times, and inverting ``K·E`` again each time was 3% of their CPU); ``b``: the bias's three,
        when the caller gives C and B of its own (one per row: :meth:`model.CorrectionPlan.correct_triad_rows`)."""
        h = np.asarray(h, dtype=float)
        c = tuple(self.correction_matrix.ravel()) if c is None else c
        h2 = h.reshape(-1, 3)
        return np.stack(corrected(c, self.bias if b is None else b, h2[:, 0], h2[:, 1], h2[:, 2]),
                        axis=1).reshape(h.shape)

    # ---- records ---------------------------------------------------------------------------
    def parameters(self) -> dict:
        """Flat dict of the twelve parameters: bias_x.., scale_x.., e_yx.."""
        d = {f"bias_{a}": float(self.bias[i]) for i, a in enumerate(AXES)}
        d.update({f"scale_{a}": float(self.scale[i]) for i, a in enumerate(AXES)})
        d.update(self.e)
        return d

    @classmethod
    def from_parameters(cls, d: dict) -> "TriadModel":
        return cls(
            scale=[d[f"scale_{a}"] for a in AXES],
            bias=[d[f"bias_{a}"] for a in AXES],
            e={k: d[k] for k in E_TERMS},
        )

    @classmethod
    def identity(cls) -> "TriadModel":
        return cls()

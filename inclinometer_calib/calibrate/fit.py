"""General least-squares fit of a :class:`LabModel` on any mix of stations.

Residuals (each divided by its noise, so the cost is a χ²):

* oriented stations (twelve-position poses, stand-grid stations with reference angles): measured
  minus predicted sensor output, per axis, in m/s² and nT over the station-mean noise
  ``σ = std/√n`` taken from the scatter inside the static segment;
* free stations (orientation unknown): the site invariants of the *corrected* vectors —
  |g| − G, |B| − B and dip − dip_site;
* a weak prior (100× the typical magnitude) on every extra-effect parameter, so that a parameter
  the data cannot see stays put instead of wandering (and is reported as not identifiable).

Solved by undamped Gauss–Newton steps (:func:`gauss_newton`: the residuals are close to linear
near a calibration), else by ``scipy.optimize.least_squares`` (Levenberg–Marquardt), both on
finite-difference Jacobians of a vectorised residual (the steps in one triad's own parameters
evaluated together, :func:`residual_rows`, the same bits).  Uncertainties from the Jacobian at the solution, scaled by the
reduced χ² when that exceeds 1; identifiability from its singular values, with physical hints.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..core import effects as fx
from ..core.formulas import dip_of
from ..core.specfun import chdtrc
from .blas import one_thread
from .labmodel import LabModel
from .wander import _free_sigmas, clear_paths, edf_total, smooth, stochastic_terms

PRIOR_FACTOR = 100.0
#: A wandering bias's path and the other parameters alternate until the path changes by less than
#: this (in units of its density over the mean station spacing: :func:`wander.smooth`).
SMOOTH_CHANGE = 0.01


def split_oriented(data) -> tuple:
    """``data``'s oriented stations and its free ones (None where there are none), in the order
    :func:`residual_vector` takes them."""
    ori = data.oriented
    return (data.subset(ori) if ori.any() else None), (data.subset(~ori) if (~ori).any() else None)


class ResidualCache:
    """What the residuals take from the data and from the model's structure, neither of which a
    fit changes: :func:`fit` computes it once for its hundreds of evaluations (recomputed at each,
    the two subsets and the prior rows' scales took a fifth of it: 0.62 against 0.49 ms on the
    simulator's 210 stations).

    It also keeps each triad's last outputs (predicted for the oriented stations, corrected for
    the free ones) with the parameters they came from: a triad's outputs depend on its own
    effects' parameters and the shared ones (dip, heading, the stand's poses) only, so a
    finite-difference step in one triad's parameter recomputes that triad and takes the other's
    as it was — the same bits, in about half the time (most of a fit's evaluations are such
    steps).  The free stations' corrected vectors do not depend on the shared parameters at all
    (the site's dip and the stand's heading and poses enter their residuals after the correction),
    unless an effect of the model takes the previous hold's input, which a free station may have
    from a pose's attitude in the site's field: a step in the dip or a pose recomputes the
    oriented stations only.  :meth:`forget` when the model changes outside its parameter vector
    (a wandering bias's path)."""

    __slots__ = ("split", "free_sigmas", "prior_mask", "prior_den", "own", "shared", "free_shared", "_last")

    def __init__(self, model: LabModel, data):
        self.split = split_oriented(data)
        # the free stations' σ of |g|, |B| and dip: their noise and the site's, which a fit holds
        self.free_sigmas = _free_sigmas(self.split[1], model) if self.split[1] is not None else None
        self.prior_mask, self.prior_den = _prior_scales(model)
        n = len(model.get_vector())
        sensor = np.array([t.effect.sensor for t in model.probe.terms for _ in range(t.effect.n_params)]
                          + [""] * (n - len(model.probe.param_names())))
        self.own = {s: np.flatnonzero(sensor == s) for s in ("acc", "mag")}
        self.shared = np.flatnonzero((sensor != "acc") & (sensor != "mag"))
        # the shared parameters reach the free stations' correction through the history only
        self.free_shared = any("history" in type(t.effect).context_needs() for t in model.probe.terms)
        self._last = {}

    def forget(self) -> None:
        self._last = {}

    def triad(self, slot: str, sensor: str, vec, compute, shared: bool = True):
        """``compute()`` (``sensor``'s outputs, kept as ``slot``), or its last result when the
        parameters it depends on (its own, and the shared ones if ``shared``) are those of the
        last call."""
        key = (vec[self.own[sensor]].tobytes(), vec[self.shared].tobytes() if shared else b"")
        last = self._last.get(slot)
        if last is None or last[0] != key:
            last = self._last[slot] = (key, compute())
        return last[1]


def residual_vector(model: LabModel, data, theta=None, prior=True, cache: ResidualCache | None = None) -> np.ndarray:
    """Noise-normalised residuals of ``model`` (with parameters ``theta`` if given) on ``data``
    (``cache``: :class:`ResidualCache` of this model and data, when the caller has it)."""
    if theta is not None:
        model.set_vector(theta)
    d_ori, d_free = split_oriented(data) if cache is None else cache.split
    vec = None
    if cache is None:
        def triad(slot, sensor, compute, shared=True):
            return compute()
    else:
        vec = model.get_vector()

        def triad(slot, sensor, compute, shared=True):
            return cache.triad(slot, sensor, vec, compute, shared)
    h_g = h_b = g = b = None
    if d_ori is not None:
        d = d_ori
        true = []

        def predicted(sensor):
            if not true:
                true.extend(model.true_vectors(d))   # shared parameters only: once for both triads
            return model.forward_triad(sensor, d, true[0] if sensor == "acc" else true[1])
        h_g = triad("oriented acc", "acc", lambda: predicted("acc"))
        h_b = triad("oriented mag", "mag", lambda: predicted("mag"))
    sigmas = None
    if d_free is not None:
        d = d_free
        g = triad("free acc", "acc", lambda: model.correct_triad("acc", d), cache is not None and cache.free_shared)
        b = triad("free mag", "mag", lambda: model.correct_triad("mag", d), cache is not None and cache.free_shared)
        sigmas = _free_sigmas(d, model) if cache is None else cache.free_sigmas
    return _assemble(model, d_ori, d_free, sigmas, (h_g, h_b, g, b),
                     _prior_residual(model, cache, vec) if prior else None)


def _assemble(model: LabModel, d_ori, d_free, free_sigmas, outputs, prior=None, rows: int = 0) -> np.ndarray:
    """The residual vector from the triads' ``outputs`` — the oriented stations' predicted outputs
    and the free ones' corrected vectors, ``(h_g, h_b, g, b)``, (N, 3) each (None where there are
    none) — then the ``prior`` rows.  With ``rows`` K: any of them may be K sets at once, (K, N, 3)
    (``prior`` (K, n)), and the result is K residual vectors (K, n_res): each the bits of its set
    alone (element by element, sums over three axes)."""
    h_g, h_b, g, b = outputs
    parts = []
    if d_ori is not None:
        for meas, pred, sigma in ((d_ori.g, h_g, d_ori.g_sigma), (d_ori.b, h_b, d_ori.b_sigma)):
            z = (meas - pred) / sigma
            parts.append(z.reshape(z.shape[:-2] + (-1,)))
    if d_free is not None:
        sg, sb, sdip = free_sigmas
        gn, bn = np.linalg.norm(g, axis=-1), np.linalg.norm(b, axis=-1)
        dip = dip_of(np.sum(g * b, axis=-1), gn, bn)
        parts += [(gn - model.site.gravity_mps2) / sg, (bn - model.site.total_field_nt) / sb,
                  (dip - model.dip_deg) / sdip]
    if prior is not None:
        parts.append(prior)
    if rows:
        parts = [np.broadcast_to(p, (rows, p.shape[-1])) for p in parts]
    return np.concatenate(parts, axis=-1)


def _rows_sensors(model: LabModel, cache: ResidualCache, stochastic: bool) -> tuple:
    """The triads whose finite-difference steps :func:`residual_rows` evaluates together: those
    whose every effect takes one row of values per sample (:func:`effects.takes_rows`), in a model
    without effects that need the history of holds or a wandering bias (those step one by one)."""
    if stochastic or cache.free_shared:
        return ()
    return tuple(s for s in ("acc", "mag")
                 if all(fx.takes_rows(t.effect) for t in model.probe.terms if t.effect.sensor == s))


def _term_rows(model: LabModel, sensor: str, V, n: int) -> None:
    """Give ``sensor``'s effects the values of the K parameter vectors ``V`` (K, n_all), each
    repeated for ``n`` rows: (K·n, axes) arrays, the K sets one after the other."""
    i = 0
    for t in model.probe.terms:
        e = t.effect
        na = e.n_params // len(e.specs) if e.specs else 0
        if e.sensor == sensor:
            for k, s in enumerate(e.specs):
                e.values[s.name] = np.repeat(V[:, i + k * na:i + (k + 1) * na], n, axis=0)
        i += e.n_params


def _triad_rows(model: LabModel, sensor: str, d, V, true=None) -> np.ndarray:
    """``sensor``'s outputs on the stations ``d`` for the K parameter vectors ``V`` (K, n_all) in
    one evaluation per role, (K, N, 3): the predicted outputs of oriented stations for their true
    vectors ``true`` (:meth:`LabModel.forward_triad`), else the corrected vectors of free ones
    (:meth:`LabModel.correct_triad`) — each set the bits of its vector alone.  Leaves the model's
    effects holding rows: the caller sets its vector back."""
    from ..core.model import CorrectionPlan

    k = len(V)
    out = np.empty((k, len(d), 3))
    for role in ("cal", "val"):
        m = d.role == role
        n = int(m.sum())
        if not n:
            continue
        temp, tim = np.tile(d.temp_c[m], k), np.tile(d.time_s[m], k)
        if true is not None:
            _term_rows(model, sensor, V, n)
            y = model.probe.forward_triad(sensor, np.tile(true[m], (k, 1)), temp, tim, role)
        else:
            c, bias = np.empty((k, 9)), np.empty((k, 3))
            for q in range(k):                   # each vector's base triad, as CorrectionPlan takes it
                model.set_vector(V[q])
                tri = model.probe.triad(sensor)
                c[q], bias[q] = tri.correction_matrix.ravel(), tri.bias
            plan = CorrectionPlan(model.probe, role, (sensor,))
            _term_rows(model, sensor, V, n)
            y = plan.correct_triad_rows(sensor, np.tile((d.g if sensor == "acc" else d.b)[m], (k, 1)),
                                        tuple(np.repeat(c[:, q], n) for q in range(9)),
                                        tuple(np.repeat(bias[:, q], n) for q in range(3)), temp, tim)
        out[:, m] = y.reshape(k, n, 3)
    return out


def residual_rows(model: LabModel, data, cache: ResidualCache, base, V, sensor: str) -> np.ndarray:
    """:func:`residual_vector` at each of the K parameter vectors ``V`` (K, n_all), which differ from
    ``base`` in ``sensor``'s own parameters only (a Jacobian's steps, :func:`forward_jacobian`): the
    other triad's outputs are ``base``'s, ``sensor``'s are evaluated for all K at once
    (:func:`_triad_rows`: about a fifth of the time of K evaluations).  Each row is the bits
    :func:`residual_vector` gives (test/lab/test_fit.py).  The model is left at ``base``."""
    model.set_vector(base)
    d_ori, d_free = cache.split
    other = "mag" if sensor == "acc" else "acc"
    si = 0 if sensor == "acc" else 1
    outs = [None] * 4
    try:
        if d_ori is not None:
            true = model.true_vectors(d_ori)
            outs[1 - si] = cache.triad(f"oriented {other}", other, base,
                                       lambda: model.forward_triad(other, d_ori, true[1 - si]))
            outs[si] = _triad_rows(model, sensor, d_ori, V, true[si])
            model.set_vector(base)
        if d_free is not None:
            outs[3 - si] = cache.triad(f"free {other}", other, base, lambda: model.correct_triad(other, d_free),
                                       cache.free_shared)
            outs[2 + si] = _triad_rows(model, sensor, d_free, V)
    finally:
        model.set_vector(base)
    return _assemble(model, d_ori, d_free, cache.free_sigmas, outs, _prior_residual(model, cache, V), rows=len(V))


def residual_groups(data) -> np.ndarray:
    """The group of each data residual of :func:`residual_vector` (same order): one group per
    role and channel (``cal acc``, ``cal mag``, ``val |B|`` …), whose noise is measured apart."""
    ori = data.oriented
    out = []
    if ori.any():
        role = data.role[ori]
        out += [np.repeat(np.char.add(role.astype(str), f" {s}"), 3) for s in ("acc", "mag")]
    if (~ori).any():
        role = data.role[~ori].astype(str)
        out += [np.char.add(role, f" {c}") for c in (" |g|", " |B|", " dip")]
    return np.concatenate(out) if out else np.zeros(0, dtype=str)


def _prior_residual(model: LabModel, cache: ResidualCache | None = None, vec=None) -> np.ndarray:
    """The weak prior rows (extra parameters over 100× their typical size), then the gauge rows
    (:meth:`LabModel.gauge_residual`); ``vec``: the model's parameter vector when the caller has it,
    or K vectors (K, n) that differ from the model's outside the stand's poses (K sets of rows)."""
    mask, den = _prior_scales(model) if cache is None else (cache.prior_mask, cache.prior_den)
    vec = model.get_vector() if vec is None else vec
    gauge = model.gauge_residual()
    return np.concatenate([vec[..., mask] / den, np.broadcast_to(gauge, vec.shape[:-1] + gauge.shape)], axis=-1)


def _prior_scales(model: LabModel) -> tuple:
    """The parameters under the weak prior (mask) and the prior's σ of each (100× typical)."""
    mask = model.prior_mask()
    return mask, PRIOR_FACTOR * model.param_scale()[mask]


@dataclass
class Identifiability:
    parameter: str
    reason: str


@dataclass
class JacobianHint:
    """The derivatives of a fitted model's data residuals (the data rows of its last Jacobian,
    unscaled, one column per free parameter ``names``) and those residuals, at its solution
    (``values`` over ``all_names``, every parameter of the model).

    A candidate effect starts absent — its parameters at values that leave the residuals as they
    were — from the base model's solution, so there the base model's derivatives are the
    candidate's for the parameters they share: the candidate fit's first Jacobian takes those
    columns and evaluates only the new ones (:func:`fit`'s ``hint``; most of a diagnosis's
    evaluations were these).  Taken only where every shared parameter has the solution's value
    and the residuals at the start are the solution's (else the Jacobian is evaluated whole).  The
    last Jacobian may be one Gauss–Newton step behind the solution (:func:`gauss_newton`): a
    first step from it is as good; every later Jacobian is the candidate's own."""

    names: list
    all_names: list
    values: np.ndarray
    r_data: np.ndarray
    jac: np.ndarray

    def columns(self, model: LabModel, free, x_all, n_data: int):
        """``known(r, x, h) -> {column: derivative}`` for :func:`forward_jacobian`, or None when
        the model does not start at this solution."""
        at = dict(zip(self.all_names, self.values))
        names = model.param_names()
        if any(n in at and at[n] != v for n, v in zip(names, x_all)):
            return None
        col = {n: k for k, n in enumerate(self.names)}
        shared = {j: col[names[i]] for j, i in enumerate(np.flatnonzero(free)) if names[i] in col}
        if not shared:
            return None
        r_ref, jac = self.r_data, self.jac

        def known(r, x, h, fun_prior):
            if len(r) < n_data or n_data != len(r_ref) or \
                    np.max(np.abs(r[:n_data] - r_ref), initial=0.0) > 1e-9 * (1.0 + np.max(np.abs(r_ref), initial=0.0)):
                return {}         # the candidate is not absent at its start: no column is known
            out = {}
            for j, k in shared.items():
                xj = x.copy()
                xj[j] += h[j]
                # the prior rows by their own (cheap) finite difference; the data rows known
                out[j] = np.concatenate([jac[:, k], (fun_prior(xj) - r[n_data:]) / (xj[j] - x[j])])
            return out
        return known


@dataclass
class FitResult:
    model: LabModel
    names: list
    units: list
    values: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    chi2: float
    dof: int
    n_data: int
    success: bool
    message: str
    seconds: float
    nfev: int
    not_identifiable: list = field(default_factory=list)
    covariance: np.ndarray | None = None
    n_free: float = -1
    #: the data rows of the fit's last Jacobian, for the fits of this model with one effect more
    #: (with ``fit(..., give_hint=True)``, else None)
    hint: "JacobianHint | None" = None
    #: the noise-normalised data residuals at the solution (:func:`residual_vector` without the
    #: prior rows: ``chi2`` is their sum of squares)
    residuals: np.ndarray | None = field(default=None, repr=False)

    @property
    def z_rms(self) -> float:
        """RMS of the noise-normalised residuals: ≈1 when the model explains the data to the noise."""
        return float(np.sqrt(self.chi2 / max(self.n_data, 1)))

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    @property
    def n_params(self) -> int:
        return len(self.values) if self.n_free < 0 else self.n_free

    def aic(self) -> float:
        return self.chi2 + 2 * self.n_params

    def bic(self) -> float:
        return self.chi2 + self.n_params * np.log(max(self.n_data, 2))

    def wald(self, index) -> tuple:
        """Wald test that the parameters ``index`` are all zero: ``(χ², k, p)`` with
        ``χ² = θᵀ·C⁻¹·θ`` from the fit's covariance (each data group's noise inflated to the
        scatter it shows when the model misfits it: the test is against the measured noise)."""
        idx = np.atleast_1d(np.asarray(index))
        theta = self.values[idx]
        c = self.covariance[np.ix_(idx, idx)]
        try:
            chi2 = float(theta @ np.linalg.solve(c, theta))
        except np.linalg.LinAlgError:
            chi2 = float(theta @ np.linalg.pinv(c) @ theta)
        return chi2, len(idx), float(chdtrc(len(idx), chi2))

    def parameter_table(self, extras_only: bool = False) -> list:
        rows = []
        for i, (n, u, v, s) in enumerate(zip(self.names, self.units, self.values, self.std)):
            if extras_only and n.split(":")[0] in fx.BASE:
                continue
            rows.append({"name": n, "value": float(v), "std": float(s), "unit": u})
        return rows

    def strong_correlations(self, threshold: float = 0.95) -> list:
        out = []
        c = self.correlation
        for i in range(len(self.names)):
            for j in range(i + 1, len(self.names)):
                if np.isfinite(c[i, j]) and abs(c[i, j]) >= threshold:
                    out.append((self.names[i], self.names[j], float(c[i, j])))
        return out


@one_thread
def fit(model: LabModel, data, progress=None, max_nfev: int = 200, uncertainty: bool = True,
        fixed=None, hint: JacobianHint | None = None, give_hint: bool = False) -> FitResult:
    """Fit ``model`` (in place, starting from its current parameters) to ``data``.

    Levenberg–Marquardt (MINPACK, QR-based: faster than the SVD-based trust region for these
    tall, narrow problems), parameters scaled by their typical magnitudes.  ``fixed``: a boolean
    mask over :meth:`LabModel.param_names` of parameters held at their current values (their
    σ is 0).  ``uncertainty=False`` skips the covariance and identifiability analysis.  ``hint``:
    the :attr:`FitResult.hint` of the model this one extends (:class:`JacobianHint`);
    ``give_hint``: keep this fit's own (its Jacobian's data rows: kept only where models that
    extend it will be fitted, not in every result).
    """
    t0 = time.perf_counter()
    x_all = model.get_vector()
    free = np.ones(len(x_all), bool) if fixed is None else ~np.asarray(fixed, bool)
    scale_all = model.param_scale()
    x0, scale = x_all[free], scale_all[free]
    cache = ResidualCache(model, data)
    n_data = len(residual_vector(model, data, x_all, prior=False, cache=cache))
    calls = [0]

    def full(x):
        v = x_all.copy()
        v[free] = x
        return v

    last = [None, None]                 # the last point evaluated and its residuals

    def fun(x):
        calls[0] += 1
        if progress and calls[0] % 500 == 0:
            progress(f"fit: {calls[0]} evaluations")
        r = residual_vector(model, data, full(x), cache=cache)
        last[0], last[1] = np.array(x, dtype=float), r
        return r

    def prior_at(x):
        model.set_vector(full(x))
        return _prior_residual(model, cache)

    stochastic = bool(stochastic_terms(model))
    first = [None if hint is None or stochastic else hint.columns(model, free, x_all, n_data)]
    # the steps in one triad's own parameters evaluated together (residual_rows)
    free_idx = np.flatnonzero(free)
    together = {s: set(cache.own[s].tolist()) for s in _rows_sensors(model, cache, stochastic)}

    def batch(x, h, columns):
        out = {}
        base = full(x)
        for sensor, own in together.items():
            js = [j for j in columns if free_idx[j] in own]
            if len(js) < 2:
                continue
            v = np.repeat(base[None], len(js), axis=0)
            for k, j in enumerate(js):
                v[k, free_idx[j]] = x[j] + h[j]
            calls[0] += len(js)
            out.update(zip(js, residual_rows(model, data, cache, base, v, sensor)))
        return out

    def lm_jacobian(x):
        """scipy's ``jac="2-point"`` for Levenberg–Marquardt: its step (``√ε·max(1, |x|)``, the sign
        of ``x``) and arithmetic, at the residuals of the point last evaluated (MINPACK asks for
        the Jacobian where it has just evaluated), with a triad's own steps evaluated together
        (:func:`residual_rows`): the same Jacobian, bit for bit, in a third of the time."""
        x = np.asarray(x, dtype=float)
        r = last[1] if last[0] is not None and np.array_equal(last[0], x) else fun(x)
        h = _SQRT_EPS * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        return forward_jacobian(fun, x, r, scale, batch=batch, h=h)[0]

    def solve(x_start):
        """Gauss–Newton (:func:`gauss_newton`), else Levenberg–Marquardt, from ``x_start``
        (with the stand's pose errors, the poses found off leave the gauge and the fit is repeated)."""
        for _ in range(3 if model.fit_poses else 1):
            res = gauss_newton(fun, x_start, scale,
                               known=(lambda r, x, h: first[0](r, x, h, prior_at)) if first[0] else None,
                               batch=batch if together else None)
            first[0] = None          # the hint is of the start point: the first Jacobian only
            if res is None:
                from scipy.optimize import least_squares   # here: 0.2 s of every process that imports the lab
                res = least_squares(fun, x_start, x_scale=scale, method="lm",
                                    jac=lm_jacobian if together else "2-point",
                                    max_nfev=max_nfev * (len(x_start) + 1), xtol=1e-10, ftol=1e-10, gtol=1e-10)
            model.set_vector(full(res.x))
            if not model.fit_poses or not model.regauge(data):
                break
            x_start = res.x
        return res

    if stochastic:
        clear_paths(model)
        cache.forget()      # the paths are the model's, outside its parameter vector
    if len(x0):
        res = solve(x0)
        # a wandering bias: its path (the smoother) and the other parameters, each holding the other
        for k in range(6 if stochastic else 0):
            # the path's σ and degrees of freedom from the smoothing that ends the alternation only
            change = smooth(model, data, posterior_below=SMOOTH_CHANGE if k < 5 else None)
            cache.forget()
            res = solve(res.x)
            if change < SMOOTH_CHANGE:
                break
        x, jac, ok, msg, nfev = res.x, res.jac, bool(res.success), str(res.message), int(res.nfev)
    else:
        if stochastic:
            smooth(model, data)
            cache.forget()
        x, jac, ok, msg, nfev = x0, np.zeros((0, 0)), True, "nothing to fit", 0
    model.set_vector(full(x))
    r_data = residual_vector(model, data, prior=False, cache=cache)
    chi2 = float(r_data @ r_data)
    # a stochastic effect's path counts with its effective degrees of freedom
    p = int(free.sum())
    p_eff = p + edf_total(model)
    dof = max(n_data - p_eff, 1)
    n = len(x_all)
    std, corr, notid = np.zeros(n), np.full((n, n), np.nan), []
    cov = np.zeros((n, n))
    if uncertainty and p:
        s_f, c_f, notid, cov_f = _uncertainty(model, jac, scale, _group_inflation(r_data, data, p), data, free)
        std[free] = s_f
        cov[np.ix_(free, free)] = cov_f
        corr[np.ix_(free, free)] = c_f
    elif not uncertainty:
        std[:] = np.nan
        cov[:] = np.nan
    hint = None
    if give_hint and p and not stochastic and jac.ndim == 2 and jac.shape[0] >= n_data and jac.shape[1] == p:
        hint = JacobianHint(names=[n for n, f in zip(model.param_names(), free) if f], all_names=model.param_names(),
                            values=model.get_vector().copy(), r_data=r_data, jac=np.array(jac[:n_data]))
    return FitResult(model=model, names=model.param_names(), units=model.param_units(), values=model.get_vector(),
                     std=std, correlation=corr, chi2=chi2, dof=dof, n_data=n_data, success=ok,
                     message=msg, seconds=time.perf_counter() - t0, nfev=nfev, not_identifiable=notid,
                     covariance=cov, n_free=p_eff, hint=hint, residuals=r_data)


#: Gauss–Newton steps (each on a Jacobian of its own point) before the fit falls back to
#: Levenberg–Marquardt.
GN_JACOBIANS = 3
#: Converged when the step at the point's own Jacobian promises a fall of χ² (noise-normalised)
#: below this, or this share of χ² (Levenberg–Marquardt's ftol).
GN_CHI2 = 1e-6
GN_FTOL = 1e-10
#: A step that promises a fall of χ² below this is the last one, taken without a Jacobian more
#: (what remains after it is of the order of its square: less than any test could see).
GN_LAST = 1e-2


class Solution:
    """What :func:`fit` reads of a solver's result (``scipy.optimize.OptimizeResult``'s names)."""
    __slots__ = ("x", "jac", "success", "message", "nfev")

    def __init__(self, x, jac, message, nfev):
        self.x, self.jac, self.success, self.message, self.nfev = x, jac, True, message, nfev


#: √ε of float64: the relative step of a forward difference.
_SQRT_EPS = float(np.sqrt(np.finfo(float).eps))


def forward_jacobian(fun, x, r, scale, known=None, batch=None, h=None) -> tuple:
    """Forward differences of ``fun`` at ``x`` (``r = fun(x)``), the step of each parameter
    ``√ε·max(|x|, scale)`` (ε the float64 resolution): relative to the parameter, or to its
    typical magnitude where it is near zero (``h``: these steps given instead).  ``known(r, x, h)``:
    the columns known without evaluating ``fun`` (:class:`JacobianHint`).  ``batch(x, h, columns)``:
    ``{column: fun at the step}`` for those of ``columns`` it evaluates together
    (:func:`residual_rows`: the same bits); the rest one by one.  Returns (Jacobian, evaluations
    of ``fun``)."""
    if h is None:
        h = _SQRT_EPS * np.maximum(np.abs(x), scale)
    jac = np.empty((len(r), len(x)))
    have = known(r, x, h) if known is not None else {}
    for j, column in have.items():
        jac[:, j] = column
    stepped = batch(x, h, [j for j in range(len(x)) if j not in have]) if batch is not None else {}
    for j, rj in stepped.items():
        jac[:, j] = (rj - r) / ((x[j] + h[j]) - x[j])
    for j in range(len(x)):
        if j in have or j in stepped:
            continue
        xj = x.copy()
        xj[j] += h[j]
        jac[:, j] = (fun(xj) - r) / (xj[j] - x[j])
    return jac, len(x) - len(have)


def gauss_newton(fun, x0, scale, max_jac: int = GN_JACOBIANS, known=None, batch=None):
    """Least squares by undamped Gauss–Newton steps, or None when they do not serve.

    The lab's residuals are close to linear in the parameters near a calibration (the base model
    is linear, the effects small): a Gauss–Newton step from a finite-difference Jacobian lands at
    the minimum, or next to it, where Levenberg–Marquardt's damped steps take three or four
    Jacobians (one evaluation per parameter each).  A step is solved by the SVD of the scaled
    Jacobian.  Converged when the step at the point's own Jacobian promises a fall of χ² below
    :data:`GN_CHI2` (or :data:`GN_FTOL` of χ²) — so a parameter the first Jacobian did not see (a
    time constant while its effect is still zero) is found at the second; a step promising less
    than :data:`GN_LAST` is the last.  The last Jacobian is the solution's (its covariance).
    Returns None — the caller falls back to Levenberg–Marquardt — when a step raises χ² or after
    ``max_jac`` Jacobians (a strongly nonlinear problem).  ``known``: the first Jacobian's known
    columns, ``batch``: its steps evaluated together (:func:`forward_jacobian`)."""
    x = np.asarray(x0, dtype=float).copy()
    if not len(x):
        return None
    r = fun(x)
    cost = float(r @ r)
    nfev = 1
    for n_jac in range(1, max_jac + 1):
        jac, evaluations = forward_jacobian(fun, x, r, scale, known if n_jac == 1 else None, batch)
        nfev += evaluations
        u, sv, vt = np.linalg.svd(jac * scale, full_matrices=False)
        keep = sv > sv[0] * 1e-12 if len(sv) and sv[0] > 0 else sv > 0
        g = u[:, keep].T @ r
        promised = float(g @ g)
        if promised <= max(GN_CHI2, GN_FTOL * cost):
            return Solution(x, jac, f"Gauss-Newton: converged in {n_jac - 1} steps", nfev)
        x_new = x + (-(vt[keep].T @ (g / sv[keep]))) * scale
        r_new = fun(x_new)
        nfev += 1
        cost_new = float(r_new @ r_new)
        gain = cost - cost_new if np.isfinite(cost_new) else -np.inf
        if promised <= GN_LAST:
            return Solution(x_new if gain > 0 else x, jac, f"Gauss-Newton: converged in {n_jac} steps", nfev)
        if gain <= 0:
            return None              # the linearisation misleads: not for Gauss–Newton
        x, r, cost = x_new, r_new, cost_new
    return None


def _group_inflation(r_data, data, n_params) -> np.ndarray:
    """Per data residual: the variance factor of its group (:func:`residual_groups`) — the group's
    reduced χ² when above 1, else 1.  The noise is then the scatter each group shows: a misfit in
    the 72 numbers of twelve stand poses is not diluted by hundreds of survey invariants that fit."""
    groups = residual_groups(data)
    out = np.ones(len(r_data))
    n = len(r_data)
    for gname in np.unique(groups):
        m = groups == gname
        dof = max(m.sum() - n_params * m.sum() / max(n, 1), 1.0)
        out[m] = max(float(np.sum(r_data[m] ** 2)) / dof, 1.0)
    return out


def _uncertainty(model, jac, scale, inflation, data, free):
    """σ, correlation and covariance of the free parameters, and what the data cannot determine.

    The covariance comes from the SVD of the (scaled) Jacobian itself, ``C = V·S⁻²·Vᵀ``, not from
    inverting ``JᵀJ``: that squares the condition number, and its rounding gave correlations
    beyond ±1 on ill-conditioned fits.  Each data row is weighted by its group's measured noise
    (``inflation``, :func:`_group_inflation`)."""
    js = np.asarray(jac) * scale  # dimensionless columns
    # drop the prior rows: identifiability is a property of the data
    n_prior = int(model.prior_mask().sum()) + len(model.gauge_residual())   # rows, fixed parameters' too
    jd = js[:len(js) - n_prior] if n_prior else js
    u, s, vt = np.linalg.svd(jd, full_matrices=False)
    names = [n for n, f in zip(model.param_names(), free) if f]
    # physical hints first: they say what data would make the parameter identifiable
    notid = physical_hints(model, data)
    hinted = {n.parameter for n in notid}
    tol = s[0] * 1e-7 if len(s) else 0
    for k in np.flatnonzero(s < tol):
        for i in np.flatnonzero(np.abs(vt[k]) > 0.3):
            if names[i].split(".")[0] not in hinted:
                notid.append(Identifiability(names[i], "no information in the data (lies in the Jacobian's "
                                                       "null space)"))
    # covariance from the full Jacobian (the prior rows keep it finite where the data say nothing)
    w = np.concatenate([1.0 / np.sqrt(inflation), np.ones(len(js) - len(inflation))])
    _, sf, vtf = np.linalg.svd(js * w[:, None], full_matrices=False)
    keep = sf > (sf[0] * 1e-12 if len(sf) else 0)
    cov_s = (vtf[keep].T / sf[keep] ** 2) @ vtf[keep]
    cov = cov_s * np.outer(scale, scale)
    std = np.sqrt(np.maximum(np.diag(cov), 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.clip(cov / np.outer(std, std), -1.0, 1.0)
    # dedupe
    seen, uniq = set(), []
    for n in notid:
        if n.parameter not in seen:
            seen.add(n.parameter)
            uniq.append(n)
    return std, corr, uniq, cov


def physical_hints(model: LabModel, data) -> list:
    """Name the effects the data cannot determine, and what data would determine them (each
    effect class says so itself: :meth:`effects.Effect.identifiability`)."""
    out = []
    for t in model.extra_terms:
        e = t.effect
        sel = np.ones(len(data), bool) if t.scope == "all" else (data.role == t.scope)
        if not sel.any():
            out.append(Identifiability(e.key, f"acts on '{t.scope}' logs only, and none was given"))
            continue
        why = e.identifiability(float(np.ptp(data.temp_c[sel])), float(np.ptp(data.time_s[sel])),
                                frozenset(data.kind[sel]))
        if why:
            out.append(Identifiability(e.key, why))
    return out

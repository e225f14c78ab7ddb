"""The path of a wandering bias (:class:`effects.BiasWander`): a smoother over the stations.

Under a random-walk prior of density ``K`` (per axis, from the noise model: :mod:`allan`) and the
stations' white noise, the most probable path given the data is the minimiser of

    Σ_stations (observation − H·w)² / σ²  +  Σ_k (w_{k+1} − w_k)² / (K²·Δt_k)

(the Rauch–Tung–Striebel smoother's answer, written as one sparse least-squares problem), with the
path's mean over the stations held at zero (the constant bias carries it).  The knots are the
stations' times: between observations the posterior mean of a random walk is linear, so the
path interpolated between the knots is exact.  What each station says about ``w``:

* an oriented station (a pose, a reference): its residual against the rest of the model, per axis,
  ``r = measured − predicted`` with the path left out — ``H = I``;
* a free station (a survey station: attitude unknown): its site invariants against the site.  A
  small output offset ``w`` changes the corrected vector by ``−w`` (to the base model's scale and
  non-orthogonality, 10⁻³), so ``|g|`` by ``−ĝ·w_acc``, ``|B|`` by ``−b̂·w_mag`` and the dip by
  ``−[(ĝ − sinδ·b̂)/|B|·w_mag + (b̂ − sinδ·ĝ)/|g|·w_acc]/cosδ`` (rad): how a rig's own QC numbers
  track a wander through the survey, the attitude changing from station to station making every
  axis visible in turn.

The smoother alternates with the least-squares fit of the model's other parameters
(:func:`calibrate.fit.fit`), each holding the other.  Its effective degrees of freedom (the trace of
its hat matrix, per axis) go into the fit's parameter count and the lab's likelihood-ratio test.
"""
from __future__ import annotations

import numpy as np

#: Above this many path states the posterior covariance (for the path's σ and the degrees of
#: freedom) is not formed densely: the path is still solved, its σ and edf left NaN.
DENSE_STATES = 4000
#: The path's mean is held at zero by a row this stiff (relative to the walk over the data).
GAUGE = 1e-3


def stochastic_terms(model) -> list:
    """The model's terms whose effect is stochastic (their paths this module estimates)."""
    return [t for t in model.terms if t.effect.stochastic]


def clear_paths(model) -> None:
    for t in stochastic_terms(model):
        t.effect.clear_path()


def _free_sigmas(data, model):
    sg = np.linalg.norm(data.g_sigma, axis=1)
    sb = np.linalg.norm(data.b_sigma, axis=1)
    sdip = np.degrees(sb / model.site.total_field_nt + sg / model.site.gravity_mps2)
    return sg, sb, sdip


def smooth(model, data, posterior_below: float | None = None) -> float:
    """Estimate the paths of ``model``'s stochastic effects from ``data`` (in place); the other
    parameters are held.  Returns the largest change of a path, in units of its density over the
    mean station spacing (0 when the model has no stochastic effect).  ``posterior_below``: the
    path's σ and effective degrees of freedom only when the change is below it (else NaN: the fit's
    alternation keeps only the last smoothing's, and the covariance is most of a smoothing's work);
    None: always.

    The normal matrix ``N = AᵀA`` of the rows below (the data's, the walk's, the gauge's) is solved
    by its Cholesky factor (LAPACK ``potrf``/``potrs``), and the posterior covariance ``N⁻¹`` taken
    from the same factor (``potri``): ``N`` is symmetric positive definite (the walk joins the knots,
    the gauge holds the constant the data might leave), a third of the work of a general inverse,
    and no second factorisation for the path (a sparse solve of the same ``N``, which the gauge's
    full rows make dense, was as dear as the inverse)."""
    terms = stochastic_terms(model)
    if not terms or not len(data):
        return 0.0
    old = [(t.effect.knots_s.copy(), t.effect.path.copy()) for t in terms]
    for t in terms:
        t.effect.clear_path()                      # the residuals of the rest of the model
    knots = np.unique(data.time_s)
    kidx = np.searchsorted(knots, data.time_s)
    nk = len(knots)
    # state layout: term i, knot k, axis j -> offset[i] + k·n_axes[i] + j
    n_ax = [len(t.effect.axes) for t in terms]
    offset = np.concatenate([[0], np.cumsum([nk * n for n in n_ax])])
    n_state = int(offset[-1])
    rows, cols, vals, rhs = [], [], [], []          # blocks of triplets (row numbers from 0 per block)
    n_row = 0

    def block(r, c, v, b):
        """Rows ``r`` (numbered within the block) with columns ``c`` and values ``v``; right sides ``b``."""
        nonlocal n_row
        rows.append(np.asarray(r, dtype=np.int64) + n_row)
        cols.append(np.asarray(c, dtype=np.int64))
        vals.append(np.asarray(v, dtype=float))
        rhs.append(np.asarray(b, dtype=float))
        n_row += len(rhs[-1])

    def acts(i, role):
        return np.array([terms[i].acts_on(r) for r in role], dtype=bool)

    def axis_cols(i):
        """The tool axis of each of term i's state columns within a knot."""
        return np.array(["xyz".index(a) for a in terms[i].effect.axes], dtype=np.int64)

    ori = data.oriented
    if ori.any():
        # an oriented station says w = its residual on each acted-on axis (H = I)
        d = data.subset(ori)
        g_t, b_t = model.true_vectors(d)
        h_g, h_b = model.forward(d, g_t, b_t)
        res = {"acc": d.g - h_g, "mag": d.b - h_b}
        sig = {"acc": d.g_sigma, "mag": d.b_sigma}
        ks = kidx[ori]
        for i, t in enumerate(terms):
            s = t.effect.sensor
            n = np.flatnonzero(acts(i, d.role))
            ax = axis_cols(i)
            c = offset[i] + ks[n][:, None] * n_ax[i] + np.arange(n_ax[i])[None, :]
            sg = sig[s][n][:, ax]
            block(np.arange(c.size), c.ravel(), (1.0 / sg).ravel(), (res[s][n][:, ax] / sg).ravel())
    if (~ori).any():
        d = data.subset(~ori)
        g, b = model.correct(d)
        sg, sb, sdip = _free_sigmas(d, model)
        gn, bn = np.linalg.norm(g, axis=1), np.linalg.norm(b, axis=1)
        gh, bh = g / gn[:, None], b / bn[:, None]
        sin_d = np.clip(np.sum(gh * bh, axis=1), -1, 1)
        cos_d = np.sqrt(1 - sin_d ** 2)
        e_g = gn - model.site.gravity_mps2
        e_b = bn - model.site.total_field_nt
        e_dip = np.degrees(np.arcsin(sin_d)) - model.dip_deg
        ks = kidx[~ori]
        # ∂(invariant)/∂w per sensor, (stations, 3) each (see the module docstring)
        zero = np.zeros_like(gh)
        jacs = (({"acc": -gh, "mag": zero}, e_g, sg),
                ({"acc": zero, "mag": -bh}, e_b, sb),
                ({"mag": -np.degrees((gh - sin_d[:, None] * bh) / bn[:, None] / cos_d[:, None]),
                  "acc": -np.degrees((bh - sin_d[:, None] * gh) / gn[:, None] / cos_d[:, None])}, e_dip, sdip))
        # per station and invariant one row over every term's acted-on axes (those with a
        # derivative); a row with none is left out
        c_all = np.concatenate([offset[i] + ks[:, None] * n_ax[i] + np.arange(n_ax[i])[None, :]
                                for i in range(len(terms))], axis=1)
        for jac, e, s_ in jacs:
            v_all = np.concatenate([np.where(acts(i, d.role)[:, None], jac[t.effect.sensor][:, axis_cols(i)], 0.0)
                                    for i, t in enumerate(terms)], axis=1) / s_[:, None]
            nz = v_all != 0
            keep = nz.any(axis=1)
            r = np.cumsum(keep) - 1
            rr, cc = np.nonzero(nz)
            block(r[rr], c_all[rr, cc], v_all[rr, cc], (-e / s_)[keep])
    n_data = n_row
    # the random-walk prior between consecutive knots, and the gauge (the path's mean at zero)
    dt = np.diff(knots)
    span = max(float(knots[-1] - knots[0]), 1.0)
    prior_rows = []
    for i, t in enumerate(terms):
        first = n_row
        dens = np.asarray(t.effect.values["density"], dtype=float)
        for j in range(n_ax[i]):
            col = offset[i] + np.arange(nk) * n_ax[i] + j
            if dens[j] <= 0:           # no wander on this axis: held at zero
                block(np.arange(nk), col, np.full(nk, 1.0 / GAUGE), np.zeros(nk))
                continue
            w = 1.0 / (dens[j] * np.sqrt(dt))
            k = np.arange(nk - 1)
            block(np.repeat(k, 2), np.column_stack([col[1:], col[:-1]]).ravel(), np.column_stack([w, -w]).ravel(),
                  np.zeros(nk - 1))
            block(np.zeros(nk, dtype=np.int64), col, np.full(nk, 1.0 / (nk * GAUGE * dens[j] * np.sqrt(span))), [0.0])
        prior_rows.append(slice(first, n_row))
    # here: scipy.sparse is 0.1 s of every process importing the lab
    from scipy import sparse

    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    a = sparse.csr_matrix((vals, (rows, cols)), shape=(n_row, n_state))
    rhs = np.concatenate(rhs)
    normal = a.T @ a
    atb = a.T @ rhs
    # the posterior σ of the path and the effective degrees of freedom per axis
    std = np.full(n_state, np.nan)
    edf = np.full(n_state, np.nan)
    factor = _cholesky(normal, atb) if n_state <= DENSE_STATES else None
    if factor is not None:
        c, x = factor
    else:
        from scipy.sparse.linalg import spsolve
        x = spsolve(normal.tocsc(), atb)
    r_prior = a @ x - rhs          # each term's roughness penalty: its prior rows' χ²
    change = 0.0
    for i, t in enumerate(terms):
        e = t.effect
        blk = slice(offset[i], offset[i + 1])
        e.knots_s = knots.copy()
        e.path = x[blk].reshape(nk, n_ax[i])
        e.penalty = float(np.sum(r_prior[prior_rows[i]] ** 2))
        k0, p0 = old[i]
        if len(k0):
            prev = np.column_stack([np.interp(knots, k0, p0[:, j]) for j in range(n_ax[i])])
            scale = np.asarray(e.values["density"]) * np.sqrt(max(span / nk, 1e-9))
            scale = np.where(scale > 0, scale, 1.0)
            change = max(change, float(np.max(np.abs(e.path - prev) / scale)))
        else:
            change = float("inf")
    if factor is not None and (posterior_below is None or change < posterior_below):
        std, edf = _posterior(c, a, n_data)
    for i, t in enumerate(terms):
        blk = slice(offset[i], offset[i + 1])
        t.effect.path_std = std[blk].reshape(nk, n_ax[i])
        t.effect.edf = edf[blk].reshape(nk, n_ax[i]).sum(axis=0)
    return change


def _cholesky(normal, atb):
    """``(factor, path)``: the dense Cholesky factor of the normal matrix ``normal`` (``AᵀA``,
    sparse) and the path ``N⁻¹·Aᵀb`` from it; None when ``normal`` is not numerically positive
    definite (the caller solves it sparsely, without σ)."""
    from scipy.linalg import lapack

    c, info = lapack.dpotrf(normal.toarray(), lower=True, clean=False, overwrite_a=True)
    if info != 0:
        return None
    x, info = lapack.dpotrs(c, atb, lower=True)
    return None if info else (c, x)


def _posterior(c, a, n_data: int):
    """``(σ, edf)`` per state from the Cholesky factor ``c`` of ``N``: the posterior σ
    ``√diag(N⁻¹)`` and the effective degrees of freedom ``(N⁻¹·AdᵀAd)ᵢᵢ`` (``Ad`` the first
    ``n_data`` rows of ``a``, the data's; only the entries of ``AdᵀAd`` that are not zero are
    needed).  NaN when the inverse cannot be formed."""
    from scipy.linalg import lapack

    n = c.shape[0]
    cov, info = lapack.dpotri(c, lower=True)
    if info:
        return np.full(n, np.nan), np.full(n, np.nan)
    ad = a[:n_data]
    data_info = (ad.T @ ad).tocoo()
    # N⁻¹ is symmetric: its lower triangle (what potri gives) serves every entry
    r, k = np.maximum(data_info.row, data_info.col), np.minimum(data_info.row, data_info.col)
    edf = np.bincount(data_info.row, weights=cov[r, k] * data_info.data, minlength=n)
    return np.sqrt(np.maximum(np.diag(cov), 0.0)), edf


def penalty_total(model) -> float:
    """The stochastic effects' roughness penalties (the prior's χ², added to the data's χ² for a
    likelihood ratio between penalised fits)."""
    return float(sum(t.effect.penalty for t in stochastic_terms(model)))


def edf_total(model) -> float:
    """The stochastic effects' effective degrees of freedom (0 without any, or before a fit)."""
    return float(sum(np.nansum(t.effect.edf) for t in stochastic_terms(model)))

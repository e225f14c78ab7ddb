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


def smooth(model, data) -> float:
    """Estimate the paths of ``model``'s stochastic effects from ``data`` (in place); the other
    parameters are held.  Returns the largest change of a path, in units of its density over the
    mean station spacing (0 when the model has no stochastic effect)."""
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
    rows, cols, vals, rhs = [], [], [], []
    n_row = [0]

    def add(row_cols, row_vals, b):
        rows.extend([n_row[0]] * len(row_cols))
        cols.extend(row_cols)
        vals.extend(row_vals)
        rhs.append(b)
        n_row[0] += 1

    def states(i, station_k):
        """Column of each acted-on axis of term i at knot ``station_k``, as {tool axis: column}."""
        e = terms[i].effect
        return {"xyz".index(a): int(offset[i] + station_k * n_ax[i] + j) for j, a in enumerate(e.axes)}

    def acts(i, role):
        return terms[i].acts_on(role)

    ori = data.oriented
    if ori.any():
        d = data.subset(ori)
        g_t, b_t = model.true_vectors(d)
        h_g, h_b = model.forward(d, g_t, b_t)
        res = {"acc": d.g - h_g, "mag": d.b - h_b}
        sig = {"acc": d.g_sigma, "mag": d.b_sigma}
        ks = kidx[ori]
        for i, t in enumerate(terms):
            s = t.effect.sensor
            for n in range(len(d)):
                if not acts(i, d.role[n]):
                    continue
                for ax, c in states(i, ks[n]).items():
                    add([c], [1.0 / sig[s][n, ax]], res[s][n, ax] / sig[s][n, ax])
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
        for n in range(len(d)):
            # ∂(invariant)/∂w per sensor (3,), see the module docstring
            dg = {"acc": -gh[n], "mag": np.zeros(3)}
            db = {"acc": np.zeros(3), "mag": -bh[n]}
            ddip = {"mag": -np.degrees((gh[n] - sin_d[n] * bh[n]) / bn[n] / cos_d[n]),
                    "acc": -np.degrees((bh[n] - sin_d[n] * gh[n]) / gn[n] / cos_d[n])}
            for jac, e, s_ in ((dg, e_g[n], sg[n]), (db, e_b[n], sb[n]), (ddip, e_dip[n], sdip[n])):
                c_, v_ = [], []
                for i, t in enumerate(terms):
                    if not acts(i, d.role[n]):
                        continue
                    for ax, c in states(i, ks[n]).items():
                        if jac[t.effect.sensor][ax] != 0:
                            c_.append(c)
                            v_.append(jac[t.effect.sensor][ax] / s_)
                if c_:
                    add(c_, v_, -e / s_)
    n_data = n_row[0]
    # the random-walk prior between consecutive knots, and the gauge (the path's mean at zero)
    dt = np.diff(knots)
    span = max(float(knots[-1] - knots[0]), 1.0)
    prior_rows = []
    for i, t in enumerate(terms):
        first = n_row[0]
        dens = np.asarray(t.effect.values["density"], dtype=float)
        for j in range(n_ax[i]):
            col = offset[i] + np.arange(nk) * n_ax[i] + j
            if dens[j] <= 0:           # no wander on this axis: held at zero
                for c in col:
                    add([int(c)], [1.0 / GAUGE], 0.0)
                continue
            for k in range(nk - 1):
                w = 1.0 / (dens[j] * np.sqrt(dt[k]))
                add([int(col[k + 1]), int(col[k])], [w, -w], 0.0)
            add([int(c) for c in col], [1.0 / (nk * GAUGE * dens[j] * np.sqrt(span))] * nk, 0.0)
        prior_rows.append(slice(first, n_row[0]))
    from scipy import sparse                      # here: scipy.sparse is 0.1 s of every process importing the lab
    from scipy.sparse.linalg import spsolve

    a = sparse.csr_matrix((vals, (rows, cols)), shape=(n_row[0], n_state))
    rhs = np.asarray(rhs)
    normal = (a.T @ a).tocsc()
    x = spsolve(normal, a.T @ rhs)
    # the posterior σ of the path and the effective degrees of freedom per axis
    std = np.full(n_state, np.nan)
    edf = np.full(n_state, np.nan)
    if n_state <= DENSE_STATES:
        cov = np.linalg.inv(normal.toarray())
        ad = a[:n_data]
        info = (ad.T @ ad).toarray()
        std = np.sqrt(np.maximum(np.diag(cov), 0.0))
        edf = np.einsum("ij,ji->i", cov, info)
    r_prior = a @ x - rhs          # each term's roughness penalty: its prior rows' χ²
    change = 0.0
    for i, t in enumerate(terms):
        e = t.effect
        block = slice(offset[i], offset[i + 1])
        e.knots_s = knots.copy()
        e.path = x[block].reshape(nk, n_ax[i])
        e.path_std = std[block].reshape(nk, n_ax[i])
        e.edf = edf[block].reshape(nk, n_ax[i]).sum(axis=0)
        e.penalty = float(np.sum(r_prior[prior_rows[i]] ** 2))
        k0, p0 = old[i]
        if len(k0):
            prev = np.column_stack([np.interp(knots, k0, p0[:, j]) for j in range(n_ax[i])])
            scale = np.asarray(e.values["density"]) * np.sqrt(max(span / nk, 1e-9))
            scale = np.where(scale > 0, scale, 1.0)
            change = max(change, float(np.max(np.abs(e.path - prev) / scale)))
        else:
            change = float("inf")
    return change


def penalty_total(model) -> float:
    """The stochastic effects' roughness penalties (the prior's χ², added to the data's χ² for a
    likelihood ratio between penalised fits)."""
    return float(sum(t.effect.penalty for t in stochastic_terms(model)))


def edf_total(model) -> float:
    """The stochastic effects' effective degrees of freedom (0 without any, or before a fit)."""
    return float(sum(np.nansum(t.effect.edf) for t in stochastic_terms(model)))

"""General least-squares fit: recovery of known parameters, uncertainties, identifiability."""
import numpy as np
import pytest

from inclinometer_calib.core.station import Station, Stations
from inclinometer_calib import lab
from inclinometer_calib.lab.spec import build_model


def test_base_fit_recovers_the_twelve_position_parameters_and_explains_clean_data(sim_factory):
    data, truth, site = sim_factory(21)
    model = lab.LabModel.base(site)
    res = lab.fit(model, data)
    assert res.success
    assert 0.85 < res.z_rms < 1.15  # clean data: residuals at the noise level
    acc = model.base_triad("acc")
    for k, v in truth["probe"]["acc"].items():
        assert acc.parameters()[k] == pytest.approx(v, abs=5e-4 if k.startswith("bias") else 5e-5), k
    i = res.names.index("site.dip_deg")
    assert res.values[i] == pytest.approx(site.dip_deg, abs=5 * res.std[i] + 1e-4)


def test_fitted_effect_parameter_matches_truth_within_its_uncertainty(sim_factory):
    data, truth, site = sim_factory(22, ["axial_interference=300"])
    model = build_model(site, "axial_interference")
    res = lab.fit(model, data)
    i = res.names.index("axial_interference:mag:z.field_z")
    assert abs(res.values[i] - 300.0) < 5 * res.std[i]
    assert 0 < res.std[i] < 5.0
    assert res.z_rms < 1.2


def test_temperature_effect_on_isothermal_data_is_reported_not_identifiable(sim_factory):
    data, truth, site = sim_factory(21)
    cal_only = data.subset(data.role == "cal")  # all at 25 °C
    model = build_model(site, "temperature_bias:mag")
    res = lab.fit(model, cal_only)
    reasons = [n.reason for n in res.not_identifiable if n.parameter.startswith("temperature_bias:mag")]
    assert reasons and "temperature span 0.0 °C is too small" in reasons[0]


def test_interference_on_pose_data_alone_is_not_identifiable(sim_factory):
    data, truth, site = sim_factory(21)
    model = build_model(site, "axial_interference@all")
    res = lab.fit(model, data.subset(data.role == "cal"))
    assert any("indistinguishable from the Z bias" in n.reason for n in res.not_identifiable)
    assert any(n.parameter.startswith("axial_interference") for n in res.not_identifiable)


def test_free_stations_fit_through_the_site_invariants(sim_factory):
    """Stations without orientation constrain the model only through |g|, |B| and dip."""
    data, truth, site = sim_factory(21)
    free = data.subset(data.role == "val")
    free.kind[:] = "free"
    free.rotation[:] = np.nan
    both = Stations.concatenate([data.subset(data.role == "cal"), free])
    res = lab.fit(lab.LabModel.base(site), both)
    assert res.success and res.z_rms < 1.3


def test_model_correction_inverts_the_forward_model(sim_factory):
    data, truth, site = sim_factory(23, ["nonlinearity:mag=2e-3", "temperature_scale:acc=1e-4"])
    model = lab.model_from_truth(truth)
    d = data.subset(data.oriented)
    g_t, b_t = model.true_vectors(d)
    h_g, h_b = model.forward(d, g_t, b_t)
    d.g, d.b = h_g, h_b
    g, b = model.correct(d)
    np.testing.assert_allclose(g, g_t, atol=1e-9)
    np.testing.assert_allclose(b, b_t, atol=1e-6)


def test_free_log_without_labels_is_segmented_and_fitted_through_the_invariants(tmp_path, sim_factory):
    """A hand-turned log: labels dropped, static intervals found by the detector."""
    import numpy as np

    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.io.probelog import write_csv

    data, truth, site = sim_factory(21)
    probe = sim.build_probe(21)
    rng = np.random.default_rng(5)
    attitudes = [Station.planned(sim.orientation_matrix(*rng.uniform([0, 0, 0], [180, 360, 360])), 2.0)
                 for _ in range(40)]
    log = sim.run_session(probe, site, attitudes, rng)
    log.pose[:] = 0
    write_csv(tmp_path / "free.csv", log)
    both = lab.load_logs(free_paths=[tmp_path / "free.csv"])
    assert 35 <= len(both) <= 40 and set(both.kind) == {"free"}
    # the free log alone fixes the triads up to a common rotation; with the poses it fits to the noise
    res = lab.fit(lab.LabModel.base(site), Stations.concatenate([data.subset(data.role == "cal"), both]))
    assert res.success and res.z_rms < 1.3


def test_the_per_triad_cache_gives_the_residuals_of_a_full_evaluation_bit_for_bit(sim_factory):
    """A finite-difference step in one triad's parameter takes the other triad's outputs from the
    cache (calibrate.fit.ResidualCache): every residual must be the bits of a full evaluation, for steps
    in acc, mag and shared parameters, on oriented and free stations, before and after a step."""
    import copy

    from inclinometer_calib.calibrate.fit import ResidualCache, residual_vector

    data, _, site = sim_factory(22, ["axial_interference=300"])
    data = copy.deepcopy(data)
    data.kind[data.role == "val"] = "free"          # the survey's |g|, |B| and dip only
    model = build_model(site, "axial_interference,temperature_bias:acc")
    cache = ResidualCache(model, data)
    x0 = model.get_vector() + 1e-4 * model.param_scale()
    names = model.param_names()
    steps = [x0]
    for name in ("scale:acc:xyz.k_x", "temperature_bias:acc:xyz.c_y", "axial_interference:mag:z.field_z",
                 "bias:mag:xyz.b_z", "site.dip_deg"):
        x = x0.copy()
        x[names.index(name)] += 1e-6
        steps += [x, x0]
    x = x0.copy()
    x[[names.index("bias:acc:xyz.b_x"), names.index("bias:mag:xyz.b_x")]] += 1e-6   # an LM step: both
    steps.append(x)
    for x in steps:
        fresh = residual_vector(copy.deepcopy(model), data, x)
        np.testing.assert_array_equal(residual_vector(model, data, x, cache=cache), fresh)


def test_a_candidates_first_jacobian_takes_the_base_fits_columns_where_the_effect_starts_absent(sim_factory):
    """calibrate.fit.JacobianHint: from the base model's solution, a candidate effect at its start values
    leaves the residuals as they were, so the base fit's derivatives are the candidate's for the
    parameters they share — equal to the evaluated columns (to the finite difference's resolution;
    the base fit's last Jacobian may be one step behind its solution) and only the new columns are
    evaluated; a candidate that does not start absent takes none."""
    import copy

    from inclinometer_calib.calibrate import fit as fitmod
    from inclinometer_calib.calibrate.fit import ResidualCache, forward_jacobian, residual_vector
    from inclinometer_calib.lab.diagnose import fit_data

    data, _, site = sim_factory(22, ["axial_interference=300"])
    fd = fit_data(data)
    base = lab.LabModel.base(site)
    assert lab.fit(copy.deepcopy(base), fd).hint is None          # kept only when asked for
    hint = lab.fit(base, fd, give_hint=True).hint
    assert hint is not None and hint.jac.shape == (len(hint.r_data), len(hint.names))
    trial = base.with_effect(lab.effect("axial_interference", "mag", "z"), "val")
    x = trial.get_vector()
    free = np.ones(len(x), bool)
    cache = ResidualCache(trial, fd)
    n_data = len(residual_vector(trial, fd, x, prior=False, cache=cache))

    def fun(v):
        return residual_vector(trial, fd, v, cache=cache)

    def prior_at(v):
        trial.set_vector(v)
        return fitmod._prior_residual(trial, cache)

    known = hint.columns(trial, free, x, n_data)
    r = fun(x)
    hinted, evaluations = forward_jacobian(fun, x, r, trial.param_scale(), lambda r_, x_, h: known(r_, x_, h, prior_at))
    full, all_evaluations = forward_jacobian(fun, x, r, trial.param_scale())
    new = [i for i, n in enumerate(trial.param_names()) if n not in hint.names]
    assert evaluations == len(new) == 1 and all_evaluations == len(x)
    scale = np.abs(full).max(axis=0) + 1e-300
    assert np.max(np.abs(hinted - full) / scale) < 1e-4
    # a candidate that starts present (its field at 300 nT) is not at the base solution's residuals
    present = copy.deepcopy(trial)
    v = x.copy()
    v[new[0]] = 300.0
    present.set_vector(v)
    cache2 = ResidualCache(present, fd)
    known2 = hint.columns(present, free, v, n_data)
    r2 = residual_vector(present, fd, v, cache=cache2)
    assert known2(r2, v, np.full(len(v), 1e-6), prior_at) == {}
    # nor one whose shared parameters are not at the solution
    moved = x.copy()
    moved[0] += 1e-3 * trial.param_scale()[0]
    assert hint.columns(trial, free, moved, n_data) is None


@pytest.mark.parametrize("effects", ["", "axial_interference,temperature_bias:acc",
                                     "nonlinearity:mag,cross_coupling,bias_drift:mag,temperature_scale:acc,scale_asymmetry:mag"])
def test_a_triads_steps_evaluated_together_give_the_jacobian_of_one_by_one_bit_for_bit(sim_factory, effects):
    """calibrate.fit.residual_rows: the finite-difference steps in one triad's own parameters are
    evaluated at once (the effects holding a row of values per station, the base triad's correction
    per row); the Jacobian must be the bits of the steps taken one by one, on oriented and on free
    stations, with effects at every stage — and a step that took the wrong triad, axis or row would
    change it."""
    import copy

    from inclinometer_calib.calibrate import fit as F

    data, _, site = sim_factory(22, ["axial_interference=300"])
    for survey_free in (False, True):
        d = copy.deepcopy(data)
        if survey_free:
            d.kind[d.role == "val"] = "free"       # the survey's |g|, |B| and dip only
        model = build_model(site, effects) if effects else lab.LabModel.base(site)
        cache = F.ResidualCache(model, d)
        sensors = F._rows_sensors(model, cache, stochastic=False)
        assert sensors == ("acc", "mag")
        x = model.get_vector() + 1e-4 * model.param_scale()

        def fun(v):
            return F.residual_vector(model, d, v, cache=cache)

        def batch(xx, h, columns):
            out = {}
            for s in sensors:
                js = [j for j in columns if j in set(cache.own[s].tolist())]
                v = np.repeat(xx[None], len(js), axis=0)
                v[np.arange(len(js)), js] = xx[js] + h[js]
                out.update(zip(js, F.residual_rows(model, d, cache, xx, v, s)))
            return out
        one_by_one, n1 = F.forward_jacobian(fun, x, fun(x), model.param_scale())
        together, n2 = F.forward_jacobian(fun, x, fun(x), model.param_scale(), batch=batch)
        np.testing.assert_array_equal(together, one_by_one)
        assert n1 == n2 == len(x)
        batch(x, np.full(len(x), 1e-6), list(range(len(x))))
        np.testing.assert_array_equal(model.get_vector(), x)          # the model left where it was


def test_effects_that_need_the_history_or_say_nothing_of_rows_step_one_by_one(sim_factory):
    """Only an effect class that says its ``_apply`` takes rows of values (effects.takes_rows, not
    inherited: a subclass may change ``_apply``) has its triad's steps evaluated together; a model
    whose effects need the history of holds steps one by one."""
    from inclinometer_calib.calibrate import fit as F
    from inclinometer_calib.core import effects as fx

    class MyBias(fx.Bias):
        def _apply(self, v, ctx):
            v[:, self._cols()] += float(self.values["b"][0])

    assert fx.takes_rows(fx.Bias(sensor="mag")) and not fx.takes_rows(MyBias(sensor="mag"))
    data, _, site = sim_factory(22, ["axial_interference=300"])
    lagged = build_model(site, "thermal_lag:mag,temperature_bias:mag")
    assert F._rows_sensors(lagged, F.ResidualCache(lagged, data), stochastic=False) == ()
    plain = build_model(site, "axial_interference")
    assert F._rows_sensors(plain, F.ResidualCache(plain, data), stochastic=True) == ()


@pytest.mark.parametrize("effects", ["", "axial_interference,temperature_bias:mag"])
def test_levenberg_marquardt_on_the_triads_steps_together_is_scipys_two_point_fit_bit_for_bit(sim_factory, monkeypatch,
                                                                                             effects):
    """When Gauss–Newton gives up, the fit falls back to MINPACK's Levenberg–Marquardt; its
    Jacobian (fit's ``lm_jacobian``: scipy's 2-point step and arithmetic, a triad's steps evaluated
    together) must leave the solution, the evaluations and the uncertainties of ``jac="2-point"``
    unchanged, bit for bit — a step of another size or sign would move them."""
    from inclinometer_calib.calibrate import fit as F

    data, _, site = sim_factory(22, ["axial_interference=300"])
    monkeypatch.setattr(F, "gauss_newton", lambda *a, **k: None)     # Levenberg–Marquardt throughout
    results = []
    for together in (True, False):
        if not together:   # no triad stepped together: fit passes jac="2-point" to scipy
            monkeypatch.setattr(F, "_rows_sensors", lambda *a, **k: ())
        model = build_model(site, effects) if effects else lab.LabModel.base(site)
        results.append(F.fit(model, data))
    a, b = results
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.std, b.std)
    assert (a.nfev, a.message, a.chi2) == (b.nfev, b.message, b.chi2)

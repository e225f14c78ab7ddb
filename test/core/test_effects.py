"""Effect catalogue: each effect's forward function against its formula; composition order."""
import numpy as np
import pytest

from inclinometer_calib.core import effects as fx

CTX = fx.Context(temperature_c=np.array([25.0, 35.0, 5.0]), time_s=np.array([0.0, 1800.0, 3600.0]))
V = np.array([[1.0, -2.0, 9.0], [-3.0, 4.0, -5.0], [0.5, 0.25, -9.5]])


def test_catalogue_has_the_required_names():
    need = {"bias", "scale", "nonorthogonality", "misalignment", "triad_misalignment", "temperature_bias",
            "temperature_scale", "scale_asymmetry", "nonlinearity", "cross_coupling", "bias_drift",
            "axial_interference"}
    assert need <= set(fx.CATALOGUE)


def test_each_effect_names_units_and_typical_magnitudes():
    for name, cls in fx.CATALOGUE.items():
        for sensor in cls.sensors:
            e = cls(sensor=sensor, axes=cls.default_axes)
            assert len(e.param_names()) == e.n_params == len(e.param_units()) == len(e.param_typical())
            assert all(u for u in e.param_units())


def test_temperature_bias_formula():
    e = fx.make_effect("temperature_bias", "acc", "xz", c=[0.01, -0.02])
    out = e.apply(V, CTX)
    dt = CTX.temperature_c - 25.0
    np.testing.assert_allclose(out[:, 0], V[:, 0] + 0.01 * dt)
    np.testing.assert_allclose(out[:, 2], V[:, 2] - 0.02 * dt)
    np.testing.assert_array_equal(out[:, 1], V[:, 1])


def test_scale_asymmetry_differs_for_positive_and_negative_input():
    e = fx.make_effect("scale_asymmetry", "acc", "x", a=0.01)
    out = e.apply(V, CTX)
    np.testing.assert_allclose(out[:, 0], [1.01, -3 * 0.99, 0.5 * 1.01])


def test_nonlinearity_quadratic_and_cubic_at_full_scale():
    e = fx.make_effect("nonlinearity", "mag", "y", q=1e-3, c=2e-3)
    v = np.array([[0.0, 50000.0, 0.0], [0.0, -25000.0, 0.0]])
    out = e.apply(v, CTX)
    np.testing.assert_allclose(out[:, 1], [50000 + 50 + 100, -25000 + 50000 * (1e-3 * 0.25 - 2e-3 * 0.125)])


def test_cross_coupling_uses_the_ieee_products():
    e = fx.make_effect("cross_coupling", "acc", "z", k_ij=0.01, k_ik=0.02, k_jk=0.03)
    out = e.apply(V, CTX)
    x, y, z = V.T
    np.testing.assert_allclose(out[:, 2], z + (0.01 * z * x + 0.02 * z * y + 0.03 * x * y) / 9.80665)


def test_cross_coupling_on_all_axes_gives_each_axis_the_bits_it_gets_alone():
    rng = np.random.default_rng(2)
    v = rng.normal(size=(40, 3)) * 9.8
    k = {n: rng.normal(size=3) * 1e-3 for n in ("k_ij", "k_ik", "k_jk")}
    together = fx.make_effect("cross_coupling", "acc", "xyz", **k).apply(v, CTX)
    for i, a in enumerate("xyz"):
        alone = fx.make_effect("cross_coupling", "acc", a, **{n: k[n][i] for n in k}).apply(v, CTX)
        assert np.array_equal(together[:, i], alone[:, i])


def test_bias_drift_is_per_hour():
    e = fx.make_effect("bias_drift", "mag", "x", rate=60.0)
    np.testing.assert_allclose(e.apply(V, CTX)[:, 0] - V[:, 0], [0, 30, 60])


def test_misalignment_is_a_rotation_preserving_norm():
    e = fx.make_effect("misalignment", "mag", "xyz", angle=[0.01, -0.02, 0.03])
    np.testing.assert_allclose(np.linalg.norm(e.apply(V, CTX), axis=1), np.linalg.norm(V, axis=1))


def test_nonorthogonality_matches_the_papers_e_matrix():
    from inclinometer_calib.core.errormodel import TriadModel
    e = fx.make_effect("nonorthogonality", "mag", "xyz", e1=[0.01, 0.02, 0.03], e2=[0.04, 0.05, 0.06])
    m = TriadModel(e={"e_yx": 0.01, "e_zx": 0.04, "e_xy": 0.02, "e_zy": 0.05, "e_xz": 0.03, "e_yz": 0.06})
    np.testing.assert_allclose(e.apply(V, CTX), V @ m.E.T)


def test_chain_applies_stages_in_physical_order():
    # bias (output stage) listed first must still be added after scale (gain stage)
    chain = [fx.make_effect("bias", "acc", "x", b=1.0), fx.make_effect("scale", "acc", "x", k=1.0)]
    out = fx.apply_chain(np.array([[2.0, 0, 0]]), chain, fx.Context(np.array([25.0]), np.array([0.0])))
    assert out[0, 0] == 2.0 * 2 + 1


def test_parameter_vector_round_trip():
    e = fx.make_effect("nonlinearity", "acc", "xy", q=[1, 2], c=[3, 4])
    assert list(e.get_vector()) == [1, 2, 3, 4]
    e.set_vector([5, 6, 7, 8])
    assert list(e.values["c"]) == [7, 8]


def test_register_refuses_a_name_collision():
    class Clash(fx.Effect):
        name = "bias"
        stage = "output"
    with pytest.raises(ValueError, match="already taken"):
        fx.register(Clash)


def test_the_stand_and_heading_options_are_taken_out_of_an_effect_list_and_refuse_values():
    """What the lab recommends is accepted verbatim: stand_pose_error and heading_offset are options
    of the lab's fit, not a triad's effects (effects.split_model_options)."""
    rest, options = fx.split_model_options("temperature_bias:mag=1,2,3, stand_pose_error,heading_offset")
    assert options == {"fit_poses": True, "fit_heading": True}
    assert [s.name for s in fx.parse_effects(rest)] == ["temperature_bias"]
    assert list(fx.parse_effects(rest)[0].values) == [1.0, 2.0, 3.0]
    for bad in ("stand_pose_error=0.2", "stand_pose_error:acc", "heading_offset@val", "heading_offset,0.5"):
        with pytest.raises(ValueError):
            fx.split_model_options(bad)
    assert fx.split_model_options(None) == (None, {})


def test_a_temperature_felt_late_skips_an_unknown_temperature_and_goes_on():
    """A station without a temperature is NaN, the ones after it still feel the known ones (a NaN
    carried forward once turned every later station NaN)."""
    import numpy as np

    from inclinometer_calib.core import effects as fx

    t = np.array([0.0, 10.0, 20.0, 30.0, 40.0])
    temp = np.array([20.0, np.nan, 24.0, 26.0, 28.0])
    felt = fx.felt_temperature(t, temp, 15.0)
    assert np.isnan(felt[1]) and np.all(np.isfinite(felt[[0, 2, 3, 4]]))
    ref = fx.felt_temperature(t[[0, 2, 3, 4]], temp[[0, 2, 3, 4]], 15.0)
    np.testing.assert_allclose(felt[[0, 2, 3, 4]], ref)
    assert 20.0 < felt[4] < 28.0                  # it lags the logged temperature


def test_a_magnetometer_effect_that_needs_the_sequence_never_stops_the_accelerometer_stream():
    import numpy as np

    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core.model import ModelContextError, ProbeModel

    model = ProbeModel.base().with_effect(fx.TemperatureBias(sensor="acc", values={"c": 1e-4}), "all") \
        .with_effect(fx.Settling(sensor="mag", values={"h": 1e-3}), "all")
    plan = model.plan("val") if hasattr(model, "plan") else __import__("inclinometer_calib.core.model", fromlist=["x"]) \
        .CorrectionPlan(model, "val")
    g = plan.correct_sample("acc", (0.1, 0.2, 9.8), 30.0, 5.0)
    assert all(np.isfinite(g))
    with pytest.raises(ModelContextError, match="history"):
        plan.correct_sample("mag", (20000.0, 0.0, 40000.0), 30.0, 5.0)

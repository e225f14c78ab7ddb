"""Short-collar axial-interference correction against simulated truth."""
import numpy as np
import pytest

from inclinometer_calib.correct import axial
from inclinometer_calib.core.frames import Site, azimuth_deg, tool_vectors, wrap180

SITE = Site(total_field_nt=50000.0, dip_deg=60.0)


def _grid():
    i, a = np.meshgrid([5.0, 20.0, 45.0, 70.0, 90.0], np.arange(0, 360, 15.0))
    return i.ravel(), a.ravel(), np.full(i.size, 30.0)


def test_recovers_the_axial_field_and_the_azimuth_where_not_degenerate():
    i, a, t = _grid()
    g, b = tool_vectors(SITE, i, a, t)
    b_dirty = b + np.array([0.0, 0.0, 400.0])
    raw_err = np.abs(wrap180(azimuth_deg(g, b_dirty) - a))
    out = axial.correct(g, b_dirty, SITE)
    ok = ~out["degenerate"]
    assert ok.mean() > 0.6
    np.testing.assert_allclose(out["axial_field_nt"][ok], 400.0, atol=1e-3)
    err = np.abs(wrap180(out["azimuth_deg"] - a))
    assert err[ok].max() < 1e-4
    assert raw_err[ok].max() > 0.3  # the interference was there to remove


def test_degenerate_stations_are_the_high_inclination_east_west_ones():
    i, a, t = _grid()
    g, b = tool_vectors(SITE, i, a, t)
    out = axial.correct(g, b + [0, 0, 400.0], SITE)
    deg = out["degenerate"]
    assert deg.any()
    assert np.all(i[deg] >= 45.0)
    assert np.all(np.abs(np.sin(np.radians(a[deg]))) > 0.7)  # near east or west
    # the uncertainty grows towards east-west at high inclination
    sel = (i == 90.0)
    assert out["azimuth_sigma_deg"][sel & (a == 90.0)][0] > 10 * out["azimuth_sigma_deg"][sel & (a == 0.0)][0]


def test_measurement_noise_propagates_into_a_bounded_error():
    rng = np.random.default_rng(3)
    i, a, t = _grid()
    g, b = tool_vectors(SITE, i, a, t)
    noise = rng.normal(0, 20.0, b.shape)
    out = axial.correct(g, b + [0, 0, 250.0] + noise, SITE)
    ok = ~out["degenerate"]
    err = np.abs(wrap180(out["azimuth_deg"] - a))[ok]
    # the error a perfect interference removal would leave: the noise alone, on clean data
    noise_only = np.abs(wrap180(azimuth_deg(g, b + noise) - a))[ok]
    # the correction adds at most ~3σ of its propagated uncertainty (σ_B = 50 nT covers the noise)
    assert np.mean(err <= noise_only + 3 * out["azimuth_sigma_deg"][ok] + 1e-3) > 0.95
    assert np.median(err) < 0.2


def test_declination_is_added():
    site = Site(total_field_nt=50000.0, dip_deg=60.0, declination_deg=-4.0)
    g, b = tool_vectors(site, 30.0, 100.0, 0.0)
    out = axial.correct(g, b, site)
    assert out["azimuth_deg"][0] == pytest.approx(100.0, abs=1e-6)


def test_the_short_collar_azimuth_is_reported_in_every_reference():
    # magnetic and grid are the corrected azimuth's too, not the measured field's
    site = Site(total_field_nt=50000.0, dip_deg=60.0, declination_deg=-4.0,
                reference={"grid_convergence_deg": 1.5, "crs": "EPSG:23031"})
    g, b = tool_vectors(site, 30.0, 100.0, 0.0)
    b = b + 400.0 * np.array([0.0, 0.0, 1.0])          # axial drill-string field
    res = axial.evaluate_with_axial(g[None], b[None], site)
    assert res["azimuth_method"][0] == "short_collar"
    assert res["azimuth_deg"][0] == pytest.approx(100.0, abs=1e-4)          # the simulated truth
    assert res["azimuth_magnetic_deg"][0] == pytest.approx(104.0, abs=1e-4)
    assert res["azimuth_grid_deg"][0] == pytest.approx(98.5, abs=1e-4)

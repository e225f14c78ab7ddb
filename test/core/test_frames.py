"""Angles from sensor vectors against rotations built from known angles (frames module)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from inclinometer_calib.core import frames as F

SITE = F.Site(total_field_nt=48000.0, dip_deg=58.0, declination_deg=0.0)


def test_orientation_matrix_is_rz_ry_rz_tool_to_ned():
    r = F.orientation_matrix(90.0, 90.0, 0.0)
    # drift 90 towards east: tool Z (down-hole) points east, tool X (high side) points up
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)


def test_rep145_conversion_is_negation_both_ways():
    f = np.array([0.1, -0.2, -9.8])
    np.testing.assert_array_equal(F.gravity_from_specific_force(f), -f)
    np.testing.assert_array_equal(F.specific_force_from_gravity(F.gravity_from_specific_force(f)), f)


angles = st.tuples(st.floats(0.01, 179.99), st.floats(0, 359.999), st.floats(0, 359.999))


@settings(max_examples=300, deadline=None)
@given(angles)
def test_drift_azimuth_gravity_toolface_round_trip(a):
    i, az, tf = a
    g, b = F.tool_vectors(SITE, i, az, tf)
    assert F.drift_deg(g) == pytest.approx(i, abs=1e-8)
    assert abs(F.wrap180(F.azimuth_deg(g, b) - az)) < 1e-6 / max(np.sin(np.radians(i)), 1e-3)
    assert abs(F.wrap180(F.gravity_toolface_deg(g) - tf)) < 1e-6 / max(np.sin(np.radians(i)), 1e-3)
    assert F.dip_deg(g, b) == pytest.approx(SITE.dip_deg, abs=1e-9)
    assert F.total_field(b) == pytest.approx(SITE.total_field_nt)
    assert F.total_gravity(g) == pytest.approx(SITE.gravity_mps2)


@pytest.mark.parametrize("drift", [1e-4, 0.01, 0.1])
@pytest.mark.parametrize("azimuth", [0.0, 45.0, 137.0, 270.0, 359.5])
def test_near_vertical_azimuth_still_exact_without_noise_and_flagged_undefined(drift, azimuth):
    g, b = F.tool_vectors(SITE, drift, azimuth, 33.0)
    assert abs(F.wrap180(F.azimuth_deg(g, b) - azimuth)) < 1e-4
    assert not F.azimuth_defined(g)


@pytest.mark.parametrize("azimuth", [0.0, 89.0, 90.0, 180.0, 271.0])
@pytest.mark.parametrize("toolface", [0.0, 90.0, 200.0])
def test_horizontal_tool_gives_drift_90_and_exact_azimuth(azimuth, toolface):
    g, b = F.tool_vectors(SITE, 90.0, azimuth, toolface)
    assert F.drift_deg(g) == pytest.approx(90.0, abs=1e-10)
    assert abs(F.wrap180(F.azimuth_deg(g, b) - azimuth)) < 1e-9


def test_azimuth_range_is_0_to_360():
    g, b = F.tool_vectors(SITE, np.full(720, 30.0), np.linspace(0, 359.5, 720), 10.0)
    a = F.azimuth_deg(g, b)
    assert a.min() >= 0 and a.max() < 360


def test_magnetic_toolface_equals_azimuth_plus_gravity_toolface_for_vertical_tool():
    g, b = F.tool_vectors(SITE, 0.0, 40.0, 25.0)
    assert F.magnetic_toolface_deg(b) == pytest.approx(65.0)


def test_paper_eq2_as_printed_gives_the_same_ratio():
    """Eq. 2 printed as arctan(num/den): our atan2 form must have the same tangent."""
    g, b = F.tool_vectors(SITE, 37.0, 123.0, 77.0)
    gx, gy, gz = g
    hx, hy, hz = b
    num = np.linalg.norm(g) * (hx * gy - hy * gx)
    den = gz * (hx * gx + hy * gy) - hz * (gx ** 2 + gy ** 2)
    assert np.tan(np.radians(F.azimuth_deg(g, b))) == pytest.approx(num / den, rel=1e-9)


def test_declination_rotates_the_field_east():
    s = F.Site(declination_deg=10.0)
    n, e, d = s.field_ned()
    assert np.degrees(np.arctan2(e, n)) == pytest.approx(10.0)

"""The trajectory by minimum curvature (:mod:`inclinometer_calib.correct.trajectory`) against a vendor's
published wellpath report, wellpathpy and welleng, and against circular arcs worked by hand."""
import csv
import importlib.resources
import io
import math

import numpy as np
import pytest

from inclinometer_calib.correct.trajectory import minimum_curvature, ratio_factor


def _reference_well():
    """The wellpath report shipped with wellpathpy (a real well: MD, Inc, Azi, TVD, North, East,
    Dogleg deg/30 m, to 0.01; "Calculation method uses Minimum Curvature method")."""
    wp = pytest.importorskip("wellpathpy")
    text = (importlib.resources.files(wp) / "test" / "fixtures" / "Well_Surveys_Projected_to_TD.csv").read_text()
    rows = []
    for r in csv.reader(io.StringIO(text)):
        try:
            rows.append([float(x) for x in r[1:7]] + [float(r[7]) if r[7] else float("nan")])
        except (ValueError, IndexError):
            continue
    return np.array(rows)


def test_the_published_wellpath_report_is_reproduced():
    ref = _reference_well()
    assert len(ref) == 80
    t = minimum_curvature(ref[:, 0], ref[:, 1], ref[:, 2])
    # the report's values are rounded to 0.01 m and 0.01 deg/30 m; its last two rows are projections
    # to TD whose printed angles do not give their printed doglegs (0.2-0.3 deg/30 m off): they
    # agree to 0.05 m only
    sur = slice(0, 78)
    np.testing.assert_allclose(t.tvd[sur], ref[sur, 3], atol=0.006)
    np.testing.assert_allclose(t.north[sur], ref[sur, 4], atol=0.006)
    np.testing.assert_allclose(t.east[sur], ref[sur, 5], atol=0.006)
    np.testing.assert_allclose(t.dls[1:78], ref[1:78, 6], atol=0.006)
    for col, ours in ((3, t.tvd), (4, t.north), (5, t.east)):
        np.testing.assert_allclose(ours[78:], ref[78:, col], atol=0.05)


def test_wellpathpy_and_welleng_give_the_same_positions():
    ref = _reference_well()
    md, inc, azi = ref[:, 0], ref[:, 1], ref[:, 2]
    ours = minimum_curvature(md, inc, azi)
    from wellpathpy.mincurve import minimum_curvature as wp_mc

    tvd, north, east, dls = wp_mc(md, inc, azi, course_length=30)
    np.testing.assert_allclose(ours.tvd, tvd, atol=1e-9)
    np.testing.assert_allclose(ours.north, north, atol=1e-9)
    np.testing.assert_allclose(ours.east, east, atol=1e-9)
    np.testing.assert_allclose(ours.dls, dls, atol=1e-9)
    we = pytest.importorskip("welleng")
    s = we.survey.Survey(md=md, inc=inc, azi=azi, start_nev=[0.0, 0.0, 0.0], deg=True, unit="meters")
    np.testing.assert_allclose(ours.north, s.n, atol=1e-6)
    np.testing.assert_allclose(ours.east, s.e, atol=1e-6)
    np.testing.assert_allclose(ours.tvd, s.tvd, atol=1e-6)


def test_a_circular_arc_and_a_straight_hold_are_exact():
    # a build from vertical to 90° over a quarter circle of radius R: TVD = R, north = R at the end
    r = 500.0
    md = np.linspace(0.0, math.pi / 2 * r, 19)
    inc = np.degrees(md / r)
    t = minimum_curvature(md, inc, np.full_like(md, 0.0))
    assert t.tvd[-1] == pytest.approx(r, abs=1e-9) and t.north[-1] == pytest.approx(r, abs=1e-9)
    np.testing.assert_allclose(t.dls[1:], 30.0 * 180 / math.pi / r, rtol=1e-12)
    # a straight hold at 60° to azimuth 135: displacement along the tangent exactly
    h = minimum_curvature([100.0, 1100.0], [60.0, 60.0], [135.0, 135.0], tie_in=(95.0, 1.0, -2.0))
    assert h.tvd[-1] == pytest.approx(95.0 + 500.0) and h.dls[-1] == 0.0
    assert h.north[-1] == pytest.approx(1.0 - 1000 * math.sin(math.radians(60)) / math.sqrt(2))
    assert h.east[-1] == pytest.approx(-2.0 + 1000 * math.sin(math.radians(60)) / math.sqrt(2))
    # the ratio factor's series meets the exact form
    assert ratio_factor(np.array([1e-4 * 0.999]))[0] == pytest.approx(2 / 1e-4 * math.tan(1e-4 / 2), rel=1e-11)


def test_stations_out_of_order_or_invalid_are_refused():
    with pytest.raises(ValueError, match="does not go deeper"):
        minimum_curvature([0.0, 100.0, 100.0], [0, 1, 2], [0, 0, 0])
    with pytest.raises(ValueError, match="not a valid station"):
        minimum_curvature([0.0, 100.0], [0, 200], [0, 0])
    with pytest.raises(ValueError, match="dls_unit"):
        minimum_curvature([0.0, 100.0], [0, 1], [0, 0], dls_unit="deg/10m")
    # a vertical station's undefined azimuth does not matter
    t = minimum_curvature([0.0, 100.0], [0.0, 0.0], [float("nan"), 0.0])
    assert t.tvd[-1] == 100.0

"""Survey evaluation: QC flags against the site reference, error tables like the paper's."""
import numpy as np
import pytest

from inclinometer_calib.core.frames import Site, tool_vectors
from inclinometer_calib.core.survey import Tolerances, evaluate, summarize, table4, table5

SITE = Site(total_field_nt=50000, dip_deg=60.0, declination_deg=0.0)


def test_clean_station_is_ok_and_exact():
    g, b = tool_vectors(SITE, 30.0, 100.0, 45.0)
    r = evaluate(g, b, SITE, ref=[[30.0, 100.0, 45.0]])
    assert r["status"][0] == 0
    assert abs(r["drift_err"][0]) < 1e-9 and abs(r["azimuth_err"][0]) < 1e-9


def test_interference_flagged_by_field_and_dip():
    g, b = tool_vectors(SITE, 60.0, 0.0, 0.0)
    r = evaluate(g, b + [0, 0, 500.0], SITE)  # 500 nT axial field, tool heading north
    clean = evaluate(g, b, SITE)
    assert not clean["interference_suspected"][0]
    assert r["interference_suspected"][0] and r["status"][0] == 1
    assert abs(r["delta_b"][0]) > 300 or abs(r["delta_dip"][0]) > 0.25


def test_near_vertical_station_has_azimuth_flagged_undefined_and_excluded():
    g, b = tool_vectors(SITE, [0.1, 20.0], [10.0, 10.0], [0.0, 0.0])
    r = evaluate(g, b, SITE, Tolerances(min_drift_deg=0.5), ref=[[0.1, 80.0, 0.0], [20.0, 10.0, 0.0]])
    assert list(r["azimuth_undefined"]) == [True, False]
    assert np.isnan(r["azimuth_err"][0])
    assert summarize(r)["azimuth_stations"] == 1


def test_gravity_out_of_tolerance_is_an_error_status():
    g, b = tool_vectors(SITE, 10.0, 10.0, 0.0)
    r = evaluate(g * 1.05, b, SITE)
    assert r["gravity_out_of_tolerance"][0] and r["status"][0] == 2


def test_declination_turns_magnetic_into_true_azimuth():
    site = Site(declination_deg=7.0)
    g, b = tool_vectors(site, 45.0, 200.0, 10.0)  # 200 from true north
    assert evaluate(g, b, site)["azimuth_deg"][0] == pytest.approx(200.0)


def test_tables_group_by_drift_and_azimuth():
    ref = np.array([[i, a, t] for i in (10, 20) for a in (0, 180) for t in (0, 120)], float)
    res = {"drift_err": ref[:, 0] / 100, "azimuth_err": ref[:, 1] / 100 + ref[:, 2] / 1000}
    t4 = table4(res, ref)
    assert t4["drifts"] == [10, 20] and t4["mean_err"] == pytest.approx([0.1, 0.2])
    t5 = table5(res, ref)
    assert t5["cells"] == [[0.0, 1.8], [0.0, 1.8]]  # at the first toolface (0)
    assert t5["rms_err"][0] == pytest.approx(np.sqrt(np.mean(np.array([0, 0.12, 1.8, 1.92]) ** 2)))

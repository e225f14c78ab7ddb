"""The site's reference from a geomagnetic model (:mod:`inclinometer_calib.core.geomag`): WMM2025 and
IGRF-14 against the values their publishers give, normal gravity against WGS84's, grid convergence
against a projection computed another way, measured (IFR) values winning over the model."""
import datetime as dt
import math

import numpy as np
import pytest

from inclinometer_calib.core import geomag
from inclinometer_calib.core.frames import Site

#: NOAA/BGS's test values for WMM2025 (WMM2025 report, test values file): year, height (km), geodetic
#: latitude, longitude, declination (deg), inclination (deg), X, Y, Z, F (nT).
WMM2025_TEST = [
    (2025.0, 28, 89, -121, -99.77, 88.47, -255.388723, -1482.460628, 56194.288771, 56214.419888),
    (2025.0, 51, -33, 109, -5.49, -67.50, 21737.778822, -2090.274098, -52710.003920, 57054.752538),
    (2025.0, 18, 0, 21, 1.29, -26.06, 29274.811882, 659.800118, -14316.722540, 32594.761714),
    (2025.5, 50, -70, -133, 57.21, -71.94, 9021.847823, 14001.865232, -51084.838301, 53731.803175),
    (2026.0, 47, -72, -22, -6.32, -61.16, 18280.800055, -2024.105320, -33397.486160, 38127.112857),
    (2026.5, 86, -11, 167, 10.24, -31.60, 32578.377044, 5882.794932, -20368.224196, 38869.300019),
    (2027.5, 72, -87, 38, -65.44, -70.97, 6926.051596, -15153.941754, -48295.635435, 51088.947370),
    (2029.5, 33, 17, 5, 0.89, 13.77, 34021.976056, 531.446418, 8341.137769, 35033.582023),
]
#: NOAA's geomagnetic calculator, IGRF (DGRF 2010.0: definitive, the same in IGRF-14), 5 km above the
#: WGS84 ellipsoid: latitude, longitude, X, Y, Z (nT, 0.1 nT).
IGRF_2010 = [(80, -179, 4095.0, 594.3, 57440.4), (55, 10, 17423.9, 482.8, 46561.4), (30, -95, 24393.5, 1349.5, 41272.5),
             (0, 120, 39326.7, 654.4, -11649.5), (-33, 151, 24678.3, 5317.1, -50645.1),
             (-60, -60, 19801.9, 3636.9, -27801.7), (60, 5, 15128.0, -188.3, 48375.3)]


def _date(year):
    y = int(year)
    d0 = dt.datetime(y, 1, 1)
    return d0 + (dt.datetime(y + 1, 1, 1) - d0) * (year - y)


@pytest.mark.parametrize("row", WMM2025_TEST)
def test_wmm2025_reproduces_its_published_test_values(row):
    year, h_km, lat, lon, d, inc, x, y, z, f = row
    m = geomag.model_field(lat, lon, h_km * 1000.0, _date(year), "WMM2025")
    assert m["decimal_year"] == pytest.approx(year, abs=1e-9)
    assert (m["x"], m["y"], m["z"], m["f"]) == pytest.approx((x, y, z, f), abs=0.05)
    assert m["declination_deg"] == pytest.approx(d, abs=0.006) and m["dip_deg"] == pytest.approx(inc, abs=0.006)


@pytest.mark.parametrize("row", IGRF_2010)
def test_igrf14_reproduces_noaas_calculator(row):
    lat, lon, x, y, z = row
    m = geomag.model_field(lat, lon, 5000.0, dt.date(2010, 1, 1), "IGRF-14")
    assert (m["x"], m["y"], m["z"]) == pytest.approx((x, y, z), abs=0.1)


def test_the_two_models_agree_where_both_hold_and_dates_outside_a_model_are_refused():
    a = geomag.model_field(57.1, 2.1, 0.0, dt.date(2026, 11, 23), "WMM2025")
    b = geomag.model_field(57.1, 2.1, 0.0, dt.date(2026, 11, 23), "IGRF-14")
    assert abs(a["f"] - b["f"]) < 100 and abs(a["dip_deg"] - b["dip_deg"]) < 0.1
    assert abs(a["declination_deg"] - b["declination_deg"]) < 0.2
    with pytest.raises(ValueError, match="valid 2025"):
        geomag.model_field(57.1, 2.1, 0.0, dt.date(2024, 6, 1), "WMM2025")
    with pytest.raises(ValueError, match="unknown"):
        geomag.model_field(57.1, 2.1, 0.0, dt.date(2026, 6, 1), "EMM")


def test_normal_gravity_is_wgs84s():
    assert geomag.normal_gravity(0.0) == pytest.approx(9.7803253359, abs=1e-9)
    assert geomag.normal_gravity(90.0) == pytest.approx(9.8321849378, abs=1e-9)
    # Somigliana in its other form, γ = γe·(1 + k·sin²φ)/√(1 − e²·sin²φ) (WGS84 k and e²)
    k, e2 = 0.00193185265241, 0.00669437999013
    for lat in (12.0, 45.0, 71.5):
        s2 = math.sin(math.radians(lat)) ** 2
        assert geomag.normal_gravity(lat) == pytest.approx(9.7803253359 * (1 + k * s2) / math.sqrt(1 - e2 * s2), abs=1e-9)
    # the free-air gradient: about -3.086e-6 (m/s²)/m
    assert geomag.normal_gravity(45.0, 1000.0) - geomag.normal_gravity(45.0) == pytest.approx(-3.086e-3, rel=2e-3)


def test_grid_convergence_matches_the_projection_itself():
    from pyproj import Transformer

    for lat, lon, epsg in ((60.0, 6.0, 32631), (57.1, 2.1, 32631), (-33.9, 151.2, 32756), (29.8, -95.4, 32615)):
        gamma = geomag.grid_convergence(lat, lon, epsg)
        t = Transformer.from_crs(4326, epsg, always_xy=True)
        e0, n0 = t.transform(lon, lat)
        e1, n1 = t.transform(lon, lat + 1e-4)
        # the grid azimuth of true north is -γ
        assert -math.degrees(math.atan2(e1 - e0, n1 - n0)) == pytest.approx(gamma, abs=1e-4)
    assert geomag.grid_convergence(60.0, 3.0, 32631) == pytest.approx(0.0, abs=1e-9)   # the central meridian
    assert geomag.grid_convergence(60.0, 6.0, "EPSG:32631") == pytest.approx(3.0 * math.sin(math.radians(60)), abs=0.01)
    with pytest.raises(ValueError, match="not a projected"):
        geomag.grid_convergence(60.0, 6.0, 4326)


def test_a_site_by_location_takes_the_model_and_measured_values_win():
    site = geomag.site_from_config({"latitude_deg": 57.1, "longitude_deg": 2.1, "altitude_m": 0, "date": "2026-11-23",
                                    "model": "IGRF-14", "crs": 32631})
    m = geomag.model_field(57.1, 2.1, 0.0, dt.date(2026, 11, 23), "IGRF-14")
    assert site.total_field_nt == pytest.approx(m["f"]) and site.declination_deg == pytest.approx(m["declination_deg"])
    assert site.gravity_mps2 == pytest.approx(geomag.normal_gravity(57.1))
    assert site.reference["sources"]["dip_deg"].startswith("IGRF-14 at 57.1, 2.1")
    assert np.isfinite(site.grid_convergence_deg)
    ifr = geomag.site_from_config({"latitude_deg": 57.1, "longitude_deg": 2.1, "date": "2026-11-23", "total_field_nt": 50123.0})
    assert ifr.total_field_nt == 50123.0 and ifr.reference["sources"]["total_field_nt"] == "measured (IFR)"
    assert ifr.reference["sources"]["declination_deg"].startswith("WMM2025")
    # a record keeps where its site came from, and reads it back the same
    again = geomag.site_from_config(ifr.to_dict())
    assert again == ifr and again.reference == ifr.reference
    with pytest.raises(ValueError, match="date"):
        geomag.site_from_config({"latitude_deg": 57.1, "longitude_deg": 2.1})
    # typed-in values alone stay as they were (no reference key, the record id unchanged)
    assert "reference" not in Site(50000.0, 60.0, 1.0).to_dict()


def test_a_bad_site_is_one_line_naming_the_key():
    with pytest.raises(ValueError, match=r"^site: unknown key\(s\) \['total_field'\]"):
        geomag.site_from_config({"total_field": 5})
    with pytest.raises(ValueError, match=r"^site: implausible reference: site.total_field_nt -1.0"):
        geomag.site_from_config({"total_field_nt": -1})
    with pytest.raises(ValueError, match=r"^site.dip_deg: expected a number, got 'steep'"):
        geomag.site_from_config({"dip_deg": "steep"})
    with pytest.raises(ValueError, match=r"^site: expected a mapping"):
        geomag.site_from_config(["dip_deg", 60])
    with pytest.raises(ValueError, match=r"^site.measured names \['dip'\]"):
        geomag.site_from_parameters({"latitude_deg": 57.1, "longitude_deg": 2.1, "date": "2026-11-23",
                                     "measured": "dip"})


def test_azimuths_are_given_in_all_three_references():
    a = geomag.azimuths([10.0, 359.0], declination_deg=-2.0, convergence_deg=1.5)
    np.testing.assert_allclose(a["true"], [10.0, 359.0])
    np.testing.assert_allclose(a["magnetic"], [12.0, 1.0])
    np.testing.assert_allclose(a["grid"], [8.5, 357.5])
    assert np.all(np.isnan(geomag.azimuths([10.0], 0.0)["grid"]))


def test_a_site_file_by_location_drives_the_cli_and_says_its_azimuth_reference(tmp_path, capsys):
    from inclinometer_calib.apps.cli import main

    assert main(["simulate", "--out", str(tmp_path / "s"), "--seed", "2"]) == 0
    assert main(["twelve-position", str(tmp_path / "s" / "cal.csv"), "--site", str(tmp_path / "s" / "site.yaml"),
                 "-o", str(tmp_path / "c.yaml")]) == 0
    (tmp_path / "rig.yaml").write_text("site:\n  latitude_deg: 57.1\n  longitude_deg: 2.1\n  date: 2026-11-23\n"
                                       "  model: IGRF-14\n  crs: 32631\n")
    capsys.readouterr()
    val, coeffs, rig = str(tmp_path / "s" / "val.csv"), str(tmp_path / "c.yaml"), str(tmp_path / "rig.yaml")
    assert main(["correct", val, "--coeffs", coeffs, "--site", rig, "--json", "-o", str(tmp_path / "st.csv")]) == 0
    import csv
    import json
    doc = json.loads(capsys.readouterr().out)
    # a site with a grid: the azimuths are grid azimuths, and the run says so with the corrections
    assert doc["azimuth_reference"].startswith("grid north of 32631 (convergence ") and "declination " in \
        doc["azimuth_reference"] and "IGRF-14 at 57.1, 2.1" in doc["azimuth_reference"]
    conv = geomag.grid_convergence(57.1, 2.1, 32631)
    with open(val) as fh:
        logged = {round(float(r["t_s"]), 3): r for r in csv.DictReader(fh)}
    with open(tmp_path / "st.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if r["azimuth_deg"]]
    assert rows and {r["azimuth_reference"] for r in rows} == {"grid"}
    for r in rows:
        assert r["azimuth_deg"] == r["azimuth_grid_deg"]
        assert (float(r["azimuth_true_deg"]) - float(r["azimuth_grid_deg"])) % 360 == pytest.approx(conv % 360, abs=2e-4)
        if r["ref_azimuth_deg"]:     # the log's (true) reference azimuth along grid north too
            src = next(x for t, x in logged.items() if float(r["t_start_s"]) <= t <= float(r["t_end_s"]))
            assert (float(src["ref_azimuth_deg"]) - float(r["ref_azimuth_deg"])) % 360 == pytest.approx(conv % 360,
                                                                                                         abs=2e-4)
    assert main(["correct", val, "--coeffs", coeffs, "--site", rig, "--json", "--north", "true"]) == 0
    assert json.loads(capsys.readouterr().out)["azimuth_reference"].startswith("true north (declination ")
    # a north the site cannot give is refused
    assert main(["correct", val, "--coeffs", coeffs, "--north", "grid"]) != 0
    assert "grid north asked for, but the site has no grid" in capsys.readouterr().err
    (tmp_path / "bad.yaml").write_text("site:\n  latitude_deg: 57.1\n  longitude_deg: 2.1\n  date: 2020-01-01\n")
    assert main(["correct", str(tmp_path / "s" / "val.csv"), "--coeffs", str(tmp_path / "c.yaml"), "--site",
                 str(tmp_path / "bad.yaml")]) != 0
    assert "WMM2025 is valid 2025–2030" in capsys.readouterr().err

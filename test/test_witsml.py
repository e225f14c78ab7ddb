"""WITSML 2.1 Trajectory out (:mod:`inclinometer_calib.witsml`): a simulated well reprocessed into a
bag, exported, validated against the vendored Energistics schema (xmlschema) and parsed back (lxml)
to the same numbers; documents the schema must refuse (a wrong uom, a missing Md, a status outside
the enum) are refused; which stations go in and how; the CLI from a bag; the vendored schema set
is complete and carries its notice."""
import math
import os
import re

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from inclinometer_calib import simulate as sim  # noqa: E402
from inclinometer_calib import witsml  # noqa: E402
from inclinometer_calib.cli import main  # noqa: E402
from inclinometer_calib.coeffs import Calibration  # noqa: E402
from inclinometer_calib.frames import Site  # noqa: E402
from inclinometer_calib.launcher import read_bag, witsml_summary  # noqa: E402
from inclinometer_calib.reprocess import reprocess, write_probe_bag  # noqa: E402

DECLINATION, CONVERGENCE = 2.5, 0.8
SITE = Site(total_field_nt=52000.0, dip_deg=50.0, declination_deg=DECLINATION,
            reference={"grid_convergence_deg": CONVERGENCE})
NAN = math.nan


@pytest.fixture(scope="module")
def well(tmp_path_factory):
    """A simulated well (8 stations, 30 m apart from 500 m) replayed through the pipeline into a bag."""
    d = tmp_path_factory.mktemp("witsml")
    probe = sim.build_probe(3)
    log = sim.run_session(probe, SITE, sim.well_path_session(8), np.random.default_rng(0), rate_hz=50)
    write_probe_bag(log, d / "well.mcap")
    reprocess(d / "well.mcap", d / "run.mcap", Calibration(probe.model, site=SITE))
    return {"dir": d, "bag": d / "run.mcap", "stations": read_bag(d / "run.mcap")[0]}


def _station(k, **kw):
    s = dict(station_id=k, drift_deg=3.0 * k + 0.25, azimuth_deg=40.0 + k, azimuth_reference="true",
             azimuth_method="standard", axial_field_nt=NAN, azimuth_magnetic_deg=40.0 + k - DECLINATION,
             azimuth_grid_deg=NAN, gravity_toolface_deg=10.0 * k, magnetic_toolface_deg=20.0 * k + 1,
             total_gravity_mps2=9.8123, total_field_nt=50012.5, dip_deg=60.25, delta_g_mps2=0.0023,
             delta_b_nt=12.5, delta_dip_deg=0.25, status=0, measured_depth_m=500.0 + 30 * k,
             tvd_m=499.0 + 29.5 * k, north_m=1.5 * k, east_m=-2.5 * k, dls_deg_per_30m=3.0,
             coefficients_id="cafe0123", stamp=1_795_000_000.25 + 30 * k, warnings=[],
             raw_gravity_mps2=[0.11, -0.22, 9.79], raw_field_nt=[1234.5, -2345.5, 40123.25])
    s.update(kw)
    return s


# ---------------------------------------------------------------------------------------------
# a real run

def test_a_reprocessed_well_validates_and_parses_back_to_the_same_numbers(well):
    stations = well["stations"]
    assert len(stations) == 8 and all(s["coefficients_id"] for s in stations)
    export = witsml.trajectory_document(stations, well="NO 15/9-F-1", wellbore="F-1 A")
    witsml.validate(export.xml)
    assert export.exported == 8 and export.skipped == {}
    back = witsml.read_trajectory(export.xml)
    assert len(back) == len(stations)
    for s, b in zip(stations, back):
        # bit for bit: the numbers are written with Python's round-trip repr
        for k in ("measured_depth_m", "tvd_m", "drift_deg", "north_m", "east_m", "dls_deg_per_30m",
                  "total_gravity_mps2", "total_field_nt", "dip_deg", "gravity_toolface_deg", "magnetic_toolface_deg"):
            assert b[k] == s[k] or (math.isnan(b[k]) and math.isnan(s[k])), (s["station_id"], k, s[k], b[k])
        assert b["raw_gravity_mps2"] == s["raw_gravity_mps2"] and b["raw_field_nt"] == s["raw_field_nt"]
        assert b["coefficients_id"] == s["coefficients_id"] and b["uid"] == f"station-{s['station_id']}"
        assert b["stamp"] == pytest.approx(s["stamp"], abs=1e-6)
        assert b["station_status"] == ("rejected" if s["status"] == 2 else "position")
        # the site has a grid: the stations' one north is grid, and the document's
        assert b["azimuth_reference"] == s["azimuth_reference"] == "grid"
        if s["azimuth_grid_deg"] == s["azimuth_grid_deg"]:
            assert b["azimuth_deg"] == s["azimuth_deg"] == s["azimuth_grid_deg"]
            assert b["declination_deg"] == pytest.approx(DECLINATION, abs=1e-9)
            assert b["grid_convergence_deg"] == pytest.approx(CONVERGENCE, abs=1e-9)
    assert any(s["azimuth_grid_deg"] == pytest.approx(s["azimuth_true_deg"] - CONVERGENCE) for s in stations)
    # a receiver's minimum curvature from Md, Incl and Azi lands on DispNs/DispEw (the same north)
    from north_well import receiver_positions
    rx = receiver_positions([b["measured_depth_m"] for b in back], [b["drift_deg"] for b in back],
                            [np.nan_to_num(b["azimuth_deg"]) for b in back])
    assert (back[-1]["north_m"], back[-1]["east_m"]) == pytest.approx(rx[-1], abs=0.01)


def test_the_same_input_gives_the_same_document_and_uuids_follow_well_wellbore_and_run(well):
    a = witsml.trajectory_document(well["stations"], well="W", wellbore="WB")
    assert witsml.trajectory_document(well["stations"], well="W", wellbore="WB").xml == a.xml
    b = witsml.trajectory_document(well["stations"], well="W", wellbore="WB2")
    c = witsml.trajectory_document(well["stations"], well="W", wellbore="WB", run_id="run 2")
    assert len({a.uuid, b.uuid, c.uuid}) == 3
    assert re.fullmatch(r"[0-9a-f]{8}-[0-9a-f]{4}-5[0-9a-f]{3}-[89ab][0-9a-f]{3}-[0-9a-f]{12}", a.uuid)  # uuid5
    # the live document (active, growing) has the same uuid as the export of the finished run
    assert witsml.trajectory_document(well["stations"][:3], well="W", wellbore="WB", active=True).uuid == a.uuid


def test_the_cli_exports_a_bag_validated_and_atomically(well, tmp_path, capsys):
    out = tmp_path / "traj.xml"
    assert main(["witsml", str(well["bag"]), "-o", str(out), "--well", "W-7", "--wellbore", "W-7 ST1"]) == 0
    assert "8 stations" in capsys.readouterr().out
    xml = out.read_bytes()
    witsml.validate(xml)
    assert [b["measured_depth_m"] for b in witsml.read_trajectory(xml)] == [500.0 + 30 * k for k in range(8)]
    assert b"<eml:Title>W-7 ST1</eml:Title>" in xml
    # to standard output: the same document
    assert main(["witsml", str(well["bag"]), "--well", "W-7", "--wellbore", "W-7 ST1"]) == 0
    assert capsys.readouterr().out.encode() == xml


def test_the_cli_refuses_a_run_without_survey_stations_and_leaves_the_file_alone(well, tmp_path, capsys):
    raw = tmp_path / "raw.mcap"
    reprocess(well["dir"] / "well.mcap", raw, None)              # no calibration: raw stations only
    out = tmp_path / "traj.xml"
    out.write_text("previous\n")
    assert main(["witsml", str(raw), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no corrected survey station with a measured depth" in err and "8 raw (no calibration)" in err
    assert out.read_text() == "previous\n"
    assert main(["witsml", str(tmp_path / "missing.mcap")]) == 2
    assert "missing.mcap" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# validation is real

def _valid_doc():
    return witsml.trajectory_document([_station(k) for k in range(1, 4)]).xml


def test_a_valid_document_passes_and_a_wrong_uom_is_refused_naming_line_path_and_station():
    xml = _valid_doc()
    witsml.validate(xml)
    bad = xml.replace(b'<Incl uom="dega">6.25<', b'<Incl uom="deg">6.25<')
    assert bad != xml
    with pytest.raises(witsml.WitsmlError) as info:
        witsml.validate(bad)
    msg = str(info.value)
    assert "/Trajectory/TrajectoryStation[2]/Incl" in msg and "uom='deg'" in msg
    assert "(station station-2)" in msg and "line " in msg
    # dogleg severity in a unit the schema does not have ("deg/30m" is written "1/30 dega/m")
    with pytest.raises(witsml.WitsmlError, match="Dls"):
        witsml.validate(xml.replace(b'uom="1/30 dega/m"', b'uom="dega/30m"'))


@pytest.mark.parametrize("old,new,what", [
    (b"<eml:Md>", b"<eml:Mdx>", "Md"),                                        # Md is required
    (b"<StatusTrajStation>position<", b"<StatusTrajStation>valid<", "StatusTrajStation"),
    (b'schemaVersion="2.1"', b"", "schemaVersion"),
    (b"<eml:Uuid>", b"<eml:Uuid>x", "Uuid"),                                # not a uuid
])
def test_documents_the_schema_refuses_are_refused(old, new, what):
    xml = _valid_doc()
    assert old in xml
    bad = xml.replace(old, new, 1)
    if old == b"<eml:Md>":
        bad = bad.replace(b"</eml:Md>", b"</eml:Mdx>", 1)
    with pytest.raises(witsml.WitsmlError, match=what):
        witsml.validate(bad)


def test_not_xml_or_another_root_is_refused():
    with pytest.raises(witsml.WitsmlError, match="not well-formed"):
        witsml.validate(b"<Trajectory")
    with pytest.raises(witsml.WitsmlError, match="root element"):
        witsml.validate(b"<Log/>")


# ---------------------------------------------------------------------------------------------
# which stations, and what each carries

def test_raw_and_depthless_stations_are_left_out_error_stations_are_rejected():
    stations = [_station(0, coefficients_id=""), _station(1), _station(2, status=1),
                _station(3, status=2, tvd_m=NAN, north_m=NAN, east_m=NAN, dls_deg_per_30m=NAN),  # moved
                _station(4, measured_depth_m=NAN), _station(5)]
    export = witsml.trajectory_document(stations)
    witsml.validate(export.xml)
    assert export.exported == 4
    assert export.skipped == {"raw (no calibration)": 1, "no measured depth": 1}
    back = witsml.read_trajectory(export.xml)
    assert [b["uid"] for b in back] == ["station-1", "station-2", "station-3", "station-5"]
    assert [b["station_status"] for b in back] == ["position", "position", "rejected", "position"]
    moved = back[2]
    assert math.isnan(moved["tvd_m"]) and math.isnan(moved["north_m"]) and moved["drift_deg"] == 9.25


def test_azimuth_reference_declination_short_collar_and_missing_raw_data():
    # magnetic north: no declination applied, none recorded
    mag = witsml.trajectory_document([_station(1, azimuth_reference="magnetic", azimuth_magnetic_deg=41.0)])
    witsml.validate(mag.xml)
    (b,) = witsml.read_trajectory(mag.xml)
    assert b["azimuth_reference"] == "magnetic" and b"<AziRef>magnetic north</AziRef>" in mag.xml
    assert math.isnan(b["declination_deg"]) and b"MagDeclUsed" not in mag.xml
    # true north: declination = true − magnetic (WITSML: true = magnetic + declination)
    tru = witsml.trajectory_document([_station(1, azimuth_magnetic_deg=359.0, azimuth_deg=1.5)])
    (b,) = witsml.read_trajectory(tru.xml)
    assert b["azimuth_reference"] == "true" and b["declination_deg"] == pytest.approx(2.5)
    # short collar: the axial interference removed is the correction, the AMI flag is set
    sc = witsml.trajectory_document([_station(1, azimuth_method="short_collar", axial_field_nt=180.5)])
    witsml.validate(sc.xml)
    assert b'<MagAxialDrlstrCor uom="nT">-180.5</MagAxialDrlstrCor>' in sc.xml
    assert b"<AxialMagInterferenceCorUsed>true<" in sc.xml
    # raw means unknown (an old bag, or NaN): no RawData, the rest unchanged
    for raw in (None, [NAN, NAN, NAN]):
        old = witsml.trajectory_document([_station(1, raw_gravity_mps2=raw, raw_field_nt=raw)])
        witsml.validate(old.xml)
        assert b"RawData" not in old.xml
        assert all(math.isnan(x) for x in witsml.read_trajectory(old.xml)[0]["raw_gravity_mps2"])
    # stations against different norths cannot share one AziRef
    with pytest.raises(witsml.WitsmlError, match="different norths"):
        witsml.trajectory_document([_station(1), _station(2, azimuth_reference="magnetic")])


def test_repeated_station_ids_get_distinct_uids():
    export = witsml.trajectory_document([_station(1), _station(1, measured_depth_m=560.0)])
    witsml.validate(export.xml)
    assert [b["uid"] for b in witsml.read_trajectory(export.xml)] == ["station-1", "station-1-2"]


def test_the_calibration_ids_are_recorded_on_stations_and_trajectory():
    export = witsml.trajectory_document([_station(1), _station(2, coefficients_id="beef4567"), _station(3)])
    witsml.validate(export.xml)
    assert [b["coefficients_id"] for b in witsml.read_trajectory(export.xml)] == ["cafe0123", "beef4567", "cafe0123"]
    from lxml import etree
    root = etree.fromstring(export.xml)
    top = [(e.findtext("eml:Name", namespaces=witsml.XP), e.findtext("eml:Value", namespaces=witsml.XP))
           for e in root.findall("eml:ExtensionNameValue", witsml.XP)]
    assert top == [("coefficients_id", "cafe0123"), ("coefficients_id", "beef4567")]


def test_reading_back_converts_units_and_names_one_it_does_not_know():
    xml = _valid_doc()
    ft = xml.replace(b'<eml:MeasuredDepth uom="m">530.0<', b'<eml:MeasuredDepth uom="ft">1000.0<')
    assert ft != xml
    witsml.validate(ft)
    assert witsml.read_trajectory(ft)[0]["measured_depth_m"] == pytest.approx(304.8)
    per100ft = xml.replace(b'<Dls uom="1/30 dega/m">3.0<', b'<Dls uom="0.01 dega/ft">3.048<', 1)
    assert witsml.read_trajectory(per100ft)[0]["dls_deg_per_30m"] == pytest.approx(3.0)
    with pytest.raises(witsml.WitsmlError, match="station station-1: Incl: unit 'gon'"):
        witsml.read_trajectory(xml.replace(b'<Incl uom="dega">3.25<', b'<Incl uom="gon">3.25<'))


def test_write_trajectory_is_atomic_and_refuses_to_replace_a_good_file_with_a_bad_document(tmp_path):
    path = tmp_path / "t.xml"
    witsml.write_trajectory(path, [_station(1)])
    good = path.read_bytes()
    with pytest.raises(witsml.WitsmlError):
        witsml.write_trajectory(path, [_station(1), _station(2, azimuth_reference="magnetic")])
    with pytest.raises(witsml.WitsmlError, match="only 2.1"):
        witsml.write_trajectory(path, [_station(1)], version="2.0")
    assert path.read_bytes() == good and os.listdir(tmp_path) == ["t.xml"]


def test_the_launcher_summary_checks_the_live_document(tmp_path):
    stations = [_station(k) for k in range(1, 4)]
    path = tmp_path / "trajectory.xml"
    witsml.write_trajectory(path, stations)
    assert witsml_summary(str(path), stations) == {"file": str(path), "stations": 3, "valid": True, "bag_stations": 3}
    path.write_bytes(path.read_bytes().replace(b'uom="dega"', b'uom="deg"'))
    res = witsml_summary(str(path), stations)
    assert res["valid"] is False and "uom='deg'" in res["error"]


# ---------------------------------------------------------------------------------------------
# the vendored schemas

def test_the_vendored_schema_set_is_complete_and_carries_the_energistics_notice():
    """Every include/import of Trajectory.xsd, followed file by file, is in the package; every file
    keeps its licence notice; the README says where they come from."""
    todo, seen = [os.path.abspath(witsml.TRAJECTORY_XSD)], set()
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
        assert "Energistics Product License Agreement" in text, path
        for loc in re.findall(r'<xs:(?:include|import)[^>]*schemaLocation="([^"]+)"', text):
            target = os.path.normpath(os.path.join(os.path.dirname(path), loc))
            assert os.path.exists(target), f"{path} needs {loc}"
            todo.append(target)
    assert len(seen) == 27                       # Trajectory + 5 WITSML files it includes + 21 common
    with open(os.path.join(witsml.SCHEMA_DIR, "README.md"), encoding="utf-8") as fh:
        readme = fh.read()
    assert "devfabiosilva/witsml21parser" in readme and "Product License Agreement" in readme


@pytest.mark.parametrize("north", ["grid", "true", "magnetic"])
def test_azi_and_displacements_are_along_the_stations_one_north_and_say_which(north):
    from north_well import projected_well, receiver_positions

    _, _, stations = projected_well(north)
    export = witsml.trajectory_document(stations)
    witsml.validate(export.xml)
    back = witsml.read_trajectory(export.xml)
    assert {b["azimuth_reference"] for b in back} == {north}
    rx = receiver_positions([b["measured_depth_m"] for b in back], [b["drift_deg"] for b in back],
                            [np.nan_to_num(b["azimuth_deg"]) for b in back])
    assert (back[-1]["north_m"], back[-1]["east_m"]) == pytest.approx(rx[-1], abs=0.01)
    # the corrections applied to the azimuths, and only those: declination unless magnetic, convergence for grid
    assert (b"<MagDeclUsed" in export.xml) == (north != "magnetic")
    assert (b"<GridConUsed" in export.xml) == (north == "grid")
    if north != "magnetic":
        assert back[-1]["declination_deg"] == pytest.approx(DECLINATION, abs=1e-9)

"""WITSML out (:mod:`inclinometer_calib.rig.witsml`): a simulated well reprocessed into a bag, exported as
WITSML 2.1 and 1.4.1.1, validated against the vendored Energistics schemas (libxml2 through lxml; xmlschema, a second
implementation, agrees) and parsed back (lxml) to the same numbers; both versions and both units give the same stations, positions that
agree with their own declared north, the ISCWSA covariance, datums, well and wellbore; documents
the schemas must refuse (a wrong uom, a missing Md, a status outside the enum) are refused; which
stations go in and how; times shifted to the survey's start; the CLI from a bag; the vendored
schema sets are complete and carry their notice."""
import math
import os
import re

import numpy as np
import pytest
import yaml
from lxml import etree

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from inclinometer_calib.calibrate import simulate as sim  # noqa: E402
from inclinometer_calib.rig import witsml  # noqa: E402
from inclinometer_calib.apps.cli import main  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.core.frames import Site  # noqa: E402
from inclinometer_calib.apps.launcher import witsml_summary  # noqa: E402
from inclinometer_calib.io.bag import read_bag  # noqa: E402
from inclinometer_calib.correct.reprocess import reprocess, write_probe_bag  # noqa: E402
from inclinometer_calib.correct.trajectory import minimum_curvature  # noqa: E402

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
    cal = Calibration(probe.model, site=SITE)
    reprocess(d / "well.mcap", d / "run.mcap", cal)
    return {"dir": d, "bag": d / "run.mcap", "stations": read_bag(d / "run.mcap")[0], "calibration": cal}


def _station(k, **kw):
    s = dict(station_id=k, drift_deg=3.0 * k + 0.25, azimuth_deg=40.0 + k, azimuth_reference="true",
             azimuth_method="standard", axial_field_nt=NAN, azimuth_magnetic_deg=40.0 + k - DECLINATION,
             azimuth_grid_deg=NAN, gravity_toolface_deg=10.0 * k, magnetic_toolface_deg=20.0 * k + 1,
             total_gravity_mps2=9.8123, total_field_nt=50012.5, dip_deg=60.25, delta_g_mps2=0.0023,
             delta_b_nt=12.5, delta_dip_deg=0.25, status=0, measured_depth_m=500.0 + 30 * k,
             tvd_m=499.0 + 29.5 * k, north_m=1.5 * k, east_m=-2.5 * k, dls_deg_per_30m=3.0,
             coefficients_id="cafe0123", stamp=1_795_000_000.25 + 30 * k, warnings=[],
             raw_gravity_mps2=[0.11, -0.22, 9.79], raw_field_nt=[1234.5, -2345.5, 40123.25],
             position_covariance_ned_m2=[NAN] * 9)
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
    assert "/Trajectory/TrajectoryStation[2]/Incl" in msg and "attribute 'uom'" in msg and "'deg'" in msg
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
    with pytest.raises(witsml.WitsmlError, match="version '2.0': 2.1 or 1.4.1.1"):
        witsml.write_trajectory(path, [_station(1)], version="2.0")
    assert path.read_bytes() == good
    # the well, datum and wellbore documents beside it, each valid
    assert sorted(os.listdir(tmp_path)) == ["t.datum.xml", "t.well.xml", "t.wellbore.xml", "t.xml"]
    for kind in ("well", "datum", "wellbore"):
        assert witsml.validate((tmp_path / f"t.{kind}.xml").read_bytes()) == "2.1"


def test_the_launcher_summary_checks_the_live_document(tmp_path):
    stations = [_station(k) for k in range(1, 4)]
    path = tmp_path / "trajectory.xml"
    witsml.write_trajectory(path, stations)
    assert witsml_summary(str(path), stations) == {"file": str(path), "stations": 3, "valid": True, "bag_stations": 3,
                                                   "version": "2.1"}
    witsml.write_trajectory(path, stations, version="1.4.1.1")
    assert witsml_summary(str(path), stations)["version"] == "1.4.1.1"
    path.write_bytes(path.read_bytes().replace(b'uom="dega"', b'uom="deg"'))
    res = witsml_summary(str(path), stations)
    assert res["valid"] is False and "attribute 'uom'" in res["error"] and "The value 'deg'" in res["error"]


# ---------------------------------------------------------------------------------------------
# 2.1 and 1.4.1.1, metres and feet: one trajectory

@pytest.fixture(scope="module")
def exports(well):
    """The well's stations exported in both versions and both units, with a datum 12.5 (m or ft)
    above mean sea level: {(version, units): (export, read_document)}."""
    out = {}
    for version in witsml.VERSIONS:
        for units in witsml.UNITS:
            e = witsml.trajectory_document(well["stations"], well="W-7", wellbore="W-7 ST1", version=version,
                                           units=units, datum="kelly bushing", datum_elevation=12.5)
            out[version, units] = (e, witsml.read_document(e.xml))
    return out


def test_both_versions_validate_with_their_well_wellbore_and_datum_and_refuse_each_others_units(exports):
    for (version, _), (e, doc) in exports.items():
        assert witsml.validate(e.xml) == version == doc["version"] == e.version
        kinds = [k for k, _ in e.parents]
        assert kinds == (["well", "vertical_crs", "datum", "wellbore"] if version == "2.1" else ["well", "wellbore"])
        for _, xml in e.parents:
            assert witsml.validate(xml) == version
        assert doc["wellbore"] == "W-7 ST1" and doc["datum"]
    # 2.1: trajectory -> wellbore -> well, and trajectory and wellbore -> one datum of kind "kelly bushing",
    # 12.5 ft up in EPSG:5714 (mean sea level height)
    e, doc = exports["2.1", "ft"]
    parents = {k: etree.fromstring(x) for k, x in e.parents}
    x = witsml.XP
    assert parents["wellbore"].get("uuid") == doc["wellbore_uid"]
    assert parents["wellbore"].findtext("w:Well/eml:Uuid", namespaces=x) == parents["well"].get("uuid")
    assert parents["datum"].get("uuid") == doc["datum_uid"] == parents["wellbore"].findtext(
        "w:DefaultMdDatum/eml:Uuid", namespaces=x) == etree.fromstring(e.xml).findtext("w:DefaultTvdDatum/eml:Uuid",
                                                                                         namespaces=x)
    assert parents["datum"].findtext("eml:Kind", namespaces=x) == "kelly bushing"
    assert parents["datum"].findtext("eml:VerticalCoordinate", namespaces=x) == "12.5"
    assert parents["vertical_crs"].get("uom") == "ft"
    assert parents["vertical_crs"].findtext("eml:AbstractVerticalCrs/eml:EpsgCode", namespaces=x) == "5714"
    # 1.4.1.1: the trajectory's uids are the well's and wellbore's; every md/tvd is against the well's KB datum
    e, doc = exports["1.4.1.1", "m"]
    well_doc, wellbore_doc = (etree.fromstring(x) for _, x in e.parents)
    y = witsml.XP14
    assert well_doc.find("w:well", y).get("uid") == doc["well_uid"] == wellbore_doc.find("w:wellbore", y).get("uidWell")
    assert wellbore_doc.find("w:wellbore", y).get("uid") == doc["wellbore_uid"]
    kb = well_doc.find("w:well/w:wellDatum[w:code='KB']", y)
    assert kb.get("uid") == doc["datum_uid"] and kb.findtext("w:elevation", namespaces=y) == "12.5"
    assert kb.find("w:elevation", y).get("datum") == well_doc.find("w:well/w:wellDatum[w:code='SL']", y).get("uid")
    traj = etree.fromstring(e.xml)
    depths = traj.findall(".//w:md", y) + traj.findall(".//w:tvd", y) + traj.findall(".//w:mdMn", y)
    assert len(depths) > 16 and {d.get("datum") for d in depths} == {doc["datum_uid"]}
    # each version's uom symbols: the other's dogleg severity is refused
    with pytest.raises(witsml.WitsmlError, match="dls"):
        witsml.validate(e.xml.replace(b'uom="dega/30m"', b'uom="1/30 dega/m"'))
    with pytest.raises(witsml.WitsmlError, match="Dls"):
        witsml.validate(exports["2.1", "m"][0].xml.replace(b'uom="1/30 dega/m"', b'uom="dega/30m"'))


def test_a_second_schema_implementation_agrees_on_every_document_written_and_a_refused_one(exports):
    """The package validates with libxml2 (lxml); xmlschema, a pure-Python XSD 1.1 processor that
    shares nothing with it, says the same of each version's documents, in both units, and refuses
    the document libxml2 refuses."""
    xmlschema = pytest.importorskip("xmlschema")
    checkers = {"2.1": xmlschema.XMLSchema(witsml.TRAJECTORY_XSD), "1.4.1.1": xmlschema.XMLSchema(list(witsml.XSD_1411))}
    for (version, _), (e, _) in exports.items():
        for xml in [e.xml] + [x for _, x in e.parents]:
            assert witsml.validate(xml) == version
            assert checkers[version].is_valid(etree.ElementTree(etree.fromstring(xml))), (version, xml[:200])
    bad = exports["2.1", "m"][0].xml.replace(b'uom="1/30 dega/m"', b'uom="dega/30m"')
    assert not checkers["2.1"].is_valid(etree.ElementTree(etree.fromstring(bad)))
    with pytest.raises(witsml.WitsmlError, match="Dls"):
        witsml.validate(bad)


def test_both_versions_and_units_read_back_to_the_same_stations(well, exports):
    ref = exports["2.1", "m"][1]["stations"]
    assert len(ref) == len(well["stations"]) == 8
    for (version, units), (_, doc) in exports.items():
        assert len(doc["stations"]) == 8 and doc["azimuth_reference"] == "grid"
        for a, b in zip(ref, doc["stations"]):
            for k, v in a.items():
                if isinstance(v, list):
                    np.testing.assert_allclose(b[k], v, rtol=1e-12, err_msg=f"{version} {units} {k}")
                elif isinstance(v, float):
                    # metres: bit for bit; feet: the conversion's rounding
                    assert b[k] == pytest.approx(v, rel=0 if units == "m" else 1e-12, nan_ok=True), (version, units, k)
                else:
                    assert b[k] == v, (version, units, k)


def test_matrixcov_is_the_stations_iscwsa_covariance_in_m2_and_ft2(well, exports):
    stations = well["stations"]
    assert all(np.all(np.isfinite(s["position_covariance_ned_m2"])) for s in stations)
    for _, doc in exports.values():
        for s, b in zip(stations, doc["stations"]):
            np.testing.assert_allclose(b["position_covariance_ned_m2"], s["position_covariance_ned_m2"], rtol=1e-12)
            assert b["tool_error_model"] == "ISCWSA MWD Rev4"
    # the numbers as written: NN in ft² is m² / 0.3048², the biases 0 (rev 4 has none), 1σ (2.1 Sigma)
    cov = np.reshape(stations[-1]["position_covariance_ned_m2"], (3, 3))
    root = etree.fromstring(exports["2.1", "ft"][0].xml)
    mc = root.findall("w:TrajectoryStation", witsml.XP)[-1].find("w:MatrixCov", witsml.XP)
    nn = mc.find("w:VarianceNN", witsml.XP)
    assert nn.get("uom") == "ft2" and float(nn.text) == pytest.approx(cov[0, 0] / 0.3048 ** 2, rel=1e-15)
    assert float(mc.findtext("w:VarianceEVert", namespaces=witsml.XP)) == pytest.approx(cov[1, 2] / 0.3048 ** 2)
    assert [mc.findtext(f"w:Bias{a}", namespaces=witsml.XP) for a in ("N", "E", "Vert")] == ["0.0"] * 3
    assert mc.findtext("w:Sigma", namespaces=witsml.XP) == "1.0"


def test_positions_agree_across_units_and_with_their_own_declared_north_to_the_centimetre(exports):
    """Minimum curvature from the document's own Md, Incl and Azi (along its AziRef) from the tie-in
    at the surface gives its Tvd, DispNs, DispEw; feet and metres agree after conversion."""
    for (version, units), (e, doc) in exports.items():
        b = doc["stations"]
        t = minimum_curvature([0.0] + [s["measured_depth_m"] for s in b], [0.0] + [s["drift_deg"] for s in b],
                              [0.0] + [s["azimuth_deg"] for s in b])
        for k, got in (("tvd_m", t.tvd), ("north_m", t.north), ("east_m", t.east)):
            np.testing.assert_allclose([s[k] for s in b], got[1:], atol=0.01, err_msg=f"{version} {units} {k}")
        np.testing.assert_allclose([s["dls_deg_per_30m"] for s in b], t.dls[1:], atol=1e-6)
        m = exports[version, "m"][1]["stations"]
        for k in ("measured_depth_m", "tvd_m", "north_m", "east_m"):
            np.testing.assert_allclose([s[k] for s in b], [s[k] for s in m], atol=0.01)
    # what feet look like: Md in ft, DLS per 100 ft (30 m = 98.4 ft: 1.016 x the per-30 m value)
    root = etree.fromstring(exports["1.4.1.1", "ft"][0].xml)
    st = root.find(".//w:trajectoryStation", witsml.XP14)
    m = exports["1.4.1.1", "m"][1]["stations"][0]
    assert st.find("w:md", witsml.XP14).get("uom") == "ft"
    assert float(st.findtext("w:md", namespaces=witsml.XP14)) == pytest.approx(m["measured_depth_m"] / 0.3048)
    assert st.find("w:dls", witsml.XP14).get("uom") == "dega/100ft"
    assert float(st.findtext("w:dls", namespaces=witsml.XP14)) == pytest.approx(m["dls_deg_per_30m"] * 30.48 / 30)


@pytest.mark.parametrize("version", witsml.VERSIONS)
def test_start_time_shifts_every_time_and_a_1970_clock_is_said(version):
    stations = [_station(k, stamp=5.25 + 30 * k) for k in range(1, 4)]   # a replayed log's clock
    old = witsml.trajectory_document(stations, version=version)
    assert len(old.notes) == 1 and "1970-01-01T00:00:35.250000Z, before 1980" in old.notes[0]
    new = witsml.trajectory_document(stations, version=version, start_time="2026-03-01T06:30:00+01:00")
    witsml.validate(new.xml)
    assert new.notes == []
    pattern = rb"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{6}Z"
    before = [witsml._stamp(t.decode()) for t in re.findall(pattern, old.xml)]
    after = [witsml._stamp(t.decode()) for t in re.findall(pattern, new.xml)]
    assert len(after) == len(before) >= 3 * 2 + 3                  # every station's, the trajectory's
    shift = witsml.parse_time("2026-03-01T05:30:00Z") - 35.25
    assert after == pytest.approx([t + shift for t in before], abs=1e-6)
    assert witsml.read_trajectory(new.xml)[0]["stamp"] == pytest.approx(witsml.parse_time("2026-03-01T05:30:00Z"))


def test_the_geomagnetic_model_is_the_one_of_the_site_each_station_was_evaluated_against():
    site = Site(50000.0, 60.0, 2.5, 9.81, reference={"model": "WMM2025", "sources": {
        "total_field_nt": "WMM2025 at 60, 5, 0 m, 2026.2", "declination_deg": "measured (IFR)"}})
    records = [{"id": "cafe0123", "coefficients_yaml": yaml.safe_dump({"id": "cafe0123", "site": site.to_dict()})},
               {"id": "typed", "coefficients_yaml": yaml.safe_dump({"site": Site(50000.0, 60.0).to_dict()})}]
    models = witsml.mag_models(records)
    assert list(models) == ["cafe0123"]                        # a site typed in names no model
    stations = [_station(1), _station(2, delta_b_nt=40.0), _station(3, coefficients_id="typed")]
    for version in witsml.VERSIONS:
        e = witsml.trajectory_document(stations, models=models, version=version)
        witsml.validate(e.xml)
        back = witsml.read_trajectory(e.xml)
        # the record's site (reference |B| = total − delta = 50000 nT, dip 60°): its model, IFR declination
        assert (back[0]["mag_model"], back[0]["mag_model_valid"]) == ("WMM2025+IFR", "2025.0-2030.0")
        assert etree.fromstring(e.xml).findtext(f".//w:{witsml.element_name('InfieldRefCorUsed', version)}",
                                                namespaces=witsml.XP if version == "2.1" else witsml.XP14) == "true"
        # evaluated against another reference (a site overridden in the correction node): not the record's
        assert back[1]["mag_model"] == back[2]["mag_model"] == ""
    named = witsml.read_trajectory(witsml.trajectory_document(stations, models=models, mag_model="IGRF-14").xml)
    assert {(b["mag_model"], b["mag_model_valid"]) for b in named} == {("IGRF-14", "1900.0-2030.0")}


def test_existing_well_and_wellbore_are_referenced_and_their_uids_checked():
    wid, bid, did = (f"0b5d7c1e-22aa-4b3c-9d{k}e-0123456789ab" for k in "012")
    e = witsml.trajectory_document([_station(1)], well_uid=wid, wellbore_uid=bid, datum_uid=did)
    witsml.validate(e.xml)
    doc = witsml.read_document(e.xml)
    assert e.parents == [] and (doc["wellbore_uid"], doc["datum_uid"]) == (bid, did)
    e = witsml.trajectory_document([_station(1)], version="1.4.1.1", well_uid="w-17", wellbore_uid="wb-17-1")
    witsml.validate(e.xml)
    doc = witsml.read_document(e.xml)
    assert e.parents == [] and (doc["well_uid"], doc["wellbore_uid"], doc["datum_uid"]) == ("w-17", "wb-17-1", "")
    assert b"datum=" not in e.xml                     # the wellbore's default datum applies
    for kw, what in (({"well_uid": "w-17", "wellbore_uid": "wb-17-1"}, "uuid"), ({"well_uid": wid}, "both"),
                     ({"datum_uid": did}, "needs well_uid"), ({"units": "yd"}, "units 'yd'"),
                     ({"datum": "floor"}, "datum 'floor'"), ({"start_time": "yesterday"}, "ISO 8601"),
                     ({"well_uid": wid, "wellbore_uid": bid, "datum_elevation": 3.0}, "datum_elevation")):
        with pytest.raises(witsml.WitsmlError, match=what):
            witsml.trajectory_document([_station(1)], **kw)


def test_the_cli_writes_1411_in_feet_beside_its_parents_and_refuses_a_bad_option_in_one_line(well, tmp_path,
                                                                                             capsys):
    out = tmp_path / "traj.xml"
    args = ["witsml", str(well["bag"]), "-o", str(out), "--version", "1.4.1.1", "--units", "ft", "--well", "W-7",
            "--wellbore", "W-7 ST1", "--datum", "kelly bushing", "--datum-elevation", "12.5"]
    assert main(args) == 0
    said = capsys.readouterr()
    assert "WITSML 1.4.1.1 trajectory of 8 stations in ft" in said.out and "traj.well.xml" in said.out
    assert said.err == ""                                     # the bag's stamps are of 2023: nothing to say
    assert witsml.validate(out.read_bytes()) == "1.4.1.1"
    for kind in ("well", "wellbore"):
        assert witsml.validate((tmp_path / f"traj.{kind}.xml").read_bytes()) == "1.4.1.1"
    assert out.read_bytes() == witsml.trajectory_document(well["stations"], well="W-7", wellbore="W-7 ST1",
                                                          version="1.4.1.1", units="ft", datum="kelly bushing",
                                                          datum_elevation=12.5).xml
    assert main(args + ["--start-time", "2026-03-01T06:30:00Z"]) == 0
    capsys.readouterr()
    assert witsml.read_trajectory(out.read_bytes())[0]["stamp"] == witsml.parse_time("2026-03-01T06:30:00Z")
    # a bag reprocessed with a record carries no record: --coeffs gives it, and its site's model
    assert all(b["mag_model"] == "" for b in witsml.read_trajectory(out.read_bytes()))
    record = yaml.safe_load(well["calibration"].to_yaml())
    record["site"]["reference"]["model"] = "IGRF-14"      # the site the record names, looked up in IGRF-14
    (tmp_path / "rec.yaml").write_text(yaml.safe_dump(record))
    assert main(args + ["--coeffs", str(tmp_path / "rec.yaml")]) == 0
    back = witsml.read_trajectory(out.read_bytes())
    assert {(b["mag_model"], b["mag_model_valid"]) for b in back} == {("IGRF-14", "1900.0-2030.0")}
    capsys.readouterr()
    before = out.read_bytes()
    for bad in (["--units", "yd"], ["--version", "1.3.1.1"], ["--start-time", "yesterday"],
                ["--version", "2.1", "--well-uid", "W1", "--wellbore-uid", "WB1"], ["--coeffs", str(tmp_path)]):
        assert main(args + bad) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err
    assert out.read_bytes() == before


# ---------------------------------------------------------------------------------------------
# the vendored schemas

@pytest.mark.parametrize("roots,directory,notice,count,source", [
    ([witsml.TRAJECTORY_XSD], witsml.SCHEMA_DIR, "Energistics Product License Agreement", 27,
     "devfabiosilva/witsml21parser"),          # Trajectory + 5 WITSML files it includes + 21 common
    (list(witsml.XSD_1411), witsml.SCHEMA_DIR_1411, "Energistics License Agreement", 40,
     "huangkai31/witsml_certification"),       # obj_trajectory/well/wellbore + 36 WITSML files + abstract
])
def test_the_vendored_schema_sets_are_complete_and_carry_the_energistics_notice(roots, directory, notice, count,
                                                                               source):
    """Every include/import of the root schemas, followed file by file, is in the package, and
    nothing else is; every file keeps its licence notice; the README says where they come from."""
    todo, seen = [os.path.abspath(r) for r in roots], set()
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
        assert notice in text, path
        for loc in re.findall(r'<xsd?:(?:include|import)[^>]*schemaLocation="([^"]+)"', text):
            target = os.path.normpath(os.path.join(os.path.dirname(path), loc))
            assert os.path.exists(target), f"{path} needs {loc}"
            todo.append(target)
    assert len(seen) == count
    shipped = {os.path.join(d, f) for d, _, fs in os.walk(directory) for f in fs if f.endswith(".xsd")}
    assert shipped == seen
    with open(os.path.join(directory, "README.md"), encoding="utf-8") as fh:
        readme = fh.read()
    assert source in readme and "License Agreement" in readme


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

"""Offline reprocessing of a recorded bag (ROS-free): read → pair → stations → correct → write."""
import math
import os

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")  # reprocessing is ROS-free but needs these two readers/writers

from inclinometer_calib.calibrate import simulate as sim  # noqa: E402
from inclinometer_calib.io.bag import BagWriter, open_bag  # noqa: E402
from inclinometer_calib.apps.cli import main  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.core.frames import Site  # noqa: E402
from inclinometer_calib.correct.reprocess import STATION_TYPE, reprocess, write_probe_bag  # noqa: E402

SITE = Site(total_field_nt=52000.0, dip_deg=50.0, declination_deg=0.0)
DRIFTS = (0, 3, 10, 45, 90)
AZIMUTHS = (30, 150, 270)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """A simulated stand survey (15 stations, 2 s each at 100 Hz) recorded as a bag, plus the
    simulator's true coefficients."""
    d = tmp_path_factory.mktemp("reprocess")
    probe = sim.build_probe(5, ["temperature_bias:mag=2"])
    sess = sim.stand_grid_session(drifts=DRIFTS, azimuths=AZIMUTHS, toolfaces=(60,), duration_s=2.0,
                                  temp_profile_c=(25, 35))
    log = sim.run_session(probe, SITE, sess, np.random.default_rng(2), rate_hz=100)
    bag = d / "survey.mcap"
    counts = write_probe_bag(log, bag)
    truth = Calibration(acc=probe.acc, mag=probe.mag, probe_id="sim-5", site=SITE)
    coeffs = d / "truth.yaml"
    truth.save(coeffs)
    return {"dir": d, "bag": bag, "log": log, "counts": counts, "cal": truth, "coeffs": coeffs,
            "n_stations": len(sess)}


def _stations(path):
    from mcap_ros2.reader import read_ros2_messages  # decodes with the definitions in the file
    return [m.ros_msg for m in read_ros2_messages(str(path), topics=["/survey/station"])]


def test_stations_match_the_reference_after_correction_with_the_true_coefficients(survey, tmp_path):
    out = tmp_path / "out.mcap"
    rep = reprocess(survey["bag"], out, survey["cal"], SITE)
    assert rep.bag_errors == [] and rep.skipped_topics == {}
    assert rep.pairs == len(survey["log"])
    st = _stations(out)
    assert len(st) == len(rep.stations) == survey["n_stations"]
    for s in st:
        assert s.reference_drift_deg in DRIFTS
        assert abs(s.drift_deg - s.reference_drift_deg) < 0.05
        assert s.samples_averaged > 150 and s.is_static
        assert s.coefficients_id == survey["cal"].id
        assert 25 <= s.temperature_c <= 35
        if s.reference_drift_deg == 0:      # near vertical: azimuth undefined, flagged, NaN
            assert s.azimuth_undefined and math.isnan(s.azimuth_deg) and s.status == 1
            assert s.toolface_type == "magnetic"
        else:
            err = (s.azimuth_deg - s.reference_azimuth_deg + 180) % 360 - 180
            assert abs(err) < 0.5, (s.reference_drift_deg, s.reference_azimuth_deg, s.azimuth_deg)
            assert s.status == 0 and not s.interference_suspected
    # input messages are copied through unchanged
    counts = {k: v.count for k, v in open_bag(out).topics.items()}
    for topic, n in survey["counts"].items():
        assert counts[topic] == n
    src = [m.data for m in open_bag(survey["bag"]).messages(["/probe/imu"])][:50]
    dst = [m.data for m in open_bag(out).messages(["/probe/imu"])][:50]
    assert src == dst


def test_uncorrected_is_worse_than_corrected(survey, tmp_path):
    raw = reprocess(survey["bag"], tmp_path / "raw.mcap", None, SITE)
    err = [abs((s["azimuth_deg"] - s["reference_azimuth_deg"] + 180) % 360 - 180)
           for s in raw.stations if not s["azimuth_undefined"]]
    assert max(err) > 1.0
    assert all(s["coefficients_id"] == "" for s in raw.stations)


def test_cli_reprocess_and_never_overwrites(survey, tmp_path, capsys):
    out = tmp_path / "o.mcap"
    assert main(["reprocess", str(survey["bag"]), "--coeffs", str(survey["coeffs"]), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{survey['n_stations']} stations" in text and "real time" in text
    size = out.stat().st_size
    assert main(["reprocess", str(survey["bag"]), "--coeffs", "none", "-o", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert out.stat().st_size == size


def test_truncated_bag_is_an_error_naming_file_and_offset_and_the_readable_part_is_processed(survey, tmp_path,
                                                                                             capsys):
    data = survey["bag"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "cut_out.mcap"
    assert main(["reprocess", str(cut), "--coeffs", str(survey["coeffs"]), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"error: {cut}" in err and "byte offset" in err and "truncated" in err
    assert "were processed and written" in err
    st = _stations(out)
    assert 3 <= len(st) < survey["n_stations"]          # the stations before the damage
    assert all(abs(s.drift_deg - s.reference_drift_deg) < 0.05 for s in st)


def test_unknown_topics_and_types_are_skipped_with_a_warning_naming_them(survey, tmp_path, capsys):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types["std_msgs/msg/String"]
    src = tmp_path / "mixed.mcap"
    with BagWriter(src) as w:
        ids = {}
        for m in open_bag(survey["bag"]).messages():
            if m.topic not in ids:
                ids[m.topic] = w.add_topic(m.topic, m.type)
            w.write(ids[m.topic], m.data, m.log_time, m.publish_time)
        chat = w.add_topic("/chatter", "std_msgs/msg/String")
        wrong = w.add_topic("/probe/imu_raw_counts", "std_msgs/msg/String")
        for k in range(5):
            w.write(chat, bytes(store.serialize_cdr(String(data=f"hello {k}"), "std_msgs/msg/String")), 10 + k)
            w.write(wrong, bytes(store.serialize_cdr(String(data="x"), "std_msgs/msg/String")), 10 + k)
    out = tmp_path / "mixed_out.mcap"
    assert main(["reprocess", str(src), "--coeffs", str(survey["coeffs"]), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "skipped topic /chatter (std_msgs/msg/String: not a probe input topic" in err
    assert "skipped topic /probe/imu_raw_counts" in err
    topics = open_bag(out).topics
    assert "/chatter" not in topics and len(_stations(out)) == survey["n_stations"]


def test_input_topic_with_the_wrong_type_is_skipped_naming_the_expected_type(survey, tmp_path, capsys):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types["std_msgs/msg/String"]
    src = tmp_path / "wrongtype.mcap"
    with BagWriter(src) as w:
        ids = {}
        for m in open_bag(survey["bag"]).messages(["/probe/imu", "/probe/mag"]):
            if m.topic not in ids:
                ids[m.topic] = w.add_topic(m.topic, m.type)
            w.write(ids[m.topic], m.data, m.log_time, m.publish_time)
        t = w.add_topic("/probe/temperature", "std_msgs/msg/String")
        w.write(t, bytes(store.serialize_cdr(String(data="25"), "std_msgs/msg/String")), 1)
    out = tmp_path / "wrongtype_out.mcap"
    assert main(["reprocess", str(src), "--coeffs", "none", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "skipped topic /probe/temperature (std_msgs/msg/String: expected sensor_msgs/msg/Temperature)" in err
    st = _stations(out)
    assert len(st) == survey["n_stations"] and all(math.isnan(s.temperature_c) for s in st)


def test_station_messages_carry_our_definition_and_hash(survey, tmp_path):
    out = tmp_path / "h.mcap"
    reprocess(survey["bag"], out, None, SITE)
    info = open_bag(out).topics["/survey/station"]
    assert info.type == STATION_TYPE and info.type_hash.startswith("RIHS01_")
    assert "uint32 station_id" in info.definition
    assert os.path.getsize(out) > 0


def test_a_well_logged_with_its_depth_is_reprocessed_into_a_trajectory(tmp_path):
    from inclinometer_calib.io.bag import read_bag
    from inclinometer_calib.io.probelog import read_csv, write_csv
    from inclinometer_calib.correct.trajectory import minimum_curvature

    probe = sim.build_probe(3)
    log = sim.run_session(probe, SITE, sim.well_path_session(12), np.random.default_rng(0), rate_hz=50)
    write_csv(tmp_path / "well.csv", log)
    assert read_csv(tmp_path / "well.csv")[0].md_m[0] == 500.0          # the CSV's md_m column
    counts = write_probe_bag(read_csv(tmp_path / "well.csv")[0], tmp_path / "well.mcap")
    assert 12 <= counts["/probe/depth"] < 60                             # held depths, and the runs between
    cal = Calibration(probe.model, site=SITE)
    reprocess(tmp_path / "well.mcap", tmp_path / "re.mcap", cal)
    stations = read_bag(tmp_path / "re.mcap")[0]
    assert [s["measured_depth_m"] for s in stations] == [500.0 + 30 * k for k in range(12)]
    ref = np.array([[s["reference_drift_deg"], s["reference_azimuth_deg"]] for s in stations])
    true = minimum_curvature(np.r_[0.0, [s["measured_depth_m"] for s in stations]], np.r_[0.0, ref[:, 0]],
                             np.r_[0.0, np.nan_to_num(ref[:, 1])])
    for k, s in enumerate(stations):
        assert abs(s["tvd_m"] - true.tvd[k + 1]) < 0.05 and abs(s["north_m"] - true.north[k + 1]) < 0.1
        assert abs(s["east_m"] - true.east[k + 1]) < 0.1


def test_the_bags_probe_serial_is_every_stations_and_another_probes_record_is_refused_unless_forced(survey, tmp_path,
                                                                                                    capsys):
    from inclinometer_calib.correct.reprocess import ReprocessError, bag_probe_serial

    bag = tmp_path / "sn.mcap"
    counts = write_probe_bag(survey["log"], bag, serial="SN-0815")
    assert counts["/probe/serial"] == 1 and bag_probe_serial(bag) == "SN-0815"
    assert bag_probe_serial(survey["bag"]) is None                  # a bag that names no probe
    mine = Calibration(acc=survey["cal"].acc, mag=survey["cal"].mag, probe_id="SN-0815", site=SITE)
    rep = reprocess(bag, None, mine)
    assert rep.probe_serial == "SN-0815"
    assert {s["probe_serial"] for s in rep.stations} == {"SN-0815"}
    assert not any("FORCED" in w for s in rep.stations for w in s["warnings"])
    other = Calibration(acc=survey["cal"].acc, mag=survey["cal"].mag, probe_id="SN-4711", site=SITE)
    with pytest.raises(ReprocessError, match="probe SN-4711, the data are of probe SN-0815"):
        reprocess(bag, tmp_path / "no.mcap", other)
    assert not (tmp_path / "no.mcap").exists()                      # refused before anything is written
    forced = reprocess(bag, None, other, force_probe=True)
    assert all(any(w.startswith("FORCED: record") and "SN-4711" in w for w in s["warnings"]) for s in forced.stations)
    assert any("FORCED" in n for n in forced.warnings())
    # the same numbers: forcing changes what is said, not the correction
    assert [s["azimuth_deg"] for s in forced.stations] == pytest.approx([s["azimuth_deg"] for s in rep.stations],
                                                                         nan_ok=True)
    # a record that names no probe (older records: 'probe') is applied unchecked
    assert reprocess(bag, None, Calibration(acc=survey["cal"].acc, mag=survey["cal"].mag, site=SITE)).stations
    # the CLI: refused with the reason, forced with --force-probe (and said)
    rec = tmp_path / "other.yaml"
    other.save(rec)
    assert main(["reprocess", str(bag), "--coeffs", str(rec), "-o", str(tmp_path / "a.mcap")]) == 2
    assert "another" not in capsys.readouterr().out
    assert main(["reprocess", str(bag), "--coeffs", str(rec), "-o", str(tmp_path / "b.mcap"), "--force-probe"]) == 0
    out = capsys.readouterr()
    assert "FORCED" in out.err and "probe SN-0815" in out.out
    assert all("FORCED" in " ".join(s.warnings) and s.probe_serial == "SN-0815" for s in _stations(tmp_path / "b.mcap"))


def test_writing_and_reprocessing_a_bag_report_their_progress_up_to_the_whole(tmp_path):
    """The CLI's progress bars follow these (bag from-csv, reprocess): counts that rise to the
    samples written and to the messages in the bag."""
    log = sim.run_session(sim.build_probe(3), SITE, sim.well_path_session(4), np.random.default_rng(0), rate_hz=200)
    written = []
    counts = write_probe_bag(log, tmp_path / "p.mcap", progress=written.append)
    assert written[0] == 0 and written[-1] == len(log) and written == sorted(written) and len(written) >= 2
    seen = []
    reprocess(tmp_path / "p.mcap", tmp_path / "out.mcap", None, SITE, progress=lambda k, n: seen.append((k, n)))
    total = sum(counts.values())
    assert seen and all(n == total for _, n in seen) and [k for k, _ in seen] == sorted(k for k, _ in seen)
    assert seen[-1][0] <= total

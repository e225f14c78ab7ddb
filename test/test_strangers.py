"""Probes unlike our default simulator, through the CLI and offline reprocessing, default settings.

Each case (test/strangers.py: noise ×0.5–×5, 10–1000 Hz, holds of 1–10 s, slow and fast moves,
vertical poses without azimuth, labelled and unlabelled, nT and tesla) must calibrate from the
calibration log followed by the survey (the session must leave the survey's stations alone),
correct the survey to within a small factor of what the true coefficients give, and give the same
coefficients and station angles through ``twelve-position`` on the CSV and ``reprocess
--calibrate`` on the same data written as a bag.  The live graph's cases are in
test/nodes/test_strangers_graph.py.
"""
import json

import numpy as np
import pytest

import strangers as S
from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.io.probelog import read_csv, segment_stations
from inclinometer_calib.core.survey import evaluate


def _run(capsys, argv):
    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("case", S.CASES, ids=[c.name for c in S.CASES])
def test_a_stranger_calibrates_alike_through_the_cli_and_reprocess(case, tmp_path, capsys):
    p = S.make(case, tmp_path)
    unit = ["--mag-unit", case.mag_unit]
    code, out, err = _run(capsys, ["twelve-position", str(p["both"]), "-o", str(tmp_path / "cli.yaml"),
                                   "--site", str(p["site"]), *unit])
    assert code == 0, err
    assert "Solved by: accelerometer closed form" in out                # every pose captured
    cli = Calibration.load(tmp_path / "cli.yaml")

    code, out, err = _run(capsys, ["correct", str(p["val"]), "--coeffs", str(tmp_path / "cli.yaml"), "--json", *unit])
    assert code == 0, err
    after = json.loads(out)
    code, out, _ = _run(capsys, ["correct", str(p["val"]), "--coeffs", str(p["truth"]), "--json", *unit])
    truth = json.loads(out)
    assert after["stations"] == truth["stations"] == 24              # every survey station found
    assert after["drift_rms_deg"] < max(1.6 * truth["drift_rms_deg"], 0.001)
    assert after["azimuth_rms_deg"] < max(1.8 * truth["azimuth_rms_deg"], 0.005)

    bag = tmp_path / "both.mcap"
    assert _run(capsys, ["bag", "from-csv", str(p["both"]), "-o", str(bag), *unit])[0] == 0
    code, out, err = _run(capsys, ["reprocess", str(bag), "--calibrate", "--site", str(p["site"]),
                                   "-o", str(tmp_path / "re.mcap"), "--coeffs-out", str(tmp_path / "re.yaml")])
    assert code == 0, err
    re = Calibration.load(tmp_path / "re.yaml")
    assert re.id == cli.id                                             # the same coefficients, bit for bit

    # ... and the same station angles: the survey stations of the reprocessed bag against the
    # CSV's stations corrected with the CLI's coefficients
    stations, coefs = S.stations_of_bag(tmp_path / "re.mcap")
    assert coefs and coefs[-1]["id"] == cli.id
    survey = [s for s in stations if s["coefficients_id"] == cli.id and np.isfinite(s["reference_azimuth_deg"])]
    log, _ = read_csv(p["both"], mag_unit=case.mag_unit)
    csv_st = [s for s in segment_stations(log)[0] if not s.pose and np.isfinite(s.ref[1])]   # the survey
    assert len(survey) == len(csv_st) == 24
    res = evaluate(*cli.correct(np.array([s.g for s in csv_st]), np.array([s.b for s in csv_st])), cli.site)
    np.testing.assert_allclose([s["drift_deg"] for s in survey], res["drift_deg"], atol=1e-9)
    np.testing.assert_allclose([s["azimuth_deg"] for s in survey], res["azimuth_deg"], atol=1e-9)

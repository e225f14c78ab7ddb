"""The model loop of a run (lab/loop.py): the lab's finding on the recorded bag becomes a record
the graph can apply, whatever it recommends."""
import numpy as np
import yaml

import independent as ind
from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.lab.loop import run_loop

OFF = {3: (0.25, -0.10, 0.20), 7: (0.0, 0.30, -0.15)}


def test_a_worn_stand_found_by_the_loop_is_fitted_into_the_record_not_refused(tmp_path):
    """A stand holding poses 3 and 7 off: the loop's lab recommends stand_pose_error, and its record
    is fitted with the stand's pose errors (it used to stop at 'a whole-probe effect of the simulator')."""
    gen = ind.Generator(ind.random_probe(21), seed=21, move_s=1.5)
    holds = ind.twelve_pose_rounds(2, hold_s=6.0, offsets=OFF) + ind.grid(hold_s=4.0)
    gen.write(tmp_path / "run.csv", holds)
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(gen.site.as_yaml_dict()))
    bag = tmp_path / "run.mcap"
    assert main(["bag", "from-csv", str(tmp_path / "run.csv"), "-o", str(bag), "--probe-serial", "WORN-1"]) == 0
    assert main(["twelve-position", str(tmp_path / "run.csv"), "--site", str(tmp_path / "site.yaml"), "-o",
                 str(tmp_path / "live.yaml"), "--probe-id", "WORN-1"]) == 0
    live = Calibration.load(tmp_path / "live.yaml")
    (tmp_path / "loop").mkdir()
    res = run_loop(bag, live, tmp_path / "loop")
    assert res.diagnosis.recommended is not None and res.diagnosis.recommended.label == "stand_pose_error", \
        res.diagnosis.verdict
    assert res.record is not None, res.lines
    assert "stand_pose_error" in res.record.method
    found = res.record.diagnostics["fit"]["stand_pose_errors_deg"]
    for pose, angles in OFF.items():
        assert np.allclose(found[pose], angles, atol=0.03), found

"""The calibration node in turntable mode, live: a simulated turntable run (the patent's procedure,
mounts unlabelled in the stream) replayed from a bag through the graph (separate processes over
DDS, this machine only).  The node recognises the mounts from gravity, estimates the step angles
and publishes a record whose magnetometer agrees with ``inclinometer-calib turntable`` on the
same log (which reads the set angles) to within their uncertainties, and with the truth."""
import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

from inclinometer_calib.apps.cli import main  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.calibrate.turntable import angles_from_matrix  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(18)


def test_the_live_node_calibrates_a_replayed_turntable_bag_as_the_cli_does(domain_env, tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--seed", "4", "--effect", "misalignment:mag=0.004,-0.003,0.005",
                 "--turntable", "12", "--rate", "50"]) == 0
    assert main(["bag", "from-csv", str(sim / "turntable.csv"), "-o", str(tmp_path / "tt.mcap")]) == 0
    capsys.readouterr()
    assert main(["turntable", str(sim / "turntable.csv"), "--site", str(sim / "site.yaml"), "-o",
                 str(tmp_path / "cli.yaml"), "--json"]) == 0
    cli_doc = json.loads(capsys.readouterr().out)
    env, _ = domain_env
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--source", "mcap", "--input",
           str(tmp_path / "tt.mcap"), "--speed", "100", "--site", str(sim / "site.yaml"), "--param",
           "calibration:method:=turntable", "--no-loop", "--timeout", "150"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=200)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-6000:]
    assert "mount yz, step 12" in log and "turntable solved from 36 steps" in log and "[ERROR]" not in log
    live = Calibration.load(out / "coeffs.yaml")
    cli = Calibration.load(tmp_path / "cli.yaml")
    assert live.method.startswith("turntable")
    doc = live.diagnostics["turntable"]["mag"]
    # the same magnetometer as the CLI's, to within their uncertainties (the live node estimates
    # the step angles the CLI reads from the log)
    for key, sd in (("k", "k_std"), ("bias_nT", "bias_std"), ("alpha_deg", "alpha_std")):
        a, b = np.array(doc[key], float), np.array(cli_doc["mag"][key], float)
        s = np.hypot(np.array(doc[sd], float), np.array(cli_doc["mag"][sd], float))
        assert np.all(np.abs(a - b) <= 3 * s), (key, a, b, s)
    truth = Calibration.load(sim / "truth_coeffs.yaml")
    from inclinometer_calib.lab.methods import linear_triad
    a_true, _ = linear_triad(truth, "mag")
    alpha_true = angles_from_matrix(a_true)["alpha_deg"]
    assert np.all(np.abs(np.array(doc["alpha_deg"]) - alpha_true) <= 3 * np.array(doc["alpha_std"]) + 1e-4)
    np.testing.assert_allclose(live.mag.A, cli.mag.A, atol=1e-4)

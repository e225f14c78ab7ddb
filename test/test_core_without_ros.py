"""The numerical core and the CLI import neither rclpy nor any ROS message module."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORE = ["frames", "errormodel", "twelve_position", "effects", "model", "plugins", "simulate", "probelog", "coeffs",
        "survey", "noise", "station", "gates", "streaming", "capture", "pipeline", "axial", "msa", "bag", "reprocess", "cli",
        "lab", "lab.fit", "lab.diagnose", "lab.report", "lab.field", "lab.stats",
        "fleet.registry", "fleet.history", "fleet.manifest", "fleet.reprocess"]


def test_core_modules_import_no_ros():
    code = ("import sys\n"
            + "".join(f"import inclinometer_calib.{m}\n" for m in CORE)
            + "bad = sorted(m for m in sys.modules if m.startswith(('rclpy', 'rosidl', 'rcl_interfaces'))"
              " or m.endswith('_msgs') or '_msgs.' in m or m.startswith('inclinometer_calib.msg')"
              " or m.startswith('inclinometer_calib.nodes'))\n"
            + "print(','.join(bad))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env={**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"ROS modules imported by the core: {r.stdout.strip()}"

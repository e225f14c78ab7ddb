"""The layers below the nodes and the CLI import neither rclpy nor any ROS message module."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PKG = os.path.join(ROOT, "inclinometer_calib")
#: Every module of the layers below the nodes (test/core/test_layers.py: the layers and their
#: order) and the CLI's modules (not its __main__, which runs it): none may import ROS (the
#: kernel's numba module and the fleet's Alembic environment are left out: an optional extra, and a
#: script Alembic runs).
CORE = sorted(
    os.path.relpath(os.path.join(d, f), PKG)[:-3].replace(os.sep, ".").removesuffix(".__init__")
    for layer in ("core", "detect", "io", "calibrate", "correct", "rig", "lab", "fleet")
    for d, _, files in os.walk(os.path.join(PKG, layer)) if "migrations" not in d
    for f in files if f.endswith(".py") and f != "_batch_numba.py") + ["apps.common"] + [
    "apps.cli" + ("" if f == "__init__.py" else "." + f[:-3])
    for f in sorted(os.listdir(os.path.join(PKG, "apps", "cli"))) if f.endswith(".py") and f != "__main__.py"]


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


def test_no_module_below_the_nodes_names_ros_even_inside_a_function():
    """Read from the source: an import inside a function is not run by the import above."""
    import ast

    import pysource

    ros = ("rclpy", "rosidl", "rcl_interfaces", "builtin_interfaces", "inclinometer_calib.msg",
           "inclinometer_calib.srv")
    found = []
    for m in CORE:
        path = os.path.join(PKG, *m.split("."))
        path = os.path.join(path, "__init__.py") if os.path.isdir(path) else path + ".py"
        for node in ast.walk(pysource.parse(path)):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            found += [f"{m}: {n}" for n in names if n.startswith(ros) or n.split(".")[0].endswith("_msgs")]
    assert found == [], found

"""Optional dependencies: declared as extras in setup.py, and a missing one is a one-line hint.

``pip install .`` installs numpy, scipy and PyYAML only. The metadata tests build what pip reads
(``setup.py egg_info`` into a temporary directory: PKG-INFO's Provides-Extra and requires.txt, read
with importlib.metadata as Requires-Dist)
and compare it with the imports in the code and the tested versions in requirements/jazzy.lock.

The CLI tests simulate a core-only install without uninstalling anything: the CLI runs in a child
Python whose first meta-path finder refuses the optional modules (ModuleNotFoundError, as when
they are not installed), and must end with the one line ``error: <what> needs <module>, which is
not installed: pip install 'inclinometer_calib[<extra>]'`` (no traceback), exit status 2.
"""
import ast
import os
import re
import subprocess
import sys
import textwrap
from importlib.metadata import Distribution

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

import pysource

from inclinometer_calib.apps import cli
from inclinometer_calib.core.deps import MissingDependency, require
from inclinometer_calib.io.probelog import read_csv
from inclinometer_calib.correct.reprocess import write_probe_bag

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PKG = os.path.join(ROOT, "inclinometer_calib")
CORE = {"numpy", "scipy", "pyyaml", "pygeomag", "ppigrf", "pyproj", "lxml", "tqdm",
        "threadpoolctl"}
#: never in a core install (issue 24): the fleet stack, the live view, the numba kernel, pyarrow
NOT_CORE = {"dask", "distributed", "sqlalchemy", "alembic", "psycopg", "pyarrow", "numba", "foxglove-sdk"}
OPTIONAL_MODULES = ("matplotlib", "mcap", "zstandard", "lz4", "rosbags", "sklearn", "sqlalchemy", "alembic",
                    "psycopg", "dask", "distributed", "pyarrow", "numba", "foxglove")
#: import name -> PyPI distribution, where they differ
DISTRIBUTION = {"yaml": "PyYAML", "foxglove": "foxglove-sdk", "sklearn": "scikit-learn"}
#: modules that come with ROS 2 (colcon / the ROS wheels), never from this package's metadata
ROS_MODULES = {"rclpy", "rcl_interfaces", "ament_index_python", "std_srvs", "launch", "launch_ros",
               "builtin_interfaces", "rosidl_runtime_py"}


# ---------------------------------------------------------------------------------------------
# metadata

@pytest.fixture(scope="module")
def metadata(tmp_path_factory):
    """(core requirement names, {extra: [Requirement]}) from the metadata pip builds from setup.py."""
    base = tmp_path_factory.mktemp("egg")
    r = subprocess.run([sys.executable, "setup.py", "-q", "egg_info", "--egg-base", str(base)],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    dist = Distribution.at(base / "inclinometer_calib.egg-info")  # PKG-INFO + requires.txt, as pip reads it
    core, extras = set(), {name: [] for name in dist.metadata.get_all("Provides-Extra") or []}
    for line in dist.requires or []:
        req = Requirement(line)
        extra = next((e for e in extras if req.marker and req.marker.evaluate({"extra": e})), None)
        if req.marker is None:
            core.add(canonicalize_name(req.name))
        elif extra is not None:
            extras[extra].append(req)
    return core, extras


def _names(reqs):
    return {canonicalize_name(r.name) for r in reqs}


def test_install_requires_is_the_numerical_core(metadata):
    core, _ = metadata
    assert core == CORE and not core & NOT_CORE


def test_extras_report_bag_lab_fleet_live_fast_all(metadata):
    _, extras = metadata
    want = {"report": {"matplotlib"}, "bag": {"mcap", "zstandard", "lz4", "rosbags"}, "lab": {"scikit-learn"},
            "fleet": {"sqlalchemy", "alembic", "psycopg", "dask", "distributed", "pyarrow"},
            "live": {"foxglove-sdk"}, "fast": {"numba", "pyarrow"}}
    assert set(want) | {"all"} <= set(extras), sorted(extras)
    for extra, names in want.items():
        assert _names(extras[extra]) == names, extra
    assert _names(extras["all"]) == set().union(*want.values())


def _python_files():
    for dirpath, _, files in os.walk(PKG):
        for f in files:
            if f.endswith(".py"):
                yield os.path.join(dirpath, f)


def _imports(path):
    for node in ast.walk(pysource.parse(path)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split(".")[0], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0], node.lineno


def test_every_third_party_import_is_declared(metadata):
    """What the code imports (outside ROS) is in install_requires or in an extra: nothing like the
    former undeclared ``rosbags`` can come back."""
    core, extras = metadata
    declared = core | {n for reqs in extras.values() for n in _names(reqs)}
    undeclared = []
    for path in _python_files():
        for module, line in _imports(path):
            if (module in sys.stdlib_module_names or module == "inclinometer_calib" or module in ROS_MODULES
                    or module.endswith(("_msgs", "_interfaces"))):
                continue
            if canonicalize_name(DISTRIBUTION.get(module, module)) not in declared:
                undeclared.append(f"{os.path.relpath(path, ROOT)}:{line}: {module}")
    assert not undeclared, "imported but declared nowhere in setup.py:\n" + "\n".join(undeclared)


def test_require_calls_name_the_extra_that_provides_the_module(metadata):
    _, extras = metadata
    calls = []
    for path in _python_files():
        for node in ast.walk(pysource.parse(path)):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "require"
                    and len(node.args) >= 2 and all(isinstance(a, ast.Constant) for a in node.args[:2])):
                module, extra = node.args[0].value, node.args[1].value
                calls.append(f"{os.path.relpath(path, ROOT)}:{node.lineno}")
                assert extra in extras, f"{calls[-1]}: require(..., {extra!r}): no such extra"
                dist = canonicalize_name(DISTRIBUTION.get(module.split(".")[0], module.split(".")[0]))
                assert dist in _names(extras[extra]), f"{calls[-1]}: extra {extra!r} does not install {dist}"
    assert len(calls) >= 5, calls  # report.py, spec.py, bag.py, reprocess.py, launcher.py


def test_tested_versions_satisfy_the_bounds(metadata):
    """requirements/jazzy.lock is the environment the tests run in: its pins meet every bound."""
    with open(os.path.join(ROOT, "requirements", "jazzy.lock"), encoding="utf-8") as fh:
        pins = {canonicalize_name(m.group(1)): m.group(2)
                for m in re.finditer(r"^([A-Za-z0-9_.\-]+)==([^\s;#]+)", fh.read(), re.M)}
    _, extras = metadata
    for extra in ("report", "bag"):
        for req in extras[extra]:
            name = canonicalize_name(req.name)
            assert name in pins, f"{req} (extra {extra}) is not pinned in requirements/jazzy.lock"
            assert req.specifier.contains(pins[name]), f"{req} excludes the tested {name}=={pins[name]}"


# ---------------------------------------------------------------------------------------------
# require()

def test_require_returns_the_module():
    assert require("json", "bag", "test").dumps([1]) == "[1]"


def test_require_names_purpose_module_and_pip_command():
    with pytest.raises(MissingDependency) as info:
        require("inclinometer_calib_no_such_module.sub", "report", "lab report")
    assert str(info.value) == ("lab report needs inclinometer_calib_no_such_module, which is not installed: "
                               "pip install 'inclinometer_calib[report]'")
    assert isinstance(info.value, ImportError)  # code probing with `except ImportError` still works


# ---------------------------------------------------------------------------------------------
# the CLI without the optional packages

BLOCKING_RUNNER = r"""
import sys

blocked = set(sys.argv[1].split(",")) - {""}


class NotInstalled:
    '''First meta-path finder: the blocked top-level modules behave as if not installed.'''

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in blocked:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, NotInstalled())
for name in [m for m in sys.modules if m.split(".")[0] in blocked]:
    del sys.modules[name]
sys.argv = ["inclinometer-calib"] + sys.argv[2:]
from inclinometer_calib.apps.cli import main

sys.exit(main())
"""


def run_cli(args, blocked, cwd):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([ROOT] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return subprocess.run([sys.executable, "-c", BLOCKING_RUNNER, ",".join(blocked), *map(str, args)],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """A simulated calibration + validation log, and the validation log as a bag."""
    d = tmp_path_factory.mktemp("sim")
    assert cli.main(["simulate", "--out", str(d), "--seed", "3"]) == 0
    log, _ = read_csv(d / "val.csv")
    write_probe_bag(log, d / "val.mcap")
    return d


def _one_line_error(r, expected):
    """Exit status 2, no traceback, and the hint as the one error line, last (warnings about the
    data may come before it)."""
    assert r.returncode == 2, f"exit {r.returncode}; stderr:\n{r.stderr}"
    assert "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert lines[-1:] == [expected], r.stderr
    assert [line for line in lines if line.startswith("error:")] == [expected], r.stderr


def test_core_commands_work_without_the_optional_packages(logs, tmp_path):
    for args in (["twelve-position", logs / "cal.csv", "-o", "coeffs.yaml"],
                 ["correct", logs / "val.csv", "--coeffs", "coeffs.yaml", "-o", "stations.csv"]):
        r = run_cli(args, OPTIONAL_MODULES, tmp_path)
        assert r.returncode == 0, f"{args}: exit {r.returncode}\n{r.stderr}"


def test_lab_report_without_matplotlib(logs, tmp_path):
    r = run_cli(["lab", "report", "--cal", logs / "cal.csv", "--val", logs / "val.csv", "--site", logs / "site.yaml",
                 "-o", "report.html", "--quiet"], OPTIONAL_MODULES, tmp_path)
    _one_line_error(r, "error: lab report needs matplotlib, which is not installed: "
                       "pip install 'inclinometer_calib[report]'")
    assert not (tmp_path / "report.html").exists()


@pytest.mark.parametrize("blocked, missing", [(OPTIONAL_MODULES, "mcap"), (("rosbags",), "rosbags")])
def test_reprocess_without_the_bag_packages(logs, tmp_path, blocked, missing):
    r = run_cli(["reprocess", logs / "val.mcap", "--coeffs", "none", "-o", "out.mcap"], blocked, tmp_path)
    _one_line_error(r, f"error: reprocess needs {missing}, which is not installed: "
                       "pip install 'inclinometer_calib[bag]'")
    assert not (tmp_path / "out.mcap").exists()


def test_bag_from_csv_without_the_bag_packages(logs, tmp_path):
    r = run_cli(["bag", "from-csv", logs / "val.csv", "-o", "val.mcap"], OPTIONAL_MODULES, tmp_path)
    _one_line_error(r, "error: writing a probe log as a bag needs mcap, which is not installed: "
                       "pip install 'inclinometer_calib[bag]'")
    assert not (tmp_path / "val.mcap").exists()


@pytest.mark.parametrize("args, purpose", [
    (["fleet", "register", "P1", "--db", "fleet.db"], "fleet register"),
    (["fleet", "history", "P1", "--db", "fleet.db"], "fleet history"),
    (["fleet", "reprocess", "x.mcap", "-o", "out"], "fleet reprocess"),
])
def test_fleet_commands_without_the_fleet_packages_say_so_before_they_start(tmp_path, args, purpose):
    r = run_cli(args, OPTIONAL_MODULES, tmp_path)
    _one_line_error(r, f"error: {purpose} needs sqlalchemy, which is not installed: "
                       "pip install 'inclinometer_calib[fleet]'")
    assert not list(tmp_path.iterdir())          # no registry, no output folder


def test_a_probe_log_is_read_row_by_row_without_pyarrow(logs, tmp_path):
    """The core reads probe logs without the ``fast`` extra: the row reader, the same numbers."""
    r = run_cli(["correct", logs / "val.csv", "--coeffs", "none", "--json"], ("pyarrow", "numba"), tmp_path)
    assert r.returncode == 0, r.stderr
    fast = run_cli(["correct", logs / "val.csv", "--coeffs", "none", "--json"], (), tmp_path)
    assert r.stdout == fast.stdout and r.stdout


# ---------------------------------------------------------------------------------------------
# the wheel

@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """The wheel pip builds from this tree (no dependencies fetched: --no-deps, no build isolation)."""
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                        "--disable-pip-version-check", "-w", str(out), ROOT], capture_output=True, text=True,
                       timeout=300, cwd=out)
    assert r.returncode == 0, r.stderr
    (path,) = out.glob("inclinometer_calib-*.whl")
    return path


def test_the_wheel_carries_the_message_definitions_and_reprocess_finds_them_where_it_installs_them(
        wheel, logs, tmp_path):
    """``pip install '.[all]'`` and then ``reprocess``: the SurveyStation definition comes with the
    wheel (it failed on every bag: msg/ was not shipped).  Installed into a prefix of its own (no
    dependencies: those of this environment serve), reprocess run from outside the source tree
    finds the definitions there — with this repository's msg/ folder out of reach."""
    import zipfile

    names = zipfile.ZipFile(wheel).namelist()
    data = [n for n in names if ".data/data/share/inclinometer_calib/" in n]
    assert {n.rsplit("/", 2)[-2] + "/" + n.rsplit("/", 1)[-1] for n in data} >= {
        "msg/SurveyStation.msg", "msg/CalibrationCoefficients.msg", "msg/StreamProgress.msg",
        "msg/CalibrationStatus.msg", "srv/RecapturePose.srv"}, data
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    reqs = [Requirement(line.split(":", 1)[1].strip()) for line in
            zipfile.ZipFile(wheel).read(meta).decode().splitlines() if line.startswith("Requires-Dist:")]
    core = {canonicalize_name(r.name) for r in reqs if r.marker is None}
    assert core == CORE and not core & NOT_CORE, sorted(core)      # what a plain install pulls
    prefix = tmp_path / "prefix"
    # --ignore-installed: beside this environment's editable install, not instead of it; --no-compile:
    # the probe below compiles what it imports, not every module of the package (0.7 CPU-s)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed", "-q",
                        "--no-compile", "--disable-pip-version-check", "--prefix", str(prefix), str(wheel)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    (site,) = prefix.glob("lib/python*/site-packages")
    probe = textwrap.dedent(f"""
        import sys
        sys.prefix = {str(prefix)!r}                 # as if the wheel were installed in this environment
        import inclinometer_calib, inclinometer_calib.io.bag as bag
        assert inclinometer_calib.__file__.startswith({str(site)!r}), inclinometer_calib.__file__
        bag._REPO_MSG_DIR = bag.Path("/nonexistent")   # this repository's msg/ out of reach
        from inclinometer_calib.apps.cli import main
        sys.exit(main(["reprocess", {str(logs / "val.mcap")!r}, "--coeffs", "none", "-o", "out.mcap"]))
    """)
    # -S: no .pth files, so not this environment's editable install of the source tree either
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH")}
    env["PYTHONPATH"] = os.pathsep.join([str(site)] + [p for p in sys.path if p.endswith("site-packages")])
    r = subprocess.run([sys.executable, "-S", "-c", probe], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "out.mcap").stat().st_size > 0

"""pip/setuptools entry point for the ROS-free core and the CLI.

In a ROS 2 workspace the package is built by colcon through ``package.xml`` (build type
ament_cmake, see ``CMakeLists.txt`` and ``docs/packaging.md``); this file serves plain
``pip install .`` (core + CLI, no ROS needed; ``pip install '.[all]'`` adds the optional parts, see
``EXTRAS``) and the PyPI-based development environment.
"""
import glob

from setuptools import find_packages, setup

# Optional parts (pip install '.[report]', '.[bag]', '.[fleet]', ..., '.[all]'); without them the
# commands that need them stop with a one-line hint before they start (inclinometer_calib/core/deps.py).
# The bag extra's lower bounds are the versions of requirements/jazzy.lock, the tested environment
# (rosbags changes its API between minor versions); test/test_extras.py checks the lock satisfies
# every bound.
EXTRAS = {
    # lab report: plots (inclinometer_calib/lab/report.py)
    "report": ["matplotlib>=3.7"],
    # reprocess, bags (inclinometer_calib/io/bag.py, reprocess.py, the launcher's summary): the MCAP
    # writer, its chunk compressions, and rosbags (type store, CDR, reading for the summary)
    "bag": ["mcap>=1.6", "zstandard>=0.25", "lz4>=4.4", "rosbags>=0.11.9"],
    # the lab's discovery beyond the catalogue (inclinometer_calib/lab/discover.py): sparse regression
    "lab": ["scikit-learn>=1.5"],
    # the fleet (inclinometer_calib/fleet/): the registry's database and migrations, PostgreSQL,
    # reprocessing on Dask into Parquet
    "fleet": ["sqlalchemy>=2.0", "alembic>=1.13", "psycopg[binary]>=3.1", "dask>=2026.8.0",
              "distributed>=2026.8.0", "pyarrow>=26.0"],
    # the live view in Foxglove (inclinometer_calib/nodes/live.py)
    "live": ["foxglove-sdk>=0.30.3"],
    # speed: the fused batch-correction kernel (inclinometer_calib/core/batchkernel.py; numpy without it)
    # and the column-wise probe-log reader (inclinometer_calib/io/probelog.py; row by row without it)
    "fast": ["numba>=0.68.1", "pyarrow>=26.0"],
}
EXTRAS["all"] = sorted({req for reqs in EXTRAS.values() for req in reqs})
EXTRAS["test"] = ["pytest>=7", "hypothesis>=6"]
#: The interface definitions the bags and messages need (reprocess writes SurveyStation with its
#: definition), installed where ROS keeps them: <prefix>/share/inclinometer_calib/{msg,srv}
#: (:class:`inclinometer_calib.io.bag.MessageDefinitions` looks there under sys.prefix).
INTERFACES = [(f"share/inclinometer_calib/{kind}", sorted(glob.glob(f"{kind}/*.{kind}"))) for kind in ("msg", "srv")]

setup(
    name="inclinometer_calib",
    version="0.1.0",
    description="Calibration and live correction of magnetic borehole inclinometers (ROS 2 Jazzy)",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["inclinometer_calib", "inclinometer_calib.*"]),
    # the core: the numerics, the site's field (WMM/IGRF, projections), WITSML out, progress bars
    install_requires=["numpy>=1.24", "scipy>=1.10", "PyYAML>=6.0",
                      # one BLAS thread around the lab's small fits (inclinometer_calib/calibrate/blas.py)
                      "threadpoolctl>=3.1",
                      "pygeomag>=1.1", "ppigrf>=2.1", "pyproj>=3.6",
                      # WITSML 2.1 / 1.4.1.1 out (inclinometer_calib/rig/witsml.py): building, reading, validating
                      "lxml>=6.1",
                      "tqdm>=4.66"],
    data_files=INTERFACES,
    # the Energistics schemas the WITSML documents are validated against (rig/schemas/witsml21/README.md,
    # rig/schemas/witsml1411/README.md)
    package_data={"inclinometer_calib": ["rig/schemas/witsml21/README.md",
                                         "rig/schemas/witsml21/energyml/data/*/*/xsd_schemas/*.xsd",
                                         "rig/schemas/witsml1411/README.md",
                                         "rig/schemas/witsml1411/*/xsd_schemas/*.xsd",
                                         # the fleet registry's Alembic environment and schema versions
                                         "fleet/migrations/README", "fleet/migrations/*.py",
                                         "fleet/migrations/script.py.mako", "fleet/migrations/versions/*.py"]},
    extras_require=EXTRAS,
    entry_points={
        "console_scripts": [
            "inclinometer-calib = inclinometer_calib.apps.cli:main",
            # ROS 2 nodes and the launcher for PyPI environments (need rclpy + built messages)
            "inclinometer-calib-probe = inclinometer_calib.nodes.probe:main",
            "inclinometer-calib-calibration = inclinometer_calib.nodes.calibration:main",
            "inclinometer-calib-correction = inclinometer_calib.nodes.correction:main",
            "inclinometer-calib-recorder = inclinometer_calib.nodes.recorder:main",
            "inclinometer-calib-wits = inclinometer_calib.nodes.wits:main",
            "inclinometer-calib-live = inclinometer_calib.nodes.live:main",
            "inclinometer-calib-launch = inclinometer_calib.apps.launcher:main",
        ],
    },
)

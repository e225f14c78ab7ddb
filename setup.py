"""pip/setuptools entry point for the ROS-free core and the CLI.

In a ROS 2 workspace the package is built by colcon through ``package.xml`` (build type
ament_cmake, see ``CMakeLists.txt`` and ``docs/packaging.md``); this file serves plain
``pip install .`` (core + CLI, no ROS needed) and the PyPI-based development environment.
"""
from setuptools import find_packages, setup

setup(
    name="inclinometer_calib",
    version="0.1.0",
    description="Calibration and live correction of magnetic borehole inclinometers (ROS 2 Jazzy)",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["inclinometer_calib", "inclinometer_calib.*"]),
    install_requires=["numpy>=1.24", "scipy>=1.10", "PyYAML>=6.0"],
    extras_require={"report": ["matplotlib>=3.7"], "test": ["pytest>=7", "hypothesis>=6"]},
    entry_points={
        "console_scripts": [
            "inclinometer-calib = inclinometer_calib.cli:main",
            # ROS 2 nodes and the launcher for PyPI environments (need rclpy + built messages)
            "inclinometer-calib-probe = inclinometer_calib.nodes.probe:main",
            "inclinometer-calib-calibration = inclinometer_calib.nodes.calibration:main",
            "inclinometer-calib-correction = inclinometer_calib.nodes.correction:main",
            "inclinometer-calib-recorder = inclinometer_calib.nodes.recorder:main",
            "inclinometer-calib-launch = inclinometer_calib.launcher:main",
        ],
    },
)

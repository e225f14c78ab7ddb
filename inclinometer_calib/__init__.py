"""inclinometer_calib: calibration and correction of magnetic borehole inclinometers.

The package is in layers; each imports only the ones before it (test/core/test_layers.py):

``core`` (frames, site, error model, effects, record, station, survey QC) → ``detect`` (static
holds, gates, noise) → ``io`` (probe logs, bags, messages) → ``calibrate`` (twelve-position,
turntable, capture, the model fit, the simulator) → ``correct`` (the survey pipeline, the stream
engine, reprocessing, axial, MSA, ISCWSA, trajectory) → ``rig`` (WITS, WITSML, the live view) →
``lab`` → ``fleet`` → ``nodes`` (the ROS 2 adapters) → ``apps`` (CLI, launcher, replay test).

Only ``nodes`` and ``apps`` touch rclpy or ROS message types.

Why ``extend_path``: the generated message modules (``inclinometer_calib.msg`` /
``inclinometer_calib.srv``) are installed by rosidl into a *different* directory named
``inclinometer_calib`` (the colcon install tree) than these sources.  Extending ``__path__``
over every ``inclinometer_calib`` directory on ``sys.path`` lets one import name serve both,
whichever of the two comes first.
"""
from pkgutil import extend_path

__path__ = extend_path(__path__, __name__)

__version__ = "0.1.0"

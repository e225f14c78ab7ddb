"""inclinometer_calib: calibration and correction of magnetic borehole inclinometers.

The numerical core (``frames``, ``errormodel``, ``twelve_position``, ``effects``, ``simulate``,
``probelog``, ``survey``, ``coeffs``) imports neither rclpy nor ROS message types.  The ROS 2
adapters live in ``inclinometer_calib.nodes``.

Why ``extend_path``: the generated message modules (``inclinometer_calib.msg`` /
``inclinometer_calib.srv``) are installed by rosidl into a *different* directory named
``inclinometer_calib`` (the colcon install tree) than these sources.  Extending ``__path__``
over every ``inclinometer_calib`` directory on ``sys.path`` lets one import name serve both,
whichever of the two comes first.
"""
from pkgutil import extend_path

__path__ = extend_path(__path__, __name__)

__version__ = "0.1.0"

"""ROS 2 nodes: thin adapters around the ROS-free core (parameters, topics, QoS, unit conversion).

Each module has a ``main()`` (``python -m inclinometer_calib.nodes.<name>``):

* :mod:`.probe` — publishes ``/probe/imu``, ``/probe/mag``, ``/probe/temperature`` from the
  simulator, a probe-log CSV or a recorded MCAP bag;
* :mod:`.calibration` — live twelve-pose capture, publishes the coefficients (transient local);
* :mod:`.correction` — applies the coefficients, publishes survey stations and diagnostics;
* :mod:`.recorder` — records the graph into an MCAP (rosbag2) file.

Shared helpers live in :mod:`.common`.  Nothing in the core imports this package.

May import: every layer below (``core`` … ``fleet``) and rclpy and the messages; not ``apps``
(the launcher starts the nodes, the nodes never import the launcher).
"""

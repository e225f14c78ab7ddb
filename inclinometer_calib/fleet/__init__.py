"""Fleet: the probe registry and calibration history (``registry``, ``history``) and reprocessing
many bags on a distributed engine (``reprocess``, ``manifest``).

Importable without rclpy, like the rest of the core; the database and Dask packages are imported
by the modules that need them.

May import: ``core``, ``detect``, ``io``, ``calibrate``, ``correct``, ``rig``, ``lab``.
"""

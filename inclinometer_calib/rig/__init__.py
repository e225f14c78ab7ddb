"""What a rig's data systems take: WITS0 records (``wits``), WITSML 2.1 and 1.4.1.1 trajectory
documents validated against the vendored Energistics schemas (``witsml``, ``schemas/``) and the
live view's content (``liveview``: the station table, the 3D scene, the run report's status words).

May import: ``core``, ``detect``, ``io``, ``calibrate``, ``correct``.
"""

"""Survey correction: the one pipeline from a station to a corrected, QC'd, positioned survey
station (``pipeline``), the stream engine the nodes and the offline reprocessing share
(``engine``), the reprocessing of a recorded run (``reprocess``), short-collar axial correction
(``axial``), multi-station analysis (``msa``), the ISCWSA error model (``iscwsa``) and the
trajectory by minimum curvature (``trajectory``).

May import: ``core``, ``detect``, ``io``, ``calibrate``.
"""

"""The core: the conventions, the models and the records every other layer builds on.

``frames`` (NED, tool Z down-hole, R = Rz(azimuth)·Ry(drift)·Rz(toolface), Table 1's poses, the
specific-force sign flip, the site reference ``Site``), ``formulas`` (the correction, angles and
QC written once, for numpy and the numba kernel), ``geomag`` (the site's field from a
location: WMM/IGRF, gravity, grid convergence, the one north), ``errormodel`` (a triad's bias,
scale and non-orthogonality), ``effects`` (the effect catalogue), ``model`` (a probe model: triads
plus effects), ``plugins`` (user effects), ``coeffs`` (the calibration record), ``station`` (a
static hold and the one correction path of stations), ``survey`` (drift, azimuth, toolface and
their QC from g and b; the batch path with ``batchkernel``/``_batch_numba``), ``output`` (every
file written: temp name + rename), ``yamltext`` (YAML in and out, libyaml when present), ``memo`` (the
last results of repeated work, handed out as copies), ``specfun`` (the χ², F and t distribution
functions the detector and the lab's tests need, without scipy.special's imports) and ``deps``
(optional dependencies, one-line hints).

May import: nothing of the package outside ``core`` — and neither ``rclpy`` nor message types
(test/core/test_layers.py, test/core/test_core_without_ros.py).
"""

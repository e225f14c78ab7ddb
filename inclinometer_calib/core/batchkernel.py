"""The batch correction of raw samples, fused into one compiled pass (numba), with the blocked
numpy path of :func:`survey.correct_samples` as the fallback that gives the same numbers.

:func:`survey.correct_samples` (the one batch path) runs on this kernel (:func:`fused`) when its
backend resolves to ``numba``, and returns the same dict: both triads corrected, ``drift_deg``, ``azimuth_deg``, ``toolface_deg``, ``total_gravity``
(m/s²), ``total_field`` (nT), ``dip_deg`` (float64) and ``flags``, ``status`` (uint8; bits
``survey.FLAG_*``) per sample.  Backends:

* ``numba`` — :mod:`_batch_numba`: one pass, per sample ``v = C·(h − B)`` per triad
  (the record's base model: :func:`formulas.corrected`, as :meth:`errormodel.TriadModel.inverse`)
  then :func:`formulas.survey` (angles, QC, status), the very text numpy runs for the station
  path, compiled by numba and inlined; no array of N samples besides the outputs.  A record with
  effects beyond the base model (Newton steps, temperature, time: :class:`model.CorrectionPlan`)
  is corrected block by block through :meth:`coeffs.Calibration.correct` — the one correction
  path, whatever the effect — and the kernel then does the angles and QC of each block.
  Agreement with the station path ``evaluate(*calibration.correct(g, m), site, tol)``: every
  addition and multiplication is numpy's, in the same order (no ``fastmath``), so |G|, |B| and
  the corrected vectors are bit-identical; the arc tangents are the kernel's own (within 1 ulp of
  numpy's), so the angles differ by at most a few 1e-14 degrees (``test/core/test_batch_kernel.py``
  pins 1e-9°).  The flags follow from the same comparisons: a value within an ulp of a QC
  threshold could in principle tip the other way.
* ``numpy`` — the blocked numpy body of :func:`survey.correct_samples`: :func:`formulas.survey`
  on numpy arrays, block by block (bit-identical to the station path).
* ``auto`` (default) — numba when it can be imported, else numpy.  The environment variable
  ``INCLINOMETER_CALIB_BATCH_BACKEND`` (``auto``, ``numba``, ``numpy``) sets the default.

Compilation: the first call in a process compiles the kernel (a few seconds) or loads it from
numba's on-disk cache (well under a second); :func:`warm_up` does it up front and says how long
it took.  The cache is ``$NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/inclinometer_calib/numba``
(``~/.cache/...``): the user's cache, not the installed package's directory; in it, a directory
per text of :mod:`formulas` (:func:`_kernels`: numba would not see a change there).

Threads: ``threads`` (None: ``$INCLINOMETER_CALIB_BATCH_THREADS``, else the CPUs this process may
run on) splits the samples into contiguous slices, a few per thread, each corrected by the
kernel on a thread of a pool (the kernel releases the GIL; the threads block when idle, they do
not spin).  Every sample's numbers are the same whatever the split (``test/core/test_batch_kernel.py``
pins the bits).  Fewer than :data:`MIN_SLICE` samples per slice run on the calling thread.  One
thread corrects ≈ 75 M samples/s on the machine of ``docs/benchmarks.md``, about half of what its
memory can move; two reach the memory's limit.  (numba's own ``prange`` on OpenMP threads was
tried first: its threads spin while they wait, and with other work on the 2 cores it was 3–4×
slower than one thread.)
"""
from __future__ import annotations

import hashlib
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import formulas
from .frames import Site

BACKEND_ENV = "INCLINOMETER_CALIB_BATCH_BACKEND"
BACKENDS = ("auto", "numba", "numpy")
THREADS_ENV = "INCLINOMETER_CALIB_BATCH_THREADS"
#: fewest samples in a slice of its own: below this a thread's hand-off (tens of µs) is not paid back
MIN_SLICE = 65536
#: slices per thread: a thread that the OS shares with other work takes fewer of them
SLICES_PER_THREAD = 4
_kernel_module = None
_pools: dict = {}
_pools_lock = threading.Lock()


def cache_dir() -> str:
    """Where numba keeps the compiled kernel: ``$NUMBA_CACHE_DIR``, else the user's cache."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return os.environ["NUMBA_CACHE_DIR"]
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "inclinometer_calib", "numba")


def numba_available() -> bool:
    """True when numba can be imported (the kernel itself is compiled on first use)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: str | None = None) -> str:
    """``numba`` or ``numpy`` for a requested backend (None: ``$INCLINOMETER_CALIB_BATCH_BACKEND``,
    else ``auto``).  Asking for ``numba`` without numba installed raises (never a silent
    substitute for an explicit request)."""
    req = backend if backend is not None else (os.environ.get(BACKEND_ENV) or "auto")
    if req not in BACKENDS:
        where = "backend" if backend is not None else f"${BACKEND_ENV}"
        raise ValueError(f"correct_samples: {where} must be one of {', '.join(BACKENDS)}, got {req!r}")
    if req == "auto":
        return "numba" if numba_available() else "numpy"
    if req == "numba" and not numba_available():
        raise ImportError("correct_samples: the numba backend needs numba (pip install numba; "
                          "requirements/core.txt pins it), or use backend='numpy'")
    return req


def _kernels():
    """The compiled kernels' module, with numba's cache in :func:`cache_dir`, in a directory of
    its own per text of :mod:`formulas` (numba checks the kernel's own file for changes, not the
    files of the functions it inlines: a kernel compiled from another version of the formulas
    must not be loaded)."""
    global _kernel_module
    if _kernel_module is None:
        import numba

        with open(formulas.__file__, "rb") as fh:
            digest = hashlib.sha256(fh.read()).hexdigest()[:16]
        given = numba.config.CACHE_DIR
        numba.config.CACHE_DIR = os.path.join(cache_dir(), f"formulas-{digest}")   # read as the kernels are decorated
        try:
            from . import _batch_numba
        finally:
            numba.config.CACHE_DIR = given
        _kernel_module = _batch_numba
    return _kernel_module


def warm_up(tol) -> float:
    """Compile the kernel (or load it from the disk cache) now, for QC tolerances ``tol`` (a
    :class:`survey.Tolerances`); returns the seconds it took."""
    t0 = time.perf_counter()
    _run(np.zeros(3), np.zeros(3), True, _IDENTITY, _IDENTITY, Site(), tol, _alloc(1))
    return time.perf_counter() - t0


#: The per-sample outputs of a batch (:func:`survey.correct_samples`), besides ``flags`` and ``status``.
BATCH_KEYS = ("drift_deg", "azimuth_deg", "toolface_deg", "total_gravity", "total_field", "dip_deg")


def _alloc(n):
    out = {k: np.empty(n) for k in BATCH_KEYS}
    out["flags"] = np.empty(n, dtype=np.uint8)
    out["status"] = np.empty(n, dtype=np.uint8)
    return out


def resolve_threads(threads: int | None = None) -> int:
    """Threads for the kernel: ``threads``; None: ``$INCLINOMETER_CALIB_BATCH_THREADS``, else the
    CPUs this process may run on.  Not a whole number ≥ 1: an error naming where it came from."""
    src = "threads"
    if threads is None:
        env = os.environ.get(THREADS_ENV, "").strip()
        if not env:
            cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(os.cpu_count() or 1)
            return max(1, len(cpus))
        src, threads = f"${THREADS_ENV}", env
    if isinstance(threads, str):
        ok = threads.strip().isdigit()
    else:
        ok = isinstance(threads, (int, np.integer)) and not isinstance(threads, bool)
    value = int(threads) if ok else 0
    if value < 1:
        raise ValueError(f"correct_samples: {src} must be a whole number of threads ≥ 1, got {threads!r}")
    return value


def _pool(threads: int) -> ThreadPoolExecutor:
    with _pools_lock:
        if threads not in _pools:
            _pools[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="batchkernel")
        return _pools[threads]


def _slices(n: int, threads: int) -> list[tuple[int, int]]:
    """Contiguous [s, e) slices of n samples: up to SLICES_PER_THREAD per thread, none shorter than
    MIN_SLICE (one slice when n is small or one thread)."""
    k = min(threads * SLICES_PER_THREAD, n // MIN_SLICE) if threads > 1 else 1
    k = max(1, k)
    edges = [n * j // k for j in range(k + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _run(g_flat, m_flat, linear, cal_a, cal_m, site, tol, out, threads: int = 1):
    """The kernel on flat (3N,) inputs (gravity vector m/s², field nT) into ``out``; ``cal_a``/``cal_m``:
    (C's nine entries row by row, B's three) as float tuples, or None; ``threads`` > 1: slices on
    the pool (:func:`_slices`)."""
    k = _kernels()
    ca, ba = cal_a if cal_a is not None else _IDENTITY
    cm, bm = cal_m if cal_m is not None else _IDENTITY
    qc = formulas.qc_parameters(site, tol)
    outs = [out[key] for key in BATCH_KEYS] + [out["flags"], out["status"]]

    def piece(s, e):
        k.fused(g_flat[3 * s:3 * e], m_flat[3 * s:3 * e], bool(linear), ca, ba, cm, bm, qc,
                *(a[s:e] for a in outs))

    parts = _slices(len(g_flat) // 3, threads)
    if len(parts) == 1:
        piece(*parts[0])
        return
    for fut in [_pool(threads).submit(piece, s, e) for s, e in parts]:
        fut.result()


#: (C, B) of no correction: the kernel's coefficients when ``linear`` is False (unused, typed alike)
_IDENTITY = ((1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0))


def fused(g, m, calibration, site, tol, temp, tim, block: int, out: dict, correct_block,
          threads: int | None = None) -> dict:
    """The kernel's part of :func:`survey.correct_samples` (which checks the inputs and calls it
    when the backend resolves to ``numba``): ``g`` (N, 3) gravity vector (down positive), m/s²; ``m``
    (N, 3) nT; ``out`` the outputs (checked here).  A record with effects beyond the base model is
    corrected block by block by ``correct_block(g, b, temp, time)`` (the caller's: the one
    correction path), and the kernel then does the angles and QC of each block (on the calling
    thread).  ``threads``: see :func:`resolve_threads`."""
    n = len(g)
    _check_out(out, n)
    nt = resolve_threads(threads)
    if n == 0:
        return out
    if calibration is None:
        _run(np.ascontiguousarray(g).reshape(-1), np.ascontiguousarray(m).reshape(-1), False, None, None,
             site, tol, out, nt)
    elif not any(calibration.plan.extra.values()):
        _run(np.ascontiguousarray(g).reshape(-1), np.ascontiguousarray(m).reshape(-1), True,
             calibration.plan.coefficients["acc"], calibration.plan.coefficients["mag"], site, tol, out, nt)
    else:   # effects beyond the base model: the one correction path per block, then the kernel
        blk = max(1, min(int(block), n))
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for s in range(0, n, blk):
                e = min(s + blk, n)
                gc, bc = correct_block(g[s:e], m[s:e], None if temp is None else temp[s:e],
                                       None if tim is None else tim[s:e])
                _run(np.ascontiguousarray(gc).reshape(-1), np.ascontiguousarray(bc).reshape(-1), False,
                     None, None, site, tol, {k: v[s:e] for k, v in out.items()})
    return out


def _check_out(out: dict, n: int) -> None:
    for key in BATCH_KEYS + ("flags", "status"):
        a = out.get(key)
        dtype = np.uint8 if key in ("flags", "status") else np.float64
        if not isinstance(a, np.ndarray) or a.shape != (n,) or a.dtype != dtype or not a.flags.c_contiguous \
                or not a.flags.writeable:
            got = "missing" if a is None else f"{getattr(a, 'shape', '?')} {getattr(a, 'dtype', type(a).__name__)}"
            raise ValueError(f"correct_samples: out[{key!r}] must be a writeable C-contiguous ({n},) "
                             f"{np.dtype(dtype).name} array, got {got}")

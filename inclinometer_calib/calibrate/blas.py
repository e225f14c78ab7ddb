"""One BLAS thread for the lab's small dense algebra.

The lab's matrices are small: a fit's Jacobian is a few hundred residuals by a few tens of
parameters (``fit._uncertainty`` takes two SVDs of it), a wandering bias' smoother a few hundred
states.  OpenBLAS threads such calls all the same, and on a busy machine (the test suite's workers,
another job) each threaded call waits for a thread that is not running: measured on 2 cores at load
average 3, ``lab diagnose`` on the 44 000-row simulated logs took 17 s wall and 8.2 s CPU with
OpenBLAS' default two threads, 4.2 s and 4.0 s with one (the SVDs alone: 4.3 s → 0.02 s over 25
fits).  :func:`one_thread` holds every BLAS loaded in the process (numpy's and scipy's each bring an
OpenBLAS) at one thread for the duration of a call, through threadpoolctl, and restores what was
set.  BLAS' setting is process-wide: other threads of the process see one thread meanwhile.
"""
from __future__ import annotations

import functools
import threading

from threadpoolctl import ThreadpoolController

_controller = None
_lock = threading.Lock()


def _limits():
    """threadpoolctl's controller of the BLAS libraries loaded so far (made once: numpy and scipy,
    which bring them, are imported before any lab function runs)."""
    global _controller
    with _lock:
        if _controller is None:
            _controller = ThreadpoolController()
        return _controller.limit(limits=1, user_api="blas")


def one_thread(fn):
    """Decorator: ``fn`` runs with one BLAS thread (nested calls restore in turn)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _limits():
            return fn(*args, **kwargs)
    return wrapper

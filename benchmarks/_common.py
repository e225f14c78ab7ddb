"""Shared helpers of the benchmark scripts (timing, machine description, table printing)."""
from __future__ import annotations

import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:  # run as `python benchmarks/X.py` from anywhere
    sys.path.insert(0, ROOT)


def best_of(fn, repeat: int = 3, min_time: float = 0.0):
    """Best wall time (s) of ``repeat`` calls of ``fn()`` (and its last result)."""
    best, result = float("inf"), None
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t)
    return best, result


def interleaved(fns: dict, rounds: int = 5) -> dict:
    """Best wall time (s) of each ``fns[name]()`` over ``rounds`` round-robin rounds.

    Round-robin rather than one function after the other: on a shared machine a burst of other
    load then hits every variant alike, and the best-of ratios stay meaningful.
    """
    best = {k: float("inf") for k in fns}
    for _ in range(max(1, rounds)):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t)
    return best


def machine() -> str:
    import numpy as np

    cpu = "?"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (f"{time.strftime('%Y-%m-%d')}; {os.cpu_count()} cores (nproc {len(os.sched_getaffinity(0))}), "
            f"{cpu}; Python {platform.python_version()}, numpy {np.__version__}")


def table(rows, headers) -> str:
    cols = list(zip(*([headers] + [[str(c) for c in r] for r in rows])))
    widths = [max(len(x) for x in col) for col in cols]
    fmt = lambda r: "  ".join(str(c).rjust(w) for c, w in zip(r, widths))  # noqa: E731
    return "\n".join([fmt(headers), fmt(["-" * w for w in widths])] + [fmt(r) for r in rows])

"""Batch correction in the core: ``survey.correct_samples`` (fused kernel, ``batchkernel``) on 10⁶–10⁷ raw samples.

Both triads corrected, drift/azimuth/toolface, |G|, |B|, dip, QC flags and status per sample.
Baseline, measured in the same run: a numpy loop that only reads the same input arrays and writes
the same output arrays (one add per float output, block by block) — the memory-bound limit of any
implementation that has to move these bytes — on one thread and on the kernel's threads (the
same slices on the same pool); the faster of the two is the limit.  Target: the fused numba
kernel (its default threads: the CPUs this process may use) ≥ 0.7× it.
Variants: the kernel (default threads, and one thread), the numpy fallback
(``survey.correct_samples``, blocked), and ``survey.evaluate`` after ``Calibration.correct`` on the
whole arrays (the station path applied to every sample).
The kernel's first-call time is measured apart, in fresh processes: compiling into an empty
cache directory, then loading from it.

    python benchmarks/bench_batch_correction.py [--quick] [--sizes 1e6,1e7] [--repeat 5]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

import _common  # noqa: F401  (sys.path)
import numpy as np

from _common import ROOT, interleaved, machine, table
from inclinometer_calib.core import batchkernel
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site, tool_vectors
from inclinometer_calib.core.frames import wrap180
from inclinometer_calib.core.survey import BATCH_KEYS, Tolerances, correct_samples, evaluate

TARGET = 0.7

BYTES_PER_SAMPLE = 6 * 8 + 6 * 8 + 2  # read h, m (float64 ×3 each); write 6 float64 + 2 uint8


def make_data(n, seed=0):
    rng = np.random.default_rng(seed)
    probe = sim.build_probe(3)
    site = Site(declination_deg=-4.5)
    drift = rng.uniform(0, 180, n)
    drift[: n // 100] = rng.uniform(0, 4, n // 100)   # some near-vertical samples (magnetic toolface)
    g, b = tool_vectors(site, drift, rng.uniform(0, 360, n), rng.uniform(0, 360, n))
    h = probe.acc.forward(g) - rng.normal(0, 0.002, (n, 3))   # raw accelerometer, gravity convention (the core's)
    m = probe.mag.forward(b) + rng.normal(0, 20, (n, 3))
    return np.ascontiguousarray(h), np.ascontiguousarray(m), Calibration(acc=probe.acc, mag=probe.mag), site


def alloc(n):
    out = {k: np.empty(n) for k in BATCH_KEYS}
    out["flags"] = np.empty(n, dtype=np.uint8)
    out["status"] = np.empty(n, dtype=np.uint8)
    for a in out.values():
        a.fill(0)  # touch the pages outside the timed region
    return out


def baseline(h, m, out, block=4096):
    """Read every input element once, write every output element once (memory-bound limit)."""
    n = len(h)
    keys = BATCH_KEYS
    for s in range(0, n, block):
        e = min(s + block, n)
        fb, mb = h[s:e], m[s:e]
        for j, k in enumerate(keys):
            np.add(fb[:, j % 3], mb[:, j % 3], out=out[k][s:e])
        np.less(fb[:, 0], mb[:, 0], out=out["flags"][s:e].view(bool))
        np.less(fb[:, 1], mb[:, 1], out=out["status"][s:e].view(bool))
    return out


def baseline_threads(h, m, out, threads):
    """:func:`baseline` on the kernel's slices, on the kernel's thread pool (numpy's ufuncs release
    the GIL): the memory-bound limit with the kernel's threads."""
    parts = batchkernel._slices(len(h), threads)
    futs = [batchkernel._pool(threads).submit(baseline, h[s:e], m[s:e], {k: v[s:e] for k, v in out.items()})
            for s, e in parts]
    for fut in futs:
        fut.result()
    return out


def first_call_times():
    """Seconds of the kernel's first call in a new process: compiling into an empty cache
    directory, then loading from that cache (numba import included)."""
    code = "from inclinometer_calib.core import batchkernel as b, survey as s; print(b.warm_up(s.Tolerances()))"
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, NUMBA_CACHE_DIR=d, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
        return [float(subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True,
                                     text=True).stdout.split()[-1]) for _ in range(2)]


def max_angle_diff(res, ref):
    """Largest difference of the angles (deg) between two results, NaN where both are NaN skipped."""
    worst = 0.0
    for k in ("drift_deg", "azimuth_deg", "toolface_deg", "dip_deg"):
        d = np.abs(wrap180(res[k] - ref[k]))
        worst = max(worst, float(np.nanmax(d)))
    return worst


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes, three rounds")
    ap.add_argument("--sizes", help="comma list of sample counts (default 1e6,1e7; quick 2e5,1e6)")
    ap.add_argument("--repeat", type=int, default=5, help="round-robin rounds (best of)")
    ap.add_argument("--block", type=int, default=16384, help="block size of the numpy fallback")
    args = ap.parse_args(argv)
    sizes = [int(float(x)) for x in (args.sizes or ("2e5,1e6" if args.quick else "1e6,1e7")).split(",")]
    repeat = 3 if args.quick else args.repeat
    print(f"machine: {machine()}; load average {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} cores")
    if batchkernel.resolve_backend() != "numba":
        sys.exit("bench_batch_correction: numba is not installed (the fused kernel is what this measures)")
    cold, warm = first_call_times()
    print(f"kernel first call in a new process: compile {cold:.2f} s (empty cache), load {warm:.2f} s (disk cache, "
          f"numba import included); cache dir here: {batchkernel.cache_dir()}")
    batchkernel.warm_up(Tolerances())
    rows = []
    tol = Tolerances()
    for n in sizes:
        h, m, cal, site = make_data(n)
        out = alloc(n)
        nt = batchkernel.resolve_threads()
        fns = {"baseline": lambda: baseline(h, m, out),
               "baseline_mt": lambda: baseline_threads(h, m, out, nt),
               "numba": lambda: correct_samples(h, m, cal, site, tol, out=out, backend="numba"),
               "numba1": lambda: correct_samples(h, m, cal, site, tol, out=out, backend="numba", threads=1)}
        fns["numpy"] = lambda: correct_samples(h, m, cal, site, tol, block=args.block, out=out, backend="numpy")
        best = interleaved(fns, repeat)
        tb = min(best["baseline"], best["baseline_mt"])
        names = {"baseline": "baseline: read inputs + write outputs, 1 thread",
                 "baseline_mt": f"baseline on {nt} threads ({len(batchkernel._slices(n, nt))} slices)",
                 "numba": f"fused kernel (numba, {nt} threads)", "numba1": "fused kernel (numba, 1 thread)",
                 "numpy": f"numpy fallback survey.correct_samples (block {args.block})"}
        for key, tk in best.items():
            ratio = tb / tk
            mark = " ✓" if key == "numba" and ratio >= TARGET else (" ✗" if key == "numba" else "")
            rows.append([f"{n:.0e}", names[key], f"{tk:.4f}", f"{n / tk / 1e6:.1f}",
                         f"{n * BYTES_PER_SAMPLE / tk / 1e9:.2f}", f"{ratio:.2f}{mark}"])
        if n <= 2_000_000:
            def station_path():
                with np.errstate(invalid="ignore"):
                    g, b = cal.correct(h, m)
                    return evaluate(g, b, site, tol)
            best = interleaved({"baseline": fns["baseline"], "evaluate": station_path}, max(1, repeat - 2))
            te, tb2 = best["evaluate"], best["baseline"]
            rows.append([f"{n:.0e}", "evaluate(Calibration.correct(...)) whole-array", f"{te:.4f}",
                         f"{n / te / 1e6:.1f}", f"{n * BYTES_PER_SAMPLE / te / 1e9:.2f}", f"{tb2 / te:.2f}"])
            ref = station_path()
            fused = correct_samples(h, m, cal, site, tol, backend="numba")
            fb = correct_samples(h, m, cal, site, tol, block=args.block, backend="numpy")
            same = all(np.array_equal(fb[k], ref[k], equal_nan=True) for k in BATCH_KEYS) and \
                np.array_equal(fb["status"], ref["status"])
            flags = np.array_equal(fused["flags"], fb["flags"]) and np.array_equal(fused["status"], fb["status"])
            rows.append([f"{n:.0e}", f"  (kernel vs station path: angles within {max_angle_diff(fused, ref):.1e}°, "
                         f"flags+status equal: {flags}; numpy fallback bitwise: {same})", "", "", "", ""])
        del h, m, out
    print(table(rows, ["N", "variant", "best s", "Msamples/s", "GB/s moved", "× baseline"]))
    print(f"(GB/s counts the {BYTES_PER_SAMPLE} bytes each sample must move: inputs read + outputs written; "
          f"× baseline is against the faster baseline of each size; target: fused kernel ≥ {TARGET}×)")


if __name__ == "__main__":
    main()

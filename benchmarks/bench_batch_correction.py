"""Batch correction in the core: ``survey.correct_samples`` on 10⁶–10⁷ raw samples.

Both triads corrected, drift/azimuth/toolface, |G|, |B|, dip, QC flags and status per sample.
Baseline, measured in the same run: a numpy loop that only reads the same input arrays and writes
the same output arrays (one add per float output, block by block like the kernel) — the
memory-bound limit of any implementation that has to move these bytes.  Target: ≥ 0.25× it.
Also shown: ``survey.evaluate`` after ``Calibration.correct`` on the whole arrays (the station
path applied to every sample; whole-array temporaries).

    python benchmarks/bench_batch_correction.py [--quick] [--sizes 1e6,1e7] [--repeat 3]
"""
from __future__ import annotations

import argparse

import _common  # noqa: F401  (sys.path)
import numpy as np

from _common import interleaved, machine, table
from inclinometer_calib import simulate as sim
from inclinometer_calib.coeffs import Calibration
from inclinometer_calib.frames import Site, tool_vectors
from inclinometer_calib.survey import BATCH_KEYS, Tolerances, correct_samples, evaluate

BYTES_PER_SAMPLE = 6 * 8 + 6 * 8 + 2  # read f, m (float64 ×3 each); write 6 float64 + 2 uint8


def make_data(n, seed=0):
    rng = np.random.default_rng(seed)
    probe = sim.build_probe(3)
    site = Site(declination_deg=-4.5)
    drift = rng.uniform(0, 180, n)
    drift[: n // 100] = rng.uniform(0, 4, n // 100)   # some near-vertical samples (magnetic toolface)
    g, b = tool_vectors(site, drift, rng.uniform(0, 360, n), rng.uniform(0, 360, n))
    f = -probe.acc.forward(g) + rng.normal(0, 0.002, (n, 3))
    m = probe.mag.forward(b) + rng.normal(0, 20, (n, 3))
    return np.ascontiguousarray(f), np.ascontiguousarray(m), Calibration(acc=probe.acc, mag=probe.mag), site


def alloc(n):
    out = {k: np.empty(n) for k in BATCH_KEYS}
    out["flags"] = np.empty(n, dtype=np.uint8)
    out["status"] = np.empty(n, dtype=np.uint8)
    for a in out.values():
        a.fill(0)  # touch the pages outside the timed region
    return out


def baseline(f, m, out, block=4096):
    """Read every input element once, write every output element once (memory-bound limit)."""
    n = len(f)
    keys = BATCH_KEYS
    for s in range(0, n, block):
        e = min(s + block, n)
        fb, mb = f[s:e], m[s:e]
        for j, k in enumerate(keys):
            np.add(fb[:, j % 3], mb[:, j % 3], out=out[k][s:e])
        np.less(fb[:, 0], mb[:, 0], out=out["flags"][s:e].view(bool))
        np.less(fb[:, 1], mb[:, 1], out=out["status"][s:e].view(bool))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes, one repeat")
    ap.add_argument("--sizes", help="comma list of sample counts (default 1e6,1e7; quick 2e5,1e6)")
    ap.add_argument("--repeat", type=int, default=5, help="round-robin rounds (best of)")
    ap.add_argument("--blocks", default="4096,16384", help="kernel block sizes to try, comma list")
    args = ap.parse_args(argv)
    sizes = [int(float(x)) for x in (args.sizes or ("2e5,1e6" if args.quick else "1e6,1e7")).split(",")]
    repeat = 3 if args.quick else args.repeat
    blocks = [int(x) for x in args.blocks.split(",")]
    print(f"machine: {machine()}")
    rows = []
    tol = Tolerances()
    for n in sizes:
        f, m, cal, site = make_data(n)
        out = alloc(n)
        fns = {"baseline": lambda: baseline(f, m, out)}
        for blk in blocks:
            fns[blk] = (lambda blk=blk: correct_samples(f, m, cal, site, tol, block=blk, out=out))
        best = interleaved(fns, repeat)
        tb = best["baseline"]
        rows.append([f"{n:.0e}", "baseline: read inputs + write outputs", f"{tb:.4f}", f"{n / tb / 1e6:.1f}",
                     f"{n * BYTES_PER_SAMPLE / tb / 1e9:.2f}", "1.00"])
        for blk in blocks:
            tk = best[blk]
            rows.append([f"{n:.0e}", f"correct_samples (block {blk})", f"{tk:.4f}", f"{n / tk / 1e6:.1f}",
                         f"{n * BYTES_PER_SAMPLE / tk / 1e9:.2f}", f"{tb / tk:.2f}"])
        if n <= 2_000_000:
            def station_path():
                g, b = cal.correct(-f, m)
                return evaluate(g, b, site, tol)
            best = interleaved({"baseline": fns["baseline"], "evaluate": station_path}, max(1, repeat - 2))
            te, tb2 = best["evaluate"], best["baseline"]
            rows.append([f"{n:.0e}", "evaluate(Calibration.correct(...)) whole-array", f"{te:.4f}",
                         f"{n / te / 1e6:.1f}", f"{n * BYTES_PER_SAMPLE / te / 1e9:.2f}", f"{tb2 / te:.2f}"])
            res = correct_samples(f, m, cal, site, tol, block=blocks[0])
            ref = station_path()
            same = all(np.array_equal(res[k], ref[k], equal_nan=True) for k in BATCH_KEYS) and \
                np.array_equal(res["status"], ref["status"])
            rows.append([f"{n:.0e}", f"  (kernel == station path, bitwise: {same})", "", "", "", ""])
        del f, m, out
    print(table(rows, ["N", "variant", "best s", "Msamples/s", "GB/s moved", "× baseline"]))
    print(f"(GB/s counts the {BYTES_PER_SAMPLE} bytes each sample must move: inputs read + outputs written; "
          "target ≥ 0.25× baseline)")


if __name__ == "__main__":
    main()

"""Probe-log reading: ``probelog.read_csv`` with the vectorised reader against the row reader.

The log is a simulated survey (twelve poses, then stand-grid stations, 100 Hz) written with
``probelog.format_csv`` and repeated, time running on, to the size asked; one row in 10⁴ is made
bad (a NaN, a saturated axis, a time going back, a pose out of range, a short row: every kind
of rejection, each with its message), so the fall-back to the per-row code is part of the timing.
Baseline, timed in the same run: ``read_csv(..., engine="rows")``, the per-row parse (csv.reader
and float() on every field, one Python pass), which is what reading was before.  Target: the
vectorised reader (``engine="arrow"``) ≥ 20× faster at 10⁶ rows.  Both readers' results are
compared (every array, every rejection message).  Peak memory of each reader is measured in a
fresh process (peak RSS while reading minus the RSS before).

    python benchmarks/bench_probelog.py [--quick] [--sizes 1e5,1e6] [--rounds 3] [--no-memory]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import _common  # noqa: F401  (sys.path)
import numpy as np

from _common import ROOT, interleaved, machine, table
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.probelog import format_csv, read_csv

TARGET = 20.0
BAD_EVERY = 10_000


def base_lines():
    """Rows of a simulated 100 Hz session (twelve poses, then a stand grid), header apart."""
    probe = sim.build_probe(4)
    sess = sim.twelve_pose_session(duration_s=3.0) + sim.stand_grid_session(duration_s=3.0)
    log = sim.run_session(probe, Site(), sess, np.random.default_rng(0), rate_hz=100.0)
    lines = format_csv(log).splitlines()
    return lines[0], lines[1:], float(log.t_s[-1] - log.t_s[0]) + 0.01


def write_log(path, n, head, lines, span):
    """``n`` data rows: the session repeated with the time running on, every BAD_EVERY-th row bad."""
    bad = [lambda f: f.__setitem__(1, "nan"), lambda f: f.__setitem__(3, "-19.6"),
           lambda f: f.__setitem__(0, f"{float(f[0]) - 1.0:.4f}"), lambda f: f.__setitem__(8, "13"),
           lambda f: f.__delitem__(11)]
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(head + "\n")
        m = len(lines)
        for k in range(n):
            line = lines[k % m]
            cut = line.index(",")
            t = float(line[:cut]) + (k // m) * span
            if k % BAD_EVERY == BAD_EVERY // 2:
                f = [f"{t:.4f}"] + line[cut + 1:].split(",")
                bad[(k // BAD_EVERY) % len(bad)](f)
                fh.write(",".join(f) + "\n")
            else:
                fh.write(f"{t:.4f}{line[cut:]}\n")


def same(a, b) -> bool:
    (la, ra), (lb, rb) = a, b
    if ra != rb:
        return False
    for f in ("t_s", "acc", "mag", "temp_c", "pose", "ref", "row", "table_deg", "md_m"):
        x, y = getattr(la, f), getattr(lb, f)
        if x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=True):
            return False
    return la.mount.tolist() == lb.mount.tolist()


PEAK = """
import sys
from inclinometer_calib.io.probelog import read_csv
import pyarrow.csv, pyarrow.compute


def status(key):
    with open("/proc/self/status") as fh:
        return next(int(ln.split()[1]) for ln in fh if ln.startswith(key))


with open("/proc/self/clear_refs", "w") as fh:     # reset the peak (VmHWM) to the RSS now
    fh.write("5")
rss0 = status("VmRSS:")
log, rej = read_csv(sys.argv[1], engine=sys.argv[2])
print((status("VmHWM:") - rss0) / 1024)
"""


def peak_rss_mb(path, engine) -> float:
    """Peak RSS growth (MB) while reading ``path`` in a fresh process, after the imports (Linux:
    the peak is reset through /proc/self/clear_refs, then read from VmHWM)."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", PEAK, str(path), engine], capture_output=True, text=True, env=env,
                         check=True)
    return float(out.stdout.strip())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="10⁴ and 10⁵ rows")
    ap.add_argument("--sizes", help="rows, comma-separated (default 1e5,1e6)")
    ap.add_argument("--rounds", type=int, default=3, help="round-robin rounds, best kept")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory runs")
    args = ap.parse_args(argv)
    sizes = [int(float(s)) for s in (args.sizes or ("1e4,1e5" if args.quick else "1e5,1e6")).split(",")]
    print(f"machine: {machine()}; load average {os.getloadavg()[0]:.2f}")
    head, lines, span = base_lines()
    work = tempfile.mkdtemp(prefix="bench_probelog_")
    rows = []
    try:
        for n in sizes:
            path = os.path.join(work, f"log_{n}.csv")
            write_log(path, n, head, lines, span)
            mb = os.path.getsize(path) / 1e6
            best = interleaved({"rows": lambda: read_csv(path, engine="rows"),
                                "arrow": lambda: read_csv(path, engine="arrow")}, args.rounds)
            ref, new = read_csv(path, engine="rows"), read_csv(path, engine="arrow")
            ok = same(ref, new)
            ratio = best["rows"] / best["arrow"]
            mem = ("", "") if args.no_memory else (f"{peak_rss_mb(path, 'rows'):.0f}",
                                                    f"{peak_rss_mb(path, 'arrow'):.0f}")
            rows.append([f"{n:.0e}", f"{mb:.0f}", len(new[1]),
                         f"{best['rows']:.3f} ({best['rows'] / n * 1e6:.2f} µs/row)",
                         f"{best['arrow']:.4f} ({best['arrow'] / n * 1e6:.3f} µs/row)",
                         f"{ratio:.1f}" + (" ✓" if ratio >= TARGET else " ✗"), *mem, "yes" if ok else "NO"])
            os.unlink(path)
    finally:
        for f in os.listdir(work):
            os.unlink(os.path.join(work, f))
        os.rmdir(work)
    print(table(rows, ["rows", "MB", "rejected", "row reader s (baseline)", "vectorised s", "× baseline",
                       "peak MB rows", "peak MB arrow", "same results"]))
    print(f"(best of {args.rounds} round-robin rounds; target: vectorised ≥ {TARGET:g}× the row reader at 10⁶ rows; "
          f"load average now {os.getloadavg()[0]:.2f})")
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import pyarrow.csv, pyarrow.compute"], check=True)
    print(f"(a fresh process imports pyarrow.csv + compute in {time.perf_counter() - t:.2f} s including "
          "interpreter start; paid once per process, on the first vectorised read)")


if __name__ == "__main__":
    main()

"""Fitting: twelve-position solve, ``lab fit`` and ``lab diagnose`` against samples and candidates.

Logs are simulated with ``inclinometer-calib simulate`` (twelve poses + the 198-station stand grid;
the sample count is set by the rate).  Per size: reading + segmenting both CSV logs (the baseline:
the work every command does before fitting), the twelve-position solve, ``lab fit`` of the base
model and ``lab diagnose`` with every catalogue candidate, as in-process times and as "× baseline"
(time / baseline time).  Then ``lab diagnose`` against the number of candidates, and the whole
``inclinometer-calib lab diagnose`` command (new process, imports included) on ~10⁵ samples and
at the largest size.
Target (issue 14, target 5): that command on 10⁶ samples under 10 s on our 2-core machine.
Segmentation is also timed alone: the batch path (``StaticDetector.run``) against the per-sample
one the live nodes use, with a check that they give the same stations.

    python benchmarks/bench_fitting.py [--quick] [--sizes 2e3,1e4,1e5,1e6]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import subprocess
import sys
import tempfile
import time

import _common  # noqa: F401  (sys.path)

from _common import ROOT, machine, table
from inclinometer_calib import lab
from inclinometer_calib.apps.cli import main as cli_main
from inclinometer_calib.apps.common import load_site
from inclinometer_calib.lab.diagnose import candidate_effects
from inclinometer_calib.calibrate.labmodel import LabModel
from inclinometer_calib.io.probelog import read_csv, segment_stations
from inclinometer_calib.calibrate.capture import CaptureSession
from inclinometer_calib.detect.streaming import StaticDetector

ROWS_PER_HZ = 442          # rows of cal.csv + val.csv per Hz of rate with 1 s stations


def simulate(out, n):
    if n < 5000:   # a few samples per station: longer stations at a low rate
        args = ["--rate", f"{n / (ROWS_PER_HZ * 1.45):.3f}", "--station-seconds", "2"]
    else:
        args = ["--rate", f"{n / ROWS_PER_HZ:.3f}"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli_main(["simulate", "--out", out, "--seed", "2", *args]) == 0


def _segment(log, batch):
    """The stations of ``log`` by the batch path or sample by sample (the live nodes' path)."""
    det = StaticDetector()
    if batch:
        out = list(det.run(log.t_s, log.gravity, log.mag, log.temp_c))
    else:
        out = []
        g = log.gravity
        for i in range(len(log)):
            out.extend(det.update(log.t_s[i], g[i], log.mag[i], log.temp_c[i]))
    return out + list(det.flush())


def timed(fn):
    t = time.perf_counter()
    r = fn()
    return time.perf_counter() - t, r


def solve_session(stations, site):
    """The twelve-position solve as the CLI and the calibration node run it (gates, sequence, screen)."""
    session = CaptureSession(site=site)
    for st in stations:
        session.offer(st)
    return session.finish()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sizes", help="comma list of sample counts (default 2e3,1e4,1e5,1e6; quick 2e3,1e4,1e5)")
    args = ap.parse_args(argv)
    sizes = [int(float(x)) for x in (args.sizes or ("2e3,1e4,1e5" if args.quick else "2e3,1e4,1e5,1e6")).split(",")]
    print(f"machine: {machine()}")
    work = tempfile.mkdtemp(prefix="bench_fit_")
    rows, cand_rows = [], []
    try:
        for n in sizes:
            d = os.path.join(work, f"n{n}")
            simulate(d, n)
            cal, val = os.path.join(d, "cal.csv"), os.path.join(d, "val.csv")
            site = load_site(os.path.join(d, "site.yaml"))
            n_rows = sum(1 for p in (cal, val) for _ in open(p)) - 2

            def read_both():
                out = []
                for p in (cal, val):
                    log, _ = read_csv(p)
                    out.append(segment_stations(log))
                return out
            t_read, segs = timed(read_both)
            n_st = sum(len(s[0]) for s in segs)
            # segmentation alone: the batch path the logs take (StaticDetector.run) against the
            # live nodes' per-sample path (StaticDetector.update), same stations
            logs = [read_csv(p)[0] for p in (cal, val)]
            t_batch, st_batch = timed(lambda: [_segment(lg, True) for lg in logs])
            t_each, st_each = timed(lambda: [_segment(lg, False) for lg in logs])
            same = all([(s.t_start, s.t_end, s.n) for s in a] == [(s.t_start, s.t_end, s.n) for s in b]
                       for a, b in zip(st_batch, st_each))
            t_12, _ = timed(lambda: solve_session(segs[0][0], site))
            data = lab.load_logs(cal, val)
            model = LabModel.base(site)
            t_fit, res = timed(lambda: lab.fit(model, data))
            t_diag, dg = timed(lambda: lab.diagnose(data, LabModel.base(site)))
            n_cand = len(candidate_effects(LabModel.base(site)))
            label = f"{n_rows:.1e}"
            rows.append([label, n_st, "read + segment CSV (baseline)", f"{t_read:.3f}", "1.00"])
            rows.append([label, n_st, f"segment: StaticDetector.run (batch{'' if same else ', STATIONS DIFFER'})",
                         f"{t_batch:.3f}", f"{t_batch / t_read:.2f}"])
            rows.append([label, n_st, "segment: StaticDetector.update per sample (live path)", f"{t_each:.3f}",
                         f"{t_each / t_read:.2f}"])
            rows.append([label, n_st, "twelve-position solve (from stations)", f"{t_12 * 1e3:.2f} ms",
                         f"{t_12 / t_read:.4f}"])
            t_12cli, _ = timed(lambda: solve_session(segment_stations(read_csv(cal)[0])[0], site))
            rows.append([label, n_st, "twelve-position: read cal.csv + solve", f"{t_12cli:.3f}",
                         f"{t_12cli / t_read:.2f}"])
            rows.append([label, n_st, f"lab fit, base model ({len(res.values)} parameters)",
                         f"{t_fit:.3f}", f"{t_fit / t_read:.2f}"])
            rows.append([label, n_st, f"lab diagnose, all {n_cand} candidates", f"{t_diag:.3f}",
                         f"{t_diag / t_read:.2f}"])
            if n == sizes[-1] or abs(n - 100_000) < 1:
                names = sorted({e.name for e, _ in candidate_effects(LabModel.base(site))})
                for k in (1, 3, 6, len(names)):
                    if k > len(names):
                        continue
                    sub = set(names[:k])
                    pairs = len(candidate_effects(LabModel.base(site), sub))
                    t, _ = timed(lambda: lab.diagnose(data, LabModel.base(site), candidates=sub))
                    cand_rows.append([label, k, pairs, f"{t:.3f}", f"{t / max(pairs, 1):.3f}"])
            if abs(n - 100_000) <= 20_000 or n == sizes[-1]:
                cmd = [sys.executable, "-m", "inclinometer_calib.apps.cli", "lab", "diagnose", "--cal", cal, "--val", val,
                       "--site", os.path.join(d, "site.yaml"), "--quiet"]
                t, r = timed(lambda: subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT))
                status = "ok" if r.returncode == 0 else f"exit {r.returncode}"
                rows.append([label, n_st, f"CLI `lab diagnose` (new process, {status})", f"{t:.3f}",
                             f"{t / t_read:.2f}"])
            shutil.rmtree(d, ignore_errors=True)
        print(table(rows, ["rows", "stations", "step", "time s", "× baseline"]))
        print()
        print(table(cand_rows, ["rows", "effects", "candidate fits", "diagnose s", "s per candidate"]))
        print("(target 5 of issue 14: CLI `lab diagnose` with all candidates on 1e6 rows under 10 s)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

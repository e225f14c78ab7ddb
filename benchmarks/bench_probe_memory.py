"""Benchmark: the probe node's memory against the length of its script (target 3 of issue 14).

    source scripts/env.sh
    python benchmarks/bench_probe_memory.py             # 10 s and 10 min scripts at 1 kHz (about 1.5 min)
    python benchmarks/bench_probe_memory.py --quick     # 10 s and 2 min scripts

Starts the probe node (``source:=simulate``, ``rate_hz:=1000``, ``truth_file`` set as the launcher
does; the long script: the twelve-pose calibration then a well path long enough, the 10-second
one: a well path of 3 stations) as a separate
process in a private DDS domain on this machine, once with a 10-second script and once with a
10-minute one, and samples its RSS (``/proc/<pid>/statm``) every ``--sample-s`` while it
publishes.  The 10-minute script is played at ``--speed`` (default 20×): the node prepares and
publishes the same samples, only sooner, so the figure is that of 10 minutes at 1 kHz in about
30 s (or as fast as the node can publish).  Nothing subscribes.

Printed per script: samples, RSS once publishing (after start-up), the highest RSS while
publishing, and the ratio of the 10-minute script's highest RSS to the 10-second script's
(target <= 1.2).  The baseline is the 10-second script, run the same way in the same run.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time

import _ros
from _common import machine, table

CAL_S = 12 * 3.0 + 2.0  # twelve poses of 2 s + 1 s moves, then the survey gap
TARGET = 1.2


def run(seconds: float, rate: float, speed: float, env: dict, work: str, sample_s: float) -> dict:
    calibrate = seconds > 2 * CAL_S   # a 10 s script is a short survey alone
    n_well = max(1, int(round((seconds - (CAL_S if calibrate else 0.0)) / 3.0)))
    name = f"probe_{int(seconds)}s"
    params = dict(source="simulate", rate_hz=float(rate), speed=float(speed), survey="well_path",
                  calibration_session=calibrate,
                  truth_file=os.path.join(work, name, "truth.json"),
                  **{"well.n_stations": n_well, "start_delay_s": 0.0, "on_end": "stop"})
    proc = _ros.start(_ros.node_cmd("probe", params), env, os.path.join(work, name + ".log"))
    t0 = time.monotonic()
    series = []
    try:
        _ros.wait_log(proc, "publishing", timeout=300)
        t_pub = time.monotonic()
        while proc.poll() is None:
            try:
                series.append((time.monotonic() - t_pub, _ros.rss_mb(proc.pid)))
            except OSError:
                break
            time.sleep(sample_s)
    finally:
        rc = _ros.stop(proc)
    wall = time.monotonic() - t0
    text = open(proc.log_path).read()
    m = re.search(r"end of script: (\d+) samples published", text)
    if rc != 0 or not m or not series:
        raise RuntimeError(f"probe ({seconds:g} s script) failed (exit {rc}):\n{text[-2000:]}")
    return {"script_s": seconds, "samples": int(m.group(1)), "wall_s": round(wall, 1),
            "rss_first_mb": round(series[0][1], 1), "rss_max_mb": round(max(r for _, r in series), 1),
            "rss_last_mb": round(series[-1][1], 1), "rss_samples": len(series)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a 2-minute long script instead of 10 minutes")
    ap.add_argument("--rate", type=float, default=1000.0, help="sample rate, Hz (default 1000)")
    ap.add_argument("--speed", type=float, default=20.0, help="playback speed of the long script (default 20)")
    ap.add_argument("--sample-s", type=float, default=0.25, help="RSS sampling period, s")
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    long_s = 120.0 if args.quick else 600.0
    domain, lock = _ros.reserve_domain()
    env = _ros.ros_env(domain)
    work = tempfile.mkdtemp(prefix="bench_probe_memory_")
    print(machine())
    print(f"domain {domain}; logs in {work}", flush=True)
    try:
        short = run(10.0, args.rate, 1.0, env, work, args.sample_s)
        longer = run(long_s, args.rate, args.speed, env, work, args.sample_s)
    finally:
        lock.close()
    rows = [[f"{r['script_s']:g} s", r["samples"], f"{r['wall_s']:.0f}", f"{r['rss_first_mb']:.1f}",
             f"{r['rss_max_mb']:.1f}", f"{r['rss_last_mb']:.1f}"] for r in (short, longer)]
    print(table(rows, ["script", "samples", "wall s", "RSS publishing MB", "RSS max MB", "RSS end MB"]))
    ratio = longer["rss_max_mb"] / short["rss_max_mb"]
    print(f"RSS max, {long_s / 60:g} min script / 10 s script: {ratio:.2f} (target <= {TARGET}: "
          f"{'met' if ratio <= TARGET else 'MISSED'})")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": machine(), "short": short, "long": longer, "ratio": ratio, "target": TARGET},
                      fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Soak run (not part of CI): the whole graph at 1 kHz for N minutes; drops and memory growth.

    source scripts/env.sh
    python benchmarks/soak.py                  # 10 minutes at 1 kHz (about 11 min of wall time)
    python benchmarks/soak.py --minutes 1      # a short check
    python benchmarks/soak.py --keep DIR       # keep the bag and the node logs in DIR

Starts probe (``source:=simulate``, ``rate_hz:=1000``, the twelve-pose calibration then a well
path long enough for the run), calibration, correction (``publish_corrected:=true``, so every
sample passes through its per-message path and out again) and recorder as separate processes
in a private DDS domain on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), with the
configs of ``config/`` and the default sensor-data QoS (best effort, depth 1000).

Every ``--sample-s`` (10 s) it reads each process' RSS and CPU time from ``/proc``.  At the end
it reports, per topic, what the probe published against what the recorder wrote (drops on the
way through DDS and the recorder), the survey stations recorded against those the probe held,
whether the calibration solved, each process' CPU load, and memory growth in MB/min: the mean
RSS of the last third of the run minus that of the first third, over the time between the
thirds' midpoints (start-up is excluded; the probe prepares its script piece by piece, so its
RSS does not depend on the script's length: ``bench_probe_memory.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import sys
import tempfile
import time

import _ros
from _common import machine, table

sys.path.insert(0, _ros.ROOT)

NODES = ("probe", "calibration", "correction", "recorder")
CAL_S = 12 * 3.0 + 2.0  # twelve poses of 2 s + 1 s moves, then the survey gap


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the probe's script (default 10)")
    ap.add_argument("--rate", type=float, default=1000.0, help="sample rate, Hz (default 1000)")
    ap.add_argument("--sample-s", type=float, default=10.0, help="RSS/CPU sampling period, s")
    ap.add_argument("--reliable", action="store_true", help="reliable QoS on the raw streams")
    ap.add_argument("--no-corrected", action="store_true", help="correction without publish_corrected")
    ap.add_argument("--keep", metavar="DIR", help="keep the bag and the logs here")
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = ap.parse_args(argv)

    out = os.path.abspath(args.keep) if args.keep else tempfile.mkdtemp(prefix="soak_")
    os.makedirs(out, exist_ok=True)
    bag_path = os.path.join(out, "soak.mcap")
    if os.path.exists(bag_path):
        os.remove(bag_path)
    n_well = max(1, int(round((args.minutes * 60.0 - CAL_S) / 3.0)))
    domain, lock = _ros.reserve_domain()
    env = _ros.ros_env(domain)
    qos = {"qos.reliability": "reliable"} if args.reliable else {}
    params = {
        "probe": dict(source="simulate", rate_hz=float(args.rate), speed=1.0, survey="well_path",
                      **{"well.n_stations": n_well, "wait_for_subscribers": 3, "wait_for_reference_subscribers": 2,
                         "start_delay_s": 1.0, "on_end": "stop"}, **qos),
        # one time base, as the launcher runs the graph: the probe's /clock (log time)
        "calibration": dict(output=os.path.join(out, "coeffs.yaml"), use_sim_time=True, **qos),
        "correction": dict(publish_corrected=not args.no_corrected, use_sim_time=True, **qos),
        "recorder": dict(output=bag_path),
    }
    print(f"soak: {args.minutes:g} min at {args.rate:g} Hz ({n_well} well stations + 12 poses), "
          f"domain {domain}, output {out}", flush=True)
    procs = {}
    samples = []  # (t, {name: (rss MB, cpu s)})
    try:
        for name in ("recorder", "calibration", "correction", "probe"):
            procs[name] = _ros.start(_ros.node_cmd(name, params[name]), env, os.path.join(out, f"{name}.log"),
                                     cwd=out)
        _ros.wait_log(procs["probe"], "publishing", timeout=300)
        t0 = time.monotonic()
        next_sample = t0
        while procs["probe"].poll() is None:
            now = time.monotonic()
            if now >= next_sample:
                row = {}
                for name, p in procs.items():
                    try:
                        row[name] = (_ros.rss_mb(p.pid), _ros.cpu_seconds(p.pid))
                    except OSError:
                        pass
                samples.append((now - t0, row))
                next_sample += args.sample_s
                if len(samples) % 6 == 1:
                    print(f"  t={now - t0:5.0f} s  " + "  ".join(f"{n} {r[0]:.0f} MB" for n, r in row.items()),
                          flush=True)
            for name, p in procs.items():
                if name != "probe" and p.poll() is not None:
                    raise RuntimeError(f"{name} exited ({p.returncode}) during the soak; see {p.log_path}")
            time.sleep(0.2)
        wall = time.monotonic() - t0
        time.sleep(3.0)  # drain: the last station closes after idle_flush_s
        final_cpu = {n: _ros.cpu_seconds(p.pid) for n, p in procs.items() if p.poll() is None}
    finally:
        rcs = {}
        for name in NODES:
            if name in procs:
                rcs[name] = _ros.stop(procs[name])
        lock.close()

    logs = {n: open(p.log_path).read() for n, p in procs.items()}
    m = re.search(r"end of script: (\d+) samples published", logs["probe"])
    published = int(m.group(1)) if m else None
    from inclinometer_calib.io import bag
    topics = bag.open_bag(bag_path).topics
    counts = {t: topics[t].count for t in sorted(topics)}
    stations_expected = 12 + n_well
    solved = "published coefficients" in logs["calibration"]

    res = {"machine": machine(), "minutes": args.minutes, "rate_hz": args.rate, "wall_s": round(wall, 1),
           "published_samples": published, "recorded": counts, "stations_expected": stations_expected,
           "calibration_solved": solved, "exit_codes": rcs, "processes": {}}
    rows = []
    for topic in ("/probe/imu", "/probe/mag", "/probe/temperature"):
        n = counts.get(topic, 0)
        rows.append([topic, published, n, published - n if published else "?",
                     f"{100.0 * (published - n) / published:.3f}" if published else "?"])
    for topic in ("/probe/imu_corrected", "/probe/mag_corrected"):
        if topic in counts:
            rows.append([topic, "(after solve)", counts[topic], "", ""])
    n_st = counts.get("/survey/station", 0)
    rows.append(["/survey/station", stations_expected, n_st, stations_expected - n_st,
                 f"{100.0 * (stations_expected - n_st) / stations_expected:.2f}"])
    print()
    print(machine())
    print(f"{args.minutes:g} min script at {args.rate:g} Hz, {wall:.0f} s of wall time; calibration "
          f"{'solved' if solved else 'NOT solved'}; exit codes {rcs}")
    print(table(rows, ["topic", "published", "recorded", "lost", "lost %"]))

    prow = []
    third = max(1, len(samples) // 3)
    for name in NODES:
        series = [(t, r[name]) for t, r in samples if name in r]
        if len(series) < 3:
            continue
        first, last = series[:third], series[-third:]
        tf = sum(t for t, _ in first) / len(first)
        tl = sum(t for t, _ in last) / len(last)
        mf = sum(x[0] for _, x in first) / len(first)
        ml = sum(x[0] for _, x in last) / len(last)
        growth = (ml - mf) / ((tl - tf) / 60.0) if tl > tf else float("nan")
        cpu0 = series[0][1][1]
        cpu1 = final_cpu.get(name, series[-1][1][1])
        load = 100.0 * (cpu1 - cpu0) / max(wall, 1e-9)
        res["processes"][name] = {"rss_start_mb": round(series[0][1][0], 1), "rss_end_mb": round(series[-1][1][0], 1),
                                  "rss_max_mb": round(max(x[0] for _, x in series), 1),
                                  "growth_mb_per_min": round(growth, 3), "cpu_percent": round(load, 1)}
        prow.append([name, f"{series[0][1][0]:.1f}", f"{series[-1][1][0]:.1f}",
                     f"{max(x[0] for _, x in series):.1f}", f"{growth:+.3f}", f"{load:.0f}"])
    print()
    print(table(prow, ["process", "RSS start MB", "RSS end MB", "RSS max MB", "growth MB/min", "CPU %"]))
    res["rss_series"] = {name: [(round(t, 1), round(r[name][0], 1)) for t, r in samples if name in r]
                         for name in NODES}
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)
    return 0 if solved and all(rc == 0 for rc in rcs.values()) else 1


if __name__ == "__main__":
    sys.exit(main())

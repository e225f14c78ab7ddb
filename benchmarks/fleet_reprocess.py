"""Fleet reprocessing on Dask: bags/s on 1 and 2 local workers against the single-process loop.

A fleet is generated (not timed): ``--probes`` simulated probes, each registered with one record in
an SQLite registry, and ``--bags`` short survey bags spread over them (``--stations`` well-path
stations of 2 s at 100 Hz each, the probe's ``/probe/serial`` recorded). Then, in the same run:

* ``reprocess()`` loop — the one pipeline alone over every bag (no registry, no Parquet): the floor;
* the single-process loop (baseline) — :func:`fleet.reprocess.reprocess_fleet` with ``n_workers=0``:
  the same per-bag work as a Dask task (hash, serial, registry lookup, pipeline, Parquet fragment,
  done-index), no Dask;
* Dask on a local cluster of 1 and 2 worker processes (as ``reprocess_fleet`` makes it), 1 bag
  per task and batches of ``--batches`` bags per task (the cluster started beforehand and warmed
  up by an untimed run: its start-up is printed apart);
* a rerun where every bag is done (hash + lookup per bag, then skipped);
* the scheduler's own cost per task (no-op tasks), which sets the task size that matters.

Each Dask figure is the best of ``--rounds``, into a fresh output folder each time.

    python benchmarks/fleet_reprocess.py [--quick] [--bags 200] [--probes 20] [--stations 4]
        [--batches 10,50] [--rounds 2]
"""
from __future__ import annotations

import argparse
import datetime as dt
import os
import shutil
import tempfile
import time

import _common  # noqa: F401  (sys.path)
import numpy as np

from _common import machine, table
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.fleet.registry import Registry
from inclinometer_calib.fleet.reprocess import RegistryResolver, local_cluster, reprocess_fleet
from inclinometer_calib.core.frames import Site
from inclinometer_calib.correct.reprocess import reprocess, write_probe_bag

T0 = dt.datetime(2026, 1, 5, tzinfo=dt.timezone.utc)


def make_fleet(work, n_bags, n_probes, n_stations):
    site = Site()
    db = f"sqlite:///{os.path.join(work, 'fleet.db')}"
    reg = Registry(db)
    records, probes = {}, {}
    for k in range(n_probes):
        serial = f"SN-{k:04d}"
        probes[serial] = p = sim.build_probe(1000 + k)
        records[serial] = cal = Calibration(acc=p.acc, mag=p.mag, site=site, probe_id=serial)
        reg.add_probe(serial, calibration_interval_days=90)
        reg.add_calibration(cal, calibrated_at=T0)
    reg.close()
    bags, cals = [], []
    os.makedirs(os.path.join(work, "bags"))
    for i in range(n_bags):
        serial = f"SN-{i % n_probes:04d}"
        log = sim.run_session(probes[serial], site, sim.well_path_session(n_stations, kickoff_deg=5.0, seed=i),
                              np.random.default_rng(i), survey=True)
        path = os.path.join(work, "bags", f"b{i:05d}.mcap")
        when = T0 + dt.timedelta(days=1 + i % 60, hours=i % 24)
        write_probe_bag(log, path, epoch_ns=int(when.timestamp()) * 10**9, serial=serial)
        bags.append(path)
        cals.append(records[serial])
    return db, bags, cals


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="40 bags of 8 probes, one round")
    ap.add_argument("--bags", type=int)
    ap.add_argument("--probes", type=int)
    ap.add_argument("--stations", type=int, default=4)
    ap.add_argument("--batches", default="10,50", help="bags per task to try beside 1 (comma-separated)")
    ap.add_argument("--rounds", type=int)
    args = ap.parse_args(argv)
    n_bags = args.bags or (40 if args.quick else 200)
    n_probes = args.probes or (8 if args.quick else 20)
    rounds = args.rounds or (1 if args.quick else 2)
    sizes = [1] + [int(x) for x in args.batches.split(",") if x.strip() and int(x) > 1]
    print(f"machine: {machine()}")
    from distributed import Client

    work = tempfile.mkdtemp(prefix="bench_fleet_")
    try:
        t = time.perf_counter()
        db, bags, cals = make_fleet(work, n_bags, n_probes, args.stations)
        size = sum(os.path.getsize(b) for b in bags)
        print(f"fleet: {n_bags} bags of {args.stations} stations from {n_probes} probes "
              f"({size / n_bags / 1e3:.0f} kB each), generated in {time.perf_counter() - t:.1f} s (not timed)")
        k = [0]

        def fresh():
            k[0] += 1
            return os.path.join(work, f"out{k[0]}")

        def run(**kw):
            out = fresh()
            best = float("inf")
            for _ in range(rounds):
                out = fresh()
                s = reprocess_fleet(bags, out_dir=out, registry_url=db, progress=False, **kw)
                assert s.count("ok") == n_bags, [r.reason for r in s.failed][:3]
                best = min(best, s.seconds)
            return best, out

        reprocess_fleet(bags[:4], out_dir=fresh(), registry_url=db, progress=False, n_workers=0)   # warm-up
        t = time.perf_counter()
        for b, c in zip(bags, cals):
            reprocess(b, None, c)
        t_core = time.perf_counter() - t
        t_base, out_base = run(n_workers=0)
        rows = [["reprocess() loop, pipeline only (floor)", "-", f"{t_core:.2f}", f"{n_bags / t_core:.1f}",
                 f"{t_base / t_core:.2f}"],
                ["single-process loop, n_workers=0 (baseline)", "-", f"{t_base:.2f}", f"{n_bags / t_base:.1f}",
                 "1.00"]]
        skip = {}
        starts = {}
        task_ms = {}
        for workers in (1, 2):
            t = time.perf_counter()
            cluster = local_cluster(workers)       # as reprocess_fleet makes it (no worker profiler)
            client = Client(cluster)
            # warm up: every worker opens the registry, then a first untimed run over a few bags
            client.run(lambda: RegistryResolver(db).registry() and None)
            reprocess_fleet(bags[:4 * workers], out_dir=fresh(), registry_url=db, progress=False, client=client)
            starts[workers] = time.perf_counter() - t
            try:
                for n in sizes:
                    tb, out = run(client=client, bags_per_task=n)
                    rows.append([f"Dask, {workers} worker(s), {n} bag(s)/task", workers, f"{tb:.2f}",
                                 f"{n_bags / tb:.1f}", f"{t_base / tb:.2f}"])
                    if n == 1:
                        s = reprocess_fleet(bags, out_dir=out, registry_url=db, progress=False, client=client)
                        assert s.count("skipped") == n_bags
                        skip[workers] = s.seconds
                noop = 2000
                t = time.perf_counter()
                futs = client.map(lambda i: i, range(noop), pure=False)
                client.gather(futs)
                task_ms[workers] = (time.perf_counter() - t) / noop * 1e3
            finally:
                client.close()
                cluster.close()
        print(table(rows, ["run", "workers", "best s", "bags/s", "× baseline"]))
        print("local cluster start-up incl. warm-up: " + ", ".join(f"{w} worker(s) {s:.1f} s" for w, s in starts.items()))
        print("rerun with every bag done (hash + lookup, skipped): "
              + ", ".join(f"{w} worker(s) {s:.2f} s ({n_bags / s:.0f} bags/s)" for w, s in skip.items()))
        print("scheduler cost per task (no-op tasks, submit to result): "
              + ", ".join(f"{w} worker(s) {ms:.2f} ms" for w, ms in task_ms.items()))
        per_bag = t_base / n_bags * 1e3
        print(f"work per bag in the baseline: {per_bag:.0f} ms; files in the dataset: "
              f"{sum(len(f) for _, _, f in os.walk(os.path.join(out_base, 'stations')))}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

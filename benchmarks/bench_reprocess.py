"""Offline reprocessing of a recorded MCAP: read → pair → detect → correct → write.

A simulated 100 Hz survey log is written as a bag (``/probe/imu``, ``/probe/mag``,
``/probe/temperature``, ``/probe/reference``), then ``reprocess.reprocess`` turns it into a new bag
with ``/survey/station`` messages plus the copied input.  Figures: speed against real time (log
span / wall time; target ≥ 200× for a 100 Hz log), and against a bare read+write loop measured in
the same run (``open_bag(...).messages()`` → ``BagWriter.write`` of every message, no decoding —
the I/O floor of any reprocessing).  Two more rows isolate reading: ``open_bag(...).messages()``
alone, and the ``mcap`` library's own ``StreamReader`` over the same file (CRCs checked, no
damage tolerance), the reference for what reading costs.  ``--profile`` prints where the time
goes.

    python benchmarks/bench_reprocess.py [--quick] [--minutes 20] [--rounds 3] [--profile]
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile

import _common  # noqa: F401  (sys.path)
import numpy as np

from _common import interleaved, machine, table
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.io.bag import BagWriter, open_bag
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site
from inclinometer_calib.correct.reprocess import reprocess, write_probe_bag


def make_bag(path, minutes: float):
    probe = sim.build_probe(4)
    site = Site()
    per_station = 2.0 + 1.0                    # held 2 s, 1 s move
    n_st = max(3, int(minutes * 60 / per_station))
    grid = sim.stand_grid_session(duration_s=2.0)
    sess = (grid * (n_st // len(grid) + 1))[:n_st]
    log = sim.run_session(probe, site, sess, np.random.default_rng(0), rate_hz=100)
    counts = write_probe_bag(log, path)
    return Calibration(acc=probe.acc, mag=probe.mag, site=site), site, counts, len(sess)


def bare_copy(src, dst):
    reader = open_bag(src)
    with BagWriter(dst) as w:
        ids = {}
        for m in reader.messages(strict=False):
            cid = ids.get(m.topic)
            if cid is None:
                info = reader.topic_info(m.topic)
                cid = ids[m.topic] = w.add_topic(m.topic, m.type, qos_yaml=info.qos_yaml,
                                                  type_hash=info.type_hash, definition=info.definition)
            w.write(cid, m.data, m.log_time, m.publish_time)


def read_only(src):
    return sum(1 for _ in open_bag(src).messages())


def read_mcap_library(src):
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    with open(src, "rb") as f:
        return sum(1 for r in StreamReader(f, validate_crcs=True).records if isinstance(r, Message))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--minutes", type=float, help="log length (default 20; quick 3)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--profile", action="store_true", help="cProfile one reprocess run")
    args = ap.parse_args(argv)
    minutes = args.minutes or (3.0 if args.quick else 20.0)
    rounds = 2 if args.quick else args.rounds
    print(f"machine: {machine()}")
    work = tempfile.mkdtemp(prefix="bench_reproc_")
    try:
        src = os.path.join(work, "in.mcap")
        cal, site, counts, n_st = make_bag(src, minutes)
        n_msgs = sum(counts.values())
        k = [0]

        def out(stem):
            k[0] += 1
            return os.path.join(work, f"{stem}{k[0]}.mcap")

        span = [0.0]
        stations = [0]

        def run():
            p = out("re")
            rep = reprocess(src, p, cal, site)
            span[0], stations[0] = rep.log_span_s, len(rep.stations)
            os.unlink(p)

        def bare():
            p = out("bare")
            bare_copy(src, p)
            os.unlink(p)
        best = interleaved({"bare": bare, "reprocess": run, "read": lambda: read_only(src),
                            "mcap": lambda: read_mcap_library(src)}, rounds)
        tb, tr = best["bare"], best["reprocess"]
        assert read_only(src) == read_mcap_library(src) == n_msgs
        rows = [["bare read + write loop (baseline)", f"{tb:.3f}", f"{n_msgs / tb / 1e3:.0f}", f"{span[0] / tb:.0f}",
                 "1.00"],
                ["reprocess (decode, pair, detect, correct, write)", f"{tr:.3f}", f"{n_msgs / tr / 1e3:.0f}",
                 f"{span[0] / tr:.0f}", f"{tb / tr:.2f}"]]
        for name, key in (("read only: open_bag(...).messages()", "read"),
                          ("read only: mcap StreamReader (library reference)", "mcap")):
            t = best[key]
            rows.append([name, f"{t:.3f}", f"{n_msgs / t / 1e3:.0f}", f"{span[0] / t:.0f}", f"{tb / t:.2f}"])
        print(f"input: {span[0] / 60:.1f} min of 100 Hz log, {n_msgs} messages "
              f"({os.path.getsize(src) / 1e6:.1f} MB zstd), {n_st} stations set, {stations[0]} found")
        print(table(rows, ["run", "best s", "kmsg/s", "× real time", "× baseline"]))
        print("(target ≥ 200× real time)")
        if args.profile:
            import cProfile
            import pstats
            pr = cProfile.Profile()
            pr.enable()
            run()
            pr.disable()
            pstats.Stats(pr).sort_stats("tottime").print_stats(12)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

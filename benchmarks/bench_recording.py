"""Recording: MCAP write throughput of the recorder's write path against a bare ``mcap`` writer.

The recorder node's subscription callback (``nodes/recorder._make_callback``) calls
``BagWriter.write(channel_id, data, time.time_ns(), info["source_timestamp"])`` with the CDR bytes
as received.  This script drives exactly that callback (imported from the node module when rclpy
is installed, an identical local copy otherwise) with serialized ``/probe/imu``, ``/probe/mag``
and ``/probe/temperature`` messages, and compares it with a bare ``mcap.writer.Writer`` loop
writing the same bytes with the same chunk size and compression.  DDS is not involved (the node
benchmark over DDS is separate).  Target: ≥ 0.8× the bare writer.

    python benchmarks/bench_recording.py [--quick] [--messages 300000] [--rounds 5]
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

import _common  # noqa: F401  (sys.path)
import numpy as np

from _common import interleaved, machine, table
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.io.bag import BagWriter, open_bag
from inclinometer_calib.core.frames import Site
from inclinometer_calib.correct.reprocess import write_probe_bag

try:  # the node's own callback factory (needs rclpy); fall back to the same three lines
    from inclinometer_calib.nodes.recorder import _make_callback
    CALLBACK_SOURCE = "inclinometer_calib.nodes.recorder._make_callback"
except ImportError:  # pragma: no cover - ROS-free machine
    CALLBACK_SOURCE = "local copy of the recorder callback (rclpy not installed)"

    def _make_callback(write, channel_id, now=time.time_ns):
        def callback(data, info):
            write(channel_id, data, now(), info["source_timestamp"])
        return callback


def sample_messages(n_messages: int, workdir: str):
    """(topic, type, definition, data, publish_time) tuples: a simulated probe's messages."""
    n_samples = n_messages // 3 + 1
    probe = sim.build_probe(1)
    sess = sim.stand_grid_session(duration_s=1.0)
    log = sim.run_session(probe, Site(), sess, np.random.default_rng(0), rate_hz=100)
    while len(log) < n_samples:
        log = type(log).concatenate([log, log])
        log.t_s = np.arange(len(log)) * 0.01
    log = type(log)(log.t_s[:n_samples], log.acc[:n_samples], log.mag[:n_samples], log.temp_c[:n_samples],
                    log.pose[:n_samples], log.ref[:n_samples])
    src = os.path.join(workdir, "src.mcap")
    write_probe_bag(log, src, reference=False, compression="")
    reader = open_bag(src)
    msgs = [(m.topic, m.data, m.publish_time) for m in reader.messages()][:n_messages]
    topics = {t: (i.type, i.definition) for t, i in reader.topics.items()}
    return msgs, topics


def run_recorder(path, msgs, topics, compression):
    w = BagWriter(path, compression=compression)
    callbacks = {t: _make_callback(w.write, w.add_topic(t, ty, definition=d)) for t, (ty, d) in topics.items()}
    for topic, data, pub in msgs:
        callbacks[topic](data, {"source_timestamp": pub})
    w.close()


def run_bare(path, msgs, topics, compression):
    from mcap.writer import CompressionType, Writer

    ctype = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}[compression]
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=1 << 20, compression=ctype)
        w.start(profile="ros2", library="bench")
        ids = {}
        for t, (ty, d) in topics.items():
            sid = w.register_schema(name=ty, encoding="ros2msg", data=d.encode())
            ids[t] = w.register_channel(topic=t, message_encoding="cdr", schema_id=sid)
        now = time.time_ns
        add = w.add_message
        for topic, data, pub in msgs:
            add(ids[topic], now(), data, pub)
        w.finish()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--messages", type=int, help="messages per run (default 300000; quick 60000)")
    ap.add_argument("--rounds", type=int, default=5, help="round-robin rounds (best of)")
    args = ap.parse_args(argv)
    n = args.messages or (60_000 if args.quick else 300_000)
    rounds = 3 if args.quick else args.rounds
    print(f"machine: {machine()}")
    print(f"recorder callback: {CALLBACK_SOURCE}")
    work = tempfile.mkdtemp(prefix="bench_rec_")
    try:
        msgs, topics = sample_messages(n, work)
        mbytes = sum(len(d) for _, d, _ in msgs) / 1e6
        rows = []
        for comp in ("zstd", ""):
            k = [0]

            def fresh(stem):
                k[0] += 1
                return os.path.join(work, f"{stem}{k[0]}.mcap")

            def rec():
                p = fresh("rec")
                run_recorder(p, msgs, topics, comp)
                os.unlink(p)

            def bare():
                p = fresh("bare")
                run_bare(p, msgs, topics, comp)
                os.unlink(p)
            best = interleaved({"bare": bare, "recorder": rec}, rounds)
            tb, tr = best["bare"], best["recorder"]
            name = comp or "none"
            rows.append([name, "bare mcap Writer loop (baseline)", f"{tb:.3f}", f"{len(msgs) / tb / 1e3:.0f}",
                         f"{mbytes / tb:.0f}", "1.00"])
            rows.append([name, "recorder callback → BagWriter.write", f"{tr:.3f}", f"{len(msgs) / tr / 1e3:.0f}",
                         f"{mbytes / tr:.0f}", f"{tb / tr:.2f}"])
        print(f"{len(msgs)} messages, {mbytes:.1f} MB of CDR (imu/mag/temperature of {len(msgs) // 3} samples)")
        print(table(rows, ["compression", "writer", "best s", "kmsg/s", "MB/s", "× baseline"]))
        print("(target ≥ 0.8× baseline; both include time.time_ns() per message as the recorder does)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

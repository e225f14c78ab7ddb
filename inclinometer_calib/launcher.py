"""Start the whole graph as separate processes, stop it cleanly, and summarize the run.

``inclinometer-calib-launch`` / ``python -m inclinometer_calib.launcher`` is the PyPI-environment
stand-in for ``ros2 launch inclinometer_calib survey.launch.py`` (``launch`` and ``launch_ros``
have no wheels).  It starts ``probe``, ``calibration``, ``correction`` and (if importable)
``recorder`` as child processes (``python -m inclinometer_calib.nodes.<name> --ros-args ...``,
each with ``config/<name>.yaml`` when present plus the run's parameters), forwards their output
line by line with a ``[name]`` prefix, and stops everything when the probe finishes (after a
short drain so the last station is closed and recorded) or on Ctrl-C/SIGTERM: SIGINT first,
then SIGTERM and SIGKILL after timeouts; the recorder is stopped last.

Then it prints a summary, read back from the recorded bag with ``rosbags`` (independent of the
recorder's writer): the calibration coefficients against the simulator truth (``truth.json``
written by the probe) and the survey station angles against their reference attitudes.

``--out DIR`` leaves ``survey.mcap``, ``coeffs.yaml``, ``truth.json`` (+ ``truth_coeffs.yaml``)
and ``summary.json``.  Exit status: 0 if the run completed, 1 if a node failed or the run timed
out, 2 on a usage error, 130 when interrupted.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np

NODES = ("probe", "calibration", "correction", "recorder")
STOP_ORDER = ("probe", "calibration", "correction", "recorder")  # the recorder last: it records the others


def config_dir():
    """``config/`` of the source tree, else ``share/inclinometer_calib/config`` of an install."""
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "config")
    if os.path.isdir(here):
        return here
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            d = os.path.join(get_package_share_directory("inclinometer_calib"), "config")
            return d if os.path.isdir(d) else None
        except PackageNotFoundError:
            return None
    except ImportError:
        return None


def _fmt(value) -> str:
    """A parameter value as ``-p name:=value`` text (floats keep a decimal point: typed params)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(json.dumps(v) if isinstance(v, str) else _fmt(v) for v in value) + "]"
    return str(value)


# --------------------------------------------------------------------------------------------
# Child processes
# --------------------------------------------------------------------------------------------
class Child:
    def __init__(self, name, cmd, env, out_lock, log_file=None):
        self.name = name
        self.cmd = cmd
        self._lock = out_lock
        self._log = log_file
        self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, text=True, bufsize=1, errors="replace",
                                     start_new_session=True)  # the launcher alone decides when to stop
        self._thread = threading.Thread(target=self._pump, name=f"out-{name}", daemon=True)
        self._thread.start()

    def _pump(self):
        for line in self.proc.stdout:
            text = f"[{self.name}] {line.rstrip()}"
            with self._lock:
                print(text, flush=True)
                if self._log:
                    self._log.write(text + "\n")

    def poll(self):
        return self.proc.poll()

    def stop(self, sigint_s=10.0, sigterm_s=5.0):
        """SIGINT, then SIGTERM, then SIGKILL; returns the exit status."""
        for sig, wait in ((signal.SIGINT, sigint_s), (signal.SIGTERM, sigterm_s), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            try:
                self.proc.send_signal(sig)
            except ProcessLookupError:
                break
            try:
                self.proc.wait(wait)
            except subprocess.TimeoutExpired:
                with self._lock:
                    print(f"[launch] {self.name} still running {wait:g} s after {signal.Signals(sig).name}",
                          flush=True)
        rc = self.proc.wait()
        self._thread.join(2.0)
        return rc


def node_command(name, params, cfg):
    cmd = [sys.executable, "-m", f"inclinometer_calib.nodes.{name}", "--ros-args"]
    if cfg:
        f = os.path.join(cfg, f"{name}.yaml")
        if os.path.isfile(f):
            cmd += ["--params-file", f]
    for key, value in params.items():
        cmd += ["-p", f"{key}:={_fmt(value)}"]
    return cmd


def build_params(args, out):
    """Per-node parameters of the run (on top of the config files)."""
    p = {n: {} for n in NODES}
    probe = p["probe"]
    probe.update(source=args.source, speed=float(args.speed), on_end="stop")
    if args.input:
        probe["path"] = os.path.abspath(args.input)
    if args.source == "simulate":
        probe.update(truth_file=os.path.join(out, "truth.json"), seed=int(args.seed), survey=args.survey,
                     rate_hz=float(args.rate))
        if args.effect:
            probe["effects"] = list(args.effect)
        if args.stations is not None:
            probe["well.n_stations"] = int(args.stations)
        if args.station_seconds is not None:
            probe["station_duration_s"] = float(args.station_seconds)
        if args.no_calibration:
            probe["calibration_session"] = False
    p["calibration"]["output"] = os.path.join(out, "coeffs.yaml")
    if args.coeffs:
        p["correction"]["coeffs_file"] = os.path.abspath(args.coeffs)
    p["recorder"]["output"] = os.path.join(out, "survey.mcap")
    if args.reliable:
        for n in ("probe", "calibration", "correction"):
            p[n]["qos.reliability"] = "reliable"
    for spec in args.param:
        node, _, rest = spec.partition(":")
        key, sep, value = rest.partition(":=")
        if node not in p or not key or not sep:
            raise SystemExit(f"--param {spec!r}: expected NODE:NAME:=VALUE with NODE one of {', '.join(NODES)}")
        p[node][key] = _literal(value)
    return p


def _literal(text):
    """A --param value: YAML-like scalars/lists as ROS would read them."""
    import yaml
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def recorder_available() -> bool:
    try:
        return importlib.util.find_spec("inclinometer_calib.nodes.recorder") is not None
    except ImportError:
        return False


def run_graph(args, out, env) -> int:
    cfg = args.config or config_dir()
    params = build_params(args, out)
    names = ["probe", "calibration", "correction"]
    if args.no_calibration:
        names.remove("calibration")
    if not args.no_recorder:
        if recorder_available():
            names.append("recorder")
        else:
            print("[launch] recorder module not available: running without recording", flush=True)
    params["probe"]["wait_for_subscribers"] = len(names) - 1  # every other node reads /probe/imu
    lock = threading.Lock()
    log = open(os.path.join(out, "launch.log"), "w", encoding="utf-8")
    children = {}
    stop = {"requested": 0}

    def on_signal(signum, _frame):
        stop["requested"] += 1
        if stop["requested"] > 2:  # third Ctrl-C: no more patience
            for ch in children.values():
                if ch.poll() is None:
                    ch.proc.kill()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    rc = 0
    t0 = time.monotonic()
    try:
        # the consumers first, so that they are up when the probe starts publishing
        for name in [n for n in names if n != "probe"] + ["probe"]:
            cmd = node_command(name, params[name], cfg)
            with lock:
                print(f"[launch] starting {name}: {' '.join(cmd[1:])}", flush=True)
            children[name] = Child(name, cmd, env, lock, log)
        reason = None
        while reason is None:
            time.sleep(0.1)
            if stop["requested"]:
                reason, rc = "interrupted", 130
                break
            if args.timeout and time.monotonic() - t0 > args.timeout:
                reason, rc = f"timeout after {args.timeout:g} s", 1
                break
            for name, ch in children.items():
                code = ch.poll()
                if code is None:
                    continue
                if name == "probe":
                    reason = f"probe finished (exit status {code})"
                    rc = 0 if code == 0 else 1
                else:
                    reason, rc = f"{name} exited unexpectedly (status {code})", 1
                break
        with lock:
            print(f"[launch] {reason}; stopping the graph", flush=True)
        if rc == 0:
            # let the consumers close the last station (idle flush) and the recorder record it
            end = time.monotonic() + args.drain
            while time.monotonic() < end and not stop["requested"]:
                time.sleep(0.1)
        for name in STOP_ORDER:
            if name in children:
                code = children[name].stop()
                with lock:
                    print(f"[launch] {name} stopped (exit status {code})", flush=True)
                if code not in (0, -signal.SIGINT) and rc == 0 and name != "probe":
                    rc = 1
    finally:
        for ch in children.values():
            if ch.poll() is None:
                ch.proc.kill()
        for s, h in old.items():
            signal.signal(s, h)
        log.close()
    return rc


# --------------------------------------------------------------------------------------------
# Summary (independent reader: rosbags)
# --------------------------------------------------------------------------------------------
def read_bag(path):
    """Stations and coefficient messages of a bag as plain dicts, read with ``rosbags``."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    stations, coefficients = [], []
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [x for x in reader.connections
                 if x.topic in ("/survey/station", "/calibration/coefficients")]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/survey/station":
                d = {k: getattr(msg, k) for k in (
                    "station_id", "drift_deg", "azimuth_deg", "toolface_deg", "gravity_toolface_deg",
                    "total_gravity_mps2", "total_field_nt", "dip_deg", "delta_g_mps2", "delta_b_nt",
                    "delta_dip_deg", "status", "azimuth_undefined", "interference_suspected",
                    "coefficients_id", "reference_drift_deg", "reference_azimuth_deg",
                    "reference_toolface_deg", "samples_averaged", "duration_s")}
                d["stamp"] = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                stations.append({k: (v.item() if hasattr(v, "item") else v) for k, v in d.items()})
            else:
                coefficients.append({"id": msg.id, "coefficients_yaml": msg.coefficients_yaml,
                                     "accel_correction_matrix": [float(x) for x in msg.accel_correction_matrix],
                                     "mag_correction_matrix": [float(x) for x in msg.mag_correction_matrix]})
    return stations, coefficients


def station_errors(stations, coefficients_id=None):
    """drift/azimuth/toolface errors of corrected stations with a reference (``survey.summarize``)."""
    from .frames import wrap180
    from .survey import summarize

    sel = [s for s in stations if math.isfinite(s["reference_drift_deg"])
           and (s["coefficients_id"] if coefficients_id is None else s["coefficients_id"] == coefficients_id)]
    if not sel:
        return {"stations": 0}
    drift = np.array([s["drift_deg"] for s in sel])
    ref = np.array([[s["reference_drift_deg"], s["reference_azimuth_deg"], s["reference_toolface_deg"]]
                    for s in sel])
    az = np.array([s["azimuth_deg"] for s in sel])
    gtf = np.array([s["gravity_toolface_deg"] for s in sel])
    res = {"drift_deg": drift, "drift_err": drift - ref[:, 0], "azimuth_err": wrap180(az - ref[:, 1]),
           "toolface_err": wrap180(gtf - ref[:, 2])}
    out = summarize(res)
    tf = res["toolface_err"][np.isfinite(res["toolface_err"])]
    out["toolface_rms_deg"] = float(np.sqrt(np.mean(tf ** 2))) if len(tf) else float("nan")
    out["toolface_max_abs_deg"] = float(np.max(np.abs(tf))) if len(tf) else float("nan")
    out["status_counts"] = {str(k): int(sum(s["status"] == k for s in sel)) for k in (0, 1, 2)}
    out["max_abs_delta_b_nt"] = float(max(abs(s["delta_b_nt"]) for s in sel))
    out["max_abs_delta_dip_deg"] = float(max(abs(s["delta_dip_deg"]) for s in sel))
    out["max_abs_delta_g_mps2"] = float(max(abs(s["delta_g_mps2"]) for s in sel))
    return out


def coefficient_errors(cal, truth):
    """Estimated minus true parameters (gravity-vector convention for acc) and matrix differences."""
    out = {}
    for s in ("acc", "mag"):
        est = cal.triad(s).parameters()
        true = truth["coefficients"][s]["parameters"]
        err = {k: est[k] - true[k] for k in est}
        cm = np.array(truth["coefficients"][s]["correction_matrix"]).reshape(3, 3)
        off = np.array(truth["coefficients"][s]["offset"])
        out[s] = {
            "bias_err": [err[f"bias_{a}"] for a in "xyz"],
            "scale_err": [err[f"scale_{a}"] for a in "xyz"],
            "e_err": {k: v for k, v in err.items() if k.startswith("e_")},
            "max_abs_bias_err": max(abs(err[f"bias_{a}"]) for a in "xyz"),
            "max_abs_scale_err": max(abs(err[f"scale_{a}"]) for a in "xyz"),
            "max_abs_e_err": max(abs(v) for k, v in err.items() if k.startswith("e_")),
            "max_abs_correction_matrix_err": float(np.max(np.abs(cal.triad(s).correction_matrix - cm))),
            "max_abs_offset_err": float(np.max(np.abs(cal.triad(s).correction_offset - off))),
        }
    return out


def raw_station_means(bag_path, stations):
    """Uncorrected mean specific force (m/s²) and field (nT) over each station's averaging window,
    re-derived from the raw /probe/imu and /probe/mag streams of the bag (an independent path:
    the bag's raw samples, not the node's arithmetic)."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    t_imu, f, t_mag, m = [], [], [], []
    with AnyReader([Path(bag_path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [x for x in reader.connections if x.topic in ("/probe/imu", "/probe/mag")]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            if conn.topic == "/probe/imu":
                a = msg.linear_acceleration
                t_imu.append(t)
                f.append((a.x, a.y, a.z))
            else:
                v = msg.magnetic_field
                t_mag.append(t)
                m.append((v.x * 1e9, v.y * 1e9, v.z * 1e9))
    t_imu, f, t_mag, m = np.array(t_imu), np.array(f), np.array(t_mag), np.array(m)
    out = []
    for s in stations:
        t1 = s["stamp"]
        t0 = t1 - s["duration_s"] - 1e-6
        si = (t_imu >= t0) & (t_imu <= t1 + 1e-6)
        sm = (t_mag >= t0) & (t_mag <= t1 + 1e-6)
        out.append((f[si].mean(axis=0) if si.any() else np.full(3, np.nan),
                    m[sm].mean(axis=0) if sm.any() else np.full(3, np.nan)))
    return out


def before_after(bag_path, stations, cal):
    """Station errors before (raw sensors) and after (the node's corrected stations) calibration."""
    from .frames import gravity_from_specific_force, wrap180
    from .survey import evaluate

    sel = [s for s in stations if math.isfinite(s["reference_drift_deg"]) and s["coefficients_id"]]
    if not sel or cal is None:
        return []
    raw = raw_station_means(bag_path, sel)
    g = gravity_from_specific_force(np.array([r[0] for r in raw]))
    b = np.array([r[1] for r in raw])
    ref = np.array([[s["reference_drift_deg"], s["reference_azimuth_deg"], s["reference_toolface_deg"]] for s in sel])
    before = evaluate(g, b, cal.site, ref=ref)
    rows = []
    for k, s in enumerate(sel):
        az_after = float(wrap180(s["azimuth_deg"] - ref[k, 1])) if math.isfinite(s["azimuth_deg"]) else float("nan")
        rows.append({"ref_drift_deg": float(ref[k, 0]), "ref_azimuth_deg": float(ref[k, 1]),
                     "drift_err_before": float(before["drift_err"][k]),
                     "drift_err_after": float(s["drift_deg"] - ref[k, 0]),
                     # no azimuth to compare where the reference itself is (near) vertical
                     "azimuth_err_before": float(before["azimuth_err"][k]) if ref[k, 0] >= 0.5 else float("nan"),
                     "azimuth_err_after": az_after if ref[k, 0] >= 0.5 else float("nan")})
    return rows


def format_before_after(rows) -> list:
    if not rows:
        return []

    def rms(key):
        x = np.array([r[key] for r in rows], dtype=float)
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")

    def fmt(v):
        return f"{v:>9.3f}" if math.isfinite(v) else f"{'-':>9}"

    lines = ["", "before/after calibration (errors against the reference, deg; 'before' from the bag's raw streams)",
             f"{'drift':>7} {'azimuth':>8} {'Δdrift before':>14} {'after':>9} {'Δazimuth before':>16} {'after':>9}"]
    for r in rows:
        lines.append(f"{r['ref_drift_deg']:>7.1f} {r['ref_azimuth_deg']:>8.1f} {fmt(r['drift_err_before']):>14} "
                     f"{fmt(r['drift_err_after'])} {fmt(r['azimuth_err_before']):>16} {fmt(r['azimuth_err_after'])}")
    lines.append(f"{'RMS':>16} {rms('drift_err_before'):>14.3f} {rms('drift_err_after'):>9.4f} "
                 f"{rms('azimuth_err_before'):>16.3f} {rms('azimuth_err_after'):>9.4f}")
    return lines


def summarize_run(out, print_fn=print) -> dict:
    """Build (and print) the run summary from the files in ``out``; writes summary.json."""
    from .coeffs import Calibration, CoefficientError

    summary = {"out": out}
    bag = os.path.join(out, "survey.mcap")
    stations, coef_msgs = [], []
    if os.path.exists(bag):
        from rosbags.highlevel import AnyReaderError
        from rosbags.rosbag2 import ReaderError
        from rosbags.serde import SerdeError
        try:
            stations, coef_msgs = read_bag(bag)
        except (AnyReaderError, ReaderError, SerdeError, OSError, ValueError) as exc:
            summary["bag_error"] = f"{type(exc).__name__}: {exc}"
            print_fn(f"[summary] cannot read {bag}: {summary['bag_error']}")
    summary["stations_recorded"] = len(stations)
    summary["coefficient_messages"] = len(coef_msgs)
    cal = None
    if coef_msgs:
        cal = Calibration.from_yaml(coef_msgs[-1]["coefficients_yaml"], source=f"{bag} /calibration/coefficients")
        summary["coefficients_source"] = "bag"
    elif os.path.exists(os.path.join(out, "coeffs.yaml")):
        try:
            cal = Calibration.load(os.path.join(out, "coeffs.yaml"))
            summary["coefficients_source"] = "coeffs.yaml"
        except (OSError, CoefficientError) as exc:
            summary["coefficients_error"] = str(exc)
    if cal is not None:
        summary["coefficients_id"] = cal.id
        file_path = os.path.join(out, "coeffs.yaml")
        if os.path.exists(file_path):
            summary["coeffs_yaml_matches_bag"] = Calibration.load(file_path).id == cal.id
    truth_path = os.path.join(out, "truth.json")
    if cal is not None and os.path.exists(truth_path):
        with open(truth_path, encoding="utf-8") as fh:
            truth = json.load(fh)
        summary["coefficient_errors"] = coefficient_errors(cal, truth)
    summary["survey"] = station_errors(stations, cal.id if cal is not None else None)
    rows = []
    if stations and cal is not None:
        try:
            rows = before_after(bag, stations, cal)
        except (OSError, ValueError, KeyError) as exc:
            print_fn(f"[summary] before/after not available: {exc}")
    summary["before_after"] = rows
    summary["raw_stations"] = sum(1 for s in stations if not s["coefficients_id"])
    from .probelog import atomic_write_text
    atomic_write_text(os.path.join(out, "summary.json"), json.dumps(summary, indent=1, default=float) + "\n")
    lines = format_summary(summary) + format_before_after(rows)
    atomic_write_text(os.path.join(out, "report.md"), format_report(summary, lines, cal, stations))
    for line in lines:
        print_fn(line)
    print_fn(f"report: {os.path.join(out, 'report.md')}; bag: {bag}")
    return summary


def format_report(summary, summary_lines, cal, stations) -> str:
    """A Markdown run report: summary, the coefficients (paper Tables 2 and 3) and every station."""
    import datetime

    from .twelve_position import format_table2, format_table3

    out = [f"# Survey run report — {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M UTC}", "",
           "```", *[ln for ln in summary_lines if ln and not ln.startswith("===")], "```", ""]
    if cal is not None:
        out += ["## Calibration coefficients", "", "```", format_table2(cal.acc, cal.mag), "",
                format_table3(cal.acc, cal.mag), "```", ""]
    if stations:
        out += ["## Survey stations", "",
                "| id | coeffs | ref drift | ref azimuth | drift | azimuth | Δdrift | Δazimuth | ΔB nT | Δdip ° | status |",
                "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        from .frames import wrap180

        for s in stations:
            ref_i, ref_a = s["reference_drift_deg"], s["reference_azimuth_deg"]
            di = s["drift_deg"] - ref_i if math.isfinite(ref_i) else float("nan")
            da = float(wrap180(s["azimuth_deg"] - ref_a)) if math.isfinite(ref_a) else float("nan")
            flags = [n for n in ("azimuth_undefined", "interference_suspected") if s.get(n)]
            status = ["ok", "warn", "error"][min(int(s["status"]), 2)] + (f" ({', '.join(flags)})" if flags else "")
            out.append(f"| {s['station_id']} | {s['coefficients_id'] or 'none'} | {ref_i:.2f} | {ref_a:.2f} | "
                       f"{s['drift_deg']:.3f} | {s['azimuth_deg']:.3f} | {di:+.4f} | {da:+.4f} | "
                       f"{s['delta_b_nt']:+.0f} | {s['delta_dip_deg']:+.3f} | {status} |")
    return "\n".join(out) + "\n"


def format_summary(s) -> list:
    lines = ["", "=== run summary ===",
             f"bag: {s['stations_recorded']} survey stations ({s['raw_stations']} uncorrected), "
             f"{s['coefficient_messages']} coefficient message(s)"]
    if "coefficients_id" in s:
        lines.append(f"coefficients {s['coefficients_id']} (from {s.get('coefficients_source')}; "
                     f"coeffs.yaml matches: {s.get('coeffs_yaml_matches_bag', 'n/a')})")
    ce = s.get("coefficient_errors")
    if ce:
        lines.append("coefficients minus simulator truth (acc in the gravity-vector convention):")
        for sensor, unit in (("acc", "m/s^2"), ("mag", "nT")):
            e = ce[sensor]
            lines.append(f"  {sensor}: bias [{', '.join(f'{v:+.3g}' for v in e['bias_err'])}] {unit}; "
                         f"scale [{', '.join(f'{v:+.2e}' for v in e['scale_err'])}]; "
                         f"max |e err| {e['max_abs_e_err']:.2e}; max |C err| {e['max_abs_correction_matrix_err']:.2e}")
    sv = s.get("survey", {})
    if sv.get("stations"):
        lines.append(f"survey: {sv['stations']} corrected stations with a reference: drift RMS "
                     f"{sv['drift_rms_deg']:.4f} max {sv['drift_max_abs_deg']:.4f} deg; azimuth RMS "
                     f"{sv['azimuth_rms_deg']:.4f} max {sv['azimuth_max_abs_deg']:.4f} deg "
                     f"({sv['azimuth_stations']} stations); toolface RMS {sv['toolface_rms_deg']:.4f} deg")
        lines.append(f"  status ok/warn/error: {sv['status_counts']['0']}/{sv['status_counts']['1']}/"
                     f"{sv['status_counts']['2']}; max |dB| {sv['max_abs_delta_b_nt']:.0f} nT, max |ddip| "
                     f"{sv['max_abs_delta_dip_deg']:.3f} deg, max |dG| {sv['max_abs_delta_g_mps2']:.4f} m/s^2")
    else:
        lines.append("survey: no corrected stations with a reference")
    return lines


# --------------------------------------------------------------------------------------------
def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="inclinometer-calib-launch", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="run", help="output directory (default: ./run)")
    ap.add_argument("--overwrite", action="store_true", help="remove survey.mcap etc. of an earlier run in --out")
    ap.add_argument("--source", choices=("simulate", "csv", "mcap"), default="simulate")
    ap.add_argument("--input", help="input file for --source csv/mcap")
    ap.add_argument("--speed", type=float, default=1.0, help="playback speed factor (default 1)")
    ap.add_argument("--rate", type=float, default=100.0, help="simulated sample rate, Hz")
    ap.add_argument("--seed", type=int, default=7, help="simulator seed")
    ap.add_argument("--survey", choices=("stand_grid", "well_path", "none"), default="well_path")
    ap.add_argument("--stations", type=int, help="number of well-path stations")
    ap.add_argument("--station-seconds", type=float, help="time held at each station, s")
    ap.add_argument("--effect", action="append", default=[], help="extra simulated effect, e.g. axial_interference=300")
    ap.add_argument("--coeffs", help="coefficient YAML for the correction node (else: from the calibration node)")
    ap.add_argument("--no-calibration", action="store_true", help="no calibration node and no twelve-pose session")
    ap.add_argument("--no-recorder", action="store_true", help="do not record (no summary from the bag)")
    ap.add_argument("--reliable", action="store_true", help="reliable QoS for the raw streams (lossless replay)")
    ap.add_argument("--param", action="append", default=[], metavar="NODE:NAME:=VALUE",
                    help="extra node parameter, e.g. correction:publish_corrected:=true")
    ap.add_argument("--config", help="directory with <node>.yaml parameter files (default: the package's config/)")
    ap.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID for the graph (default: inherited)")
    ap.add_argument("--drain", type=float, default=3.0, help="seconds between the probe's end and stopping the rest")
    ap.add_argument("--timeout", type=float, default=0.0, help="stop the run after this many seconds (0: none)")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.source != "simulate" and not args.input:
        print("error: --source csv/mcap needs --input", file=sys.stderr)
        return 2
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    existing = [f for f in ("survey.mcap", "coeffs.yaml", "summary.json", "truth.json")
                if os.path.exists(os.path.join(out, f))]
    if existing:
        if not args.overwrite:
            print(f"error: {out} already holds {', '.join(existing)} (use --overwrite or another --out)",
                  file=sys.stderr)
            return 2
        for f in existing + ["truth_coeffs.yaml", "launch.log"]:
            p = os.path.join(out, f)
            if os.path.isdir(p):
                shutil.rmtree(p)
            elif os.path.exists(p):
                os.remove(p)
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    if args.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    t0 = time.monotonic()
    rc = run_graph(args, out, env)
    print(f"[launch] graph ran for {time.monotonic() - t0:.1f} s", flush=True)
    if rc in (0, 130) and not args.no_recorder:
        try:
            summarize_run(out)
        except (OSError, ValueError, KeyError) as exc:
            print(f"[summary] failed: {type(exc).__name__}: {exc}", flush=True)
            rc = rc or 1
    return rc


if __name__ == "__main__":
    sys.exit(main())

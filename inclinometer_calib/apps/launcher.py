"""Start the whole graph as separate processes, stop it cleanly, and summarize the run.

``inclinometer-calib-launch`` / ``python -m inclinometer_calib.apps.launcher`` is the PyPI-environment
stand-in for ``ros2 launch inclinometer_calib survey.launch.py`` (``launch`` and ``launch_ros``
have no wheels).  It starts ``probe``, ``calibration``, ``correction`` and (if importable)
``recorder`` as child processes (``python -m inclinometer_calib.nodes.<name> --ros-args ...``,
each with ``config/<name>.yaml`` when present plus the run's parameters), forwards their output
line by line with a ``[name]`` prefix, and stops everything when the probe finishes (after a
short drain so the last station is closed and recorded) or on Ctrl-C/SIGTERM: SIGINT first,
then SIGTERM and SIGKILL after timeouts (a node still running 10 s after SIGINT is first asked
for its threads' stacks, which the log then shows: where it hangs); the recorder is stopped last.

Then it prints a summary, read back from the recorded bag (:func:`bag.read_messages`: the
definitions the bag records, ``rosbags``' deserializer, not the recorder's code): the calibration coefficients against the simulator truth (``truth.json``
written by the probe) and the survey station angles against their reference attitudes.

``--out DIR`` leaves ``survey.mcap``, ``coeffs.yaml``, ``truth.json`` (+ ``truth_coeffs.yaml``),
``correction_state.json`` and ``summary.json``.

Recovery.  A recorder that dies while the graph runs is restarted, once the other nodes have
forgotten the process that died (:func:`restart_delay_s`), into a new file in the same directory
(``survey_1.mcap``, ``survey_2.mcap``, …: the bag writer never overwrites); the latched
``/calibration/coefficients`` reach the new recorder again (transient local).  The calibration and
correction nodes are restarted the same way, resuming from the run's recording (``resume.bags``);
the correction node applies the calibration node's ``coeffs.yaml`` (``fallback_coeffs_file``) until
a record arrives on the topic and continues the station ids from ``correction_state.json``
(``state_file``).  At most :data:`MAX_RESTARTS` restarts per node; a probe that dies ends the run,
and the run waits for a restart still due when the probe ends.  The summary is built from all bag
parts in time order; a part the killed recorder left without its summary is first recovered
(:func:`bag.recover`) into ``<part>.recovered.mcap`` (into the temporary directory when ``--out``
has no room for it) and the summary says so.  A recorder that ends with exit status 4 (its recording
incomplete: a write the disk refused), or dies while the disk holding ``--out`` has less than
:data:`RESTART_MIN_FREE_BYTES` free, is not restarted: a new part would not hold a chunk.  Nor is
a node that ends with exit status 2 (:data:`NODE_REFUSED`) after refusing its parameters or input
at its start (its ``<Node>: error:`` line), which a restart would repeat; the run stops and its
last line gives the node's own error line (an error in a callback mid-run, ``error while
running``, is restarted as any death).

Pre-flight.  Before anything starts (no domain reserved, ``--out`` untouched, no node started)
:func:`preflight` checks what the nodes would refuse at their start: ``--input`` (a CSV's header, a
bag's /probe/imu and /probe/mag in its summary), the node parameters (``--plugin``, ``--site``,
``--param``, ``--foxglove-port``) and ``--coeffs``, loaded as the correction node loads it (the
``--plugin`` sources named first); a problem is one ``error:`` line, exit status 2.

Domain.  Without ``--domain-id`` and without ``ROS_DOMAIN_ID`` in the environment the launcher
reserves a free domain (:func:`rosenv.reserve_domain_id`) for the whole run and prints it; a
given id (option or environment) is reserved exactly, and refused (exit 2) when another
inclinometer_calib run holds it.  The graph runs on the probe's time base: with ``stamp:=log``
the probe publishes ``/clock`` and the calibration and correction nodes get ``use_sim_time``.

Exit status (the last line says why):

* 0 — a clean run: every node ran to the end, the calibration (if it ran) solved, the input was
  intact, the summary was written;
* 1 — the run completed but is not clean: a node died (also when it was restarted), the
  calibration node ran but no coefficients were recorded (it did not solve), the probe's MCAP
  input was damaged (probe exit status 3; the readable part was replayed), the probe failed,
  the run timed out, the summary failed, the recording is incomplete (recorder exit status 4: a
  write the disk refused; not a reason to restart it), or a file of the launcher's own could not
  be written (``launch.log``, ``summary.json``, ``report.md``, … : said once each, in words; the
  summary is still printed, and the last line says e.g. ``the disk is full: OUT: summary.json,
  report.md not written``).  The graph is still drained and summarized;
* 2 — usage error (the pre-flight checks included: a bad ``--input``, ``--coeffs``, ``--plugin``,
  ``--site`` or ``--param``; nothing has started), ``--out`` in use, or the requested ROS_DOMAIN_ID
  is in use by another run;
* 130 — interrupted (Ctrl-C / SIGTERM).
"""
from __future__ import annotations

import argparse
import errno
import importlib.util
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..io.bag import RUN_BAG as BAG, next_run_part as next_bag_part, read_bag, run_parts as bag_parts
from ..core.deps import MissingDependency, require
from ..core.geomag import NORTH_CHOICES
from ..rig.liveview import station_label
from ..io.topics import TOPIC_STATION

NODES = ("probe", "calibration", "correction", "wits", "live", "recorder")
STOP_ORDER = ("probe", "calibration", "correction", "wits", "live", "recorder")  # the recorder last: it records the others
#: Nodes restarted when they die mid-run: they carry no state the run cannot rebuild — the recorder
#: writes a new part (the probe's and the correction node's history give it what it missed); the
#: calibration and correction nodes rebuild theirs from the run's recording (``resume.bags``) and go
#: on where the node that died left off (a paced replay waits for them meanwhile).
RESTARTABLE = ("recorder", "correction", "calibration")
#: The Fast DDS transport the nodes use instead of shared memory (:func:`loopback_profile`)
LOOPBACK_TRANSPORT_ID = "inclinometer_calib_udp_loopback"
#: Fast DDS's participant lease (s) where no profile sets one
FASTDDS_DEFAULT_LEASE_S = 20.0
#: A node that died is restarted this long (s) after its DDS participant's lease has run out, so
#: that every other participant has forgotten it first (see :func:`restart_delay_s`)
RESTART_AFTER_LEASE_S = 1.0
#: The least drain (s, wall) after a node restarted once the probe had finished: its start-up and
#: what its publishers' history gives it
RESTART_DRAIN_S = 5.0
#: --reliable: the raw streams' history depth (keep last), messages: 20 s at 1 kHz
RELIABLE_DEPTH = 20_000
MAX_RESTARTS = 3  # per node: a node that keeps dying ends the run
#: A paced replay waits this long (s, wall) for a reader that left the graph (a restart takes a
#: second or two) before it goes on without it.
FLOW_GONE_S = 10.0
#: ... and waits at most this long (s, wall) after its last sample for every reader to take the end.
FLOW_END_S = 30.0
#: Exit status of the probe node when its MCAP input was damaged (it replayed the readable part).
PROBE_INPUT_DAMAGED = 3
#: Exit status of a node that refused its parameters or input (``nodes.common.run``; its reason in
#: one line, ``<Node>: error: ...``): not restarted, a restart with the same parameters would fail
#: the same way; the run's last line carries the node's reason (:attr:`Child.error`)
NODE_REFUSED = 2
ERROR_MARK = ": error: "
#: Exit status of the recorder when its recording is incomplete (a write the disk refused:
#: ``nodes.recorder.RECORDING_INCOMPLETE``); its last line, after this mark, says what is missing
RECORDING_INCOMPLETE = 4
INCOMPLETE_MARK = "recording incomplete: "
#: The signal on which a node prints every thread's Python stack and goes on
#: (``nodes.executor.STACKS_SIGNAL``, registered by every node's ``main``); the launcher sends it
#: to a node still running after SIGINT, and waits this long (s) for the stacks to be said.
STACKS_SIGNAL = signal.SIGUSR1
STACKS_WAIT_S = 1.0
#: Free bytes below which the disk holding --out counts as full: a recorder that dies then is not
#: restarted into a new part (it would not get past its first chunk)
RESTART_MIN_FREE_BYTES = 1 << 20
#: errno of a write refused for want of room: a full disk, a quota, a file size limit
REFUSED_WRITES = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
STATE_FILE = "correction_state.json"
WITSML_FILE = "trajectory.xml"  # the wits node's WITSML trajectory (--witsml or --wits-port; its parents beside it)


#: Fast DDS defaults for the graph's nodes, in the config directory (see :func:`dds_profile_env`)
DDS_PROFILE = "fastdds.xml"
#: The variables Fast DDS 2 and 3 read a default profiles file from.
DDS_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def dds_profile_env(env: dict, cfg) -> str:
    """Point the nodes' Fast DDS at ``<cfg>/fastdds.xml`` (reliable writers' heartbeat 0.1 s,
    participant announcements every 0.5 s: the end of a replay and a late-starting node's discovery
    in tenths of a second, not 3 s) — unless the user's environment names a profiles file already
    (a rig's own DDS set-up wins) or there is none.  Sets ``env`` in place; returns what to say."""
    given = [v for v in DDS_PROFILE_VARS if env.get(v)]
    if given:
        return f"Fast DDS profile {env[given[0]]} (from {given[0]})"
    path = os.path.join(cfg, DDS_PROFILE) if cfg else ""
    if not path or not os.path.isfile(path):
        return "Fast DDS defaults"
    for v in DDS_PROFILE_VARS:
        env[v] = path
    return f"Fast DDS profile {path} (heartbeats 0.1 s, announcements 0.5 s)"


def loopback_profile(env: dict, cfg):
    """``(the nodes' environment, profiles file to remove at the end)``: every node of the graph
    talks over UDP on the loopback only, never through shared memory.

    Why: with Fast DDS 2.14's shared-memory transport a node SIGKILLed while the probe writes to
    it can leave the probe's ``publish`` blocked for good (its stack, taken by the launcher at the
    stop: ``rclpy/publisher.py ... in publish``, the process deaf to SIGINT and SIGTERM), or its
    restarted successor matched but never served, or never hearing the probe's discovery
    (eProsima/Fast-DDS #5053, #5469): 5 times in about 95 runs of the killed-nodes test.  With
    every node on UDP: none in 92 runs (docs/benchmarks.md, section 10).  The cost is
    the loopback's system calls: the graph tests' CPU 103 → 113–119 s.

    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` makes rmw_fastrtps set the transports itself
    (shared memory and UDP), whatever ``FASTDDS_BUILTIN_TRANSPORTS`` says: the nodes run instead
    with the range left to the profile (``SYSTEM_DEFAULT``) and a copy of the graph's profile
    (``config/fastdds.xml``: its lease, announcements, heartbeats) that adds what LOCALHOST gives —
    a UDPv4 transport on 127.0.0.1 only, peers looked for on 127.0.0.1 among 32 participants,
    discovery on its unicast port — without the shared memory: discovery stays on this machine,
    and a process of the domain under plain LOCALHOST (``ros2 topic echo``, a test) still finds
    them over UDP.  ``(env, None)`` unchanged where the graph does not run on the package's profile
    under Fast DDS with LOCALHOST (a rig's own DDS set-up is left as it is), or where the copy
    cannot be written."""
    import xml.etree.ElementTree as ET

    ours = os.path.join(cfg, DDS_PROFILE) if cfg else ""
    if not (env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps")
            and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST" and ours and os.path.isfile(ours)
            and all(env.get(v) == ours for v in DDS_PROFILE_VARS)):
        return env, None
    ns = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
    q = lambda tag: f"{{{ns}}}{tag}"                                               # noqa: E731

    def sub(parent, tag, text=None, first=False):
        e = ET.Element(q(tag))
        e.text = text
        parent.insert(0, e) if first else parent.append(e)
        return e

    def loopback(parent, tag):
        sub(sub(sub(sub(parent, tag), "locator"), "udpv4"), "address", "127.0.0.1")

    ET.register_namespace("", ns)
    try:
        tree = ET.parse(ours)
    except (ET.ParseError, OSError):
        return env, None
    root = tree.getroot()
    participant = next((e for e in root.iter(q("participant")) if e.get("is_default_profile") == "true"), None)
    if participant is None:
        return env, None
    descriptor = sub(sub(root, "transport_descriptors", first=True), "transport_descriptor")
    sub(descriptor, "transport_id", LOOPBACK_TRANSPORT_ID)
    sub(descriptor, "type", "UDPv4")
    sub(sub(descriptor, "interfaceWhiteList"), "address", "127.0.0.1")
    sub(descriptor, "maxInitialPeersRange", "32")
    rtps = participant.find(q("rtps"))
    rtps = rtps if rtps is not None else sub(participant, "rtps")
    builtin = rtps.find(q("builtin"))
    builtin = builtin if builtin is not None else sub(rtps, "builtin")
    loopback(builtin, "metatrafficUnicastLocatorList")
    loopback(builtin, "initialPeersList")
    sub(sub(rtps, "userTransports"), "transport_id", LOOPBACK_TRANSPORT_ID)
    sub(rtps, "useBuiltinTransports", "false")
    try:
        fd, path = tempfile.mkstemp(prefix="inclinometer_calib_fastdds_", suffix=".xml")
        with os.fdopen(fd, "wb") as fh:
            tree.write(fh, encoding="UTF-8", xml_declaration=True)
    except OSError:
        return env, None
    return dict(env, ROS_AUTOMATIC_DISCOVERY_RANGE="SYSTEM_DEFAULT", **{v: path for v in DDS_PROFILE_VARS}), path


def participant_lease_s(env: dict):
    """The lease (s) after which the graph's Fast DDS participants take a silent one as gone: the
    default participant profile's ``leaseDuration`` in the profiles file the nodes read (ours,
    ``config/fastdds.xml``: 5 s, or a rig's own), else Fast DDS's default (20 s).  A file named by
    ``FASTDDS_DEFAULT_PROFILES_FILE`` alone, which Fast DDS 2 (Jazzy's) does not read, gives at
    least the default.  ``None`` under another RMW (its restarts are not delayed) or for an infinite
    lease (any of Fast DDS's ``DURATION_INFINITY``, ``DURATION_INFINITE_SEC``,
    ``DURATION_INFINITE_NSEC``: the dead one is never forgotten, waiting would not help)."""
    if not env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        return None
    path = next((env[v] for v in DDS_PROFILE_VARS if env.get(v)), "")
    floor = FASTDDS_DEFAULT_LEASE_S if path and not env.get(DDS_PROFILE_VARS[0]) else 0.0
    if not path or not os.path.isfile(path):
        return FASTDDS_DEFAULT_LEASE_S
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return FASTDDS_DEFAULT_LEASE_S    # Fast DDS itself will say what is wrong with it
    local = lambda e: e.tag.rsplit("}", 1)[-1]                                    # noqa: E731
    profiles = [e for e in root.iter() if local(e) == "participant"]
    profile = next((e for e in profiles if e.get("is_default_profile") == "true"), None)
    lease = next((e for e in profile.iter() if local(e) == "leaseDuration"), None) if profile is not None else None
    if lease is None:
        return FASTDDS_DEFAULT_LEASE_S
    parts = {local(e): (e.text or "").strip() for e in lease}
    texts = [(lease.text or "").strip(), *parts.values()]
    if any(t.upper() in ("DURATION_INFINITY", "DURATION_INFINITE_SEC", "DURATION_INFINITE_NSEC") for t in texts):
        return None
    try:
        return max(floor, float(parts.get("sec", 0) or 0) + float(parts.get("nanosec", 0) or 0) * 1e-9)
    except ValueError:
        return FASTDDS_DEFAULT_LEASE_S


def restart_delay_s(env: dict) -> float:
    """How long after a node died the launcher restarts it: until the other participants have
    forgotten the dead one (its lease, :func:`participant_lease_s`, and a second).  A successor
    matched while the writers still hold the dead reader (and, over shared memory, its port) can
    stay matched but deaf: no sample ever reaches it (eProsima/Fast-DDS #5053, #5469; seen here,
    once in 21 runs, with the restart 0.1 s after the kill).  A paced replay waits meanwhile."""
    lease = participant_lease_s(env)
    return 0.0 if lease is None else lease + RESTART_AFTER_LEASE_S


def config_dir():
    """``config/`` of the source tree, else ``share/inclinometer_calib/config`` of an install."""
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "config")
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
    if isinstance(value, str) and not value:
        return '""'          # rcl cannot parse "name:=" (nothing after it)
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
        self.incomplete = ""   # the recorder's "recording incomplete: ..." words, if it said them
        self.error = ""        # the reason of the node's last "<Node>: error: <reason>" line (exit status 2)
        self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, text=True, bufsize=1, errors="replace",
                                     start_new_session=True)  # the launcher alone decides when to stop
        self._thread = threading.Thread(target=self._pump, name=f"out-{name}", daemon=True)
        self._thread.start()

    def _pump(self):
        for line in self.proc.stdout:
            text = f"[{self.name}] {line.rstrip()}"
            if INCOMPLETE_MARK in line:
                self.incomplete = line.split(INCOMPLETE_MARK, 1)[1].strip()
            head, mark, reason = line.partition(ERROR_MARK)
            if mark and head and " " not in head:    # nodes.common.run's one line, not a log record
                self.error = reason.strip()
            with self._lock:
                print(text, flush=True)
                if self._log:
                    self._log.write(text + "\n")

    def poll(self):
        return self.proc.poll()

    def stop(self, sigint_s=10.0, sigterm_s=5.0):
        """SIGINT, then SIGTERM, then SIGKILL; returns the exit status.  A node still running
        ``sigint_s`` after SIGINT is first asked for its threads' stacks (:data:`STACKS_SIGNAL`),
        which its output carries into the run's log: where it hangs, said before it is killed."""
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
                self._say(f"[launch] {self.name} still running {wait:g} s after {signal.Signals(sig).name}"
                          + (": its threads' stacks follow" if sig == signal.SIGINT else ""))
                if sig == signal.SIGINT:
                    self._stacks()
        rc = self.proc.wait()
        self._thread.join(2.0)
        return rc

    def _say(self, text):
        with self._lock:
            print(text, flush=True)
            if self._log:
                self._log.write(text + "\n")

    def _stacks(self, wait_s=STACKS_WAIT_S):
        """Ask the node for every thread's Python stack (:data:`STACKS_SIGNAL`) and give its
        output that long to reach the log."""
        try:
            self.proc.send_signal(STACKS_SIGNAL)
            self.proc.wait(wait_s)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass


def refused_write(path, exc, print_fn=print, who="launch", name=None) -> dict:
    """A write of the launcher's own that the OS refused, said once in words (``[summary] cannot
    write OUT/summary.json: no space left on the device (ENOSPC)``); returns the entry for the
    run's list of files not written (``name``: how the last line names it, default the file name)."""
    from ..core.output import refused_write_words

    short, words = refused_write_words(exc)
    print_fn(f"[{who}] cannot write {path}: {words}")
    return {"file": name or os.path.basename(os.path.normpath(path)), "reason": short, "errno": exc.errno}


def not_written_text(out, entries) -> str:
    """The last line's words for the files a refused write left out, by reason: ``the disk is full:
    OUT: launch.log, summary.json, report.md not written``."""
    said = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded"}
    by_reason = {}
    for e in entries:
        reason = said.get(e.get("errno")) or f"writes were refused ({e['reason']})"
        by_reason.setdefault(reason, []).append(e["file"])
    return "; ".join(f"{reason}: {out}: {', '.join(dict.fromkeys(files))} not written"
                     for reason, files in by_reason.items())


class RunLog:
    """``launch.log``: every line the launcher prints, also on disk.  A write the disk refuses
    (Python's buffer flushes every few kB) is said once on stdout and ends the file: the run and
    its output on stdout go on.  :attr:`not_written` is then the entry for the final line."""

    def __init__(self, path):
        self.path = path
        self.not_written = None
        self._fh = None
        try:
            self._fh = open(path, "w", encoding="utf-8")
        except OSError as exc:
            self._refused(exc)

    def write(self, text):
        if self._fh is not None:
            try:
                self._fh.write(text)
            except OSError as exc:
                self._refused(exc)

    def close(self):
        if self._fh is not None:
            fh, self._fh = self._fh, None
            try:
                fh.close()   # flushes what is buffered
            except OSError as exc:
                self._refused(exc)

    def _refused(self, exc):
        fh, self._fh = self._fh, None
        if fh is not None:
            try:
                fh.close()   # releases the descriptor; its flush is refused again
            except OSError:
                pass
        self.not_written = refused_write(self.path, exc, lambda text: print(
            f"{text}: the launch log stops here, the output goes on on stdout", flush=True))
        self.not_written["file"] += " (from then on)"


def disk_full(out):
    """Why the disk holding ``out`` counts as full (less than :data:`RESTART_MIN_FREE_BYTES`
    free), or None."""
    try:
        st = os.statvfs(out)
    except OSError:
        return None
    free = st.f_bavail * st.f_frsize
    if free >= RESTART_MIN_FREE_BYTES:
        return None
    return f"the disk holding {out} is full ({free} bytes free)"


def node_command(name, params, cfg):
    cmd = [sys.executable, "-m", f"inclinometer_calib.nodes.{name}", "--ros-args"]
    if cfg:
        f = os.path.join(cfg, f"{name}.yaml")
        if os.path.isfile(f):
            cmd += ["--params-file", f]
    for key, value in params.items():
        cmd += ["-p", f"{key}:={_fmt(value)}"]
    return cmd


def site_node_parameters(path) -> dict:
    """The nodes' ``site.*`` parameters of a site file (:func:`geomag.site_parameters`, read back
    by the nodes with :func:`geomag.site_from_parameters`); the file is parsed here first
    (:func:`geomag.load_site_file`) so that a bad site is refused once, in the CLI's words, rather
    than by three nodes.  ``ValueError`` (one line naming the file and the key) for a bad site."""
    from ..core.geomag import load_site_file, read_site_section, site_parameters

    load_site_file(path)
    return {f"site.{k}": v for k, v in site_parameters(read_site_section(path)).items()}


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
    if args.model_effects:
        p["calibration"]["model.effects"] = args.model_effects
    if args.coeffs:
        p["correction"]["coeffs_file"] = os.path.abspath(args.coeffs)
    if args.north != "auto":
        p["correction"]["north"] = args.north
    if args.plugin:
        # the nodes' plug-in sources, named here too (the summary reads the run's records)
        from ..core.plugins import PluginError, name_plugins
        try:
            specs = [ref.get("file") or ref["module"] for ref in name_plugins(args.plugin)]
        except PluginError as exc:
            raise SystemExit(f"--plugin: {exc}") from None
        p["calibration"]["plugins"] = p["correction"]["plugins"] = specs
    if not args.no_calibration:
        # a restarted correction node applies what the calibration node wrote until the topic speaks
        p["correction"]["fallback_coeffs_file"] = os.path.join(out, "coeffs.yaml")
    p["correction"]["state_file"] = os.path.join(out, STATE_FILE)  # station ids continue across restarts
    p["recorder"]["output"] = os.path.join(out, BAG)
    if args.wits_port:
        p["wits"].update(port=int(args.wits_port), output=os.path.join(out, "wits0.dat"))
    if args.wits_port or args.witsml:
        p["wits"]["witsml_file"] = os.path.join(out, WITSML_FILE)
    if args.foxglove_port:
        if not 1 <= args.foxglove_port <= 65535:
            raise SystemExit(f"--foxglove-port {args.foxglove_port}: a TCP port is 1..65535 (0: no live view)")
        try:   # before the graph starts, not as a node's traceback in it
            require("foxglove", "live", "the live view (--foxglove-port)")
        except MissingDependency as exc:
            raise SystemExit(f"error: {exc}") from None
        p["live"]["port"] = int(args.foxglove_port)   # the live view in Foxglove (host: config/live.yaml, loopback)
    if not args.unpaced or args.reliable:
        # lossless: reliable, and a history deep enough that a node running behind the replay on a
        # loaded machine catches up instead of losing the oldest samples (keep-last 1000 is 1 s at 1 kHz)
        for n in ("probe", "calibration", "correction"):
            p[n]["qos.reliability"] = "reliable"
            p[n].setdefault("qos.depth", RELIABLE_DEPTH)
    if not args.unpaced:
        # a paced replay (flow control): the probe never runs more than its window ahead of the
        # slowest reader; the readers' stations wait on the data's time alone (the source's
        # announcement, the calibration node's progress): the stations are reprocess's; the streams
        # are transient local: a node restarted mid-run gets what it missed from the probe's history
        for n in ("calibration", "correction"):
            p[n].setdefault("source.wait", True)
        for n in ("probe", "calibration", "correction"):
            p[n].setdefault("qos.durability", "transient_local")
    if not args.no_calibration:
        # the records apply from the data time they were solved at; a station waits until the
        # calibration node has taken it too (data time, not wall time)
        p["correction"].setdefault("calibration.node", "calibration")
    if args.site:
        # the site reference of the run (total field, dip, declination, gravity): the calibration
        # and correction nodes use it, the simulated probe lives in it
        # (a location is looked up by each node, in the same geomagnetic model: geomag.site_parameters)
        try:
            site_params = site_node_parameters(args.site)
        except ValueError as exc:
            raise SystemExit(f"--site: {exc}") from None
        for n in ("probe", "calibration", "correction"):
            p[n].update(site_params)
        for n in ("calibration", "correction"):
            p[n]["site.given"] = True
    for spec in args.param:
        node, _, rest = spec.partition(":")
        key, sep, value = rest.partition(":=")
        if node not in p or not key or not sep:
            raise SystemExit(f"--param {spec!r}: expected NODE:NAME:=VALUE with NODE one of {', '.join(NODES)}")
        p[node][key] = _literal(value)
    return p


def _literal(text):
    """A --param value: YAML-like scalars/lists as ROS would read them."""
    from ..core import yamltext
    try:
        return yamltext.load(text)
    except yamltext.YAMLError:
        return text


def recorder_available() -> bool:
    try:
        return importlib.util.find_spec("inclinometer_calib.nodes.recorder") is not None
    except ImportError:
        return False


@dataclass
class GraphResult:
    """What the graph run itself says about the run (the summary adds its own checks)."""

    interrupted: bool = False
    problems: list = field(default_factory=list)  # why the run is not clean, one sentence each
    calibration_ran: bool = False
    restarts: dict = field(default_factory=dict)  # node -> times it was restarted
    not_written: list = field(default_factory=list)  # the launcher's files a refused write left out
    recording_incomplete: bool = False  # the recorder said so (exit status 4)


def _config_value(cfg, node, key, default):
    """``key`` of ``config/<node>.yaml`` (``node: ros__parameters: ...``; dotted keys nest), else ``default``."""
    from ..core import yamltext

    path = os.path.join(cfg, f"{node}.yaml") if cfg else None
    if not path or not os.path.isfile(path):
        return default
    with open(path, encoding="utf-8") as fh:
        value = ((yamltext.load(fh) or {}).get(node) or {}).get("ros__parameters") or {}
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return default
        value = value[part]
    return value


def _exit_text(code) -> str:
    """``-9`` -> ``"killed by SIGKILL"``; other codes as ``"exit status N"``."""
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


def _node_error(ch, code) -> str:
    """``": <reason>"`` of a node that ended with :data:`NODE_REFUSED` after refusing its
    parameters or input at its start — its own ``<Node>: error:`` line (:attr:`Child.error`, read
    to the end of its output first; ``nodes.common.run``) — else ``""``: the run's last line then
    says why the node stopped, not only that it did."""
    if code != NODE_REFUSED:
        return ""
    ch._thread.join(2.0)
    return f": {ch.error}" if ch.error else ""


def run_graph(args, out, env) -> GraphResult:
    """Start the nodes, watch them (restarting the :data:`RESTARTABLE` ones that die), drain and
    stop them; see the module docstring."""
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
    if (args.wits_port or args.witsml) and "correction" in names:
        names.append("wits")
    if args.foxglove_port and "correction" in names:
        names.append("live")
    consumers = [n for n in names if n not in ("probe", "wits", "live")]
    if not args.unpaced:
        params["probe"].setdefault("flow.readers", list(consumers))
        params["probe"].setdefault("flow.gone_s", FLOW_GONE_S)
        params["probe"].setdefault("flow.end_timeout_s", FLOW_END_S)
    else:
        # not paced, but the run ends once the nodes have taken the end (with what they lost
        # counted): the accounting then has their final counts, whatever the machine's speed (the
        # recorder, which never ends once it lost a sample, writes what it holds at its stop)
        params["probe"].setdefault("flow.end_readers", [n for n in consumers if n != "recorder"])
    # every other node reads imu, mag and temperature; the reference goes to correction and recorder
    params["probe"].setdefault("wait_for_subscribers", len(consumers))
    params["probe"].setdefault("wait_for_reference_subscribers",
                               sum(n in ("correction", "recorder") for n in consumers))
    station_readers = sum(n in ("recorder", "wits", "live") for n in names)
    if station_readers and "correction" in consumers:
        # stations are reliable but volatile: a reader not yet subscribed would miss the first ones
        params["probe"].setdefault("wait_for_topic_subscribers", [f"{TOPIC_STATION}={station_readers}"])
        # ... and a reader the probe sees in the graph may not be matched yet with the correction
        # node's publisher (seen under load: the WITS node missed the first station)
        params["correction"].setdefault("wait_for_station_readers", station_readers)
    if params["probe"].get("stamp", _config_value(cfg, "probe", "stamp", "log")) == "log":
        # one time base: the probe publishes /clock (log time), the others run on it
        for n in ("calibration", "correction"):
            params[n].setdefault("use_sim_time", True)
    result = GraphResult(calibration_ran="calibration" in names)
    lock = threading.Lock()
    log = RunLog(os.path.join(out, "launch.log"))
    children = {}
    restarts = {n: 0 for n in RESTARTABLE}
    due = {}      # node -> (monotonic time of its restart, why): it died; the graph forgets it first
    delay = restart_delay_s(env)
    node_env, node_profile = loopback_profile(env, cfg)
    stop = {"requested": 0}

    def say(text):
        with lock:
            print(f"[launch] {text}", flush=True)
            log.write(f"[launch] {text}\n")

    def start(name):
        cmd = node_command(name, params[name], cfg)
        children[name] = Child(name, cmd, node_env, lock, log)
        say(f"starting {name} (pid {children[name].proc.pid}): {' '.join(cmd[1:])}")

    def on_signal(signum, _frame):
        stop["requested"] += 1
        if stop["requested"] > 2:  # third Ctrl-C: no more patience
            for ch in children.values():
                if ch.poll() is None:
                    ch.proc.kill()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    t0 = time.monotonic()
    try:
        if node_profile:
            say(f"the nodes talk over UDP on the loopback only, not shared memory (a node killed while the probe "
                f"writes to it can leave the probe's writer blocked, or its successor deaf): Fast DDS profile "
                f"{node_profile}")
        # the consumers first, so that they are up when the probe starts publishing
        for name in consumers + [n for n in names if n in ("wits", "live")] + ["probe"]:
            start(name)
            if name == "live":
                host = params["live"].get("host", _config_value(cfg, "live", "host", "127.0.0.1"))
                say(f"live view: open ws://{host}:{params['live']['port']} in Foxglove (Open connection -> "
                    f"Foxglove WebSocket) with the layout {os.path.join(cfg or 'config', 'foxglove_layout.json')}")
        reason = None
        drain_until = None  # set when the probe has finished: let the others close the last station
        while reason is None:
            time.sleep(0.1)
            if stop["requested"]:
                reason, result.interrupted = "interrupted", True
                break
            if args.timeout and time.monotonic() - t0 > args.timeout:
                reason = f"timeout after {args.timeout:g} s"
                result.problems.append(f"the run timed out after {args.timeout:g} s")
                break
            if drain_until is not None and not due and time.monotonic() >= drain_until:
                reason = "probe finished and the graph drained"
                break
            for name, (when, died) in list(due.items()):
                if time.monotonic() >= when:
                    del due[name]
                    result.restarts[name] = restarts[name]
                    result.problems.append(f"{died}; restarted")
                    start(name)
                    if drain_until is not None:
                        # restarted after the probe's end: the drain gives it time to take what its
                        # publishers' history holds (the latched stations and records)
                        drain_until = max(drain_until, time.monotonic() + max(args.drain, RESTART_DRAIN_S))
            for name, ch in list(children.items()):
                code = ch.poll()
                if code is None or name in due or (name == "probe" and drain_until is not None):
                    continue
                if name == "probe":
                    if code == 0:
                        say("probe finished")
                    elif code == PROBE_INPUT_DAMAGED:
                        say(f"probe finished (exit status {code}): its input bag was damaged")
                        result.problems.append("the probe's input bag was damaged: only its readable part was "
                                               "replayed (see the [probe] warnings for where)")
                    else:
                        reason = f"probe failed ({_exit_text(code)})" + _node_error(ch, code)
                        result.problems.append(reason)
                        break
                    # the probe ends once every reader has taken the end (paced: and the recorder
                    # every station and record): a short drain is enough
                    drain_until = time.monotonic() + args.drain
                    continue
                died = f"{name} died unexpectedly ({_exit_text(code)})"
                refused = _node_error(ch, code)
                if refused:
                    # it refused its parameters or input at its start (its "<Node>: error:" line; a
                    # callback's error mid-run says "error while running" and is restarted): a
                    # restart would fail the same way; the run's last line says why in its words
                    reason = (f"{name} refused its parameters or input ({_exit_text(code)})"
                              f"{refused}; not restarted: it would fail the same way")
                    result.problems.append(reason)
                    del children[name]   # it has ended: said once here, not again as a node that did not stop
                    break
                if name == "recorder" and code == RECORDING_INCOMPLETE:
                    # it ended by itself with a recording it says is incomplete: a new part would
                    # not mend that (a disk that refuses writes), so no restart
                    ch._thread.join(2.0)   # its last line, which says what is missing, read to the end
                    reason = (f"the recorder ended early: the recording is incomplete: "
                              f"{ch.incomplete or _exit_text(code)}")
                    result.problems.append(reason)
                    result.recording_incomplete = True
                    break
                full = disk_full(out) if name == "recorder" else None
                if full is not None:
                    reason = f"{died}; not restarted into a new part: {full}"
                    result.problems.append(reason)
                    break
                if name in restarts and restarts[name] < MAX_RESTARTS:
                    restarts[name] += 1
                    when = (f" in {delay:g} s, once the graph has forgotten the process that died (its DDS "
                            f"participant's lease)") if delay else ""
                    if name == "recorder":
                        params["recorder"]["output"] = next_bag_part(out)
                        say(f"{died}: restarting it into {os.path.basename(params['recorder']['output'])}{when} "
                            f"(restart {restarts[name]} of at most {MAX_RESTARTS}); the run goes on")
                    else:
                        parts = bag_parts(out) if "recorder" in children else []
                        if parts:
                            params[name]["resume.bags"] = parts
                        say(f"{died}: restarting it{when} (restart {restarts[name]} of at most {MAX_RESTARTS})"
                            + (f", resuming from the recording ({', '.join(os.path.basename(x) for x in parts)})"
                               if parts else ", without a recording to resume from") + "; the run goes on")
                    due[name] = (time.monotonic() + delay, died)
                    continue
                reason = died + (f" after {restarts[name]} restarts" if restarts.get(name) else "")
                result.problems.append(reason)
                break
        say(f"{reason}; stopping the graph")
        for name, (_, died) in due.items():
            say(f"{name}: not restarted: the run ended before its restart was due")
            result.problems.append(f"{died}; not restarted: the run ended before its restart was due")
        for name in STOP_ORDER:
            if name in children and name not in due:
                code = children[name].stop()
                say(f"{name} stopped ({_exit_text(code)})")
                if name == "recorder" and code == RECORDING_INCOMPLETE:
                    # what it did not record is a problem of the run, said in the recorder's words
                    said = f"the recording is incomplete: {children[name].incomplete or _exit_text(code)}"
                    if not result.recording_incomplete:
                        result.problems.append(said)
                    result.recording_incomplete = True
                elif name != "probe" and code not in (0, -signal.SIGINT) and not result.interrupted:
                    result.problems.append(f"{name} did not stop cleanly ({_exit_text(code)})")
    finally:
        for ch in children.values():
            if ch.poll() is None:
                ch.proc.kill()
        for s, h in old.items():
            signal.signal(s, h)
        log.close()
        if log.not_written is not None:
            result.not_written.append(log.not_written)
        if node_profile:
            try:
                os.remove(node_profile)
            except OSError:
                pass
    return result


# --------------------------------------------------------------------------------------------
# Summary (read back from the bag: io.bag's decoding, rosbags' deserializer)
# --------------------------------------------------------------------------------------------
def trajectory_summary(stations, coefficients_id=None) -> dict:
    """The deepest corrected station with a position: MD, TVD, north, east and its ISCWSA 1σ
    (horizontal semi-major and vertical, m), and how many stations have a position."""
    placed = [s for s in stations if (coefficients_id is None or s["coefficients_id"] == coefficients_id)
              and math.isfinite(s.get("tvd_m", math.nan))]
    out = {"stations": len(placed)}
    if placed:
        import numpy as np

        last = max(placed, key=lambda s: s["measured_depth_m"])
        out.update({k: last[k] for k in ("measured_depth_m", "tvd_m", "north_m", "east_m", "azimuth_reference")})
        cov = np.reshape(last.get("position_covariance_ned_m2", [math.nan] * 9), (3, 3))
        if np.all(np.isfinite(cov)):
            out["sigma_horizontal_major_m"] = float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2])[-1], 0.0)))
            out["sigma_vertical_m"] = float(math.sqrt(max(cov[2, 2], 0.0)))
    return out


def station_errors(stations, coefficients_id=None):
    """drift/azimuth/toolface errors of corrected stations with a reference (``survey.summarize``)."""
    from ..core.frames import wrap180
    from ..core.survey import summarize

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


DASH = "—"  # a value that does not exist (NaN: no reference, no azimuth near vertical, no data)


def _num(value, spec: str) -> str:
    """``format(value, spec)``, or an em dash for a missing value (None, NaN, inf)."""
    try:
        ok = value is not None and math.isfinite(value)
    except TypeError:
        ok = False
    return format(value, spec) if ok else DASH


def readable_parts(out, print_fn=print) -> list:
    """Every bag part of ``out`` (:func:`bag_parts`) with the file to read it from.

    A part that is not a finalized, intact bag (a killed recorder leaves no summary section, which
    ``rosbags`` refuses) is first rewritten with :func:`bag.recover` into ``<part>.recovered.mcap``
    (the part itself is kept).  Returns one dict per part: ``file`` (its name), ``read`` (the path
    to read, None if unreadable), and for a recovered part ``recovered_into``, ``messages_saved``
    and ``problem`` (the first damage found); ``error`` when nothing could be read.
    """
    from ..io.bag import BagError, open_bag, recover

    parts = []
    for path in bag_parts(out):
        info = {"file": os.path.basename(path), "read": path}
        parts.append(info)
        try:
            reader = open_bag(path)
            for _ in reader.messages(strict=False):
                pass
            if reader.finalized and not reader.errors:
                continue
            dst = path[:-len(".mcap")] + ".recovered.mcap"
            if os.path.exists(dst):
                os.remove(dst)  # derived from the part, which is kept: rebuild it
            try:
                report = recover(path, dst)
            except OSError as exc:
                # no room beside the part (a full disk): the copy goes to the temporary directory
                if os.path.exists(dst):
                    os.remove(dst)   # the writer cut it back to whole records: still only a part
                info["not_written"] = refused_write(dst, exc, print_fn, who="summary")
                dst = os.path.join(tempfile.mkdtemp(prefix="inclinometer_calib_"), os.path.basename(dst))
                report = recover(path, dst)
                print_fn(f"[summary] {info['file']} recovered into {dst} instead (kept there)")
        except (BagError, OSError) as exc:
            info.update(read=None, error=str(exc))
            print_fn(f"[summary] cannot read {path}: {exc}")
            continue
        info.update(read=dst, recovered_into=dst if "not_written" in info else os.path.basename(dst),
                    messages_saved=report.saved,
                    problem=str(reader.errors[0]) if reader.errors else "not finalized")
        print_fn(f"[summary] {info['file']} was not finalized (its recorder died): recovered "
                 f"{report.saved} messages into {info['recovered_into']}")
    return parts


def summarize_run(out, print_fn=print, loop: bool = True, graph=None, paced: bool = True,
                  input_counts=None) -> dict:
    """Build (and print) the run summary from the files in ``out``; writes summary.json and report.md,
    and with ``loop`` the model loop (:func:`model_loop`): lab_model.yaml, compare/ and report.html.
    ``input_counts``: an MCAP input's messages per topic (:func:`check_bag_input`), set against
    what the probe sent.

    Stations and coefficient messages come from all bag parts (:func:`readable_parts`), in the
    order the parts were written, which is time order; a coefficient record that a restarted
    recorder received again (latched) is counted once.
    """
    from ..core.coeffs import Calibration, CoefficientError

    summary = {"out": out}
    stations, coef_msgs, status, progress = [], [], None, []
    parts = readable_parts(out, print_fn) if bag_parts(out) else []
    if parts:
        seen = set()
        for part in parts:
            if part["read"] is None:
                continue
            try:
                st, co, stat = read_bag(part["read"], progress)
            except (OSError, ValueError) as exc:
                part["error"] = f"{type(exc).__name__}: {exc}"
                print_fn(f"[summary] cannot read {part['read']}: {part['error']}")
                continue
            stations += st
            for m in co:
                if (m["id"], m["stamp"]) not in seen:  # latched: re-delivered to a restarted recorder
                    seen.add((m["id"], m["stamp"]))
                    coef_msgs.append({**m, "part": part["file"]})
            status = stat or status
    errors = [f"{p['file']}: {p['error']}" for p in parts if "error" in p]
    if errors:
        summary["bag_error"] = "; ".join(errors)
    summary["bag_parts"] = [{k: v for k, v in p.items() if k != "read"} for p in parts]
    readable = [p["read"] for p in parts if p["read"] is not None and "error" not in p]
    summary["stations_recorded"] = len(stations)
    summary["coefficient_messages"] = len(coef_msgs)
    if status is not None:
        summary["calibration_status"] = status
    from ..io.accounting import account, first_record, recorded_counts, unique_stations

    try:        # the stand captures the first record was solved from, and where they lie in time
        first = Calibration.from_yaml(coef_msgs[0]["coefficients_yaml"]) if coef_msgs else None
    except (CoefficientError, ValueError):
        first = None            # a record the summary cannot read: said below, where it is used
    captures, stand = first_record(first)
    summary["accounting"] = account(stations, progress, restarts=getattr(graph, "restarts", None),
                                    calibration_ran=getattr(graph, "calibration_ran", True), paced=paced,
                                    recorded=recorded_counts([p["read"] for p in parts if p["read"] is not None]),
                                    records=len(coef_msgs), captures=captures, stand=stand,
                                    input_counts=input_counts)
    stations, _ = unique_stations(stations)     # a restarted recorder received the latest ones again
    summary["stations_recorded"] = len(stations)
    cal = None
    if coef_msgs:
        cal = Calibration.from_yaml(coef_msgs[-1]["coefficients_yaml"],
                                    source=f"{coef_msgs[-1]['part']} /calibration/coefficients")
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
    summary["raw_stations"] = summary["accounting"]["stations"]["uncorrected"]
    summary["trajectory"] = trajectory_summary(stations, cal.id if cal is not None else None)
    if os.path.exists(os.path.join(out, WITSML_FILE)):
        summary["witsml"] = witsml_summary(os.path.join(out, WITSML_FILE), stations)
    misfit = [s for s in stations if s.get("model_misfit")]
    summary["model_misfit_stations"] = len(misfit)
    if misfit:
        summary["model_diagnosis"] = misfit[-1]["model_diagnosis"]
    # the launcher's files a refused write left out (a full disk): said as they fail, the summary
    # is printed all the same, and the launcher's last line names them
    not_written = [p.pop("not_written") for p in summary["bag_parts"] if "not_written" in p]
    want_loop, loop = loop, None
    if want_loop and stations and cal is not None and readable:
        loop = model_loop(out, readable, cal, print_fn, not_written=not_written)
        if loop is not None:
            summary["model_loop"] = loop_summary(loop)
    if not_written:
        summary["not_written"] = not_written
    write_text(os.path.join(out, "summary.json"), json.dumps(summary, indent=1, default=float) + "\n",
               not_written, print_fn)
    lines = format_summary(summary) + (loop.lines if loop is not None else [])
    report = os.path.join(out, "report.md")
    if not write_text(report, format_report(summary, lines, cal, stations, loop), not_written, print_fn):
        report = None
    page = write_html_report(out, summary, cal, loop, print_fn, not_written=not_written)
    if not_written:
        summary["not_written"] = not_written   # for the launcher's last line (summary.json has what it knew)
    for line in lines:
        print_fn(line)
    bags = ", ".join(p["file"] for p in parts) or "none"
    written = [f for f in (report, page) if f]
    print_fn(f"report: {' and '.join(written) or 'none written'}; bag: {bags}")
    return summary


def write_text(path, text, not_written, print_fn=print) -> bool:
    """``atomic_write_text``; a write the OS refuses is said once in words (:func:`refused_write`)
    and added to ``not_written``.  True if written."""
    from ..core.output import atomic_write_text

    try:
        atomic_write_text(path, text)
        return True
    except OSError as exc:
        not_written.append(refused_write(path, exc, print_fn, who="summary"))
        return False


def witsml_summary(path, stations) -> dict:
    """The live WITSML document checked: valid against the schema, and its stations those the
    recorded bag's stations export to (:mod:`witsml`)."""
    from ..rig import witsml

    res = {"file": path}
    try:
        with open(path, "rb") as fh:
            xml = fh.read()
        res["version"] = witsml.validate(xml)
        res["stations"] = len(witsml.read_trajectory(xml))
        res["valid"] = True
    except (OSError, witsml.WitsmlError) as exc:
        res.update(valid=False, error=str(exc))
        return res
    res["bag_stations"] = len(witsml.select_stations(stations)[0])
    return res


def model_loop(out, readable, cal, print_fn, not_written=None):
    """The model loop of the run (:func:`lab.loop.run_loop`) on its bag: the lab's finding on the
    captured data and the field effect ladder.  With several bag parts (a recorder restarted) the
    largest is used, and said.  None (said) when it cannot run; a write the disk refused
    (``lab_model.yaml``, ``compare/``) is said in words and added to ``not_written``."""
    from ..core.coeffs import Calibration, CoefficientError
    from ..lab.loop import run_loop

    bag = max(readable, key=os.path.getsize)
    if len(readable) > 1:
        print_fn(f"[summary] model loop on the largest bag part, {os.path.basename(bag)}")
    truth = None
    truth_path = os.path.join(out, "truth_coeffs.yaml")
    if os.path.exists(truth_path):
        try:
            truth = Calibration.load(truth_path)
        except (OSError, CoefficientError) as exc:
            print_fn(f"[summary] {truth_path} not used: {exc}")
    try:
        require("matplotlib", "report", "the run report's plots")
        return run_loop(bag, cal, out, truth=truth, warn=lambda m: None)
    except OSError as exc:
        if exc.errno not in REFUSED_WRITES:
            print_fn(f"[summary] the model loop did not run: {type(exc).__name__}: {exc}")
            return None
        entry = refused_write(f"the model loop's files ({os.path.join(out, 'lab_model.yaml')}, "
                              f"{os.path.join(out, 'compare')}/)", exc, print_fn, who="summary",
                              name="lab_model.yaml, compare/ (the model loop)")
        if not_written is not None:
            not_written.append(entry)
        return None
    except (MissingDependency, ValueError) as exc:
        print_fn(f"[summary] the model loop did not run: {type(exc).__name__}: {exc}")
        return None


def loop_summary(loop) -> dict:
    """The loop's figures for summary.json."""
    out = {"ladder": [{"model": r.name, "record": r.calibration.id if r.calibration is not None else None,
                       **r.metrics} for r in loop.runs]}
    if loop.skipped:
        out["lab_skipped"] = loop.skipped
    if loop.diagnosis is not None:
        rec = loop.diagnosis.recommended
        out["lab_finding"] = rec.label if rec is not None else None
        out["lab_verdict"] = loop.diagnosis.verdict
    if loop.record is not None:
        out["lab_record"] = loop.record.id
        out["lab_model"] = loop.record.model.describe()
    return out


def loop_findings(loop) -> list:
    """The lab's finding in a sentence, for the top of the run report: the effect the live record
    misses and the lab's record, or why the lab found nothing or did not look."""
    from ..lab.diagnose import FINDING_SUMMARY

    if loop.skipped:
        return [f"The lab did not look for a missing effect: {loop.skipped}."]
    dg = loop.diagnosis
    if dg is None:
        return []
    rec = dg.recommended
    if rec is None:
        return ["The lab finds nothing missing from the live record: "
                + FINDING_SUMMARY.get(dg.finding, dg.finding).format(effect="", refused=dg.refused) + "."]
    return [f"The lab finds {rec.label} missing from the live record"
            + (f"; its record {loop.record.id} (lab_model.yaml) is lab_model below, fitted on this run's stations "
               "(in-sample)." if loop.record is not None else ".")]


def write_html_report(out, summary, cal, loop, print_fn, not_written=None):
    """``report.html``: the run's figures with plots (the field effect ladder, residuals model by
    model).  None (said) without matplotlib or a loop, or when the disk refuses it (said, and added
    to ``not_written``)."""
    if loop is None or not loop.runs:
        return None
    from ..lab import compare

    try:
        page = compare.to_html(loop.runs, os.path.basename(bag_parts(out)[0]) if bag_parts(out) else "",
                               title="Survey run report: the model loop", findings=loop_findings(loop),
                               intro=[ln for ln in format_summary(summary) if ln and not ln.startswith("===")]
                               + ([loop.skipped] if loop.skipped else [])
                               + ([loop.diagnosis.verdict] if loop.diagnosis is not None else []))
    except MissingDependency as exc:
        print_fn(f"[summary] report.html not written: {exc}")
        return None
    path = os.path.join(out, "report.html")
    written = write_text(path, page, not_written if not_written is not None else [], print_fn)
    return path if written else None


def format_report(summary, summary_lines, cal, stations, loop=None) -> str:
    """A Markdown run report: summary, the model loop (the lab's finding, the field effect ladder),
    the coefficients (paper Tables 2 and 3) and every station."""
    import datetime

    from ..calibrate.twelve_position import format_table2, format_table3

    out = [f"# Survey run report — {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M UTC}", "",
           "```", *[ln for ln in summary_lines if ln and not ln.startswith("===")], "```", ""]
    if loop is not None and loop.runs:
        from ..lab import compare
        md = compare.to_markdown(loop.runs, "survey.mcap", title="The model loop")
        out += ["## The model loop", ""]
        if loop.skipped:
            out += [loop.skipped, ""]
        if loop.diagnosis is not None:
            out += ["The lab on the run's captured data:", "", "```", loop.diagnosis.verdict, "```", ""]
        if loop.record is not None:
            out += [f"The lab's record `{loop.record.id}` ({loop.record.model.describe()}) is `lab_model.yaml`.", ""]
        out += md.split("\n", 2)[2].splitlines() + ["", "Plots: `report.html`.", ""]
    if cal is not None:
        out += ["## Calibration coefficients", "", "```", format_table2(cal.acc, cal.mag), "",
                format_table3(cal.acc, cal.mag), "```", ""]
    if stations:
        out += ["## Survey stations", "",
                "| id | coeffs | ref drift | ref azimuth | drift | azimuth | Δdrift | Δazimuth | ΔB nT | Δdip ° | status |",
                "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        from ..core.frames import wrap180

        for s in stations:
            ref_i, ref_a = s["reference_drift_deg"], s["reference_azimuth_deg"]
            di = s["drift_deg"] - ref_i if math.isfinite(ref_i) else float("nan")
            da = float(wrap180(s["azimuth_deg"] - ref_a)) if math.isfinite(ref_a) else float("nan")
            out.append(f"| {s['station_id']} | {s['coefficients_id'] or DASH} | {_num(ref_i, '.2f')} | "
                       f"{_num(ref_a, '.2f')} | {_num(s['drift_deg'], '.3f')} | {_num(s['azimuth_deg'], '.3f')} | "
                       f"{_num(di, '+.4f')} | {_num(da, '+.4f')} | {_num(s['delta_b_nt'], '+.0f')} | "
                       f"{_num(s['delta_dip_deg'], '+.3f')} | {station_label(s)} |")
    return "\n".join(out) + "\n"


def _part_text(p) -> str:
    if "error" in p:
        return f"{p['file']} (unreadable: {p['error']})"
    if "recovered_into" in p:
        return (f"{p['file']} (not finalized, its recorder died: {p['messages_saved']} messages recovered "
                f"into {p['recovered_into']})")
    return p["file"]


def format_summary(s) -> list:
    lines = ["", "=== run summary ==="]
    parts = s.get("bag_parts") or []
    if len(parts) > 1 or any("recovered_into" in p or "error" in p for p in parts):
        lines.append(f"bag parts ({len(parts)}, in time order): " + "; ".join(_part_text(p) for p in parts))
    raw = s.get("raw_stations") or {}
    said = (" (" + (", ".join(f"{v} uncorrected: {k}" for k, v in raw.items()) or "all corrected") + ")"
            if s["stations_recorded"] else "")
    lines.append(f"bag: {s['stations_recorded']} survey stations{said}, {s['coefficient_messages']} coefficient "
                 "message(s)")
    if s.get("accounting"):
        from ..io.accounting import format_account
        lines.extend(format_account(s["accounting"]))
    if "coefficients_id" in s:
        lines.append(f"coefficients {s['coefficients_id']} (from {s.get('coefficients_source')}; "
                     f"coeffs.yaml matches: {s.get('coeffs_yaml_matches_bag', 'n/a')})")
    elif s.get("calibration_status"):
        st = s["calibration_status"]
        said = f"{len(st['captured'])} of 12 poses captured"
        lines.append(f"calibration not solved: state {st['state']}, {said}, pending {st['pending']}"
                     + (f" ({st['message']})" if st["message"] and st["message"] != said else ""))
    ce = s.get("coefficient_errors")
    if ce:
        lines.append("coefficients minus simulator truth (acc in the gravity-vector convention):")
        for sensor, unit in (("acc", "m/s^2"), ("mag", "nT")):
            e = ce[sensor]
            lines.append(f"  {sensor}: bias [{', '.join(_num(v, '+.3g') for v in e['bias_err'])}] {unit}; "
                         f"scale [{', '.join(_num(v, '+.2e') for v in e['scale_err'])}]; "
                         f"max |e err| {_num(e['max_abs_e_err'], '.2e')}; "
                         f"max |C err| {_num(e['max_abs_correction_matrix_err'], '.2e')}")
    sv = s.get("survey", {})
    if sv.get("stations"):
        lines.append(f"survey: {sv['stations']} corrected stations with a reference: drift RMS "
                     f"{_num(sv['drift_rms_deg'], '.4f')} max {_num(sv['drift_max_abs_deg'], '.4f')} deg; azimuth RMS "
                     f"{_num(sv['azimuth_rms_deg'], '.4f')} max {_num(sv['azimuth_max_abs_deg'], '.4f')} deg "
                     f"({sv['azimuth_stations']} stations); toolface RMS {_num(sv['toolface_rms_deg'], '.4f')} deg")
        lines.append(f"  status ok/warn/error: {sv['status_counts']['0']}/{sv['status_counts']['1']}/"
                     f"{sv['status_counts']['2']}; max |dB| {_num(sv['max_abs_delta_b_nt'], '.0f')} nT, max |ddip| "
                     f"{_num(sv['max_abs_delta_dip_deg'], '.3f')} deg, max |dG| "
                     f"{_num(sv['max_abs_delta_g_mps2'], '.4f')} m/s^2")
    else:
        lines.append("survey: no corrected stations with a reference")
    tr = s.get("trajectory") or {}
    if tr.get("stations"):
        line = (f"trajectory: {tr['stations']} stations placed by minimum curvature; deepest MD "
                f"{tr['measured_depth_m']:.1f} m: TVD {tr['tvd_m']:.1f} m, N {tr['north_m']:+.1f} m, "
                f"E {tr['east_m']:+.1f} m" + (f" ({tr['azimuth_reference']} north)" if tr.get("azimuth_reference") else ""))
        if "sigma_vertical_m" in tr:
            line += (f"; ISCWSA 1σ there {tr['sigma_horizontal_major_m']:.2f} m horizontal (semi-major), "
                     f"{tr['sigma_vertical_m']:.2f} m vertical")
        lines.append(line)
    if s.get("model_misfit_stations"):
        lines.append(f"field monitor (live): {s['model_misfit_stations']} station(s) flagged — the last said: "
                     f"{s['model_diagnosis']}")
    elif sv.get("stations"):
        lines.append("field monitor (live): the record's model explained every station tested")
    wx = s.get("witsml")
    if wx:
        if wx.get("valid"):
            lines.append(f"WITSML {wx['version']} trajectory: {wx['file']}: {wx['stations']} stations, valid against "
                         f"the schema (the bag's stations export to {wx['bag_stations']})")
        else:
            lines.append(f"WITSML trajectory: {wx['file']}: NOT valid: {wx['error']}")
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
    ap.add_argument("--model-effects", default="", metavar="NAME[:sensor[:axes]][@scope],...",
                    help="effects the calibration node fits beyond the paper's model on the captured poses, e.g. "
                         "temperature_bias:mag")
    ap.add_argument("--plugin", action="append", help="Python file (or module) defining plug-in effects that records "
                    "may use: the calibration and correction nodes' plugins parameter (repeatable)")
    ap.add_argument("--site", help="site reference YAML for the calibration and correction nodes (and the simulated "
                                   "probe): values (total_field_nt, dip_deg, declination_deg, gravity_mps2) and/or a "
                                   "location (latitude_deg, longitude_deg, altitude_m, date, model WMM2025|IGRF-14, crs) "
                                   "looked up by each node; e.g. config/rig_site.yaml")
    ap.add_argument("--north", choices=NORTH_CHOICES, default="auto",
                    help="north of every azimuth and position the run puts out (stations, WITS0, WITSML, live view): "
                         "grid, true or magnetic; auto (default): grid on a site with a grid (crs), else true with a "
                         "declination, else magnetic")
    ap.add_argument("--no-calibration", action="store_true", help="no calibration node and no twelve-pose session")
    ap.add_argument("--no-recorder", action="store_true", help="do not record (no summary from the bag)")
    ap.add_argument("--wits-port", type=int, default=0, metavar="PORT",
                    help="also start the wits node: the corrected stations as WITS0 record 07 on tcp://127.0.0.1:PORT "
                         "and in <out>/wits0.dat (0: no wits node); it also writes <out>/trajectory.xml")
    ap.add_argument("--foxglove-port", type=int, default=0, metavar="PORT",
                    help="also start the live node: the survey live in Foxglove on ws://127.0.0.1:PORT (stations, "
                         "QC residuals, trajectory, diagnostics; layout config/foxglove_layout.json; 0: no live node)")
    ap.add_argument("--witsml", action="store_true",
                    help="start the wits node for <out>/trajectory.xml: the survey as a WITSML trajectory (2.1 unless "
                         "config/wits.yaml's witsml.version says 1.4.1.1), rewritten after every station")
    ap.add_argument("--no-loop", action="store_true", help="no model loop in the summary (the lab's finding on the "
                    "recorded data and the field effect ladder)")
    ap.add_argument("--unpaced", action="store_true",
                    help="publish at --speed like a live source, without waiting for the readers (by default a replay "
                         "is paced: it never runs ahead of the slowest reader, --speed is a ceiling); what a slow "
                         "reader loses is counted in the summary")
    ap.add_argument("--reliable", action="store_true",
                    help=f"with --unpaced: reliable QoS for the raw streams, with a history of {RELIABLE_DEPTH} messages")
    ap.add_argument("--param", action="append", default=[], metavar="NODE:NAME:=VALUE",
                    help="extra node parameter, e.g. correction:publish_corrected:=true")
    ap.add_argument("--config", help="directory with <node>.yaml parameter files (default: the package's config/)")
    ap.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID for the graph, reserved exactly (refused if another "
                    "run holds it; default: ROS_DOMAIN_ID if set, else a free one)")
    ap.add_argument("--drain", type=float, default=0.5,
                    help="seconds between the probe's exit (once its readers have taken the end) and stopping the rest")
    ap.add_argument("--timeout", type=float, default=0.0, help="stop the run after this many seconds (0: none)")
    return ap.parse_args(argv)


def reserve_run_domain(args, env):
    """The run's ROS_DOMAIN_ID and the lock that reserves it (None: the parent holds it).

    ``--domain-id`` or ``ROS_DOMAIN_ID`` from the environment: exactly that id, refused with
    :class:`rosenv.DomainInUse` when another run holds it — unless the environment says the
    parent process reserved it for us (:data:`rosenv.RESERVED_BY_PARENT`, set by the tests'
    and benchmarks' isolated environments).  Neither: a free id (:func:`rosenv.reserve_domain_id`).
    Raises ValueError for an id that is not an integer in 0..232.
    """
    from . import rosenv

    text = str(args.domain_id) if args.domain_id is not None else (env.get("ROS_DOMAIN_ID") or "").strip()
    origin = "--domain-id" if args.domain_id is not None else "ROS_DOMAIN_ID"
    if not text:
        domain_id, lock = rosenv.reserve_domain_id()
        return domain_id, lock, "a free domain, reserved for this run"
    try:
        domain_id = int(text)
    except ValueError:
        raise ValueError(f"{origin} {text!r} is not an integer") from None
    if env.get(rosenv.RESERVED_BY_PARENT, "").strip() == str(domain_id):
        return domain_id, None, f"from {origin}, reserved by the parent process"
    return domain_id, rosenv.reserve_this_domain_id(domain_id), f"from {origin}, reserved for this run"


def _lock_out_dir(out):
    """Lock ``out`` for this run (an ``flock`` on ``out/.launch.lock``); None if another run holds it."""
    from .rosenv import try_lock_file

    return try_lock_file(os.path.join(out, ".launch.lock"))


def run_files(out) -> list:
    """Files of an earlier run in ``out`` that a new run would mix with (refused without --overwrite)."""
    from ..rig.witsml import PARENT_KINDS, parent_path

    names = ["coeffs.yaml", "summary.json", "truth.json", STATE_FILE, "lab_model.yaml", "report.html", "compare",
             WITSML_FILE, "wits0.dat"] + [parent_path(WITSML_FILE, kind) for kind in PARENT_KINDS]
    found = [os.path.basename(p) for p in bag_parts(out)]
    return found + [f for f in names if os.path.exists(os.path.join(out, f))]


def calibration_problems(out, summary) -> list:
    """Why the calibration of a run in which the calibration node ran did not deliver (empty if it did)."""
    solved_file = os.path.exists(os.path.join(out, "coeffs.yaml"))
    recorded = bool(summary and summary.get("coefficient_messages"))
    if recorded or (solved_file and summary is None):
        return []
    if solved_file:
        return ["the calibration solved (coeffs.yaml was written) but no coefficient message was recorded"]
    st = (summary or {}).get("calibration_status")
    detail = ""
    if st:
        said = f"{len(st['captured'])} of 12 poses captured"
        detail = (f" (last status: {st['state']}, {said}, pending {st['pending']}"
                  + (f"; {st['message']}" if st["message"] and st["message"] != said else "") + ")")
    return ["the calibration did not solve: the calibration node ran but no coefficients were recorded and no "
            f"coeffs.yaml was written{detail}"]


def check_bag_input(path) -> dict | None:
    """A replay's ``--input`` (``--source mcap``), checked cheaply before any node starts with the
    package's bag reader: it opens as an MCAP bag (:func:`bag.open_bag`: the file, its magic and
    header) and its summary section counts messages on /probe/imu and /probe/mag
    (:meth:`bag.BagReader.summary_counts`: no message is read).  A bag without a usable summary (a
    recorder that was killed) is left to the probe, which replays its readable part and says where
    it is damaged (exit status 3).  Raises :class:`common.UserError`, one line naming the file and
    what is wrong: the probe would refuse it (exit status 2) only once the graph had started.
    Returns the summary's message count per topic (None: no usable summary), which the run summary
    compares with what the probe sent (:func:`accounting.account`'s ``input_counts``)."""
    from ..io.bag import BagError, open_bag
    from ..io.topics import TOPIC_IMU, TOPIC_MAG
    from .common import UserError

    if os.path.isfile(path) and os.path.getsize(path) == 0:
        raise UserError(f"--input {path}: empty file (expected an MCAP bag)")
    try:
        reader = open_bag(path)
    except BagError as exc:
        raise UserError(f"--input {exc.path}: {exc.reason}") from None
    except OSError as exc:
        raise UserError(f"--input {path}: {exc.strerror}" if exc.strerror else f"--input {exc}") from None
    counts = reader.summary_counts()
    if counts is None:
        return None
    missing = [t for t in (TOPIC_IMU, TOPIC_MAG) if not counts.get(t)]
    if missing:
        held = ", ".join(f"{n} on {t}" for t, n in sorted(counts.items()) if n) or "no messages"
        raise UserError(f"--input {path}: no {' and no '.join(missing)} messages, nothing for the probe to "
                        f"replay (the bag holds {held})")
    return counts


def check_csv_input(path) -> None:
    """A ``--source csv`` ``--input``, checked before any node starts: it can be read (``.gz`` as
    gzip, as the probe reads it), is not empty, and its first line is a probe-log header (the
    reader's own check, :func:`probelog.canonical_text`, on that line alone); its rows are the
    probe's to read.  Raises :class:`common.UserError`, one line naming the file."""
    import gzip
    import zlib

    from ..io.probelog import HEADER, canonical_text
    from .common import UserError

    opener = gzip.open if str(path).endswith(".gz") else open
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace", newline="") as fh:
            first = fh.readline(1 << 16)
    except (OSError, EOFError, zlib.error) as exc:   # missing, unreadable, a directory, not gzip, corrupt
        raise UserError(f"--input {path}: {getattr(exc, 'strerror', None) or exc}") from None
    said = ("empty file" if not first else "line 1 is blank" if not first.strip()
            else "not text (a binary file?)" if "\ufffd" in first or "\x00" in first else "")
    if said:    # a binary file's "line 1" is not said back: it may be any length of bytes
        raise UserError(f"--input {path}: {said}: expected a probe-log CSV with the header {','.join(HEADER)}")
    try:
        canonical_text(first.rstrip("\r\n"), f"--input {path}")
    except ValueError as exc:
        raise UserError(str(exc)) from None


def check_coeffs(args) -> None:
    """``--coeffs`` loaded before any node starts, as the correction node will load it and
    ``reprocess`` loads its ``--coeffs`` (:func:`common.load_calibration`, :meth:`Calibration.load`),
    with the ``--plugin`` sources named first (:func:`build_params`, as the nodes name their
    ``plugins``): a missing or invalid record, or one that needs a plug-in not named, is refused
    here in one line instead of a node that exits 2 at its start.  Raises :class:`common.UserError`."""
    from .common import UserError, load_calibration

    if not args.coeffs:
        return
    if str(args.coeffs).lower() == "none":    # reprocess's word for "no record": not the launcher's
        raise UserError("--coeffs none: the launcher takes a coefficient file; leave --coeffs out to apply the "
                        "calibration node's records")
    try:
        load_calibration(args.coeffs)
    except UserError as exc:
        raise UserError(f"--coeffs {exc}") from None


def preflight(args) -> dict | None:
    """Check what the nodes would otherwise refuse only once the graph runs, before anything starts
    (no domain reserved, ``--out`` untouched, no node started): ``--input`` for csv/mcap
    (:func:`check_csv_input`, :func:`check_bag_input`), the run's node parameters
    (:func:`build_params`: ``--plugin``, ``--site``, ``--param``, ``--foxglove-port``) and ``--coeffs``
    (:func:`check_coeffs`).  Raises :class:`common.UserError` (one line; ``main`` exits 2).  Returns
    an MCAP input's message counts per topic (:func:`check_bag_input`; None otherwise)."""
    from .common import UserError

    if args.source != "simulate" and not args.input:
        raise UserError("--source csv/mcap needs --input")
    counts = None
    try:
        if args.source == "mcap":
            counts = check_bag_input(args.input)
        elif args.source == "csv":
            check_csv_input(args.input)
        try:
            build_params(args, os.path.abspath(args.out))   # names the --plugin sources the record may need
        except SystemExit as exc:
            raise UserError(str(exc.code).removeprefix("error: ")) from None
        check_coeffs(args)
    except MissingDependency as exc:
        raise UserError(str(exc)) from None
    return counts


def main(argv=None) -> int:
    from . import rosenv
    from .common import UserError

    args = parse_args(argv)
    try:
        input_counts = preflight(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    env = dict(os.environ)
    try:
        domain_id, domain_lock, how = reserve_run_domain(args, env)
    except rosenv.DomainInUse as exc:
        print(f"error: {exc}. Give another --domain-id (or ROS_DOMAIN_ID), or give neither to get a free one; "
              "or wait for that run to end", file=sys.stderr)
        return 2
    except (ValueError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = os.path.abspath(args.out)
    try:
        os.makedirs(out, exist_ok=True)
        out_lock = _lock_out_dir(out)
    except OSError as exc:   # e.g. a full disk: the lock file takes our pid
        from ..core.output import refused_write_words

        if domain_lock is not None:
            domain_lock.close()
        print(f"[launch] exit status 1: cannot start the run in {out}: {refused_write_words(exc)[1]}", flush=True)
        return 1
    try:
        if out_lock is None:
            print(f"error: another inclinometer-calib-launch is writing to {out}: choose another --out",
                  file=sys.stderr)
            return 2
        existing = run_files(out)
        if existing:
            if not args.overwrite:
                print(f"error: {out} already holds {', '.join(existing)} (use --overwrite or another --out)",
                      file=sys.stderr)
                return 2
            recovered = [f for f in os.listdir(out) if f.endswith(".recovered.mcap")]
            for f in existing + recovered + ["truth_coeffs.yaml", "launch.log", "report.md"]:
                p = os.path.join(out, f)
                if os.path.isdir(p):
                    shutil.rmtree(p)
                elif os.path.exists(p):
                    os.remove(p)
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST"
        env["PYTHONUNBUFFERED"] = "1"
        env["ROS_DOMAIN_ID"] = str(domain_id)
        env[rosenv.RESERVED_BY_PARENT] = str(domain_id)  # this launcher holds it for its nodes
        dds = dds_profile_env(env, args.config or config_dir())
        print(f"[launch] ROS_DOMAIN_ID={domain_id} ({how}); discovery range "
              f"{env['ROS_AUTOMATIC_DISCOVERY_RANGE']}; {dds}", flush=True)
        t0 = time.monotonic()
        result = run_graph(args, out, env)
        print(f"[launch] graph ran for {time.monotonic() - t0:.1f} s", flush=True)
        problems = list(result.problems)
        summary = None
        if not args.no_recorder:
            try:
                summary = summarize_run(out, loop=not args.no_loop, graph=result, paced=not args.unpaced,
                                        input_counts=input_counts)
                problems += summary.get("accounting", {}).get("problems", [])
            except (OSError, ValueError, KeyError, MissingDependency) as exc:
                print(f"[summary] failed: {type(exc).__name__}: {exc}", flush=True)
                problems.append(f"the summary failed ({type(exc).__name__}: {exc})")
        if result.calibration_ran and not result.interrupted:
            unsolved = calibration_problems(out, summary)
            if unsolved and result.recording_incomplete and not os.path.exists(os.path.join(out, "coeffs.yaml")):
                # the record may have been refused by the disk on both ways out (the bag, coeffs.yaml):
                # that is not evidence that the calibration did not solve
                unsolved = ["no coefficients were recorded and no coeffs.yaml was written: whether the calibration "
                            "solved is not on disk (the recording is incomplete; see the [calibration] lines)"]
            problems += unsolved
        not_written = result.not_written + list((summary or {}).get("not_written", []))
        if not_written:   # first: the reason the rest (an incomplete recording, …) follows from
            problems.insert(0, not_written_text(out, not_written))
    finally:
        if out_lock is not None:
            out_lock.close()
        if domain_lock is not None:
            domain_lock.close()
    if result.interrupted:
        print("[launch] exit status 130: interrupted", flush=True)
        return 130
    if problems:
        print(f"[launch] exit status 1: the run is not clean: {'; '.join(problems)}", flush=True)
        return 1
    print("[launch] exit status 0: clean run", flush=True)
    return 0

if __name__ == "__main__":
    sys.exit(main())

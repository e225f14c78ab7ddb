"""A full disk, for real: the recorder and the launcher writing onto a small file system that fills.

The file system is a tmpfs mounted in a mount namespace of its own (``unshare --mount``, which
needs root or CAP_SYS_ADMIN; without it the tests are skipped and say what is missing).  A holder
process (``sleep``) keeps the namespace, and so the mount, alive; the nodes run inside it
(``nsenter --mount``), the test reads and fills the disk through ``/proc/<holder>/root``.  When
the holder ends the namespace and its mount go with it: nothing is left mounted, whatever
happens to the test (the holder sleeps at most :data:`HOLD_S`).

* the recorder: the disk fills while it records (one ERROR line, in words; the messages counted
  per topic; space freed again: a new part, said at WARNING; exit status 4; the first part
  readable with ``bag.open_bag`` and ``bag.recover``), and a disk full before it starts (no crash,
  no empty file, exit status 4);
* the launcher: ``--out`` on a tmpfs that a short simulated run fills: no traceback, the summary
  printed, exit status 1, the last line says the disk is full.
"""
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

try:
    import rclpy  # noqa: F401
    from sensor_msgs.msg import Imu  # noqa: F401
except Exception as exc:  # ImportError or missing shared libraries
    pytest.skip(f"rclpy not importable ({exc!r}): run scripts/setup.sh and source scripts/env.sh",
                allow_module_level=True)

from inclinometer_calib.io import bag  # noqa: E402

# the suite's long poles run first (test/conftest.py): its wall time on a quiet 2-core machine, s
pytestmark = pytest.mark.long(24)

HOLD_S = 240  # longest life of a mount namespace (the holder's sleep), s

PUBLISHER = textwrap.dedent("""
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, DurabilityPolicy, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import Imu
    from inclinometer_calib.msg import CalibrationCoefficients
    rclpy.init()
    node = Node("full_disk_publisher")
    latched = node.create_publisher(CalibrationCoefficients, "/calibration/coefficients", QoSProfile(
        depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE))
    c = CalibrationCoefficients()
    c.id = "cal-full"
    latched.publish(c)
    imu = node.create_publisher(Imu, "/probe/imu", qos_profile_sensor_data)
    count = [0]
    def tick():
        m = Imu()
        m.header.stamp.sec = 1000 + count[0] // 200
        m.header.stamp.nanosec = (count[0] % 200) * 5_000_000
        m.angular_velocity.z = float(count[0])
        count[0] += 1
        imu.publish(m)
    node.create_timer(1.0 / 200.0, tick)
    print("READY", flush=True)
    try:
        rclpy.spin(node)
    except BaseException:
        pass
""")


class SmallDisk:
    """A tmpfs of ``size`` at ``mnt`` seen only by the processes started with :meth:`popen`."""

    def __init__(self, mnt: Path, size: str):
        missing = [t for t in ("unshare", "nsenter", "mount") if shutil.which(t) is None]
        if missing:
            pytest.skip(f"a real full disk needs {', '.join(missing)} (util-linux)")
        self.mnt = mnt
        mnt.mkdir(parents=True)
        self.holder = subprocess.Popen(
            ["unshare", "--mount", "--propagation", "private", "sh", "-c",
             f'mount -t tmpfs -o size={size} tmpfs "$0" && echo READY && exec sleep {HOLD_S}', str(mnt)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if "READY" not in self.holder.stdout.readline():
            err = self.holder.stderr.read().strip()
            self.holder.wait()
            pytest.skip("a real full disk needs a tmpfs mounted in a private mount namespace (unshare --mount: root "
                        f"or CAP_SYS_ADMIN), not available here: {err}")

    def path(self, *rel) -> Path:
        """A path on the small disk, as this (outside) process reaches it."""
        return Path(f"/proc/{self.holder.pid}/root") / self.mnt.relative_to("/") / Path(*rel)

    def popen(self, args, **kw):
        """A process in the disk's mount namespace (nsenter execs it: its pid is the process's)."""
        return subprocess.Popen(["nsenter", "-t", str(self.holder.pid), "-m", "--", *args], **kw)

    def free(self) -> int:
        st = os.statvfs(self.path())
        return st.f_bavail * st.f_frsize

    def fill(self, leave: int = 0) -> None:
        """Take all the free space but ``leave`` bytes (a filler file; ENOSPC ends it)."""
        with open(self.path("filler"), "ab", buffering=0) as fh:
            block = b"\0" * 4096
            try:
                while self.free() > leave:
                    fh.write(block)
            except OSError:
                pass

    def unfill(self) -> None:
        os.unlink(self.path("filler"))

    def close(self) -> None:
        if self.holder.poll() is None:
            self.holder.kill()
        self.holder.wait()
        self.holder.stdout.close()
        self.holder.stderr.close()


@pytest.fixture
def small_disk(tmp_path):
    disks = []

    def make(size):
        disks.append(SmallDisk(tmp_path / f"disk{len(disks)}", size))
        return disks[-1]
    yield make
    for d in disks:
        d.close()
    assert not any(str(tmp_path) in line for line in open("/proc/self/mounts")), "a mount was left behind"


def _publisher(tmp_path, env):
    from test_recorder import _start_publisher   # the recorder tests' publisher process, with this script

    return _start_publisher(tmp_path, env, PUBLISHER)


def _recorder(disk, tmp_path, env, *params):
    log = open(tmp_path / "recorder.log", "w+")
    args = [sys.executable, "-m", "inclinometer_calib.nodes.recorder", "--ros-args",
            "-p", f"output:={disk.mnt / 'survey.mcap'}", "-p", "topics:=[/probe/imu, /calibration/coefficients]",
            "-p", "compression:=none", "-p", "max_chunk_s:=0.3", "-p", "retry_s:=0.5",
            *[x for p in params for x in ("-p", p)]]
    return disk.popen(args, env=env, stdout=log, stderr=subprocess.STDOUT, text=True), log


def _wait_log(log, needle, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        text = Path(log.name).read_text()
        if needle in text:
            return text
        time.sleep(0.05)
    raise AssertionError(f"no {needle!r} in the recorder's output:\n{Path(log.name).read_text()}")


def _stop(proc, timeout=15):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


def _not_recorded(last_line):
    """{topic: n} from ``recording incomplete: 12 messages on /a, 3 on /b not recorded: disk full``."""
    words = last_line.split("recording incomplete: ", 1)[1].split(" not recorded:", 1)[0]
    return {t: int(n) for n, t in re.findall(r"(\d+) (?:messages )?on (/[^\s,]+)", words)}


def test_recorder_on_a_disk_that_fills_says_it_once_counts_and_goes_on_in_a_new_part(
        small_disk, tmp_path, ros_env):
    disk = small_disk("2m")
    pub = _publisher(tmp_path, ros_env)
    try:
        rec, log = _recorder(disk, tmp_path, ros_env)
        try:
            _wait_log(log, "recording /probe/imu")
            time.sleep(1.0)                     # some complete chunks first
            disk.fill(leave=24 * 1024)          # ~0.3 s of raw Imu at 200 Hz: full within a chunk or two
            _wait_log(log, "[ERROR]")
            time.sleep(1.5)                     # messages go by, counted, not recorded
            assert not disk.path("survey_1.mcap").exists()   # no new part while the disk is full
            disk.unfill()
            _wait_log(log, "the disk takes writes again")
            time.sleep(1.0)
        finally:
            rc = _stop(rec)
        text = Path(log.name).read_text()
        assert rc == 4, text                                      # recording incomplete
        assert "Traceback" not in text, text
        errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
        assert len(errors) == 1, text                             # said once
        err = errors[0]
        assert f"cannot write {disk.mnt / 'survey.mcap'}: no space left on the device (ENOSPC)" in err
        assert re.search(r"not recording from \d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d\d UTC on", err), err
        assert re.search(r"survey\.mcap holds \d+ messages, the last one received at .* UTC \(header stamp 10\d\d\.\d{3} "
                         r"s, on /probe/imu\)", err), err
        warn = [ln for ln in text.splitlines() if "the disk takes writes again" in ln]
        assert len(warn) == 1 and "[WARN]" in warn[0] and f"{disk.mnt / 'survey_1.mcap'} (a new part)" in warn[0]
        last = text.strip().splitlines()[-1]
        assert last.startswith("recording incomplete: ") and last.endswith(
            "not recorded: disk full; not finalized: survey.mcap"), last
        lost = _not_recorded(last)
        assert set(lost) == {"/probe/imu"} and lost["/probe/imu"] >= 150, last   # >= 0.75 s at 200 Hz

        first = bag.open_bag(disk.path("survey.mcap"))            # the part the disk filled
        got = [m for m in first.messages(strict=False)]
        assert got and not first.finalized
        assert [e.reason for e in first.errors] == [
            "file ends without a data-end record: the recording was not finalized (recorder crashed or was killed); "
            "all complete chunks were read"]                      # cut back to its last whole chunk
        report = bag.recover(disk.path("survey.mcap"), tmp_path / "recovered.mcap")
        assert report.saved == len(got)
        second = bag.open_bag(disk.path("survey_1.mcap"))         # the new part: finalized
        more = list(second.messages())                            # strict: intact
        assert second.finalized and {m.topic for m in more} == {"/probe/imu"}
        # the shutdown report: what each part holds, and every /probe/imu message either recorded or counted
        n_first = sum(m.topic == "/probe/imu" for m in got)
        assert f"  /probe/imu: {n_first + len(more)}" in text
        stamps = [m.log_time for m in got] + [m.log_time for m in more]
        assert stamps == sorted(stamps)
        assert any(m.topic == "/calibration/coefficients" for m in got)
    finally:
        _stop(pub)


def test_recorder_on_a_disk_full_before_it_starts_does_not_crash_or_leave_an_empty_file(
        small_disk, tmp_path, ros_env):
    disk = small_disk("1m")
    disk.fill()
    pub = _publisher(tmp_path, ros_env)
    try:
        rec, log = _recorder(disk, tmp_path, ros_env)
        try:
            _wait_log(log, "[ERROR]")
            _wait_log(log, "counting (not recording, see the error above) /probe/imu")  # what it misses
            time.sleep(1.5)
            assert rec.poll() is None                  # no crash, no restart loop for a launcher
        finally:
            rc = _stop(rec)
    finally:
        _stop(pub)
    text = Path(log.name).read_text()
    assert rc == 4, text
    assert "Traceback" not in text, text
    errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1, text
    assert f"cannot create {disk.mnt / 'survey.mcap'}: no space left on the device (ENOSPC)" in errors[0]
    last = text.strip().splitlines()[-1]
    assert last.startswith("recording incomplete: ") and "not recorded: disk full" in last, last
    assert last.endswith(f"no bag written, {disk.mnt / 'survey.mcap'} could not be created"), last
    assert _not_recorded(last)["/probe/imu"] >= 200, last
    assert sorted(p.name for p in disk.path().iterdir()) == ["filler"]   # no 0-byte bag left behind


def test_launcher_on_a_disk_that_fills_ends_with_words_not_a_traceback(small_disk, domain_env, tmp_path):
    env, _domain = domain_env
    disk = small_disk("300k")   # a short simulated run records ~650 kB: full about half-way
    out = disk.mnt / "run"
    t0 = time.monotonic()
    # --speed 100 is a ceiling (the run is paced by its readers) and the recorder's chunks span at
    # most 1 s of the log's time: the disk fills at the same place of the log whatever the speed
    proc = disk.popen([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--stations", "3",
                       "--speed", "100", "--no-loop", "--drain", "1.5", "--timeout", "60"],
                      env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout = ""
    try:
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for copy in re.findall(r"recovered into (\S+) instead", stdout):   # the temporary directory's copy
            shutil.rmtree(os.path.dirname(copy), ignore_errors=True)
    print(f"launcher on a full disk: {time.monotonic() - t0:.1f} s\n{stdout}\n{stderr}")
    assert "Traceback" not in stdout + stderr
    assert proc.returncode == 1, stdout[-4000:]
    lines = stdout.strip().splitlines()
    last = lines[-1]
    assert last.startswith(f"[launch] exit status 1: the run is not clean: the disk is full: {out}: ")
    # which of the launcher's files the disk refused depends on when it filled (the recorder frees its
    # torn chunk): at least one, each named in the last line and said once where it happened
    named = re.search(r"the disk is full: \S+: (.*?) not written;", last).group(1).split(", ")
    assert named and set(n.replace(" (from then on)", "") for n in named) <= {
        "launch.log", "summary.json", "report.md", "report.html", "survey.recovered.mcap"}, named
    # the recorder said it once, did not die and was not restarted; its words reach the last line
    assert sum("[recorder] [ERROR]" in ln and "no space left on the device (ENOSPC)" in ln for ln in lines) == 1
    assert "restarting it" not in stdout and not disk.path("run", "survey_1.mcap").exists()
    assert "[launch] recorder stopped (exit status 4)" in stdout
    assert re.search(r"the recording is incomplete: \d+ messages on /probe/\w+, .* not recorded: disk full", last), last
    # each refused write of the launcher said once, in words; the summary printed all the same
    for name in (n.replace(" (from then on)", "") for n in named):
        said = [ln for ln in lines if f"cannot write {out / name}: no space left on the device (ENOSPC)" in ln]
        assert len(said) == 1, (name, said)
    summary = lines.index("=== run summary ===")
    assert lines[summary + 1].startswith("bag parts (1, in time order): survey.mcap (not finalized")
    assert any(ln.startswith("bag: ") and "survey stations" in ln for ln in lines[summary:])
    if "report.md" in named:
        assert "report: none written; bag: survey.mcap" in lines
    # the part the summary could not recover beside itself was recovered elsewhere, and said
    assert re.search(r"^\[summary\] survey\.mcap recovered into /\S+/survey\.recovered\.mcap instead \(kept there\)$",
                     stdout, flags=re.M)
    # what was recorded stays readable
    first = bag.open_bag(disk.path("run", "survey.mcap"))
    assert sum(1 for _ in first.messages(strict=False)) > 1000 and len(first.errors) == 1


def test_launcher_does_not_restart_a_recorder_that_dies_on_a_full_disk(small_disk, domain_env):
    """A recorder killed (SIGKILL) once the disk is full: a new part could not hold a chunk, so the
    launcher does not restart it (it used to, three times, into 0-byte files) and stops the run."""
    env, _domain = domain_env
    disk = small_disk("300k")
    out = disk.mnt / "run"
    proc = disk.popen([sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--stations", "3",
                       "--speed", "100", "--no-loop", "--drain", "1.5", "--timeout", "60"],
                      env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines, pid = [], None
    try:
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            m = re.match(r"\[launch\] starting recorder \(pid (\d+)\)", line)
            if m:
                pid = int(m.group(1))
            if line.startswith("[recorder] [ERROR]") and pid is not None:
                os.kill(pid, signal.SIGKILL)
                break
        rest, _ = proc.communicate(timeout=60)
        lines += rest.splitlines()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for copy in re.findall(r"recovered into (\S+) instead", "\n".join(lines)):
            shutil.rmtree(os.path.dirname(copy), ignore_errors=True)
    text = "\n".join(lines)
    print(text)
    assert pid is not None and "Traceback" not in text
    assert proc.returncode == 1, text[-4000:]
    said = [ln for ln in lines if "[launch] recorder died unexpectedly (killed by SIGKILL)" in ln]
    assert len(said) == 1 and re.search(rf"; not restarted into a new part: the disk holding {out} is full "
                                        r"\(\d+ bytes free\); stopping the graph$", said[0]), said
    assert "restarting it" not in text and not disk.path("run", "survey_1.mcap").exists()
    assert "=== run summary ===" in lines
    last = lines[-1]
    assert last.startswith(f"[launch] exit status 1: the run is not clean: the disk is full: {out}: "), last
    assert "recorder died unexpectedly (killed by SIGKILL); not restarted into a new part" in last

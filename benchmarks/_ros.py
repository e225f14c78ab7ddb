"""Helpers of the ROS benchmark scripts (bench_correction_node.py, soak.py): a private DDS domain
on this machine only, child processes, and per-process CPU time and RSS from ``/proc``.

Nothing here imports rclpy (the children do)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(ROOT, "config")
sys.path.insert(0, ROOT)
from inclinometer_calib.apps.rosenv import isolated_env, reserve_domain_id  # noqa: E402
_CLK_TCK = os.sysconf("SC_CLK_TCK")
_PAGE = os.sysconf("SC_PAGE_SIZE")


def reserve_domain():
    """(domain id, lock file): an id no test or other benchmark holds (``rosenv``)."""
    return reserve_domain_id()


def ros_env(domain_id: int) -> dict:
    """Environment of the children: own domain, discovery on localhost only, source tree first."""
    return isolated_env(domain_id)


def node_cmd(name: str, params: dict, config: bool = True) -> list:
    """``python -m inclinometer_calib.nodes.<name> --ros-args [--params-file config/<name>.yaml] -p ..``"""
    cmd = [sys.executable, "-m", f"inclinometer_calib.nodes.{name}", "--ros-args"]
    f = os.path.join(CONFIG, f"{name}.yaml")
    if config and os.path.isfile(f):
        cmd += ["--params-file", f]
    for k, v in params.items():
        if isinstance(v, bool):
            v = "true" if v else "false"
        elif isinstance(v, float):
            v = repr(v)
        cmd += ["-p", f"{k}:={v}"]
    return cmd


def start(cmd, env, log_path, cwd=None) -> subprocess.Popen:
    log = open(log_path, "w")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            cwd=cwd, start_new_session=True)
    proc.log_path = log_path
    return proc


def stop(proc, timeout: float = 10.0) -> int:
    """SIGINT, then SIGTERM, then SIGKILL (this process only, by pid)."""
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            pass
    return proc.wait()


def wait_log(proc, needle: str, timeout: float = 30.0) -> str:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with open(proc.log_path) as fh:
            text = fh.read()
        if needle in text:
            return text
        if proc.poll() is not None:
            raise RuntimeError(f"{proc.args[2] if len(proc.args) > 2 else proc.args} exited "
                               f"({proc.returncode}) before {needle!r}:\n{text[-3000:]}")
        time.sleep(0.05)
    raise TimeoutError(f"no {needle!r} in {proc.log_path} after {timeout:g} s")


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process, s (/proc/<pid>/stat fields 14, 15)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/statm") as fh:
        return int(fh.read().split()[1]) * _PAGE / 1e6


def percentile(values, q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    k = min(len(v) - 1, max(0, int(round(q / 100.0 * (len(v) - 1)))))
    return v[k]

"""Every shell example of README.md runs as written.

The fenced blocks tagged ``bash``/``sh``/``shell`` are the runnable ones; anything shown but not
meant to be run (the CSV header, the layout) is fenced as ``text``, and an untagged fence is an
error here so that the choice is always explicit. The commands run in README order, each with
``bash -c``, all in one empty temporary directory (as a newcomer would, after the set-up), with
this process's environment: the test runs inside ``scripts/env.sh``, so the venv's console scripts
are on PATH and the source tree comes first on PYTHONPATH.

Lines that are not run, and why:

* ``./scripts/demo.sh`` and ``./scripts/test.sh`` build the very environment this test runs in
  (venv, ROS messages); ``test.sh`` runs this test (it would recurse) and ``demo.sh`` is the live
  ROS graph, run by test/nodes.
* ``source scripts/env.sh`` (or ``. scripts/env.sh``): already in effect for this process, and a
  ``source`` in a ``bash -c`` child could not change the environment of the next command anyway.
* ``pip install ...``: would change the environment under test and needs the network; the
  metadata it reads is checked by test/test_extras.py.

A launcher command (``inclinometer-calib-launch``) would run with discovery on this machine only
and a ROS_DOMAIN_ID reserved for it (:mod:`inclinometer_calib.apps.rosenv`); the README keeps the
launcher in prose (its runs are in docs/nodes.md), so today none is run.

A failing command fails the test with its README line, exit status and stderr; the remaining
commands still run, so one report lists every broken example (later failures may follow from
earlier ones).
"""
import os
import re
import shutil
import subprocess
import time

import pytest

from inclinometer_calib.apps import rosenv

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
RUNNABLE = ("bash", "sh", "shell")
NOT_RUN = (re.compile(r"^\./scripts/(demo|test)\.sh\b"),
           re.compile(r"^(source|\.)\s+scripts/env\.sh\b"),
           re.compile(r"^(python3? -m )?pip3? install\b"))
ROS_COMMANDS = re.compile(r"^(inclinometer-calib-launch|ros2)\b")
#: option placeholders that cannot run: "[--site FILE]", "[--effects …]", "NAME ..."
PLACEHOLDER = re.compile(r"\[--?\w|…")
TIMEOUT_S = 120


def fenced_blocks(path=README):
    """[(language, [(line number, text), ...])] of every fenced block; raises on an unclosed one."""
    blocks, current, lang = [], None, None
    with open(path, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            fence = re.match(r"^\s*```(.*)$", line)
            if fence and current is None:
                lang, current = fence.group(1).strip(), []
                start = n
            elif fence:
                blocks.append((lang, start, current))
                current = None
            elif current is not None:
                current.append((n, line.rstrip("\n")))
    assert current is None, f"README.md:{start}: fence never closed"
    return blocks


def commands(path=README):
    """[(line number, command)] of the runnable blocks, in order, set-up lines left out.
    A trailing backslash continues a command on the next line."""
    out, pending, first = [], "", None
    for lang, _, lines in fenced_blocks(path):
        if lang not in RUNNABLE:
            continue
        for n, text in lines:
            if pending:
                pending += "\n" + text
            else:
                first, pending = n, text
            if text.endswith("\\"):
                continue
            cmd, pending = pending.strip(), ""
            if not cmd or cmd.startswith("#") or any(p.match(cmd) for p in NOT_RUN):
                continue
            out.append((first, cmd))
    return out


def test_every_fence_says_what_it_is():
    untagged = [start for lang, start, _ in fenced_blocks() if not lang]
    assert not untagged, (f"README.md lines {untagged}: fence without a language; use ```bash for "
                          "examples to run, ```text for anything else")


def test_runnable_blocks_hold_no_placeholders():
    bad = [f"README.md:{n}: {cmd}" for n, cmd in commands() if PLACEHOLDER.search(cmd)]
    assert not bad, ("placeholders in a runnable block (describe options in prose or a table):\n"
                     + "\n".join(bad))


@pytest.mark.long(34)
def test_readme_examples_run(tmp_path):
    cmds = commands()
    assert len(cmds) >= 8, cmds  # the CLI chain and the model lab at least
    assert shutil.which("inclinometer-calib"), "inclinometer-calib not on PATH: source scripts/env.sh first"
    env = dict(os.environ)
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p != ROOT]
    env["PYTHONPATH"] = os.pathsep.join([ROOT] + paths)  # the source tree, as scripts/env.sh sets
    failures, times = [], []
    for n, cmd in cmds:
        run_env, lock = env, None
        if ROS_COMMANDS.match(cmd):
            domain_id, lock = rosenv.reserve_domain_id()
            run_env = rosenv.isolated_env(domain_id, env)
        t0 = time.monotonic()
        try:
            r = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], cwd=tmp_path, env=run_env,
                               capture_output=True, text=True, timeout=TIMEOUT_S)
            rc, stderr = r.returncode, r.stderr
        except subprocess.TimeoutExpired as exc:
            rc, stderr = f"timeout after {TIMEOUT_S} s", exc.stderr or ""
            stderr = stderr.decode(errors="replace") if isinstance(stderr, bytes) else stderr
        finally:
            if lock is not None:
                lock.close()
        times.append(f"{time.monotonic() - t0:5.1f} s  README.md:{n}")
        if rc != 0:
            tail = "\n".join(stderr.strip().splitlines()[-15:])
            failures.append(f"README.md:{n}: `{cmd}` exited {rc}; stderr:\n{tail}")
    print("\n".join(times))
    assert not failures, (f"{len(failures)} of {len(cmds)} README examples failed (run in order in "
                          f"{tmp_path}; a failure can follow from an earlier one):\n\n" + "\n\n".join(failures))

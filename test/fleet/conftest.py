"""Fixtures of the fleet tests: a registry URL for each database the registry supports.

``db_url`` is parametrized over SQLite (a file in the test's tmp folder) and PostgreSQL: a
throw-away cluster made with the Debian ``postgresql`` package's ``initdb`` (scripts/setup.sh
installs it when missing), started once per test session with ``pg_ctl`` on 127.0.0.1 at a free
port (its unix socket in the cluster's tmp folder, not /var/run), stopped and removed at the end.
PostgreSQL refuses to run as root: as root the cluster belongs to the ``postgres`` system user
(``runuser``).  Each test gets a database of its own in the cluster.  Without initdb, or when the
cluster does not start, the PostgreSQL cases are skipped with the reason.
"""
import glob
import itertools
import os
import shutil
import socket
import subprocess
import tempfile

import pytest

PG_BIN_GLOBS = ("/usr/lib/postgresql/*/bin",)
PG_USER = "fleet"   # the cluster's superuser (trust authentication, loopback only)


def _pg_bin():
    """The folder of initdb/pg_ctl/postgres: the newest Debian cluster version, else the PATH."""
    for pattern in PG_BIN_GLOBS:
        dirs = sorted(glob.glob(pattern), key=lambda d: [int(x) if x.isdigit() else 0 for x in d.split("/")])
        for d in reversed(dirs):
            if os.access(os.path.join(d, "initdb"), os.X_OK):
                return d
    initdb = shutil.which("initdb")
    return os.path.dirname(initdb) if initdb else None


def _free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PgCluster:
    """A temporary PostgreSQL cluster on loopback (see the module docstring)."""

    def __init__(self, bindir):
        self.bindir = bindir
        self.root = tempfile.mkdtemp(prefix="ic-fleet-pg-")
        self.data = os.path.join(self.root, "data")
        self.port = _free_port()
        self.as_user = []
        if os.geteuid() == 0:   # "initdb: cannot be run as root"
            runuser = shutil.which("runuser")
            if runuser is None:
                raise RuntimeError("running as root and no runuser to run PostgreSQL as the postgres user")
            shutil.chown(self.root, user="postgres")
            self.as_user = [runuser, "-u", "postgres", "--"]
        os.chmod(self.root, 0o700)
        self._names = itertools.count()

    def _run(self, tool, *args, timeout=60):
        cmd = self.as_user + [os.path.join(self.bindir, tool), *args]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}): {res.stderr.strip() or res.stdout.strip()}")
        return res.stdout

    def start(self):
        self._run("initdb", "-D", self.data, "-A", "trust", "-U", PG_USER, "-E", "UTF8", "--no-sync")
        opts = (f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.root} -c fsync=off "
                "-c synchronous_commit=off -c full_page_writes=off")
        try:
            self._run("pg_ctl", "-D", self.data, "-o", opts, "-l", os.path.join(self.root, "server.log"), "-w",
                      "-t", "30", "start")
        except RuntimeError as exc:
            log = os.path.join(self.root, "server.log")
            tail = open(log, encoding="utf-8", errors="replace").read()[-2000:] if os.path.exists(log) else ""
            raise RuntimeError(f"{exc}\n{tail}") from None

    def new_database(self):
        name = f"fleet_{next(self._names)}"
        self._run("createdb", "-h", "127.0.0.1", "-p", str(self.port), "-U", PG_USER, name)
        return f"postgresql+psycopg://{PG_USER}@127.0.0.1:{self.port}/{name}"

    def stop(self):
        try:
            if os.path.exists(os.path.join(self.data, "postmaster.pid")):
                self._run("pg_ctl", "-D", self.data, "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture(scope="session")
def pg_cluster():
    """The session's PostgreSQL cluster (skips when PostgreSQL or psycopg is not available)."""
    pytest.importorskip("psycopg", reason="psycopg (requirements/core.txt) is needed for PostgreSQL")
    bindir = _pg_bin()
    if bindir is None:
        pytest.skip("PostgreSQL not installed (no initdb in /usr/lib/postgresql/*/bin or on PATH; "
                    "scripts/setup.sh installs the Debian package)")
    cluster = PgCluster(bindir)
    try:
        cluster.start()
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        cluster.stop()
        pytest.skip(f"PostgreSQL cluster did not start: {exc}")
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    """A registry URL of an empty database: an SQLite file, or a new database of the PostgreSQL cluster."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'fleet.db'}"
    return request.getfixturevalue("pg_cluster").new_database()


def _calibrate(probe, serial, seed):
    """A twelve-pose calibration of a simulated ``probe`` on the stand, solved as the calibration
    node solves it (detector + capture session); the record carries the fit's 1σ."""
    import numpy as np

    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.calibrate.capture import CaptureSession
    from inclinometer_calib.core.frames import Site
    from inclinometer_calib.detect.streaming import StaticDetector

    log = sim.run_session(probe, Site(), sim.twelve_pose_session(duration_s=2.0), np.random.default_rng(seed))
    session = CaptureSession(site=Site(), probe_id=serial)
    det = StaticDetector()
    g = log.gravity
    for i in range(len(log)):
        for st in det.update(log.t_s[i], g[i], log.mag[i], log.temp_c[i]):
            session.offer(st)
    for st in det.flush():
        session.offer(st)
    session.finish()
    assert session.calibration is not None, session.message
    return session.calibration


@pytest.fixture(scope="session")
def calibrate():
    """``calibrate(probe, serial, seed) -> coeffs.Calibration`` of a simulated probe (about 40 ms)."""
    return _calibrate

"""``inclinometer-calib fleet register | add | history`` on SQLite and PostgreSQL."""
import datetime as dt
import hashlib
import json
import threading
import traceback

import pytest

from inclinometer_calib.apps import cli
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.fleet.registry import Registry

from test_history import JUMP_NT, with_mag_bias_jump


@pytest.fixture(scope="module")
def records(calibrate, tmp_path_factory):
    """Record files of probe SN-C: a calibration, a re-calibration, one after a 50 nT mag bias jump."""
    d = tmp_path_factory.mktemp("records")
    probe = sim.build_probe(5)
    paths = []
    for k, p in enumerate((probe, probe, with_mag_bias_jump(probe, JUMP_NT))):
        path = d / f"cal{k + 1}.yaml"
        calibrate(p, "SN-C", k + 1).save(path)
        paths.append(str(path))
    raw = d / "raw.csv"
    raw.write_text("t_s,ax,ay,az\n0,0,0,9.81\n")
    return paths, str(raw)


def run(capsys, *argv):
    rc = cli.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_register_add_history(db_url, records, capsys, tmp_path):
    paths, raw = records
    rc, out, _ = run(capsys, "fleet", "register", "SN-C", "--model", "MX-3", "--interval", "60", "--db", db_url)
    assert rc == 0 and "probe SN-C: model MX-3, calibration interval 60 days" in out
    rc, out, _ = run(capsys, "fleet", "add", paths[0], "--date", "2026-01-10", "--note", "new probe",
                     "--raw-log", raw, "--db", db_url)
    assert rc == 0 and "stored" in out
    for k, date in ((1, "2026-02-09T00:00Z"), (2, "2026-03-11T02:00+02:00")):   # = 2026-03-11 00:00 UTC
        assert run(capsys, "fleet", "add", paths[k], "--date", date, "--db", db_url)[0] == 0
    with Registry(db_url) as reg:
        h = reg.history("SN-C")
        assert [e.date for e in h] == [dt.datetime(2026, 1, 10, tzinfo=dt.timezone.utc),
                                       dt.datetime(2026, 2, 9, tzinfo=dt.timezone.utc),
                                       dt.datetime(2026, 3, 11, tzinfo=dt.timezone.utc)]
        with open(raw, "rb") as fh:
            assert h[0].raw_log_sha256 == hashlib.sha256(fh.read()).hexdigest()
        assert h[0].operator_note == "new probe"
    # the page is drawn from the history the text pins for each database: drawn once (2 s), on SQLite
    html = tmp_path / "hist.html" if db_url.startswith("sqlite") else None
    rc, out, _ = run(capsys, "fleet", "history", "SN-C", "--at", "2026-06-01", *(("--html", str(html)) if html else ()),
                     "--db", db_url)
    assert rc == 0
    flags = [ln for ln in out.splitlines() if ln.startswith("FLAG")]
    assert len(flags) == 1 and flags[0].startswith("FLAG #3 2026-03-11") and flags[0].endswith(": mag bias_x")
    assert "OVERDUE at 2026-06-01: last calibrated 2026-03-11, 82 days ago" in out
    assert html is None or html.read_text().count("data:image/png;base64,") == 2
    rc, out, _ = run(capsys, "fleet", "history", "SN-C", "--at", "2026-04-01", "--json", "--db", db_url)
    js = json.loads(out)
    assert rc == 0 and js["overdue"] is None and [f["index"] for f in js["flags"]] == [2]
    assert [m["parameter"] for m in js["flags"][0]["moved"]] == ["mag bias_x"]
    assert js["calibrations"][0]["parameters"]["mag e_yx"]["sigma"] is None


def test_errors_are_one_line_and_name_the_problem(db_url, records, capsys, tmp_path):
    paths, _ = records
    rc, _, err = run(capsys, "fleet", "add", paths[0], "--date", "2026-01-10", "--db", db_url)
    assert rc == 2 and f"error: {paths[0]}: calibration" in err and "probe 'SN-C' is not registered" in err
    assert run(capsys, "fleet", "register", "SN-C", "--db", db_url)[0] == 0
    rc, _, err = run(capsys, "fleet", "add", paths[0], "--date", "10/01/2026", "--db", db_url)
    assert rc == 2 and "--date: '10/01/2026' is not an ISO 8601 date" in err
    rc, _, err = run(capsys, "fleet", "add", str(tmp_path / "none.yaml"), "--date", "2026-01-10", "--db", db_url)
    assert rc == 2 and "none.yaml: No such file or directory" in err
    rc, _, err = run(capsys, "fleet", "add", paths[0], "--date", "2026-01-10", "--raw-log", str(tmp_path / "x.csv"),
                     "--db", db_url)
    assert rc == 2 and "--raw-log" in err and "No such file" in err
    rc, _, err = run(capsys, "fleet", "history", "SN-X", "--db", db_url)
    assert rc == 2 and "probe 'SN-X' is not registered" in err
    rc, _, err = run(capsys, "fleet", "register", "SN-C", "--model", "other", "--db", db_url)
    assert rc == 2 and "already registered" in err
    rc, out, _ = run(capsys, "fleet", "register", "SN-C", "--update", "--model", "other", "--db", db_url)
    assert rc == 0 and "model other" in out
    rc, _, err = run(capsys, "fleet", "register", "SN-C", "--db", str(tmp_path / "missing" / "f.db"))
    assert rc == 2 and "does not exist" in err


@pytest.mark.parametrize("command", [["fleet", "history", "P1"], ["fleet", "reprocess", "x.mcap", "-o", "out"]])
def test_a_command_that_reads_the_registry_never_creates_one(tmp_path, capsys, monkeypatch, command):
    """A mistyped ``--db`` is said, not answered from a new empty registry (it used to make one)."""
    monkeypatch.chdir(tmp_path)
    assert cli.main(command + ["--db", "typo.db"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"error: registry {tmp_path / 'typo.db'} does not exist (fleet register creates one; check --db)"
    assert list(tmp_path.iterdir()) == []


def _at_once(argvs):
    """Each command line in a thread of its own (each opens the registry: its own engine and
    connection), all released at once; returns each one's exit status, or its traceback."""
    start = threading.Barrier(len(argvs))
    got = [None] * len(argvs)

    def one(i):
        start.wait()
        try:
            got[i] = cli.main(argvs[i])
        except BaseException:   # noqa: BLE001 - a traceback is what the test looks for
            got[i] = traceback.format_exc()

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(argvs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return got


def test_concurrent_first_registrations_and_additions_are_safe(request, db_url, records, capsys, tmp_path):
    """Six registrations at once on a fresh registry — three of one probe, three of others — then six
    additions at once, two of each of three records; three times over.  They used to fail 3 times in
    8 on PostgreSQL (an IntegrityError traceback: both saw no probe, the second insert collided)."""
    paths, _ = records
    for round_ in range(3):
        url = db_url if round_ == 0 else (f"sqlite:///{tmp_path / f'fleet{round_}.db'}" if db_url.startswith("sqlite")
                                          else request.getfixturevalue("pg_cluster").new_database())
        serials = ["SN-C", "SN-C", "SN-C", "SN-D", "SN-E", "SN-F"]
        got = _at_once([["fleet", "register", s, "--model", "MX-3", "--db", url] for s in serials])
        _, err = capsys.readouterr()
        assert got == [0] * 6 and err == "", (got, err)
        dates = ["2026-01-10", "2026-02-09", "2026-03-11"]
        got = _at_once([["fleet", "add", paths[k % 3], "--date", dates[k % 3], "--db", url] for k in range(6)])
        _, err = capsys.readouterr()
        assert got == [0] * 6 and err == "", (got, err)
        with Registry(url) as reg:
            assert [(p.serial, p.model) for p in reg.probes()] == [(s, "MX-3") for s in ("SN-C", "SN-D", "SN-E", "SN-F")]
            assert [e.date.date().isoformat() for e in reg.history("SN-C")] == dates
            with reg.engine.connect() as c:
                assert c.exec_driver_sql("SELECT count(*) FROM calibrations").scalar() == 3


#: Runs each command line of argv[2] (JSON) in this one interpreter, in the current folder, and prints
#: for each its exit status (None: it raised, and err is the traceback), its stderr, the files left
#: there, and whether fleet.db is byte for byte the copy in the folder argv[1].
_IN_THE_FOLDER = r"""
import contextlib, io, json, os, sys, traceback
from inclinometer_calib.apps import cli
seed, out = sys.argv[1], []
for argv in json.loads(sys.argv[2]):
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            rc = cli.main(argv)
    except BaseException:
        rc, err = None, io.StringIO(traceback.format_exc())
    with open("fleet.db", "rb") as now, open(os.path.join(seed, "fleet.db"), "rb") as before:
        same = now.read() == before.read()
    out.append({"rc": rc, "err": err.getvalue(), "left": sorted(set(os.listdir(".")) - {".fill"}), "same": same})
print(json.dumps(out))
"""


def test_a_registry_on_a_full_or_read_only_disk_is_one_line_and_left_as_it_was(full_disk, records, tmp_path):
    """``fleet register``/``fleet add`` on a registry whose file system is full (a real full tmpfs)
    or read-only, and ``fleet register`` making a new registry there: one line naming the file and
    the cause, exit 2, the registry byte for byte as it was, no new file (they were a traceback).
    ``fleet reprocess`` into a new folder there, or into a folder whose parent is missing: the same,
    and no folder left behind (it said the path twice, or errno words, and left its folder)."""
    import sys

    paths, _ = records
    seed = tmp_path / "seed"
    seed.mkdir()
    assert cli.main(["fleet", "register", "SN-C", "--db", str(seed / "fleet.db")]) == 0
    assert cli.main(["fleet", "add", paths[0], "--date", "2026-01-10", "--db", str(seed / "fleet.db")]) == 0
    reprocess = ["fleet", "reprocess", paths[1], "--db", "fleet.db", "--workers", "0", "--no-progress", "-o"]
    commands = [["fleet", "register", "SN-D", "--db", "fleet.db"],
                ["fleet", "add", paths[1], "--date", "2026-02-09", "--db", "fleet.db"],
                ["fleet", "register", "SN-D", "--db", "new.db"],
                reprocess + ["out"], reprocess + ["sub/out"]]
    mnt = full_disk.mnt
    for ro, cause, index in ((False, "no space left on the device (ENOSPC)", "/done-index.json"),
                             (True, "the file system is read-only (EROFS)", "")):
        r = full_disk.run([sys.executable, "-c", _IN_THE_FOLDER, seed, json.dumps(commands)], ro=ro, seed=seed)
        assert r.returncode == 0 and r.stderr.strip().splitlines()[-1] == "LEFT:fleet.db", r.stderr
        want = [f"{mnt / 'fleet.db'}: {cause}", f"{mnt / 'fleet.db'}: {cause}", f"{mnt / 'new.db'}: {cause}",
                f"{mnt / 'out'}{index}: {cause}", f"{mnt / 'sub' / 'out'}: the folder {mnt / 'sub'} does not exist"]
        for got, line in zip(json.loads(r.stdout), want, strict=True):
            assert (got["rc"], got["err"]) == (2, f"error: cannot write {line}\n"), got
            assert got["same"] and got["left"] == ["fleet.db"], got

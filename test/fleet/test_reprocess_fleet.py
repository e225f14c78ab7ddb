"""Fleet reprocessing on Dask (issue 13, item 4): a generated fleet of bags from several probes,
each calibrated twice, reprocessed on a real local Dask cluster into one Parquet dataset whose
stations are single-bag ``reprocess``'s exactly; the registry's record per bag by serial and date;
failed bags reported with their reason while the others finish; reruns skip what is done and redo
what changed; the CLI on a separately started scheduler and worker (real processes, loopback)."""
from __future__ import annotations

import datetime as dt
import math
import os
import shutil
import socket
import subprocess
import sys
import time

import numpy as np
import pyarrow.compute as pc
import pytest

from inclinometer_calib.apps import cli
from inclinometer_calib.apps.cli.bags import field_monitor
from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.fleet.manifest import ManifestError, read_manifest
from inclinometer_calib.fleet.registry import Registry
from inclinometer_calib.fleet.reprocess import (DATASET_DIR, INDEX_FILE, LOST_REASON, RUNNING_DIR, _outcome,
                                                _running_note, local_cluster, lost_attempts, read_stations,
                                                reprocess_fleet, write_fragment)
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.bag import read_bag
from inclinometer_calib.correct.reprocess import reprocess, write_probe_bag

# one worker runs the whole module (scripts/test.sh: --dist loadgroup), so that its module
# fixtures, which build the data every test reads, run once, not once per worker
pytestmark = [pytest.mark.xdist_group("fleet-reprocess"), pytest.mark.long(20)]

UTC = dt.timezone.utc
T0 = dt.datetime(2026, 3, 2, 8, 0, tzinfo=UTC)      # first calibration of every probe
T1 = T0 + dt.timedelta(days=30)                     # second
PROBES = {"SN-A": 21, "SN-B": 22, "SN-C": 23}       # serial -> simulator seed


def _ns(t: dt.datetime) -> int:
    return int(t.timestamp()) * 1_000_000_000


def survey_bag(probe, path, when: dt.datetime, seed: int, serial: str = ""):
    log = sim.run_session(probe, Site(), sim.well_path_session(4, kickoff_deg=5.0, seed=seed),
                          np.random.default_rng(seed), survey=True)
    write_probe_bag(log, path, epoch_ns=_ns(when), serial=serial)
    return str(path)


@pytest.fixture(scope="module")
def fleet_bags(tmp_path_factory, calibrate):
    """Three probes, each calibrated at T0 and T1, each with a survey under each record; and four
    bags that must fail, each for its own reason (no database yet: see ``fleet``)."""
    root = tmp_path_factory.mktemp("fleet")
    (root / "bags").mkdir()
    probes, records, expected, good = {}, {}, {}, []
    for k, (serial, seed) in enumerate(PROBES.items()):
        probe = probes[serial] = sim.build_probe(seed)
        recs = records[serial] = [calibrate(probe, serial, 100 + 2 * seed), calibrate(probe, serial, 101 + 2 * seed)]
        assert recs[0].id != recs[1].id
        for j, when in enumerate((T0 + dt.timedelta(days=10 + k), T1 + dt.timedelta(days=5 + k))):
            path = survey_bag(probe, root / "bags" / f"{serial}-{j}.mcap", when, seed=10 * seed + j, serial=serial)
            expected[path] = (serial, recs[j], when.date().isoformat())
            good.append(path)
    bad = {}
    a = probes["SN-A"]
    bad[survey_bag(a, root / "bags" / "unknown.mcap", T1, 7, serial="SN-Z")] = "'SN-Z' is not registered"
    bad[survey_bag(a, root / "bags" / "early.mcap", T0 - dt.timedelta(days=3), 8, serial="SN-A")] = \
        "no calibration at or before"
    bad[survey_bag(a, root / "bags" / "overdue.mcap", T1 + dt.timedelta(days=61), 12, serial="SN-A")] = "overdue"
    bad[survey_bag(a, root / "bags" / "noserial.mcap", T1, 9)] = "no probe serial recorded"
    whole = survey_bag(a, root / "bags" / "whole.mcap", T1, 11, serial="SN-A")
    cut = root / "bags" / "truncated.mcap"
    data = open(whole, "rb").read()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    os.unlink(whole)
    bad[str(cut)] = "damaged bag"
    return {"root": root, "expected": expected, "good": good, "bad": bad, "probes": probes, "records": records}


def new_registry(request, backend: str, folder) -> str:
    """A fresh registry URL: an SQLite file in ``folder``, or a new PostgreSQL database of the
    session's cluster (``pg_cluster`` of conftest.py)."""
    if backend == "sqlite":
        return f"sqlite:///{folder / 'fleet.db'}"
    return request.getfixturevalue("pg_cluster").new_database()


def fill_registry(url: str, bags) -> None:
    """Every probe (interval 60 days) with its two calibrations, at T0 and T1."""
    with Registry(url) as reg:
        for serial, recs in bags["records"].items():
            reg.add_probe(serial, model="sim", calibration_interval_days=60)
            reg.add_calibration(recs[0], calibrated_at=T0, operator_note="first")
            reg.add_calibration(recs[1], calibrated_at=T1, operator_note="second")


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def fleet(request, fleet_bags, tmp_path_factory):
    """The fleet's bags with a registry of their probes on each database the registry supports."""
    folder = tmp_path_factory.mktemp(request.param)
    url = new_registry(request, request.param, folder)
    fill_registry(url, fleet_bags)
    return dict(fleet_bags, db=url, backend=request.param, root=folder)


def same(a, b) -> bool:
    """Equal, NaN equal to NaN, floats bit for bit."""
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b and type(a) is type(b)


def rows_of(table, bag):
    rows = table.filter(pc.field("bag") == bag).to_pylist()
    return sorted(rows, key=lambda r: r["station_id"])


#: Worker processes of the first run's local cluster: two share the bags on SQLite; on PostgreSQL
#: one (a process of its own reading the registry is what differs there; a second only costs the
#: start of another interpreter with the package and distributed, about 2 CPU-s)
WORKERS = {"sqlite": 2, "postgresql": 1}


@pytest.fixture(scope="module")
def first_run(fleet):
    out = fleet["root"] / "out"
    summary = reprocess_fleet(fleet["good"] + list(fleet["bad"]), out_dir=out, registry_url=fleet["db"],
                              n_workers=WORKERS[fleet["backend"]], progress=False)
    return out, summary


def test_local_cluster_dataset_equals_single_bag_reprocess_with_the_record_of_each_bags_date(fleet, first_run):
    out, summary = first_run
    assert summary.engine.startswith(f"local Dask cluster, {WORKERS[fleet['backend']]} worker")
    by_bag = {r.bag: r for r in summary.results}
    table = read_stations(out)
    fields = None
    for path, (serial, rec, date) in fleet["expected"].items():
        r = by_bag[path]
        assert (r.status, r.serial, r.record_id) == ("ok", serial, rec.id), r
        want = reprocess(path, None, rec, monitor=field_monitor(cli.build_parser().parse_args(
            ["reprocess", path, "-o", "x"]))).stations
        got = rows_of(table, path)
        assert len(got) == len(want) == r.stations == 4
        for g, w in zip(got, want):
            fields = list(w)
            assert (g["probe"], g["survey_date"], g["record_id"], g["probe_forced"]) == (serial, date, rec.id, False)
            assert g["coefficients_id"] == rec.id and g["probe_serial"] == serial
            for k in w:
                assert same(g[k], w[k]), (path, k, g[k], w[k])
    assert "raw_gravity_mps2" in fields and "position_covariance_ned_m2" in fields and "warnings" in fields
    assert table.schema.field("position_covariance_ned_m2").type.list_size == 9
    # each good bag once; nothing else in the dataset
    assert sorted(set(table.column("bag").to_pylist())) == sorted(fleet["good"])


def test_dataset_equals_the_reprocess_command_output_bag(fleet, first_run, tmp_path):
    out, _ = first_run
    path = fleet["good"][3]
    rec = fleet["expected"][path][1]
    rec_file = tmp_path / "rec.yaml"
    rec.save(rec_file)
    assert cli.main(["reprocess", path, "--coeffs", str(rec_file), "-o", str(tmp_path / "one.mcap")]) == 0
    stations, _, _ = read_bag(tmp_path / "one.mcap")
    got = rows_of(read_stations(out), path)
    assert len(stations) == len(got) == 4
    for g, w in zip(got, sorted(stations, key=lambda s: s["station_id"])):
        for k, v in w.items():
            assert same(g[k], v), (k, g[k], v)


def test_each_failed_bag_has_its_reason_and_the_others_finish(fleet, first_run):
    out, summary = first_run
    by_bag = {r.bag: r for r in summary.results}
    for path, reason in fleet["bad"].items():
        r = by_bag[path]
        assert r.status == "failed" and reason in r.reason, (path, r.reason)
        assert r.fragment == ""
    assert summary.count("ok") == len(fleet["good"]) and summary.count("failed") == len(fleet["bad"])
    csv_text = (out / "summary.csv").read_text()
    assert csv_text.count(",failed,") == len(fleet["bad"]) and "damaged bag" in csv_text
    # no temporary or half fragment anywhere
    names = [f for _, _, fs in os.walk(out / DATASET_DIR) for f in fs]
    assert len(names) == len(fleet["good"]) and all(n.startswith("part-") and n.endswith(".parquet") for n in names)


def test_rerun_skips_what_is_done_and_redoes_a_bag_whose_record_changed(request, fleet, first_run, tmp_path,
                                                                       calibrate):
    out0, _ = first_run
    out = tmp_path / "out"
    shutil.copytree(out0, out)
    db = new_registry(request, fleet["backend"], tmp_path)     # the same records in a registry of its own
    fill_registry(db, fleet)
    bags = fleet["good"] + list(fleet["bad"])
    again = reprocess_fleet(bags, out_dir=out, registry_url=db, n_workers=0, progress=False)
    assert again.count("skipped") == len(fleet["good"]) and again.count("failed") == len(fleet["bad"])
    assert again.count("ok") == 0
    # SN-B recalibrated after T1: its survey under the second record is redone with the new one
    target = next(p for p, (s, _, _) in fleet["expected"].items() if s == "SN-B" and p.endswith("-1.mcap"))
    new = calibrate(fleet["probes"]["SN-B"], "SN-B", 999)
    when = T1 + dt.timedelta(days=2)
    with Registry(db) as reg:
        reg.add_calibration(new, calibrated_at=when, operator_note="after a knock")
    third = reprocess_fleet(bags, out_dir=out, registry_url=db, n_workers=0, progress=False)
    by_bag = {r.bag: r for r in third.results}
    assert by_bag[target].status == "ok" and by_bag[target].record_id == new.id
    assert third.count("ok") == 1 and third.count("skipped") == len(fleet["good"]) - 1
    table = read_stations(out)
    rows = rows_of(table, target)
    assert len(rows) == 4 and {r["record_id"] for r in rows} == {new.id}   # the old fragment is gone
    want = reprocess(target, None, new, monitor=field_monitor(cli.build_parser().parse_args(
        ["reprocess", target, "-o", "x"]))).stations
    for g, w in zip(rows, want):
        assert all(same(g[k], w[k]) for k in w)
    assert table.num_rows == 4 * len(fleet["good"])


def test_manifest_serial_refused_against_the_bags_own_unless_forced_then_said(fleet, tmp_path):
    a_bag = next(p for p, (s, _, _) in fleet["expected"].items() if s == "SN-A")
    noserial = next(p for p, why in fleet["bad"].items() if "serial" in why)
    man = tmp_path / "list.csv"
    man.write_text("# two bags\nbag,serial\n"
                   f"{os.path.relpath(a_bag, tmp_path)},SN-B\n{os.path.relpath(noserial, tmp_path)},SN-A\n")
    entries = read_manifest(man)
    assert [e.path for e in entries] == [a_bag, noserial] and [e.serial for e in entries] == ["SN-B", "SN-A"]
    s = reprocess_fleet(entries, out_dir=tmp_path / "o1", registry_url=fleet["db"], n_workers=0, progress=False)
    r = {x.bag: x for x in s.results}
    assert r[a_bag].status == "failed" and "records probe 'SN-A' but the manifest says 'SN-B'" in r[a_bag].reason
    assert r[noserial].status == "ok" and r[noserial].serial == "SN-A"   # the manifest names its probe
    s = reprocess_fleet(entries[:1], out_dir=tmp_path / "o2", registry_url=fleet["db"], n_workers=0,
                        progress=False, force_probe=True)
    assert s.results[0].status == "ok" and s.results[0].probe_forced and s.results[0].serial == "SN-B"
    rows = read_stations(tmp_path / "o2").to_pylist()
    assert rows and all(r["probe"] == "SN-B" and r["probe_forced"] and r["probe_serial"] == "SN-A" for r in rows)
    assert all(any("SN-B" in w and "SN-A" in w for w in r["warnings"]) for r in rows)


def test_manifest_errors_name_the_line(tmp_path):
    man = tmp_path / "m.csv"
    man.write_text("bag,probe\nx.mcap,SN-1\n")
    with pytest.raises(ManifestError, match=r"m\.csv:1: unknown column\(s\) \['probe'\]"):
        read_manifest(man)
    man.write_text("# nothing\n\n")
    with pytest.raises(ManifestError, match="lists no bag"):
        read_manifest(man)
    man.write_text("bag,serial\na.mcap,SN-1,extra\n")
    with pytest.raises(ManifestError, match=r"m\.csv:2: 3 fields"):
        read_manifest(man)
    assert cli.main(["fleet", "reprocess", "--manifest", str(man), "-o", str(tmp_path / "o")]) == 2


def test_a_crashed_fragment_write_leaves_no_file(tmp_path, monkeypatch):
    import pyarrow as pa
    import pyarrow.parquet as pq

    real = pq.write_table

    def crash(table, where, **kw):
        real(table.slice(0, 1), where, **kw)      # part of it is on disk, then the task dies
        raise OSError("disk full")

    monkeypatch.setattr(pq, "write_table", crash)
    with pytest.raises(OSError, match="disk full"):
        write_fragment(pa.table({"x": [1, 2]}), tmp_path, "stations/probe=A/part-1.parquet")
    assert os.listdir(tmp_path / "stations" / "probe=A") == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("fleet", ["sqlite"], indirect=True)   # the cluster is the point, not the database
def test_cli_on_a_separately_started_scheduler_and_worker(fleet, tmp_path):
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    bindir = os.path.dirname(sys.executable)
    procs = [subprocess.Popen([os.path.join(bindir, "dask"), "scheduler", "--host", "127.0.0.1", "--port",
                               str(port), "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([os.path.join(bindir, "dask"), "worker", addr, "--nworkers", "1",
                                       "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        man = tmp_path / "bags.txt"
        man.write_text("\n".join(fleet["good"][:3] + [p for p, why in fleet["bad"].items() if "damaged" in why]) + "\n")
        out = tmp_path / "out"
        t = time.monotonic()
        res = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.cli", "fleet", "reprocess", "--manifest",
                              str(man), "--scheduler", addr, "--db", fleet["db"], "-o", str(out), "--no-progress"],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 1, res.stderr         # one bag failed, the others were done
        assert f"Dask cluster {addr}" in res.stdout and "3 ok, 0 skipped (done), 1 failed" in res.stdout
        assert "damaged bag" in res.stdout
        assert read_stations(out).num_rows == 12 and time.monotonic() - t < 120
        assert (out / INDEX_FILE).exists() and (out / "summary.csv").exists()
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def test_default_task_size_batches_short_bags_but_keeps_every_worker_busy():
    from inclinometer_calib.fleet.reprocess import auto_bags_per_task

    assert auto_bags_per_task(200, 2) == 10          # the measured best on 2 local workers
    assert auto_bags_per_task(10_000, 50) == 10
    assert auto_bags_per_task(40, 2) == 5            # 8 tasks: 4 per worker
    assert auto_bags_per_task(13, 2) == 1 and auto_bags_per_task(3, 0) == 1


@pytest.mark.parametrize("fleet", ["sqlite"], indirect=True)
def test_two_copies_of_a_bag_under_two_names_are_two_surveys(fleet, tmp_path):
    """The same bytes under two names: two surveys, two fragments, every row (they collapsed into
    one fragment, the second overwriting the first)."""
    src = fleet["good"][0]
    copy = str(tmp_path / ("copy-" + os.path.basename(src)))
    shutil.copyfile(src, copy)
    out = tmp_path / "out"
    summary = reprocess_fleet([src, copy], out_dir=out, registry_url=fleet["db"], n_workers=0, progress=False)
    assert summary.count("ok") == 2, summary.lines()
    table = read_stations(out)
    a, b = rows_of(table, src), rows_of(table, copy)
    assert len(a) == len(b) > 0 and table.num_rows == len(a) + len(b)
    assert all(same(x[k], y[k]) for x, y in zip(a, b) for k in x if k != "bag")
    assert len({r.fragment for r in summary.results}) == 2


def test_a_task_whose_result_is_lost_with_its_worker_is_a_lost_task_not_an_error_out_of_the_run():
    """A task that finished keeps its result in its worker's memory; a worker that dies before the
    client fetched it (killed by the bag of the next task it took) makes Dask run the task again, and
    give up with KilledWorker when workers keep dying: fetching the result then raises.  Seen once
    in a fresh-clone run of the worker-lost test below, as a traceback out of ``reprocess_fleet``;
    the outcome is now the task's, handled as a task that failed (its bags retried or failed)."""
    from distributed.scheduler import KilledWorker

    class Finished:
        status = "finished"

        def __init__(self, fetch):
            self.fetch = fetch

        def result(self):
            return self.fetch()

        def exception(self):
            raise AssertionError("a finished task's outcome is its result")

    def lost():
        raise KilledWorker("dask_batch-1", "tcp://127.0.0.1:1", 1)

    assert _outcome(Finished(lambda: ["r"])) == (["r"], None)
    result, exc = _outcome(Finished(lost))
    assert result is None and isinstance(exc, KilledWorker) and exc.allowed_failures == 1

    class Erred:
        status = "error"

        def exception(self):
            return ValueError("bad")

    result, exc = _outcome(Erred())
    assert result is None and isinstance(exc, ValueError)


@pytest.mark.parametrize("fleet", ["sqlite"], indirect=True)
def test_a_worker_lost_on_a_bag_is_put_on_that_bag_retried_or_failed(fleet, tmp_path):
    """A real local cluster whose worker process dies (``os._exit``, by a test's hook passed in, as an
    out-of-memory kill or a crash in native code would) on two bags: on ``once`` the first time only
    — Dask retries it on a new worker, it is done, and it says so; on ``always`` every time — Dask
    gives up (KilledWorker, allowed-failures 1): that bag fails as lost with its workers, named, and
    its batch-mate ``mate`` (after it in the task; a file that is not a bag, which fails quickly for
    its own reason) is done in a new task.  They were a bare ``task failed: KilledWorker`` for the
    whole batch, or nothing at all when retried.  (``always`` first in its task: the workers it kills
    die before they import the pipeline, which is what costs here.)"""
    import dask
    from distributed import Client

    mate = str(tmp_path / "notes.mcap")
    with open(mate, "w") as fh:
        fh.write("not a bag\n")
    always, once = fleet["good"][:2]
    flag = str(tmp_path / "died-once")

    def die_on(entry):          # runs on the worker, before each bag
        if entry.path == always:
            os._exit(70)
        if entry.path == once:
            try:
                os.close(os.open(flag, os.O_CREAT | os.O_EXCL))
            except FileExistsError:
                return
            os._exit(70)

    out = tmp_path / "out"
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = local_cluster(1)
    try:
        with Client(cluster) as client:
            summary = reprocess_fleet([always, mate, once], out_dir=out, registry_url=fleet["db"], client=client,
                                      bags_per_task=2, progress=False, before_bag=die_on)
    finally:
        cluster.close()
    r = {x.bag: x for x in summary.results}
    assert (r[once].status, r[once].stations, len(r[once].workers_lost)) == ("ok", 4, 1), r[once]
    assert r[always].status == "failed" and r[always].reason.startswith(LOST_REASON), r[always]
    assert len(r[always].workers_lost) >= 2 and "given up after 2 (distributed.scheduler.allowed-failures 1" \
        in r[always].reason
    assert all(w in r[always].reason for w in r[always].workers_lost)
    assert r[mate].status == "failed" and "not" in r[mate].reason and r[mate].workers_lost == [], r[mate]
    assert [x.bag for x in summary.lost] == [always] and [x.bag for x in summary.retried] == [once]
    lines = summary.lines()
    assert lines[2].startswith(f"ok      {once}: 4 stations") and \
        lines[2].endswith(f"; RETRIED: worker {r[once].workers_lost[0]} was lost while on this bag")
    assert lines[0].startswith(f"failed  {always}: {LOST_REASON}: ")
    assert "3 bags: 1 ok, 0 skipped (done), 2 failed (1 lost with their workers), 1 retried after a worker was " \
           "lost;" in lines[-1]
    csv_rows = (out / "summary.csv").read_text().splitlines()
    assert csv_rows[0].endswith(",workers_lost") and csv_rows[3].endswith("," + r[once].workers_lost[0])
    assert set(read_stations(out).column("bag").to_pylist()) == {once}
    assert not (out / RUNNING_DIR).exists()


def test_the_note_a_lost_worker_leaves_names_the_bag_it_was_on(tmp_path):
    """``lost_attempts`` reads the notes of ``dask_batch``: the last bag begun, per task and worker;
    none begun is None; each note read once."""
    (tmp_path / RUNNING_DIR).mkdir()
    for key, worker, text in (("dask_batch-1", "tcp://10.0.0.7:4001", "0\n1\n2\n"),
                              ("dask_batch-1", "tcp://10.0.0.8:4002", ""), ("dask_batch-2", "tcp://[::1]:4003", "0\n")):
        with open(_running_note(str(tmp_path), key, worker), "w") as fh:
            fh.write(text)
    assert lost_attempts(str(tmp_path), "dask_batch-1") == [("dask_batch-1", "tcp://10.0.0.7:4001", 2),
                                                             ("dask_batch-1", "tcp://10.0.0.8:4002", None)]
    assert lost_attempts(str(tmp_path), "dask_batch-1") == []
    assert lost_attempts(str(tmp_path)) == [("dask_batch-2", "tcp://[::1]:4003", 0)]
    assert os.listdir(tmp_path / RUNNING_DIR) == []

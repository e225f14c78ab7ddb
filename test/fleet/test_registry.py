"""The probe registry (issue 13, item 1): probes by serial, calibration records by content hash,
the record valid for a survey at a date looked up by the rule of docs/fleet.md — on SQLite and on
a real PostgreSQL server (conftest.py)."""
import datetime as dt

import pytest
import sqlalchemy as sa

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.fleet import registry as rg
from inclinometer_calib.fleet.registry import Registry, RegistryError

UTC = dt.timezone.utc
T0 = dt.datetime(2026, 1, 10, 9, 0, tzinfo=UTC)
DAY = dt.timedelta(days=1)


@pytest.fixture(scope="module")
def cals(calibrate):
    """Two calibrations of probe SN-1 and two of SN-2 (simulated, solved like the calibration node)."""
    p1, p2 = sim.build_probe(5), sim.build_probe(6)
    return {"a": calibrate(p1, "SN-1", 1), "b": calibrate(p1, "SN-1", 2),
            "x": calibrate(p2, "SN-2", 3), "y": calibrate(p2, "SN-2", 4)}


@pytest.fixture
def reg(db_url, cals):
    """SN-1 calibrated at T0 and T0+60 d (interval 90 d); SN-2 at T0-10 d and T0+5 d."""
    r = Registry(db_url)
    r.add_probe("SN-1", model="MX-3", calibration_interval_days=90)
    r.add_probe("SN-2", calibration_interval_days=90)
    r.add_calibration(cals["a"], calibrated_at=T0, operator_note="first")
    r.add_calibration(cals["b"], calibrated_at=T0 + 60 * DAY)
    r.add_calibration(cals["x"], calibrated_at=T0 - 10 * DAY)
    r.add_calibration(cals["y"], calibrated_at=T0 + 5 * DAY)
    yield r
    r.close()


def test_valid_record_is_the_latest_at_or_before_the_date(reg, cals):
    assert reg.valid_record("SN-1", T0).id == cals["a"].id                      # on the day
    assert reg.valid_record("SN-1", T0 + 30 * DAY).id == cals["a"].id           # between two: the earlier
    assert reg.valid_record("SN-1", T0 + 60 * DAY - dt.timedelta(seconds=1)).id == cals["a"].id
    assert reg.valid_record("SN-1", T0 + 60 * DAY).id == cals["b"].id
    assert reg.valid_record("SN-1", T0 + 150 * DAY).id == cals["b"].id          # 90 days old: still valid
    got = reg.valid_record("SN-1", T0 + 30 * DAY)
    assert got.to_yaml() == cals["a"].to_yaml()                                 # the record itself, unchanged
    assert got.uncertainty["mag"]["bias"] == pytest.approx(cals["a"].uncertainty["mag"]["bias"])


def test_before_the_first_calibration_is_refused_even_when_another_probe_has_one(reg):
    with pytest.raises(RegistryError, match=r"SN-1: no calibration at or before 2026-01-09 09:00 UTC "
                                            r"\(its first calibration is of 2026-01-10 09:00 UTC\)"):
        reg.valid_record("SN-1", T0 - DAY)        # SN-2 has one at T0-10 d: never picked


def test_overdue_is_refused_with_the_reason(reg, cals):
    with pytest.raises(RegistryError, match=rf"SN-1: overdue at 2026-06-09 10:00 UTC: its latest calibration "
                                            rf"{cals['b'].id} of 2026-03-11 09:00 UTC is 90.04 days old, "
                                            r"beyond its calibration interval of 90 days"):
        reg.valid_record("SN-1", T0 + 150 * DAY + dt.timedelta(hours=1))
    reg.update_probe("SN-1", calibration_interval_days=365)                     # a longer interval: valid again
    assert reg.valid_record("SN-1", T0 + 200 * DAY).id == cals["b"].id


def test_a_second_probes_record_is_never_picked(reg, cals):
    for t in (T0 - 10 * DAY, T0, T0 + 5 * DAY, T0 + 30 * DAY, T0 + 70 * DAY):
        try:
            got = reg.valid_record("SN-1", t)
        except RegistryError:
            continue
        assert got.probe_id == "SN-1" and got.id in (cals["a"].id, cals["b"].id)
    assert reg.valid_record("SN-2", T0 + 30 * DAY).id == cals["y"].id
    assert reg.valid_record("SN-2", T0).id == cals["x"].id
    with pytest.raises(RegistryError, match=r"probe 'SN-9' is not registered"):
        reg.valid_record("SN-9", T0)


def test_dates_are_aware_and_compared_as_instants(reg, cals):
    with pytest.raises(RegistryError, match="has no time zone"):
        reg.valid_record("SN-1", dt.datetime(2026, 2, 1))
    # 08:30 at UTC+01:00 is 07:30 UTC, before the 09:00 UTC calibration; 10:30+01:00 is after it
    plus1 = dt.timezone(dt.timedelta(hours=1))
    with pytest.raises(RegistryError, match="no calibration at or before"):
        reg.valid_record("SN-1", dt.datetime(2026, 1, 10, 8, 30, tzinfo=plus1))
    assert reg.valid_record("SN-1", dt.datetime(2026, 1, 10, 10, 30, tzinfo=plus1)).id == cals["a"].id
    h = reg.history("SN-1")
    assert h[0].date == T0 and h[0].date.tzinfo is not None and h[0].date.utcoffset() == dt.timedelta(0)


def test_adding_the_same_record_is_idempotent_and_conflicts_are_refused(reg, cals):
    assert reg.add_calibration(cals["a"], calibrated_at=T0) == cals["a"].id           # again: nothing changes
    assert len(reg.history("SN-1")) == 2
    with pytest.raises(RegistryError, match=rf"{cals['a'].id} of probe SN-1 is already stored with calibrated_at"):
        reg.add_calibration(cals["a"], calibrated_at=T0 + DAY)
    with pytest.raises(RegistryError, match="raw log SHA-256 none"):
        reg.add_calibration(cals["a"], calibrated_at=T0, raw_log_sha256="ab" * 32)
    other = sim.build_probe(7)
    with pytest.raises(RegistryError, match=rf"SN-1 already has calibration {cals['a'].id} at 2026-01-10T09:00:00"):
        reg.add_calibration(_cal_of(other, "SN-1"), calibrated_at=T0)
    with pytest.raises(RegistryError, match=r"probe 'SN-3' is not registered in .*\(register it first: fleet register SN-3\)"):
        reg.add_calibration(_cal_of(other, "SN-3"), calibrated_at=T0)
    with pytest.raises(RegistryError, match="is not 64 hex digits"):
        reg.add_calibration(cals["a"], calibrated_at=T0, raw_log_sha256="xyz")
    with pytest.raises(RegistryError, match="no time zone"):
        reg.add_calibration(cals["a"], calibrated_at=dt.datetime(2026, 1, 10, 9))


def _cal_of(probe, serial):
    from inclinometer_calib.core.coeffs import Calibration
    return Calibration(acc=probe.acc, mag=probe.mag, probe_id=serial, method="simulator truth")


def test_probes_by_serial(reg):
    assert reg.add_probe("SN-1", model="MX-3", calibration_interval_days=90).serial == "SN-1"   # same: idempotent
    with pytest.raises(RegistryError, match=r"SN-1 is already registered with model 'MX-3' \(given 'MX-4'\)"):
        reg.add_probe("SN-1", model="MX-4", calibration_interval_days=90)
    for bad in ("", " SN", "SN 1", "x" * 65, None):
        with pytest.raises(RegistryError, match="is not valid"):
            reg.add_probe(bad)
    with pytest.raises(RegistryError, match="positive number of days"):
        reg.add_probe("SN-5", calibration_interval_days=0)
    assert [p.serial for p in reg.probes()] == ["SN-1", "SN-2"]
    assert reg.probe("SN-1").model == "MX-3"


def test_history_and_reopening(reg, cals, db_url):
    h = reg.history("SN-1")
    assert [(e.id, e.date, e.operator_note) for e in h] == [(cals["a"].id, T0, "first"),
                                                            (cals["b"].id, T0 + 60 * DAY, "")]
    assert h[0].record.probe_id == "SN-1" and h[0].method == cals["a"].method
    with pytest.raises(RegistryError, match="not registered"):
        reg.history("nope")
    reg.close()
    with Registry(db_url) as again:                  # already at head: opened without migrating
        assert rg.current_revision(again.engine) == rg.head_revision()
        assert again.valid_record("SN-1", T0 + DAY).id == cals["a"].id
        assert again.record(cals["y"].id).probe_id == "SN-2"


def test_a_fleet_worker_opens_the_registry_at_the_revision_its_client_found_or_refuses_it(reg, cals, db_url):
    """The client of a fleet run opens (and migrates) the registry; the resolver it sends to the
    workers carries the revision it found, and a worker opens the registry checking it with one
    query instead of Alembic; a registry at another revision by then is refused, naming both."""
    import pickle

    from inclinometer_calib.fleet.reprocess import RegistryResolver

    client = RegistryResolver(db_url)
    client.registry()
    assert client.revision == rg.head_revision()
    worker = pickle.loads(pickle.dumps(client))
    assert worker.revision == client.revision
    with Registry(worker.url, revision=worker.revision) as r:
        assert r.valid_record("SN-1", T0 + DAY).id == cals["a"].id
    with pytest.raises(RegistryError, match=r"schema revision '[0-9a-f]+', not 'f00' as when this run opened it"):
        Registry(worker.url, revision="f00")


def test_the_database_refuses_what_sql_should(reg, cals):
    """The constraints hold in the database itself (another client cannot break them either)."""
    with reg.engine.connect() as c:
        with pytest.raises(sa.exc.IntegrityError):   # foreign key: a calibration of an unregistered probe
            with c.begin():
                c.execute(sa.text("UPDATE calibrations SET probe_serial='SN-77' WHERE id=:i"), {"i": cals["a"].id})
        with pytest.raises(sa.exc.IntegrityError):   # one calibration per probe per instant
            with c.begin():
                c.execute(sa.text("UPDATE calibrations SET calibrated_at=(SELECT calibrated_at FROM calibrations "
                                  "WHERE id=:b) WHERE id=:a"), {"a": cals["a"].id, "b": cals["b"].id})


def test_a_newer_schema_and_bad_urls_are_refused(db_url, tmp_path):
    with Registry(db_url) as r:
        with r.engine.begin() as c:
            c.execute(sa.text("UPDATE alembic_version SET version_num='9999'"))
    with pytest.raises(RegistryError, match=r"schema revision '9999', unknown to this version .* upgrade the package"):
        Registry(db_url)
    with pytest.raises(RegistryError, match="does not exist"):
        Registry(str(tmp_path / "no" / "such" / "fleet.db"))
    with pytest.raises(RegistryError, match=r"registry sqlite\+nodriver://x: cannot use this database"):
        Registry("sqlite+nodriver://x")
    with pytest.raises(RegistryError, match=r"registry URL '://x' is not valid"):
        Registry("://x")
    with pytest.raises(RegistryError, match=r"registry postgresql\+psycopg://u:\*\*\*@127.0.0.1:1/db: cannot open the "
                                            r"database: .*refused") as e:
        Registry("postgresql://u:secret@127.0.0.1:1/db")
    assert "secret" not in str(e.value)
    (tmp_path / "not.db").write_text("not a database " * 100)
    with pytest.raises(RegistryError, match="cannot open the database: .*not a database"):
        Registry(str(tmp_path / "not.db"))


def test_a_plain_path_is_an_sqlite_file(tmp_path, cals):
    path = tmp_path / "f.db"
    with Registry(str(path)) as r:
        r.add_probe("SN-1")
        assert r.engine.dialect.name == "sqlite"
    assert path.exists()
    assert rg.normalize_url("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"

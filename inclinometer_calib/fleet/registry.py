"""The probe registry and calibration history: a real database behind a small API.

A :class:`Registry` is one SQLAlchemy database: an SQLite file by default (embedded, no set-up),
or any SQLAlchemy URL, e.g. a shared PostgreSQL server
(``postgresql+psycopg://user@host:5432/fleet``; ``postgresql://`` is read as psycopg 3 too).
Opening a registry creates the schema or migrates it to the newest version with the Alembic
migrations shipped in this package (``fleet/migrations``, no ``alembic.ini`` needed).

Tables (:data:`Base.metadata`):

* ``probes`` — one row per probe, keyed by its **serial number** (unique), with its model, a
  note, its calibration interval (days) and when it was registered;
* ``calibrations`` — one row per calibration record, keyed by the record's **content hash**
  (:attr:`coeffs.Calibration.id`, which covers the model, the probe and the site), with the probe's
  serial, the date the probe was calibrated (``calibrated_at``, timezone-aware, stored as UTC), the
  method, a description of the model, the site reference (JSON), the full record as YAML (the
  authoritative form: loading it re-checks its hash), the operator's note, the SHA-256 of the raw
  calibration log, the record's 1σ (JSON) and when the row was written.  One calibration per probe
  per instant (unique ``(probe_serial, calibrated_at)``), so the lookup below never has to choose.

**Validity rule** (:meth:`Registry.valid_record`): the record valid for a survey of probe ``S`` at
date ``t`` is the latest calibration of ``S`` with ``calibrated_at <= t``; it is refused when ``S``
is unknown, when ``S`` has no calibration at or before ``t``, or when that calibration is older
than ``S``'s calibration interval at ``t`` (the probe was overdue).  Nothing is guessed: no other
probe's record, no later record, no default.

All dates at the API are timezone-aware :class:`datetime.datetime` (a naive one is refused: the
registry does not guess a time zone); they come back in UTC.
"""
from __future__ import annotations

import datetime as _dt
import errno
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass
from typing import List, Optional

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column

from ..core.coeffs import Calibration, CoefficientError
from ..core.output import OutputError, check_output, refused_write_words

#: Where the Alembic environment and versions of the registry's schema live (shipped with the package).
MIGRATIONS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "migrations")
DEFAULT_URL = "sqlite:///fleet.db"
DEFAULT_INTERVAL_DAYS = 90.0
#: A serial: letters, digits and ``-_.:/``, 1–64 characters (it names Parquet partitions and files too).
SERIAL_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.:/-]{0,63}$")
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
#: The key of the registry's write lock on PostgreSQL (a transaction-scoped advisory lock).
PG_WRITE_LOCK = 7213411


class RegistryError(ValueError):
    """A registry request that cannot be met: says what and why (unknown probe, no valid record,
    a conflicting record, a database that cannot be opened)."""


# ---------------------------------------------------------------------------------------------
# Schema (the ORM; the migrations in fleet/migrations create exactly this, test/fleet checks it)
# ---------------------------------------------------------------------------------------------
class UTCDateTime(sa.types.TypeDecorator):
    """A timezone-aware instant stored as UTC: ``TIMESTAMP WITH TIME ZONE`` on PostgreSQL, the UTC
    wall time on SQLite (which has no time zones; every value is UTC, so text order is time order).
    Naive values are refused rather than guessed."""

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is None:
            return None
        if value.tzinfo is None or value.utcoffset() is None:
            raise RegistryError(f"{value!r} has no time zone (give an aware datetime, e.g. UTC)")
        value = value.astimezone(_dt.timezone.utc)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value, dialect):
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=_dt.timezone.utc)
        return value.astimezone(_dt.timezone.utc)


class Base(DeclarativeBase):
    metadata = sa.MetaData(naming_convention={
        "ix": "ix_%(column_0_label)s", "uq": "uq_%(table_name)s_%(column_0_name)s",
        "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s", "pk": "pk_%(table_name)s"})


class ProbeRow(Base):
    """A probe of the fleet (table ``probes``)."""
    __tablename__ = "probes"

    serial: Mapped[str] = mapped_column(sa.String(64), primary_key=True)
    model: Mapped[str] = mapped_column(sa.String(200), nullable=False, default="")
    note: Mapped[str] = mapped_column(sa.Text, nullable=False, default="")
    calibration_interval_days: Mapped[float] = mapped_column(sa.Float, nullable=False)
    created: Mapped[_dt.datetime] = mapped_column(UTCDateTime, nullable=False)


class CalibrationRow(Base):
    """A calibration record of a probe (table ``calibrations``)."""
    __tablename__ = "calibrations"
    __table_args__ = (
        # the lookups: a probe's calibrations in date order; one calibration per probe per instant
        sa.UniqueConstraint("probe_serial", "calibrated_at", name="uq_calibrations_probe_serial_calibrated_at"),
        sa.Index("ix_calibrations_calibrated_at", "calibrated_at"),
    )

    id: Mapped[str] = mapped_column(sa.String(64), primary_key=True)   # coeffs.Calibration.id (content hash)
    probe_serial: Mapped[str] = mapped_column(sa.String(64), sa.ForeignKey("probes.serial", ondelete="RESTRICT"),
                                              nullable=False)
    calibrated_at: Mapped[_dt.datetime] = mapped_column(UTCDateTime, nullable=False)
    method: Mapped[str] = mapped_column(sa.Text, nullable=False)
    model_description: Mapped[str] = mapped_column(sa.Text, nullable=False)
    site: Mapped[dict] = mapped_column(sa.JSON, nullable=False)
    record_yaml: Mapped[str] = mapped_column(sa.Text, nullable=False)
    operator_note: Mapped[str] = mapped_column(sa.Text, nullable=False, default="")
    raw_log_sha256: Mapped[str] = mapped_column(sa.String(64), nullable=False, default="")
    uncertainty: Mapped[dict] = mapped_column(sa.JSON, nullable=False)
    created: Mapped[_dt.datetime] = mapped_column(UTCDateTime, nullable=False)


# ---------------------------------------------------------------------------------------------
# What the API returns
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ProbeInfo:
    """A registered probe; ``calibration_interval_days``: how long a calibration stays valid."""
    serial: str
    model: str
    note: str
    calibration_interval_days: float
    created: _dt.datetime


@dataclass(frozen=True)
class HistoryEntry:
    """One calibration of a probe, as stored: ``date`` (UTC, when the probe was calibrated), the
    record's ``id`` and ``method``, the ``record`` itself (:class:`coeffs.Calibration`, loaded and
    re-checked from the stored YAML), the operator's note, the raw log's SHA-256 ("" if not given),
    the model's description and when the row was written."""
    date: _dt.datetime
    id: str
    method: str
    record: Calibration
    operator_note: str
    raw_log_sha256: str
    model_description: str
    created: _dt.datetime


def aware(t: _dt.datetime, what: str) -> _dt.datetime:
    """``t`` in UTC; a naive datetime or a non-datetime is refused (naming ``what``)."""
    if not isinstance(t, _dt.datetime):
        raise RegistryError(f"{what}: expected a datetime, got {t!r}")
    if t.tzinfo is None or t.utcoffset() is None:
        raise RegistryError(f"{what}: {t.isoformat()} has no time zone (the registry does not guess one; "
                            "give e.g. 2026-03-01T00:00Z)")
    return t.astimezone(_dt.timezone.utc)


def normalize_url(url: str) -> str:
    """A registry location as an SQLAlchemy URL: a URL is kept (``postgresql://`` gets the psycopg 3
    driver this package uses), anything else is a path to an SQLite file."""
    url = str(url)
    if "://" not in url:
        return "sqlite:///" + os.path.abspath(url)
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        return "postgresql+psycopg://" + url.split("://", 1)[1]
    return url


def _display(url: sa.engine.URL) -> str:
    return url.render_as_string(hide_password=True)


def _check_serial(serial) -> str:
    if not isinstance(serial, str) or not SERIAL_RE.match(serial):
        raise RegistryError(f"probe serial {serial!r} is not valid: 1-64 characters, letters, digits and -_.:/ "
                            "starting with a letter or digit")
    return serial


class Registry:
    """The probe registry and calibration history in the database at ``url`` (see the module's
    docstring): created if absent, migrated to the newest schema on opening.  Writers run one at a
    time (:func:`write_lock`).  A write the SQLite file's disk or folder refuses raises
    :class:`output.OutputError` (the file and the cause), anything else :class:`RegistryError`."""

    def __init__(self, url: str = DEFAULT_URL, *, echo: bool = False, create: bool = True,
                 revision: Optional[str] = None):
        """``create=False`` (a command that only reads): a SQLite file that does not exist is an
        error, not a new empty registry (a mistyped ``--db`` would otherwise make one).
        ``revision``: the schema revision another process of the same run already brought the
        database to (a fleet run's workers: its client opened the registry first); the database
        is then checked to be at it with one query, not migrated (Alembic and its imports are half
        a CPU-second of each worker process)."""
        try:
            self.url = make_url(normalize_url(url))
        except ArgumentError as exc:
            raise RegistryError(f"registry URL {url!r} is not valid: {exc}") from None
        #: The SQLite file (None for a server or an in-memory database): named by a write it refuses.
        self.path = None
        if self.url.get_backend_name() == "sqlite" and self.url.database not in (None, "", ":memory:"):
            self.path = self.url.database
            if not create and not os.path.isfile(self.url.database):
                raise RegistryError(f"registry {self.url.database} does not exist (fleet register creates one; "
                                    "check --db)")
            folder = os.path.dirname(os.path.abspath(self.url.database))
            if not os.path.isdir(folder):
                raise RegistryError(f"registry {self.url.database}: folder {folder} does not exist")
        try:
            self.engine = sa.create_engine(self.url, echo=echo, future=True)
        except (ArgumentError, ImportError) as exc:   # ImportError: the URL's driver is not installed
            raise RegistryError(f"registry {_display(self.url)}: cannot use this database: {exc}") from None
        if self.engine.dialect.name == "sqlite":
            event.listen(self.engine, "connect", _sqlite_pragmas)
        new_file = self.path is not None and not os.path.exists(self.path)
        try:
            if revision is None:
                migrate(self.engine)
            else:
                at_revision(self.engine, revision)
        except DBAPIError as exc:   # cannot connect, no such database, no permission, a full disk ...
            self.engine.dispose()
            if new_file and os.path.isfile(self.path) and os.path.getsize(self.path) == 0:
                os.unlink(self.path)     # the empty file SQLite made before the schema was refused
            raise self._refused(exc, "cannot open the database") from None

    def __repr__(self):
        return f"Registry({_display(self.url)!r})"

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _refused(self, exc: DBAPIError, what: str) -> Exception:
        """What the database refused, in one line: a write an SQLite file's disk or folder refuses
        (full, read-only, not permitted, an I/O error) is an :class:`output.OutputError` naming the
        file and the cause; anything else a :class:`RegistryError` with the database's own words."""
        orig = exc.orig if exc.orig is not None else exc
        code = getattr(orig, "sqlite_errorcode", None)
        if self.path is not None and code is not None:
            primary = code & 0xFF       # extended result codes carry the primary one in their low byte
            if primary == 13:                                       # SQLITE_FULL
                return OutputError(self.path, refused_write_words(OSError(errno.ENOSPC, ""))[1], errno.ENOSPC)
            if primary in (8, 14, 3):                               # SQLITE_READONLY, _CANTOPEN, _PERM
                try:
                    check_output(self.path)     # names a missing or unwritable folder, a read-only file system
                except OutputError as refusal:
                    return refusal
                if os.path.exists(self.path) and not os.access(self.path, os.W_OK):
                    return OutputError(self.path, refused_write_words(OSError(errno.EACCES, ""))[1], errno.EACCES)
            if primary == 10:                                       # SQLITE_IOERR
                return OutputError(self.path, f"{refused_write_words(OSError(errno.EIO, ''))[1]}: {orig}", errno.EIO)
        return RegistryError(f"registry {_display(self.url)}: {what}: {' '.join(str(orig).split())}")

    @contextmanager
    def _writing(self, what: str):
        """A session whose transaction holds the registry's write lock (:func:`write_lock`) from its
        start: a registration reads what is there and writes what is not, and no other writer comes
        between (two processes registering the same probe at once both saw none, and the second
        insert failed).  A refusal of the database becomes one line (:meth:`_refused`); ``what``
        names the request in it."""
        try:
            with Session(self.engine) as s, s.begin():
                write_lock(s.connection())
                yield s
        except IntegrityError as exc:   # a client that does not take the lock wrote the same key meanwhile
            raise RegistryError(f"{what}: conflicts with a row another client of {_display(self.url)} wrote "
                                f"meanwhile: {' '.join(str(exc.orig).split())}") from None
        except DBAPIError as exc:
            raise self._refused(exc, what) from None

    # ---- probes ---------------------------------------------------------------------------
    def add_probe(self, serial: str, model: str = "", note: str = "",
                  calibration_interval_days: float = DEFAULT_INTERVAL_DAYS) -> ProbeInfo:
        """Register a probe.  Registering the same probe again with the same model, note and
        interval does nothing; with different ones it is refused (a serial names one probe)."""
        _check_serial(serial)
        try:
            interval = float(calibration_interval_days)
        except (TypeError, ValueError):
            raise RegistryError(f"probe {serial}: calibration interval {calibration_interval_days!r} is not a number") \
                from None
        if not (interval > 0 and interval < 1e6):
            raise RegistryError(f"probe {serial}: calibration interval must be a positive number of days, got {interval}")
        with self._writing(f"probe {serial}") as s:
            row = s.get(ProbeRow, serial)
            if row is None:
                row = ProbeRow(serial=serial, model=str(model), note=str(note), calibration_interval_days=interval,
                               created=_dt.datetime.now(_dt.timezone.utc))
                s.add(row)
            else:
                diff = [f"{k} {getattr(row, k)!r} (given {v!r})" for k, v in
                        (("model", str(model)), ("note", str(note)), ("calibration_interval_days", interval))
                        if getattr(row, k) != v]
                if diff:
                    raise RegistryError(f"probe {serial} is already registered with {', '.join(diff)}: a serial names "
                                        "one probe (use update_probe to change its details)")
            s.flush()
            return _probe_info(row)

    def update_probe(self, serial: str, *, model: Optional[str] = None, note: Optional[str] = None,
                     calibration_interval_days: Optional[float] = None) -> ProbeInfo:
        """Change a registered probe's model, note or calibration interval (days)."""
        with self._writing(f"probe {serial}") as s:
            row = self._probe_row(s, serial)
            if model is not None:
                row.model = str(model)
            if note is not None:
                row.note = str(note)
            if calibration_interval_days is not None:
                interval = float(calibration_interval_days)
                if not (interval > 0 and interval < 1e6):
                    raise RegistryError(f"probe {serial}: calibration interval must be a positive number of days, "
                                        f"got {interval}")
                row.calibration_interval_days = interval
            s.flush()
            return _probe_info(row)

    def probe(self, serial: str) -> ProbeInfo:
        """The registered probe ``serial`` (RegistryError if unknown)."""
        with Session(self.engine) as s:
            return _probe_info(self._probe_row(s, serial))

    def probes(self) -> List[ProbeInfo]:
        """Every registered probe, by serial."""
        with Session(self.engine) as s:
            return [_probe_info(r) for r in s.scalars(sa.select(ProbeRow).order_by(ProbeRow.serial))]

    def _probe_row(self, s: Session, serial: str) -> ProbeRow:
        row = s.get(ProbeRow, serial) if isinstance(serial, str) else None
        if row is None:
            raise RegistryError(f"probe {serial!r} is not registered in {_display(self.url)}")
        return row

    # ---- calibrations ---------------------------------------------------------------------
    def add_calibration(self, cal: Calibration, *, calibrated_at: _dt.datetime, operator_note: str = "",
                        raw_log_sha256: str = "") -> str:
        """Store a calibration record of the probe ``cal.probe_id`` (its serial; it must be
        registered), calibrated at ``calibrated_at`` (aware).  Returns the record's id
        (``cal.id``).  Storing the same record again with the same date and raw-log hash returns
        its id and changes nothing; the same record with another date or raw log, or another
        record of the probe at the same instant, is refused."""
        if not isinstance(cal, Calibration):
            raise RegistryError(f"expected a coeffs.Calibration, got {type(cal).__name__}")
        when = aware(calibrated_at, f"calibration {cal.id} of probe {cal.probe_id}: calibrated_at")
        raw = str(raw_log_sha256 or "").lower()
        if raw and not _SHA256_RE.match(raw):
            raise RegistryError(f"calibration {cal.id}: raw log SHA-256 {raw_log_sha256!r} is not 64 hex digits")
        rid = cal.id
        with self._writing(f"calibration {rid} of probe {cal.probe_id}") as s:
            probe = s.get(ProbeRow, cal.probe_id)
            if probe is None:
                raise RegistryError(f"calibration {rid}: probe {cal.probe_id!r} is not registered in "
                                    f"{_display(self.url)} (register it first: fleet register {cal.probe_id})")
            old = s.get(CalibrationRow, rid)
            if old is not None:
                diff = [f"{k} {a} (given {b})" for k, a, b in (
                    ("calibrated_at", old.calibrated_at.isoformat(), when.isoformat()),
                    ("raw log SHA-256", old.raw_log_sha256 or "none", raw or "none")) if a != b]
                if diff:
                    raise RegistryError(f"calibration {rid} of probe {cal.probe_id} is already stored with {'; '.join(diff)}: "
                                        "one record is one calibration")
                return rid
            clash = s.scalar(sa.select(CalibrationRow.id).where(CalibrationRow.probe_serial == cal.probe_id,
                                                                CalibrationRow.calibrated_at == when))
            if clash is not None:
                raise RegistryError(f"probe {cal.probe_id} already has calibration {clash} at {when.isoformat()}: "
                                    f"refusing {rid} at the same instant (which would be valid?)")
            s.add(CalibrationRow(
                id=rid, probe_serial=cal.probe_id, calibrated_at=when, method=cal.method,
                model_description=cal.model.describe(), site=cal.site.to_dict(), record_yaml=cal.to_yaml(),
                operator_note=str(operator_note or ""), raw_log_sha256=raw,
                uncertainty=_jsonable(cal.uncertainty), created=_dt.datetime.now(_dt.timezone.utc)))
        return rid

    def valid_record(self, serial: str, at: _dt.datetime) -> Calibration:
        """The calibration record valid for a survey of probe ``serial`` at ``at`` (the validity
        rule of the module's docstring); RegistryError saying why when there is none."""
        at = aware(at, f"probe {serial}: survey date")
        with Session(self.engine) as s:
            probe = self._probe_row(s, serial)
            row = s.scalars(sa.select(CalibrationRow)
                            .where(CalibrationRow.probe_serial == serial, CalibrationRow.calibrated_at <= at)
                            .order_by(CalibrationRow.calibrated_at.desc()).limit(1)).first()
            if row is None:
                first = s.scalar(sa.select(sa.func.min(CalibrationRow.calibrated_at))
                                 .where(CalibrationRow.probe_serial == serial))
                after = (f"its first calibration is of {first:%Y-%m-%d %H:%M UTC}" if first is not None
                         else "it has no calibration at all")
                raise RegistryError(f"probe {serial}: no calibration at or before {at:%Y-%m-%d %H:%M UTC} ({after})")
            age = (at - row.calibrated_at).total_seconds() / 86400.0
            if age > probe.calibration_interval_days:
                raise RegistryError(
                    f"probe {serial}: overdue at {at:%Y-%m-%d %H:%M UTC}: its latest calibration {row.id} of "
                    f"{row.calibrated_at:%Y-%m-%d %H:%M UTC} is {age:.2f} days old, beyond its calibration interval "
                    f"of {probe.calibration_interval_days:g} days")
            return _load(row)

    def record(self, record_id: str) -> Calibration:
        """The stored record with this id (RegistryError if none)."""
        with Session(self.engine) as s:
            row = s.get(CalibrationRow, record_id)
            if row is None:
                raise RegistryError(f"no calibration record {record_id!r} in {_display(self.url)}")
            return _load(row)

    def history(self, serial: str) -> List[HistoryEntry]:
        """Every calibration of probe ``serial``, oldest first (RegistryError if the probe is unknown)."""
        with Session(self.engine) as s:
            self._probe_row(s, serial)
            rows = s.scalars(sa.select(CalibrationRow).where(CalibrationRow.probe_serial == serial)
                             .order_by(CalibrationRow.calibrated_at)).all()
            return [HistoryEntry(date=r.calibrated_at, id=r.id, method=r.method, record=_load(r),
                                 operator_note=r.operator_note, raw_log_sha256=r.raw_log_sha256,
                                 model_description=r.model_description, created=r.created) for r in rows]


def _probe_info(row: ProbeRow) -> ProbeInfo:
    return ProbeInfo(serial=row.serial, model=row.model, note=row.note,
                     calibration_interval_days=float(row.calibration_interval_days), created=row.created)


def _load(row: CalibrationRow) -> Calibration:
    try:
        return Calibration.from_yaml(row.record_yaml, source=f"registry record {row.id}")
    except CoefficientError as exc:
        raise RegistryError(f"stored record {row.id} of probe {row.probe_serial} no longer loads: {exc}") from None


def _jsonable(x):
    """Plain JSON types (numpy arrays and scalars in a record's uncertainty become lists and floats)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return x.tolist()
    return x


def _sqlite_pragmas(dbapi_conn, _record):
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA foreign_keys=ON")   # SQLite enforces the probe FK only when asked
    cur.execute("PRAGMA busy_timeout=30000")  # several processes (Dask workers) may read and write
    cur.close()


# ---------------------------------------------------------------------------------------------
# Migrations (Alembic, run from code)
# ---------------------------------------------------------------------------------------------
def alembic_config(connection=None):
    """An Alembic configuration for the shipped migrations, built in code (no alembic.ini);
    ``connection``: the connection env.py migrates (else it connects to the main option's URL)."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", MIGRATIONS_DIR)
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def head_revision() -> str:
    from alembic.script import ScriptDirectory

    return ScriptDirectory.from_config(alembic_config()).get_current_head()


def current_revision(engine) -> Optional[str]:
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def at_revision(engine, revision: str) -> None:
    """Raise :class:`RegistryError` unless the database's schema is at ``revision`` (read from
    Alembic's ``alembic_version`` table with one query; no Alembic import)."""
    with engine.connect() as conn:
        try:
            current = conn.execute(sa.text("SELECT version_num FROM alembic_version")).scalar()
        except DBAPIError:
            current = None        # no table: not a registry (yet)
    if current != revision:
        raise RegistryError(f"registry {_display(engine.url)} has schema revision {current!r}, not {revision!r} "
                            "as when this run opened it (migrated or replaced since?)")


def migrate(engine, revision: str = "head") -> None:
    """Bring the database to ``revision`` (default the newest) with the shipped migrations.  A
    database already there is left untouched (no lock, no write); one written by a newer version of
    this package (a revision this one does not know) is refused.  The upgrade is one transaction
    holding the registry's write lock (:func:`write_lock`), so that several processes opening a
    fresh registry at once migrate it once, and a failed upgrade leaves the schema as it was."""
    from alembic import command
    from alembic.script import ScriptDirectory
    from alembic.util import CommandError

    script = ScriptDirectory.from_config(alembic_config())
    head = script.get_current_head()
    current = current_revision(engine)
    if revision == "head" and current == head:
        return
    if current is not None:
        try:
            script.get_revision(current)
        except CommandError:
            raise RegistryError(f"registry {_display(engine.url)} has schema revision {current!r}, unknown to this "
                                f"version of inclinometer_calib (newest known: {head}): upgrade the package") from None
    with engine.begin() as conn:
        write_lock(conn)
        command.upgrade(alembic_config(conn), revision)   # reads the revision again, under the lock


def write_lock(conn) -> None:
    """Take the registry's write lock for the rest of ``conn``'s transaction (its first statement):
    writers of the registry — migrations, registrations — then run one at a time, each seeing what
    the one before committed; readers are not held up.  PostgreSQL: a transaction-scoped advisory
    lock (:data:`PG_WRITE_LOCK`, released at commit or rollback).  SQLite: ``BEGIN IMMEDIATE``, its
    database write lock taken now rather than at the first write (the driver would begin the
    transaction only at the first INSERT, and run DDL outside any), waiting up to the busy timeout."""
    name = conn.dialect.name
    if name == "postgresql":
        conn.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"), {"key": PG_WRITE_LOCK})
    elif name == "sqlite":
        conn.exec_driver_sql("BEGIN IMMEDIATE")

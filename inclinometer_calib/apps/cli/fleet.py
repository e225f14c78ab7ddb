"""The probe fleet's commands: ``fleet register``, ``fleet add``, ``fleet history`` (the registry)
and ``fleet reprocess`` (many bags on Dask)."""
from __future__ import annotations

import json

from ...core.deps import require
from ...core.output import OutputError, atomic_write_text
from ..common import UserError, load_calibration
from .shared import load_plugins, tolerance_options


def parse_date(text: str, what: str):
    """A date or date-time given on the command line (ISO 8601: ``2026-03-01``,
    ``2026-03-01T14:30``, ``2026-03-01T14:30+02:00``) as an aware datetime; without a zone it is UTC."""
    import datetime as dt

    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise UserError(f"{what}: {text!r} is not an ISO 8601 date (e.g. 2026-03-01 or 2026-03-01T14:30Z)") from None
    return t.replace(tzinfo=dt.timezone.utc) if t.tzinfo is None else t


#: What the fleet's commands import (the ``fleet`` extra), checked before any work starts.
FLEET_REGISTRY = ("sqlalchemy", "alembic")


FLEET_REPROCESS = FLEET_REGISTRY + ("dask", "distributed", "pyarrow")


def _fleet_needs(purpose: str, modules) -> None:
    """One line, exit status 2, when the ``fleet`` extra is not installed (:func:`deps.require`)."""
    for module in modules:
        require(module, "fleet", purpose)


def _registry(args, create: bool = True):
    """The registry ``--db`` names; ``create=False`` for a command that only reads it."""
    from ...fleet.registry import DEFAULT_URL, Registry, RegistryError

    try:
        return Registry(args.db or DEFAULT_URL, create=create)
    except RegistryError as exc:
        raise UserError(str(exc)) from None


def cmd_fleet_register(args):
    """``fleet register SERIAL``: add a probe to the registry (or, with --update, change its details)."""
    _fleet_needs("fleet register", FLEET_REGISTRY)
    from ...fleet.registry import RegistryError

    with _registry(args) as reg:
        try:
            if args.update:
                p = reg.update_probe(args.serial, model=args.model, note=args.note,
                                     calibration_interval_days=args.interval)
            else:
                p = reg.add_probe(args.serial, model=args.model or "", note=args.note or "",
                                  calibration_interval_days=args.interval if args.interval is not None else 90.0)
        except RegistryError as exc:
            raise UserError(str(exc)) from None
        print(f"probe {p.serial}: model {p.model or '-'}, calibration interval {p.calibration_interval_days:g} days"
              + (f", note: {p.note}" if p.note else "") + f" (registry {reg.url.render_as_string(hide_password=True)})")
    return 0


def cmd_fleet_add(args):
    """``fleet add RECORD.yaml --date DATE``: store a calibration record of a registered probe, with
    the date of the calibration, the operator's note and the SHA-256 of the raw log."""
    _fleet_needs("fleet add", FLEET_REGISTRY)
    import hashlib

    from ...fleet.registry import RegistryError

    load_plugins(args.plugin, run=False)
    cal = load_calibration(args.record)
    if cal is None:
        raise UserError("fleet add: give a calibration record file")
    when = parse_date(args.date, "--date")
    raw = ""
    if args.raw_log:
        h = hashlib.sha256()
        try:
            with open(args.raw_log, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
        except OSError as exc:
            raise UserError(f"--raw-log {args.raw_log}: {exc.strerror}") from None
        raw = h.hexdigest()
    with _registry(args) as reg:
        try:
            rid = reg.add_calibration(cal, calibrated_at=when, operator_note=args.note or "", raw_log_sha256=raw)
        except RegistryError as exc:
            raise UserError(f"{args.record}: {exc}") from None
    print(f"calibration {rid} of probe {cal.probe_id} at {when.astimezone().isoformat()} stored"
          + (f" (raw log sha256 {raw})" if raw else ""))
    return 0


def cmd_fleet_history(args):
    """``fleet history SERIAL``: each parameter over time with its 1σ, the calibrations that moved
    beyond their combined uncertainty, and whether the probe is overdue (text; --html with plots)."""
    _fleet_needs("fleet history", FLEET_REGISTRY)
    from ...fleet import history as fh
    from ...fleet.registry import RegistryError

    at = parse_date(args.at, "--at") if args.at else None
    if not (args.k > 0):
        raise UserError(f"--k must be positive, got {args.k}")
    with _registry(args, create=False) as reg:
        try:
            h = fh.analyse(reg.probe(args.serial), reg.history(args.serial), at=at, k=args.k)
        except RegistryError as exc:
            raise UserError(str(exc)) from None
    if args.json:
        print(json.dumps(fh.to_json(h), indent=2))
    else:
        print(fh.format_history(h))
    if args.html:
        try:
            atomic_write_text(args.html, fh.to_html(h))
        except OSError as exc:
            raise UserError(f"--html {args.html}: {exc.strerror}") from None
        if not args.json:
            print(f"wrote {args.html}")
    return 0


def _fleet_registry_parser(fsub):
    """``fleet register``, ``fleet add``, ``fleet history`` (the registry, docs/fleet.md)."""
    def db(p):
        p.add_argument("--db", help="registry: SQLAlchemy URL (e.g. postgresql+psycopg://user@host/fleet) or SQLite "
                                    "file (default sqlite:///fleet.db in the working folder)")

    r = fsub.add_parser("register", help="register a probe by its serial number")
    r.add_argument("serial", help="the probe's serial number (letters, digits, -_.:/)")
    r.add_argument("--model", help="the probe's model")
    r.add_argument("--note", help="a note on the probe")
    r.add_argument("--interval", type=float, metavar="DAYS", help="calibration interval, days (default 90): a "
                   "calibration older than this is not valid for a survey")
    r.add_argument("--update", action="store_true", help="change the details of a registered probe")
    db(r)
    r.set_defaults(func=cmd_fleet_register)
    a = fsub.add_parser("add", help="store a calibration record of a registered probe (its probe_id is the serial)")
    a.add_argument("record", help="calibration record YAML (twelve-position, turntable, lab fit ...)")
    a.add_argument("--date", required=True, help="when the probe was calibrated, ISO 8601 (UTC unless a zone is given)")
    a.add_argument("--note", help="the operator's note")
    a.add_argument("--raw-log", metavar="FILE", help="the raw calibration log (its SHA-256 is stored)")
    a.add_argument("--plugin", action="append", help="Python file (or module) defining plug-in effects the record "
                   "uses: loaded only from these, after its SHA-256 matches (repeatable)")
    db(a)
    a.set_defaults(func=cmd_fleet_add)
    h = fsub.add_parser("history", help="a probe's parameters over time with 1σ; flags calibrations that moved beyond "
                                        "their combined uncertainty and an overdue probe")
    h.add_argument("serial", help="the probe's serial number")
    h.add_argument("--html", metavar="FILE", help="also write the history with plots as one HTML file")
    h.add_argument("--at", metavar="DATE", help="check the calibration interval at this date (default now)")
    h.add_argument("--k", type=float, default=3.0, help="flag a parameter that moved by more than k·sqrt(σ1²+σ2²) "
                                                        "(default 3)")
    h.add_argument("--json", action="store_true", help="the history as JSON")
    db(h)
    h.set_defaults(func=cmd_fleet_history)


def cmd_fleet_reprocess(args):
    """``fleet reprocess BAGS... | --manifest FILE -o OUT``: many bags on Dask into one Parquet
    dataset (:mod:`inclinometer_calib.fleet.reprocess`). Exit status 0 when every bag is done
    (now or before), 1 when some failed (each with its reason in the summary), 2 when nothing
    could be done."""
    _fleet_needs("fleet reprocess", FLEET_REPROCESS)
    from ...fleet.manifest import ManifestError, entries_from_paths, read_manifest
    from ...fleet.registry import DEFAULT_URL
    from ...fleet.reprocess import Settings, reprocess_fleet

    if bool(args.bags) == bool(args.manifest):
        raise UserError("give the bags either as arguments or with --manifest FILE (one of the two)")
    try:
        entries = read_manifest(args.manifest) if args.manifest else entries_from_paths(args.bags)
    except ManifestError as exc:
        raise UserError(str(exc)) from None
    settings = Settings(field_nt=args.field_tol, dip_deg=args.dip_tol, gravity_mps2=args.gravity_tol,
                        monitor_window=args.monitor_window, force_probe=args.force_probe)
    with _registry(args, create=False):     # the records come from it: an existing one, before any cluster
        pass
    try:
        summary = reprocess_fleet(entries, out_dir=args.output, registry_url=args.db or DEFAULT_URL,
                                  scheduler=args.scheduler, n_workers=args.workers, progress=not args.no_progress,
                                  bags_per_task=args.bags_per_task, settings=settings)
    except OutputError:             # the output folder refused: "cannot write PATH: CAUSE"
        raise
    except OSError as exc:          # the scheduler cannot be reached
        raise UserError(f"{args.scheduler or args.output}: {exc}") from None
    except ValueError as exc:       # RegistryError (the registry cannot be opened), a run already there, bad options
        raise UserError(str(exc)) from None
    for line in summary.lines():
        print(line)
    print(f"wrote {summary.paths['dataset']}/ (Parquet, by probe and survey date: every run's), "
          f"{summary.paths['summary']} (this run's bags only: it replaces the last run's), {summary.paths['index']} "
          "(every bag done, and under what)")
    return 1 if summary.failed else 0


def _fleet_reprocess_parser(fsub):
    r = fsub.add_parser("reprocess", help="reprocess many bags on Dask (each with its probe's valid record from the "
                                          "registry) into one Parquet dataset partitioned by probe and survey date")
    r.add_argument("bags", nargs="*", help="bags (.mcap files or bag folders)")
    r.add_argument("--manifest", help="text file of bag paths, one a line, or CSV with columns bag[,serial]; relative "
                                      "paths are relative to the manifest's folder")
    r.add_argument("-o", "--output", required=True, help="output folder: stations/ (the dataset), summary.csv, "
                                                          "done-index.json (a rerun skips the bags done there)")
    r.add_argument("--db", help="registry: SQLAlchemy URL or SQLite file (default sqlite:///fleet.db)")
    r.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on this Dask scheduler's cluster (default: a "
                   "local cluster on this machine)")
    r.add_argument("--workers", type=int, metavar="N", help="worker processes of the local cluster (default: the "
                   "cores; 0: no Dask, one bag after the other in this process)")
    r.add_argument("--bags-per-task", type=int, metavar="N", help="bags per Dask task (default: up to 10, at least 4 "
                   "tasks per worker; see docs/fleet.md)")
    r.add_argument("--force-probe", action="store_true", help="apply the record of the serial the manifest gives to a "
                   "bag that records another serial (refused otherwise); every station and the summary say so")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--monitor-window", type=int, default=30, metavar="N",
                   help="the field monitor's window, as reprocess (0: off)")
    tolerance_options(r)
    r.set_defaults(func=cmd_fleet_reprocess)
    return r


def register(sub):
    """The ``fleet`` group: each part of the fleet adds its sub-commands to ``fsub`` here."""
    fleet = sub.add_parser("fleet", help="probe fleet: registry, calibration history, reprocessing many bags")
    fsub = fleet.add_subparsers(dest="fleet_command", required=True)
    _fleet_registry_parser(fsub)
    _fleet_reprocess_parser(fsub)
    return fsub

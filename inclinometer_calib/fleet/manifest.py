"""The list of bags a fleet reprocessing run takes: a manifest file, or bag paths given directly.

A manifest is a text file with one bag a line::

    # survey centre, November re-run
    2026-11/well-17.mcap
    2026-11/well-18.mcap

or a CSV with a header line naming its columns: ``bag`` (required) and ``serial`` (optional: the
probe's serial for a bag that records none, or that records another one — then applied only with
``--force-probe``, and every output says so)::

    bag,serial
    old/2019-well-3.mcap,SN-0042
    2026-11/well-17.mcap,

Blank lines and lines starting with ``#`` are skipped. A relative path is relative to the
manifest's folder (not the working directory), so a manifest travels with its bags.
"""
from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from typing import Iterable, List, Optional

#: Columns a CSV manifest may have.
COLUMNS = ("bag", "serial")


class ManifestError(ValueError):
    """A manifest that cannot be read: names the file, the line and what is wrong."""


@dataclass(frozen=True)
class BagEntry:
    """One bag of a run: its path (absolute, normalized) and the serial the manifest gives for it
    (None: the serial the bag records is used)."""

    path: str
    serial: Optional[str] = None


def _absolute(path: str, base: str) -> str:
    return os.path.normpath(os.path.join(base, os.path.expanduser(path)))


def read_manifest(path) -> List[BagEntry]:
    """The bags a manifest lists, in its order (a bag listed twice is kept once, at its first
    line). Raises :class:`ManifestError` (file, line, reason) for an unreadable file, an unknown
    or missing column, a row with too many fields, or a manifest that lists no bag."""
    path = os.fspath(path)
    base = os.path.dirname(os.path.abspath(path))
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: cannot read the manifest: {exc}") from None
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise ManifestError(f"{path}: the manifest lists no bag")
    entries: List[BagEntry] = []
    first_no, first = lines[0]
    header = [c.strip().lower() for c in next(csv.reader(io.StringIO(first)))]
    if "bag" in header:                                   # CSV with a header line
        unknown = [c for c in header if c not in COLUMNS]
        if unknown:
            raise ManifestError(f"{path}:{first_no}: unknown column(s) {unknown} (a manifest has "
                                f"{', '.join(COLUMNS)})")
        for n, line in lines[1:]:
            row = next(csv.reader(io.StringIO(line)))
            if len(row) > len(header):
                raise ManifestError(f"{path}:{n}: {len(row)} fields, the header names {len(header)}")
            rec = dict(zip(header, (c.strip() for c in row)))
            if not rec.get("bag"):
                raise ManifestError(f"{path}:{n}: no bag path in column 'bag'")
            entries.append(BagEntry(_absolute(rec["bag"], base), rec.get("serial") or None))
    else:                                                 # one path a line
        entries = [BagEntry(_absolute(line.strip(), base)) for _, line in lines]
    if not entries:
        raise ManifestError(f"{path}: the manifest lists no bag (only its header line)")
    return dedupe(entries)


def entries_from_paths(paths: Iterable) -> List[BagEntry]:
    """Bag paths given directly (relative to the working directory) as entries."""
    return dedupe([BagEntry(_absolute(os.fspath(p), os.getcwd())) for p in paths])


def dedupe(entries: Iterable[BagEntry]) -> List[BagEntry]:
    """Each path once, at its first place (the same bag twice would be reprocessed twice into one
    dataset)."""
    seen, out = set(), []
    for e in entries:
        if e.path not in seen:
            seen.add(e.path)
            out.append(e)
    return out

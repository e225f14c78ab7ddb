"""Replay testing: a recorded bag through the live graph, its stations compared with an expected set.

The regression test a rig integrator runs in their own CI::

    inclinometer-calib replay-test run.mcap --expect reprocess --calibrate --site site.yaml
    inclinometer-calib replay-test run.mcap --expect golden.mcap --coeffs probe.yaml --junit replay.xml

The bag is replayed by the launcher (``--source mcap``: the probe node, the calibration and
correction nodes and the recorder as processes over DDS on this machine; paced, so the result does
not depend on the machine's speed) into ``--out``; the stations it recorded are compared, station
by station (matched by their stamp, the end of the hold), with the expected ones:

* ``--expect reprocess``: what ``reprocess`` makes of the same bag with the same calibration
  options — the live graph must equal the offline path;
* ``--expect FILE.mcap``: the ``/survey/station`` messages of another bag (an earlier run, a
  reprocessed golden bag).

Every station must be there (none missing, none extra), with the same record (``coefficients_id``),
status and flags, and its numbers within the tolerances (``--tolerance``: angles in degrees,
default 1e-6; fields, depth and positions in their own units, scaled the same way).  The result is
a table of the differences, a JUnit XML file with ``--junit``, and the exit status: 0 equal, 1 a
difference or a replay that was not clean (its summary's reasons are listed), 2 a usage error.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

#: Compared numbers: name -> (unit, how the angle tolerance scales to it).
NUMBERS = {
    "drift_deg": ("deg", 1.0), "azimuth_deg": ("deg", 1.0), "toolface_deg": ("deg", 1.0),
    "gravity_toolface_deg": ("deg", 1.0), "magnetic_toolface_deg": ("deg", 1.0), "dip_deg": ("deg", 1.0),
    "azimuth_magnetic_deg": ("deg", 1.0), "azimuth_grid_deg": ("deg", 1.0), "azimuth_true_deg": ("deg", 1.0),
    "total_gravity_mps2": ("m/s^2", 1e-2), "total_field_nt": ("nT", 1e2), "delta_g_mps2": ("m/s^2", 1e-2),
    "delta_b_nt": ("nT", 1e2), "delta_dip_deg": ("deg", 1.0), "temperature_c": ("degC", 1.0),
    "measured_depth_m": ("m", 1.0), "tvd_m": ("m", 1e2), "north_m": ("m", 1e2), "east_m": ("m", 1e2),
    "dls_deg_per_30m": ("deg/30m", 1.0),
}
#: Compared exactly.
EXACT = ("coefficients_id", "status", "samples_averaged", "azimuth_undefined", "interference_suspected",
         "gravity_out_of_tolerance", "moved_during_capture", "model_misfit", "uncorrected_reason", "azimuth_reference")
#: Stations are matched by stamp (s) within this.
STAMP_EPS = 1e-6


@dataclass
class Difference:
    stamp: float
    station_id: object
    field: str
    expected: object
    got: object
    delta: float = math.nan


@dataclass
class Comparison:
    expected: int = 0
    got: int = 0
    missing: list = field(default_factory=list)      # expected stations the replay did not give (stamps)
    extra: list = field(default_factory=list)        # stations the replay gave that were not expected
    differences: list = field(default_factory=list)

    @property
    def equal(self) -> bool:
        return not (self.missing or self.extra or self.differences)


def _nan(x) -> bool:
    return isinstance(x, float) and math.isnan(x)


def _wrapped(name, a, b) -> float:
    d = float(a) - float(b)
    if name.endswith("_deg") and "delta" not in name and name not in ("drift_deg", "dip_deg"):
        d = (d + 180.0) % 360.0 - 180.0
    return d


def compare(got, expected, tolerance: float = 1e-6) -> Comparison:
    """Compare station dicts (``surveystation.from_msg``) ``got`` with ``expected``, matched by stamp."""
    from ..io.accounting import unique_stations

    got, _ = unique_stations(got)
    expected, _ = unique_stations(expected)
    res = Comparison(expected=len(expected), got=len(got))
    by_stamp = sorted(got, key=lambda s: s["stamp"])
    used = set()
    for e in sorted(expected, key=lambda s: s["stamp"]):
        match = next((i for i, g in enumerate(by_stamp) if i not in used and abs(g["stamp"] - e["stamp"]) <= STAMP_EPS),
                     None)
        if match is None:
            res.missing.append(e)
            continue
        used.add(match)
        g = by_stamp[match]
        for name in EXACT:
            a, b = g.get(name), e.get(name)
            if a != b and not (_nan(a) and _nan(b)):
                res.differences.append(Difference(e["stamp"], g["station_id"], name, b, a))
        for name, (_, scale) in NUMBERS.items():
            a, b = g.get(name, math.nan), e.get(name, math.nan)
            if _nan(a) and _nan(b):
                continue
            if _nan(a) != _nan(b):
                res.differences.append(Difference(e["stamp"], g["station_id"], name, b, a))
                continue
            d = _wrapped(name, a, b)
            if abs(d) > tolerance * scale:
                res.differences.append(Difference(e["stamp"], g["station_id"], name, b, a, d))
    res.extra = [g for i, g in enumerate(by_stamp) if i not in used]
    return res


def format_comparison(c: Comparison, tolerance: float, limit: int = 40) -> list:
    lines = [f"stations: {c.got} replayed, {c.expected} expected"]
    for s in c.missing[:limit]:
        lines.append(f"  MISSING station at t={s['stamp']:.3f} s (expected id {s['station_id']})")
    for s in c.extra[:limit]:
        lines.append(f"  EXTRA   station at t={s['stamp']:.3f} s (id {s['station_id']})")
    if c.differences:
        lines.append(f"  {len(c.differences)} difference(s) beyond the tolerance ({tolerance:g} deg, scaled per field):")
        lines.append(f"  {'t (s)':>14} {'id':>5}  {'field':<24} {'expected':>20} {'replayed':>20} {'delta':>12}")
        for d in c.differences[:limit]:
            delta = f"{d.delta:+.3g}" if not _nan(d.delta) else ""
            lines.append(f"  {d.stamp:>14.3f} {d.station_id!s:>5}  {d.field:<24} {d.expected!s:>20.20} "
                         f"{d.got!s:>20.20} {delta:>12}")
        if len(c.differences) > limit:
            lines.append(f"  ... and {len(c.differences) - limit} more")
    if c.equal:
        lines.append(f"  every station equal within {tolerance:g} deg (and the same record, status and flags)")
    return lines


def junit_xml(c: Comparison, problems, name: str) -> str:
    """A JUnit report: one test case per expected station, plus the run itself."""
    from xml.sax.saxutils import escape, quoteattr

    cases = []
    bad = {}
    for d in c.differences:
        delta = "" if _nan(d.delta) else f" (delta {d.delta:+.6g} {NUMBERS[d.field][0]})"   # replayed - expected
        bad.setdefault(round(d.stamp, 6), []).append(f"{d.field}: expected {d.expected}, replayed {d.got}{delta}")
    missing = {round(s["stamp"], 6) for s in c.missing}
    stamps = sorted({round(d.stamp, 6) for d in c.differences} | missing)
    n_ok = c.expected - len(stamps)
    cases.append(f'<testcase classname={quoteattr(name)} name="graph run">' +
                 (f'<failure message={quoteattr("; ".join(problems))}/>' if problems else "") + "</testcase>")
    for st in stamps:
        text = "missing from the replay" if st in missing else "; ".join(bad[st])
        cases.append(f'<testcase classname={quoteattr(name)} name="station at t={st:.3f} s">'
                     f'<failure message={quoteattr(text)}>{escape(text)}</failure></testcase>')
    for s in c.extra:
        cases.append(f'<testcase classname={quoteattr(name)} name="station at t={s["stamp"]:.3f} s (extra)">'
                     '<failure message="not expected"/></testcase>')
    cases.append(f'<testcase classname={quoteattr(name)} name="{max(n_ok, 0)} stations equal"/>')
    failures = len(cases) - 2 + (1 if problems else 0)
    return (f'<?xml version="1.0" encoding="utf-8"?>\n<testsuite name={quoteattr(name)} tests="{len(cases)}" '
            f'failures="{failures}">\n' + "\n".join(cases) + "\n</testsuite>\n")


def run(args) -> int:
    """The ``replay-test`` command (see the module docstring).

    Everything the user gave is checked before the replay (a usage error must not cost one): the
    bag opens as an MCAP, ``--out`` can be the run's folder, ``--junit`` can be written, the
    plug-ins are named, the record and site load, the expected stations are read or reprocessed."""
    from .cli.shared import load_plugins
    from .common import UserError, load_calibration, load_site
    from ..core.output import check_output
    from ..io.bag import BagError, open_bag, read_bag
    from .launcher import readable_parts

    bag = Path(args.bag)
    if not bag.exists():
        raise UserError(f"{bag} does not exist")
    try:
        open_bag(bag)                   # its header only: an empty file, a folder without a bag
    except BagError as exc:
        raise UserError(f"{exc.path}: not a bag to replay: {exc.reason}") from None
    except OSError as exc:
        raise UserError(f"{bag}: {exc.strerror or exc}") from None
    out = Path(args.out or f"{bag.with_suffix('')}.replay")
    _check_out(out, args.overwrite)
    if args.junit:
        check_output(args.junit)        # OutputError: one line, exit 2 (cli.main)
    # the plug-ins the records use, named (or run, to fit --effects) as reprocess names them
    load_plugins(args.plugin, run=bool(args.calibrate and args.effects))
    cal = load_calibration(args.coeffs) if args.coeffs else None
    if args.coeffs and cal is None and not args.calibrate:      # --coeffs none
        raise UserError("--coeffs none: the live graph has no uncorrected mode (every station would go out without "
                        "a record, which its summary counts as not clean): give the record (--coeffs FILE) or "
                        "--calibrate")
    site = load_site(args.site) if args.site else None
    # the expected stations first: a usage error must not cost a replay
    if args.expect == "reprocess":
        expected = _reprocessed(bag, args, cal, site)
    else:
        path = Path(args.expect)
        if not path.exists():
            raise UserError(f"--expect {path}: no such file (a bag with /survey/station, or 'reprocess')")
        try:
            expected = read_bag(path)[0]
        except ValueError as exc:       # not a bag, a damaged one
            raise UserError(f"--expect {path}: {exc}") from None
        except OSError as exc:
            raise UserError(f"--expect {path}: {exc.strerror or exc}") from None
        if not expected:
            raise UserError(f"--expect {path}: no /survey/station messages in it")
    cmd = [sys.executable, "-m", "inclinometer_calib.apps.launcher", "--out", str(out), "--source", "mcap", "--input",
           str(bag), "--speed", str(args.speed), "--no-loop", "--overwrite"]
    if args.site:
        cmd += ["--site", args.site]
    if cal is not None:
        cmd += ["--coeffs", args.coeffs, "--no-calibration"] if not args.calibrate else ["--coeffs", args.coeffs]
    elif not args.calibrate:
        cmd += ["--no-calibration"]
    if args.effects:
        cmd += ["--model-effects", args.effects]
    if getattr(args, "north", "auto") != "auto":
        cmd += ["--north", args.north]
    for plug in args.plugin or ():
        cmd += ["--plugin", plug]
    for p in args.param or ():
        cmd += ["--param", p]
    if args.timeout:
        cmd += ["--timeout", str(args.timeout)]
    print(f"replaying {bag} through the live graph into {out} ...", flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
    lines = proc.stdout.strip().splitlines() or [""]
    last = lines[-1]
    if "=== run summary ===" in lines:      # the run's accounting, as the launcher said it
        for line in lines[lines.index("=== run summary ==="):]:
            print(line)
    else:
        print("\n".join(lines[-20:]))
    problems = []
    if proc.returncode not in (0,):
        problems.append(f"the replay was not clean: {last.removeprefix('[launch] ')}")
    got = []
    for part in readable_parts(str(out), print_fn=lambda *a: None):
        if part["read"] is not None:
            got += read_bag(part["read"])[0]
    c = compare(got, expected, args.tolerance)
    for line in format_comparison(c, args.tolerance):
        print(line)
    for p in problems:
        print(p)
    if args.junit:
        from ..core.output import atomic_write_text
        atomic_write_text(args.junit, junit_xml(c, problems, f"replay-test {bag.name}"))
        print(f"wrote {args.junit}")
    ok = c.equal and not problems
    print(f"replay-test: {'PASS' if ok else 'FAIL'} (the run: {out}; its log: {out / 'launch.log'})")
    return 0 if ok else 1


def _check_out(out: Path, overwrite: bool) -> None:
    """Refuse an ``--out`` that cannot be the run's folder (a file, under a file, unreadable) or
    holds a run (without ``overwrite``); a missing one is made by the launcher, parents too."""
    from .common import UserError

    if out.exists():
        if not out.is_dir():
            raise UserError(f"--out {out}: a file of that name exists (the run's folder is meant)")
        try:
            held = any(out.iterdir())
        except OSError as exc:
            raise UserError(f"--out {out}: {exc.strerror or exc}") from None
        if held and not overwrite:
            raise UserError(f"{out} already holds a run (use --overwrite or another --out)")
        return
    above = out.absolute().parent
    while not above.exists():
        above = above.parent
    if not above.is_dir():
        raise UserError(f"--out {out}: {above} is a file, not a folder")


def _reprocessed(bag, args, cal, site) -> list:
    """The stations ``reprocess`` makes of the bag with the replay's calibration options (``cal``,
    ``site``: the loaded ``--coeffs``, ``--site``)."""
    from .common import UserError
    from ..io.bag import BagError
    from ..lab.field import FieldMonitor
    from ..correct.reprocess import ReprocessError, reprocess

    try:
        # the correction node's own settings: its field monitor (30 stations), the default QC tolerances
        rep = reprocess(bag, None, calibration=cal, site=site, calibrate=args.calibrate, effects=args.effects or "",
                        monitor=FieldMonitor(window=30), north=getattr(args, "north", "auto"))
    except (ReprocessError, BagError, ValueError, OSError) as exc:
        raise UserError(f"{bag}: reprocess: {exc}") from None
    print(f"expected: reprocess of {bag}: {len(rep.stations)} stations", flush=True)
    return rep.stamped_stations()

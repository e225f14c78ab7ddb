"""Probes unlike our default simulator, written the way other tools write their logs.

Shared by the test matrix through the CLI and ``reprocess`` (test/test_strangers.py) and the
live-graph cases (test/nodes/test_strangers_graph.py).  A case changes one thing at a time from a
stranger-like base: 2.5× our default noise (0.005 m/s², 50 nT), large uncalibrated errors,
100 Hz, 3 s holds with 1.5 s moves, two rounds of the twelve poses whose vertical poses give drift
and toolface but no azimuth, a small validation grid.  Everything is seeded.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import yaml

from inclinometer_calib import simulate as sim
from inclinometer_calib.coeffs import Calibration
from inclinometer_calib.frames import Site
from inclinometer_calib.probelog import ProbeLog, write_csv

SITE = Site(total_field_nt=50500.0, dip_deg=45.1, declination_deg=0.0, gravity_mps2=9.7913)


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    noise: float = 2.5            # × our default noise (0.002 m/s², 20 nT)
    rate_hz: float = 100.0
    hold_s: float = 3.0
    move_s: float = 1.5
    labels: bool = True           # pose labels and stand references in the calibration log
    mag_unit: str = "nT"
    severity: float = 3.0         # × our default uncalibrated errors
    seed: int = 11


CASES = [
    Case("base"),
    Case("quiet", noise=0.5),
    Case("noise x5", noise=5.0),
    Case("10 Hz", rate_hz=10.0, hold_s=4.0),
    Case("1000 Hz", rate_hz=1000.0, hold_s=1.5, move_s=0.5),
    Case("1 s holds", hold_s=1.0, move_s=1.0),
    Case("10 s holds", hold_s=10.0),
    Case("slow moves", move_s=6.0),
    Case("fast moves", move_s=0.25),
    Case("unlabelled", labels=False),
    Case("tesla", mag_unit="T"),
]

VAL_GRID = dict(drifts=(5, 30, 60, 90), azimuths=(0, 120, 240), toolfaces=(0, 150))


def make(case: Case, out) -> dict:
    """Write ``cal.csv``, ``val.csv``, ``both.csv`` (one after the other), ``site.yaml`` and
    ``truth_coeffs.yaml`` for a case into directory ``out``; returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    probe = sim.build_probe(case.seed, severity=case.severity, noise_acc=0.002 * case.noise,
                            noise_mag=20.0 * case.noise)
    rng = np.random.default_rng(case.seed + 1)
    cal = sim.run_session(probe, SITE, sim.twelve_pose_session((25.0, 28.0), duration_s=case.hold_s, refs=True),
                          rng, rate_hz=case.rate_hz, move_s=case.move_s)
    if not case.labels:
        cal.pose[:] = 0
        cal.ref[:] = np.nan
    val = sim.run_session(probe, SITE, sim.stand_grid_session(duration_s=case.hold_s, **VAL_GRID), rng,
                          rate_hz=case.rate_hz, move_s=case.move_s, t0=cal.t_s[-1] + 5.0)
    paths = {k: out / f"{k}.csv" for k in ("cal", "val", "both")}
    write_csv(paths["cal"], cal, mag_unit=case.mag_unit)
    write_csv(paths["val"], val, mag_unit=case.mag_unit)
    write_csv(paths["both"], ProbeLog.concatenate([cal, val]), mag_unit=case.mag_unit)
    paths["site"] = out / "site.yaml"
    paths["site"].write_text(yaml.safe_dump({"site": SITE.to_dict()}))
    paths["truth"] = out / "truth_coeffs.yaml"
    Calibration(acc=probe.acc, mag=probe.mag, probe_id="stranger", method="simulator truth", site=SITE).save(
        paths["truth"])
    return paths


def stations_of_bag(path):
    """``/survey/station`` and ``/calibration/coefficients`` of a bag, read with rosbags (the run
    summary's reader, independent of our writer)."""
    from inclinometer_calib.launcher import read_bag

    stations, coefficients = read_bag(path)[:2]
    return stations, coefficients


def json_out(text: str) -> dict:
    return json.loads(text)

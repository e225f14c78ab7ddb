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

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.probelog import ProbeLog, write_csv

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
    """``/survey/station`` (station dicts, :func:`io.surveystation.from_msg`) and
    ``/calibration/coefficients`` (``id``, ``coefficients_yaml``) of a bag, read with rosbags'
    ``AnyReader`` and its Jazzy type store: a reader and decoder independent of our bag code."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from inclinometer_calib.io.surveystation import from_msg

    stations, coefficients = [], []
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic in ("/survey/station", "/calibration/coefficients")]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/survey/station":
                stations.append(from_msg(msg))
            else:
                coefficients.append({"id": msg.id, "coefficients_yaml": msg.coefficients_yaml})
    return stations, coefficients


def json_out(text: str) -> dict:
    return json.loads(text)


# ---------------------------------------------------------------------------------------------
# The independent simulator's probe (test/data/stranger-probe, see its README)
# ---------------------------------------------------------------------------------------------
STRANGER_DIR = __import__("pathlib").Path(__file__).resolve().parent / "data" / "stranger-probe"


def stranger_truth():
    """``(Calibration, Site)`` of the independent simulator's probe, in our conventions.

    Its accelerometer model applies to the REP-145 specific force, ``f_out = K·E·f + B_f``; ours
    to the gravity vector ``g = -f``, ``g_out = K·E·g - B_f``: the same K and E, the bias negated.
    Its ``e`` keys ``ab`` are our ``e_ab`` (the coefficient of component a in sensor b's output).
    """
    from inclinometer_calib.core.errormodel import TriadModel

    t = json.loads((STRANGER_DIR / "truth.json").read_text())

    def triad(d, sign):
        return TriadModel(scale=d["K"], bias=[sign * b for b in d["B"]], e={f"e_{k}": v for k, v in d["e"].items()})

    site = Site(total_field_nt=t["site"]["F_nT"], dip_deg=t["site"]["dip_deg"],
                declination_deg=t["site"]["declination_deg"], gravity_mps2=t["site"]["g_mps2"])
    cal = Calibration(acc=triad(t["acc"], -1.0), mag=triad(t["mag"], 1.0), probe_id="stranger",
                      method="independent simulator's truth", site=site)
    return cal, site


def stranger_files(out, val_stations: int | None = None):
    """The stranger's logs as the tests use them: ``cal`` and ``val`` (the compressed originals),
    ``both`` (one CSV, validation after calibration; only its first ``val_stations`` stations if
    given), ``site`` (its site as our YAML)."""
    from inclinometer_calib.io.probelog import label_runs, read_csv

    out.mkdir(parents=True, exist_ok=True)
    cal, _ = read_csv(STRANGER_DIR / "calibration.csv.gz")
    val, _ = read_csv(STRANGER_DIR / "validation.csv.gz")
    if val_stations is not None:
        end = label_runs(val)[val_stations - 1][1] + 50           # the last hold and half of the move after it
        val = ProbeLog(*(getattr(val, k)[:end] for k in ("t_s", "acc", "mag", "temp_c", "pose", "ref")))
    val.t_s = val.t_s + cal.t_s[-1] + 2.0          # its validation log starts at 0 again
    both = out / "both.csv"
    write_csv(both, ProbeLog.concatenate([cal, val]))
    _, site = stranger_truth()
    site_file = out / "site.yaml"
    site_file.write_text(yaml.safe_dump({"site": site.to_dict()}))
    return {"cal": STRANGER_DIR / "calibration.csv.gz", "val": STRANGER_DIR / "validation.csv.gz",
            "both": both, "site": site_file}

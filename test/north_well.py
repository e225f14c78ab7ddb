"""A survey on a projected site (grid convergence and declination both non-zero), processed along
each north, and a rig receiver's own minimum curvature — for the tests that every output's
azimuth and north/east agree with each other along the one north they declare.

``receiver_positions`` is written here from the textbook form (SPE 84246: the dogleg by the
arc-cosine, the ratio factor ``2/β·tan(β/2)``), not with :mod:`inclinometer_calib.correct.trajectory`
(which takes the dogleg by the arc-sine of the chord), as a receiver of WITS0 or WITSML would.
"""
import copy
import functools
import math

import numpy as np

DECLINATION, CONVERGENCE = 2.5, 0.8
EPOCH_S = 1_795_000_000.0


def projected_site():
    from inclinometer_calib.core.frames import Site

    return Site(total_field_nt=52000.0, dip_deg=50.0, declination_deg=DECLINATION,
                reference={"grid_convergence_deg": CONVERGENCE, "crs": "EPSG:23031"})


def receiver_positions(md, inc_deg, azi_deg):
    """(north, east) m of each station by minimum curvature, tied in at the surface (vertical)."""
    n = e = 0.0
    out = []
    prev = (0.0, 0.0, 0.0)
    for m, i, a in zip(md, inc_deg, azi_deg):
        m0, i0, a0 = prev
        i0, a0, i1, a1 = (math.radians(x) for x in (i0, a0, i, a))
        cos_dl = math.cos(i1 - i0) - math.sin(i0) * math.sin(i1) * (1.0 - math.cos(a1 - a0))
        dl = math.acos(max(-1.0, min(1.0, cos_dl)))
        rf = 1.0 if dl < 1e-9 else 2.0 / dl * math.tan(dl / 2.0)
        n += (m - m0) / 2.0 * (math.sin(i0) * math.cos(a0) + math.sin(i1) * math.cos(a1)) * rf
        e += (m - m0) / 2.0 * (math.sin(i0) * math.sin(a0) + math.sin(i1) * math.sin(a1)) * rf
        out.append((n, e))
        prev = (m, i, a)
    return out


@functools.lru_cache(maxsize=1)
def projected_survey():
    """(site, probe log, its stations, the probe's calibration record) of a simulated 8-station
    well (500–710 m MD, 30 m apart) on :func:`projected_site` (made once per session)."""
    from inclinometer_calib.calibrate import simulate as sim
    from inclinometer_calib.core.coeffs import Calibration
    from inclinometer_calib.io.probelog import segment_stations

    site = projected_site()
    probe = sim.build_probe(3)
    log = sim.run_session(probe, site, sim.well_path_session(8), np.random.default_rng(0), rate_hz=50)
    stations, _ = segment_stations(log)
    return site, log, stations, Calibration(probe.model, site=site)


def projected_well(north):
    """(site, probe log, station dicts) of :func:`projected_survey`'s well processed along
    ``north`` (the pipeline's ``north`` setting); each dict with a ``stamp`` as a bag's has."""
    from inclinometer_calib.correct.pipeline import SurveyProcessor

    site, log, stations, cal = projected_survey()
    proc = SurveyProcessor(calibration=cal, north=north)
    out = [dict(proc.process(st, ref=tuple(st.ref)), stamp=EPOCH_S + st.t_end) for st in copy.deepcopy(stations)]
    return site, log, out

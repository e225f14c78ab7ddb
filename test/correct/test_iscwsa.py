"""ISCWSA MWD position uncertainty (inclinometer_calib.correct.iscwsa): against welleng's implementation of
the same model term by term, against our own physics (a systematic sensor error applied to the
vectors, the well re-surveyed), and with the sensor terms taken from a calibration's uncertainty."""
import math
import warnings

import numpy as np
import pytest

from inclinometer_calib.core import frames
from inclinometer_calib.correct import iscwsa, trajectory
from inclinometer_calib.calibrate import twelve_position as tp
from inclinometer_calib.core.coeffs import Calibration, CoefficientError
from inclinometer_calib.core.errormodel import TriadModel
from inclinometer_calib.core.frames import Site

G, B, DIP, DEC = 9.80665, 50000.0, 65.0, 5.0


def _well():
    """A surface tie-in, then a build-and-turn well 500–3000 m, stations every 30 m."""
    md = np.r_[0.0, np.arange(500.0, 3001.0, 30.0)]
    n = len(md)
    inc = np.r_[0.0, np.linspace(3.0, 88.0, n - 1)]
    azi = np.r_[0.0, np.linspace(20.0, 140.0, n - 1)]
    return md, inc, azi


def _welleng(md, inc, azi):
    welleng = pytest.importorskip("welleng")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        header = welleng.survey.SurveyHeader(G=G, b_total=B, dip=DIP, declination=DEC, azi_reference="true")
        s = welleng.survey.Survey(md=md, inc=inc, azi=azi, header=header, error_model="ISCWSA MWD Rev4")
        return s, {k: np.asarray(e.cov_NEV) for k, e in s.err.errors.errors.items()}


def test_every_rev4_term_equals_wellengs_iscwsa_implementation_on_the_same_well():
    md, inc, azi = _well()
    s, theirs = _welleng(md, inc, azi)
    ours = iscwsa.position_covariance(md, inc, azi, total_gravity_mps2=G, total_field_nt=B, dip_deg=DIP,
                                      declination_deg=DEC, tvd=s.tvd)
    assert set(theirs) == set(iscwsa.REV4_TERMS)        # the same tool model, term for term
    for name, cov in theirs.items():
        scale = np.max(np.abs(cov[1:]))
        assert scale > 0, name
        np.testing.assert_allclose(ours.by_term[name][1:], cov[1:], rtol=0, atol=1e-9 * scale, err_msg=name)
    total = sum(theirs.values())
    np.testing.assert_allclose(ours.cov[1:], total[1:], rtol=0, atol=1e-9 * np.max(np.abs(total)))
    # the figures a survey engineer reads: 1σ lateral at TD of this 3 km well, metres
    assert 5.0 < ours.horizontal_semi_axes()[-1, 0] < 30.0


def test_sensor_terms_from_our_calibration_scale_wellengs_terms_by_the_squared_ratio():
    md, inc, azi = _well()
    s, theirs = _welleng(md, inc, azi)
    cal = Calibration(acc=TriadModel(), mag=TriadModel(), site=Site(B, DIP, DEC, G),
                      uncertainty={"acc": {"bias": [3e-4, 5e-4, 2e-4], "scale": [1e-4, 2e-4, 3e-4]},
                                   "mag": {"bias": [8.0, 6.0, 12.0], "scale": [5e-4, 4e-4, 9e-4]}})
    terms = iscwsa.terms_from_calibration(cal)
    assert terms["MBZ"].magnitude == 12.0 and terms["MBZ"].source == f"calibration {cal.id}"
    assert terms["ABXY-TI1S"].magnitude == pytest.approx(math.sqrt((3e-4 ** 2 + 5e-4 ** 2) / 2))
    assert terms["AMIL"].source == iscwsa.MODEL_NAME          # not a sensor term: the standard's
    ours = iscwsa.position_covariance(md, inc, azi, total_gravity_mps2=G, total_field_nt=B, dip_deg=DIP,
                                      declination_deg=DEC, tvd=s.tvd, terms=terms)
    expected = sum((terms[k].magnitude / iscwsa.REV4_TERMS[k].magnitude) ** 2 * c for k, c in theirs.items())
    np.testing.assert_allclose(ours.cov[1:], expected[1:], rtol=0, atol=1e-9 * np.max(np.abs(expected)))
    default = iscwsa.position_covariance(md, inc, azi, total_gravity_mps2=G, total_field_nt=B, dip_deg=DIP,
                                         declination_deg=DEC, tvd=s.tvd)
    # a well-calibrated probe's sensors add less than the standard's typical tool
    assert ours.sigma()[-1, 1] < default.sigma()[-1, 1]


@pytest.mark.parametrize("term,sensor,axis,size", [
    ("MBZ", "mag", 2, 70.0), ("ABZ", "acc", 2, 0.004), ("MSZ", "mag_scale", 2, 0.0016),
    ("ASZ", "acc_scale", 2, 0.0005)])
def test_a_systematic_sensor_error_moves_the_resurveyed_well_as_the_weighting_function_predicts(term, sensor, axis,
                                                                                                 size):
    # our physics: true vectors from the angles (frames), the error applied to the sensor, the angles
    # recomputed (paper eq. 2) and the well placed by minimum curvature; the model's systematic
    # e-vector sum (σ = the error) must predict the displacement (balanced tangential vs minimum
    # curvature derivatives and second-order terms: a few per cent)
    md, inc, azi = _well()
    site = Site(B, DIP, 0.0, G)
    rng = np.random.default_rng(3)
    tf = rng.uniform(0, 360, len(md))
    g, b = _vectors(site, inc, azi, tf)
    g2, b2 = g.copy(), b.copy()
    if sensor == "mag":
        b2[:, axis] += size
    elif sensor == "acc":
        g2[:, axis] += size
    elif sensor == "mag_scale":
        b2[:, axis] *= 1 + size
    else:
        g2[:, axis] *= 1 + size
    inc2, azi2 = frames.drift_deg(g2), frames.azimuth_deg(g2, b2)
    inc2[0], azi2[0] = 0.0, 0.0                     # the tie-in is not surveyed
    before = trajectory.minimum_curvature(md, inc, azi)
    after = trajectory.minimum_curvature(md, inc2, azi2)
    moved = np.c_[after.north - before.north, after.east - before.east, after.tvd - before.tvd]
    unc = iscwsa.position_covariance(md, inc, azi, total_gravity_mps2=G, total_field_nt=B, dip_deg=DIP,
                                     terms={term: iscwsa.Term(term, size, "", "systematic")})
    predicted = np.sqrt(np.diagonal(unc.cov, axis1=1, axis2=2))        # |systematic sum| per axis
    k = -1
    assert np.linalg.norm(moved[k]) > 0.05
    np.testing.assert_allclose(np.abs(moved[k]), predicted[k], rtol=0.05, atol=0.02 * np.linalg.norm(moved[k]))


def _vectors(site, inc, azi, tf):
    out = [frames.tool_vectors(site, i, a, t) for i, a, t in zip(inc, azi, tf)]
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


def test_a_vertical_station_gives_a_finite_horizontal_error():
    md = np.array([0.0, 100.0, 200.0, 300.0])
    unc = iscwsa.position_covariance(md, [0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 45.0], total_gravity_mps2=G,
                                     total_field_nt=B, dip_deg=DIP)
    assert np.all(np.isfinite(unc.cov)) and unc.sigma()[2, 0] > 0


def test_depths_that_do_not_increase_are_refused():
    with pytest.raises(ValueError, match="increase"):
        iscwsa.position_covariance([0.0, 100.0, 100.0], [0, 1, 2], [0, 0, 0], total_gravity_mps2=G,
                                   total_field_nt=B, dip_deg=DIP)


def test_declination_term_follows_the_site_references_source():
    from inclinometer_calib.core.geomag import site_from_config

    cal = Calibration(acc=TriadModel(), mag=TriadModel())
    loc = {"latitude_deg": 57.1, "longitude_deg": 2.1, "date": "2026-11-23"}
    ifr = site_from_config({**loc, "declination_deg": -0.4})
    wmm = site_from_config(loc)
    assert iscwsa.terms_from_calibration(cal, ifr)["DECG"].magnitude == iscwsa.DECLINATION_SIGMA["ifr"]
    assert iscwsa.terms_from_calibration(cal, wmm)["DECG"].magnitude == iscwsa.DECLINATION_SIGMA["global"]
    # no uncertainty in the record: the standard's sensor terms, and it says so
    plain = iscwsa.terms_from_calibration(cal)
    assert all(t.source == iscwsa.MODEL_NAME for t in plain.values())


MN, MD_ = 27000.0, 40000.0


@pytest.mark.parametrize("method", ["closed form", "least squares"])
def test_twelve_position_uncertainty_is_the_spread_of_repeated_calibrations(method):
    # Monte Carlo: the same probe calibrated 150 times with fresh noise; the reported 1σ of bias and
    # scale must be the spread of the values solved (ratio within the MC's own ±15 %) — for the
    # paper's closed form (all twelve poses) and for the least-squares fit (a pose missing); the
    # closed form is the less efficient of the two, so each needs its own propagation
    rng = np.random.default_rng(11)
    truth = TriadModel(scale=[1.01, 0.99, 1.02], bias=[120.0, -80.0, 40.0],
                       e={"e_xy": 0.002, "e_zx": -0.001, "e_yz": 0.0015})
    ref = np.array([MN, 0.0, MD_])
    noise = 3.0
    errs_b, errs_s, sig_b, sig_s = [], [], [], []
    use = list(tp.POSES) if method == "closed form" else [p for p in tp.POSES if p != 7]
    for k in range(150):
        poses = use * 2
        means = [truth.forward(tp.pose_reference(p, ref)) + rng.normal(0, noise, 3) for p in poses]
        sig = [np.full(3, noise)] * len(poses)
        caps = tp.CaptureSet(poses, means, sig, [f"capture {j}" for j in range(len(poses))])
        sol = tp.solve_triad_captures(caps, MD_, (MN, 0.0), name="magnetometer", unit="nT", scale_range=None)
        assert sol.method.startswith(method)
        u = sol.uncertainty
        c = np.linalg.inv(sol.model.A)
        errs_b.append(c @ (truth.bias - sol.model.bias))       # corrected output at zero true field
        errs_s.append(np.diag(sol.model.A) / np.diag(truth.A) - 1)
        sig_b.append(u["bias"])
        sig_s.append(u["scale"])
    ratio_b = np.std(errs_b, axis=0) / np.mean(sig_b, axis=0)
    ratio_s = np.std(errs_s, axis=0) / np.mean(sig_s, axis=0)
    assert np.all((ratio_b > 0.8) & (ratio_b < 1.15)), ratio_b
    assert np.all((ratio_s > 0.8) & (ratio_s < 1.15)), ratio_s


def test_a_record_keeps_its_uncertainty_and_refuses_a_bad_one(tmp_path):
    unc = {"acc": {"bias": [1e-4, 2e-4, 3e-4], "scale": [1e-5, 2e-5, 3e-5], "basis": "test"},
           "mag": {"bias": [2.0, 3.0, 4.0], "scale": [1e-4, 1e-4, 2e-4]}}
    cal = Calibration(acc=TriadModel(), mag=TriadModel(), uncertainty=unc)
    back = Calibration.from_record(cal.to_record())
    assert back.uncertainty["mag"]["bias"] == [2.0, 3.0, 4.0] and back.uncertainty["acc"]["basis"] == "test"
    assert back.id == Calibration(acc=TriadModel(), mag=TriadModel()).id     # not part of what the record means
    rec = cal.to_record()
    rec["magnetometer"]["uncertainty"]["bias"] = [2.0, -3.0, 4.0]
    with pytest.raises(CoefficientError, match="magnetometer.uncertainty.bias"):
        Calibration.from_record(rec)

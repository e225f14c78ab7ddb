"""Twelve-position solution (Table 1; eqs. 5-16) and inversion (17-32)."""
import numpy as np
import pytest

from inclinometer_calib import simulate as sim
from inclinometer_calib import twelve_position as tp
from inclinometer_calib.errormodel import E_TERMS, TriadModel
from inclinometer_calib.frames import Site
from inclinometer_calib.probelog import segment_stations

MN, ME, MD = 31000.0, -2500.0, 36000.0
TABLE1_M = {  # Table 1's M columns, typed from the paper
    1: (MD, -ME, MN), 2: (MD, ME, -MN), 3: (-MD, ME, MN), 4: (-MD, -ME, -MN),
    5: (ME, MD, MN), 6: (-ME, MD, -MN), 7: (ME, -MD, -MN), 8: (-ME, -MD, MN),
    9: (MN, ME, MD), 10: (-MN, -ME, MD), 11: (-MN, ME, -MD), 12: (MN, -ME, -MD),
}


@pytest.mark.parametrize("pose", tp.POSES)
def test_pose_matrices_reproduce_table1_columns_and_are_rotations(pose):
    r = tp.pose_matrix(pose)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(tp.pose_reference(pose, [MN, ME, MD]), TABLE1_M[pose])


def _random_triad(rng):
    return TriadModel(scale=1 + rng.normal(0, 0.05, 3), bias=rng.normal(0, 300, 3),
                      e={k: rng.normal(0, 0.04) for k in E_TERMS})


def test_noiseless_recovery_of_known_parameters_to_1e_9():
    rng = np.random.default_rng(11)
    truth = _random_triad(rng)
    h = np.array([truth.forward(TABLE1_M[p]) for p in tp.POSES])
    sol = tp.solve_triad({p: [h[i]] for i, p in enumerate(tp.POSES)}, MD)
    for k, v in truth.parameters().items():
        assert sol.model.parameters()[k] == pytest.approx(v, abs=1e-9), k
    np.testing.assert_allclose(sol.residuals, 0, atol=1e-8)
    # the horizontal reference components, never used by eqs. 5-16, are recovered for the residuals
    np.testing.assert_allclose(sol.reference_ned, [MN, ME, MD], atol=1e-7)


def test_horizontal_components_and_stand_rotation_do_not_matter():
    """'No north reference needed': the same outputs' parameters for any Mn, Me."""
    rng = np.random.default_rng(12)
    truth = _random_triad(rng)
    for mn, me in ((0.0, 0.0), (20000.0, 15000.0), (-5000.0, 30000.0)):
        h = [truth.forward(tp.pose_reference(p, [mn, me, MD])) for p in tp.POSES]
        sol = tp.solve_triad({p: [h[i]] for i, p in enumerate(tp.POSES)}, MD)
        np.testing.assert_allclose(sol.model.A, truth.A, atol=1e-12)


def test_several_rounds_are_all_used_and_their_spread_reported():
    rng = np.random.default_rng(13)
    truth = _random_triad(rng)
    rounds = {p: [truth.forward(TABLE1_M[p]) + rng.normal(0, 5.0, 3) for _ in range(4)] for p in tp.POSES}
    sol = tp.solve_triad(rounds, MD)
    means = np.array([np.mean(rounds[p], axis=0) for p in tp.POSES])
    np.testing.assert_allclose(sol.pose_means, means)
    np.testing.assert_allclose(sol.round_spread, [np.std(rounds[p], axis=0, ddof=1) for p in tp.POSES])
    assert list(sol.rounds) == [4] * 12
    # the solution of the mean equals the mean of the per-round solutions (eqs. 5-16 are linear in H)
    per_round = [tp.solve_closed_form(np.array([rounds[p][k] for p in tp.POSES]), MD).A for k in range(4)]
    np.testing.assert_allclose(sol.model.A, np.mean(per_round, axis=0), atol=1e-12)


def test_single_round_spread_is_nan():
    truth = _random_triad(np.random.default_rng(14))
    sol = tp.solve_triad({p: [truth.forward(TABLE1_M[p])] for p in tp.POSES}, MD)
    assert np.all(np.isnan(sol.round_spread))


def test_missing_pose_is_named():
    truth = _random_triad(np.random.default_rng(15))
    data = {p: [truth.forward(TABLE1_M[p])] for p in tp.POSES if p not in (4, 9)}
    with pytest.raises(ValueError, match=r"pose\(s\) \[4, 9\] missing"):
        tp.solve_triad(data, MD)


def test_non_finite_pose_mean_is_named():
    h = np.ones((12, 3))
    h[6, 1] = np.nan
    with pytest.raises(ValueError, match=r"pose\(s\) \[7\]"):
        tp.solve_closed_form(h, MD)


def test_printed_closed_forms_agree_with_the_inverse_except_eq21_and_eq23():
    """Eqs. 20-32 as printed vs the matrix inverse, over random parameters: every coefficient
    agrees except B1 (eq. 21: e_zx·e_zy should read e_zx·e_yz) and D1 (eq. 23)."""
    rng = np.random.default_rng(16)
    for _ in range(20):
        m = _random_triad(rng)
        c, d = tp.paper_correction_closed_form(m)
        agree_c = np.isclose(c, m.correction_matrix, rtol=1e-12, atol=1e-14)
        agree_d = np.isclose(d, m.correction_offset, rtol=1e-12, atol=1e-10)
        expected_c = np.ones((3, 3), bool)
        expected_c[0, 1] = False
        np.testing.assert_array_equal(agree_c, expected_c)
        np.testing.assert_array_equal(agree_d, [False, True, True])
        # with the typo mended, B1 agrees: (e_yx - e_zx e_yz) / (Ky T)
        e = m.e
        t = -np.linalg.det(m.E)  # eq. 32's T is minus det(E)
        b1 = (e["e_yx"] - e["e_zx"] * e["e_yz"]) / (m.scale[1] * t)
        assert b1 == pytest.approx(m.correction_matrix[0, 1], rel=1e-12)
        # and D1 follows the pattern D_i = -(A_i Bx + B_i By + C_i Bz) like D2, D3
        assert -m.correction_matrix[0] @ m.bias == pytest.approx(m.correction_offset[0])


def test_simulated_twelve_pose_log_recovers_the_probe_to_noise_level():
    site = Site()
    probe = sim.build_probe(seed=5, noise_acc=0.0, noise_mag=0.0)
    log = sim.run_session(probe, site, sim.twelve_pose_session(), np.random.default_rng(0), rate_hz=50)
    stations, problems = segment_stations(log)
    assert problems == [] and len(stations) == 12
    res = tp.solve_stations(stations, site)
    for k, v in probe.acc.parameters().items():
        assert res.acc.model.parameters()[k] == pytest.approx(v, abs=1e-9), k
    for k, v in probe.mag.parameters().items():
        assert res.mag.model.parameters()[k] == pytest.approx(v, abs=1e-9), k
    imp = res.implied_site()
    assert imp["total_field"] == pytest.approx(site.total_field_nt, rel=1e-9)
    assert imp["dip_deg"] == pytest.approx(site.dip_deg, abs=1e-8)


def test_identify_pose_uses_the_field_to_resolve_the_roll():
    site = Site()
    for p in tp.POSES:
        g = tp.pose_reference(p, site.gravity_ned())
        b = tp.pose_reference(p, site.field_ned())
        pose, misfit = tp.identify_pose_with_field(g, b, site.field_ned())
        assert pose == p and misfit < 1e-6
    assert tp.identify_pose_with_field([1.0, 1.0, 1.0], [1.0, 0, 0], site.field_ned())[0] is None


def test_ill_conditioned_solution_is_refused():
    # two sensor axes (nearly) parallel: K·E is close to singular
    a = np.array([[1.0, 0.999, 0.0], [0.999, 1.0, 0.0], [0.0, 0.0, 1.0]])
    truth = TriadModel.from_matrix(a, np.zeros(3))
    h = np.array([truth.forward(TABLE1_M[p]) for p in tp.POSES])
    with pytest.raises(ValueError, match="singular or ill-conditioned \\(condition number"):
        tp.solve_triad({p: [h[i]] for i, p in enumerate(tp.POSES)}, MD)


def test_pose_far_off_the_model_is_refused_naming_it():
    truth = TriadModel(scale=np.ones(3), bias=np.zeros(3), e={})
    data = {p: [truth.forward(TABLE1_M[p])] for p in tp.POSES}
    data[11] = [truth.forward(TABLE1_M[12])]      # pose 11 captured in pose 12's orientation
    with pytest.raises(ValueError, match="magnetometer: pose 1[12] does not fit the twelve-pose model"):
        tp.solve_triad(data, MD, name="magnetometer", unit="nT")

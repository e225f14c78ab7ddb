"""Twelve-position solution (Table 1; eqs. 5-16) and inversion (17-32)."""
import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.calibrate import twelve_position as tp
from inclinometer_calib.core.errormodel import E_TERMS, TriadModel
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.probelog import segment_stations

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
    from inclinometer_calib.calibrate.capture import CaptureSession

    site = Site()
    probe = sim.build_probe(seed=5, noise_acc=0.0, noise_mag=0.0)
    log = sim.run_session(probe, site, sim.twelve_pose_session(), np.random.default_rng(0), rate_hz=50)
    stations, problems = segment_stations(log)     # default detector: noise from the data, even none
    assert problems == [] and len(stations) == 12
    session = CaptureSession(site=site)
    for st in stations:
        session.offer(st)
    res = session.result
    assert session.state == "done" and res.acc.method.startswith("closed form")
    for k, v in probe.acc.parameters().items():
        assert res.acc.model.parameters()[k] == pytest.approx(v, abs=1e-9), k
    for k, v in probe.mag.parameters().items():
        assert res.mag.model.parameters()[k] == pytest.approx(v, abs=1e-9), k
    imp = res.implied_site()
    assert imp["total_field"] == pytest.approx(site.total_field_nt, rel=1e-9)
    assert imp["dip_deg"] == pytest.approx(site.dip_deg, abs=1e-8)


def _captures(truth, poses, ref, noise=0.0, rng=None, rounds=1):
    rng = rng or np.random.default_rng(0)
    ps = [p for _ in range(rounds) for p in poses]
    means = [truth.forward(tp.pose_reference(p, ref)) + rng.normal(0, noise, 3) if noise else
             truth.forward(tp.pose_reference(p, ref)) for p in ps]
    sig = [np.full(3, max(noise, 1e-6 * np.linalg.norm(ref)))] * len(ps)
    return tp.CaptureSet(ps, means, sig, [f"pose {p} (capture {k})" for k, p in enumerate(ps)])


def test_least_squares_over_captures_equals_the_closed_form_and_needs_no_complete_set():
    rng = np.random.default_rng(21)
    truth = _random_triad(rng)
    full = tp.fit_triad(*(lambda c: (c.poses, c.means, c.sigmas))(_captures(truth, tp.POSES, [MN, ME, MD])),
                        MD, (MN, 0.0))
    np.testing.assert_allclose(full.model.A, truth.A, atol=1e-9)
    np.testing.assert_allclose(full.reference, [MN, ME, MD], atol=1e-6)   # the stand's horizontal field
    for missing in (5, 9, 12):
        caps = _captures(truth, [p for p in tp.POSES if p != missing], [MN, ME, MD])
        sol = tp.solve_triad_captures(caps, MD, (MN, 0.0), name="magnetometer", unit="nT", scale_range=None)
        assert "least squares" in sol.method and np.all(np.isnan(sol.residuals[missing - 1]))
        np.testing.assert_allclose(sol.model.A, truth.A, atol=1e-9)


def test_a_capture_that_does_not_fit_is_left_out_and_named():
    rng = np.random.default_rng(22)
    truth = _random_triad(rng)
    caps = _captures(truth, tp.POSES, [MN, ME, MD], noise=2.0, rng=rng, rounds=2)
    caps.means[3] = caps.means[3] + np.array([0.0, 400.0, 0.0])      # one capture 0.8° off
    sol = tp.solve_triad_captures(caps, MD, (MN, 0.0), name="magnetometer", unit="nT", scale_range=None)
    assert len(sol.left_out) == 1 and "pose 4 (capture 3)" in sol.left_out[0]
    assert sol.method.startswith("closed form") and sol.rounds[3] == 1
    assert sol.z_rms < 1.5


def test_a_pose_wrong_in_every_round_is_left_out_as_a_pose():
    # both rounds' captures of pose 11 taken in pose 12's orientation: each supports the other,
    # only leaving the pose out shows it
    rng = np.random.default_rng(23)
    truth = _random_triad(rng)
    caps = _captures(truth, tp.POSES, [MN, ME, MD], noise=2.0, rng=rng, rounds=2)
    for k, p in enumerate(caps.poses):
        if p == 11:
            caps.means[k] = truth.forward(TABLE1_M[12]) + rng.normal(0, 2.0, 3)
    sol = tp.solve_triad_captures(caps, MD, (MN, 0.0), name="magnetometer", unit="nT", scale_range=None)
    assert len(sol.left_out) == 1 and "pose 11 (all 2 captures)" in sol.left_out[0]
    assert "least squares" in sol.method
    np.testing.assert_allclose(sol.model.A, truth.A, atol=2e-4)


def test_random_stand_pose_errors_leave_every_capture_in_and_are_reported_as_excess_residual():
    from scipy.spatial.transform import Rotation

    from inclinometer_calib.core.frames import Site as S

    rng = np.random.default_rng(24)
    site = S()
    truths = {"acc": TriadModel(scale=[1.001, 0.998, 1.0], bias=[0.02, -0.01, 0.03], e={"e_xy": 0.01}),
              "mag": _random_triad(rng)}
    refs = {"acc": site.gravity_ned(), "mag": site.field_ned()}
    noise = {"acc": 0.0002, "mag": 2.0}
    ps = list(tp.POSES) * 2
    errs = [Rotation.from_rotvec(np.radians(rng.normal(0, 0.1, 3))).as_matrix() for _ in ps]  # stand 0.1° off
    caps = {}
    for k in ("acc", "mag"):
        means = [truths[k].forward(e.T @ tp.pose_reference(p, refs[k])) + rng.normal(0, noise[k], 3)
                 for p, e in zip(ps, errs)]
        caps[k] = tp.CaptureSet(ps, means, [np.full(3, noise[k])] * len(ps), [f"pose {p}" for p in ps])
    res = tp.solve_captures(caps["acc"], caps["mag"], site)
    assert res.acc.left_out == [] and res.mag.left_out == []
    assert res.acc.z_rms > 10 and res.mag.z_rms > 10
    assert any("magnetometer: the residuals are" in n and "lab diagnose" in n for n in res.notes)


def test_captures_far_off_the_model_everywhere_refuse_the_solve_naming_the_worst():
    # a stand whose poses are off by a degree at random: nothing to leave out, nothing to keep
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(25)
    truth = _random_triad(rng)
    ref = np.array([MN, ME, MD])
    ps = list(tp.POSES) * 2
    means = [truth.forward(Rotation.from_rotvec(np.radians(rng.normal(0, 1.0, 3))).as_matrix().T
                           @ tp.pose_reference(p, ref)) for p in ps]
    caps = tp.CaptureSet(ps, means, [np.full(3, 2.0)] * len(ps), [f"pose {p} (capture {k})" for k, p in enumerate(ps)])
    with pytest.raises(ValueError, match=r"magnetometer: the captures do not fit the twelve-pose model even after "
                                         r"screening: residual \d\.\d+° RMS .* worst pose \d+ \(capture \d+\) "
                                         r"\d\.\d\d°.*no coefficients written"):
        tp.solve_triad_captures(caps, MD, (MN, 0.0), name="magnetometer", unit="nT", scale_range=None)


@pytest.mark.parametrize("heading", [0.0, 35.0, -80.0, 100.0, 180.0])
def test_identify_pose_takes_the_pair_from_gravity_and_the_member_from_the_stands_heading(heading):
    # a stand turned `heading` from magnetic north: the field's heading in the stand frame is -heading
    site = Site()
    field = Site(site.total_field_nt, site.dip_deg, -heading).field_ned()
    for p in tp.POSES:
        g = tp.pose_reference(p, site.gravity_ned())
        b = tp.pose_reference(p, field)
        pose, misfit = tp.identify_pose(g, b, heading_deg=-heading)
        assert pose == p and misfit < 1e-6
        assert tp.field_heading_deg(p, b) == pytest.approx(tp._wrap180(-heading), abs=1e-9)
    assert tp.identify_pose([1.0, 1.0, 1.0], [1.0, 0, 0])[0] is None


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


def test_an_accelerometer_axis_never_vertical_is_not_determined_though_a_tilted_stand_gives_rank_14():
    rng = np.random.default_rng(26)
    truth = TriadModel(scale=[1.01, 0.99, 1.0], bias=[0.05, -0.02, 0.01], e={"e_xy": 0.01, "e_zx": -0.02})
    tilted = [0.05, 0.03, 9.8]                     # the stand 0.3° off level: r_N, r_E tiny, not 0
    caps = _captures(truth, [p for p in tp.POSES if p > 4], tilted, noise=0.0003, rng=rng, rounds=2)
    fit = tp.fit_triad(caps.poses, caps.means, caps.sigmas, 9.8, (0.0, 0.0))
    assert fit.weak == "x" and fit.model is None and fit.rank < 14
    with pytest.raises(ValueError, match="tool axis x is never vertical \\(poses 1-4\\)"):
        tp.solve_triad_captures(caps, 9.8, (0.0, 0.0), name="accelerometer", unit="m/s^2")

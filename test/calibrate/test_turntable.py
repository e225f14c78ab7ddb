"""The patent's turntable calibration (:mod:`inclinometer_calib.calibrate.turntable`) against the simulator's
truth: every parameter within 3σ, the closed form against the joint fit, the derivation against the
fitted sinusoids, nuisances it must not need, and bad logs refused with the mount and step named."""
import json

import numpy as np
import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.calibrate import turntable as tt
from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.coeffs import Calibration
from inclinometer_calib.core.frames import Site
from inclinometer_calib.io.probelog import write_csv

SITE = Site()
MISALIGNED = "misalignment:mag=0.004,-0.003,0.005"


def _probe(seed=3):
    return sim.build_probe(seed, [MISALIGNED], noise_mag=20.0)


def _truth(probe):
    """M and bias of the probe's magnetometer: its output for unit inputs (the model is linear)."""
    f = lambda v: probe.model.forward(np.zeros((1, 3)), np.atleast_2d(v), 25.0, 0.0, role="cal")[1][0]  # noqa: E731
    h0 = f(np.zeros(3))
    return np.stack([f(np.eye(3)[j]) - h0 for j in range(3)], axis=1), h0


def _steps(probe, seed=1, **kw):
    log = sim.run_turntable(probe, SITE, sim.turntable_session(**kw), np.random.default_rng(seed))
    steps, _ = tt.steps_from_log(log, "sim")
    return steps, log


def _within(est, sd, true, z=3.0):
    est, sd, true = map(np.asarray, (est, sd, true))
    return np.all(np.abs(est - true) <= z * sd), np.abs(est - true) / sd


def test_every_parameter_is_recovered_within_three_sigma():
    probe = _probe()
    m_true, b_true = _truth(probe)
    truth = tt.angles_from_matrix(m_true)
    res = tt.solve(_steps(probe)[0], SITE.total_field_nt)
    p = res.parameters()
    for name, sd, true in (("k", "k_std", truth["k"]), ("bias_nT", "bias_std", b_true),
                           ("alpha_deg", "alpha_std", truth["alpha_deg"]), ("beta_deg", "beta_std", truth["beta_deg"])):
        ok, z = _within(p[name], p[sd], true)
        assert ok, (name, z)
    ok, z = _within(p["misalignment_rad"], p["misalignment_std"] + 1e-12, truth["misalignment_rad"])
    assert ok, z
    assert res.residual_rms_nt == pytest.approx(20.0, rel=0.05)       # the white noise, nothing else


def test_without_a_site_the_sensitivities_are_relative_and_the_axes_the_same():
    probe = _probe()
    m_true, _ = _truth(probe)
    truth = tt.angles_from_matrix(m_true)
    res = tt.solve(_steps(probe)[0], None)
    p = res.parameters()
    assert np.mean(p["k"]) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(p["k"] / np.mean(p["k"]), truth["k"] / np.mean(truth["k"]), rtol=1e-4)
    assert _within(p["alpha_deg"], p["alpha_std"], truth["alpha_deg"])[0]
    assert not res.scale_known and any("relative" in m for m in res.messages)


def test_the_closed_form_agrees_with_the_joint_refinement_and_the_derivation_with_the_fit():
    probe = _probe()
    steps, _ = _steps(probe)
    res = tt.solve(steps, SITE.total_field_nt)
    m0, b0 = res.closed
    sd = np.sqrt(np.diag(res.cov))
    assert np.all(np.abs(m0 - res.matrix).ravel() <= 4 * sd[:9] + 1e-7)
    assert np.all(np.abs(b0 - res.bias) <= 4 * sd[9:12])
    # the sinusoids predicted from the fitted parameters by the derivation match those fitted
    for s in res.sinusoids:
        a, c, cc = tt.predicted_sinusoid(s.mount, s.axis, res.matrix, res.bias, res.nuisance[s.mount])
        amp_sd = max(s.std["A"], 1e-6)
        assert abs(a - s.a) < 4 * amp_sd and abs(c - s.c) < 4 * amp_sd and abs(cc - s.C) < 4 * s.std["C"], s


@pytest.mark.parametrize("kw", [{"tilt_deg": 2.0}, {"steps": 9}, {"angles_deg": [0, 20, 65, 100, 150, 200, 230, 300, 330]}])
def test_a_table_that_is_not_level_or_unequal_steps_change_nothing(kw):
    probe = _probe(5)
    m_true, b_true = _truth(probe)
    truth = tt.angles_from_matrix(m_true)
    res = tt.solve(_steps(probe, **kw)[0], SITE.total_field_nt)
    p = res.parameters()
    assert _within(p["alpha_deg"], p["alpha_std"], truth["alpha_deg"])[0]
    assert _within(p["bias_nT"], p["bias_std"], b_true)[0]
    assert res.residual_rms_nt == pytest.approx(20.0, rel=0.05)


def test_without_table_angles_the_steps_are_measured_by_the_probe():
    probe = _probe()
    m_true, b_true = _truth(probe)
    steps, _ = _steps(probe, angles_deg=[0, 25, 70, 100, 150, 190, 235, 280, 320])
    for s in steps:
        s.table_deg = float("nan")
    res = tt.solve(steps, SITE.total_field_nt)
    p = res.parameters()
    assert _within(p["alpha_deg"], p["alpha_std"], tt.angles_from_matrix(m_true)["alpha_deg"])[0]
    assert _within(p["bias_nT"], p["bias_std"], b_true)[0]


def test_a_step_off_its_set_angle_is_reported():
    probe = _probe()
    steps, _ = _steps(probe)
    steps[4].table_deg += 0.5            # the log says 0.5° more than the table was at
    off = tt.check_angles(steps, SITE.total_field_nt)
    assert len(off) == 1 and off[0][0] == steps[4].where and off[0][1] == pytest.approx(-0.5, abs=0.05)


def test_an_aligned_axis_has_no_beta():
    probe = sim.build_probe(3, noise_mag=20.0, severity=0.0)   # a perfect probe: α = 0
    res = tt.solve(_steps(probe)[0], SITE.total_field_nt)
    p = res.parameters()
    assert not any(p["beta_defined"]) and np.all(np.isnan(p["beta_deg"]))
    assert all(v is None for v in res.to_json()["mag"]["beta_deg"])


def _bad(log, tmp_path, capsys):
    path = tmp_path / "tt.csv"
    write_csv(path, log)
    code = main(["turntable", str(path), "-o", str(tmp_path / "r.yaml")])
    return code, capsys.readouterr().err


def test_bad_logs_are_refused_naming_the_mount_and_the_step(tmp_path, capsys):
    probe = _probe()
    _, log = _steps(probe)
    # a mounting missing
    cut = log.mount != "yz"
    sub = type(log)(log.t_s[cut], log.acc[cut], log.mag[cut], log.temp_c[cut], log.pose[cut], log.ref[cut],
                    mount=log.mount[cut], table_deg=log.table_deg[cut])
    code, err = _bad(sub, tmp_path, capsys)
    assert code != 0 and "mount yz is missing" in err
    # fewer than 8 steps
    short = sim.run_turntable(probe, SITE, sim.turntable_session(steps=6), np.random.default_rng(2))
    code, err = _bad(short, tmp_path, capsys)
    assert code != 0 and "6 steps" in err and "at least 8" in err
    # mixed-up mount labels: the xy and xz labels swapped
    swapped = read_csv_copy(log)
    swapped.mount = np.where(log.mount == "xy", "xz", np.where(log.mount == "xz", "xy", log.mount))
    code, err = _bad(swapped, tmp_path, capsys)
    assert code != 0 and "mixed up" in err and "mount xy" in err
    # a step in which the probe moved
    moved = read_csv_copy(log)
    k = np.flatnonzero(moved.mount == "xz")[40]
    moved.mag[k:k + 40] += np.linspace(0, 3000, 40)[:, None]
    code, err = _bad(moved, tmp_path, capsys)
    assert code != 0 and "moved during the step" in err and "mount xz" in err


def read_csv_copy(log):
    return type(log)(log.t_s.copy(), log.acc.copy(), log.mag.copy(), log.temp_c.copy(), log.pose.copy(),
                     log.ref.copy(), mount=log.mount.copy(), table_deg=log.table_deg.copy())


def test_simulate_then_turntable_gives_a_record_that_corrects_a_survey_to_the_true_level(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out), "--seed", "4", "--effect", MISALIGNED, "--turntable", "12",
                 "--rate", "50", "--no-survey-effects"]) == 0
    assert main(["twelve-position", str(out / "cal.csv"), "--site", str(out / "site.yaml"), "-o",
                 str(out / "tp.yaml")]) == 0
    capsys.readouterr()
    assert main(["turntable", str(out / "turntable.csv"), "--site", str(out / "site.yaml"), "--acc",
                 str(out / "tp.yaml"), "-o", str(out / "tt.yaml"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["mag"]) >= {"k", "bias_nT", "alpha_deg", "beta_deg", "misalignment_rad"}
    assert len(doc["sinusoids"]) == 9 and {"mount", "axis", "A", "b_deg", "C", "rms"} <= set(doc["sinusoids"][0])
    assert np.array(doc["mag"]["misalignment_rad"]).shape == (3, 3) and doc["residual_rms_nT"] < 25
    rec = Calibration.load(out / "tt.yaml")
    assert rec.method.startswith("turntable + ") and rec.diagnostics["turntable"]["mag"]["alpha_deg"] == doc["mag"]["alpha_deg"]
    az = {}
    for name in ("tt", "truth_coeffs"):
        assert main(["correct", str(out / "val.csv"), "--coeffs", str(out / f"{name}.yaml"), "--json"]) == 0
        az[name] = json.loads(capsys.readouterr().out)["azimuth_rms_deg"]
    assert az["tt"] <= 1.2 * az["truth_coeffs"], az


def test_the_live_session_recognises_the_mounts_shows_progress_and_solves_without_labels():
    from inclinometer_calib.io.probelog import segment_stations

    probe = _probe()
    m_true, b_true = _truth(probe)
    _, log = _steps(probe)
    stations, _ = segment_stations(log, use_labels=False)
    session = tt.TurntableSession(site=SITE)
    states = []
    for st in stations:
        assert session.offer(st) == "accepted"
        states.append(session.state)
    # solved once the third mount's steps cover the turn (11 of 12 steps: 330°), again at the end with all
    assert 24 + tt.MIN_STEPS - 1 <= states.index("done") < len(stations) - 1
    session.finish()
    assert session.solves == 2 and session.result.step_angles_deg.shape == (36,)
    prog = session.progress()
    assert all(ok and n == 12 and cov > 320 for n, cov, ok in prog.values()), prog
    assert "mount yz: 12 steps" in session.progress_text()
    p = session.result.parameters()
    assert _within(p["alpha_deg"], p["alpha_std"], tt.angles_from_matrix(m_true)["alpha_deg"])[0]
    assert _within(p["bias_nT"], p["bias_std"], b_true)[0]
    assert session.calibration.method == "turntable" and session.calibration.not_identifiable
    # an incomplete run says which mount is short
    short = tt.TurntableSession(site=SITE)
    for st in stations[:30]:
        short.offer(st)
    short.finish()
    assert short.state == "error" and "mount yz: 6 steps" in short.message

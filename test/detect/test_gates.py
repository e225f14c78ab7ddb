"""Acceptance gates of a station: creep, unsteady, flat, implausible |g|; saturation named."""
import numpy as np
import pytest

from inclinometer_calib.detect.gates import GateLimits, SaturationMonitor, apply_gates, station_findings
from inclinometer_calib.core.station import Station

G = np.array([0.0, 0.0, 9.80665])
B = np.array([35000.0, 0.0, 35000.0])


def _station(**kw):
    n = kw.pop("n", 300)
    base = dict(t_start=0.0, t_end=3.0, n=n, g=G.copy(), b=B.copy(), g_std=np.full(3, 0.005),
                b_std=np.full(3, 30.0), g_noise=np.full(3, 0.005), b_noise=np.full(3, 30.0),
                t_std=3.0 / np.sqrt(12), pose=9)
    base.update(kw)
    return Station(**base)


def test_a_still_station_passes_every_gate():
    assert station_findings(_station(), gravity_mps2=9.80665) == []


def test_a_creep_of_a_tenth_of_a_degree_is_named_with_the_turn_and_rate():
    rate = np.array([9.80665 * np.radians(0.1) / 3.0, 0.0, 0.0])   # gravity tilts 0.1° over 3 s
    f = station_findings(_station(g_rate=rate))
    assert [x.code for x in f] == ["creep"] and f[0].sensors == ("acc", "mag")
    assert "turned 0.100° during the 3.00 s hold" in f[0].message and "pose 9" in f[0].message


def test_a_trend_within_the_noise_or_below_the_limit_is_not_a_creep():
    tiny = np.array([9.80665 * np.radians(0.02) / 3.0, 0.0, 0.0])  # 0.02° < 0.05°
    assert station_findings(_station(g_rate=tiny)) == []
    few = _station(n=5, t_end=0.04, t_std=0.015, g_rate=np.array([0.5, 0.0, 0.0]))  # 5 samples: not significant
    assert all(x.code != "creep" for x in station_findings(few))


def test_a_magnetometer_turn_alone_is_a_creep_too():
    rate = np.array([0.0, 35000.0 * np.radians(0.2) / 3.0, 0.0])    # a turn about the vertical
    assert [x.code for x in station_findings(_station(b_rate=rate))] == ["creep"]


def test_scatter_far_above_the_noise_is_unsteady():
    f = station_findings(_station(b_std=np.array([30.0, 90.0, 30.0])))
    assert [x.code for x in f] == ["unsteady"] and "magnetometer y scatters 3.0× its noise" in f[0].message


def test_a_flat_axis_refuses_that_sensor_only_and_names_its_level():
    f = station_findings(_station(g=np.array([-9.6, 0.1, 1.9]), g_std=np.array([0.0, 0.005, 0.005])))
    assert [x.code for x in f] == ["flat"] and f[0].sensors == ("acc",)
    assert "accelerometer x reads a constant 9.6000 m/s^2" in f[0].message and f[0].axis == "accelerometer x"


def test_an_implausible_raw_gravity_refuses_the_accelerometer():
    f = station_findings(_station(g=G * 0.85), gravity_mps2=9.80665)
    assert [x.code for x in f] == ["gravity"] and "-15%" in f[0].message


def test_apply_gates_records_the_outcome_once():
    st = _station(g_rate=np.array([0.01, 0.0, 0.0]))
    assert [x.code for x in apply_gates(st)] == ["creep"]
    assert st.moved and st.gated and len(st.warnings) == 1
    assert apply_gates(st) == [] and len(st.warnings) == 1


def test_saturation_is_named_when_the_same_level_repeats():
    mon = SaturationMonitor()
    out = []
    for _ in range(3):
        st = _station(g=np.array([-9.6, 0.1, 1.9]), g_std=np.array([0.0, 0.005, 0.005]))
        out += mon.add(st, station_findings(st))
    assert len(out) == 1 and "accelerometer x is flat at 9.6000 m/s^2 in 2 stations: it saturates" in out[0]


def test_limits_are_settings():
    rate = np.array([9.80665 * np.radians(0.1) / 3.0, 0.0, 0.0])
    assert station_findings(_station(g_rate=rate), GateLimits(max_creep_deg=0.2)) == []
    with pytest.raises(TypeError):
        GateLimits(0.1, 1.5, 0.1, 5)


def test_a_magnetometer_that_changes_the_total_field_while_the_accelerometer_holds_is_a_transient_not_motion():
    """A fluxgate settling after a move: its x axis drifts by 90 nT over the hold while gravity does
    not move — the field's direction turns 0.074°, as a creep would, but |B| changes by 64 nT, which
    no rigid rotation does. Named, only the magnetometer refused, the station not 'moved'."""
    st = _station(b_rate=np.array([30.0, 0.0, 0.0]))                 # +30 nT/s on the sensor's x axis
    f = station_findings(st)
    assert [x.code for x in f] == ["transient"] and f[0].sensors == ("mag",), f
    assert "not motion" in f[0].message and "|B| changed by +63.6 nT" in f[0].message
    apply_gates(st)
    assert st.unusable == ("mag",) and not st.moved


def test_a_rotation_about_the_vertical_keeps_the_invariants_and_stays_a_creep():
    rate = np.cross([0.0, 0.0, np.radians(0.2) / 3.0], B)          # the field turned about gravity
    f = station_findings(_station(b_rate=rate))
    assert [x.code for x in f] == ["creep"], f
    # and a moving accelerometer makes any magnetometer trend motion, not a transient
    tilt = np.array([9.80665 * np.radians(0.1) / 3.0, 0.0, 0.0])
    codes = [x.code for x in station_findings(_station(g_rate=tilt, b_rate=np.array([30.0, 0.0, 0.0])))]
    assert "creep" in codes and "transient" not in codes


def _settling_hold(tau_s, amplitude, seconds=6.0, rate_hz=50.0, seed=0):
    """One hold of a probe whose magnetometer settles after the move (``amplitude`` nT at the
    hold's first sample, decaying with ``tau_s``), found by the detector from its samples."""
    from inclinometer_calib.detect.streaming import StaticDetector

    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t = np.arange(n) / rate_hz
    f = -G + rng.normal(0, 0.004, (n, 3))                              # REP-145 specific force at rest
    m = B + rng.normal(0, 25.0, (n, 3)) + np.outer(np.exp(-t / tau_s), amplitude)
    det = StaticDetector(noise_acc=0.004, noise_mag=25.0, max_duration_s=60.0)
    (st,) = list(det.run(t, f, m)) + list(det.flush())
    st.b_noise, st.g_noise = np.full(3, 25.0), np.full(3, 0.004)
    return st


def test_a_magnetometer_that_settles_after_the_move_is_measured_and_its_hold_kept_from_where_it_settled():
    """A fluxgate settling after every move (issue 23): the gates measure the time constant from
    the hold's shape, leave out the start until no transient is left, say so with the figures,
    and keep the hold — its magnetometer mean then within the noise of the settled field."""
    st = _settling_hold(1.2, np.array([250.0, -180.0, 120.0]))
    n0 = st.n
    found = apply_gates(st)
    assert [f.code for f in found] == ["settled"], [f.message for f in found]
    tau = float(found[0].message.split("time constant of ")[1].split(" s")[0])
    assert abs(tau - 1.2) < 0.25
    assert not st.unusable and not st.moved and st.n < n0 and st.settled_s > 1.0
    assert "not motion" in found[0].message and f"({st.n} of {n0} samples kept)" in found[0].message
    se = 25.0 / np.sqrt(st.n)
    assert np.all(np.abs(st.b - B) < 5 * se), (st.b - B) / se
    assert station_findings(st) == []                                 # what is kept passes every gate


def test_a_drift_that_never_settles_or_a_hold_too_short_to_settle_stays_refused():
    slow = _settling_hold(200.0, np.array([0.0, 0.0, 1500.0]))        # a drift, not a settling
    found = apply_gates(slow)
    assert "settled" not in [f.code for f in found] and slow.unusable == ("mag",), [f.message for f in found]
    short = _settling_hold(3.0, np.array([400.0, 300.0, 0.0]), seconds=2.0)
    found = apply_gates(short)
    assert "settled" not in [f.code for f in found] and short.unusable == ("mag",), [f.message for f in found]


def test_a_settling_at_every_hold_is_said_twice_then_summed_up_in_one_line():
    from inclinometer_calib.detect.gates import SettlingTally

    tally, said = SettlingTally(), []
    for k, tau in enumerate((1.0, 1.2, 0.9, 1.1)):
        st = _settling_hold(tau, np.array([250.0, -180.0, 120.0]), seed=k)
        said += tally.add(apply_gates(st))
    assert len(said) == 2 and all("settles after the move (" in m for m in said)
    line = tally.summary(5, "log.csv")
    assert line.startswith("log.csv: the magnetometer settles after the move in 4 of 5 holds (time constant ")
    assert "(2 of these holds not said one by one)" in line
    assert SettlingTally().summary() is None


def test_a_slow_drift_of_a_few_nanotesla_over_a_long_hold_is_not_a_transient():
    """The invariants' trend is significant (a long, quiet hold), but 3 nT over 30 s is far less than
    the creep limit moves the field: not a transient, the magnetometer kept."""
    from inclinometer_calib.detect.streaming import StaticDetector

    rng = np.random.default_rng(2)
    t = np.arange(3000) / 100.0
    f = -G + rng.normal(0, 0.004, (3000, 3))
    m = B + rng.normal(0, 5.0, (3000, 3)) + np.outer(0.1 * t, B / np.linalg.norm(B))
    det = StaticDetector(noise_acc=0.004, noise_mag=5.0, max_duration_s=60.0)
    (st,) = list(det.run(t, f, m)) + list(det.flush())
    found = apply_gates(st)
    assert not st.unusable and not st.moved, [x.message for x in found]

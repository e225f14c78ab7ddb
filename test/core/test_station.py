"""The one station type: merging the pieces of a hold is exactly the statistics of all its samples."""
import numpy as np

from inclinometer_calib.core.station import Station, merge_stations


def _from_samples(t, x, **kw):
    rate = np.polyfit(t, x, 1)[0]
    return Station(t_start=float(t[0]), t_end=float(t[-1]), n=len(t), g=x[:, :3].mean(0), b=x[:, 3:].mean(0),
                   g_std=x[:, :3].std(0, ddof=1), b_std=x[:, 3:].std(0, ddof=1), g_rate=rate[:3], b_rate=rate[3:],
                   t_std=float(np.std(t, ddof=1)), **kw)


def test_merged_pieces_have_the_means_and_scatter_of_all_their_samples():
    rng = np.random.default_rng(0)
    t = np.arange(500) * 0.01
    x = np.c_[rng.normal(0, 0.005, (500, 3)) + [0, 0, 9.8], rng.normal(0, 30, (500, 3)) + [3e4, 0, 3e4]]
    a = _from_samples(t[:200], x[:200], pose=4, first_row=10, last_row=209, temp_c=20.0)
    b = _from_samples(t[203:], x[203:], first_row=213, last_row=509, temp_c=30.0, warnings=["piece"])
    whole = np.r_[x[:200], x[203:]]
    m = merge_stations(a, b)
    assert m.n == len(whole) and (m.t_start, m.t_end) == (a.t_start, b.t_end)
    np.testing.assert_allclose(m.g, whole[:, :3].mean(0), rtol=1e-12)
    np.testing.assert_allclose(m.b_std, whole[:, 3:].std(0, ddof=1), rtol=1e-9)
    assert m.pose == 4 and (m.first_row, m.last_row) == (10, 509) and m.warnings == ["piece"]
    assert m.temp_c == (20.0 * a.n + 30.0 * b.n) / m.n


def test_a_station_says_where_it_is_and_what_reference_it_has():
    st = Station(t_start=1.0, t_end=3.5, n=250, g=np.zeros(3), b=np.zeros(3), ref=[0.0, np.nan, 90.0])
    assert st.has_partial_ref and not st.has_ref and st.duration_s == 2.5
    assert st.where == "t=1.00-3.50 s" and st.label == "I=0 A=- T=90"
    st.first_row, st.last_row = 101, 350
    assert st.where.startswith("rows 101-350")


def test_a_hold_taken_from_a_profile_row_has_the_statistics_of_its_samples_from_there():
    """The detector keeps its running sums through the hold (``Station.profile``); a station taken
    from any row of it (a sensor settling after the move trimmed off) has the means, scatter,
    trend and times of exactly the samples from that row on."""
    from inclinometer_calib.detect.streaming import StaticDetector

    rng = np.random.default_rng(3)
    t = np.arange(600) * 0.02                                         # 12 s at 50 Hz
    g = np.c_[rng.normal(0, 0.004, (600, 2)), rng.normal(9.81, 0.004, 600)]    # gravity vector: at rest, +g down
    m = rng.normal(0, 25, (600, 3)) + [20000.0, 0.0, 40000.0] + np.outer(np.exp(-t / 1.5), [120.0, -80.0, 40.0])
    det = StaticDetector(noise_acc=0.004, noise_mag=60.0, max_duration_s=60.0)      # no sample left out as a spike
    (st,) = list(det.run(t, g, m)) + list(det.flush())
    assert st.n == 600 and st.profile.shape == (32 + 1, 22)           # a row a quarter second to 8 s, then the totals
    for row in (0, 5, 19, 31):
        k = int(st.profile[row, 1])                                    # samples before the row's
        assert np.isclose(t[k], st.profile[row, 0] + t[0])
        part = st.settled_from(row)
        x = np.c_[g[k:], m[k:]]
        ref = _from_samples(t[k:], x)
        assert part.n == 600 - k and part.t_start == t[k] and part.t_end == st.t_end
        assert np.isclose(part.settled_s, t[k] - t[0]) and part.pose == st.pose
        np.testing.assert_allclose(part.b, ref.b, rtol=1e-12)
        np.testing.assert_allclose(part.g, ref.g, rtol=1e-12)
        np.testing.assert_allclose(part.b_std, ref.b_std, rtol=1e-7)
        np.testing.assert_allclose(part.b_rate, ref.b_rate, rtol=1e-7, atol=1e-9)
        assert np.isclose(part.t_std, ref.t_std, rtol=1e-9)
        # and taken again from a later row of the part: the same as from the whole
        if row + 3 < 32:
            later = part.settled_from(3)
            np.testing.assert_allclose(later.b, st.settled_from(row + 3).b, rtol=1e-12)
            assert later.t_start == st.settled_from(row + 3).t_start

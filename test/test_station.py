"""The one station type: merging the pieces of a hold is exactly the statistics of all its samples."""
import numpy as np

from inclinometer_calib.station import Station, merge_stations


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

"""The paper's Table 3 reproduced from its Table 2 within the printed rounding.

Tolerance per coefficient: half a unit of Table 3's last printed digit, plus the first-order effect
of Table 2's own rounding (half a unit of each printed parameter, propagated through the inverse).
Which e-term each of Table 2's two 'installation error' columns holds: the row of axis j lists the
terms found from that axis' group of poses (eqs. 7-8, 11-12, 15-16): X: e_xy, e_xz; Y: e_yx, e_yz;
Z: e_zx, e_zy.
"""
import numpy as np
import pytest

from inclinometer_calib.core.errormodel import TriadModel

# (bias, scale, install.1, install.2) per axis, and the decimals each was printed with
TABLE2 = {
    "mag": [(-188.795, 0.9514, 0.0312, 0.0306), (129.94, 0.9716, -0.0076, 0.0399), (-314.095, 0.9067, 0.0062, -0.0566)],
    "acc": [(-17.5863, 0.9998, 0.0046, -0.0013), (-46.3725, 0.9977, -0.0074, -0.0606), (-6.8975, 0.9977, 0.0019, 0.0585)],
}
TABLE2_DECIMALS = {"mag": [(3, 4, 4, 4), (2, 4, 4, 4), (3, 4, 4, 4)], "acc": [(4, 4, 4, 4)] * 3}
TABLE3 = {  # A_i, B_i, C_i, D_i
    "mag": [(1.051, 0.0081, -0.0063, 195), (-0.0345, 1.0266, 0.0625, -120), (-0.0308, -0.0412, 1.1006, 345)],
    "acc": [(1.0002, 0.0072, -0.0023, 18), (-0.0047, 0.9987, -0.0584, 46), (0.001, 0.0605, 0.9988, 10)],
}
E_COLUMNS = [("e_xy", "e_xz"), ("e_yx", "e_yz"), ("e_zx", "e_zy")]


def _model(vec):
    """vec: 12 numbers (bias, scale, i1, i2 per axis) -> TriadModel."""
    v = np.asarray(vec).reshape(3, 4)
    e = {}
    for j, (n1, n2) in enumerate(E_COLUMNS):
        e[n1], e[n2] = v[j, 2], v[j, 3]
    return TriadModel(scale=v[:, 1], bias=v[:, 0], e=e)


def _coefficients(vec):
    m = _model(vec)
    return np.c_[m.correction_matrix, m.correction_offset]


def _decimals(x):
    s = repr(float(x))
    return len(s.split(".")[1]) if "." in s and not s.endswith(".0") else 0


@pytest.mark.parametrize("sensor", ["mag", "acc"])
def test_table3_follows_from_table2_within_printed_rounding(sensor):
    vec = np.array(TABLE2[sensor], dtype=float).ravel()
    half_ulp = 0.5 * 10.0 ** -np.array(TABLE2_DECIMALS[sensor], dtype=float).ravel()
    ours = _coefficients(vec)
    # first-order propagation of Table 2's rounding, by central differences
    prop = np.zeros_like(ours)
    for k in range(12):
        d = np.zeros(12)
        d[k] = half_ulp[k]
        prop += np.abs(_coefficients(vec + d) - _coefficients(vec - d)) / 2
    printed = np.array(TABLE3[sensor], dtype=float)
    printed_half_ulp = 0.5 * 10.0 ** -np.vectorize(_decimals)(printed)
    tol = printed_half_ulp + prop + 1e-12
    excess = np.abs(ours - printed) - tol
    assert np.all(excess <= 0), f"{sensor}: outside rounding at\n{np.round(excess, 6)}\nours\n{np.round(ours, 5)}"


def test_printed_offsets_follow_d_equals_minus_c_times_b():
    for sensor in ("mag", "acc"):
        c = np.array(TABLE3[sensor], dtype=float)
        bias = np.array(TABLE2[sensor], dtype=float)[:, 0]
        d = -(c[:, :3] @ bias)
        np.testing.assert_allclose(d, c[:, 3], atol=1.0)


def test_other_column_assignment_does_not_reproduce_table3():
    """Swapping the two installation columns must fail: the assignment is not arbitrary."""
    vec = np.array(TABLE2["mag"], dtype=float).reshape(3, 4)[:, [0, 1, 3, 2]].ravel()
    ours = _coefficients(vec)
    assert np.max(np.abs(ours[:, :3] - np.array(TABLE3["mag"])[:, :3])) > 0.01

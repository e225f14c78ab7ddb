"""The paper's Poisson model (eqs. 3-4) in matrix form."""
import numpy as np
import pytest

from inclinometer_calib.core.errormodel import E_TERMS, TriadModel


def _model(rng):
    return TriadModel(scale=1 + rng.normal(0, 0.05, 3), bias=rng.normal(0, 100, 3),
                      e={k: rng.normal(0, 0.03) for k in E_TERMS})


def test_forward_is_the_papers_eq3_written_out():
    m = TriadModel(scale=[0.9514, 0.9716, 0.9067], bias=[-188.795, 129.94, -314.095],
                   e=dict(e_xy=0.0312, e_xz=0.0306, e_yx=-0.0076, e_yz=0.0399, e_zx=0.0062, e_zy=-0.0566))
    mx, my, mz = 300.0, -120.0, 450.0
    e = m.e
    hx = 0.9514 * (mx + e["e_yx"] * my + e["e_zx"] * mz) - 188.795
    hy = 0.9716 * (e["e_xy"] * mx + my + e["e_zy"] * mz) + 129.94
    hz = 0.9067 * (e["e_xz"] * mx + e["e_yz"] * my + mz) - 314.095
    np.testing.assert_allclose(m.forward([mx, my, mz]), [hx, hy, hz], rtol=0, atol=1e-12)


def test_inverse_undoes_forward():
    rng = np.random.default_rng(3)
    m = _model(rng)
    v = rng.normal(0, 1000, (50, 3))
    np.testing.assert_allclose(m.inverse(m.forward(v)), v, atol=1e-9)


def test_offset_is_minus_correction_times_bias():
    m = _model(np.random.default_rng(4))
    np.testing.assert_allclose(m.correction_offset, -m.correction_matrix @ m.bias)
    np.testing.assert_allclose(m.inverse(np.zeros(3)), m.correction_offset)


def test_from_matrix_decomposes_k_and_e():
    m = _model(np.random.default_rng(5))
    m2 = TriadModel.from_matrix(m.A, m.bias)
    for k, v in m.parameters().items():
        assert m2.parameters()[k] == pytest.approx(v, abs=1e-14)


def test_unknown_e_term_is_refused():
    with pytest.raises(ValueError, match="e_xx"):
        TriadModel(e={"e_xx": 0.1})

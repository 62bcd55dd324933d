"""
The friction sum of ``gp.means``: ``FrictionMean`` and ``BasisFrictionMean`` share one function.

Both evaluate ``m_d(|v|) = F_v + Coulomb terms + Stribeck terms``; ``_friction_diag`` is that
sum. Pinned here, bit for bit, to the two implementations each class had of it, on speeds that
include 0, speeds below the small-speed switch of ``tanh(a / eps) / a`` and large ones.
"""
import numpy as np
import pytest

from dgp_ros.gp.means import _tanh_over, BasisFrictionMean, FrictionMean


def _friction_before(m, a):
    t = _tanh_over(a, m.eps)
    out = m.coef[:, 0] + m.coef[:, 1] * t
    if m.stribeck:
        out = out + m.coef[:, 2] * t * np.exp(-(a / m.v_s) ** 2)
    return out


def _basis_before(m, a):
    K = m.eps.size
    out = m.coef[:, 0] + 0.0 * a
    if K == 0 and not m.vs.size:
        return out
    T = _tanh_over(a[..., None], np.append(m.eps, m.eps_s))
    for k in range(K):
        out = out + m.coef[:, 1 + k] * T[..., k]
    if m.vs.size:
        t = T[..., K]
        G = np.exp(-(a[..., None] / m.vs) ** 2)
        for s in range(m.vs.size):
            out = out + m.coef[:, 1 + K + s] * t * G[..., s]
    return out


def _speeds(rng, N):
    a = np.abs(rng.standard_t(1.5, (400, N)))
    a[:5] = 0.0
    a[5:10] = 1e-12
    return a


@pytest.mark.parametrize('stribeck', [False, True])
def test_friction_mean_sum_is_unchanged(stribeck):
    rng = np.random.default_rng(4)
    qd = rng.normal(size=(300, 3)) * [0.05, 1.0, 3.0]
    tau = 2.0 * qd + 0.5 * np.tanh(qd / 0.02) + 0.01 * rng.normal(size=qd.shape)
    m = FrictionMean(stribeck=stribeck).fit(qd, tau)
    if stribeck:
        m.coef[:, 2] = [0.3, 0.0, 1.2]                  # make the Stribeck terms count
    a = _speeds(rng, 3)
    assert np.array_equal(m._diag_at(a), _friction_before(m, a))
    assert np.array_equal(m._diag_at(a[7]), _friction_before(m, a[7]))


@pytest.mark.parametrize('K,S', [(0, 0), (1, 0), (0, 2), (3, 2)])
def test_basis_friction_mean_sum_is_unchanged(K, S):
    rng = np.random.default_rng(K + 10 * S)
    m = BasisFrictionMean(rng.uniform(0, 2, (4, 1 + K + S)), eps=rng.uniform(0.01, 0.1, K),
                          eps_s=0.02, vs=rng.uniform(0.05, 0.5, S))
    a = _speeds(rng, 4)
    assert np.array_equal(m._diag_at(a), _basis_before(m, a))
    assert np.array_equal(m.diag(-a), _basis_before(m, a))

"""
Coupled transmissions: the passive prior part (gp.transmission) and the long history's choice.

The prior: passive at random velocities inside and 100x outside an arm's speeds, its matrix
times qd equal to its force, its symmetric part positive semi-definite, its box bounds holding
every sampled matrix, saved and read back equal. The history (dynamics.history): a motor on two
adjacent joints' sum or difference is found and fitted where the residual carries one, and none
is served where it does not.
"""
import numpy as np
import pytest

from dgp_ros.dynamics.history import LongHistory
from dgp_ros.dynamics.parametric import EPS_S, F, FRICTION_EPS, STRIBECK_VS
from dgp_ros.gp.means import BasisFrictionMean, mean_from_dict
from dgp_ros.gp.transmission import motor_columns, TransmissionMean


def _prior(N=7, seed=0):
    rng = np.random.default_rng(seed)
    base = BasisFrictionMean(np.abs(rng.normal(0.0, 0.3, (N, F))), FRICTION_EPS, EPS_S,
                             STRIBECK_VS)
    base.bias = np.zeros(N)
    return TransmissionMean(base, [(5, 6, 1), (2, 3, -1)], [[0.6, 0.3], [0.2, 0.0]])


@pytest.mark.parametrize('scale', [1.0, 100.0], ids=['inside', 'outside'])
def test_the_prior_is_passive_and_its_matrix_is_its_force(scale):
    m = _prior()
    rng = np.random.default_rng(1)
    Q = rng.normal(0.0, 1.0, (4000, 7)) * scale * rng.choice([1e-4, 1e-2, 1.0], (4000, 1))
    f, M = m.force(Q), m.matrix(Q)
    assert int((np.einsum('ki,ki->k', Q, f) < 0.0).sum()) == 0
    assert np.allclose(np.einsum('kij,kj->ki', M, Q), f, rtol=1e-12, atol=1e-12)
    assert np.linalg.eigvalsh(0.5 * (M + M.transpose(0, 2, 1))).min() >= 0.0
    # where the two joints' motor turns, its force shows in both: not a per-joint curve
    q = np.zeros((1, 7))
    q[0, 5], q[0, 6] = 0.4, 0.1
    d = m.force(q)[0] - m.base.force(q)[0]
    f56 = motor_columns(np.array(0.5)) @ np.array([0.6, 0.3])
    assert d[5] == pytest.approx(f56) and d[6] == pytest.approx(f56)


def test_the_prior_bounds_and_file():
    m = _prior()
    rng = np.random.default_rng(2)
    lo = rng.normal(0.0, 0.5, (50, 7))
    hi = lo + rng.uniform(0.0, 0.3, (50, 7))
    Mlo, Mhi = m.matrix_bounds(lo, hi)
    for _ in range(20):
        M = m.matrix(lo + rng.uniform(0.0, 1.0, lo.shape) * (hi - lo))
        assert np.all(M >= Mlo - 1e-12) and np.all(M <= Mhi + 1e-12)
    back = mean_from_dict(m.to_dict(), 7)
    Q = rng.normal(0.0, 1.0, (100, 7))
    assert np.array_equal(back.force(Q), m.force(Q))
    assert back.pairs == m.pairs and not back.is_diagonal


def test_the_prior_refuses_what_is_not_passive():
    base = _prior().base
    with pytest.raises(ValueError, match='>= 0'):
        TransmissionMean(base, [(5, 6, 1)], [[0.6, -0.1]])
    with pytest.raises(ValueError, match='distinct'):
        TransmissionMean(base, [(5, 5, 1)], [[0.6, 0.1]])
    with pytest.raises(ValueError, match='beyond'):
        TransmissionMean(base, [(5, 9, 1)], [[0.6, 0.1]]).force(np.zeros((1, 7)))


def _history(motor, seconds=40.0, hz=100.0, seed=3):
    """
    Feed a 4-joint history per-joint friction and, with ``motor`` = (a, s), a shared motor.

    Velocities: sums of sines of different frequencies per joint (each reverses, the pairs'
    sums and differences move on their own); noise 0.02 N m. Returns the history.
    """
    rng = np.random.default_rng(seed)
    N = 4
    t = np.arange(0.0, seconds, 1.0 / hz)
    fr = rng.uniform(0.2, 0.9, (N, 3))
    ph = rng.uniform(0.0, 2 * np.pi, (N, 3))
    V = sum(0.4 * np.sin(2 * np.pi * fr[:, k] * t[:, None] + ph[:, k]) for k in range(3))
    R = 0.3 * np.tanh(V / 0.02) + 0.2 * V
    if motor is not None:
        a, s = motor
        f = motor_columns(V[:, a] + s * V[:, a + 1]) @ np.array([0.5, 0.25])
        R[:, a] += f
        R[:, a + 1] += s * f
    R = R + 0.02 * rng.normal(size=R.shape)
    h = LongHistory(N, None, 'friction', offsets=False)
    z = np.zeros(N)
    for k in range(t.size):
        h.push(float(t[k]), z, V[k], z, R[k])
    return h


@pytest.mark.parametrize('motor', [(1, 1), (2, -1)], ids=['sum', 'difference'])
def test_the_history_finds_a_motor_where_the_data_hold_one(motor):
    fit = _history(motor).select()
    a, s = motor
    assert fit.transmission is not None, fit.label()
    assert fit.transmission[0] == ((a, a + 1, s),)
    assert np.allclose(fit.transmission[1][0], [0.5, 0.25], rtol=0.2, atol=0.05)
    assert 'transmission on' in fit.label()
    assert fit.motors() == ((a, s),)
    assert isinstance(fit.friction_mean(), TransmissionMean)
    # refitted and refitted by name, it keeps its motor
    assert fit.motors() == _history(motor).refit(fit).motors()


def test_the_history_serves_no_motor_where_there_is_none():
    fit = _history(None).select()
    assert fit.transmission is None, fit.label()
    assert not isinstance(fit.friction_mean(), TransmissionMean)

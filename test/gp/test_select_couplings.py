"""
Couplings where velocities reverse: kept where the data show them, never on an arm's path.

``gp.select`` with ``couplings='evidence'`` (a system that is not an arm) tries each output's
couplings beside its own element and keeps them where they beat it in the held-out blocks and
on the newest block predicted by a fit (hyper-parameters too) on the rows before it; with
``couplings='persistent'`` (an arm: ``EstimatorConfig.model_kwargs`` with inverse dynamics)
only beside a velocity that never nears zero. Scored on fresh velocities in the visited box,
and passive there and ten times beyond it.
"""
import numpy as np
import pytest

from dgp_ros.gp import FullDGP
from dgp_ros.gp.select import row_choices
from dgp_ros.online import EstimatorConfig

N = 3


def _velocities(t, rng):
    """(n, N): each axis a sum of three sines of random frequencies, reversing."""
    f = rng.uniform(0.05, 0.5, (N, 3))
    ph = rng.uniform(0, 2 * np.pi, (N, 3))
    return np.stack([np.sin(2 * np.pi * f[i] * t[:, None] + ph[i]).sum(axis=1)
                     for i in range(N)], axis=1)


def _force(V):
    """Return a coupled passive damping force D(qd) qd: sym(D) diagonally dominant, skew part."""
    D = np.zeros((len(V), N, N))
    for i in range(N):
        D[:, i, i] = 2.0 + np.exp(-(V[:, i] / 0.3) ** 2) + 0.5 * np.abs(V[:, i])
    for i, j, m in ((0, 1, 0.6), (1, 2, -0.5)):
        c = m * (1.0 + 0.5 * np.tanh(V[:, (j + 1) % N]))
        D[:, i, j] += c
        D[:, j, i] += c
    w = 0.8 * np.sin(V[:, 2])
    D[:, 0, 2] += w
    D[:, 2, 0] -= w
    return np.einsum('nij,nj->ni', D, V)


@pytest.fixture(scope='module')
def fitted():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 90.0, 0.3)                       # 300 rows, oldest first
    V = _velocities(t, rng)
    F = _force(V)
    T = F + 0.01 * F.std(axis=0) * rng.normal(size=F.shape)
    lo, hi = V.min(axis=0), V.max(axis=0)
    box = rng.uniform(lo, hi, (3000, N))
    out = {}
    for couplings in ('evidence', 'persistent'):
        m = FullDGP(prior='viscous', elements='auto', couplings=couplings,
                    n_restarts=0).fit(V, T)
        P = m.predict(box)
        truth = _force(box)
        out[couplings] = (m, np.mean((P - truth) ** 2, axis=0) / truth.var(axis=0))
    return out, lo, hi, rng


def test_couplings_the_data_show_are_kept_and_predict_fresh_velocities(fitted):
    out, *_ = fitted
    m, nmse = out['evidence']
    choices = row_choices(m.posterior_.structure, m.posterior_.hyper)
    assert 'all' in choices, choices
    _, nmse_own = out['persistent']
    # the outputs with couplings: far better in the box than their own element alone
    assert np.max(nmse) < 0.02 and np.max(nmse) < 0.3 * np.max(nmse_own), (nmse, nmse_own)


def test_an_arm_tries_couplings_only_beside_a_velocity_that_never_nears_zero(fitted):
    out, *_ = fitted
    m, _ = out['persistent']
    assert 'all' not in row_choices(m.posterior_.structure, m.posterior_.hyper)
    assert EstimatorConfig(inverse_dynamics='urdf').model_kwargs()['couplings'] == 'persistent'
    assert EstimatorConfig().model_kwargs()['couplings'] == 'evidence'


def test_the_coupled_model_is_passive_inside_and_far_outside_the_data(fitted):
    out, lo, hi, rng = fitted
    m, _ = out['evidence']
    span = hi - lo
    for scale in (1.0, 10.0):
        Q = rng.uniform(lo - (scale - 1) * span / 2, hi + (scale - 1) * span / 2, (20000, N))
        power = np.einsum('ni,ni->n', Q, m.predict(Q))
        assert np.all(power >= -1e-9 * np.abs(Q).sum(axis=1) ** 2), power.min()

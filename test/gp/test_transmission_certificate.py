"""
A transmission prior (gp.transmission) under the global certificate and the earned-gain blend.

The prior is its diagonal base plus a PSD part (``psd_over_diagonal``), so the lemma that proves
a posterior's symmetric part PSD over a diagonal prior (``diag(m_inf) - B`` copositive) proves
it over this one: a 7-joint Full-D-GP with a small correction is certified globally
('a-posteriori-bound', no eigenvalue clip on its answers). Its answers blended by earned gains
keep the symmetric part PSD (the congruence ``S D S + R M R``), and so does the prior's fallback
with gains. Each checked at 4,000 random velocities inside and 100x outside the data.
"""
import numpy as np
import pytest

from dgp_ros.dynamics.parametric import EPS_S, F, FRICTION_EPS, STRIBECK_VS
from dgp_ros.gp import FullDGP
from dgp_ros.gp.blend import prior_answer
from dgp_ros.gp.means import BasisFrictionMean
from dgp_ros.gp.transmission import TransmissionMean

N = 7
PAIRS = [(5, 6, 1), (2, 3, -1)]
MOTORS = np.array([[0.6, 0.3], [0.2, 0.1]])


def _prior():
    coef = np.zeros((N, F))
    coef[:, 0], coef[:, 1] = 0.4, 0.2          # viscous 0.4 (the infimum), Coulomb 0.2
    base = BasisFrictionMean(coef, FRICTION_EPS, EPS_S, STRIBECK_VS)
    base.bias = np.zeros(N)
    return TransmissionMean(base, PAIRS, MOTORS)


def _model(grounds=None):
    rng = np.random.default_rng(4)
    Qd = rng.normal(0.0, 0.8, (80, N))
    prior = _prior()
    # the prior's force, motors included, and a little the GP learns
    Tau = prior.force(Qd) + 0.02 * np.sin(2.0 * Qd) + 0.005 * rng.normal(size=Qd.shape)
    m = FullDGP(prior=prior, n_restarts=0, passivity='certified').fit(Qd, Tau)
    if grounds is not None:
        m.grounds_ = grounds
    return m


def _velocities(scale, seed=1):
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 0.8, (4000, N)) * scale * rng.choice([1e-3, 0.1, 1.0], (4000, 1))


def _sym_min(D):
    return float(np.linalg.eigvalsh(0.5 * (D + D.transpose(0, 2, 1))).min())


@pytest.fixture(scope='module')
def certified():
    return _model()


def test_the_global_certificate_holds_over_a_transmission_prior(certified):
    cert = certified.certificate()
    assert cert.guarantee == 'psd' and cert.method == 'a-posteriori-bound', cert


@pytest.mark.parametrize('scale', [1.0, 100.0], ids=['inside', 'outside'])
def test_certified_answers_are_psd_inside_and_outside(certified, scale):
    Q = _velocities(scale)
    D = certified.damping_matrix(Q)
    tau = certified.predict(Q)
    assert _sym_min(D) >= -1e-12 * float(np.abs(D).max())
    assert int((np.einsum('ki,ki->k', Q, tau) < 0.0).sum()) == 0
    assert np.allclose(np.einsum('kij,kj->ki', D, Q), tau, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize('scale', [1.0, 100.0], ids=['inside', 'outside'])
def test_the_blend_by_earned_gains_keeps_the_symmetric_part_psd(scale):
    rng = np.random.default_rng(7)
    g = {'model_weight': rng.uniform(0.1, 0.9, N).tolist(),
         'prior_gain': rng.uniform(0.3, 1.0, N).tolist(), 'confidence': [1.0] * N}
    m = _model(g)
    Q = _velocities(scale, seed=2)
    D = m.damping_matrix(Q)
    tau = m.predict(Q)
    # the congruence of two PSD parts: the symmetric part stays PSD (a row-wise mix does not)
    assert _sym_min(D) >= -1e-12 * float(np.abs(D).max())
    assert np.allclose(np.einsum('kij,kj->ki', D, Q), tau, rtol=1e-9, atol=1e-12)
    assert int((np.einsum('ki,ki->k', Q, tau) < 0.0).sum()) == 0


def test_the_prior_fallback_with_gains_is_psd():
    prior = _prior()
    Q = _velocities(1.0, seed=3)
    a = np.random.default_rng(8).uniform(0.0, 1.0, N)
    tau, D = prior_answer(prior, Q, a, True)
    assert _sym_min(D) >= -1e-12
    assert np.allclose(np.einsum('kij,kj->ki', D, Q), tau, rtol=1e-12, atol=1e-14)
    # a diagonal joint far from the motors keeps its gained friction exactly
    assert np.allclose(tau[:, 0], a[0] * prior.base.force(Q)[:, 0], rtol=1e-12)
    one, Done = prior_answer(prior, Q, None, True)
    assert np.array_equal(one, prior.force(Q)) and np.array_equal(Done, prior.matrix(Q))

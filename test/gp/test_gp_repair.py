"""
Certified passivity on data that is not passive everywhere (up to 3 velocities: domain proofs).

Local repair by cutting planes (the least change of the weights at counterexamples), a blend
narrowed instead of a model changed where the counterexample lies beyond the kept box, and no
certificate (every answer projected) where no proof exists.
"""
import numpy as np
import pytest

from dgp_ros.gp import DiagDGP, FullDGP
from dgp_ros.gp.repair import power_rows, repair


def _power(X, T):
    return np.einsum('ij,ij->i', X, T)


def _bumpy(n=150, seed=3):
    """Passive friction with one locally energy-injecting patch in the data."""
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-2, 2, (n, 2))
    truth = Q * [1.5, 0.8] + 0.3 * np.tanh(Q / 0.1)
    T = truth.copy()
    T[:, 0] -= 4.0 * np.exp(-((Q - [0.8, 0.6]) ** 2).sum(1) / 0.1) * np.sign(Q[:, 0])
    return Q, T + 0.05 * rng.normal(size=T.shape)


def test_repair_makes_the_power_non_negative_there_and_changes_only_nearby():
    Q, T = _bumpy()
    m = FullDGP(passivity='none', n_restarts=0).fit(Q, T)
    post = m.posterior_
    rng = np.random.default_rng(0)
    Z = rng.uniform(-2, 2, (20000, 2))
    P = _power(Z, post.predict(Z)[0])
    bad = Z[P < 0][:50]
    assert len(bad) >= 10                      # the unconstrained posterior does violate
    far = Q[np.min(np.linalg.norm(Q[:, None] - bad[None], axis=2), axis=1) > 1.5]
    before = post.predict(far)[0]
    margin = np.full(len(bad), 1e-3)
    delta, info = repair(post, power_rows(post, bad, np.ones(len(bad))), margin)
    assert info['holds'] and 1 <= info['active'] <= len(bad)
    post.set_delta(delta)
    assert _power(bad, post.predict(bad)[0]).min() >= 1e-3 * (1 - 1e-6)
    assert len(far) > 10
    assert np.abs(post.predict(far)[0] - before).max() < 0.05 * np.abs(T).max()
    # the variance is the GP's: the repair moves the mean only
    assert np.array_equal(post.predict(far, return_var=True)[1],
                          m.posterior_.predict(far, return_var=True)[1])


def test_certified_repairs_locally_and_stays_close_to_projected():
    Q, T = _bumpy()
    rng = np.random.default_rng(1)
    Qt = rng.uniform(-2, 2, (4000, 2))
    truth = Qt * [1.5, 0.8] + 0.3 * np.tanh(Qt / 0.1)
    base = FullDGP(passivity='none', n_restarts=0).fit(Q, T)
    proj = FullDGP(passivity='projected', hyperparams=base.hyperparams_).fit(Q, T, optimize=False)
    cert = FullDGP(passivity='certified', hyperparams=base.hyperparams_).fit(Q, T,
                                                                             optimize=False)
    c = cert.certificate()
    assert c.certified and c.correction_scale == 1.0 and c.details['repaired_points'] > 0
    assert len(c.details['repair_max_change_in_domain']) == 2
    nm = lambda m: np.mean((m.predict(Qt) - truth) ** 2, 0) / np.var(truth, 0)  # noqa: E731
    assert nm(cert).mean() <= 1.2 * nm(proj).mean()
    for X in (rng.uniform(-2.5, 2.5, (300_000, 2)), rng.uniform(-300, 300, (300_000, 2))):
        assert _power(X, cert.predict(X)).min() >= 0
        D = cert.damping_matrix(X[:20000])
        assert np.einsum('ki,kij,kj->k', X[:20000], D, X[:20000]).min() >= 0
    # the repair survives saving and loading (and is re-proven, not trusted)
    import os
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        cert.save(os.path.join(d, 'm.npz'))
        r = FullDGP.load(os.path.join(d, 'm.npz'))
    assert r.certificate().stale and r.recertify().certified
    assert np.allclose(r.predict(Qt), cert.predict(Qt), atol=1e-9 * np.abs(T).max())


@pytest.mark.parametrize('cls', [FullDGP, DiagDGP])
def test_counterexamples_beyond_the_kept_box_narrow_the_blend_instead(cls):
    """
    Narrow the blend zone where the extrapolation is not passive.

    D_00 of the data is 0.3 + 2 q_0 on q_0 in [0, 1]: the extrapolation turns negative in the blend
    zone below q_0 = -0.15, so the proof narrows the blend on that side and changes nothing.
    """
    rng = np.random.default_rng(4)
    Q = np.c_[rng.uniform(0, 1, 80), rng.uniform(-1, 1, 80)]
    T = np.c_[(0.3 + 2 * Q[:, 0]) * Q[:, 0], Q[:, 1]] + 0.002 * rng.normal(size=(80, 2))
    base = cls(passivity='none', n_restarts=0).fit(Q, T)
    lo0 = -0.25                                     # where the default blend would end
    assert base.posterior_.damping(np.array([[lo0, 0.0]]))[0, 0, 0] < 0
    m = cls(passivity='certified', hyperparams=base.hyperparams_).fit(Q, T, optimize=False)
    c = m.certificate()
    assert c.certified and c.method == 'domain-bnb+blend' and 'repaired_points' not in c.details
    olo, ohi = (np.array(v) for v in c.details['outer_box'])
    assert lo0 < olo[0] < c.domain[0][0]           # narrowed on that side only
    assert ohi[0] == pytest.approx(Q[:, 0].max() + 0.2 * np.ptp(Q[:, 0]), rel=1e-9)
    ilo, ihi = c.domain
    X = rng.uniform(ilo, ihi, (5000, 2))
    np.testing.assert_array_equal(m.predict(X), base.predict(X))
    for Z in (rng.uniform(olo, ohi, (100_000, 2)), rng.uniform(-50, 50, (100_000, 2))):
        assert np.einsum('ij,ij->i', Z, m.predict(Z)).min() >= 0


def test_without_a_proof_every_answer_is_projected():
    """Energy-injecting data: no passive posterior; certified says so and answers as projected."""
    rng = np.random.default_rng(6)
    Q = rng.uniform(-1, 1, (60, 2))
    T = -(Q * [1.0, 0.5]) + 0.01 * rng.normal(size=Q.shape)
    base = FullDGP(passivity='none', n_restarts=0).fit(Q, T)
    hp = base.hyperparams_
    cert = FullDGP(passivity='certified', hyperparams=hp, max_boxes=5000).fit(Q, T,
                                                                              optimize=False)
    proj = FullDGP(passivity='projected', hyperparams=hp).fit(Q, T, optimize=False)
    c = cert.certificate()
    assert not c.certified and c.method == 'projection' and c.guarantee == 'pointwise'
    assert 'no proof' in c.details['reason']
    X = rng.uniform(-3, 3, (20000, 2))
    np.testing.assert_array_equal(cert.predict(X), proj.predict(X))
    assert np.einsum('ij,ij->i', X, cert.predict(X)).min() >= 0
    assert np.einsum('ij,ij->i', X, base.predict(X)).min() < 0     # there was something to fix

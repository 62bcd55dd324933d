"""
Certified passivity on data that is not passive everywhere.

Local repair by cutting planes (the least change of the weights at counterexamples) and the
element-wise proof in 7-D.
"""
import numpy as np

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
    base = FullDGP(n_restarts=0).fit(Q, T)
    proj = FullDGP(passivity='projected', hyperparams=base.hyperparams_).fit(Q, T, optimize=False)
    cert = FullDGP(passivity='certified', hyperparams=base.hyperparams_).fit(Q, T,
                                                                             optimize=False)
    c = cert.certificate()
    assert c.certified and c.correction_scale == 1.0 and c.details['repaired_points'] > 0
    assert len(c.details['repair_max_change_in_data_box']) == 2
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


def test_seven_joints_are_proven_element_wise_within_budget():
    rng = np.random.default_rng(2)
    N = 7
    Q = rng.uniform(-1, 1, (200, N))
    T = Q * np.linspace(0.5, 2.0, N) + 0.3 * np.tanh(Q / 0.05) + 0.05 * rng.normal(size=Q.shape)
    m = DiagDGP(passivity='certified', prior='friction', n_restarts=0, max_opt_samples=120,
                max_boxes=20000).fit(Q, T)
    c = m.certificate()
    assert c.certified and c.method in ('elementwise-bnb+blend', 'a-posteriori-bound'), c
    assert c.details['seconds'] < 30
    for X in (rng.uniform(-1.2, 1.2, (100_000, N)), rng.uniform(-100, 100, (100_000, N))):
        assert _power(X, m.predict(X)).min() >= 0

"""
Passivity properties.

Checked numerically on many random points inside and far outside the data.
"""
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from dgp_ros.gp import FullDGP, make_model, project_passive
from dgp_ros.gp.bounds import correction_terms
from dgp_ros.gp.verify import verify_box


def _power(Q, T):
    return np.einsum('ij,ij->i', Q, T)


def _queries(Q, k, rng):
    lo, hi = Q.min(axis=0), Q.max(axis=0)
    span = np.maximum(hi - lo, 1e-3)
    inside = rng.uniform(lo, hi, (k, Q.shape[1]))
    far = rng.uniform(-100 * span + lo, hi + 100 * span, (k, Q.shape[1]))
    return inside, far


@st.composite
def datasets(draw):
    N = draw(st.integers(1, 4))
    n = draw(st.integers(3, 200))
    seed = draw(st.integers(0, 2 ** 31 - 1))
    out_scale = 10.0 ** draw(st.floats(-3, 6))
    in_scale = 10.0 ** draw(st.floats(-2, 2))
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-1, 1, (n, N)) * in_scale
    A = rng.uniform(0.2, 2.0, (N, N)) * 0.5
    A = A + A.T + np.eye(N) * N            # a passive linear part
    T = (Q / in_scale) @ A.T + 0.3 * np.tanh(Q / in_scale / 0.2) * rng.uniform(-1, 1, N)
    T = T * out_scale + 0.01 * out_scale * rng.standard_normal((n, N))
    return Q, T, seed


@pytest.mark.parametrize('kind', ['full', 'diag'])
@pytest.mark.parametrize('mode', ['paper', 'certified', 'projected'])
@settings(max_examples=6, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(data=datasets())
def test_guaranteed_modes_are_passive_everywhere(kind, mode, data):
    Q, T, seed = data
    # a small branch-and-bound budget keeps the test fast; the guarantee does not depend on it
    m = make_model(kind, passivity=mode, n_restarts=0, max_opt_samples=60,
                   max_boxes=10_000).fit(Q, T)
    assert m.certificate().certified
    rng = np.random.default_rng(seed)
    for X in _queries(Q, 10_000, rng):
        P = _power(X, m.predict(X))
        assert np.all(np.isfinite(P))
        assert P.min() >= 0.0, f'{(P < 0).sum()} violations, min {P.min()}'
        if mode != 'projected':
            D = m.damping_matrix(X[:2000])
            assert np.einsum('ki,kij,kj->k', X[:2000], D, X[:2000]).min() >= 0.0


def test_unconstrained_model_can_violate():
    """The property above can fail: a non-passive truth learned with passivity='none'."""
    rng = np.random.default_rng(0)
    Q = rng.uniform(-1, 1, (80, 2))
    T = np.c_[np.sin(3 * Q[:, 1]), -Q[:, 0] + 0.5 * Q[:, 1]] + 0.3 * Q   # circulating field
    m = FullDGP(passivity='none', n_restarts=0).fit(Q, T)
    inside, far = _queries(Q, 10_000, rng)
    assert (_power(inside, m.predict(inside)) < 0).sum() > 0
    # and the guaranteed modes fix exactly that data set
    for mode in ('paper', 'certified', 'projected'):
        mm = FullDGP(passivity=mode, n_restarts=0).fit(Q, T)
        assert (_power(inside, mm.predict(inside)) < 0).sum() == 0


def test_certified_million_points_inside_and_far_outside():
    rng = np.random.default_rng(7)
    Q = rng.uniform(-2, 2, (50, 2))
    T = Q @ np.array([[2.0, 0.3], [0.1, 1.0]]).T + 0.5 * np.tanh(Q / 0.3) + 0.2 * Q ** 3
    m = FullDGP(passivity='certified').fit(Q, T)
    cert = m.certificate()
    assert cert.certified and cert.margin >= 0
    viol = 0
    for X in (rng.uniform(-2.5, 2.5, (500_000, 2)), rng.uniform(-400, 400, (500_000, 2))):
        viol += int((_power(X, m.predict(X)) < 0).sum())
    assert viol == 0


def test_certified_updates_stay_passive_pointwise_then_recertify():
    rng = np.random.default_rng(3)
    Q = rng.uniform(-2, 2, (60, 2))
    T = Q * [1.5, 0.7] + 0.4 * np.tanh(Q / 0.2)
    m = FullDGP(passivity='certified', max_boxes=20_000).fit(Q[:30], T[:30])
    for i in range(30, 60):
        m.update(Q[i], T[i])
        X = rng.uniform(-5, 5, (2000, 2))
        assert _power(X, m.predict(X)).min() >= 0
    cert = m.recertify()
    assert cert.certified and not m.certificate_stale
    X = rng.uniform(-5, 5, (50_000, 2))
    assert _power(X, m.predict(X)).min() >= 0


def test_bnb_proof_holds_on_samples_of_its_box():
    rng = np.random.default_rng(11)
    Q = rng.uniform(-1, 1, (40, 3))
    T = Q * [3.0, 2.0, 1.0] + 0.2 * np.sin(3 * Q)
    m = FullDGP(passivity='none', n_restarts=0).fit(Q, T)
    lo, hi = Q.min(0) - 0.5, Q.max(0) + 0.5
    res = verify_box(correction_terms(m.posterior_, 1.0), lo, hi)
    X = rng.uniform(lo, hi, (200_000, 3))
    P = np.einsum('ki,kij,kj->k', X, m.posterior_.damping(X), X)
    if res.ok:
        assert P.min() >= 0
    else:
        assert res.witness is not None or 'budget' in res.reason


def test_projection_is_non_expansive_on_passive_truth():
    rng = np.random.default_rng(5)
    for N in (1, 2, 3, 4):
        Q = rng.standard_normal((20_000, N))
        # passive truth: tau = S(q) q with S(q) positive definite
        M = rng.standard_normal((N, N))
        truth = Q @ (M @ M.T + 0.1 * np.eye(N)).T
        est = truth + rng.standard_normal((20_000, N)) * 3.0
        w_inv = rng.uniform(0.2, 5.0, N)
        proj = project_passive(Q, est, w_inv)
        assert _power(Q, proj).min() >= 0
        W = 1.0 / w_inv
        err_before = np.einsum('ij,j,ij->i', est - truth, W, est - truth)
        err_after = np.einsum('ij,j,ij->i', proj - truth, W, proj - truth)
        assert np.all(err_after <= err_before * (1 + 1e-12) + 1e-12)
        moved = _power(Q, est) < 0
        assert moved.any() and np.all(err_after[moved] < err_before[moved])
        assert np.array_equal(proj[~moved], est[~moved])


def test_declared_operating_domain_keeps_the_correction_where_no_data_was_seen():
    """
    Data in one corner of the operating box.

    With the box declared, the certified model equals the unconstrained one over the whole box (no
    blend to the prior mean), and stays passive inside and far outside it.
    """
    rng = np.random.default_rng(5)
    lo, hi = np.array([-2.0, -2.0]), np.array([2.0, 2.0])
    Q = rng.uniform(-2, 0, (40, 2))                          # one quadrant only
    f = lambda X: X @ np.array([[2.0, 0.3], [0.1, 1.0]]).T + 0.5 * np.tanh(X / 0.3)  # noqa: E731
    T = f(Q)
    base = FullDGP(passivity='none').fit(Q, T)
    hp = base.hyperparams_
    plain = FullDGP(passivity='certified', hyperparams=hp).fit(Q, T, optimize=False)
    decl = FullDGP(passivity='certified', hyperparams=hp,
                   operating_domain=(lo, hi)).fit(Q, T, optimize=False)
    c = decl.certificate()
    assert c.certified and c.method == 'domain-bnb+blend'
    ilo, ihi = c.domain
    assert np.all(ilo <= lo) and np.all(ihi >= hi)           # the declared box is proven
    X = rng.uniform(lo, hi, (20_000, 2))
    assert np.allclose(decl.predict(X), base.predict(X), rtol=1e-12, atol=1e-9)
    # without the declaration the far quadrant falls back to the prior mean: a real difference
    opp = rng.uniform(0.8, 2.0, (2000, 2))
    assert np.abs(plain.predict(opp) - base.predict(opp)).max() > 1e-3
    viol = 0
    for Z in (X, rng.uniform(-400, 400, (200_000, 2))):
        viol += int((_power(Z, decl.predict(Z)) < 0).sum())
    assert viol == 0


def test_operating_domain_is_validated_and_saved(tmp_path):
    rng = np.random.default_rng(1)
    Q = rng.uniform(-1, 1, (20, 2))
    with pytest.raises(ValueError, match='lo < hi'):
        FullDGP(passivity='certified', operating_domain=([0.0, 1.0], [1.0, 1.0])).fit(Q, Q)
    with pytest.raises(ValueError, match='finite'):
        FullDGP(passivity='certified', operating_domain=([0.0, np.nan], [1.0, 1.0])).fit(Q, Q)
    with pytest.raises(ValueError, match='one per velocity'):
        FullDGP(passivity='certified', operating_domain=([0, 0, 0], [1, 1, 1])).fit(Q, Q)
    m = FullDGP(passivity='certified', n_restarts=0,
                operating_domain=([-3.0, -3.0], [3.0, 3.0])).fit(Q, 2 * Q)
    m.save(tmp_path / 'm.npz')
    r = FullDGP.load(tmp_path / 'm.npz')
    assert r.get_params()['operating_domain'] == [[-3.0, -3.0], [3.0, 3.0]]
    X = rng.uniform(-3, 3, (1000, 2))
    assert np.array_equal(r.predict(X), m.predict(X))

"""D-GP estimators: exactness against the paper's dense formulation, gradients, updates, I/O."""
import json
import zipfile

import numpy as np
import pytest

from dgp_ros.gp import (ArdGP, copositivity_margin, DiagDGP, FullDGP, load_model, make_model,
                        PASSIVITY_MODES, prior_mean_diag, se_ard)
from dgp_ros.gp.hyper import LmlObjective
from dgp_ros.gp.kernels import Structure


def _friction(Q):
    D = np.array([[2.0, 0.3], [0.1, 1.0]])
    return Q @ D.T + 0.5 * np.tanh(Q / 0.1) + 0.2 * Q ** 3


def _data(n=40, N=2, seed=0):
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-2, 2, (n, N))
    A = rng.uniform(0.5, 2.0, N)
    T = Q * A + 0.3 * np.tanh(Q / 0.2) + 0.05 * rng.standard_normal((n, N))
    return Q, T


def _hp(kind, N, rng):
    E = N * N if kind == 'full' else N
    return {'log_sf2': np.log(rng.uniform(0.2, 2.0, E)),
            'log_ls': np.log(rng.uniform(0.5, 2, (E, N))),
            'log_sn2': np.log(rng.uniform(0.01, 0.1, N)), 'sx': np.ones(N), 'sy': np.ones(N),
            'mean': rng.uniform(0.5, 2.0, N)}


def _dense_reference(kind, hp, X, Y, Xs):
    """
    Compute the paper's stacked formulation.

    One (nN x nN) GP over the stacked force vector and the posterior damping matrix from the
    cross-covariance Cov(d_mn(q*), tau(q_i)).
    """
    n, N = X.shape
    elems = [(m, k) for m in range(N) for k in range(N)] if kind == 'full' else \
        [(k, k) for k in range(N)]
    sf2 = np.exp(hp['log_sf2'])
    ls = np.exp(hp['log_ls'])
    sn2 = np.exp(hp['log_sn2'])
    Ky = np.zeros((n * N, n * N))
    for e, (m, k) in enumerate(elems):
        ke = se_ard(X, X, ls[e], sf2[e]) * np.outer(X[:, k], X[:, k])
        Ky[m::N, m::N] += ke                        # K_tau: block of output m
    Ky += np.diag(np.repeat(sn2[None, :], n, axis=0).ravel())
    mu = (X * hp['mean']).ravel()
    alpha = np.linalg.solve(Ky, Y.ravel() - mu)     # dense, stacked
    k_ = Xs.shape[0]
    tau = (Xs * hp['mean'])
    D = np.zeros((k_, N, N))
    D[:, np.arange(N), np.arange(N)] = hp['mean']
    for e, (m, k) in enumerate(elems):
        Kd = se_ard(Xs, X, ls[e], sf2[e]) * X[:, k][None, :]   # Cov(d_mk(q*), tau_m(q_i))
        D[:, m, k] += Kd @ alpha[m::N]
    tau = np.einsum('kij,kj->ki', D, Xs)
    return tau, D


@pytest.mark.parametrize('kind', ['full', 'diag'])
@pytest.mark.parametrize('N', [1, 2, 3])
def test_block_solve_equals_dense_stacked(kind, N):
    rng = np.random.default_rng(N)
    X = rng.uniform(-2, 2, (25, N))
    Y = rng.standard_normal((25, N))
    Xs = rng.uniform(-3, 3, (30, N))
    hp = _hp(kind, N, rng)
    m = make_model(kind, passivity='none', hyperparams=hp).fit(X, Y, optimize=False)
    tau_ref, D_ref = _dense_reference(kind, hp, X, Y, Xs)
    tau = m.predict(Xs)
    D = m.damping_matrix(Xs)
    assert np.max(np.abs(tau - tau_ref)) <= 1e-8 * max(1.0, np.abs(tau_ref).max())
    assert np.max(np.abs(D - D_ref)) <= 1e-8 * max(1.0, np.abs(D_ref).max())
    # and tau = D q holds for the model itself
    assert np.allclose(np.einsum('kij,kj->ki', D, Xs), tau, rtol=1e-10, atol=1e-10)


def test_variance_matches_dense():
    rng = np.random.default_rng(5)
    X = rng.uniform(-2, 2, (20, 2))
    Y = rng.standard_normal((20, 2))
    Xs = rng.uniform(-2, 2, (7, 2))
    hp = _hp('full', 2, rng)
    m = FullDGP(passivity='none', hyperparams=hp).fit(X, Y, optimize=False)
    _, var = m.predict(Xs, return_var=True)
    sf2, ls, sn2 = np.exp(hp['log_sf2']), np.exp(hp['log_ls']), np.exp(hp['log_sn2'])
    for out in range(2):
        def k(A, B):
            return sum(se_ard(A, B, ls[out * 2 + j], sf2[out * 2 + j]) * np.outer(A[:, j], B[:, j])
                       for j in range(2))
        K = k(X, X) + sn2[out] * np.eye(20)
        Ks = k(Xs, X)
        ref = np.diag(k(Xs, Xs)) - np.einsum('ij,ji->i', Ks, np.linalg.solve(K, Ks.T))
        assert np.allclose(var[:, out], ref, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize('kind', ['full', 'diag', 'ard'])
def test_lml_gradient_matches_finite_differences(kind):
    rng = np.random.default_rng(1)
    N = 2
    X = rng.uniform(-1.5, 1.5, (30, N))
    y = np.sin(2 * X[:, 0]) * X[:, 1] + 0.1 * rng.standard_normal(30)
    s = Structure.of(kind, N)
    rows = s.rows[0]
    f = LmlObjective(X, y, [s.elems[e][1] for e in rows], N)
    theta = rng.uniform(-1, 0.5, len(rows) * (N + 1) + 1)
    _, g = f(theta)
    h = 1e-6
    fd = np.array([(f(theta + h * e)[0] - f(theta - h * e)[0]) / (2 * h)
                   for e in np.eye(theta.size)])
    assert np.allclose(g, fd, rtol=1e-4, atol=1e-6)
    if len(rows) > 1:                # tied: one lengthscale vector for the output's elements
        ft = LmlObjective(X, y, [s.elems[e][1] for e in rows], N, tied=True)
        th = np.concatenate([theta[:len(rows)], theta[len(rows):len(rows) + N], theta[-1:]])
        untied = np.concatenate([th[:len(rows)], np.tile(th[len(rows):-1], len(rows)), th[-1:]])
        v, gt = ft(th)
        assert np.isclose(v, f(untied)[0], rtol=1e-12)
        fdt = np.array([(ft(th + h * e)[0] - ft(th - h * e)[0]) / (2 * h)
                        for e in np.eye(th.size)])
        assert np.allclose(gt, fdt, rtol=1e-4, atol=1e-6)


def test_optimization_improves_likelihood_and_is_scale_invariant():
    Q, T = _data(60)
    m0 = FullDGP().fit(Q, T, optimize=False)
    m1 = FullDGP().fit(Q, T, optimize=True)
    assert m1.log_marginal_likelihood() > m0.log_marginal_likelihood()
    # rad vs m/s vs 1e5 N: rescaling inputs and outputs changes nothing relative
    S_in, S_out = np.array([0.01, 100.0]), np.array([1e5, 1e-3])
    m2 = FullDGP().fit(Q * S_in, T * S_out, optimize=True)
    Qt = np.random.default_rng(3).uniform(-2, 2, (50, 2))
    assert np.allclose(m2.predict(Qt * S_in) / S_out, m1.predict(Qt), rtol=1e-5, atol=1e-6)


def test_prior_mean_least_squares_and_clamp():
    rng = np.random.default_rng(0)
    Q = rng.standard_normal((100, 3))
    T = Q * np.array([2.0, -1.0, 0.5])
    md = prior_mean_diag(Q, T)
    assert np.allclose(md, [2.0, 0.0, 0.5])
    assert np.array_equal(prior_mean_diag(np.zeros((0, 3)), np.zeros((0, 3))), np.zeros(3))
    assert np.array_equal(prior_mean_diag(np.zeros((5, 2)), np.ones((5, 2))), np.zeros(2))


@pytest.mark.parametrize('kind', ['full', 'diag', 'ard'])
def test_update_matches_refit(kind):
    Q, T = _data(50)
    m = make_model(kind).fit(Q[:30], T[:30])
    for i in range(30, 50):
        m.update(Q[i], T[i])
    ref = make_model(kind, hyperparams=m.hyperparams_).fit(Q, T, optimize=False)
    Qt = np.random.default_rng(9).uniform(-2.5, 2.5, (200, 2))
    a, va = m.predict(Qt, return_var=True)
    b, vb = ref.predict(Qt, return_var=True)
    assert np.max(np.abs(a - b)) <= 1e-8 * max(1, np.abs(b).max())
    assert np.max(np.abs(va - vb)) <= 1e-8 * max(1, np.abs(vb).max())
    # batch update equals one-by-one
    m2 = make_model(kind).fit(Q[:30], T[:30]).update(Q[30:], T[30:])
    assert np.allclose(m2.predict(Qt), a, rtol=1e-10, atol=1e-10)


def test_window_matches_refit_on_window():
    Q, T = _data(80)
    m = FullDGP(window=25).fit(Q[:25], T[:25])
    for i in range(25, 80):
        m.update(Q[i], T[i])
    assert m.n_samples_ == 25
    assert np.array_equal(m.X_train_.round(12), Q[-25:].round(12))
    ref = FullDGP(hyperparams=m.hyperparams_).fit(Q[-25:], T[-25:], optimize=False)
    Qt = np.random.default_rng(2).uniform(-2, 2, (100, 2))
    assert np.max(np.abs(m.predict(Qt) - ref.predict(Qt))) <= 1e-8 * np.abs(ref.predict(Qt)).max()


@pytest.mark.parametrize('mode', PASSIVITY_MODES)
def test_save_load_round_trip_is_exact(tmp_path, mode):
    Q, T = _data(40)
    m = FullDGP(passivity=mode).fit(Q, T)
    m.update(Q[:3] * 0.9, T[:3])
    p = tmp_path / 'model.npz'
    m.save(p)
    r = FullDGP.load(p)
    Qt = np.random.default_rng(4).uniform(-3, 3, (100, 2))
    assert np.array_equal(m.predict(Qt), r.predict(Qt))
    assert np.array_equal(m.damping_matrix(Qt), r.damping_matrix(Qt))
    assert r.certificate().method == m.certificate().method
    with pytest.raises(ValueError, match='not a DiagDGP'):
        DiagDGP.load(p)


def test_tampered_truncated_and_foreign_files_raise_clear_errors(tmp_path):
    Q, T = _data(30)
    m = DiagDGP().fit(Q, T)
    p = tmp_path / 'm.npz'
    m.save(p)
    # tampered: an array changed, header kept
    with np.load(p, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays['alpha'] = arrays['alpha'] * 1.0001
    bad = tmp_path / 'tampered.npz'
    np.savez(bad, **arrays)
    with pytest.raises(ValueError, match='checksum mismatch'):
        load_model(bad)
    # incompatible version
    hdr = json.loads(str(arrays['header']))
    hdr['format_version'] = 99
    arrays['header'] = np.array(json.dumps(hdr))
    np.savez(tmp_path / 'v99.npz', **arrays)
    with pytest.raises(ValueError, match='format version 99'):
        load_model(tmp_path / 'v99.npz')
    # truncated
    raw = p.read_bytes()
    (tmp_path / 'trunc.npz').write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match='unreadable or truncated'):
        load_model(tmp_path / 'trunc.npz')
    # foreign: a pickled object array must not be loaded
    np.save(tmp_path / 'obj.npy', np.array([object()], dtype=object), allow_pickle=True)
    with zipfile.ZipFile(tmp_path / 'pickle.npz', 'w') as zf:
        zf.write(tmp_path / 'obj.npy', 'header.npy')
    with pytest.raises(ValueError):
        load_model(tmp_path / 'pickle.npz')
    with pytest.raises(ValueError, match='no such model file'):
        load_model(tmp_path / 'missing.npz')


@pytest.mark.parametrize('bad, match', [
    (lambda Q, T: (Q * np.nan, T), 'NaN or Inf'),
    (lambda Q, T: (Q, T[:-1]), 'samples'),
    (lambda Q, T: (Q[:0], T[:0]), 'empty'),
    (lambda Q, T: (Q[:, 0], T), '2-D'),
    (lambda Q, T: (Q, T[:, :1]), 'columns'),
    (lambda Q, T: (np.full(Q.shape, np.inf), T), 'NaN or Inf'),
])
def test_fit_input_validation(bad, match):
    Q, T = _data(10)
    with pytest.raises(ValueError, match=match):
        FullDGP().fit(*bad(Q, T))


def test_predict_and_update_validation():
    Q, T = _data(10)
    m = FullDGP().fit(Q, T)
    with pytest.raises(ValueError, match='columns'):
        m.predict(np.zeros((3, 3)))
    with pytest.raises(ValueError, match='NaN'):
        m.predict([np.nan, 0.0])
    with pytest.raises(ValueError, match='NaN'):
        m.update([0.0, 1.0], [np.inf, 0.0])
    with pytest.raises(RuntimeError, match='not fitted'):
        FullDGP().predict([[0.0, 0.0]])
    with pytest.raises(ValueError, match='passivity'):
        FullDGP(passivity='maybe').fit(Q, T)
    with pytest.raises(ValueError, match="'ard'"):
        ArdGP(passivity='certified').fit(Q, T)
    with pytest.raises(NotImplementedError):
        ArdGP().fit(Q, T).damping_matrix(Q)
    assert m.predict(Q[0]).shape == (1, 2)


def test_copositivity_margin_is_exact_against_sampling():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((200, 3, 3))
    marg = copositivity_margin(A)
    Z = np.abs(rng.standard_normal((20000, 3)))
    Z /= np.linalg.norm(Z, axis=1, keepdims=True)
    for k in range(200):
        sampled = np.einsum('ij,jk,ik->i', Z, A[k], Z).min()
        assert marg[k] <= sampled + 1e-12          # a lower bound of every sample...
        assert sampled - marg[k] < 0.05            # ...and tight
    assert copositivity_margin(np.array([[1.0, -1.0], [-1.0, 1.0]])) == \
        pytest.approx(0.0, abs=1e-12)
    assert copositivity_margin(np.array([[0.0, 1.0], [1.0, 0.0]])) >= 0   # copositive, not PSD


@pytest.mark.parametrize('N', [2, 3, 5, 7])
def test_copositivity_margin_of_z_matrices_is_their_least_eigenvalue(N):
    # diag(m) - B with B >= 0 (the a-posteriori bound's matrix) takes the least-eigenvalue path;
    # it must agree with Kaplan's enumeration of principal submatrices, done here by hand
    from itertools import combinations
    rng = np.random.default_rng(N)
    for _ in range(40):
        A = np.diag(rng.uniform(0.1, 3.0, N)) - rng.uniform(0, 1, (N, N)) * rng.uniform(0, 1.5)
        S = 0.5 * (A + A.T)
        kaplan = np.inf
        for r in range(1, N + 1):
            for sub in combinations(range(N), r):
                w, V = np.linalg.eigh(S[np.ix_(sub, sub)])
                pos = np.all(V > 0, axis=0) | np.all(V < 0, axis=0)
                kaplan = min(kaplan, w[pos].min(initial=np.inf))
        assert copositivity_margin(A) == pytest.approx(kaplan, rel=1e-10, abs=1e-12)


@pytest.mark.parametrize('window', [None, 7, 40])
def test_window_cholesky_equals_fresh_factorization(window):
    """
    Check the in-place append and drop-oldest against a fresh Cholesky.

    In-place append / drop-oldest (buffer growth and block moves included) against a fresh
    Cholesky of the same kernel window, factor and alpha = K^-1 r.
    """
    from scipy.linalg import cho_solve, cholesky

    from dgp_ros.gp._chol import WindowCholesky
    rng = np.random.default_rng(4)
    X = rng.uniform(-1, 1, (260, 2))
    r = rng.standard_normal(260)
    sn2 = 1e-3
    K = se_ard(X, X, np.array([0.4, 0.7]), 1.3) + sn2 * np.eye(260)
    lo, hi = 0, 3
    wc = WindowCholesky(cholesky(K[:3, :3], lower=True), r[:3],
                        limit=None if window is None else window + 1)
    caps = set()
    for i in range(3, 260):
        wc.append(K[lo:hi, i], K[i, i], sn2, r[i])
        hi += 1
        if window is not None and hi - lo > window:
            wc.drop_first()
            lo += 1
        caps.add(wc.capacity)
        if i % 23 == 0 or i == 259:
            L = cholesky(K[lo:hi, lo:hi], lower=True)
            assert wc.n == hi - lo
            assert np.max(np.abs(wc.L - L)) <= 1e-10 * np.abs(L).max()
            a = cho_solve((L, True), r[lo:hi])
            assert np.max(np.abs(wc.alpha() - a)) <= 1e-8 * np.abs(a).max()
    if window is None:
        assert len(caps) > 3                      # grew several times
    else:
        assert max(caps) <= window + 1 + max(8, (window + 1) // 8)   # bounded memory


def test_window_cholesky_clamps_an_exact_duplicate():
    from scipy.linalg import cholesky

    from dgp_ros.gp._chol import WindowCholesky
    X = np.array([[0.0, 0.0], [1.0, 0.5]])
    sn2 = 1e-6
    K = se_ard(X, X, np.ones(2), 1.0) + sn2 * np.eye(2)
    wc = WindowCholesky(cholesky(K, lower=True), np.array([1.0, 2.0]), limit=3)
    c = se_ard(X, X[:1], np.ones(2), 1.0)[:, 0]
    wc.append(c, 1.0 + sn2, sn2, 1.0)           # the first sample again
    d = wc.diag()
    assert np.all(np.isfinite(wc.alpha())) and d[-1] >= np.sqrt(sn2) * (1 - 1e-12)
    with pytest.raises(ValueError, match='rows'):
        wc.solve(np.ones(5))


@pytest.mark.parametrize('kind', ['full', 'diag', 'ard'])
@pytest.mark.parametrize('passivity', ['none', 'projected'])
def test_predict_with_damping_equals_separate_calls_and_batch_path(kind, passivity):
    """
    Check the one-pass per-message path against the other paths.

    The one-pass per-message path (all element kernels at once, exact differences) agrees
    with predict + damping_matrix, and with the large-batch GEMM path.
    """
    Q, T = _data(60)
    m = make_model(kind, passivity=passivity).fit(Q, T)
    Qs = np.random.default_rng(3).uniform(-3, 3, (25, 2))
    tau, var, D = m.predict_with_damping(Qs)
    t2, v2 = m.predict(Qs, return_var=True)
    assert np.array_equal(tau, t2) and np.array_equal(var, v2)
    if kind == 'ard':
        assert D is None
    else:
        assert np.array_equal(D, m.damping_matrix(Qs))
        assert np.allclose(np.einsum('kij,kj->ki', D, Qs), tau, rtol=1e-9, atol=1e-9)
    # more than 16 queries at once take the per-element GEMM path
    t3, v3 = (a[:25] for a in m.predict(np.vstack([Qs, Qs]), return_var=True))
    scale = np.abs(t3).max()
    assert np.max(np.abs(t3 - tau)) <= 1e-9 * scale
    assert np.max(np.abs(v3 - var)) <= 1e-9 * max(np.abs(v3).max(), 1e-300) + 1e-12 * scale ** 2


def test_rkhs_norms_kept_from_the_factorization_equal_a_rebuild():
    """
    The certificate's RKHS norms are taken from the element kernels of the fit.

    They must equal a^T K_e a rebuilt from scratch (and be recomputed, not reused, after an
    update).
    """
    Q, T = _data(60, N=3)
    m = FullDGP(passivity='none', n_restarts=0).fit(Q, T)
    p = m.posterior_
    cached = p.rkhs_sq().copy()
    s, hp = p.structure, p.hyper
    rebuilt = np.zeros(s.E)
    for e, (out, n) in enumerate(s.elems):
        a = p.X[:, n] * p.alpha[:, out]
        rebuilt[e] = a @ se_ard(p.X, p.X, np.exp(hp.log_ls[e]), np.exp(hp.log_sf2[e])) @ a
    assert np.allclose(cached, rebuilt, rtol=1e-10, atol=1e-12) and np.all(cached > 0)
    m.update(Q[:2] * 0.7, T[:2])
    assert not np.allclose(m.posterior_.rkhs_sq(), cached, rtol=1e-6)


def test_get_and_set_params_round_trip_without_refit():
    m = FullDGP(passivity='projected', window=50)
    p = m.get_params()
    assert p['passivity'] == 'projected' and p['window'] == 50 and p['prior'] == 'viscous'
    Q, T = _data(30)
    m.fit(Q, T)
    before = m.predict(Q)
    m.set_params(window=10, n_restarts=0)
    assert m.get_params()['window'] == 10
    assert np.array_equal(m.predict(Q), before)        # takes effect at the next fit only
    with pytest.raises(ValueError, match='unknown'):
        m.set_params(windw=3)
    clone = FullDGP(**m.get_params())
    assert clone.get_params() == m.get_params()


def test_friction_prior_stays_bounded_without_slow_samples():
    """
    A joint seen only at |v| in [0.24, 0.5] one way (the start of a trajectory).

    The Stribeck term must not explode towards qd = 0, and no bias is learned (it cannot be told
    apart from Coulomb friction); found by bench/hostile.py (128 N m towards qd = 0 from 1 N m of
    data).
    """
    from dgp_ros.gp.means import make_mean
    rng = np.random.default_rng(0)
    for seed in range(20):
        rng = np.random.default_rng(seed)
        v = rng.uniform(0.24, 0.5, (60, 1)) * rng.choice([-1.0, 1.0])
        tau = 0.5 * v + 0.3 * np.sign(v) + 0.2 * np.sin(9 * v) + rng.normal(0, 0.02, v.shape)
        m = make_mean('friction+stribeck', 'full', bias=True).fit(v, tau)
        assert m.bias[0] == 0.0
        grid = np.linspace(-1.0, 1.0, 2001)[:, None]
        f = m.force(grid)
        assert np.all(np.abs(f) <= 2.0 * np.abs(tau).max() + 0.5 * np.abs(grid)), seed
        assert np.all(f * grid >= 0)


def test_friction_prior_learns_a_bias_once_both_directions_are_seen():
    from dgp_ros.gp.means import make_mean
    rng = np.random.default_rng(1)
    v = rng.uniform(-1, 1, (300, 2))
    tau = 0.8 * v + 0.4 * np.tanh(v / 0.02) + np.array([-0.2, 0.3]) + rng.normal(0, 0.02, v.shape)
    m = make_mean('friction+stribeck', 'full', bias=True).fit(v, tau)
    np.testing.assert_allclose(m.bias, [-0.2, 0.3], atol=0.03)


@pytest.mark.parametrize('kind', ['full', 'diag', 'ard'])
@pytest.mark.parametrize('passivity', ['none', 'projected', 'certified'])
def test_the_lean_message_path_equals_the_full_one(kind, passivity):
    """
    Check that the lean message path equals the full one.

    Without variance (what the node computes when nobody subscribes to the stddev) the
    force and the damping matrix come from one einsum over the element kernels: equal to the
    per-output loop, for 1..16 queries, also after updates and with switched-off elements.
    """
    if kind == 'ard' and passivity == 'certified':
        pytest.skip('ARD cannot be certified')
    Q, T = _data(60)
    m = make_model(kind, passivity=passivity).fit(Q, T)
    rng = np.random.default_rng(5)
    for step in range(3):
        for k in (1, 5, 16):
            Qs = rng.uniform(-3, 3, (k, 2))
            tau, var, D = m.predict_with_damping(Qs)
            t2, v2, D2 = m.predict_with_damping(Qs, return_var=False)
            assert v2 is None
            scale = max(np.abs(tau).max(), 1e-300)
            assert np.max(np.abs(t2 - tau)) <= 1e-12 * scale
            if kind != 'ard':
                assert np.max(np.abs(D2 - D)) <= 1e-12 * max(np.abs(D).max(), 1e-300)
            _, _, D3 = m.predict_with_damping(Qs, return_var=False, return_damping=False)
            assert D3 is None
        m.update(rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2))


@pytest.mark.parametrize('kind', ['full', 'ard'])
def test_large_batches_are_predicted_in_chunks_with_the_same_result(kind, monkeypatch):
    """
    Predict large batches in chunks, with the result of one pass.

    A million-query passivity check at n = 500 built (k, n) kernels at once (24 GB, OOM).
    """
    import dgp_ros.gp.models as models
    Q, T = _data(60)
    m = make_model(kind, passivity='projected').fit(Q, T)
    Qs = np.random.default_rng(9).uniform(-3, 3, (1000, 2))
    tau, var = m.predict(Qs, return_var=True)
    D = m.damping_matrix(Qs) if kind != 'ard' else None
    monkeypatch.setattr(models, 'CHUNK_ELEMENTS', 60 * 300)        # 300 rows per chunk
    t2, v2 = m.predict(Qs, return_var=True)
    np.testing.assert_allclose(t2, tau, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(v2, var, rtol=1e-12, atol=1e-12)
    t3, v3, D3 = m.predict_with_damping(Qs, return_var=False)
    assert v3 is None and t3.shape == tau.shape
    np.testing.assert_allclose(t3, tau, rtol=1e-12, atol=1e-12)
    if kind != 'ard':
        np.testing.assert_allclose(m.damping_matrix(Qs), D, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(D3, D, rtol=1e-12, atol=1e-12)

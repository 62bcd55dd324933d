"""
More than three velocities: the damping matrix is made positive semi-definite where it is not.

The smooth eigenvalue floor (``dgp_ros.gp.psd``) and the certified policy that uses it, checked on
many random matrices and on random velocities inside and far outside the data.
"""
import numpy as np
import pytest

from dgp_ros.gp import DiagDGP, FullDGP
from dgp_ros.gp.psd import psd_clip, smooth_floor


def _sym_min_eig(D):
    return np.linalg.eigvalsh(0.5 * (D + np.swapaxes(D, 1, 2)))[:, 0]


def test_smooth_floor_is_a_c1_majorant_of_the_clip():
    delta = 0.3
    lam = np.linspace(-2, 2, 400_001)
    f = lam + smooth_floor(lam, delta)
    assert np.all(f >= np.maximum(lam, 0.0))                     # never below the clip
    assert np.array_equal(f[lam >= delta], lam[lam >= delta])     # the identity above delta
    assert np.all(f[lam <= -delta] == 0.0)
    h = lam[1] - lam[0]
    df = np.diff(f) / h
    assert np.abs(np.diff(f)).max() < 2 * h                       # continuous
    assert np.abs(np.diff(df)).max() < 1e-3                       # and so is its slope
    with pytest.raises(ValueError):
        psd_clip(np.zeros((1, 2, 2)), 0.0)


@pytest.mark.parametrize('N', [2, 4, 7])
def test_psd_clip_makes_random_matrices_psd_and_leaves_the_others(N):
    rng = np.random.default_rng(N)
    k, delta = 20_000, 1e-3
    A = rng.normal(size=(k, N, N))
    D = A + np.eye(N) * rng.uniform(-1.0, 4.0, (k, 1, 1))        # many indefinite, many not
    lam0 = _sym_min_eig(D)
    assert np.mean(lam0 < 0) > 0.1 and np.mean(lam0 > delta) > 0.1
    P, touched = psd_clip(D, delta)
    lam = _sym_min_eig(P)
    scale = np.abs(D).max(axis=(1, 2))
    assert np.all(lam >= -1e-13 * scale)
    keep = lam0 >= delta
    assert np.array_equal(P[keep], D[keep]) and not np.any(touched[keep])
    assert np.all(touched[lam0 < 0])
    # the change is the smallest eigenvalue shift that can do it (at most max(delta, -lam_min))
    change = np.linalg.norm(P - D, ord=2, axis=(1, 2))
    assert np.all(change <= np.maximum(delta, -lam0) * (1 + 1e-9) + 1e-12)
    # the antisymmetric part (no work) is untouched
    np.testing.assert_allclose(P - np.swapaxes(P, 1, 2), D - np.swapaxes(D, 1, 2), atol=1e-12)


def _arm(n=200, N=7, seed=2):
    """Friction of 7 joints with a non-passive patch (as the real Panda residual has)."""
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-1, 1, (n, N))
    T = Q * np.linspace(0.5, 2.0, N) + 0.3 * np.tanh(Q / 0.05)
    T[:, 1] -= 2.0 * np.exp(-(Q[:, 1] - 0.3) ** 2 / 0.1) * np.sign(Q[:, 1])
    return Q, T + 0.05 * rng.normal(size=Q.shape)


@pytest.mark.parametrize('cls', [FullDGP, DiagDGP])
def test_seven_joints_are_psd_everywhere_and_unchanged_where_they_were(cls, tmp_path):
    Q, T = _arm()
    base = cls(passivity='none', n_restarts=0, max_opt_samples=120).fit(Q, T)
    m = cls(passivity='certified', hyperparams=base.hyperparams_).fit(Q, T, optimize=False)
    c = m.certificate()
    assert c.certified and c.method == 'psd-clip' and c.guarantee == 'psd' and c.domain is None
    delta = c.details['delta']
    # touched: exactly the training samples where the fit's D was below the floor (none on
    # some BLAS builds: the optimized hyper-parameters differ by machine)
    below = _sym_min_eig(base.damping_matrix(Q)) < delta
    assert c.details['touched_fraction_of_samples'] == pytest.approx(np.mean(below))
    assert np.mean(below) < 1
    rng = np.random.default_rng(0)
    inside = rng.uniform(-1, 1, (10_000, 7))
    outside = rng.uniform(-10, 10, (10_000, 7))
    for X in (inside, outside):
        D = m.damping_matrix(X)
        assert np.all(_sym_min_eig(D) >= -1e-12 * np.abs(D).max())
        assert np.einsum('ij,ij->i', X, m.predict(X)).min() >= 0
        if X is inside:
            Dm = D
    D0 = base.damping_matrix(inside)
    lam0 = _sym_min_eig(D0)
    assert np.mean(lam0 < 0) > 0.001                      # the fit was not PSD everywhere
    keep = lam0 >= delta
    np.testing.assert_array_equal(Dm[keep], D0[keep])
    np.testing.assert_allclose(m.predict(inside)[keep], base.predict(inside)[keep],
                               rtol=1e-12, atol=1e-12)
    # a certificate of this kind holds for any weights: updates never make it stale
    for i in range(5):
        m.update(inside[i], -inside[i])                   # energy-injecting samples
        assert m.certificate().certified and not m.certificate().stale
    D = m.damping_matrix(inside[:3000])
    assert np.all(_sym_min_eig(D) >= -1e-12 * np.abs(D).max())
    # and a model read from a file is certified at once, with the same answers
    m.save(tmp_path / 'm.npz')
    r = cls.load(tmp_path / 'm.npz')
    assert r.certificate().certified and r.certificate().method == 'psd-clip'
    np.testing.assert_array_equal(r.predict(inside[:5000]), m.predict(inside[:5000]))


def test_certified_is_the_library_default_for_damping_models():
    from dgp_ros.gp import ArdGP
    assert FullDGP().passivity == 'certified' and DiagDGP().passivity == 'certified'
    a = ArdGP()
    assert a.passivity == 'none'                      # no damping matrix to certify
    assert set(a.get_params()) == set(FullDGP().get_params())
    assert ArdGP(**a.get_params()).get_params() == a.get_params()
    Q, T = _arm(n=80, N=4)
    c = FullDGP(n_restarts=0, max_opt_samples=60).fit(Q, T).certificate()
    assert c.certified and c.guarantee == 'psd'

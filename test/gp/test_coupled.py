"""The prior's couplings through a persistent column (gp/coupled.py): passivity, bounds, files."""
import numpy as np
import pytest

from dgp_ros.gp import make_model
from dgp_ros.gp.coupled import BOX_MARGIN, CoupledMean, CouplingBasis
from dgp_ros.gp.means import BasisFrictionMean, mean_from_dict


def aircraft(t):
    """
    Return an aircraft-like stream at times t (k,): velocities [alpha, beta, airspeed], forces.

    Drag, side force and lift are dynamic pressure times polynomials in alpha and beta (the
    couplings' own form), so the part can learn them; alpha crosses zero, beta reverses, the
    airspeed never nears zero.
    """
    t = np.asarray(t, float)
    a = 0.05 + 0.07 * np.sin(0.5 * t + 1.0)
    b = 0.03 * np.sin(0.7 * t)
    V = 90.0 + 6.0 * np.sin(0.3 * t)
    qS = 0.5 * 1.225 * V * V * 122.6
    drag = qS * (0.03 + 0.6 * a * a + 0.4 * b * b + 0.05 * a)
    side = qS * (-0.8 * b + 0.1 * a * b)
    lift = qS * (0.4 + 5.0 * a - 2.0 * a ** 3 + 0.3 * np.abs(b))
    return np.stack([a, b, V], axis=1), np.stack([drag, -side, lift], axis=1)


def _mean(seed=0, scale=1.0, box=True):
    """Return a coupled prior of 3 velocities with random weights (large: raw power < 0)."""
    rng = np.random.default_rng(seed)
    base = BasisFrictionMean(np.abs(rng.normal(0.0, 0.3, (3, 4))), (0.01, 0.05), 0.01, (0.1,))
    basis = CouplingBasis(3, [2], [90.0])
    if box:
        basis = basis.boxed([-0.1, -0.05, 80.0], [0.2, 0.05, 100.0])
    W = scale * rng.normal(0.0, 1e4, (3, basis.K))
    return CoupledMean(base, basis, W)


def _velocities(rng, k, spread):
    Q = rng.standard_normal((k, 3)) * np.array([0.1, 0.05, 10.0]) * spread
    Q[:, 2] += 90.0 * rng.choice([1.0, -1.0, 0.0], k)
    return Q * rng.choice([1e-4, 1e-2, 1.0, 1e2], (k, 1))


@pytest.mark.parametrize('spread', [1.0, 1e3], ids=['inside', 'far outside'])
def test_the_coupled_prior_is_passive_everywhere_and_its_matrix_gives_its_force(spread):
    m = _mean()
    rng = np.random.default_rng(1)
    Q = _velocities(rng, 50000, spread)
    f = m.force(Q)
    M = m.matrix(Q)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(M))
    power = np.einsum('kn,kn->k', Q, f)
    assert np.all(power >= -1e-12 * np.abs(Q * f).sum(axis=1))
    assert np.allclose(np.einsum('kij,kj->ki', M, Q), f, rtol=1e-9,
                       atol=1e-9 * np.abs(f).max())
    # the couplings matter: the raw force is not passive somewhere (the projection acts)
    raw = np.einsum('kn,kn->k', Q, m.raw_force(Q))
    assert np.mean(raw < 0) > 0.01
    # and the diagonal of the matrix is what diag says
    assert np.allclose(m.diag(Q[:100]), M[:100][:, np.arange(3), np.arange(3)])


@pytest.mark.parametrize('box', [True, False])
def test_matrix_bounds_enclose_the_raw_matrix_on_random_boxes(box):
    m = _mean(seed=3, box=box)
    rng = np.random.default_rng(4)
    for width in (1e-3, 0.1, 1.0, 30.0):
        c = rng.normal(0.0, 1.0, (200, 3)) * np.array([0.1, 0.05, 20.0]) + [0.0, 0.0, 90.0]
        lo = c - width * rng.uniform(0, 1, (200, 3)) * [0.1, 0.05, 5.0]
        hi = c + width * rng.uniform(0, 1, (200, 3)) * [0.1, 0.05, 5.0]
        Mlo, Mhi = m.matrix_bounds(lo, hi)
        for t in rng.uniform(0.0, 1.0, (40, 1, 3)):
            M = m.raw_matrix(lo + t * (hi - lo))
            tol = 1e-9 * np.abs(M).max()
            assert np.all(M >= Mlo - tol) and np.all(M <= Mhi + tol)


def test_the_box_holds_the_couplings_at_what_was_learned():
    m = _mean(seed=5)
    lo, hi = m.basis.box
    assert np.allclose(lo, np.array([-0.1, -0.05, 80.0]) - BOX_MARGIN * np.array([0.3, 0.1, 20.0]))
    inside = np.array([[0.05, 0.0, 95.0]])
    far = np.array([[5.0, 0.0, 95.0]])              # alpha far beyond the box: clipped to it
    edge = np.array([[hi[0], 0.0, 95.0]])

    def couplings(Q):
        return m.raw_force(Q) - m.base.force(Q)
    assert np.allclose(couplings(far), couplings(edge))
    assert not np.allclose(couplings(inside), couplings(edge))
    # the persistent column itself is not clipped (dynamic pressure: v_p^2)
    fast = np.array([[0.05, 0.0, 300.0]])
    assert np.allclose(couplings(fast), couplings(inside) * (300.0 / 95.0) ** 2)


def test_a_coupled_prior_round_trips_through_its_record():
    m = _mean(seed=6)
    back = mean_from_dict(m.to_dict(), 3)
    assert isinstance(back, CoupledMean) and not back.is_diagonal
    Q = _velocities(np.random.default_rng(7), 500, 1.0)
    assert np.array_equal(back.force(Q), m.force(Q))
    assert np.array_equal(back.matrix(Q), m.matrix(Q))
    with pytest.raises(ValueError):
        CoupledMean(m.base, m.basis, np.zeros((3, 5)))
    with pytest.raises(ValueError):
        CouplingBasis(3, [2], [0.0])
    with pytest.raises(ValueError):
        CoupledMean(m, m.basis, m.W)              # the base must be diagonal


def _fitted_model(n=150):
    """Return a Full-D-GP on an aircraft-like stream with a coupled prior fitted to it."""
    t = np.linspace(0.0, 12.0, n)
    Q, T = aircraft(t)
    basis = CouplingBasis(3, [2], [Q[0, 2]])
    Phi = basis.columns(Q)
    W = np.linalg.lstsq(Phi, T, rcond=None)[0].T
    base = BasisFrictionMean(np.zeros((3, 1)), (), 0.01, ())
    prior = CoupledMean(base, basis.boxed(Q.min(axis=0), Q.max(axis=0)), W)
    model = make_model('full', prior=prior, bias=False).fit(Q, T)
    return model, Q, T


def test_a_model_with_a_coupled_prior_is_proven_on_its_domain_and_passive_outside():
    model, Q, T = _fitted_model()
    cert = model.certificate()
    # no global bound for a non-diagonal prior; the domain proof (3 velocities) holds
    assert cert.method == 'domain-bnb+blend' and cert.certified
    assert cert.guarantee == 'passive-on-domain'
    rng = np.random.default_rng(8)
    for spread in (1.0, 1e3):
        Qr = _velocities(rng, 20000, spread)
        tau, _, D = model.predict_with_damping(Qr, False, True)
        power = np.einsum('kn,kn->k', Qr, tau)
        assert np.all(power >= -1e-9 * np.abs(Qr * tau).sum(axis=1))
        assert np.allclose(np.einsum('kij,kj->ki', D, Qr), tau, rtol=1e-7,
                           atol=1e-7 * np.abs(tau).max())
    # held out: the stream's continuation is answered near the truth
    Qh, Th = aircraft(np.linspace(12.0, 14.0, 60))
    err = ((model.predict(Qh) - Th) ** 2).mean(axis=0) / Th.var(axis=0)
    assert np.all(err < 0.05), err


def test_a_model_with_a_coupled_prior_saves_and_loads(tmp_path):
    from dgp_ros.gp import load_model
    model, Q, T = _fitted_model()
    path = str(tmp_path / 'm.npz')
    model.save(path)
    back = load_model(path)
    Qr = _velocities(np.random.default_rng(9), 300, 1.0)
    assert isinstance(back.mean_, CoupledMean)
    assert np.allclose(back.predict(Qr), model.predict(Qr), rtol=1e-9,
                       atol=1e-9 * np.abs(model.predict(Qr)).max())


def test_paper_mode_refuses_a_coupled_prior():
    t = np.linspace(0.0, 5.0, 40)
    Q, T = aircraft(t)
    m = _mean()
    with pytest.raises(ValueError, match='diagonal'):
        make_model('full', prior=m, bias=False, passivity='paper').fit(Q, T)


def test_remean_equals_a_fit_with_the_new_prior_at_the_same_kernel():
    fitted, Q, T = _fitted_model()
    # projected answers: a certified model's blend outside its domain belongs to its proof
    model = make_model('full', prior=fitted.mean_, bias=False, passivity='projected',
                       hyperparams=fitted.hyperparams_).fit(Q, T, optimize=False)
    other = CoupledMean(model.mean_.base, model.mean_.basis, model.mean_.W * 1.05)
    hp = dict(model.hyperparams_, mean=other.to_dict())
    ref = make_model('full', prior=other, bias=False, passivity='projected',
                     hyperparams=hp).fit(Q, T, optimize=False)
    model.remean(other)
    assert fitted.remean(other).certificate().stale     # a domain proof must be made again
    Qt = _velocities(np.random.default_rng(10), 400, 1.0)
    a, va = model.predict(Qt, return_var=True)
    b, vb = ref.predict(Qt, return_var=True)
    scale = np.abs(b).max()
    assert np.allclose(a, b, rtol=1e-8, atol=1e-8 * scale)
    assert np.allclose(va, vb, rtol=1e-8, atol=1e-12 * scale ** 2)
    # the training data are the same data: the forces come back through the new prior
    assert np.allclose(model.Y_train_, T, rtol=1e-9, atol=1e-9 * np.abs(T).max())

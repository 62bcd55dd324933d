"""The per-joint element of D (gp/joint_element.py): passivity, bounds, files, its fit."""
import numpy as np
import pytest

from dgp_ros.gp.joint_element import (_prior, _solve, agreement, ElementFold, fit_elements,
                                      JointElementMean, M_BASIS, VelocityBasis)
from dgp_ros.gp.means import BasisFrictionMean, mean_from_dict


def _mean(N=3, seed=0, scale=3.0, decay=0.0):
    """
    Return a friction prior with random elements on joints 0 and 2 (large: the sum goes < 0).

    decay: the weights fall as ``k^-decay`` (a fitted element's do: the SE spectrum).
    """
    rng = np.random.default_rng(seed)
    base = BasisFrictionMean(np.abs(rng.normal(0.0, 0.3, (N, 4))), (0.01, 0.05), 0.01, (0.1,))
    W = np.zeros((N, M_BASIS))
    W[[0, 2]] = scale * rng.normal(size=(2, M_BASIS)) / np.arange(1, M_BASIS + 1) ** decay
    return JointElementMean(base, VelocityBasis(rng.uniform(0.3, 2.0, N)), W)


def _velocities(rng, k, N, spread):
    return rng.standard_normal((k, N)) * spread * rng.choice([1e-4, 1e-2, 1.0, 1e2], (k, 1))


@pytest.mark.parametrize('spread', [1.0, 1e3], ids=['inside', 'far outside'])
def test_the_prior_with_elements_is_passive_everywhere(spread):
    m = _mean()
    rng = np.random.default_rng(1)
    V = _velocities(rng, 50000, 3, spread)
    d = m.diag(V)
    assert np.all(np.isfinite(d)) and np.all(d >= 0.0)
    assert np.all(np.einsum('kn,kn->k', V, m.force(V)) >= 0.0)
    # the elements do change the damping (they are not floored away everywhere)
    assert np.mean(m.diag(V)[:, 0] != m.base.diag(V)[:, 0]) > 0.5


def _enclosed(m, rng, width, spread, boxes, points):
    """Check ``m.diag_bounds`` on random boxes at ``points`` points each; (lo, hi, dlo, dhi)."""
    c = rng.normal(0.0, spread, (boxes, 3))
    lo, hi = c - width * rng.uniform(0, 1, (boxes, 3)), c + width * rng.uniform(0, 1, (boxes, 3))
    dlo, dhi = m.diag_bounds(lo, hi)
    for t in rng.uniform(0.0, 1.0, (points, 1, 3)):
        d = m.diag(lo + t * (hi - lo))
        assert np.all(d >= dlo - 1e-12) and np.all(d <= dhi + 1e-12)
    return lo, hi, dlo, dhi


@pytest.mark.parametrize('decay', [0.0, 2.0])
def test_diag_bounds_enclose_every_value_of_the_box_and_shrink_with_it(decay):
    m = _mean(seed=3, scale=1.0, decay=decay)
    rng = np.random.default_rng(4)
    for width in (1e-3, 0.1, 1.0, 50.0):
        lo, hi, dlo, dhi = _enclosed(m, rng, width, 1.0, 200, 50)
        if width == 1e-3 and decay:     # tight on small boxes away from rest (steep t(v) there)
            far = np.all(np.minimum(np.abs(lo), np.abs(hi)) > 0.2, axis=1)
            assert far.sum() > 20
            assert np.max((dhi - dlo)[far]) < 0.05 * np.max(dhi[far])


def test_diag_inf_is_a_lower_bound_of_the_damping():
    m = _mean(seed=5, scale=0.5)
    v = np.concatenate([-np.logspace(-6, 4, 20001), np.logspace(-6, 4, 20001), [0.0]])
    lower = m.diag_inf()
    assert np.all(lower >= 0.0)
    assert np.all(m.diag(np.repeat(v[:, None], 3, axis=1)).min(axis=0) >= lower - 1e-12)
    # the joint without an element keeps its base's infimum
    assert lower[1] == pytest.approx(m.base.diag_inf()[1])


def test_the_element_fades_beyond_the_speeds_it_was_learned_on():
    m = _mean(seed=7, scale=0.5)
    e = np.abs(m.element_force(np.full((1, 3), 1e4)))
    assert np.all(e < 1e-3 * np.abs(m.W).sum(axis=1).max())


def test_a_model_file_keeps_the_elements(tmp_path):
    m = _mean(seed=8)
    m2 = mean_from_dict(m.to_dict(), N=3)
    assert isinstance(m2, JointElementMean) and isinstance(m2.base, BasisFrictionMean)
    V = np.random.default_rng(9).normal(0.0, 1.0, (500, 3))
    np.testing.assert_array_equal(m2.diag(V), m.diag(V))


def test_agreement_is_zero_for_identical_halves_and_large_for_opposite_ones():
    b = VelocityBasis(np.ones(1))
    rng = np.random.default_rng(0)
    X = np.c_[b.columns(rng.normal(size=(300, 1)))[:, 0, :], np.ones(300)]
    y = X[:, :M_BASIS] @ (rng.normal(size=M_BASIS) / np.arange(1, M_BASIS + 1))
    prior = _prior(b, 0.2, 10.0)
    G = X.T @ X
    same = ElementFold(G, X.T @ y)
    w = _solve(G, X.T @ y, prior)[:M_BASIS]
    assert agreement(G[:M_BASIS, :M_BASIS], w, [same, same], prior) == 0.0
    flip = ElementFold(G, -(X.T @ y))
    assert agreement(G[:M_BASIS, :M_BASIS], w, [same, flip], prior) > 1.5


def test_fit_elements_keeps_none_without_folds():
    b = VelocityBasis(np.ones(2))
    G = np.eye(M_BASIS + 1)
    full = [ElementFold(G, np.ones(M_BASIS + 1))] * 2
    fit = fit_elements(b, full, [[], []])
    assert not fit.on.any() and np.all(np.isnan(fit.scores))


def _spanned(seed=11):
    m = _mean(seed=seed, scale=1.0)
    span = (np.array([-0.8, -1.0, -0.3]), np.array([0.6, 1.0, 1.2]))
    return m, JointElementMean(m.base, m.basis, m.W, span=span), span


def test_beyond_its_span_the_element_keeps_its_edge_value_and_hands_back():
    m, s, (lo, hi) = _spanned()
    rng = np.random.default_rng(12)
    inside = rng.uniform(lo, hi, (2000, 3))
    np.testing.assert_array_equal(s.diag(inside), m.diag(inside))
    out = np.concatenate([rng.uniform(hi + 0.01, hi + 5.0, (500, 3)),
                          rng.uniform(lo - 5.0, lo - 0.01, (500, 3))])
    edge = np.clip(out, lo, hi)
    # g at the edge, times tanh(|v| / eps) / |v| at the velocity itself
    t = np.tanh(np.abs(out) / s.basis.eps) / np.abs(out)
    t_edge = np.tanh(np.abs(edge) / s.basis.eps) / np.abs(edge)
    np.testing.assert_allclose(s.element_diag(out), m.element_diag(edge) * t / t_edge,
                               rtol=1e-9, atol=1e-12)
    # so the element's force does not grow past the edge (the parametric part answers)
    f_far = np.abs(s.element_force(np.array([hi * 20.0])))[0]
    f_edge = np.abs(s.element_force(np.array([hi])))[0]
    assert np.all(f_far <= f_edge * 1.0001 + 1e-12)
    assert np.all(s.diag(out) >= 0.0) and np.all(np.einsum('kn,kn->k', out, s.force(out)) >= 0)


def test_bounds_and_files_with_a_span():
    _, s, _ = _spanned(13)
    rng = np.random.default_rng(14)
    for width in (1e-3, 0.3, 5.0):
        _enclosed(s, rng, width, 1.5, 300, 40)
    v = np.concatenate([-np.logspace(-6, 4, 5001), np.logspace(-6, 4, 5001)])
    assert np.all(s.diag(np.repeat(v[:, None], 3, axis=1)).min(axis=0) >= s.diag_inf() - 1e-12)
    s2 = mean_from_dict(s.to_dict(), N=3)
    V = rng.normal(0.0, 3.0, (500, 3))
    np.testing.assert_array_equal(s2.diag(V), s.diag(V))
    with pytest.raises(ValueError, match='span'):
        JointElementMean(s.base, s.basis, s.W, span=(np.ones(3), np.zeros(3)))

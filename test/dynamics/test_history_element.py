"""The per-joint element of D learned from the long history: what it learns and when not."""
import numpy as np

from dgp_ros.dynamics.history import LongHistory
from dgp_ros.gp.joint_element import _prior, _solve, M_BASIS


def _stream(seconds=60.0, hz=100.0, seed=0, drift=False):
    """
    Two joints reversing, friction outside the parametric family on joint 0 (a hump at 0.8).

    ``drift``: joint 0's velocity curve alternates between two shapes every 3 s (a residual
    that is no velocity curve: the element must not be served).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / hz)
    V = np.c_[1.5 * np.sin(0.9 * t) * np.cos(0.13 * t), 0.8 * np.sin(0.5 * t + 1.0)]
    f0 = _hump(V[:, 0])
    if drift:
        f0 = 0.3 * np.tanh(V[:, 0] / 0.01) + np.where((t // 3) % 2 == 0, 1.0, -0.6) * \
            np.sin(4.0 * V[:, 0])
    R = np.c_[f0, 0.2 * np.tanh(V[:, 1] / 0.01) + 0.3 * V[:, 1]]
    return t, V, R + 0.05 * rng.standard_normal(R.shape), np.c_[f0, R[:, 1]]


def _hump(v):
    return 0.3 * np.tanh(v / 0.01) + 0.4 * v + 0.5 * np.tanh(v / 0.01) * np.exp(
        -((np.abs(v) - 0.8) / 0.2) ** 2)


def _history(t, V, R):
    h = LongHistory(2, None, 'friction', offsets=True)
    for i in range(len(t)):
        h.push(t[i], None, V[i], None, R[i])
    return h


def test_the_element_learns_what_the_parametric_part_leaves_from_every_sample():
    t, V, R, truth = _stream()
    fit = _history(t, V, R).select()
    assert fit.element is not None and fit.element.on[0]
    m = fit.friction_mean()
    v = np.linspace(-1.4, 1.4, 400)
    Q = np.c_[v, np.zeros_like(v)]
    f = _hump(v)
    err = np.mean((m.force(Q)[:, 0] - f) ** 2)
    err_param = np.mean((m.base.force(Q)[:, 0] - f) ** 2)
    assert err < 0.5 * err_param
    assert 'elements on 0' in fit.label()
    # it serves on the velocities the run visited, and hands back to the parametric part
    # beyond them: its element's value there stays at the edge's
    np.testing.assert_array_equal(m.span[0], V.min(axis=0))
    np.testing.assert_array_equal(m.span[1], V.max(axis=0))
    far = np.c_[np.linspace(V[:, 0].max() * 1.05, 6.0, 50), np.zeros(50)]
    edge = np.c_[np.full(50, V[:, 0].max()), np.zeros(50)]
    assert np.all(np.abs(m.element_force(far)[:, 0]) <= np.abs(m.element_force(edge)[0, 0])
                  * 1.0001)


def test_the_elements_statistics_are_those_of_the_samples():
    """The element fitted from the history's sums equals a direct fit on the same samples."""
    t, V, R, _ = _stream(seconds=20.0)
    h = _history(t, V, R)
    fit = h.select()
    el = fit.element
    start = t >= t[0] + 3.0         # the element's columns start 3 s into the run
    # the target: what the fitted parametric part leaves (no offsets were chosen, or each is
    # subtracted), and the nuisance offset fitted beside the element
    resid = R - fit.friction_mean().base.force(V) - fit.bias
    assert el.on[0]
    for j in np.flatnonzero(el.on):
        X = np.c_[el.basis.columns(V)[:, j, :] * start[:, None], np.ones(len(t))]
        w = _solve(X.T @ X, X.T @ resid[:, j], _prior(el.basis, el.lengthscale[j],
                                                      el.ratio[j]))
        np.testing.assert_allclose(w[:M_BASIS], el.W[j], rtol=1e-7,
                                   atol=1e-9 * np.abs(el.W[j]).max())


def test_an_element_the_two_halves_learn_differently_is_not_served():
    t, V, R, _ = _stream(drift=True)
    fit = _history(t, V, R).select()
    el = fit.element
    assert not el.on[0] and el.agreement[0] >= 0.7


def test_no_element_on_what_is_noise():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 40.0, 0.01)
    V = np.c_[np.sin(0.7 * t), np.cos(0.4 * t)]
    R = 0.4 * np.tanh(V / 0.01) + 0.2 * V + 0.2 * rng.standard_normal(V.shape)
    fit = _history(t, V, R).select()
    assert not np.any(fit.element.on)

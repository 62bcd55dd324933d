"""Friction with a level per direction of motion: the prior, its bounds, the history's choice."""
import numpy as np
import pytest

from dgp_ros.dynamics import joint_choice
from dgp_ros.dynamics.history import LongHistory
from dgp_ros.dynamics.layout import Unknowns
from dgp_ros.dynamics.parametric import EPS_S, F, friction_columns, FRICTION_EPS, STRIBECK_VS
from dgp_ros.dynamics.statistics import Stats
from dgp_ros.gp.means import BasisFrictionMean, mean_from_dict


def _mean(N=3, seed=0):
    rng = np.random.default_rng(seed)
    return BasisFrictionMean(np.abs(rng.normal(0.0, 0.3, (N, F))), FRICTION_EPS, EPS_S,
                             STRIBECK_VS, coef_neg=np.abs(rng.normal(0.0, 0.6, (N, F))))


@pytest.mark.parametrize('spread', [1.0, 1e3], ids=['inside', 'far outside'])
def test_the_asymmetric_prior_is_passive_and_differs_between_directions(spread):
    m = _mean()
    rng = np.random.default_rng(1)
    V = rng.standard_normal((40000, 3)) * spread * rng.choice([1e-4, 1e-2, 1.0], (40000, 1))
    d = m.diag(V)
    assert np.all(np.isfinite(d)) and np.all(d >= 0.0)
    assert np.all(np.einsum('kn,kn->k', V, m.force(V)) >= 0.0)
    v = np.full((1, 3), 0.3)
    assert np.all(np.abs(m.force(v) + m.force(-v)) > 1e-3)        # not odd


def test_its_bounds_enclose_every_value_of_a_box_and_its_infimum_holds():
    m = _mean(seed=2)
    rng = np.random.default_rng(3)
    for width in (1e-3, 0.1, 1.0, 30.0):
        c = rng.normal(0.0, 0.5, (300, 3))
        lo = c - width * rng.uniform(0, 1, (300, 3))
        hi = c + width * rng.uniform(0, 1, (300, 3))
        dlo, dhi = m.diag_bounds(lo, hi)
        for t in np.r_[0.0, 1.0, rng.uniform(0, 1, 30)]:
            d = m.diag(np.clip(lo + t * (hi - lo), lo, hi))
            tol = 1e-12 * np.maximum(np.abs(d), 1.0)
            assert np.all(d >= dlo - tol) and np.all(d <= dhi + tol)
    v = np.concatenate([-np.logspace(-6, 4, 5001), np.logspace(-6, 4, 5001), [0.0]])
    assert np.all(m.diag(np.repeat(v[:, None], 3, axis=1)).min(axis=0) >= m.diag_inf() - 1e-12)


def test_a_model_file_keeps_both_directions():
    m = _mean(seed=4)
    m2 = mean_from_dict(m.to_dict(), N=3)
    V = np.random.default_rng(5).normal(0.0, 1.0, (500, 3))
    np.testing.assert_array_equal(m2.diag(V), m.diag(V))
    sym = BasisFrictionMean(m.coef, FRICTION_EPS, EPS_S, STRIBECK_VS)
    assert mean_from_dict(sym.to_dict(), N=3).coef_neg is None


def test_the_solve_keeps_each_direction_passive_and_recovers_it():
    """Noiseless asymmetric Coulomb + viscous: both directions' levels, each >= 0."""
    rng = np.random.default_rng(6)
    v = rng.uniform(-1.5, 1.5, (2000, 1))
    y = np.where(v > 0, 0.8 * np.tanh(v / 0.02) + 0.5 * v, 0.3 * np.tanh(v / 0.02) + 0.9 * v)
    U = Unknowns(1, 0, 0)
    st = Stats(1, U.L)
    A = np.concatenate([friction_columns(v), np.ones((2000, 1, 1))], axis=2)
    st.add_rows(A, A, y)
    G, b = U.gram(st)
    theta = U.solve(G, b, U.mask('friction', False, False, asymmetric=True), st.n)
    pos, neg = U.friction(theta)
    assert neg is not None and np.all(pos >= 0) and np.all(neg >= 0)
    m = BasisFrictionMean(pos, FRICTION_EPS, EPS_S, STRIBECK_VS, coef_neg=neg)
    x = np.linspace(-1.5, 1.5, 301)[:, None]
    truth = np.where(x > 0, 0.8 * np.tanh(x / 0.02) + 0.5 * x, 0.3 * np.tanh(x / 0.02) + 0.9 * x)
    assert np.max(np.abs(m.force(x) - truth)) < 0.02
    # the symmetric family cannot: it averages the directions
    sym = U.friction(U.solve(G, b, U.mask('friction', False, False), st.n))
    assert sym[1] is None


def _stream(seconds, asym, seed=0, hz=100.0):
    """Two reversing joints; joint 0's friction differs between its directions if ``asym``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / hz)
    V = np.c_[1.2 * np.sin(0.9 * t) * np.cos(0.21 * t), 0.8 * np.sin(0.5 * t + 1.0)]
    # the viscous levels differ between the directions (an offset cannot mimic that)
    hi, lo = (0.9, 0.2) if asym else (0.55, 0.55)
    f0 = 0.3 * np.tanh(V[:, 0] / 0.01) + np.where(V[:, 0] > 0, hi, lo) * V[:, 0]
    R = np.c_[f0, 0.2 * np.tanh(V[:, 1] / 0.01) + 0.3 * V[:, 1]]
    return t, V, R + 0.03 * rng.standard_normal(R.shape)


def _select(t, V, R):
    h = LongHistory(2, None, 'friction', offsets=True)
    for i in range(len(t)):
        h.push(t[i], None, V[i], None, R[i])
    return h.select()


def test_the_history_gives_the_asymmetric_joint_its_levels_and_no_other():
    fit = _select(*_stream(60.0, True))
    assert list(np.flatnonzero(fit.asymmetric)) == [0]
    assert 'asymmetric on 0' in fit.label()
    m = fit.friction_mean()
    base = getattr(m, 'base', m)
    x = np.array([[0.6, 0.0], [-0.6, 0.0]])
    f = base.force(x)[:, 0]
    assert f[0] == pytest.approx(0.3 + 0.9 * 0.6, abs=0.08)
    assert f[1] == pytest.approx(-(0.3 + 0.2 * 0.6), abs=0.08)


def test_no_asymmetry_where_friction_is_symmetric_or_the_run_is_short(monkeypatch):
    assert not np.any(_select(*_stream(60.0, False)).asymmetric)
    # nine seconds at 30 Hz: the CV blocks favour it, but the two halves of the run hold too
    # few samples to confirm it (with the halves' minimum at 0 it is chosen)
    short = _stream(9.0, True, hz=30.0)
    assert not np.any(_select(*short).asymmetric)
    monkeypatch.setattr(joint_choice, 'MIN_HALF_SAMPLES', 0)
    assert list(np.flatnonzero(_select(*short).asymmetric)) == [0]


def test_an_offset_the_newest_blocks_cannot_see_is_kept_from_the_halves(monkeypatch):
    """
    Keep an offset by the newest blocks alone, or across the halves.

    Across the halves only where the newest blocks are no worse (equal: the offset was no part
    of any forward fold).
    """
    h = LongHistory(2, None, 'friction', offsets=True)
    best = ('friction', False, False)
    same = {('friction', True, False): np.array([1.0, 1.0]),
            ('friction', False, False): np.array([1.0, 1.0])}
    monkeypatch.setattr(LongHistory, '_across', lambda self, *c: None)
    assert not h._joint_offsets(same, best).any()
    monkeypatch.setattr(LongHistory, '_across',
                        lambda self, *c: [np.array([0.5, 0.9]), np.array([1.0, 1.0])])
    assert list(h._joint_offsets(same, best)) == [True, False]
    worse = dict(same)
    worse[('friction', True, False)] = np.array([1.2, 1.0])
    assert not h._joint_offsets(worse, best).any()
    ahead = dict(same)
    ahead[('friction', True, False)] = np.array([1.0, 0.6])          # the newest blocks: joint 1
    assert list(h._joint_offsets(ahead, best)) == [True, True]

"""The long history: structure selection, conservative correction, frozen friction prior."""
import os

import numpy as np
import pytest

from dgp_ros.dynamics.conservative import Correction, PotentialBasis
from dgp_ros.dynamics.history import LongHistory
from dgp_ros.dynamics.parametric import FAMILIES
from dgp_ros.gp import FullDGP, load_model
from dgp_ros.gp.joint_element import JointElementMean
from dgp_ros.gp.means import BasisFrictionMean
from dgp_ros.online.learner.selection import Buffer

PANDA = os.environ.get('DGP_PANDA_REAL', os.path.join(
    os.path.dirname(__file__), '..', '..', '..', 'shared', 'data', 'panda_real'))


def _arm(n=3000, N=3, seed=0, offsets=None, cons_scale=0.5):
    """Coulomb + viscous friction, a potential force in q, noise; 1.5 ms steps of 'time'."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    q = np.stack([np.sin(0.3 * (j + 1) * t + j) for j in range(N)], axis=1)
    qd = np.stack([0.3 * (j + 1) * np.cos(0.3 * (j + 1) * t + j) for j in range(N)], axis=1)
    basis = PotentialBasis(N)
    theta = rng.normal(size=basis.C) * cons_scale
    friction = 0.8 * qd + 0.3 * np.tanh(qd / 0.02)
    cons = np.einsum('knc,c->kn', basis.deploy(q), theta)
    r = friction + cons + 0.02 * rng.normal(size=qd.shape)
    if offsets is not None:
        r = r + offsets
    return t, q, qd, r, basis, theta, friction, cons


def _feed(hist, t, q, qd, r):
    for i in range(t.size):
        hist.push(t[i], q[i], qd[i], None, r[i])


def test_selection_finds_friction_and_correction_and_not_offsets():
    t, q, qd, r, basis, theta, friction, cons = _arm()
    hist = LongHistory(3, basis)
    _feed(hist, t, q, qd, r)
    fit = hist.select()
    assert fit.family in ('friction', 'friction+stribeck') and fit.conservative, fit.label()
    assert not np.any(fit.offsets), fit.scores
    assert fit.scores and min(fit.scores.values()) < 0.05
    # the split: friction in the passive prior, the potential force in the correction
    f_hat = fit.friction_mean().force(qd)
    c_hat = fit.correction()(q)
    assert np.mean((f_hat - friction) ** 2) / np.var(friction) < 0.02
    assert np.mean((c_hat - cons) ** 2) / np.var(cons) < 0.05
    assert np.all(fit.coef >= 0)


def test_offsets_are_chosen_when_they_are_real_and_refused_without_a_rigid_body_model():
    b = np.array([0.5, -0.4, 0.3])
    t, q, qd, r, basis, *_ = _arm(offsets=b, cons_scale=0.0)
    fit = LongHistory(3, None).select()      # nothing learned yet: the default, no offsets
    assert not np.any(fit.offsets)
    hist = LongHistory(3, None)
    _feed(hist, t, q, qd, r)
    fit = hist.select()
    assert np.all(fit.offsets) and np.allclose(fit.bias, b, atol=0.15), (fit.label(), fit.bias)
    hist = LongHistory(3, None, offsets=False)
    _feed(hist, t, q, qd, r)
    assert not np.any(hist.select().offsets)
    assert all(not c[1] for c in hist.candidates())
    assert len(LongHistory(2, None).candidates()) == 2 * len(FAMILIES)


def test_frozen_friction_prior_is_passive_everywhere_and_bounded_by_its_corners():
    rng = np.random.default_rng(1)
    coef = np.abs(rng.normal(size=(4, 9)))
    m = BasisFrictionMean(coef, (0.005, 0.01, 0.02, 0.05, 0.1, 0.2), 0.01, (0.05, 0.2))
    m.fit(None, None)
    for scale in (1.0, 10.0, 1e3):
        V = rng.uniform(-scale, scale, (100000, 4))
        d = m.diag(V)
        assert np.all(d >= 0) and np.all((m.force(V) * V).sum(1) >= 0)
    lo, hi = -np.ones((1, 4)), 2 * np.ones((1, 4))
    dlo, dhi = m.diag_bounds(lo, hi)
    V = rng.uniform(lo, hi, (20000, 4))
    d = m.diag(V)
    assert np.all(d >= dlo - 1e-12) and np.all(d <= dhi + 1e-12)


def test_saved_model_keeps_prior_and_correction_and_predicts_the_residual(tmp_path):
    t, q, qd, r, basis, theta, friction, cons = _arm(n=1500)
    hist = LongHistory(3, basis)
    _feed(hist, t, q, qd, r)
    fit = hist.select()
    target = r - fit.correction()(q)
    m = FullDGP(passivity='projected', prior=fit.friction_mean()).fit(qd[::10], target[::10])
    m.correction_ = fit.correction()
    path = tmp_path / 'm.npz'
    m.save(path)
    m2 = load_model(path)
    # the frozen friction, with the elements the history learned beside it (if any)
    assert type(m2.mean_) is type(fit.friction_mean())
    base = m2.mean_.base if isinstance(m2.mean_, JointElementMean) else m2.mean_
    assert isinstance(base, BasisFrictionMean)
    Q, V = q[5::37], qd[5::37]
    np.testing.assert_allclose(m2.predict_residual(q=Q, qd=V), m.predict_residual(q=Q, qd=V))
    np.testing.assert_allclose(m2.predict(V, q=Q), m.predict(V))
    err = m2.predict_residual(q=Q, qd=V) - r[5::37]
    assert np.mean(err ** 2) / np.var(r[5::37]) < 0.05
    with pytest.raises(ValueError, match='q='):
        m2.predict_residual(qd=V)
    assert isinstance(Correction.from_dict(m.correction_.to_dict()).basis, PotentialBasis)


def test_coverage_buffer_keeps_the_visited_velocities():
    rng = np.random.default_rng(2)
    cov, rec = Buffer(50, 2, 'coverage'), Buffer(50, 2, 'recency')
    wide = rng.uniform(-2, 2, (50, 2))
    for v in wide:                        # first the whole range, then a long hover near 0
        cov.append(v, v)
        rec.append(v, v)
    for v in 0.01 * rng.normal(size=(500, 2)):
        cov.append(v, v)
        rec.append(v, v)
    Qc, _ = cov.arrays()
    Qr, _ = rec.arrays()
    assert np.abs(Qc).max() > 1.5 and np.abs(Qr).max() < 0.1
    assert cov.size == 50


def test_coverage_buffer_keeps_each_rows_nearest_neighbour_exact():
    """The incrementally kept nearest distances equal the full matrix's row minima."""
    rng = np.random.default_rng(5)
    for n, N in ((30, 2), (120, 7)):
        b = Buffer(n, N, 'coverage')
        checked = 0
        for k in range(6 * n):
            q = rng.normal(size=N) * (1 + k % 5)
            b.append(q, q)
            if b._d is not None:
                np.testing.assert_array_equal(b._near, b._d.min(axis=1))
                np.testing.assert_array_equal(b._d[np.arange(n), b._nn], b._near)
                checked += 1
        assert checked >= 5 * n


@pytest.mark.skipif(not os.path.isfile(os.path.join(PANDA, 'panda_log_train.npz')),
                    reason='the real Panda log (development data) is not present')
def test_real_panda_selection_beats_friction_alone_held_out():
    """Learn the structure on t < 7.5 s of the real log; its parametric part held out."""
    import sys
    from dgp_ros.dynamics import AccelFilter, FrictionResidual
    from dgp_ros.dynamics.conservative import correction_basis
    sys.path.insert(0, PANDA)
    import panda_rb
    z = np.load(os.path.join(PANDA, 'panda_log_train.npz'))
    t, q, qd, tau = z['t'], z['q'], z['qd'], z['tau_meas']
    front = FrictionResidual(panda_rb.tau_rb, AccelFilter(0.05))
    hist = LongHistory(7, correction_basis(panda_rb.tau_rb,
                                           [f'panda_joint{j}' for j in range(1, 8)]))
    last = None
    for i in np.flatnonzero(t < 7.5):
        want = last is None or t[i] >= last + 0.01
        last = t[i] if want else last
        for s in front.push(t[i], q[i], qd[i], tau[i], want=want):
            hist.push(s.stamp_s, s.q, s.qd, s.qdd, s.residual)
    te = t >= 7.5
    ref = z['tau_friction_offline'][te]

    def nmse(f):
        p = f.friction_mean().force(qd[te]) + f.correction()(q[te])
        return ((p - ref) ** 2).mean(0) / ref.var(0)
    sel = hist.select()
    alone = nmse(hist.fit('friction', False, False))
    chosen = nmse(sel)
    assert sel.conservative and not np.any(sel.offsets), sel.label()
    assert chosen.mean() < 0.9 * alone.mean(), (chosen, alone)


def _drifting(rise, seconds=300.0, seed=3):
    """Two joints, Coulomb + viscous friction scaled by 1 -> 1 + rise over the last 2/3, 100 Hz."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * 100)) * 0.01
    qd = np.stack([0.7 * np.sin(0.21 * t) + 0.4 * np.sin(0.53 * t + 1.0),
                   0.5 * np.sin(0.37 * t + 2.0) + 0.3 * np.sin(0.11 * t)], axis=1)
    s = 1.0 + rise * np.clip((t - seconds / 3) / (seconds / 2), 0.0, 1.0)
    friction = s[:, None] * (np.array([2.0, 1.0]) * np.tanh(qd / 0.02) + np.array([3.0, 1.5]) * qd)
    return t, qd, friction, friction + 0.02 * rng.normal(size=qd.shape)


def test_drifting_friction_is_fitted_from_the_recent_memory_and_steady_friction_from_all():
    # a gearbox warming up: +40 % Coulomb and viscous friction; the whole history is biased
    # towards the past, the recent memory tracks it (forward CV on the last blocks decides)
    t, qd, friction, r = _drifting(0.4)
    hist = LongHistory(2, None, offsets=False)
    for i in range(t.size):
        hist.push(t[i], None, qd[i], None, r[i])
    fit = hist.select()
    last = t > t[-1] - 20.0
    err = np.mean((fit.friction_mean().force(qd[last]) - friction[last]) ** 2) / \
        np.var(friction[last])
    whole = hist.fit(fit.family, False, False)
    err_whole = np.mean((whole.friction_mean().force(qd[last]) - friction[last]) ** 2) / \
        np.var(friction[last])
    assert fit.memory != 'all' and 'memory' in fit.label(), fit.label()
    assert err < 0.01 and err < 0.25 * err_whole, (err, err_whole)
    # the same motion without the drift: every sample counts (nothing is forgotten)
    t, qd, friction, r = _drifting(0.0)
    hist = LongHistory(2, None, offsets=False)
    for i in range(t.size):
        hist.push(t[i], None, qd[i], None, r[i])
    fit = hist.select()
    assert fit.memory == 'all' and 'memory' not in fit.label(), fit.label()
    copy = hist.copy()
    assert copy.select().memory == 'all'

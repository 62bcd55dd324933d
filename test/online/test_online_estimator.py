"""
Unit tests of dgp_ros.online (pure Python, no ROS).

Validation, selection, prior, refits, passivity, persistence, diagnostics.
"""
import math

import numpy as np
import pytest

from dgp_ros.gp import Certificate, FullDGP, prior_mean_diag
from dgp_ros.online import EstimatorConfig, OK, OnlineEstimator, WARN

NAMES = ['a', 'b', 'c']


def true_tau(q):
    """Return a passive nonlinear damping D(q) q (D symmetric positive definite)."""
    q = np.asarray(q, float)
    D = np.diag([2.0 + np.sin(q[0]), 1.0 + 0.5 * q[1] ** 2, 0.5 + 0.1 * abs(q[2])])
    D[0, 1] = D[1, 0] = 0.3 * np.cos(q[2])
    return D @ q


def traj(t):
    return np.array([np.sin(0.7 * t), 0.8 * np.cos(0.31 * t), 2.0 + np.sin(0.13 * t)])


def feed(est, n, t0=0.0, dt=0.05, noise=0.02, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = t0 + i * dt
        q = traj(t)
        out.append(est.process(t, NAMES, q, true_tau(q) + rng.normal(0, noise, 3)))
    return out


def cfg(**kw):
    # the data here follow a smooth viscous law: the paper's prior (the defaults are for arms)
    base = {'model': 'full', 'passivity': 'projected', 'buffer_size': 40, 'min_samples': 10,
            'refit_mode': 'sync', 'refit_period_s': 0.0, 'selection': 'all', 'prior': 'viscous',
            'bias': False}
    base.update(kw)
    return EstimatorConfig(**base)


# ----------------------------------------------------------------------------- config
@pytest.mark.parametrize('field,value,words', [
    ('model', 'gpytorch', 'model'), ('passivity', 'sometimes', 'passivity'),
    ('buffer_size', 1, 'buffer_size'), ('buffer_size', 10.5, 'integer'),
    ('min_samples', 0, 'min_samples'), ('min_samples', 500, 'buffer_size'),
    ('refit_period_s', -1.0, 'refit_period_s'), ('refit_period_s', float('nan'), 'finite'),
    ('optimize_every_n_refits', -2, 'optimize_every_n_refits'),
    ('selection', 'random', 'selection'), ('selection_min_distance', -0.1, '[0, 100]'),
    ('selection_min_distance', 1e200, '[0, 100]'), ('max_abs_velocity', float('inf'), 'finite'),
    ('buffer_size', 10 ** 9, '[2, 5000]'), ('model_path', '/tmp/model.txt', '.npz'),
    ('joints', ['a', 'a'], 'unique'), ('joints', ['a', ''], 'joints'),
    ('refit_mode', 'thread', 'refit_mode'), ('model_path', '/nonexistent/dir/m.npz', 'directory'),
    ('selection_scale', [1.0, -1.0], 'selection_scale'), ('max_abs_effort', 0.0, 'max_abs_effort'),
    ('operating_domain', [0.0, 1.0, 2.0], 'even'), ('operating_domain', [1.0, 0.0], 'below'),
    ('operating_domain', [0.0, float('inf')], 'finite'),
    ('min_sample_interval_s', -0.001, 'min_sample_interval_s'),
])
def test_config_validate_rejects_with_reason(field, value, words):
    c = EstimatorConfig(**{field: value})
    with pytest.raises(ValueError) as exc:
        c.validate()
    assert field in str(exc.value) and words in str(exc.value)


def test_config_ard_cannot_be_certified():
    with pytest.raises(ValueError, match="does not apply to model 'ard'"):
        EstimatorConfig(model='ard', passivity='certified').validate()
    EstimatorConfig(model='ard', passivity='projected').validate()


def test_node_default_is_certified_and_the_diagnostics_name_the_guarantee():
    assert EstimatorConfig().passivity == 'certified'
    seen = {}
    for passivity in ('certified', 'projected', 'none'):
        est = OnlineEstimator(cfg(passivity=passivity))
        before = est.diagnostics()['guarantee']       # the prior mean: PSD by construction
        feed(est, 20)
        assert est.trained
        seen[passivity] = (before, est.diagnostics()['guarantee'])
    # N = 3: a bound or a branch-and-bound proof of D itself; projected: each answer only
    assert seen['certified'][0] == 'psd' and seen['certified'][1] in ('psd', 'passive-on-domain')
    assert seen['projected'] == ('psd', 'pointwise')
    # none enforces nothing; once fitted it reports what the a-posteriori bound happens to prove
    assert seen['none'][0] == 'none' and seen['none'][1] in ('none', 'psd')


def test_config_from_dict_unknown_key():
    with pytest.raises(ValueError, match='bogus'):
        EstimatorConfig.from_dict({'bogus': 1})


# ----------------------------------------------------------------------------- validation
def test_bad_messages_rejected_and_counted_never_raise():
    est = OnlineEstimator(cfg(joints=['a', 'b', 'c'], max_abs_velocity=100.0))
    good = est.process(0.0, NAMES, [0.1, 0.2, 0.3], [0.2, 0.2, 0.1])
    assert good is not None
    bad = [
        ((0.1, NAMES, [0.1, float('nan'), 0.3], [1, 1, 1]), 'non_finite'),
        ((0.1, NAMES, [0.1, 0.2, 0.3], [1, float('inf'), 1]), 'non_finite'),
        ((0.1, NAMES, [0.1, 0.2], [1, 1]), 'length_mismatch'),
        ((0.1, NAMES, [0.1, 0.2, 0.3], [1, 1]), 'length_mismatch'),
        ((0.1, ['a', 'a', 'c'], [0.1, 0.2, 0.3], [1, 1, 1]), 'duplicate_name'),
        ((0.1, ['a', 'b', 'x'], [0.1, 0.2, 0.3], [1, 1, 1]), 'missing_joint'),
        ((0.1, [], [0.1, 0.2, 0.3], [1, 1, 1]), 'missing_joint'),
        ((0.1, NAMES, [], []), 'empty'),
        ((0.1, NAMES, [0.1, 200.0, 0.3], [1, 1, 1]), 'out_of_range'),
        ((float('nan'), NAMES, [0.1, 0.2, 0.3], [1, 1, 1]), 'bad_stamp'),
        ((0.1, NAMES, ['x', 'y', 'z'], [1, 1, 1]), 'non_finite'),
        ((0.1, NAMES, None, [1, 1, 1]), 'empty'),
    ]
    for args, reason in bad:
        before = est.health.rejected[reason]
        assert est.process(*args) is None, reason
        assert est.health.rejected[reason] == before + 1, reason
    d = est.diagnostics()
    assert d['rejected_total'] == len(bad)
    assert d['messages_accepted'] == 1 and d['buffer_fill'] == 1
    assert d['level'] >= WARN and 'many rejected samples' in d['message']


def test_dimension_mismatch_without_joint_names():
    est = OnlineEstimator(cfg())
    assert est.process(0.0, [], [0.1, 0.2, 0.3], [1, 1, 1]) is not None
    assert est.process(0.1, [], [0.1, 0.2], [1, 1]) is None
    assert est.health.rejected['dimension_mismatch'] == 1


def test_joints_select_and_order_by_name():
    est = OnlineEstimator(cfg(joints=['c', 'a']))
    e = est.process(1.0, ['a', 'b', 'c'], [1.0, 2.0, 3.0], [10.0, 20.0, 30.0])
    assert e.names == ['c', 'a']
    np.testing.assert_array_equal(e.qd, [3.0, 1.0])
    np.testing.assert_array_equal(e.tau, [30.0, 10.0])
    # the message order may change: still selected by name
    e = est.process(1.1, ['c', 'b', 'a'], [3.0, 2.0, 1.5], [30.0, 20.0, 15.0])
    np.testing.assert_array_equal(e.qd, [3.0, 1.5])


def test_names_latched_from_first_message_when_joints_empty():
    est = OnlineEstimator(cfg())
    est.process(0.0, ['a', 'b', 'c'], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    e = est.process(0.1, ['b', 'c', 'a'], [2.0, 3.0, 1.0], [2.0, 3.0, 1.0])
    assert e.names == ['a', 'b', 'c']
    np.testing.assert_array_equal(e.qd, [1.0, 2.0, 3.0])


# ----------------------------------------------------------------------------- selection
def test_novelty_selection_keeps_hover_out_of_buffer():
    est = OnlineEstimator(cfg(selection='novelty', selection_min_distance=0.1, buffer_size=100,
                              min_samples=100))
    feed(est, 30, dt=0.3)                      # diverse flight
    n0 = est.diagnostics()['buffer_fill']
    assert n0 >= 20
    rng = np.random.default_rng(1)
    hover = np.array([0.3, 0.4, 2.1])
    for i in range(500):                        # hovering: tiny noise around one state
        q = hover + rng.normal(0, 1e-4, 3)
        est.process(20.0 + i * 0.01, NAMES, q, true_tau(q))
    d = est.diagnostics()
    assert d['buffer_fill'] <= n0 + 2
    assert d['samples_skipped'] >= 498

    all_est = OnlineEstimator(cfg(selection='all', buffer_size=100, min_samples=100))
    for i in range(50):
        q = hover + rng.normal(0, 1e-4, 3)
        all_est.process(i * 0.01, NAMES, q, true_tau(q))
    assert all_est.diagnostics()['buffer_fill'] == 50   # the check above can fail


# ----------------------------------------------------------------------------- prior + refit
def test_prior_mean_before_min_samples():
    est = OnlineEstimator(cfg(min_samples=10))
    rng = np.random.default_rng(3)
    Q, T = [], []
    for i in range(9):
        q = traj(i * 0.2)
        tau = true_tau(q) + rng.normal(0, 0.02, 3)
        Q.append(q), T.append(tau)
        gain = est.learner.skill_gains()[1]
        e = est.process(i * 0.2, NAMES, q, tau)
        assert e.source == 'prior'
        # answered before it is learned: the prior of the samples before it (none: zero) times
        # the gain it earned one step ahead (online.grounds), each joint clipped by the gate
        # to 1.5 x the largest force learned on it
        m_d = prior_mean_diag(np.array(Q[:-1]), np.array(T[:-1])) if i else np.zeros(3)
        if gain is not None:
            assert np.all((0.0 <= gain) & (gain <= 1.0))
            m_d = m_d * gain
        if i >= 4:
            assert np.all(gain > 0.9), gain        # a prior that fits earns its weight at once
        limit = 1.5 * np.abs(np.array(T[:-1])).max(axis=0) if i else np.zeros(3)
        inside = np.abs(m_d * q) <= limit
        np.testing.assert_allclose(e.tau_hat[inside], (m_d * q)[inside])
        assert np.all(np.abs(e.tau_hat[~inside]) <= limit[~inside] * (1 + 1e-12))
        np.testing.assert_allclose(e.D, np.diag(e.tau_hat / np.where(q == 0, 1.0, q)))
        assert e.power >= 0
    d = est.diagnostics()
    assert not d['trained'] and d['level'] == WARN and 'not yet trained' in d['message']


def test_sync_refit_trains_and_converges():
    est = OnlineEstimator(cfg(buffer_size=50, min_samples=15, refit_period_s=5.0,
                              optimize_every_n_refits=2))
    out = feed(est, 120, dt=0.1)
    assert out[-1].source == 'model'
    d = est.diagnostics()
    assert d['trained'] and d['certified'] and d['method'] == 'projection' and \
        d['refits_ok'] >= 2 and d['refits_failed'] == 0
    assert d['level'] == OK, d['message']
    err = np.array([e.tau_hat - true_tau(e.qd) for e in out[-50:]])
    ref = np.array([true_tau(e.qd) for e in out])
    nmse = (err ** 2).mean(0) / ref.var(0)
    assert np.all(nmse < 0.02), nmse
    assert out[-1].D.shape == (3, 3)
    np.testing.assert_allclose(out[-1].D @ out[-1].qd, out[-1].tau_hat, rtol=1e-6, atol=1e-9)
    assert np.all(out[-1].stddev >= 0)


def test_refit_on_request_and_not_enough_samples():
    est = OnlineEstimator(cfg(min_samples=10))
    ok, msg = est.request_refit()
    assert not ok and 'not enough samples' in msg
    feed(est, 12)
    n = est.diagnostics()['refits_ok']
    ok, msg = est.request_refit()
    assert ok, msg
    assert est.diagnostics()['refits_ok'] == n + 1


def test_async_refit_replays_samples_and_swaps():
    est = OnlineEstimator(cfg(refit_mode='async', buffer_size=50, min_samples=10))
    feed(est, 40)                             # refit started at 10 samples, others arrive
    assert est.wait_for_refit(timeout=120)
    d = est.diagnostics()
    assert d['trained'] and d['refits_ok'] >= 1     # (a quick fit leaves time for the next)
    # every buffered sample is in the swapped-in model (replayed with update)
    assert est.model.n_samples_ == d['buffer_fill'] == 40
    X, _ = est.samples()
    np.testing.assert_allclose(est.model.X_train_, X, rtol=1e-12, atol=1e-12)
    est.close()


class _Unprovable(FullDGP):
    """A model whose certificate never holds: pending after a fit, failed once proven."""

    def certificate(self):
        return Certificate(False, -1.0, 'test: certificate fails',
                           stale=not getattr(self, '_proven', False))

    def recertify(self, full=False):
        self._proven = True
        return self.certificate()


def test_an_unproven_refit_serves_projected_and_says_so():
    # a certifying mode never freezes the learning on a proof that fails: the candidate serves,
    # every answer projected onto qd^T tau >= 0, and /diagnostics names the missing proof (the
    # proofs run beside the answers: refit_mode async; in line they wait for the stream's end)
    # a refit serves its model at once and proves it in the re-proof job that follows
    est = OnlineEstimator(cfg(min_samples=10, passivity='certified', refit_mode='async'),
                          model_factory=lambda kind, **kw: _Unprovable(**kw))
    out = feed(est, 30)
    assert est.wait_for_refit(60)
    out = feed(est, 2, t0=5.0)
    assert out[-1].source == 'model' and est.wait_for_refit(60)
    for k in range(50):                 # the stream pauses: the served model is proven
        est.learner.poll(idle=True)
        est.wait_for_refit(60)
        if est.diagnostics()['proofs_failed']:
            break
    d = est.diagnostics()
    assert d['trained'] and d['refits_ok'] >= 2 and d['refits_failed'] == 0
    assert d['proofs_failed'] >= 1
    assert 'test: certificate fails' in d['last_proof_error']
    assert d['level'] == WARN and 'not certified' in d['message']
    assert 'projected' in d['message']
    rng = np.random.default_rng(3)
    Qs = np.vstack([rng.uniform(-2, 3, (2000, 3)), rng.normal(0, 50, (1000, 3))])
    P = np.einsum('ij,ij->i', Qs, est.predict(Qs))
    assert P.min() >= -1e-12 * np.abs(P).max()


# ----------------------------------------------------------------------------- passivity
@pytest.mark.parametrize('passivity', ['paper', 'certified', 'projected'])
def test_never_non_passive(passivity):
    # data with a non-passive region (negative damping near q = 0 on output 0) and big noise
    est = OnlineEstimator(cfg(passivity=passivity, buffer_size=30, min_samples=10,
                              refit_period_s=2.0, optimize_every_n_refits=0))
    rng = np.random.default_rng(7)
    for i in range(50):
        q = rng.uniform(-2, 2, 3)
        tau = true_tau(q) + rng.normal(0, 0.5, 3)
        tau[0] -= 3.0 * q[0] * np.exp(-q[0] ** 2)        # locally negative damping
        e = est.process(i * 0.1, NAMES, q, tau)
        assert e.power >= 0.0
    assert est.trained
    Qs = np.vstack([rng.uniform(-3, 3, (3000, 3)), rng.normal(0, 20, (500, 3)),
                    rng.uniform(-1e-3, 1e-3, (500, 3))])
    tau = est.predict(Qs)
    power = np.einsum('ij,ij->i', Qs, tau)
    assert power.min() >= 0.0


class _Evil(FullDGP):
    """A broken model: anti-damping answers, or non-finite ones."""

    answer = -1.0

    def predict_with_damping(self, Q, return_var=True, return_damping=True):
        tau = self.answer * np.atleast_2d(Q)
        return tau, np.ones_like(tau), self.answer * np.eye(Q.shape[1])[None]


def test_output_gate_falls_back_to_prior_when_model_is_not_passive_or_not_finite():
    est = OnlineEstimator(cfg(passivity='projected'),
                          model_factory=lambda kind, **kw: _Evil(**kw))
    feed(est, 12)
    assert est.trained
    # the gate itself: a model with full weight (the blend would have scored this one to 0)
    est.learner.restore_gains(np.ones(3), np.ones(3), np.ones(3))
    n = est.diagnostics()['passivity_fallbacks']
    e = est.process(5.0, NAMES, [0.5, 0.5, 2.0], [1.0, 0.5, 1.0])
    assert e.source == 'fallback' and e.power >= 0
    assert est.diagnostics()['passivity_fallbacks'] == n + 1
    _Evil.answer = float('nan')
    try:
        e = est.process(5.1, NAMES, [0.5, 0.5, 2.0], [1.0, 0.5, 1.0])
    finally:
        _Evil.answer = -1.0
    assert e.source == 'fallback' and np.all(np.isfinite(e.tau_hat)) and e.power >= 0
    assert est.diagnostics()['nonfinite_outputs'] == 1


def test_optional_outputs_are_skipped_on_request_and_the_force_is_unchanged():
    est = OnlineEstimator(cfg())
    feed(est, 30)
    q = [0.4, -0.3, 1.5]
    est.process(9.0, NAMES, q, [1.0, 0.5, 1.0])       # learned; the same stamp again is not
    full = est.process(9.0, NAMES, q, [1.0, 0.5, 1.0])
    est.set_outputs(stddev=False, damping=False)
    lean = est.process(9.0, NAMES, q, [1.0, 0.5, 1.0])
    assert lean.D is None and np.all(np.isnan(lean.stddev)) and lean.source == 'model'
    np.testing.assert_allclose(lean.tau_hat, full.tau_hat, rtol=1e-12, atol=1e-12)
    assert est.diagnostics()['nonfinite_outputs'] == 0
    est.set_outputs()
    again = est.process(9.0, NAMES, q, [1.0, 0.5, 1.0])
    assert again.D is not None and np.all(np.isfinite(again.stddev))


# ----------------------------------------------------------------------------- persistence
def test_save_and_restore_give_identical_estimates(tmp_path):
    path = str(tmp_path / 'model.npz')
    est = OnlineEstimator(cfg(model_path=path))
    with pytest.raises(RuntimeError):
        est.save()
    feed(est, 30)
    assert est.trained
    assert est.save() == path                      # also saved on refit; explicit save here
    rng = np.random.default_rng(5)
    Qs = rng.uniform(-2, 2, (200, 3))
    before = est.predict(Qs)
    est2 = OnlineEstimator(cfg(model_path=path))
    assert est2.trained and not est2.load_error
    np.testing.assert_array_equal(est2.predict(Qs), before)
    q, tau = traj(7.0), true_tau(traj(7.0))
    a = est.process(10.0, NAMES, q, tau)
    b = est2.process(10.0, NAMES, q, tau)
    np.testing.assert_array_equal(a.tau_hat, b.tau_hat)
    np.testing.assert_array_equal(a.stddev, b.stddev)
    assert not [p for p in tmp_path.iterdir() if p.name != 'model.npz']   # no temp leftovers


def test_model_path_that_is_not_a_model_is_refused_and_a_damaged_model_is_reported(tmp_path):
    path = tmp_path / 'm.npz'
    path.write_bytes(b'not a model')
    with pytest.raises(ValueError, match='not a dgp_ros model file'):
        OnlineEstimator(cfg(model_path=str(path)))
    assert path.read_bytes() == b'not a model'
    # a model file damaged after writing: the estimator starts without it and says why
    good = str(tmp_path / 'good.npz')
    est = OnlineEstimator(cfg(model_path=good))
    feed(est, 30)
    est.save()
    raw = bytearray(open(good, 'rb').read())
    raw[len(raw) // 2] ^= 0xFF
    open(good, 'wb').write(bytes(raw))
    est = OnlineEstimator(cfg(model_path=good))
    assert not est.trained and 'could not use' in est.load_error
    assert 'model file not used' in est.diagnostics()['message']


def test_loaded_model_of_other_kind_not_used(tmp_path):
    path = str(tmp_path / 'm.npz')
    est = OnlineEstimator(cfg(model='diag', model_path=path))
    feed(est, 12)
    est.save()
    est2 = OnlineEstimator(cfg(model='full', model_path=path))
    assert not est2.trained and "'diag'" in est2.load_error


# ----------------------------------------------------------------------------- clock, reset
def test_stamp_jump_back_keeps_model_and_counts():
    est = OnlineEstimator(cfg(refit_period_s=3.0, optimize_every_n_refits=0))
    feed(est, 25, t0=100.0, dt=0.1)
    n_ok = est.diagnostics()['refits_ok']
    assert est.trained
    feed(est, 5, t0=0.0, dt=0.1)                 # bag looped: stamps restart at 0
    d = est.diagnostics()
    assert d['time_jumps_back'] == 1 and d['trained']
    assert d['refits_ok'] == n_ok                # no spurious refit
    feed(est, 30, t0=0.5, dt=0.1)                # refit clock restarted at the new stamp
    assert est.diagnostics()['refits_ok'] > n_ok


def test_reset_and_reconfigure():
    est = OnlineEstimator(cfg())
    feed(est, 20)
    assert est.trained
    msg = est.reconfigure(cfg(min_samples=12))
    assert msg == 'applied' and est.trained
    msg = est.reconfigure(cfg(model='diag'))
    assert 'model' in msg and not est.trained
    assert est.diagnostics()['buffer_fill'] == 20
    e = feed(est, 1, t0=10.0)[0]                 # refit requested: trains on the next sample
    assert est.trained and e is not None
    est.reset()
    d = est.diagnostics()
    assert not d['trained'] and d['buffer_fill'] == 0 and d['messages_received'] == 0


def test_ard_baseline_has_no_damping_matrix():
    est = OnlineEstimator(cfg(model='ard', passivity='projected'))
    out = feed(est, 15)
    assert out[-1].source == 'model' and out[-1].D is None
    assert all(e.power >= 0 for e in out)
    assert math.isfinite(out[-1].power)


def test_learning_rate_limit_in_stamp_time():
    """
    1 kHz stamps, min_sample_interval_s = 10 ms.

    Every message gets an estimate, one in ten is learned; a clock jump back (bag loop) is learned
    at once; 0 learns every sample.
    """
    est = OnlineEstimator(cfg(min_sample_interval_s=0.01, buffer_size=200))
    out = feed(est, 500, dt=0.001)
    d = est.diagnostics()
    assert all(e is not None and np.all(np.isfinite(e.tau_hat)) for e in out)
    assert d['samples_added'] == 50 and d['samples_rate_limited'] == 450
    assert sum(e.added for e in out) == 50
    e = est.process(0.0, NAMES, traj(0.3), true_tau(traj(0.3)))      # stamp went back
    assert e.added and est.diagnostics()['samples_added'] == 51
    est0 = OnlineEstimator(cfg(min_sample_interval_s=0.0, buffer_size=200))
    feed(est0, 100, dt=0.001)
    assert est0.diagnostics()['samples_added'] == 100
    assert est0.diagnostics()['samples_rate_limited'] == 0


def test_periodic_refits_run_after_loading_a_model(tmp_path):
    """
    A model loaded from model_path starts the refit clock at the first message.

    The periodic refits happen as for a model trained in this run (they never started before the
    fix).
    """
    path = str(tmp_path / 'model.npz')
    est = OnlineEstimator(cfg(model_path=path))
    feed(est, 30)
    est.save()
    est2 = OnlineEstimator(cfg(model_path=path, refit_period_s=1.0))
    assert est2.trained
    feed(est2, 60, t0=100.0, dt=0.05)             # 3 s of stamps
    d = est2.diagnostics()
    assert d['refits_ok'] >= 2, d


def test_hyper_parameters_relearned_each_time_the_buffer_doubles():
    """
    min_samples = 10, buffer 80, no periodic refits.

    Optimized refits at 10, 20, 40 and 80 buffered samples (the first optimum, from 10 samples, is
    not kept for the whole run).
    """
    est = OnlineEstimator(cfg(buffer_size=80, min_samples=10, refit_period_s=0.0,
                              optimize_every_n_refits=0))
    seen = []
    for i in range(120):
        feed(est, 1, t0=0.05 * i, seed=i)
        d = est.diagnostics()
        seen.append((d['refits_ok'], d['hyper_samples']))
    d = est.diagnostics()
    assert d['refits_ok'] == 4 and d['hyper_samples'] == 80, d
    assert sorted({n for _, n in seen}) == [0, 10, 20, 40, 80]      # 0: before the first fit
    assert d['last_refit_optimized']


class _Wild(FullDGP):
    """A candidate that extrapolates wildly beyond its data (a fit on a short stretch can)."""

    wild = False

    def predict(self, Qs, return_var=False):
        out = super().predict(Qs, return_var)
        if _Wild.wild:
            tau = out[0] if return_var else out
            tau[np.abs(np.atleast_2d(Qs)).max(axis=1) > 1.0] *= 1e4
        return out


def test_a_wild_candidate_is_not_swapped_in_and_the_status_says_so():
    est = OnlineEstimator(cfg(refit_period_s=1.0), model_factory=lambda kind, **kw: _Wild(**kw))
    feed(est, 40)
    assert est.trained
    good = est.model
    _Wild.wild = True
    try:
        feed(est, 40, t0=2.0, seed=1)
    finally:
        _Wild.wild = False
    d = est.diagnostics()
    # no refit of the wild stretch was swapped in: the hyper-parameters are still the good
    # model's (rebases keep them; the served model already held their samples, appended)
    hp, hp_good = est.model.hyperparams_, good.hyperparams_
    assert all(hp[k] == hp_good[k] for k in ('log_ls', 'log_sf2', 'log_sn2'))
    assert d['refits_rejected'] >= 1 and d['absorbs'] >= 1
    assert d['level'] >= WARN and 'model rejected' in d['message'] and \
        'sanity check' in d['message']


class _WildOnce(FullDGP):
    """The second hyper-parameter fit ever made extrapolates wildly; the others are sound."""

    fits = 0
    _wild = False

    def fit(self, Qd, Tau, optimize=True, prove=True, **kw):
        super().fit(Qd, Tau, optimize, prove, **kw)
        if optimize:                   # a refit job's candidate (absorbs keep the hyper)
            _WildOnce.fits += 1
            self._wild = _WildOnce.fits == 2
        return self

    def predict(self, Qs, return_var=False):
        out = super().predict(Qs, return_var)
        if self._wild:
            tau = out[0] if return_var else out
            tau *= 1e4
        return out


def test_a_rejected_candidate_is_retried_on_fresh_samples_without_a_refit_period():
    """refit_period_s = 0: without a retry the first model (10 samples) would serve for good."""
    _WildOnce.fits = 0
    est = OnlineEstimator(cfg(buffer_size=40, min_samples=10, refit_period_s=0.0,
                              optimize_every_n_refits=0),
                          model_factory=lambda kind, **kw: _WildOnce(**kw))
    feed(est, 10)
    assert est.model is not None and _WildOnce.fits == 1
    feed(est, 10, t0=1.0, seed=1)                 # 20 buffered: hyper-parameters outgrown
    d = est.diagnostics()
    assert d['refits_rejected'] == 1 and d['hyper_samples'] == 10, d
    assert not est.model._wild                    # the rejected one does not serve
    feed(est, 9, t0=2.0, seed=2)                  # the retry waits for 10 fresh samples
    assert _WildOnce.fits == 2 and est.diagnostics()['hyper_samples'] == 10
    feed(est, 1, t0=3.0, seed=3)
    d = est.diagnostics()
    assert _WildOnce.fits == 3 and d['hyper_samples'] == 30 and d['refits_ok'] == 2, d
    assert 'model rejected' not in d['message'] and d['consecutive_refit_failures'] == 0


class _UnprovenFirst(FullDGP):
    """The first fit ever made cannot be proven (as 3 of 120 small certified fits were)."""

    fits = 0

    def fit(self, Qd, Tau, optimize=True, prove=True, **kw):
        type(self).fits += 1
        if type(self).fits == 1:
            raise RuntimeError('no proof: box budget exhausted')
        return super().fit(Qd, Tau, optimize, prove, **kw)


def test_a_first_fit_that_fails_is_retried_without_a_refit_period():
    """refit_period_s = 0, no model yet: a failed first fit must not leave the prior for good."""
    _UnprovenFirst.fits = 0
    est = OnlineEstimator(cfg(buffer_size=40, min_samples=10, refit_period_s=0.0),
                          model_factory=lambda kind, **kw: _UnprovenFirst(**kw))
    feed(est, 10)
    d = est.diagnostics()
    assert est.model is None and _UnprovenFirst.fits == 1 and d['refits_failed'] == 1, d
    feed(est, 9, t0=1.0, seed=1)                  # the retry waits for 10 fresh samples
    assert est.model is None and _UnprovenFirst.fits == 1
    out = feed(est, 1, t0=2.0, seed=2)
    assert est.model is not None and _UnprovenFirst.fits == 2
    assert est.diagnostics()['consecutive_refit_failures'] == 0
    out = feed(est, 1, t0=2.1, seed=3)           # answered by the model that learned the last
    assert out[-1].source == 'model'

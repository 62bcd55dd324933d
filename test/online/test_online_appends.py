"""
New samples reach the model at once (issue 30): appended, rebased, never held up by a proof.

In line every learned sample is in the model before the next answer; the model is brought back
to the buffer by rebases, so it never grows beyond the buffer by more than a rebase's worth; a
certified model whose proof is pending answers exactly as the projected mode does; the learner
process appends once per round.
"""
import time

import numpy as np

from dgp_ros.online import EstimatorConfig, OnlineEstimator
from dgp_ros.online.jobs.rebase import Rebases
from dgp_ros.online.learner.learner import Learner

NAMES = ['a', 'b', 'c']


def true_tau(q):
    """Return a passive nonlinear damping force (positive definite D)."""
    q = np.asarray(q, float)
    return np.array([2.0 + np.sin(q[0]), 1.0 + 0.5 * q[1] ** 2, 0.5 + 0.1 * abs(q[2])]) * q


def path(t):
    """Return a trajectory that keeps reaching new velocities (a drift plus a wobble)."""
    return np.array([np.sin(0.9 * t) + 0.05 * t, 0.8 * np.cos(0.4 * t), 1.0 + 0.1 * t])


def cfg(**kw):
    base = {'model': 'full', 'passivity': 'projected', 'buffer_size': 60, 'min_samples': 10,
            'refit_mode': 'sync', 'refit_period_s': 3.0, 'selection': 'all', 'prior': 'viscous',
            'bias': False, 'optimize_every_n_refits': 0, 'elements': 'all'}
    base.update(kw)
    return EstimatorConfig(**base)


def _stream(est, n, dt=0.05, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        q = path(i * dt)
        out.append(est.process(i * dt, NAMES, q, true_tau(q) + rng.normal(0, noise, 3)))
    return out


def test_each_learned_sample_is_in_the_model_before_the_next_answer():
    est = OnlineEstimator(cfg())
    for i in range(150):
        q = path(i * 0.05)
        est.process(i * 0.05, NAMES, q, true_tau(q))
        if est.trained:
            # the message just processed is a training input, and the model reproduces its
            # (noise-free) force
            assert np.any(np.all(np.abs(est.model.X_train_ - q) <= 1e-12, axis=1))
            assert np.allclose(est.model.predict(q[None])[0], true_tau(q), rtol=1e-2, atol=1e-2)
    d = est.diagnostics()
    assert d['appends'] > 100 and d['absorbs'] >= 1 and d['absorbs_rejected'] == 0, d
    est.close()


def test_one_step_ahead_beats_learning_in_batches():
    # the same stream with rebases only every 10 samples (the appends switched off): on a
    # trajectory that keeps reaching new velocities the lag costs accuracy
    def one_step(append):
        est = OnlineEstimator(cfg())
        Learner.append_each = append
        try:
            out = _stream(est, 300, noise=0.01)
        finally:
            Learner.append_each = True
        tau = np.array([e.tau for e in out])
        err = np.array([e.tau_hat for e in out]) - tau
        est.close()
        return (err[40:] ** 2).mean(axis=0) / tau[40:].var(axis=0)
    at_once, lagging = one_step(True), one_step(False)
    assert np.all(at_once < lagging), (at_once, lagging)


def test_rebases_keep_the_model_near_the_buffer_size():
    est = OnlineEstimator(cfg(buffer_size=40, buffer_policy='coverage'))
    biggest = 0
    for e in _stream(est, 400, noise=0.01):
        if est.trained:
            biggest = max(biggest, est.model.n_samples_)
    assert est.diagnostics()['absorbs'] >= 5
    assert 40 < biggest <= 40 + 40 // Rebases.REBASE_FRACTION
    est.close()


def test_certified_with_a_pending_proof_answers_as_projected():
    # up to 3 velocities a certified model made stale by new samples answers from the
    # posterior itself, projected (no blend, no repair of an older proof): in line the
    # certified answers equal the projected mode's except right after a refit's proof
    a = OnlineEstimator(cfg(passivity='certified'))
    b = OnlineEstimator(cfg(passivity='projected'))
    ea, eb = _stream(a, 250, noise=0.02), _stream(b, 250, noise=0.02)
    ta = np.array([e.tau_hat for e in ea])
    tb = np.array([e.tau_hat for e in eb])
    same = np.all(np.isclose(ta, tb, rtol=1e-9, atol=1e-9), axis=1)
    # (after the first 20 answers. A rebase (every buffer_size / 4 = 15 samples) proves the
    # global bound, psd: until the next append that model blends joint by joint where a
    # projected one blends all joints alike (online.grounds), so while a joint's weight is below
    # 1 (here joint 3's model is barely better than its prior) one answer in 15 may differ)
    same = same[20:]
    assert same.mean() > 1.0 - 1.5 / 15, same.mean()
    tau = np.array([e.tau for e in ea])
    ratio = ((ta - tau) ** 2).mean(axis=0) / ((tb - tau) ** 2).mean(axis=0)
    assert np.all(ratio < 1.1), ratio
    assert a.diagnostics()['absorbs_rejected'] == 0
    assert all(e.power >= 0.0 for e in ea)
    a.close()
    b.close()


def test_the_learner_process_appends_each_round():
    est = OnlineEstimator(cfg(refit_mode='process', refit_period_s=0.0))
    try:
        t, i = 0.0, 0
        end = time.monotonic() + 60
        while not est.trained and time.monotonic() < end:
            q = path(t)
            est.process(t, NAMES, q, true_tau(q))
            t += 0.05
            i += 1
            time.sleep(0.005)
        assert est.trained, est.diagnostics()
        # a few more samples, slowly: each reaches the served model without a rebase
        for _ in range(5):
            q = path(t)
            est.process(t, NAMES, q, true_tau(q))
            t += 0.05
            time.sleep(0.005)
        last = path(t - 0.05)

        def holds_last(snap):
            # the last sample is in the served model: appended (the last row), or taken in by a
            # refit or rebase that ran since (rows in the buffer's order: anywhere); under load
            # the doubled buffer's refit can come after it
            return snap is not None and snap.model is not None and np.any(
                np.all(np.abs(snap.model.X_train_ - last) <= 1e-12, axis=1))
        end = time.monotonic() + 30
        while time.monotonic() < end and not holds_last(est._learner.snapshot()):
            time.sleep(0.02)
        assert holds_last(est._learner.snapshot())
        # and the process appends: samples that arrive while no refit runs are appended (under
        # load a refit may take in the first ones; more keep coming until one is appended)
        end = time.monotonic() + 30
        while est.diagnostics().get('appends', 0) == 0 and time.monotonic() < end:
            q = path(t)
            est.process(t, NAMES, q, true_tau(q))
            t += 0.05
            time.sleep(0.1)
        assert est.diagnostics()['appends'] > 0, est.diagnostics()
    finally:
        est.close()

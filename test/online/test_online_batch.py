"""
The array path (``OnlineEstimator.process_arrays``: the node's raw path) is ``process_batch``.

Two estimators with the same configuration get the same streams, one message by message
(``process_batch``), one as arrays in batches of every size; good messages are mixed with bad
ones of every kind a batch of like messages can hold (non-finite, out of range, negative stamps,
names in another order, a joint missing, duplicate names, missing positions). Every answer, every
rejection counter, the gap estimate and what reaches the learner must be the same. ``async``
learners that never fit: the answers come from the prior fitted to the buffer, deterministic.
"""
import numpy as np
import pytest

from dgp_ros.online import EstimatorConfig, OnlineEstimator
from dgp_ros.online.path.arrays import answers_of

NAMES = ('j0', 'j1', 'j2', 'j3')


def _config(**kw):
    base = {'refit_mode': 'async', 'joints': list(NAMES), 'min_samples': 5000,
            'buffer_size': 5000, 'refit_period_s': 0.0, 'min_sample_interval_s': 0.0,
            'selection': 'all'}
    base.update(kw)
    return EstimatorConfig(**base)


def _stream(rng, k, t0, names=NAMES):
    """Return k like messages (sec, nsec, V, E, P), some rows bad."""
    n = len(names)
    t = t0 + 0.001 * np.arange(k) + rng.uniform(0, 1e-4, k)
    sec = np.floor(t).astype(np.int64)
    nsec = np.round((t - sec) * 1e9).astype(np.int64).clip(0, 999_999_999)
    V = rng.normal(size=(k, n))
    E = 2.0 * V + 0.3 * np.tanh(V / 0.05) + 0.01 * rng.normal(size=(k, n))
    P = rng.normal(size=(k, n))
    for i in range(k):
        r = rng.random()
        if r < 0.05:
            V[i, rng.integers(n)] = rng.choice([np.nan, np.inf, -np.inf])
        elif r < 0.1:
            E[i, rng.integers(n)] = 1e9                     # beyond max_abs_effort
        elif r < 0.13:
            V[i, rng.integers(n)] = -2e4                    # beyond max_abs_velocity
        elif r < 0.16:
            sec[i] = -rng.integers(1, 5)                    # before the epoch
        elif r < 0.18:
            P[i, rng.integers(n)] = np.nan                  # non-finite position
    return sec, nsec, V, E, P


def _compare(a, b, ests, names=None):
    """Answers ``a`` against ``process_batch``'s estimates for the same messages."""
    ref = answers_of(ests)
    assert list(a.rows) == list(ref.rows)
    if not len(ref.rows):
        return
    for f in ('stamp_s', 'qd', 'tau', 'tau_hat', 'power', 'measured_power'):
        x, y = getattr(a, f), getattr(ref, f)
        assert np.array_equal(np.asarray(x).view(np.int64) if np.asarray(x).size else x,
                              np.asarray(y).view(np.int64) if np.asarray(y).size else y), \
            (f, names, x, y)
    assert np.array_equal(np.isnan(a.stddev), np.isnan(ref.stddev))
    assert list(a.source) == list(ref.source)


@pytest.mark.parametrize('positions', [False, True])
def test_array_path_decides_and_answers_as_the_message_path(positions, tmp_path, monkeypatch):
    kw = {}
    if positions:                       # a learner that needs positions: a rigid-body plugin
        (tmp_path / 'batch_test_dyn.py').write_text(
            'import numpy as np\n'
            'def tau_rb(q, qd, qdd):\n'
            '    return 0.1 * np.sin(q)\n')
        monkeypatch.syspath_prepend(str(tmp_path))
        kw = {'inverse_dynamics': 'python:batch_test_dyn:tau_rb', 'urdf_file': ''}
    one, many = OnlineEstimator(_config(**kw)), OnlineEstimator(_config(**kw))
    rng = np.random.default_rng(7)
    t0 = 1000.0
    try:
        for est in (one, many):          # the first message teaches the joints (message path)
            est.set_outputs(stddev=False, damping=False, residuals=False)
            est.process_batch([(t0, list(NAMES), np.ones(4), np.ones(4), np.ones(4))])
        t0 += 0.01
        answered = 0
        for round_ in range(60):
            k = int(rng.integers(1, 40))
            perm = rng.permutation(4) if rng.random() < 0.3 else np.arange(4)
            names = tuple(NAMES[i] for i in perm)
            if rng.random() < 0.05:
                names = ('j0', 'j1', 'j2', 'zz')                    # a joint missing
            elif rng.random() < 0.05:
                names = ('j0', 'j1', 'j1', 'j3')                    # duplicate names
            sec, nsec, V, E, P = _stream(rng, k, t0, names)
            t0 += 0.001 * k + 0.02 * rng.random()
            pos = None if (positions and rng.random() < 0.1) else P
            ests = one.process_batch([
                (int(sec[i]) + 1e-9 * int(nsec[i]), list(names), V[i], E[i],
                 None if pos is None else pos[i]) for i in range(k)])
            a = many.process_arrays(sec, nsec, names, V, E, pos)
            assert a is not None
            _compare(a, None, ests, names)
            answered += len(a)
        assert answered > 500
        d1, d2 = one.diagnostics(), many.diagnostics()
        for key in ('messages_received', 'messages_accepted', 'rejected', 'messages_missing',
                    'rejected_total', 'recent_rejected_fraction', 'passivity_fallbacks',
                    'answers_bounded', 'nonfinite_outputs', 'samples_added', 'estimated_power',
                    'measured_power', 'last_source'):
            assert d1.get(key) == d2.get(key), key
        assert sum(d1['rejected'].values()) > 50
        for x, y in zip(one.samples(), many.samples()):
            assert np.array_equal(x, y)
    finally:
        one.close(5)
        many.close(5)


def test_array_path_declines_what_it_does_not_cover():
    est = OnlineEstimator(_config(joints=[]))
    try:
        sec, nsec = np.array([1000]), np.array([0])
        V = E = np.ones((1, 4))
        # the joints are not known yet: the message path first (nothing counted here)
        assert est.process_arrays(sec, nsec, NAMES, V, E) is None
        assert est.diagnostics()['messages_received'] == 0
        est.process_batch([(999.0, list(NAMES), np.ones(4), np.ones(4), None)])
        assert est.process_arrays(sec, nsec, (), np.ones((1, 0)), np.ones((1, 0))) is None
        assert est.process_arrays(sec, nsec, NAMES, np.ones((1, 3)), np.ones((1, 3))) is None
        assert est.process_arrays(sec, nsec, NAMES, V, E) is not None
    finally:
        est.close(5)
    sync = OnlineEstimator(_config(refit_mode='sync'))
    sync.process_batch([(999.0, list(NAMES), np.ones(4), np.ones(4), None)])
    assert sync.process_arrays(np.array([1000]), np.array([0]), NAMES, np.ones((1, 4)),
                               np.ones((1, 4))) is None

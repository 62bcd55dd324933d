"""
Dropped messages are counted from stamp gaps and reported.

The 1 kHz issue: a best-effort queue that overflows drops silently, and the DDS lost-message event
does not fire for it.
"""
import numpy as np
import pytest

from dgp_ros.online import EstimatorConfig, OK, OnlineEstimator, WARN
from dgp_ros.online.path.health import GapCounter

NAMES = ['a', 'b']


def stamps(n=20000, period=1e-3, jitter=2e-4, seed=0):
    rng = np.random.default_rng(seed)
    return np.cumsum(period + rng.uniform(-jitter, jitter, n))


@pytest.mark.parametrize('seed', range(3))
def test_jittered_stream_counts_no_drops_and_scattered_drops_are_counted(seed):
    t = stamps(seed=seed)
    g = GapCounter()
    for s in t:
        g.note(s)
    assert g.missing == 0 and g.recent_fraction == 0.0
    rng = np.random.default_rng(10 + seed)
    keep = np.ones(t.size, bool)
    keep[rng.choice(np.arange(100, t.size), 300, replace=False)] = False
    g = GapCounter()
    for s in t[keep]:
        g.note(s)
    # adjacent drops merge into one gap: still counted once each
    assert abs(g.missing - 300) <= 3, g.missing


def test_a_burst_is_counted_but_a_pause_or_a_loop_is_not():
    t = stamps()
    g = GapCounter()
    for s in np.r_[t[:5000], t[5400:]]:          # a queue overflow: 400 in a row
        g.note(s)
    assert 380 <= g.missing <= 420
    g = GapCounter()
    for s in np.r_[t[:5000], t[5000:] + 5.0, t[:3000]]:   # a 5 s pause, then a bag loop
        g.note(s)
    assert g.missing == 0


def test_the_estimator_reports_missing_messages_and_warns():
    est = OnlineEstimator(EstimatorConfig(model='diag', prior='viscous', bias=False,
                                          refit_mode='sync', buffer_size=50, min_samples=10))
    rng = np.random.default_rng(0)
    t = stamps(3000, period=0.01, jitter=1e-3)
    drop = set(rng.choice(np.arange(200, 3000), 150, replace=False).tolist())
    for i, s in enumerate(t):
        if i in drop:
            continue
        q = np.array([np.sin(s), np.cos(0.5 * s)])
        est.process(s, NAMES, q, 2.0 * q)
    d = est.diagnostics()
    assert abs(d['messages_missing'] - 150) <= 3, d['messages_missing']
    assert d['recent_missing_fraction'] > 0.01
    # no loss reported by the middleware: the cause named is the publisher's stamps
    assert d['level'] >= WARN and 'gaps in the message stamps' in d['message']
    assert 'reported none lost' in d['message'] and 'queue_depth' not in d['message']
    est.note_lost(150)                                # the message-lost event counted them
    d = est.diagnostics()
    assert d['messages_lost'] == 150 and 'messages missing from the stream' in d['message']
    assert 'queue_depth' in d['message']
    est.set_source('bag')                             # a recorded log: its own holes
    d = est.diagnostics()
    assert 'gaps in the recorded stamps' in d['message'] and 'queue_depth' not in d['message']
    for s in t[-1] + 0.01 * np.arange(1, 1200):       # a clean stretch clears the warning
        q = np.array([np.sin(s), np.cos(0.5 * s)])
        est.process(s, NAMES, q, 2.0 * q)
    d = est.diagnostics()
    assert d['recent_missing_fraction'] == 0.0 and 'gaps in the' not in d['message']
    assert d['level'] == OK, d['message']


def test_a_change_of_publishing_rate_is_learned_not_counted_forever():
    t1 = stamps(3000, period=1e-3, jitter=1e-4)
    t2 = t1[-1] + stamps(3000, period=1e-2, jitter=1e-3, seed=1)     # 1 kHz -> 100 Hz
    g = GapCounter()
    for s in np.r_[t1, t2]:
        g.note(s)
    assert g.recent_fraction == 0.0 and g.missing < 2000

"""
The message path never waits on the learner process (issue 33).

No timing is asserted here: bench/arm_floor.py measures the latencies beside a bare relay.

* the learner runs under SCHED_IDLE where the OS allows it (else nice), and /diagnostics says
  which it got; ``DGP_LEARNER_SCHED=nice`` chooses nice;
* every new snapshot is received, unpickled and its answer plan built in the receiver thread
  before it is swapped in (the swap log counts them), so the message path only picks it up;
* a learner that gets no CPU at all (SIGSTOP) holding the ring's lock or not: every message is
  still answered, the samples wait on the node's side and reach the learner once it runs again;
* the ring's producer never waits for the lock.
"""
import os
import signal
import threading
import time

import numpy as np
import pytest

from dgp_ros.online import EstimatorConfig, OnlineEstimator
from dgp_ros.online.learner.plan import PlanCache
from dgp_ros.online.learner.snapshot import SwapLog
from dgp_ros.online.process.child import lower_priority
from dgp_ros.online.process.ring import SampleRing

NAMES = ['a', 'b', 'c']


def _cfg(**kw):
    base = {'buffer_size': 40, 'min_samples': 10, 'refit_period_s': 0.0, 'selection': 'all',
            'prior': 'viscous', 'bias': False, 'refit_mode': 'process'}
    base.update(kw)
    return EstimatorConfig(**base)


def _feed(est, rng, t, n, sleep=0.001):
    out = []
    for i in range(n):
        q = rng.uniform(-1.0, 1.0, 3)
        out.append(est.process(t + 0.01 * i, NAMES, q, 2.0 * q + 0.3 * np.tanh(q / 0.05)))
        if sleep:
            time.sleep(sleep)
    return out, t + 0.01 * n


#: how long a learner child at nice 10 may take for its first fit: a hang guard, not a speed
#: bar (two suites at once on 2 cores starved it past 60 s)
TRAIN_S = 200.0


def _train(est, rng):
    """
    Feed 20 samples, then wait (up to 5 s) for the first fit without feeding; again if need be.

    A stream fed on through the fit keeps the child's loop learning samples beside its own fit
    thread: under two suites at once the first fit of 10 samples was still running after 200 s
    with 18000 samples learned.
    """
    t = 0.0
    end = time.monotonic() + TRAIN_S
    while not est.trained and time.monotonic() < end:
        _, t = _feed(est, rng, t, 20)
        pause = min(end, time.monotonic() + 5.0)
        while not est.trained and time.monotonic() < pause:
            time.sleep(0.02)
    assert est.trained, str(est.diagnostics())
    return t


def _wait_status(est, key, end_s=10.0):
    end = time.monotonic() + end_s
    while time.monotonic() < end:
        d = est.diagnostics()
        if d.get(key):
            return d
        time.sleep(0.05)
    return est.diagnostics()


def _sched_of(pid: int) -> int:
    return os.sched_getscheduler(pid)


def test_lower_priority_idle_or_nice_in_a_child():
    """``lower_priority`` in a forked child: SCHED_IDLE (or the nice fallback), or nice."""
    for want in ('idle', 'nice'):
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:                                     # the child: report and exit
            try:
                got = lower_priority(want, 10)
                os.write(w, f'{got}|{os.sched_getscheduler(0)}|{os.nice(0)}'.encode())
            finally:
                os._exit(0)
        os.close(w)
        got, policy, nice = os.read(r, 100).decode().split('|')
        os.waitpid(pid, 0)
        os.close(r)
        if want == 'idle' and got == 'idle':
            assert int(policy) == os.SCHED_IDLE
        else:
            assert got.startswith('nice ') and int(nice) == int(got.split()[1]) >= 10 or \
                got == 'normal'
    with pytest.raises(ValueError):
        lower_priority('fifo', 10)


@pytest.mark.parametrize('sched', ['idle', 'nice'])
def test_the_learner_scheduling_is_reported_on_diagnostics(monkeypatch, sched):
    monkeypatch.setenv('DGP_LEARNER_SCHED', sched)
    est = OnlineEstimator(_cfg())
    try:
        d = _wait_status(est, 'learner_sched')
        got = d['learner_sched']
        pid = est._learner._proc.pid
        if got == 'idle':
            assert sched == 'idle' and _sched_of(pid) == os.SCHED_IDLE
        else:
            assert got.startswith('nice') and _sched_of(pid) == os.SCHED_OTHER
            assert sched == 'nice' or not hasattr(os, 'SCHED_IDLE')
    finally:
        est.close()


def test_the_snapshot_pipe_is_grown():
    import fcntl
    est = OnlineEstimator(_cfg())
    try:
        size = fcntl.fcntl(est._learner._out.fileno(), getattr(fcntl, 'F_GETPIPE_SZ', 1032))
        limit = int(open('/proc/sys/fs/pipe-max-size').read())
        assert size == min(1 << 20, limit) or size == 65536      # refused: the default
    finally:
        est.close()


def test_an_unknown_learner_scheduling_is_refused(monkeypatch):
    monkeypatch.setenv('DGP_LEARNER_SCHED', 'fast')
    with pytest.raises(ValueError, match='DGP_LEARNER_SCHED'):
        OnlineEstimator(_cfg())


def test_snapshots_are_prepared_off_the_message_path_and_logged():
    est = OnlineEstimator(_cfg())
    rng = np.random.default_rng(1)
    try:
        est.set_outputs(stddev=False, damping=False, residuals=False)
        t = _train(est, rng)
        _, t = _feed(est, rng, t, 100)
        d = est.diagnostics()
        assert d['snapshot_swaps'] >= 1
        assert d['snapshot_prepare_max_ms'] >= 0.0 and d['snapshot_receive_max_ms'] >= 0.0
        log = est._learner.swaps.recent()
        assert log and all(v >= 0 and r >= 0.0 and p >= 0.0 for v, r, p in log)
        # the plan of the snapshot answered from was built by the receiver thread
        plans = est._plans
        swaps0, built = est.diagnostics()['snapshot_swaps'], plans.built
        snap = est._learner.snapshot(False)
        plans.prepare(snap.model)                # already prepared: nothing is built again
        _, t = _feed(est, rng, t, 5, sleep=0)
        # the answers build nothing: only the receiver's swaps (one may be in flight) do
        swaps = est.diagnostics()['snapshot_swaps'] - swaps0
        assert plans.built - built <= swaps + 1, (plans.built - built, swaps)
        assert plans._plan is not None and plans._ok
    finally:
        est.close()


def test_plan_cache_picks_up_a_prepared_plan():
    est = OnlineEstimator(dataclasses_replace(_cfg(), refit_mode='sync'))
    rng = np.random.default_rng(2)
    _train(est, rng)
    model = est.model
    cache = PlanCache()
    cache.prepare(model)
    assert cache.built == 1 and cache._ready is not None
    plan = cache.get(model)
    assert cache.built == 1                         # picked up, not built again
    assert plan is not None and plan.current(model)
    Q = rng.uniform(-1, 1, (4, 3))
    tau, _ = plan.answers(Q, False)
    assert np.allclose(tau, model.predict_with_damping(Q, False, False)[0], rtol=1e-9,
                       atol=1e-12)


def dataclasses_replace(cfg, **kw):
    import dataclasses
    return dataclasses.replace(cfg, **kw)


def test_swap_log_summary():
    log = SwapLog()
    assert log.summary() == {'snapshot_swaps': 0}
    log.note(3, 0.001, 0.002)
    log.note(4, 0.0005, 0.004)
    s = log.summary()
    assert s['snapshot_swaps'] == 2 and s['snapshot_receive_max_ms'] == 1.0
    assert s['snapshot_prepare_max_ms'] == 4.0 and s['snapshot_prepare_last_ms'] == 4.0
    assert [v for v, _, _ in log.recent()] == [3, 4]


def test_ring_push_never_waits_for_a_held_lock():
    import multiprocessing
    lock = multiprocessing.get_context('fork').Lock()
    ring = SampleRing(2, 8, lock)
    try:
        lock.acquire()                  # the consumer holds it (preempted, stopped)
        for i in range(5):
            assert ring.push(np.array([i, i]))
        assert ring.backlog == 5
        ring.BACKLOG_ROWS = 6
        assert ring.push(np.array([5, 5]))
        assert not ring.push(np.array([6, 6]))         # the backlog is full: refused
        lock.release()
        assert ring.push(np.array([7, 7]))              # the backlog goes first, in order
        assert ring.backlog == 0
        assert ring.take()[:, 0].tolist() == [0, 1, 2, 3, 4, 5, 7]
        for i in range(8):
            ring.push(np.array([i, i]))
        assert not ring.push(np.array([9, 9]))         # full ring: refused
    finally:
        ring.close()


def test_ring_pending_counts_and_hands_over_the_backlog():
    """0 pending means every row pushed reached the consumer (the settle test's flake)."""
    import multiprocessing
    lock = multiprocessing.get_context('fork').Lock()
    ring = SampleRing(2, 4, lock)
    try:
        lock.acquire()                  # the consumer holds it at the last pushes
        for i in range(6):
            assert ring.push(np.array([i, i]))
        assert ring.pending(timeout=0) is None          # it never waits for the consumer
        lock.release()
        assert ring.pending() == 6                      # 4 in the ring, 2 kept back (full)
        assert ring.backlog == 2
        assert ring.take()[:, 0].tolist() == [0, 1, 2, 3]
        assert ring.pending() == 2 and ring.backlog == 0
        assert ring.take()[:, 0].tolist() == [4, 5]
        assert ring.pending() == 0
    finally:
        ring.close()


def test_ring_backlog_reaches_the_ring_when_the_stream_pauses():
    """The rows kept while the lock was held are written by ``flush`` with no further push."""
    import multiprocessing
    lock = multiprocessing.get_context('fork').Lock()
    ring = SampleRing(2, 4, lock)
    try:
        lock.acquire()
        for i in range(3):
            assert ring.push(np.array([i, i]))
        ring.flush()                                    # the lock is held: nothing moves
        assert ring.backlog == 3
        lock.release()
        ring.flush()
        assert ring.backlog == 0
        assert ring.take()[:, 0].tolist() == [0, 1, 2]
        lock.acquire()
        for i in range(6):
            ring.push(np.array([i, i]))
        lock.release()
        ring.flush()                                    # a full ring keeps the rest back
        assert ring.backlog == 2 and ring.take()[:, 0].tolist() == [0, 1, 2, 3]
    finally:
        ring.close()


def test_answers_keep_coming_while_the_learner_is_stopped():
    """SIGSTOP the learner (no CPU at all, maybe holding the ring's lock): nothing waits."""
    est = OnlineEstimator(_cfg())
    rng = np.random.default_rng(3)
    try:
        t = _train(est, rng)
        L = est._learner
        pid = L._proc.pid
        # stop it while it holds the ring's lock at least once: take the lock in its name
        os.kill(pid, signal.SIGSTOP)
        try:
            got, t = _feed(est, rng, t, 300, sleep=0)
            assert all(a is not None and a.source == 'model' for a in got)
            assert L._lock_ring.acquire(timeout=1.0)
            try:                              # the lock taken (as a stopped learner may hold it)
                got, t = _feed(est, rng, t, 300, sleep=0)
                assert all(a is not None for a in got)
                assert L._ring.backlog == 300
                d = est.diagnostics()          # never waits for the lock either
                assert 'samples_pending' not in d or d['samples_pending'] >= 300
            finally:
                L._lock_ring.release()
        finally:
            os.kill(pid, signal.SIGCONT)
        got, t = _feed(est, rng, t, 20)
        assert L._ring.backlog == 0                        # handed over at the next push
        end = time.monotonic() + 120                       # a starved child catches up late
        while time.monotonic() < end and est.diagnostics().get('samples_pending', 0):
            time.sleep(0.05)
        assert est.diagnostics().get('samples_pending', 0) == 0
        assert L.restarts == 0
    finally:
        est.close()


def test_reset_does_not_hold_the_message_path_while_the_learner_answers():
    est = OnlineEstimator(_cfg())
    rng = np.random.default_rng(4)
    try:
        t = _train(est, rng)
        pid = est._learner._proc.pid
        os.kill(pid, signal.SIGSTOP)            # the learner cannot answer the reset yet
        th = threading.Thread(target=est.reset)
        th.start()
        try:
            time.sleep(0.2)
            assert th.is_alive()
            got, t = _feed(est, rng, t, 50, sleep=0)   # answered meanwhile
            assert all(a is not None for a in got)
        finally:
            os.kill(pid, signal.SIGCONT)
        th.join(30)
        assert not th.is_alive()
    finally:
        est.close()


def test_the_plan_answers_a_model_with_elements_off_as_the_model():
    # an arm's outputs keep one element or none of the N x N (gp.select): the lean pass
    # computes only those, and answers (and damping matrices) as the model does
    from dgp_ros.gp import FullDGP
    from dgp_ros.gp.select import row_choices
    from dgp_ros.online.learner.plan import AnswerPlan
    rng = np.random.default_rng(4)
    Q = rng.normal(0.0, 0.6, (120, 4))
    T = 0.4 * Q + 0.3 * np.tanh(Q / 0.05) + 0.2 * np.sin(3 * Q) * Q + \
        0.01 * rng.normal(size=Q.shape)
    T[:, 2] = 0.5 * Q[:, 2] + 0.05 * rng.normal(size=120)        # nothing for a GP to add
    m = FullDGP(prior='friction', elements='auto', couplings='persistent',
                n_restarts=0).fit(Q, T)
    choices = row_choices(m.posterior_.structure, m.posterior_.hyper)
    assert 'all' not in choices and 0 < sum(c == 'own' for c in choices) < 4, choices
    plan = AnswerPlan(m)
    assert plan.rows.size == sum(c == 'own' for c in choices)
    Qs = rng.uniform(-2, 2, (16, 4))
    tau, D = plan.answers(Qs, True)
    t_ref, _, D_ref = m.predict_with_damping(Qs, False, True)
    assert np.allclose(tau, t_ref, rtol=1e-9, atol=1e-12)
    assert np.allclose(D, D_ref, rtol=1e-9, atol=1e-12)

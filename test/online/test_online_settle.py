"""
A learner that fell behind settles when the stream pauses; the answers carry the newest gains.

- The learner process's loop appends nothing while samples queue up (its rebases take them in).
  When the queue runs dry, the last samples still reach the model before the stream resumes
  (a CI run under load served a model that lacked the last 600 samples for as long as the
  stream paused).
- ``wait_for_refit`` returns once every sample sent is learned and held by the model and the
  node's snapshot carries the learner's newest gains, so a model saved then answers as the
  node did.
- A sample that moves the gains but not the model (a near-duplicate the buffer skips) reaches
  the snapshot's gains all the same.
"""
import dataclasses
import multiprocessing
import threading
import time

import numpy as np
from test_online_appends import cfg as _appends_cfg, NAMES, path, true_tau

from dgp_ros.online import OnlineEstimator
from dgp_ros.online.learner.learner import Learner
from dgp_ros.online.process.child import LearnerLoop
from dgp_ros.online.process.ring import SampleRing


def cfg(**kw):
    """Return the appends tests' configuration, refitting beside the answers at every chance."""
    return _appends_cfg(**dict({'refit_mode': 'async', 'refit_period_s': 0.0}, **kw))


def _row(t):
    q = path(t)
    return np.concatenate(([t], q, true_tau(q), np.full(3, np.nan)))


def _until(cond, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not cond():
        time.sleep(0.01)
    return cond()


def _loop():
    """Return a learner loop on a fresh ring: (loop, ring, its lock, command pipe, out pipe)."""
    ctx = multiprocessing.get_context('fork')
    lock = ctx.Lock()
    cmd_node, cmd_child = ctx.Pipe()
    out_node, out_child = ctx.Pipe()
    ring = SampleRing(10, 4096, lock)
    got = []
    threading.Thread(target=lambda: _read(out_node, got), daemon=True).start()
    loop = LearnerLoop(dataclasses.asdict(cfg()), cmd_child, out_child, lock,
                       (ring.name, ring.width, ring.capacity), None, False, False)
    return loop, ring, lock, cmd_node, out_node


def _fall_behind(ring_held_at_the_end: bool):
    """
    Feed a learner loop faster than it learns, then stop; return what it holds and why not.

    ``ring_held_at_the_end``: the last rows are pushed while the consumer holds the ring's lock
    (a learner preempted in ``take``, as a loaded machine does at any push): they wait in the
    producer's backlog, and no later push hands them over.
    """
    loop, ring, lock, cmd_node, out_node = _loop()
    # one sample per round: every round is full, as in a learner that cannot keep up (each
    # sample costs more than ROUND_S); the loop then never appends while samples wait
    loop.ROUND_S = 0.0
    # ... and takes every sample in (a loop seconds behind learns the newest thinned instead:
    # test_a_loop_far_behind_learns_the_newest_samples_thinned)
    loop.BEHIND_S = float('inf')
    runner = threading.Thread(target=loop.run, daemon=True)
    runner.start()
    L = loop.learner
    # and its rebases wait long while samples queue up: only the end of the queue brings them
    L.rebases.BACKLOG_ABSORB_WAIT = 1e6
    try:
        t = 0.0
        for _ in range(70):
            ring.push(_row(t))
            t += 0.05
        # trained, the buffer full and its hyper-parameters learned on at least half of it (no
        # refit for a doubled buffer would take the samples in)
        assert _until(lambda: L.trained and L.refits.hyper_samples >= 30 and
                      not L.refit_running(), 60), L.status()
        for i in range(300):                     # a burst: the loop falls behind
            if ring_held_at_the_end and i == 295:
                assert lock.acquire(timeout=10)  # the consumer holds the lock ...
            ring.push(_row(t))
            t += 0.05
        if ring_held_at_the_end:
            assert ring.backlog == 5             # ... so the last rows wait on this side
            lock.release()
        last = path(t - 0.05)
        # every row pushed has reached the learner (the backlog's too), and it learned them
        assert _until(lambda: ring.pending() == 0, 60)

        def holds_last():
            X = L.snapshot(variance=False, frozen=True).model.X_train_
            return np.any(np.all(np.abs(X - last) <= 1e-12, axis=1))
        if not _until(lambda: L.unheld == 0 and holds_last(), 30):
            X = L.snapshot(variance=False, frozen=True).model.X_train_
            raise AssertionError(                # all a failure under load needs to be read
                f'unheld {L.unheld}, learned {L.health.samples_added} (seq {L.window.seq}, '
                f'model {L.served.held}), outliers {L.health.samples_outliers}, skipped '
                f'{L.health.samples_skipped}, {len(X)} rows, closest to the last sample '
                f'{np.abs(X - last).max(axis=1).min():.3g}, ring backlog {ring.backlog}, '
                f'counters {L.health.counters()}')
        assert L.health.samples_added == 370
    finally:
        cmd_node.send(('stop', 5.0))
        runner.join(30)
        ring.close()
        cmd_node.close()
        out_node.close()
    assert not runner.is_alive()


def test_a_loop_that_fell_behind_brings_the_last_samples_to_the_model_when_they_run_out():
    _fall_behind(False)


def test_rows_kept_while_the_learner_held_the_ring_reach_it_when_the_stream_stops():
    # the settle test's flake (one full run in five: 'unheld 0' while the model lacked the
    # last sample): the last pushes met a learner holding the ring's lock, so they waited in
    # the producer's backlog; 'pending() == 0' did not count them and no push came to write
    # them. Forced here: it fails without SampleRing.pending writing the backlog
    _fall_behind(True)


def _read(conn, got):
    try:
        while True:
            got.append(conn.recv()[0])
    except (EOFError, OSError):
        pass


def test_wait_for_refit_returns_caught_up_and_a_saved_model_answers_as_the_node_did(tmp_path):
    path_ = str(tmp_path / 'model.npz')
    est = OnlineEstimator(cfg(refit_mode='process', model_path=path_))
    try:
        t = 0.0
        for _ in range(400):                       # faster than a first fit: a backlog
            q = path(t)
            est.process(t, NAMES, q, true_tau(q))
            t += 0.05
        last = path(t - 0.05)
        assert est.wait_for_refit(300)
        snap = est._learner.snapshot()
        assert np.any(np.all(np.abs(snap.model.X_train_ - last) <= 1e-12, axis=1))
        d = est.diagnostics()
        # every sample learned or, by a learner behind its stream, thinned and counted
        assert d['samples_added'] + d['samples_thinned'] == 400, d
        assert d['samples_added'] >= 1 and d['samples_pending'] == 0, d
        Qs = np.random.default_rng(2).uniform(-2, 2, (100, 3))
        before = est.predict(Qs)
        est.save()
    finally:
        est.close()
    again = OnlineEstimator(cfg(refit_mode='process', model_path=path_))
    try:
        assert again.trained and not again.load_error
        np.testing.assert_array_equal(again.predict(Qs), before)
    finally:
        again.close()


def test_gains_earned_without_a_new_model_reach_the_snapshot():
    L = Learner(cfg(refit_mode='sync', selection='novelty', selection_min_distance=0.5))
    t = 0.0
    for _ in range(60):
        q = path(t)
        L.learn(t, q, true_tau(q))
        t += 0.05
    assert L.trained
    before = L.snapshot(variance=False, frozen=True)
    q = path(t - 0.05)
    for _ in range(20):                             # the same velocity: skipped, yet scored
        L.learn(t, q, 1.3 * true_tau(q))
        t += 0.05
    assert L.health.samples_skipped >= 20 and L.version == before.version
    snap = L.snapshot(variance=False, frozen=True)
    w, a, c = L.skill_gains()
    assert not np.array_equal(w, before.model_weight) or not np.array_equal(a, before.prior_gain)
    np.testing.assert_array_equal(snap.model_weight, w)
    np.testing.assert_array_equal(snap.prior_gain, a)
    np.testing.assert_array_equal(snap.confidence, c)
    assert snap.model is before.model                # no copy of the model for new gains


def test_a_loop_far_behind_learns_the_newest_samples_thinned():
    """
    Seconds of samples waiting: the loop takes them all and learns one in k, the newest always.

    The others pass the front end and are counted (``samples_thinned``); the ring is drained at
    once instead of row by row, so the model follows the stream (issue 53: beside two busy
    processes the A320 at 4x real time learned samples from 30 s before).
    """
    loop, ring, lock, cmd_node, out_node = _loop()
    L = loop.learner
    try:
        t = 0.0
        for _ in range(2000):                    # 100 s of stamps before the loop runs
            ring.push(_row(t))
            t += 0.05
        loop.row_dt, loop.row_s = 0.05, 1e-3     # 1 ms a sample: 10 a round (both measured)
        assert loop._samples()                   # one round takes them all
        assert ring.pending() == 0
        thinned, added = L.health.samples_thinned, L.health.samples_added
        assert thinned > 1000 and 0 < added < 2000 - thinned + 1, (thinned, added)
        # the newest row was learned: it is the window's last
        assert np.allclose(L.window.rows[-1][2], path(t - 0.05))
        # a loop that keeps up learns every sample again
        for _ in range(3):
            ring.push(_row(t))
            t += 0.05
        before = L.health.samples_thinned
        assert loop._samples() and L.health.samples_thinned == before
    finally:
        ring.close()
        cmd_node.close()
        out_node.close()


def test_thinning_counts_the_samples_the_front_end_gives_not_the_measurements():
    """
    A stream faster than its interval, thinned one in k, learns one in k of what it lets through.

    A thinning by measurement index beside the interval's one in ten
    learned next to nothing of a 1 kHz burst (a loaded CI run: fewer than 20 samples).
    """
    L = Learner(cfg(refit_mode='sync', min_sample_interval_s=0.01, selection='all'))
    t = 0.0
    for _ in range(1000):                       # 1 s at 1 kHz: the interval gives 100
        q = path(t)
        L.learn(t, q, true_tau(q), thin=5)
        t += 0.001
    added, thinned = L.health.samples_added, L.health.samples_thinned
    assert added + thinned == 100 and added == 20, (added, thinned)

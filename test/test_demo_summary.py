"""
The demo's summary prints whatever the estimator's last /diagnostics held (no rclpy needed).

On a loaded machine the learner may not have finished a refit by the end of the demo: the
diagnostics then say 'None' for the refit's duration, and the summary printed a traceback
instead of the table (a learner at SCHED_IDLE beside four busy processes, 12 s synthetic demo).
"""
from types import SimpleNamespace

import numpy as np

from dgp_ros.apps.demo import analyse, print_summary


def _recorder(n=50):
    rng = np.random.default_rng(0)
    meas, est = {}, {}
    for i in range(n):
        qd = rng.uniform(-1, 1, 3)
        meas[0.01 * i] = (float(i), ['alpha', 'beta', 'airspeed'], qd, 2.0 * qd)
        est[0.01 * i] = (float(i) + 1e-3, qd, np.zeros(3))
    return SimpleNamespace(meas=meas, est=est, std={}, power=[], n_matrix=n, diag=None)


def test_the_summary_prints_before_any_refit_finished(capsys):
    res = analyse(_recorder())
    diag = {'level': 1, 'message': 'not yet trained (0/20 samples)', 'refits_ok': '0',
            'refits_failed': '0', 'last_refit_duration_s': 'None', 'latency_median_s': 'None',
            'latency_p99_s': '0.00092', 'certified_share': '1.0'}
    print_summary(res, diag, 22.1)
    out = capsys.readouterr().out
    assert 'last duration none yet;' in out
    assert 'median none yet, p99 0.92 ms' in out
    assert 'status: WARN: not yet trained' in out
    # a zero answer to a zero-mean force scores 1 (no answer)
    assert 'dgp_ros demo summary' in out and np.allclose(list(res['nmse'].values()), 1.0,
                                                         atol=0.3)


def test_the_summary_prints_the_numbers_it_has(capsys):
    res = analyse(_recorder())
    diag = {'level': 0, 'message': 'ok', 'refits_ok': '6', 'refits_failed': '1',
            'last_refit_duration_s': '0.2812', 'latency_median_s': '0.00193',
            'latency_p99_s': '0.00398'}
    print_summary(res, diag, 16.7)
    out = capsys.readouterr().out
    assert 'last duration 0.28 s;' in out and 'median 1.93 ms, p99 3.98 ms' in out

"""
The node's array path and the message path answer through one step (``OnlineEstimator._respond``).

So they give the same residual samples too: an in-process learner (``async``) with inverse
dynamics completes residual samples in ``learn``; the array path once dropped them (its
``learn_many`` returned a count), and the node's ``~/friction_residual`` stayed silent.
"""
import numpy as np

from dgp_ros.online import EstimatorConfig, OnlineEstimator
from dgp_ros.online.path.arrays import answers_of

NAMES = ('j0', 'j1', 'j2')


def test_the_array_path_gives_the_residuals_the_message_path_gives(tmp_path, monkeypatch):
    (tmp_path / 'one_path_dyn.py').write_text(
        'import numpy as np\n'
        'def tau_rb(q, qd, qdd):\n'
        '    return 0.1 * np.sin(q)\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = EstimatorConfig(refit_mode='async', joints=list(NAMES), min_samples=5000,
                          buffer_size=5000, refit_period_s=0.0, min_sample_interval_s=0.0,
                          selection='all', inverse_dynamics='python:one_path_dyn:tau_rb',
                          urdf_file='')
    one, many = OnlineEstimator(cfg), OnlineEstimator(cfg)
    rng = np.random.default_rng(3)
    t0, got = 1000.0, 0
    try:
        for est in (one, many):          # the first message teaches the joints (message path)
            est.process_batch([(t0, list(NAMES), np.ones(3), np.ones(3), np.ones(3))])
        for _ in range(20):
            k = int(rng.integers(1, 20))
            t = t0 + 0.01 + 0.001 * np.arange(k)
            t0 = t[-1]
            sec = np.floor(t).astype(np.int64)
            nsec = np.round((t - sec) * 1e9).astype(np.int64)
            V, P = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
            E = 2.0 * V + 0.01 * rng.normal(size=(k, 3))
            ref = answers_of(one.process_batch([
                (int(sec[i]) + 1e-9 * int(nsec[i]), list(NAMES), V[i], E[i], P[i])
                for i in range(k)]))
            a = many.process_arrays(sec, nsec, NAMES, V, E, P)
            assert np.array_equal(a.tau_hat, ref.tau_hat)
            assert np.array_equal(a.power.view(np.int64), ref.power.view(np.int64))
            assert [(r.stamp_s, r.residual.tolist()) for r in a.residuals] == \
                [(r.stamp_s, r.residual.tolist()) for r in ref.residuals]
            got += len(a.residuals)
        assert got > 100
    finally:
        one.close(5)
        many.close(5)

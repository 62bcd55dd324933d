"""
The samples spread evenly over the run: what hyper-parameters and elements are learned on.

``selection.Buffer(policy='even')`` keeps every stride-th row offered and halves itself when
full, so its rows span the whole run at any length in bounded memory; the window feeds it
every learned sample and retargets it with the buffer; a refit that learns hyper-parameters
takes it (``RefitJob.hyper_rows``), and ``fit(hyper_rows=)`` learns them there while the
posterior stays on the window's rows.
"""
import numpy as np

from dgp_ros.gp import FullDGP
from dgp_ros.online.learner.selection import Buffer
from dgp_ros.online.learner.window import Window


def test_an_even_buffer_spans_the_whole_run_in_bounded_memory():
    b = Buffer(64, 1, 'even')
    for k in range(10_000):
        b.append([float(k)], [float(k)])
        assert b.size <= 64
    Q, T = b.arrays()
    t = Q[:, 0]
    assert np.all(np.diff(t) > 0)                    # oldest first
    assert t[0] < 10_000 * 0.05 and t[-1] > 10_000 * 0.9   # from the start to the end
    gaps = np.diff(t)
    assert gaps.max() <= 2.0 * np.median(gaps)       # evenly: no stretch left out
    assert b.size >= 32


def test_the_window_feeds_and_retargets_its_even_sample():
    w = Window(16, 'coverage')
    w.ensure(2)
    rng = np.random.default_rng(0)
    for k in range(500):
        qd = rng.normal(size=2)
        r = 2.0 * qd
        w.add(float(k), qd, r, extra=(r, None))
    Q, T = w.even_arrays()
    assert 8 <= len(Q) <= 16
    np.testing.assert_allclose(T, 2.0 * Q)
    w.retarget(lambda y: 0.5)                        # targets = residual - correction
    Q2, T2 = w.even_arrays()
    np.testing.assert_allclose(T2, 2.0 * Q2 - 0.5)


def test_fit_learns_hyper_parameters_on_the_rows_it_is_given():
    rng = np.random.default_rng(1)
    Q = rng.uniform(-1, 1, (80, 2))
    T = np.sin(3 * Q) + 2.0 * Q
    Qh = rng.uniform(-1, 1, (120, 2))
    Th = np.sin(12 * Qh) + 2.0 * Qh                  # a shorter lengthscale than Q, T
    a = FullDGP(passivity='none', prior='viscous', n_restarts=0).fit(Q, T)
    b = FullDGP(passivity='none', prior='viscous', n_restarts=0).fit(Q, T, hyper_rows=(Qh, Th))
    np.testing.assert_allclose(b.X_train_, Q, rtol=1e-12)   # the posterior on the training rows
    ls_a = np.asarray(a.hyperparams_['log_ls'])
    ls_b = np.asarray(b.hyperparams_['log_ls'])
    assert ls_b.min() < ls_a.min() - 0.5, (ls_a, ls_b)   # the shortest lengthscale learned
    few = FullDGP(passivity='none', prior='viscous', n_restarts=0).fit(
        Q, T, hyper_rows=(Qh[:10], Th[:10]))         # too few rows: the training rows
    np.testing.assert_array_equal(few.hyperparams_['log_ls'], a.hyperparams_['log_ls'])
    arm = FullDGP(passivity='none', prior='viscous', n_restarts=0, couplings='persistent').fit(
        Q, T, hyper_rows=(Qh, Th))                   # an arm: its window's own rows
    np.testing.assert_array_equal(arm.hyperparams_['log_ls'], a.hyperparams_['log_ls'])
    drift = FullDGP(passivity='none', prior='viscous', n_restarts=0).fit(
        Q + [0.0, 3.0], T, hyper_rows=(Qh + [0.0, 3.0], Th))   # a velocity far from zero
    plain = FullDGP(passivity='none', prior='viscous', n_restarts=0).fit(Q + [0.0, 3.0], T)
    np.testing.assert_array_equal(drift.hyperparams_['log_ls'], plain.hyperparams_['log_ls'])

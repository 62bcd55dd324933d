"""
The robust spread of ``online.selection``: one function for the coverage buffer and the selector.

The coverage buffer's distance scale and the selector's novelty and outlier scales are the same
statistic (1.4826 x the median absolute deviation, floored), computed by ``robust_scale``; pinned
here to the formula, bit for bit.
"""
import numpy as np

from dgp_ros.online.learner.selection import Buffer, robust_scale, Selector


def _formula(A):
    med = np.median(A, axis=0)
    mad = 1.4826 * np.median(np.abs(A - med), axis=0)
    return med, np.maximum(mad, 1e-3 * (np.abs(A).mean(axis=0) + 1e-3))


def test_the_buffer_and_the_selector_use_the_same_robust_scale():
    rng = np.random.default_rng(3)
    Q = rng.standard_t(2, (64, 3)) * [1.0, 0.01, 0.0]        # heavy tails, a tiny and a
    T = rng.normal(size=(64, 3))                              # constant joint
    buf = Buffer(64, 3, 'coverage')
    for q, t in zip(Q, T):
        buf.append(q, t)
    med, scale = robust_scale(Q)
    assert np.array_equal(buf.scale, scale) and np.array_equal(buf.scale, _formula(Q)[1])
    assert np.array_equal(med, _formula(Q)[0])
    sel = Selector()
    st = sel._robust_stats(buf)
    assert all(np.array_equal(a, b) for a, b in zip(st, robust_scale(Q) + robust_scale(T)))
    med0, s0 = robust_scale(np.zeros((0, 3)))
    assert np.array_equal(med0, np.zeros(3)) and np.array_equal(s0, np.ones(3))

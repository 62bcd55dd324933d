"""Centred acceleration filter: no lag, jittered stamps, delay, wanted samples only, restarts."""
import numpy as np
import pytest

from dgp_ros.dynamics import AccelFilter
from dgp_ros.dynamics.filter import MIN_SIDE_SAMPLES


def _stamps(n, rate=1000.0, jitter=50e-6, seed=0, t0=1.7e9):
    """Epoch-like jittered stamps, strictly increasing."""
    rng = np.random.default_rng(seed)
    period = 1.0 / rate
    return t0 + np.arange(n) * period + np.clip(rng.normal(0, jitter, n), -0.4 * period,
                                                0.4 * period)


def _run(f, t, qd, want=None):
    out = []
    for i in range(len(t)):
        out += f.push(t[i], qd[i], want=True if want is None else bool(want[i]))
    return out


def test_estimate_of_a_sine_is_at_the_centre_not_lagged():
    """
    Check that the estimate of a sine is at the window centre, not lagged.

    qd = (sin, 2 cos)(w t) at 1 Hz: the estimate at t_c matches the derivative at t_c to the
    window's curvature bias (relative (w h)^2 / 10: 0.01 and 0.02 rad/s^2 here), while the
    derivative at t_c - h is off by up to 2 w^2 h = 1.6 rad/s^2.
    """
    t = _stamps(3000)
    w, h = 2 * np.pi, 0.02
    tt = t - t[0]
    qd = np.stack([np.sin(w * tt), 2.0 * np.cos(w * tt)], axis=1)
    out = _run(AccelFilter(h), t, qd)
    tc = np.array([s.t for s in out]) - t[0]
    qdd = np.array([s.qdd for s in out])
    truth = np.stack([w * np.cos(w * tc), -2.0 * w * np.sin(w * tc)], axis=1)
    lagged = np.stack([w * np.cos(w * (tc - h)), -2.0 * w * np.sin(w * (tc - h))], axis=1)
    assert len(out) > 2900
    assert np.abs(qdd - truth).max(axis=0) == pytest.approx([0.01, 0.02], rel=0.2)
    assert np.abs(lagged - truth).max() > 1.5   # what a lag of h would cost
    # the smoothed velocity is centred too, and the measured one is the sample's own
    np.testing.assert_allclose([s.qd_smooth[0] for s in out], np.sin(w * tc), atol=2e-3)
    np.testing.assert_array_equal([s.qd for s in out], qd[np.searchsorted(t, [s.t for s in out])])


def test_quadratic_velocity_is_exact_on_jittered_stamps():
    """A degree-2 fit reproduces a quadratic velocity exactly, whatever the stamps."""
    t = _stamps(400, jitter=300e-6, seed=3)
    tt = t - t[0]
    qd = np.stack([0.3 + 1.5 * tt - 4.0 * tt ** 2, -2.0 * tt ** 2], axis=1)
    out = _run(AccelFilter(0.01), t, qd)
    tc = np.array([s.t for s in out]) - t[0]
    np.testing.assert_allclose(np.array([s.qdd for s in out]),
                               np.stack([1.5 - 8.0 * tc, -4.0 * tc], axis=1), atol=1e-6)


def test_output_trails_input_by_the_half_window_and_only_wanted_samples_are_fitted():
    t = _stamps(1000)
    h = 0.03
    f = AccelFilter(h)
    got = {}
    for i in range(1000):
        for s in f.push(t[i], np.ones(3), want=(i % 10 == 0), payload=i):
            got[s.payload] = t[i] - s.t
    wanted = range(0, 1000, 10)
    early = {i for i in wanted if t[i] - h < t[0]}              # no full left half window yet
    late = {i for i in wanted if t[i] + h > t[-1]}              # still waiting for the right one
    assert set(got) == set(wanted) - early - late and len(got) > 90
    delays = np.array(list(got.values()))
    assert delays.min() >= h and delays.max() < h + 0.002     # next sample after t_c + h
    assert f.samples_in == 1000 and f.samples_out == len(got)
    assert f.pending == len(late) and f.dropped == len(early) and f.delay_s == h


def test_stamps_backwards_and_gaps_restart():
    dt = 2.0 ** -10                                             # exact binary stamps
    t = np.arange(300) * dt
    f = AccelFilter(8 * dt, max_gap_s=0.1)
    v = np.zeros(2)
    assert sum(len(f.push(x, v)) for x in t[:200]) == 200 - 8 - 8   # both edges
    assert f.pending == 8 and f.dropped == 8
    assert f.push(t[100], v) == [] and f.restarts == 1 and f.dropped == 16
    assert f.push(t[100], v) == [] and f.rejected == 1          # repeated stamp: ignored
    assert f.push(float('nan'), v) == [] and f.rejected == 2
    out = [s for x in t[101:150] for s in f.push(x, v)]
    assert out[0].t == t[108] and f.dropped == 16 + 8           # a new start, full window
    f.push(t[149] + 0.15, v)                                    # gap > max_gap_s
    assert f.restarts == 2 and f.dropped == 24 + 8 and f.pending == 1


def test_the_window_widens_to_the_stream_rate_and_too_slow_a_stream_is_named():
    # 250 Hz with a 5 ms half window: 1 sample per side, too few for the fit; the filter
    # widens the window to MIN_SIDE_SAMPLES per side at the measured rate and estimates
    f = AccelFilter(0.005)
    t = 10.0 + np.arange(100) * 0.004
    out = []
    for x in t:
        out += f.push(x, [2.0 * x])                              # qdd = 2
    assert abs(f.sample_interval_s - 0.004) < 1e-9
    assert abs(f.effective_half_window_s - MIN_SIDE_SAMPLES * 0.004) < 1e-9
    assert f.delay_s == f.effective_half_window_s and not f.too_slow
    assert len(out) >= 90 and np.allclose([s.qdd[0] for s in out], 2.0)
    # 30 Hz: the default 50 ms would hold one sample per side; 100 ms holds three
    g = AccelFilter(0.05)
    out = []
    for x in np.arange(90) / 30.0:
        out += g.push(x, [np.sin(x)])
    assert abs(g.effective_half_window_s - 0.1) < 1e-6 and len(out) >= 80
    assert max(abs(s.qdd[0] - np.cos(s.t)) for s in out) < 0.02
    # 10 Hz: the longest window (MAX_DELAY_S) holds 2 per side; 5 Hz: one, too slow to fit;
    # and an interval of 0.2 s is no gap at that rate
    h = AccelFilter(0.05)
    for x in np.arange(50) / 10.0:
        h.push(x, [1.0])
    assert not h.too_slow and h.samples_out >= 45
    h = AccelFilter(0.05)
    for x in np.arange(50) / 5.0:
        assert h.push(x, [1.0]) == []
    assert h.too_slow and h.restarts == 0 and h.dropped >= 45


def test_nonfinite_velocity_gives_no_estimate():
    t = _stamps(200)
    qd = np.ones((200, 1))
    qd[100] = np.nan
    g = AccelFilter(0.01)
    out = _run(g, t, qd)
    assert out and all(np.isfinite(s.qdd).all() for s in out)
    assert min(abs(s.t - t[100]) for s in out) > 0.009          # windows holding the NaN
    assert g.dropped >= 10 + 19


@pytest.mark.parametrize('kwargs, match', [
    ({'half_window_s': 0.3}, 'delay'), ({'half_window_s': 0.0}, 'delay'),
    ({'order': 0}, 'order'), ({'order': 2.5}, 'order'), ({'max_gap_s': 0.0}, 'max_gap_s'),
    ({'kernel': 'gauss'}, 'kernel'),
])
def test_parameters_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AccelFilter(**kwargs)


def test_joint_count_is_fixed_by_the_first_push():
    f = AccelFilter()
    f.push(0.0, np.zeros(7))
    with pytest.raises(ValueError, match=r'\(7,\)'):
        f.push(0.001, np.zeros(6))


def test_weighted_kernels_and_other_orders_are_also_centred():
    """
    All variants are centred.

    Degree 1 is not exact on jittered stamps (the curvature leaks through the asymmetric window),
    which is why the default degree is 2.
    """
    t = _stamps(600)
    tt = t - t[0]
    qd = np.sin(3.0 * tt)[:, None]
    errs = []
    for kw, tol in (({'kernel': 'tricube'}, 1e-3), ({'kernel': 'epanechnikov'}, 1e-3),
                    ({'order': 3}, 1e-5), ({'order': 2}, 1.5e-3), ({'order': 1}, 1e-2)):
        out = _run(AccelFilter(0.02, **kw), t, qd)
        tc = np.array([s.t for s in out]) - t[0]
        errs.append(np.abs(np.array([s.qdd[0] for s in out]) - 3.0 * np.cos(3.0 * tc)).max())
        assert errs[-1] < tol, kw
    assert errs[-1] > 3 * errs[-2]

"""
The grounds of an answer (issue 36): the skill gains, the blend toward the fallback, novelty.

The blend must keep every answer passive on many random points, inside and outside the data;
the gains must be zero without evidence and grow to one for a model that is right; a sample in
new territory that the model answers badly asks for an optimizing refit, a sample inside the
box of the last optimization never does.
"""
import numpy as np
import pytest

from dgp_ros.gp.hyper import _sf2_floor, PERSISTENT_SF2
from dgp_ros.gp.kernels import Structure
from dgp_ros.online import EstimatorConfig, OnlineEstimator
from dgp_ros.online.learner.grounds import blend
from dgp_ros.online.learner.skill import EVIDENCE_S, Skill

N = 3
RNG = np.random.default_rng(36)


class _Diag:
    """A diagonal prior whose m_d at the queries is given (the blend reads ``diag``)."""

    is_diagonal = True

    def __init__(self, m):
        self.m = m

    def diag(self, Q):
        return self.m


def _random_D(k, psd):
    A = RNG.normal(size=(k, N, N))
    if psd:                                         # PSD symmetric part plus a skew part
        S = RNG.normal(size=(k, N, N))
        return np.einsum('kij,klj->kil', A, A) + (S - np.transpose(S, (0, 2, 1)))
    return A


@pytest.mark.parametrize('scale', [0.1, 1.0, 30.0])    # inside and far outside any data
def test_the_per_joint_blend_keeps_a_psd_symmetric_part(scale):
    k = 2000
    Q = RNG.normal(size=(k, N)) * scale
    D = _random_D(k, psd=True)
    tau = np.einsum('kij,kj->ki', D, Q)
    for _ in range(20):
        w, a = RNG.uniform(size=N), RNG.uniform(size=N)
        m = RNG.uniform(0, 5, size=(k, N))
        tb, Db = blend(Q, tau, D, _Diag(m), w, a, per_joint=True)
        sym = 0.5 * (Db + np.transpose(Db, (0, 2, 1)))
        assert np.linalg.eigvalsh(sym).min() >= -1e-9 * np.abs(sym).max()
        assert np.all(np.einsum('ki,ki->k', Q, tb) >= -1e-9 * np.abs(tb * Q).sum(axis=1))
        assert np.allclose(tb, np.einsum('kij,kj->ki', Db, Q))


@pytest.mark.parametrize('scale', [0.1, 1.0, 30.0])
def test_the_scalar_blend_keeps_a_passive_answer_passive(scale):
    k = 2000
    Q = RNG.normal(size=(k, N)) * scale
    D = _random_D(k, psd=False)
    tau = np.einsum('kij,kj->ki', D, Q)
    # a projection: answers with negative power are moved onto q^T tau = 0
    p = np.einsum('ki,ki->k', Q, tau)
    tau = tau - np.minimum(p, 0.0)[:, None] * Q / np.einsum('ki,ki->k', Q, Q)[:, None]
    for _ in range(20):
        w, a = RNG.uniform(size=N), RNG.uniform(size=N)
        m = RNG.uniform(0, 5, size=(k, N))
        tb, _ = blend(Q, tau, None, _Diag(m), w, a, per_joint=False)
        assert np.all(np.einsum('ki,ki->k', Q, tb) >= -1e-9 * (np.abs(tb * Q).sum(axis=1) + 1))
        # weight 1: the model's answer; weight 0: the fallback a m q
        t1, _ = blend(Q, tau, None, _Diag(m), np.ones(N), a, per_joint=False)
        t0, _ = blend(Q, tau, None, _Diag(m), np.zeros(N), a, per_joint=False)
        assert np.allclose(t1, tau) and np.allclose(t0, a * m * Q)


def _feed(skill, n, model_err, prior_gain, noise=0.01, seed=0, dt=0.01):
    rng = np.random.default_rng(seed)
    for i in range(n):
        t = rng.normal(size=N)
        p = t / prior_gain if prior_gain else rng.normal(size=N)
        u = t + model_err * rng.normal(size=N)
        skill.note(t + noise * rng.normal(size=N), u, p, stamp=i * dt)
    return skill.gains()


def test_no_evidence_no_weight_and_a_right_model_earns_full_weight():
    s = Skill(N)
    w, a, c = s.gains()
    assert np.all(w == 0) and np.all(a == 0) and np.all(c == 0)
    # a right model beside a useless prior: full weight at once, confidence after the evidence
    w, a, c = _feed(s, 20, 0.01, 0.0, dt=0.01)              # right, but only 0.2 s of evidence
    assert np.all(w > 0.9) and np.all(c < 0.1), (w, c)
    w, a, c = _feed(s, int(2 * EVIDENCE_S / 0.01), 0.01, 0.0, seed=1)
    assert np.all(w > 0.95) and np.all(a < 0.2) and np.all(c > 0.95), (w, a, c)
    # a right prior: the model adds nothing over it, the answer is as confident
    w, a, c = _feed(Skill(N), int(2 * EVIDENCE_S / 0.01), 0.01, 1.0)
    assert np.all(a > 0.95) and np.all(c > 0.95), (w, a, c)


def test_a_model_worse_than_its_prior_falls_back_and_a_useless_prior_to_zero():
    w, a, c = _feed(Skill(N), 600, 3.0, 1.0)                 # the prior is right, the model not
    assert np.all(w < 0.3) and np.all(a > 0.95) and np.all(c > 0.8), (w, a, c)
    s = Skill(N)
    w, a, c = _feed(s, 600, 3.0, 0.0)                        # neither: answer (near) zero
    assert np.all(w < 0.3) and np.all(a < 0.2), (w, a, c)
    # and what is published, scaled by its confidence, is no worse than no answer
    rng = np.random.default_rng(9)
    t, p = rng.normal(size=(4000, N)), rng.normal(size=(4000, N))
    u = t + 3.0 * rng.normal(size=(4000, N))
    y = c * (a * p + w * (u - a * p))
    assert np.all(np.mean((t - y) ** 2, axis=0) <= np.mean(t ** 2, axis=0)), (w, a, c)


def test_the_gains_move_by_one_samples_weight_at_a_time():
    s = Skill(N)
    _feed(s, 400, 0.01, 0.0)
    w0, a0, c0 = s.gains()
    rng = np.random.default_rng(3)
    for i in range(400, 800):        # the model goes wrong at once, by the signal's size
        t = rng.normal(size=N)
        s.note(t, t + rng.normal(size=N), rng.normal(size=N), stamp=i * 0.01)
        w1, a1, c1 = s.gains()
        assert np.all(np.abs(w1 - w0) < 0.1) and np.all(np.abs(c1 - c0) < 0.1)
        w0, c0 = w1, c1
    assert np.all(w0 < 0.7)


def test_seeded_gains_are_the_gains_and_move_on_from_there():
    s = Skill(N)
    w, a, c = np.array([1.0, 0.5, 0.0]), np.array([0.2, 1.0, 0.7]), np.array([0.9, 0.4, 1.0])
    s.seed(w, a, c)
    for x, y in zip(s.gains(), (w, a, c)):
        assert np.allclose(x, y)
    w1, _, _ = _feed(s, 300, 0.01, 0.0)
    assert np.all(w1 > 0.9)


def test_the_signal_variance_floor_is_for_features_that_never_near_zero():
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.normal(size=500), 10.0 + rng.normal(size=500)])
    st = Structure.of('full', 2)
    floors = {st.elems[e]: _sf2_floor(st, X, e) for e in range(len(st.elems))}
    assert floors[(0, 0)] < 1e-4 and floors[(1, 0)] < 1e-4      # a reversing velocity
    assert 0.5 * PERSISTENT_SF2 < floors[(0, 1)] <= PERSISTENT_SF2   # an airspeed
    assert floors[(1, 1)] == floors[(0, 1)]


NAMES = ['a', 'b', 'c']


def _cfg(**kw):
    base = {'model': 'diag', 'passivity': 'projected', 'buffer_size': 200, 'min_samples': 20,
            'refit_mode': 'sync', 'refit_period_s': 100.0, 'selection': 'all',
            'prior': 'viscous', 'bias': False, 'optimize_every_n_refits': 5}
    base.update(kw)
    return EstimatorConfig(**base)


def _stream(est, force, leave):
    """Cover a box of velocities for 6 s, then 4 s beyond it (``leave``) or inside it."""
    rng = np.random.default_rng(1)
    for i in range(1000):
        t = 0.01 * i
        q = rng.uniform(0.2, 1.0, size=3)
        if t >= 6.0 and leave:
            q = np.array([3.0, 2.0, 2.5]) + 0.1 * np.sin(t)
        est.process(t, NAMES, q, force(q, t) + 1e-3 * rng.normal(size=3))
        if i == 599:
            before = est.diagnostics()['novelty_refits']
    d = est.diagnostics()
    est.close()
    return d['novelty_refits'] - before


def test_new_territory_answered_badly_asks_for_an_optimizing_refit():
    law = lambda q, t: (1.0 + (t >= 6.0) * 4.0 * q ** 2) * q        # noqa: E731
    assert _stream(OnlineEstimator(_cfg()), law, True) >= 1
    # by request (no optimizing refits at all): never
    assert _stream(OnlineEstimator(_cfg(optimize_every_n_refits=0)), law, True) == 0


def test_a_changed_law_inside_the_box_is_left_to_the_clock():
    law = lambda q, t: (1.0 + (t >= 6.0) * 4.0 * q ** 2) * q        # noqa: E731
    assert _stream(OnlineEstimator(_cfg()), law, False) == 0


def test_a_surprise_counts_only_where_the_error_matters_against_the_force():
    """Far above the model's recent error but small against the force: no new territory."""
    from dgp_ros.online.learner.skill import SURPRISE_SIGNAL
    rng = np.random.default_rng(3)

    def skill():
        s = Skill(N)
        for i in range(300):               # forces of RMS ~1, the model right to ~1e-3
            t = rng.normal(size=N)
            s.note(t, t + 1e-3 * rng.normal(size=N), 0.5 * t, stamp=0.01 * i)
        return s
    t = np.ones(N)
    assert 0.05 < SURPRISE_SIGNAL < 0.3
    s = skill()
    s.note(t, t + 0.05, 0.5 * t, stamp=3.0)     # 50x the model's recent error, 5 % of the force
    assert s.surprise == 0.0
    s = skill()
    s.note(t, t + 0.3, 0.5 * t, stamp=3.0)      # 30 % of the force
    assert s.surprise > 2.5
    # and a law that changes beyond the box by far more than that still asks for a refit
    law = lambda q, t: (1.0 + (t >= 6.0) * 4.0 * q ** 2) * q        # noqa: E731
    assert _stream(OnlineEstimator(_cfg()), law, True) >= 1


def test_a_model_that_goes_wrong_falls_back_within_about_a_second():
    # an arm learning every 10 ms (or a stream at 60 or 30 Hz): right for 10 s, then wrong by
    # three times the force; the model's weight falls below 0.3 within a second
    from dgp_ros.online.learner.skill import GAIN_HALF_LIFE_S, GAIN_HALF_LIFE_SAMPLES

    def fall_time(rate):
        s, rng, dt = Skill(N), np.random.default_rng(0), 1.0 / rate
        for i in range(int(10 * rate)):
            t = rng.normal(size=N)
            s.note(t, t + 0.05 * rng.normal(size=N), np.zeros(N), stamp=i * dt)
        for k in range(int(5 * rate)):
            t = rng.normal(size=N)
            s.note(t, t + 3.0 * rng.normal(size=N), np.zeros(N), stamp=(int(10 * rate) + k) * dt)
            if s.gains()[0].max() < 0.3:
                return (k + 1) * dt
        return np.inf
    assert GAIN_HALF_LIFE_S == 1.0 and GAIN_HALF_LIFE_SAMPLES == 100
    # within a second at every rate: the floor drops a model that does worse than no answer
    # (the short memory alone took 1.5 to 3 s at 30 Hz)
    assert max(fall_time(100), fall_time(60), fall_time(30)) <= 1.0

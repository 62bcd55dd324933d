"""The stream part (online/path/stream_part.py): where it answers, what, and when not."""
import os
import sys

import numpy as np

from dgp_ros.online import EstimatorConfig, OnlineEstimator
from dgp_ros.online.path.stream_part import StreamPart

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'gp'))
from test_coupled import aircraft  # noqa: E402,I100,I201

NAMES = ['alpha', 'beta', 'airspeed']


def _one_step(part, t, Q, T, after):
    """
    Stream t (k,), Q and T (k, N) through ``part`` beside a model that answers zero.

    Returns the part's answers one step ahead after ``after`` s: (index, (tau, D)) each.
    """
    answers = []
    for i in range(len(t)):
        mine = part.answer(Q[i:i + 1])
        if mine is not None and t[i] > after:
            answers.append((i, mine))
        part.learn(t[i:i + 1], Q[i:i + 1], T[i:i + 1], np.zeros((1, 3)),
                   None if mine is None else mine[0])
    return answers


def test_the_part_learns_an_aircraft_from_every_sample_and_answers_passively():
    part = StreamPart(3)
    t = np.arange(0.0, 20.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    # a model that answers nothing: the part's share grows toward 1
    answers = _one_step(part, t, Q, T, after=1.0)
    for i, mine in answers:
        assert np.allclose(np.einsum('kij,kj->ki', mine[1], Q[i:i + 1]), mine[0])
    errs = [(mine[0][0] - T[i]) ** 2 for i, mine in answers]
    nmse = np.mean(errs, axis=0) / T.var(axis=0)
    assert np.all(nmse < 1e-4), nmse
    assert part.share() > 0.99
    rng = np.random.default_rng(0)
    for scale in (1.0, 1e3):                       # inside and far outside the data
        Qr = rng.standard_normal((20000, 3)) * [0.1, 0.05, 30.0] * scale + [0, 0, 90.0]
        tau, D = part.answer(Qr)
        assert np.all(np.einsum('kn,kn->k', Qr, tau) >= 0.0)


def test_a_model_that_does_no_worse_answers_alone():
    part = StreamPart(3)
    t = np.arange(0.0, 5.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    for i in range(len(t)):
        mine = part.answer(Q[i:i + 1])
        part.learn(t[i:i + 1], Q[i:i + 1], T[i:i + 1], T[i:i + 1],    # a perfect model
                   None if mine is None else mine[0])
    assert part.share() == 0.0
    tau = np.ones((2, 3))
    assert part.weigh(Q[:2], tau, None)[0] is tau      # unchanged, the same array


def _stream(est, t, Q, T):
    out = np.zeros_like(T)
    for i in range(len(t)):
        out[i] = est.predict(Q[i])[0]
        est.process(float(t[i]), NAMES, Q[i], T[i])
    return out


def test_the_estimator_weighs_the_part_and_counts_its_answers_as_projected():
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    t = np.arange(0.0, 6.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    try:
        P = _stream(est, t, Q, T)
        assert est.stream is not None and est.stream.samples == len(t)
        d = est.diagnostics()
        assert 'couplings through airspeed' in d['structure']
        err = ((P[60:] - T[60:]) ** 2).mean(axis=0) / T.var(axis=0)
        assert np.all(err < 1e-3), err
        # every answer counted once, under a guarantee
        assert sum(d['answers_by_guarantee'].values()) == len(t)
    finally:
        est.close()


def test_no_part_on_an_arm_a_frozen_model_or_the_papers_mode():
    for cfg in (EstimatorConfig(refit_mode='sync', inverse_dynamics='urdf'),
                EstimatorConfig(refit_mode='sync', learning=False),
                EstimatorConfig(refit_mode='sync', passivity='paper'),
                EstimatorConfig(refit_mode='sync', prior='viscous')):
        assert not StreamPart.belongs(cfg)
    assert StreamPart.belongs(EstimatorConfig(refit_mode='sync'))


def test_a_reversing_system_silences_the_part_within_its_first_swing():
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    t = np.arange(0.0, 4.0, 0.01)
    Q = np.stack([np.sin(1.3 * t + 0.2), 0.5 * np.cos(0.9 * t), np.sin(2.1 * t + 1)], 1)
    T = 2.0 * Q + 0.3 * np.tanh(Q / 0.05)
    try:
        for i in range(len(t)):
            est.process(float(t[i]), ['a', 'b', 'c'], Q[i], T[i])
        assert not est.stream.active and est.stream.track.cols == []
        Qr = np.random.default_rng(1).standard_normal((50, 3))
        tau = np.ones((50, 3))
        assert est.stream.weigh(Qr, tau, None)[0] is tau       # the model's answers alone
    finally:
        est.close()


def test_the_forgetting_keeps_a_slow_stream_s_samples():
    # a half-life of FORGET_HALF_LIFE_S at 60 Hz, of FORGET_HALF_LIFE_SAMPLES messages at 5 Hz:
    # a slow stream keeps enough samples for the features, and still learns the aircraft
    from dgp_ros.online.path import stream_part as sp
    for rate, half_life in ((60.0, sp.FORGET_HALF_LIFE_S),
                            (5.0, sp.FORGET_HALF_LIFE_SAMPLES / 5.0)):
        part = StreamPart(3)
        t = np.arange(0.0, 120.0, 1.0 / rate)
        Q, T = aircraft(t)
        errs = [(mine[0][0] - T[i]) ** 2 for i, mine in _one_step(part, t, Q, T, after=60.0)]
        assert abs(part.half_life_s - half_life) < 1e-6 * half_life
        # the effective samples: a geometric sum over the half-life's messages
        assert abs(part.n - rate * half_life / np.log(2.0)) < 0.05 * part.n, part.n
        assert np.all(np.mean(errs, axis=0) / T.var(axis=0) < 1e-3)


def test_a_thinning_learner_still_feeds_every_sample_to_the_long_history():
    # a learner behind its stream learns one sample in k into its window, and every one into
    # the long history whose couplings the saved prior carries (Structure.push_thinned)
    from dgp_ros.online.learner.learner import Learner
    t = np.arange(0.0, 20.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    learner = Learner(EstimatorConfig(refit_mode='sync'))
    learner.set_joint_names(NAMES)
    try:
        for i in range(len(t)):
            learner.learn(float(t[i]), Q[i], T[i], None, thin=8)
        h = learner.health
        assert h.samples_thinned >= 0.8 * len(t)
        assert h.samples_added <= len(t) / 8 + 1
        # every sample but the window's outliers reached the history
        assert learner.structure.history_samples >= len(t) - h.samples_outliers - 1
        assert 'couplings through airspeed' in learner.status()['structure']
    finally:
        learner.close()


def _verdict_after(published_of):
    """
    Stream 20 s of the aircraft through a part; return its verdict at the end.

    The model beside it answers zero until 1 s and exactly after; ``published_of(t, weighed)``
    is what went out for the message at t, given the model's answer weighed with the part's
    (``StreamPart.weigh``, as the estimator publishes).
    """
    part = StreamPart(3)
    t = np.arange(0.0, 20.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    for i in range(len(t)):
        mine = part.answer(Q[i:i + 1])
        model = np.zeros((1, 3)) if t[i] < 1.0 else T[i:i + 1]
        weighed = part.weigh(Q[i:i + 1], model, None)[0]
        part.learn(t[i:i + 1], Q[i:i + 1], T[i:i + 1], model,
                   None if mine is None else mine[0], published_of(t[i], weighed))
    return part.verdict()


def test_the_first_answers_of_the_part_do_not_warn_for_the_rest_of_the_run():
    """
    The part's first answers are not held against the answers of the last seconds.

    Published while the part had just started (its skill not known yet: the model's zero went
    out), they counted from the part's first answer on: a run whose answers had been 1000x better
    than the part alone for 10 s said it did 5.9x worse (the demo, quiet), from its first
    second's few answers.
    """
    assert _verdict_after(lambda t, weighed: weighed) == []


def test_answers_worse_than_the_part_in_the_last_seconds_are_said():
    rng = np.random.default_rng(0)
    _, T = aircraft(np.arange(0.0, 20.0, 1.0 / 60.0))
    sd = 0.1 * T.std(axis=0)

    def noisy_late(t, weighed):              # 1 % of the variance: far worse than the part
        return weighed + (rng.standard_normal(3) * sd if t > 15.0 else 0.0)
    out = _verdict_after(noisy_late)
    assert len(out) == 1 and 'did worse than the parametric part alone' in out[0], out

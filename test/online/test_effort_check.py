"""
The effort is checked: a joint's effort that is no joint torque in N m gets a WARN with the fix.

``dynamics.effort_check`` regresses each joint's effort on the rigid-body torque; ``effort_scale``
turns a published unit (a motor current) into torque at the estimator's intake. On the shared
real UR10 log (skipped with the reason where ../shared is absent): its effort divided by a drive
gain of 12, as a driver that publishes currents would, warns within seconds; with
``effort_scale`` it learns as from torques. Torques never warn: the simulated Panda here, every
real arm's case of ``test_robot_family`` (``robot_family.check``).
"""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))), 'bench'))

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, simulate_arm  # noqa: E402,I100
from dgp_ros.dynamics.effort_check import EffortCheck, GAIN_RANGE, MIN_SAMPLES  # noqa: E402
from dgp_ros.online import EstimatorConfig, OnlineEstimator, WARN  # noqa: E402

import robot_family  # noqa: E402,I100

SAID = 'does not behave as joint torque'


def _check(gains, n=400, noise=0.05, seed=0, dt=0.01):
    rng = np.random.default_rng(seed)
    c = EffortCheck()
    for i in range(n):
        x = rng.normal(size=len(gains)) * 10.0
        y = np.asarray(gains) * x + 0.7 + noise * rng.normal(size=len(gains)) * 10.0
        c.learn_one(dt * i, x, y)
    return c


def test_the_gain_per_joint_and_the_warning_name_the_joint_and_the_fix():
    c = _check([1.0, 1.0 / 12.0, -1.0, 1.3])
    gain, corr = c.gains()
    np.testing.assert_allclose(gain, [1.0, 1 / 12, -1.0, 1.3], atol=0.02)
    said = c.warning(['a', 'b', 'c', 'd'], [])
    assert SAID in said and 'on b, c:' in said and 'effort_scale' in said
    assert '12' in said.split('here about')[1]             # the suggested scale of b
    assert not _check([1.0, 0.9, 1.6, 2.5, 0.4]).warning(['a', 'b', 'c', 'd', 'e'])
    # many samples over too short a time (the start of a motion) are not judged yet
    assert np.isnan(_check([0.08], n=MIN_SAMPLES * 2, dt=0.001).gains()[0]).all()
    # a scale in use multiplies the suggestion; one entry stands for every joint
    assert 'here about 24)' in _check([0.5 / 12.0], noise=0.002).warning(['a'], [1.0])
    assert 'here about 120)' in _check([0.1], noise=0.005).warning(['a'], [12.0])
    assert 'opposite sign' in _check([-1.0, -1.1]).warning(['a', 'b'])


def test_nothing_is_judged_before_enough_samples_or_where_the_model_explains_nothing():
    assert not _check([0.08], n=MIN_SAMPLES - 1).warning(['a'])
    assert np.isnan(_check([0.08], n=MIN_SAMPLES - 1).gains()[0]).all()
    # friction dominates: the effort hardly correlates with the model's torque
    noisy = _check([0.08, 1.0], noise=3.0)
    assert not noisy.judged()[0] and not noisy.warning(['a', 'b'])
    flat = EffortCheck()
    for i in range(MIN_SAMPLES + 500):
        flat.learn_one(0.01 * i, np.zeros(2), np.ones(2))
    assert np.isnan(flat.gains()[0]).all() and not flat.warning(['a', 'b'])


def test_effort_scale_is_validated_and_sized_by_the_joints():
    EstimatorConfig(effort_scale=[12.0]).validate()
    EstimatorConfig(effort_scale=[12.0, -1.0], joints=['a', 'b']).validate()
    for bad, why in (([0.0], 'zero'), ([1.0, 2.0], 'one per joint'), (['x'], 'finite numbers')):
        with pytest.raises(ValueError, match=why):
            EstimatorConfig(effort_scale=bad, joints=['a', 'b', 'c']).validate()
    with pytest.raises(ValueError, match='1 or 3'):
        EstimatorConfig(effort_scale=[1.0, 2.0]).check_dimension(3)
    EstimatorConfig(effort_scale=[2.0]).check_dimension(3)


@pytest.mark.parametrize('mode', ['sync', 'async'])
def test_the_scaled_effort_is_what_the_estimator_answers_and_learns(mode):
    est = OnlineEstimator(EstimatorConfig(effort_scale=[2.0, -3.0], refit_mode=mode))
    try:
        e = est.process(1.0, ['a', 'b'], [0.5, 0.2], [1.0, 1.0])
        np.testing.assert_array_equal(e.tau, [2.0, -3.0])
        assert e.measured_power == pytest.approx(0.5 * 2.0 - 0.2 * 3.0)
        # the node's batch path
        a = est.process_arrays(np.array([2, 3]), np.zeros(2, np.int64), ('b', 'a'),
                               np.array([[0.2, 0.5], [0.2, 0.5]]), np.ones((2, 2)))
        if a is not None:
            np.testing.assert_array_equal(a.tau, [[2.0, -3.0]] * 2)
    finally:
        est.close()


def test_torques_of_a_simulated_arm_do_not_warn():
    names = list(ARM_JOINTS['panda'])
    sim = simulate_arm('panda', duration_s=4.0, seed=3)
    est = OnlineEstimator(EstimatorConfig(inverse_dynamics='urdf', refit_mode='sync',
                                          urdf_file=example_robot_urdf('panda'), joints=names))
    for i in range(0, len(sim['t']), 2):
        est.process(sim['t'][i], names, sim['qd'][i], sim['effort'][i], sim['q'][i])
    d = est.diagnostics()
    est.close()
    assert SAID not in d['message'], d['message']
    gains = [g for g in d['effort_gain'] if g is not None]
    assert len(gains) >= 3 and all(0.8 < g < 1.25 for g in gains), d['effort_gain']


def _stream(log, div, seconds, **params):
    """Stream ``seconds`` of ``log``, effort / ``div``; (time, text) of the first WARN on it."""
    est = OnlineEstimator(EstimatorConfig(inverse_dynamics=log['plugin'], refit_mode='sync',
                                          **params))
    t, first, look = log['t'], None, log['t'][0]
    try:
        for i in np.flatnonzero(t - t[0] < seconds):
            est.process(robot_family._stamp(t[i]), log['names'], log['qd'][i],
                        log['tau'][i] / div, log['q'][i])
            if first is None and t[i] >= look:          # as a user watching /diagnostics
                look += 0.25
                d = est.diagnostics()
                if d['level'] >= WARN and SAID in d['message']:
                    first = (t[i] - t[0], d['message'])
        return first, est.diagnostics()
    finally:
        est.close()


@pytest.mark.parametrize('arm', ['ur10_real'])   # the Panda's torques: test_robot_family
def test_a_real_arm_whose_effort_is_a_current_warns_within_seconds(arm):
    path = robot_family.arm_dir(arm)
    if path is None:
        pytest.skip(f'the shared log of {arm} (../shared/data) is not here')
    log = robot_family.load_log(arm, path)
    first, _ = _stream(log, 12.0, 4.0)
    assert first is not None and first[0] <= 3.5, first
    said = first[1]
    assert 'effort_scale' in said and 'current' in said
    assert ('shoulder_lift_joint' if arm == 'ur10_real' else 'panda_joint2') in said
    # the same stream as torques, or as currents with their scale: no such warning, gains ~1
    for div, params in ((1.0, {}), (12.0, {'effort_scale': [12.0]})):
        first, d = _stream(log, div, 3.0, **params)
        assert first is None and SAID not in d['message'], (div, d['message'])
        assert all(g is None or GAIN_RANGE[0] < g < GAIN_RANGE[1] for g in d['effort_gain']), \
            d['effort_gain']


def test_a_current_with_its_scale_learns_as_torque():
    path = robot_family.arm_dir('ur10_real')
    if path is None:
        pytest.skip('the shared log of ur10_real (../shared/data) is not here')
    log = robot_family.load_log('ur10_real', path)
    split = float(log['t'][0] + 6.0)
    torque = robot_family.arm_case(log, split_s=split, baselines=False)
    current = robot_family.arm_case(dict(log, tau=log['tau'] / 12.0), split_s=split,
                                    baselines=False, effort_scale=[12.0])
    assert torque['trained'] and current['trained']
    np.testing.assert_allclose(current['held'], torque['held'], rtol=1e-3)
    # (without the scale the same stream warns: the test above)

"""Parametric friction baselines (dgp_ros/dynamics/baselines.py): recovery and the front end."""
import numpy as np
import pytest

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, friction_truth, simulate_arm
from dgp_ros.dynamics.baselines import fit_cv, fit_sigmoid, residual_stream


def test_coulomb_viscous_fit_recovers_its_parameters_and_the_bias():
    v = np.linspace(-2, 2, 801)
    y = 1.2 * np.tanh(v / 0.01) + 0.4 * v - 0.3
    c = fit_cv(v, y)
    assert c['eps'] == 0.01
    assert (c['Fc'], c['Fv'], c['b']) == pytest.approx((1.2, 0.4, -0.3), abs=1e-9)
    np.testing.assert_allclose(c['f'](v), y + 0.3, atol=1e-9)       # no bias in f


def test_sigmoid_fit_follows_a_stribeck_curve_better_than_coulomb_viscous():
    rng = np.random.default_rng(0)
    v = rng.uniform(-1.5, 1.5, 3000)
    truth = friction_truth('panda', np.tile(v[:, None], (1, 7)))[:, 1]
    y = truth + 0.2 + rng.normal(0, 0.1, v.size)
    c = fit_cv(v, y)
    s = fit_sigmoid(v, y, c)
    grid = np.linspace(-1.5, 1.5, 301)
    ref = friction_truth('panda', np.tile(grid[:, None], (1, 7)))[:, 1]

    def nmse(f):
        return np.mean((f(grid) - ref) ** 2) / np.var(ref)
    assert nmse(s['f']) < 0.01 and nmse(s['f']) < nmse(c['f'])
    assert s['b'] == pytest.approx(0.2, abs=0.05)


def test_residual_stream_is_friction_plus_bias_one_sample_per_interval():
    pytest.importorskip('pinocchio')
    d = simulate_arm('panda', 2.0, seed=0, noise_sd=0.0, velocity_noise_sd=0.0)
    Q, R = residual_stream(d['t'], d['q'], d['qd'], d['effort'], example_robot_urdf('panda'),
                           ARM_JOINTS['panda'], 0.02, 0.01)
    assert Q.shape == R.shape and Q.shape[1] == 7
    assert 180 <= Q.shape[0] <= 200                     # 2 s at one sample per 10 ms
    # the residual is friction + bias up to the acceleration filter's error (inertia)
    err = R - friction_truth('panda', Q) - d['bias']
    assert np.median(np.abs(err)) < 0.05

"""Friction residual on simulated arm data: ~0 without friction, the friction + bias with it."""
import numpy as np
import pytest

from dgp_ros.dynamics import (AccelFilter, ARM_JOINTS, example_robot_urdf, FrictionResidual,
                              simulate_arm, UrdfInverseDynamics)

pytest.importorskip('pinocchio')


@pytest.fixture(scope='module')
def panda_dyn():
    return UrdfInverseDynamics(urdf_file=example_robot_urdf('panda'), joints=ARM_JOINTS['panda'])


def _stream(fr, d, every=1):
    out = []
    for i in range(len(d['t'])):
        out += fr.push(d['t'][i], d['q'][i], d['qd'][i], d['effort'][i], want=(i % every == 0))
    idx = np.searchsorted(d['t'], [s.stamp_s for s in out])
    assert np.array_equal(d['t'][idx], [s.stamp_s for s in out])
    return out, idx


def test_residual_is_zero_without_friction_bias_and_noise(panda_dyn):
    """
    Only the filter's error remains.

    |qdd_hat - qdd| ~ 1e-3 rad/s^2 on this trajectory, times inertias of a few kg m^2; a lag of h
    instead would leave ~M qddd h ~ 0.1 N m.
    """
    d = simulate_arm('panda', 3.0, bias=False, noise_sd=0.0, velocity_noise_sd=0.0,
                     friction=False, seed=1, pause_hz=0.0)
    assert np.abs(d['effort']).max() > 20.0
    fr = FrictionResidual(panda_dyn, AccelFilter(0.02))
    out, idx = _stream(fr, d)
    assert len(out) > 2900 and fr.delay_s == 0.02
    res = np.array([s.residual for s in out])
    assert np.abs(res).max() < 0.01
    np.testing.assert_allclose([s.qdd for s in out], d['qdd'][idx], atol=5e-3)
    np.testing.assert_allclose([s.tau_rb for s in out], d['tau_rb'][idx], atol=0.01)
    np.testing.assert_array_equal([s.q for s in out], d['q'][idx])
    np.testing.assert_array_equal([s.effort for s in out], d['effort'][idx])


def test_residual_recovers_friction_and_bias_to_the_noise(panda_dyn):
    d = simulate_arm('panda', 4.0, seed=2)
    fr = FrictionResidual(panda_dyn)
    out, idx = _stream(fr, d, every=10)
    err = np.array([s.residual for s in out]) - (d['friction'] + d['bias'])[idx]
    assert np.sqrt(np.mean(err ** 2)) == pytest.approx(0.3, rel=0.08)   # torque noise 0.3
    assert abs(err.mean(axis=0)).max() < 0.1                            # no systematic part
    assert fr.samples_in == len(d['t']) and fr.samples_out == len(out)
    assert fr.negative_power_fraction < 0.02 and fr.restarts == 0


def test_without_inverse_dynamics_samples_pass_through_at_once():
    fr = FrictionResidual(None)
    assert fr.filter is None and fr.delay_s == 0.0
    out = fr.push(1.0, None, [1.0, -1.0], [2.0, 3.0])
    assert len(out) == 1 and out[0].stamp_s == 1.0 and out[0].qdd is None and out[0].q is None
    np.testing.assert_array_equal(out[0].residual, [2.0, 3.0])
    np.testing.assert_array_equal(out[0].tau_rb, [0.0, 0.0])
    assert fr.push(1.001, None, [1.0, -1.0], [2.0, 3.0], want=False) == []
    assert fr.negative_power == 1 and fr.samples_in == 2 and fr.samples_out == 1


def test_raw_effort_of_an_arm_has_negative_power_on_many_samples():
    d = simulate_arm('panda', 3.0, seed=3)
    fr = FrictionResidual(None)
    for i in range(0, len(d['t']), 5):
        fr.push(d['t'][i], d['q'][i], d['qd'][i], d['effort'][i])
    assert fr.negative_power_fraction > 0.25   # gravity: what the URDF front end removes


def test_inputs_are_checked(panda_dyn):
    fr = FrictionResidual(panda_dyn)
    with pytest.raises(ValueError, match='q .joint positions'):
        fr.push(0.0, None, np.zeros(7), np.zeros(7))
    with pytest.raises(ValueError, match='one shape'):
        fr.push(0.0, np.zeros(7), np.zeros(7), np.zeros(6))

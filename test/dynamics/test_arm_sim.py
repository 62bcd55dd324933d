"""
Simulated arm data.

Trajectories inside the limits, analytic derivatives, passive friction, the effort decomposition,
jittered stamps, determinism, and the URDF lookup.
"""
import numpy as np
import pytest

from dgp_ros.dynamics import (ARM_JOINTS, example_robot_urdf, FRICTION_TABLES, friction_truth,
                              simulate_arm, UrdfInverseDynamics)
from dgp_ros.dynamics import arm_sim

pytest.importorskip('pinocchio')


@pytest.fixture(scope='module')
def panda():
    return simulate_arm('panda', 10.0, seed=0)


def test_shapes_names_and_jittered_increasing_stamps(panda):
    d = panda
    assert d['names'] == ARM_JOINTS['panda'] and d['rate_hz'] == 1000.0
    k = 10000
    for key in ('q', 'qd', 'qd_true', 'qdd', 'effort', 'tau_rb', 'friction'):
        assert d[key].shape == (k, 7), key
    dt = np.diff(d['t'])
    assert dt.min() > 0.0 and 0.0003 < dt.max() - dt.min() < 0.0008   # jitter, clipped
    assert np.std(d['t'] - np.arange(k) * 1e-3) == pytest.approx(50e-6, rel=0.1)


def test_trajectory_inside_the_limits_and_exciting(panda):
    dyn = UrdfInverseDynamics(urdf_file=example_robot_urdf('panda'), joints=ARM_JOINTS['panda'])
    margin = 0.14 * 0.5 * (dyn.upper - dyn.lower)
    assert (panda['q'].min(axis=0) > dyn.lower + margin).all()
    assert (panda['q'].max(axis=0) < dyn.upper - margin).all()
    peak = np.abs(panda['qd_true']).max(axis=0)
    assert (peak[:4] > 1.0).all() and (peak <= 2.0 + 1e-9).all()
    assert (peak < dyn.velocity_limit).all()


def test_derivatives_are_consistent():
    """
    Check that qd and qdd are the derivatives of q and qd.

    Central differences, regular stamps.
    """
    d = simulate_arm('panda', 2.0, seed=0, jitter_sd_s=0.0)
    t, q, qd, qdd = d['t'], d['q'], d['qd_true'], d['qdd']
    dt = (t[2:] - t[:-2])[:, None]
    np.testing.assert_allclose((q[2:] - q[:-2]) / dt, qd[1:-1], atol=1e-5)
    np.testing.assert_allclose((qd[2:] - qd[:-2]) / dt, qdd[1:-1], atol=1e-4)


def test_effort_decomposition_and_noise(panda):
    d = panda
    noise = d['effort'] - d['tau_rb'] - d['friction'] - d['bias']
    assert noise.std() == pytest.approx(0.3, rel=0.03) and abs(noise.mean()) < 0.01
    np.testing.assert_array_equal(d['bias'], FRICTION_TABLES['panda'][:, 4])
    np.testing.assert_allclose(d['friction'], friction_truth('panda', d['qd_true']))
    assert np.std(d['qd'] - d['qd_true']) == pytest.approx(0.003, rel=0.05)


def test_friction_is_passive_with_panda_magnitudes():
    v = np.linspace(-3, 3, 6001)[:, None] * np.ones(7)
    f = friction_truth('panda', v)
    assert (v * f >= 0).all() and f.shape == v.shape
    fast = f[-1] - FRICTION_TABLES['panda'][:, 3] * 3.0     # Coulomb level at 3 rad/s
    assert (fast >= 0.3 - 1e-6).all() and (fast <= 1.3 + 1e-6).all()
    peak = np.abs(f[(v[:, 0] > 0) & (v[:, 0] < 0.05)]).max(axis=0)   # Stribeck hump
    assert (peak > FRICTION_TABLES['panda'][:, 0] + 0.1).all()
    assert friction_truth('panda', np.zeros(7)) == pytest.approx(np.zeros(7))
    with pytest.raises(ValueError, match='N = 6'):
        friction_truth('ur5', np.zeros(7))


def test_power_fractions(panda):
    # residual: passive up to noise and bias, a few percent negative near the common standstills
    # (as in a real friction log); raw effort: gravity makes it often negative
    assert 0.01 < panda['nonpassive_fraction'] < 0.05
    assert 0.25 < panda['raw_negative_power_fraction'] < 0.6
    per_joint = panda['nonpassive_fraction_per_joint']
    assert per_joint.shape == (7,) and per_joint.max() < 0.2
    # without the standstills, seven joints moving at once almost never sum to a negative power
    calm = simulate_arm('panda', 10.0, seed=0, pause_hz=0.0)
    assert calm['nonpassive_fraction'] < 0.002


def test_pauses_stop_every_joint_together(panda):
    speed = np.abs(panda['qd_true']).max(axis=1)
    t = panda['t']
    for stop in (0.0, 5.0):                      # pause_hz = 0.2: a standstill every 5 s
        near = np.abs(t - stop) < 0.002
        assert speed[near].max() < 1e-3
    assert speed[np.abs(t - 2.5) < 0.002].min() > 0.05


def test_seed_determinism_and_options():
    a = simulate_arm('ur5', 1.0, seed=5)
    b = simulate_arm('ur5', 2.0, seed=5)
    c = simulate_arm('ur5', 1.0, seed=6)
    np.testing.assert_array_equal(a['q'], b['q'][:1000])     # trajectory independent of length
    assert not np.array_equal(a['q'], c['q'])
    assert a['names'] == ARM_JOINTS['ur5'] and a['effort'].shape == (1000, 6)
    z = simulate_arm('ur5', 0.5, noise_sd=0.0, velocity_noise_sd=0.0, bias=False,
                     friction=False, t0_s=100.0)
    np.testing.assert_array_equal(z['effort'], z['tau_rb'])
    np.testing.assert_array_equal(z['qd'], z['qd_true'])
    assert 99.9995 < z['t'][0] < 100.0005


def test_urdf_lookup(monkeypatch, tmp_path):
    assert example_robot_urdf('panda').endswith('panda_description/urdf/panda.urdf')
    with pytest.raises(ValueError, match="'panda', 'ur5'"):
        example_robot_urdf('kuka')
    monkeypatch.setattr(arm_sim.sys, 'prefix', str(tmp_path))
    monkeypatch.setattr(arm_sim.site, 'getsitepackages', lambda: [str(tmp_path)])
    monkeypatch.setattr(arm_sim.site, 'getusersitepackages', lambda: str(tmp_path))
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    monkeypatch.setattr(arm_sim, '_FALLBACK_PREFIXES', ())
    with pytest.raises(FileNotFoundError, match='pip install example-robot-data'):
        example_robot_urdf('panda')


def test_a_coupled_wrist_motor_is_passive_and_shows_in_both_joints():
    """Its friction rides on the last two joints' velocity sum: passive, not per joint."""
    rng = np.random.default_rng(3)
    for scale in (0.1, 1.0, 100.0):                   # inside and far outside an arm's speeds
        qd = rng.standard_normal((5000, 7)) * scale
        f = arm_sim.coupled_wrist_friction(qd, 0.6)
        assert np.all(np.einsum('kn,kn->k', qd, f) >= 0.0)
        assert np.all(f[:, :5] == 0.0) and np.array_equal(f[:, 5], f[:, 6])
    # opposite velocities: the motor stands still and neither joint feels it
    assert np.allclose(arm_sim.coupled_wrist_friction(np.array([0, 0, 0, 0, 0, 1.0, -1.0]),
                                                      0.6), 0.0)
    a = arm_sim.simulate_arm('ur5', 2.0, rate_hz=200.0, seed=1, friction='realistic')
    b = arm_sim.simulate_arm('ur5', 2.0, rate_hz=200.0, seed=1, friction='realistic',
                             coupled_wrist=0.6)
    extra = b['friction'] - a['friction']
    assert np.allclose(extra, arm_sim.coupled_wrist_friction(a['qd_true'], 0.6))
    assert np.abs(extra[:, -2:]).max() > 0.5 and b['coupled_wrist'] == 0.6

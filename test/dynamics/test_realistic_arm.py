"""
Realistic friction and the payload error of the simulated arm (dgp_ros/dynamics/realistic.py).

The friction is passive, asymmetric, pose-dependent and outside the estimator's prior family (a
least-squares fit of that family leaves a residual it does not leave on the table friction); the
payload appears in the residual ``effort - tau_rb_urdf`` as the gradient of its potential energy
(a conservative, pose-dependent torque) plus a small inertial part; the defaults are unchanged.
"""
import numpy as np
import pytest

from dgp_ros.dynamics import (ARM_JOINTS, example_robot_urdf, FRICTION_TABLES, friction_truth,
                              payload_inverse_dynamics, realistic_friction, REALISTIC_TABLES,
                              simulate_arm)
from dgp_ros.dynamics.realistic import PAYLOAD_MOUNT

pytest.importorskip('pinocchio')

G = 9.81


def _family_fit_nmse(v, f):
    """
    Best NMSE of the prior family per joint, by least squares.

    Coulomb + Gaussian Stribeck + viscous + a constant bias (the estimator's ``friction+stribeck``
    with ``bias``), the sign and Stribeck velocities from fine grids, the coefficients linear.
    """
    out = []
    for j in range(f.shape[1]):
        x, y = v[:, j], f[:, j]
        best = np.inf
        for eps in np.geomspace(0.003, 0.05, 9):
            for vs in np.geomspace(0.01, 0.5, 30):
                s = np.tanh(x / eps)
                A = np.column_stack([s, np.exp(-(x / vs) ** 2) * s, x, np.ones_like(x)])
                c, *_ = np.linalg.lstsq(A, y, rcond=None)
                best = min(best, float(np.mean((A @ c - y) ** 2)))
        out.append(best / float(np.mean(y ** 2)))
    return np.array(out)


@pytest.mark.parametrize('robot', ['panda', 'ur5'])
def test_realistic_friction_is_passive_for_any_load(robot):
    n = REALISTIC_TABLES[robot].shape[0]
    rng = np.random.default_rng(1)
    v = rng.uniform(-3, 3, (20000, n)) * rng.choice([1e-4, 1e-2, 1.0], (20000, n))
    load = rng.normal(0, 30, (20000, n))
    f = realistic_friction(robot, v, load)
    assert f.shape == v.shape
    assert (v * f >= 0).all()
    assert np.all(realistic_friction(robot, np.zeros(n)) == 0.0)


def test_realistic_friction_is_asymmetric_and_grows_with_the_load():
    v = np.full(7, 0.5)
    up, down = realistic_friction('panda', v), realistic_friction('panda', -v)
    assert (up > 0).all() and (down < 0).all()
    assert (up + down > 0.1 * up).all()                 # |f(+v)| > |f(-v)| by > 10 %
    loaded = realistic_friction('panda', v, np.full(7, 20.0))
    np.testing.assert_allclose(loaded - up, REALISTIC_TABLES['panda'][:, 7] * 20.0 *
                               np.tanh(0.5 / 0.015))


def test_realistic_friction_is_not_in_the_prior_family_but_the_table_friction_is():
    """A least-squares fit of Coulomb + Stribeck + viscous + bias: what it leaves."""
    v = np.tile(np.linspace(-2.0, 2.0, 2001)[:, None], (1, 7))
    realistic = _family_fit_nmse(v, realistic_friction('panda', v))
    table = _family_fit_nmse(v, friction_truth('panda', v))
    assert (table < 1e-4).all(), table                  # in the family: the grid's error
    assert (realistic > 5e-4).all(), realistic          # > 2.2 % RMS left on every joint
    assert (realistic > 30 * table).all()
    # on a trajectory the load (pose) adds to it: measured 3e-3 .. 1.7e-2 (joint 2)
    d = simulate_arm('panda', 10.0, seed=0, friction='realistic', payload_kg=0.5)
    loaded = _family_fit_nmse(d['qd_true'][::5], d['friction'][::5])
    assert (loaded > 2e-3).all() and loaded[1] > 1e-2, loaded


def test_simulated_realistic_friction_depends_on_the_pose():
    """The same velocity at different poses: different friction (the gravity load)."""
    d = simulate_arm('panda', 10.0, seed=0, friction='realistic', payload_kg=0.5)
    table = REALISTIC_TABLES['panda']
    unloaded = realistic_friction('panda', d['qd_true'])
    extra = d['friction'] - unloaded
    frame, offset = PAYLOAD_MOUNT['panda']
    true_arm = payload_inverse_dynamics(example_robot_urdf('panda'), ARM_JOINTS['panda'], frame,
                                        0.5, offset)
    g = true_arm(d['q'], 0 * d['q'], 0 * d['q'])     # the gravity torque the joints carry
    np.testing.assert_allclose(extra, table[:, 7] * np.abs(g) * np.tanh(d['qd_true'] / 0.015),
                               atol=1e-9)
    assert extra[:, 1].std() > 0.3           # joint 2 carries the arm: > 0.3 N m of variation
    assert (d['qd_true'] * d['friction'] >= 0).all()


@pytest.mark.parametrize('robot', ['panda', 'ur5'])
def test_payload_is_a_conservative_pose_dependent_gravity_torque_in_the_residual(robot):
    m = 0.5
    d = simulate_arm(robot, 4.0, seed=3, friction=False, bias=False, noise_sd=0.0,
                     velocity_noise_sd=0.0, payload_kg=m)
    # the residual after the URDF's rigid body is exactly the payload's torque
    np.testing.assert_allclose(d['effort'] - d['tau_rb_urdf'], d['payload'], atol=1e-9)
    # its gravity part is the gradient of m g z(q) (z: height of the payload), by central
    # differences of pinocchio's forward kinematics: a conservative torque
    import pinocchio as pin
    dyn = payload_inverse_dynamics(example_robot_urdf(robot), ARM_JOINTS[robot], 'x', 0.0)
    frame, offset = PAYLOAD_MOUNT[robot]
    fid = dyn.model.getFrameId(frame)

    def height(q):
        pin.framesForwardKinematics(dyn.model, dyn.data, dyn._config(q))
        return float((dyn.data.oMf[fid] * np.asarray(offset))[2])

    h = 1e-6
    for i in range(0, 4000, 500):
        q = d['q'][i]
        grad = np.array([(height(q + h * e) - height(q - h * e)) / (2 * h)
                         for e in np.eye(len(q))])
        np.testing.assert_allclose(d['payload_gravity'][i], m * G * grad, atol=1e-5)
    # pose-dependent (not an offset the bias could take) and larger than the inertial part
    g = d['payload_gravity']
    assert g.std(axis=0).max() > 0.2          # m = 0.5 kg, 4 s: 0.47 N m measured
    assert np.abs(d['payload'] - g).mean() < np.abs(g).mean()


def test_defaults_are_unchanged():
    d = simulate_arm('panda', 1.0, seed=0)
    assert d['friction_model'] == 'table' and d['payload_kg'] == 0.0
    np.testing.assert_array_equal(d['friction'], friction_truth('panda', d['qd_true']))
    np.testing.assert_array_equal(d['tau_rb'], d['tau_rb_urdf'])
    assert not d['payload'].any() and not d['payload_gravity'].any()
    np.testing.assert_array_equal(d['bias'], FRICTION_TABLES['panda'][:, 4])
    same = simulate_arm('panda', 1.0, seed=0, friction='table')
    np.testing.assert_array_equal(same['effort'], d['effort'])


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match='friction'):
        simulate_arm('panda', 0.1, friction='lugre')
    with pytest.raises(ValueError, match='qd'):
        realistic_friction('panda', np.zeros(6))
    with pytest.raises(ValueError, match='robot'):
        realistic_friction('kuka', np.zeros(7))
    with pytest.raises(ValueError, match='mass'):
        payload_inverse_dynamics(example_robot_urdf('panda'), ARM_JOINTS['panda'],
                                 'panda_hand_tcp', -1.0)
    with pytest.raises(ValueError, match='frame'):
        payload_inverse_dynamics(example_robot_urdf('panda'), ARM_JOINTS['panda'], 'nowhere',
                                 1.0)

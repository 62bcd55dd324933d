"""
The robot front end through the online estimator: raw joint torques in, friction learned.

Simulated Panda (dgp_ros.dynamics.simulate_arm): effort = rigid-body torque + friction + bias +
noise at 1 kHz with jittered stamps. With ``inverse_dynamics='urdf'`` the estimator learns the
residual, delayed by the filter's half window; without it, on raw torques, it warns.
"""
import numpy as np
import pytest

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, friction_truth, simulate_arm
from dgp_ros.gp import model_class
from dgp_ros.online import EstimatorConfig, OnlineEstimator, WARN

NAMES = list(ARM_JOINTS['panda'])


def _factory(kind, **kw):
    kw.update(n_restarts=0, max_opt_samples=120)     # keep the 7-joint fits quick in CI
    return model_class(kind)(**kw)


def _cfg(**kw):
    base = {'model': 'diag', 'passivity': 'projected', 'prior': 'friction', 'bias': True,
            'buffer_size': 150, 'min_samples': 60, 'refit_period_s': 0.0, 'selection': 'all',
            'refit_mode': 'sync', 'inverse_dynamics': 'urdf',
            'urdf_file': example_robot_urdf('panda'),
            'joints': NAMES}
    base.update(kw)
    return EstimatorConfig(**base)


@pytest.fixture(scope='module')
def sim():
    return simulate_arm('panda', duration_s=10.0, seed=1)      # one period of the excitation


def _feed(est, d, every=1):
    out = []
    for i in range(0, len(d['t']), every):
        out.append(est.process(d['t'][i], NAMES, d['qd'][i], d['effort'][i], d['q'][i]))
    return out


def test_urdf_residual_is_learned_delayed_and_the_answers_are_immediate(sim):
    est = OnlineEstimator(_cfg(), model_factory=_factory)
    out = _feed(est, sim)
    assert all(e is not None for e in out)
    # every answer is at the message's own velocity, at once
    assert all(np.array_equal(e.qd, q) for e, q in zip(out[:50], sim['qd'][:50]))
    res = [r for e in out for r in e.residuals]
    assert 900 <= len(res) <= 1000                   # ~100 Hz learning for 10 s
    # each residual answers a past sample: delayed by the half window, paired with its own qd
    lag = np.array([e.stamp_s - r.stamp_s for e in out for r in e.residuals])
    h = EstimatorConfig().accel_half_window_s           # the filter's half window
    assert np.all((lag >= h - 1e-9) & (lag < h + 0.005)), (lag.min(), lag.max())
    idx = np.searchsorted(sim['t'], [r.stamp_s for r in res])
    assert np.array_equal(np.array([r.qd for r in res]), sim['qd'][idx])
    # the residual is friction + bias + noise (0.3 Nm): the rigid-body torque is gone
    target = sim['friction'][idx] + sim['bias']
    err = np.array([r.residual for r in res]) - target
    assert np.sqrt(np.mean(err ** 2)) < 0.45
    raw = np.array([r.effort for r in res]) - target
    assert np.sqrt(np.mean(raw ** 2)) > 5.0          # what the effort alone would have taught
    d = est.diagnostics()
    assert est.trained and d['residual_delay_s'] == h
    assert 'not damping' not in d['message']
    assert d['negative_power_fraction'] < 0.1
    # the learned friction, held out: velocities of the trajectory it has not seen yet
    later = simulate_arm('panda', duration_s=16.0, seed=1)
    Qs = later['qd'][10500::20]
    truth = friction_truth('panda', Qs)
    pred = est.predict(Qs)
    nmse = np.mean((pred - truth) ** 2, axis=0) / np.var(truth, axis=0)
    assert np.all(np.einsum('ij,ij->i', Qs, pred) >= 0)
    assert np.median(nmse) < 0.5, nmse
    np.testing.assert_allclose(est.model.bias_, sim['bias'], atol=0.25)


def test_raw_torques_without_inverse_dynamics_warn_with_the_reason(sim):
    est = OnlineEstimator(_cfg(inverse_dynamics='', urdf_file='', min_samples=150),
                          model_factory=_factory)
    _feed(est, sim, every=2)
    d = est.diagnostics()
    assert d['negative_power_fraction'] > 0.2
    assert d['level'] >= WARN and 'data are not damping' in d['message']
    assert 'inverse_dynamics' in d['message']


def test_positions_are_required_with_inverse_dynamics(sim):
    est = OnlineEstimator(_cfg(), model_factory=_factory)
    assert est.process(0.0, NAMES, sim['qd'][0], sim['effort'][0]) is None
    assert est.process(0.0, NAMES, sim['qd'][0], sim['effort'][0], [0.0] * 3) is None
    d = est.diagnostics()
    assert d['rejected']['missing_position'] == 1 and d['rejected']['length_mismatch'] == 1


def test_python_plugin_and_bad_specs(tmp_path, monkeypatch, sim):
    (tmp_path / 'my_robot_dyn.py').write_text(
        'import numpy as np\n'
        'from dgp_ros.dynamics import UrdfInverseDynamics, example_robot_urdf\n'
        '_D = UrdfInverseDynamics(urdf_file=example_robot_urdf("panda"),\n'
        '                         joints=["panda_joint%d" % i for i in range(1, 8)])\n'
        'def tau_rb(q, qd, qdd):\n'
        '    return _D(q, qd, qdd)\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    est = OnlineEstimator(_cfg(inverse_dynamics='python:my_robot_dyn:tau_rb', urdf_file='',
                               min_samples=150), model_factory=_factory)
    out = _feed(est, sim, every=5)
    res = [r for e in out for r in e.residuals]
    assert res and np.allclose([r.residual for r in res], [r.effort - r.tau_rb for r in res])
    assert np.abs(np.array([r.tau_rb for r in res])).max() > 1.0       # the plugin's torque
    with pytest.raises(ValueError, match='python:<module>:<function>'):
        EstimatorConfig(inverse_dynamics='python:only_module').validate()
    # urdf without a URDF is valid: the node takes it from /robot_description; until then the
    # learner learns nothing and says so
    cfg = EstimatorConfig(inverse_dynamics='urdf').validate()
    assert cfg.awaits_urdf and not EstimatorConfig(inverse_dynamics='').awaits_urdf
    with pytest.raises(ValueError, match='no such file'):
        EstimatorConfig(inverse_dynamics='urdf', urdf_file='/nonexistent.urdf').validate()
    with pytest.raises(ValueError):
        OnlineEstimator(_cfg(urdf_file='', robot_description='<robot name="x"><bad'))
    with pytest.raises(ValueError, match='nope'):
        OnlineEstimator(_cfg(joints=NAMES[:-1] + ['nope']))

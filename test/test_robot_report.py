"""
The robot demo's evaluation (dgp_ros/apps/robot_report.py) on a small run, without DDS.

A listener record is made up (every measurement answered 2 ms later by a passive model); the
saved model is a small Full-D-GP. Checks the numbers and the figures, and that a model with
``predict_residual`` is scored against friction + payload gravity + bias.
"""
import json

import numpy as np
import pytest

pytest.importorskip('pinocchio')
pytest.importorskip('rclpy')


class _Lis:
    """What robot_demo.Listener records: arrival times [s] by stamp [ns], raw answers."""

    def __init__(self, stamps, qd, tau):
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import JointState
        self.meas, self.ans = {}, {}
        for i, t in enumerate(stamps):
            ns = int(round(t * 1e9))
            m = JointState()
            m.header.stamp.sec, m.header.stamp.nanosec = ns // 10 ** 9, ns % 10 ** 9
            m.velocity, m.effort = qd[i].tolist(), tau[i].tolist()
            self.meas[ns] = 100.0 + t
            self.ans[ns] = (100.0 + t + 0.002, serialize_message(m))


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    from dgp_ros.dynamics import example_robot_urdf
    from dgp_ros.dynamics.arm_stream import demo_arm
    from dgp_ros.gp import FullDGP
    from dgp_ros.apps import robot_report
    d = demo_arm('panda', 4.0, seed=2, base_hz=0.25)
    k = int(np.searchsorted(d['t'], 2.4))
    model = FullDGP(prior='friction')
    idx = np.arange(0, k, 40)
    model.fit(d['qd'][idx], d['friction'][idx])
    path = str(tmp_path_factory.mktemp('report') / 'm.npz')
    model.save(path)
    sel = np.arange(0, k, 20)
    lis = _Lis(d['t'][sel], d['qd'][sel], model.predict(d['qd'][sel]))
    return d, path, lis, example_robot_urdf('panda'), robot_report


def test_evaluate_scores_the_model_and_the_baselines_and_plots(run, tmp_path, monkeypatch):
    d, path, lis, urdf, rr = run
    monkeypatch.setattr(rr, 'N_RANDOM', 4000)
    res = rr.evaluate(d, 2.4, path, lis, published=2400, urdf=urdf)
    names = list(d['names'])
    for key in ('nmse', 'nmse_sigmoid', 'nmse_coulomb_viscous'):
        assert sorted(res[key]) == sorted(names)
        assert all(np.isfinite(v) for v in res[key].values())
    # a model fitted on the true friction of the same cycle beats a wrong one by far
    assert np.median(list(res['nmse'].values())) < 0.5
    # every model has predict_residual now (without a learned correction it is predict)
    assert res['has_predict_residual']
    assert all(np.isfinite(v) for v in res['nmse_residual'].values())
    assert res['answers'] == res['paired'] == 120 and res['answered_fraction'] == 120 / 2400
    assert res['latency_ms']['median'] == pytest.approx(2.0, abs=1e-3)
    assert res['answers_negative_power_beyond_roundoff'] == 0
    assert res['random_velocities'] == 4000 and res['random_negative_power_beyond_roundoff'] == 0
    res['wall_time_s'] = 1.0
    files = rr.plot(res, d, str(tmp_path))
    assert len(files) == 5 and all((tmp_path / f.split('/')[-1]).stat().st_size > 0
                                   for f in files)
    assert any(f.endswith('friction_curves.png') for f in files)
    rr.print_summary(res)
    json.dumps(rr.jsonable(res), default=str)
    rr.save_stream(res, str(tmp_path / 'a.npz'))
    assert np.load(tmp_path / 'a.npz')['qd'].shape == (120, 7)


def test_a_model_with_predict_residual_is_scored_against_the_whole_residual(run, monkeypatch):
    d, path, lis, urdf, rr = run
    import dgp_ros.gp
    real = dgp_ros.gp.load_model(path)
    k = int(np.searchsorted(d['t'], 2.4))
    g_by_q = {tuple(q): g for q, g in zip(d['q'][k:], d['payload_gravity'][k:])}

    class WithResidual:
        def predict(self, Qd):
            return real.predict(Qd)

        def predict_residual(self, q, qd):        # an oracle of friction + gravity + bias
            g = np.array([g_by_q[tuple(r)] for r in q])
            return real.predict(qd) + g + d['bias']

    monkeypatch.setattr(dgp_ros.gp, 'load_model', lambda p: WithResidual())
    monkeypatch.setattr(rr, 'N_RANDOM', 2000)
    res = rr.evaluate(d, 2.4, path, lis, published=2400, urdf=urdf)
    assert res['has_predict_residual']
    A = res['_arrays']
    np.testing.assert_allclose(A['rtruth'] - A['Fh'],
                               d['payload_gravity'][k::10] + d['bias'], atol=1e-12)
    # the oracle's residual error is its friction error, so the two NMSEs are close
    for n in d['names']:
        assert res['nmse_residual'][n] < 1.5 * res['nmse'][n] + 0.05, n

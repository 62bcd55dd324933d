"""In-process tests of the dgp_estimator node: a context per test, always shut down."""
import dataclasses
import os
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402,I100
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64, Float64MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from dgp_ros.nodes.estimator import EstimatorNode  # noqa: E402
from dgp_ros.nodes.executor import WaitSetExecutor  # noqa: E402
from dgp_ros.nodes.runtime import _executor  # noqa: E402
from dgp_ros.online import EstimatorConfig  # noqa: E402

pytestmark = pytest.mark.ros
NAMES = ['alpha', 'beta', 'airspeed']
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def true_tau(q):
    D = np.diag([2.0 + np.sin(q[0]), 1.0 + 0.5 * q[1] ** 2, 0.5 + 0.1 * abs(q[2])])
    D[0, 1] = D[1, 0] = 0.3 * np.cos(q[2])
    return D @ q


def traj(t):
    return np.array([np.sin(0.7 * t), 0.8 * np.cos(0.31 * t), 2.0 + np.sin(0.13 * t)])


def state_msg(t, q, tau, names=NAMES):
    m = JointState()
    m.header.stamp.sec = int(t)
    m.header.stamp.nanosec = int(round((t - int(t)) * 1e9))
    m.name = list(names)
    m.velocity = [float(v) for v in q]
    m.effort = [float(v) for v in tau]
    return m


FAST = [Parameter('buffer_size', value=40), Parameter('min_samples', value=10),
        Parameter('refit_period_s', value=0.0), Parameter('selection', value='all'),
        Parameter('diagnostics_period_s', value=0.2),
        Parameter('prior', value='viscous'), Parameter('bias', value=False)]   # a viscous law


class Rig:
    """A context, an executor, the estimator node and a helper node (publisher/recorder)."""

    def __init__(self, overrides=()):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.nodes = []
        # the node's own executor (DGP_EXECUTOR, default the wait-set loop)
        self.ex = _executor(self.ctx)
        self.est = None
        self.helper = rclpy.create_node('helper', context=self.ctx)
        self._add(self.helper)
        self.got = {k: [] for k in ('force', 'std', 'D', 'power', 'diag', 'conf')}
        h = self.helper
        h.create_subscription(JointState, '/dgp_estimator/damping_force',
                              lambda m: self.got['force'].append(m), 100)
        h.create_subscription(JointState, '/dgp_estimator/damping_force_confidence',
                              lambda m: self.got['conf'].append(m), 100)
        h.create_subscription(JointState, '/dgp_estimator/damping_force_stddev',
                              lambda m: self.got['std'].append(m), 100)
        h.create_subscription(Float64MultiArray, '/dgp_estimator/damping_matrix',
                              lambda m: self.got['D'].append(m), 100)
        h.create_subscription(Float64, '/dgp_estimator/dissipated_power',
                              lambda m: self.got['power'].append(m), 100)
        h.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: self.got['diag'].append(m), 100)
        self.pub = h.create_publisher(JointState, 'generalized_state', 100)
        self.pub_be = h.create_publisher(
            JointState, 'generalized_state',
            QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
        if overrides is not None:
            self.start_estimator(overrides)

    def _add(self, node):
        self.nodes.append(node)
        self.ex.add_node(node)

    def start_estimator(self, overrides):
        self.est = EstimatorNode(context=self.ctx, parameter_overrides=list(overrides))
        self._add(self.est)
        self.spin_until(lambda: self.pub.get_subscription_count() >= 1, 10)
        return self.est

    def stop_estimator(self):
        self.est.shutdown()
        self.ex.remove_node(self.est)
        self.nodes.remove(self.est)
        self.est.destroy_node()
        self.est = None

    def spin_until(self, cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            self.ex.spin_once(timeout_sec=0.05)
        return cond()

    def call(self, name, timeout=30.0):
        cli = self.helper.create_client(Trigger, name)
        assert self.spin_until(lambda: cli.service_is_ready(), 10), name
        fut = cli.call_async(Trigger.Request())
        assert self.spin_until(fut.done, timeout), name
        self.helper.destroy_client(cli)
        return fut.result()

    def close(self):
        try:
            if self.est is not None:
                self.est.estimator.close(timeout=30)
            for n in self.nodes:
                self.ex.remove_node(n)
                n.destroy_node()
            self.ex.shutdown()
        finally:
            self.ctx.try_shutdown()


@pytest.fixture
def rig():
    r = Rig(overrides=None)
    try:
        yield r
    finally:
        r.close()


def feed(rig, n, t0=0.0, dt=0.1, pub=None, noise=0.01, seed=0, wait=True, pace=0.0):
    """Publish n samples of the trajectory (``pace``: wall seconds between them, at least)."""
    rng = np.random.default_rng(seed)
    pub = pub or rig.pub
    for i in range(n):
        t = t0 + i * dt
        q = traj(t)
        t_pub = time.monotonic()
        pub.publish(state_msg(t, q, true_tau(q) + rng.normal(0, noise, 3)))
        k = len(rig.got['force'])
        if wait:
            rig.spin_until(lambda: len(rig.got['force']) > k, 5)
        if pace:
            rig.spin_until(lambda: time.monotonic() - t_pub >= pace, pace + 1.0)


def test_every_topic_publishes_and_estimate_converges(rig):
    est = rig.start_estimator(FAST)
    feed(rig, 12)                                  # reliable publisher
    assert est.estimator.wait_for_refit(120)
    # best-effort publisher matches too; enough samples for the model to earn its full weight
    # over the fallback one step ahead (grounds: the early models' errors count for 100 more)
    feed(rig, 200, t0=1.2, pub=rig.pub_be)
    assert est.estimator.wait_for_refit(120)       # the learner has caught up
    # answered before they are learned (from the learner's last snapshot): a stream slow
    # enough for the learner to keep up (10 ms of stamp time in 20 ms of wall time)
    feed(rig, 30, t0=21.2, pub=rig.pub_be, pace=0.02)
    assert rig.spin_until(lambda: len(rig.got['diag']) >= 2, 10)

    def certified():
        st = rig.got['diag'][-1].status[0]
        return {kv.key: kv.value for kv in st.values}.get('certified') == 'True'
    # the stream has paused: the learner re-proves the certificate that the last samples left
    # stale (3 velocities, a proof on the data's domain)
    assert rig.spin_until(certified, 30)
    g = rig.got
    assert len(g['force']) >= 230 and len(g['std']) >= 230 and len(g['power']) >= 230
    assert len(g['D']) >= 230
    # the confidence comes with the force: one per answer, same stamp, in [0, 1], earned
    assert len(g['conf']) >= 230
    stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in g['force']}
    for m in g['conf'][-30:]:
        assert (m.header.stamp.sec, m.header.stamp.nanosec) in stamps
        assert all(0.0 <= c <= 1.0 for c in m.effort) and len(m.effort) == 3
    assert min(g['conf'][-1].effort) > 0.5
    f = g['force'][-1]
    assert list(f.name) == NAMES
    # each answer pairs with its measurement: same stamp, velocity it was evaluated at
    for m in g['force'][-20:]:
        t = m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
        np.testing.assert_allclose(m.velocity, traj(t), rtol=1e-9, atol=1e-9)
    tau_hat = np.array(f.effort)
    qf = np.array(f.velocity)
    truth = true_tau(qf)
    # the model has converged; what is published is blended toward the fallback by the weight
    # the model earned one step ahead (under load the learner lags and earns it later), so it
    # is passive and no farther from the truth than no answer at all
    model = est.estimator._learner.snapshot().model
    np.testing.assert_allclose(model.predict(qf[None])[0], truth, atol=0.1)
    assert qf @ tau_hat >= 0.0
    assert np.linalg.norm(tau_hat - truth) <= np.linalg.norm(truth), (tau_hat, truth)
    # damping matrix: layout and D qd = tau_hat
    D = g['D'][-1]
    assert [d.label for d in D.layout.dim] == ['rows', 'cols']
    assert [d.size for d in D.layout.dim] == [3, 3]
    assert [d.stride for d in D.layout.dim] == [9, 3]
    # (a matrix has no stamp: pair it with one of the last answers)
    Dm = np.array(D.data).reshape(3, 3)
    assert any(np.allclose(Dm @ np.array(m.velocity), np.array(m.effort), rtol=1e-6, atol=1e-9)
               for m in g['force'][-5:])
    assert any(g['power'][-1].data == pytest.approx(float(np.dot(m.velocity, m.effort)))
               for m in g['force'][-5:])
    assert all(p.data >= 0 for p in g['power'])
    assert all(np.all(np.array(s.effort) >= 0) for s in g['std'])
    # the estimate converged: errors one step ahead are small against the force (the blend
    # toward the fallback recovers over ~100 samples after a model that answered badly)
    last = [(np.array(m.effort), true_tau(np.array(m.velocity))) for m in g['force'][-30:]]
    errs = np.array([e - t for e, t in last])
    size = np.array([t for _, t in last])
    assert np.sqrt(np.mean(np.square(errs))) < 0.25 * np.sqrt(np.mean(np.square(size)))
    st = g['diag'][-1].status[0]
    vals = {kv.key: kv.value for kv in st.values}
    # OK; on a loaded machine (two suites at once) the one warning may be that the learner is
    # short of CPU, which it then is: the status says so, with the measured ratio
    # what holds is said at every level ('every answer passive; the model proven passive on
    # ...'); beside it, only a starved learner may warn
    starved = [w for w in st.message.split('; ') if not w.startswith(
        ('the learner is short', 'every answer passive', 'the model proven passive',
         'the model last proven passive', 'the model not proven passive'))]
    assert st.level == b'\x00' or (st.level == b'\x01' and not starved), st.message
    assert vals['trained'] == 'True' and vals['certified'] == 'True'
    assert int(vals['buffer_fill']) == 40 and 'rejected/non_finite' in vals
    assert float(vals['refits_ok']) >= 1


def test_bad_messages_rejected_and_reported(rig):
    rig.start_estimator(FAST)
    feed(rig, 1)                                   # the first good message fixes N = 3
    rig.pub.publish(state_msg(0.0, [0.1, float('nan'), 1.0], [1, 1, 1]))
    rig.pub.publish(state_msg(0.1, [0.1, 0.2], [1, 1], names=NAMES[:2]))
    rig.pub.publish(state_msg(0.2, [0.1, 0.2, 1.0], [1, 1, 1], names=['a', 'a', 'b']))
    assert rig.spin_until(lambda: any(
        kv.key == 'rejected_total' and kv.value == '3'
        for m in rig.got['diag'] for kv in m.status[0].values), 10)
    st = rig.got['diag'][-1].status[0]
    assert st.level == b'\x01' and 'many rejected samples' in st.message
    assert len(rig.got['force']) == 1


def test_bytes_the_codec_cannot_read_are_answered_by_rclpy_or_rejected(rig):
    """The raw path: garbage is rejected (``undecodable``), big-endian CDR answered by rclpy."""
    from rclpy.serialization import serialize_message
    est = rig.start_estimator(FAST)
    feed(rig, 3)
    good = serialize_message(state_msg(0.5, traj(0.5), true_tau(traj(0.5))))
    big = _big_endian(state_msg(0.6, traj(0.6), true_tau(traj(0.6))))
    for raw in (b'\x00\x01\x00\x00' + b'\xff' * 9, good[:30], big, b'', good):
        rig.pub.publish(raw)
    rig.spin_until(lambda: len(rig.got['force']) >= 5, 10)
    h = est.estimator.health
    assert rig.spin_until(lambda: h.messages_received >= 8, 10)
    stamps = sorted(m.header.stamp.nanosec for m in rig.got['force'][3:])
    assert stamps == [500_000_000, 600_000_000]            # the good one and the big-endian one
    assert h.rejected['undecodable'] >= 2 and est.path.fallback >= 3
    f = [m for m in rig.got['force'] if m.header.stamp.nanosec == 600_000_000][0]
    np.testing.assert_array_equal(f.velocity, traj(0.6))


def _big_endian(m) -> bytes:
    """``m`` as big-endian CDR (what a big-endian host sends; rclpy reads it, the codec not)."""
    import struct
    out = bytearray(b'\x00\x00\x00\x00')

    def align(n):
        out.extend(b'\x00' * (-(len(out) - 4) % n))

    def string(s):
        b = s.encode() + b'\x00'
        align(4)
        out.extend(struct.pack('>I', len(b)) + b)
    align(4)
    out.extend(struct.pack('>iI', m.header.stamp.sec, m.header.stamp.nanosec))
    string(m.header.frame_id)
    align(4)
    out.extend(struct.pack('>I', len(m.name)))
    for n in m.name:
        string(n)
    for arr in (m.position, m.velocity, m.effort):
        align(4)
        out.extend(struct.pack('>I', len(arr)))
        if len(arr):
            align(8)
            out.extend(struct.pack(f'>{len(arr)}d', *arr))
    return bytes(out)


def test_refit_is_answered_while_the_learner_is_busy(rig):
    """A learner that does not reply in ``REFIT_REPLY_S``: ~/refit says the request is queued."""
    est = rig.start_estimator(FAST)
    if not isinstance(est.executor, WaitSetExecutor):
        pytest.skip('rclpy executors answer ~/refit in line (DGP_EXECUTOR)')
    asked = []
    est.estimator.request_refit_async = asked.append      # a learner that never replies
    r = rig.call('/dgp_estimator/refit', timeout=10.0)
    assert r.success and 'busy' in r.message and len(asked) == 1, r.message
    asked[0]((False, 'late reply'))                        # ignored: already answered
    r = rig.call('/dgp_estimator/refit', timeout=10.0)
    assert r.success and 'busy' in r.message and len(asked) == 2, r.message


def test_services(rig, tmp_path, monkeypatch):
    # the learner's own replies (a loaded machine may take longer than REFIT_REPLY_S)
    monkeypatch.setattr(EstimatorNode, 'REFIT_REPLY_S', 30.0)
    path = str(tmp_path / 'model.npz')
    est = rig.start_estimator(FAST)
    r = rig.call('/dgp_estimator/refit')
    assert not r.success and 'not enough samples' in r.message
    r = rig.call('/dgp_estimator/save_model')
    assert not r.success and 'model_path' in r.message
    feed(rig, 12)
    assert est.estimator.wait_for_refit(120)
    r = rig.call('/dgp_estimator/refit')
    assert r.success, r.message
    assert est.estimator.wait_for_refit(120)
    assert est.estimator.diagnostics()['refits_ok'] == 2
    res = est.set_parameters([Parameter('model_path', value=path)])
    assert res[0].successful, res[0].reason
    r = rig.call('/dgp_estimator/save_model')
    assert r.success and os.path.exists(path), r.message
    r = rig.call('/dgp_estimator/reset')
    assert r.success
    assert est.estimator.diagnostics()['buffer_fill'] == 0 and not est.estimator.trained


def test_save_and_reset_run_beside_the_message_path(rig):
    """A save (or reset) that waits for the learner: messages are answered meanwhile (issue 33)."""
    import threading
    est = rig.start_estimator(FAST)
    if not isinstance(est.executor, WaitSetExecutor):
        pytest.skip('rclpy executors run the services in line (DGP_EXECUTOR)')
    gate, entered = threading.Event(), threading.Event()

    def slow_save(path=None):
        entered.set()
        assert gate.wait(30)
        return '/tmp/saved.npz'
    est.estimator.save = slow_save
    cli = rig.helper.create_client(Trigger, '/dgp_estimator/save_model')
    assert rig.spin_until(cli.service_is_ready, 10)
    fut = cli.call_async(Trigger.Request())
    assert rig.spin_until(entered.is_set, 10)
    n = len(rig.got['force'])
    feed(rig, 5)                                  # answered while the save is running
    assert len(rig.got['force']) >= n + 5 and not fut.done()
    gate.set()
    assert rig.spin_until(fut.done, 10)
    assert fut.result().success and fut.result().message == 'saved to /tmp/saved.npz'
    est.estimator.save = lambda path=None: (_ for _ in ()).throw(OSError('disk full'))
    fut = cli.call_async(Trigger.Request())
    assert rig.spin_until(fut.done, 10)
    assert not fut.result().success and 'disk full' in fut.result().message
    r = rig.call('/dgp_estimator/reset')
    assert r.success and est.estimator.diagnostics()['buffer_fill'] == 0


def test_invalid_parameters_rejected_with_reason(rig):
    est = rig.start_estimator(FAST)
    cases = [('model', 'gpytorch', 'model'), ('passivity', 'maybe', 'passivity'),
             ('min_samples', 500, 'buffer_size'), ('buffer_size', 1, 'buffer_size'),
             ('selection_min_distance', -1.0, 'selection_min_distance'),
             ('joints', ['a', 'a'], 'unique'), ('diagnostics_period_s', 0.0, 'diagnostics'),
             ('refit_mode', 'later', 'refit_mode')]
    for name, value, word in cases:
        res = est.set_parameters([Parameter(name, value=value)])
        assert not res[0].successful, name
        assert word in res[0].reason, (name, res[0].reason)
    # wrong type: refused by rclpy (static typing)
    res = est.set_parameters([Parameter('buffer_size', value='big')])
    assert not res[0].successful
    # a valid change is applied to the estimator
    res = est.set_parameters([Parameter('selection', value='novelty'),
                              Parameter('selection_min_distance', value=0.2)])
    assert all(r.successful for r in res)
    assert est.estimator.config.selection == 'novelty'
    assert est.estimator.config.selection_min_distance == 0.2
    res = est.set_parameters([Parameter('joints', value=['beta', 'alpha'])])
    assert res[0].successful and est.estimator.config.joints == ['beta', 'alpha']


def test_invalid_start_parameters_raise(rig):
    with pytest.raises(ValueError, match='min_samples'):
        rig.start_estimator(FAST + [Parameter('min_samples', value=100)])


def test_save_and_restart_gives_identical_estimates(rig, tmp_path):
    path = str(tmp_path / 'model.npz')
    est = rig.start_estimator(FAST + [Parameter('model_path', value=path)])
    feed(rig, 25)
    assert est.estimator.wait_for_refit(120) and est.estimator.trained
    rng = np.random.default_rng(2)
    Qs = rng.uniform(-2, 2, (100, 3))
    before = est.estimator.predict(Qs)
    rig.stop_estimator()                           # saves on shutdown
    assert os.path.exists(path)
    est2 = rig.start_estimator(FAST + [Parameter('model_path', value=path)])
    assert est2.estimator.trained and not est2.estimator.load_error
    np.testing.assert_array_equal(est2.estimator.predict(Qs), before)
    # and the restarted node answers at once with the model, not the prior
    rig.got['force'].clear()
    feed(rig, 1, t0=50.0)
    assert rig.got['force'] and est2.estimator.diagnostics()['last_source'] == 'model'


def test_yaml_defaults_match_config():
    """config/estimator.yaml is generated from the parameter table, and parses to its defaults."""
    from dgp_ros.online.config import NODE_PARAMS, defaults_yaml
    yaml = pytest.importorskip('yaml')
    with open(os.path.join(REPO, 'config', 'estimator.yaml')) as f:
        text = f.read()
    assert text == defaults_yaml(), 'regenerate config/estimator.yaml (see its header)'
    params = yaml.safe_load(text)['dgp_estimator']['ros__parameters']
    defaults = dict(dataclasses.asdict(EstimatorConfig()),
                    **{k: p.default for k, p in NODE_PARAMS.items()})
    for k, v in params.items():
        assert v == defaults[k], (k, v, defaults[k])
    assert set(defaults) - set(params) == {'joints', 'selection_scale', 'effort_scale',
                                           'operating_domain'}

"""
What a peer sends never ends the node (issue 67's attacks, each of which ended it before).

The node as the README starts it on an arm (``inverse_dynamics=urdf``, ``joints``, the learner
in its own process), with listeners on ``~/friction_residual`` and ``~/rigid_body_correction``:

* a JointState whose ``header.frame_id`` (or a joint name) is not UTF-8 is dropped and counted
  (``bad_text``), and the stream goes on being answered;
* ``joints`` set at run time to another number of joints is refused with the reason (twice),
  and every message after it is still answered.
"""
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.executors import SingleThreadedExecutor  # noqa: E402,I100
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, simulate_arm  # noqa: E402
from dgp_ros.nodes.estimator import EstimatorNode  # noqa: E402

pytestmark = pytest.mark.ros
NAMES = list(ARM_JOINTS['panda'])


class Rig:
    def __init__(self):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.helper = rclpy.create_node('attack_helper', context=self.ctx)
        self.ex.add_node(self.helper)
        self.got = {'force': [], 'residual': [], 'corr': []}
        for key, topic in (('force', 'damping_force'), ('residual', 'friction_residual'),
                           ('corr', 'rigid_body_correction')):
            self.helper.create_subscription(JointState, f'/dgp_estimator/{topic}',
                                            self.got[key].append, 1000)
        self.pub = self.helper.create_publisher(JointState, '/generalized_state', 1000)
        self.est = EstimatorNode(context=self.ctx, parameter_overrides=[
            Parameter('inverse_dynamics', value='urdf'),
            Parameter('urdf_file', value=example_robot_urdf('panda')),
            Parameter('joints', value=NAMES), Parameter('min_samples', value=20)])
        self.ex.add_node(self.est)
        self.spin_until(lambda: self.pub.get_subscription_count() >= 1, 10)

    def spin_until(self, cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            self.ex.spin_once(timeout_sec=0.05)
        return cond()

    def message(self, d, i, frame='base'):
        m = JointState()
        m.header.stamp.sec, m.header.stamp.nanosec = int(d['t'][i]), \
            int(round((d['t'][i] % 1) * 1e9)) % 1_000_000_000
        m.header.frame_id = frame
        m.name = NAMES
        m.position, m.velocity, m.effort = (d['q'][i].tolist(), d['qd'][i].tolist(),
                                            d['effort'][i].tolist())
        return m

    def feed(self, d, start, n):
        k = len(self.got['force'])
        for i in range(start, start + n):
            self.pub.publish(self.message(d, i))
            if i % 20 == 0:
                self.ex.spin_once(timeout_sec=0.0)
        return self.spin_until(lambda: len(self.got['force']) >= k + n, 30)

    def close(self):
        try:
            self.est.shutdown()
            self.est.estimator.close(timeout=30)
            for n in (self.est, self.helper):
                self.ex.remove_node(n)
                n.destroy_node()
            self.ex.shutdown()
        finally:
            self.ctx.try_shutdown()


@pytest.fixture
def rig():
    r = Rig()
    try:
        yield r
    finally:
        r.close()


@pytest.fixture(scope='module')
def arm():
    return simulate_arm('panda', 3.5, seed=11)


def _not_utf8(msg, text: str) -> bytes:
    """``msg`` serialized with the first byte of ``text`` (in a string field) made 0xff."""
    raw = bytearray(serialize_message(msg))
    i = raw.find(text.encode())
    assert i > 0
    raw[i] = 0xff
    return bytes(raw)


def test_a_string_that_is_not_utf8_is_dropped_and_counted(rig, arm):
    # until the residuals (and corrections) flow: the paths that decode the frame_id again
    for start in range(0, 2400, 400):
        assert rig.feed(arm, start, 400)
        if rig.got['residual']:
            break
    assert rig.got['residual'], 'no friction residual published'
    h = rig.est.estimator.health
    i = start + 400
    rig.pub.publish(_not_utf8(rig.message(arm, i, frame='base_link'), 'base_link'))
    rig.pub.publish(_not_utf8(rig.message(arm, i + 1), 'panda_joint3'))
    assert rig.spin_until(lambda: h.rejected['bad_text'] >= 2, 10), h.rejected
    assert rig.feed(arm, i + 2, 300)               # the node lives and answers on
    assert rig.est.estimator.diagnostics()['rejected_total'] >= 2


def test_joints_of_another_count_at_run_time_are_refused_with_the_reason(rig, arm):
    assert rig.feed(arm, 0, 300)
    for names in (NAMES[:5], NAMES + ['panda_finger_joint1', 'panda_finger_joint2', 'x']):
        r = rig.est.set_parameters([Parameter('joints', value=names)])[0]
        assert not r.successful and 'serves 7 joints' in r.reason, r.reason
    assert list(rig.est.get_parameter('joints').value) == NAMES
    assert rig.feed(arm, 300, 500)                 # every message after it answered
    f = np.array(rig.got['force'][-1].effort)
    assert f.shape == (7,) and np.all(np.isfinite(f))

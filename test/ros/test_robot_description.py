"""
The robot model from /robot_description (std_msgs/String, transient local), as ros2_control.

``inverse_dynamics=urdf`` with neither ``robot_description`` nor ``urdf_file``: the estimator
waits for the URDF on the topic (started before or after its publisher), says so on
/diagnostics, and learns once it has it; a malformed URDF is an ERROR with its reason, not a
crash, and a good one published later is taken.
"""
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402,I100
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, simulate_arm  # noqa: E402
from dgp_ros.nodes.estimator import EstimatorNode  # noqa: E402

pytestmark = pytest.mark.ros
NAMES = list(ARM_JOINTS['panda'])
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
PARAMS = [Parameter('inverse_dynamics', value='urdf'), Parameter('joints', value=NAMES),
          Parameter('model', value='diag'), Parameter('min_samples', value=20),
          Parameter('diagnostics_period_s', value=0.1)]


class Rig:
    """A context with a helper node (URDF publisher, joint states, diagnostics) and the node."""

    def __init__(self):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.helper = rclpy.create_node('urdf_helper', context=self.ctx)
        self.ex.add_node(self.helper)
        self.diag, self.answers = [], []
        self.helper.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda m: self.diag.extend(s for s in m.status if 'dgp_estimator' in s.name), 100)
        self.helper.create_subscription(JointState, '/dgp_estimator/damping_force',
                                        self.answers.append, 1000)
        self.urdf_pub = self.helper.create_publisher(String, '/robot_description', LATCHED)
        self.js_pub = self.helper.create_publisher(JointState, '/generalized_state', 100)
        self.est = None

    def start(self):
        self.est = EstimatorNode(context=self.ctx, parameter_overrides=list(PARAMS))
        self.ex.add_node(self.est)
        return self.est

    def spin_until(self, cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            self.ex.spin_once(timeout_sec=0.05)
        return cond()

    def last_status(self):
        return self.diag[-1] if self.diag else None

    def status_says(self, text):
        return lambda: self.last_status() is not None and text in self.last_status().message

    def feed(self, d, n, t0=0):
        for i in range(t0, t0 + n):
            m = JointState()
            m.header.stamp.sec, m.header.stamp.nanosec = int(d['t'][i]), \
                int(round((d['t'][i] % 1) * 1e9)) % 1_000_000_000
            m.name = NAMES
            m.position, m.velocity, m.effort = (d['q'][i].tolist(), d['qd'][i].tolist(),
                                                d['effort'][i].tolist())
            self.js_pub.publish(m)
            if i % 20 == 0:
                self.ex.spin_once(timeout_sec=0.0)

    def close(self):
        try:
            if self.est is not None:
                self.est.shutdown()
                self.ex.remove_node(self.est)
                self.est.destroy_node()
            self.ex.remove_node(self.helper)
            self.helper.destroy_node()
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
    return simulate_arm('panda', 3.0, seed=5)


def _urdf():
    with open(example_robot_urdf('panda')) as f:
        return f.read()


def test_urdf_published_after_the_estimator_started_is_taken(rig, arm):
    est = rig.start()
    assert rig.spin_until(rig.status_says('waiting for the robot model'), 20), \
        rig.last_status()
    rig.feed(arm, 200)                       # answered, not learned, until the model comes
    assert rig.spin_until(lambda: len(rig.answers) >= 150, 20)
    assert est.estimator.diagnostics()['samples_added'] == 0
    rig.urdf_pub.publish(String(data=_urdf()))
    assert rig.spin_until(lambda: est.estimator.config.robot_description != '', 20)
    rig.feed(arm, 1500, t0=200)
    assert rig.spin_until(lambda: est.estimator.diagnostics()['samples_added'] >= 20, 30)
    assert rig.spin_until(lambda: 'waiting for the robot model' not in
                          rig.last_status().message, 10), rig.last_status().message
    assert est.estimator.learner.joint_names() == NAMES


def test_urdf_published_before_the_estimator_started_is_taken(rig, arm):
    rig.urdf_pub.publish(String(data=_urdf()))       # latched: a late subscriber gets it
    est = rig.start()
    assert rig.spin_until(lambda: est.estimator.config.robot_description != '', 20)
    rig.feed(arm, 1500)
    assert rig.spin_until(lambda: est.estimator.diagnostics()['samples_added'] >= 20, 30)
    residual = np.array(est.estimator.samples()[1])
    assert residual.shape[1] == len(NAMES)
    # the rigid-body torque was subtracted: the learned targets are friction-sized, not gravity
    # (joints 2 and 4 hold about 22 N m of gravity; one sample may carry a filter transient)
    held = np.median(np.abs(np.asarray(arm['effort'])[:1500, [1, 3]]), axis=0)
    learned = np.median(np.abs(residual[:, [1, 3]]), axis=0)
    assert np.all(learned < 0.25 * held), (learned, held)


def test_malformed_urdf_is_an_error_on_diagnostics_not_a_crash(rig, arm):
    est = rig.start()
    rig.urdf_pub.publish(String(data='<robot name="broken"><link name="a"'))
    assert rig.spin_until(rig.status_says('URDF on /robot_description is not usable'), 20), \
        rig.last_status()
    assert rig.last_status().level == b'\x02'
    rig.feed(arm, 100)                               # still answering
    assert rig.spin_until(lambda: len(rig.answers) >= 80, 20)
    rig.urdf_pub.publish(String(data=_urdf()))       # a good one later is taken
    assert rig.spin_until(lambda: est.estimator.config.robot_description != '', 20)
    assert rig.spin_until(lambda: 'not usable' not in rig.last_status().message, 10)

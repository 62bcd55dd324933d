"""arm_sim node in-process: a driver's raw joint states, real-time pacing, the end, parameters."""
import math
import time

import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('pinocchio')
from rclpy.exceptions import ParameterException  # noqa: E402,I100
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from dgp_ros.nodes.arm_sim import ArmSimNode  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture
def ctx():
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        context.try_shutdown()


def _spin_until(executor, cond, timeout):
    t_end = time.monotonic() + timeout
    while not cond() and time.monotonic() < t_end:
        executor.spin_once(timeout_sec=0.02)


def test_streams_raw_panda_joint_states_at_real_time_after_its_subscriber(ctx):
    params = [Parameter('duration_s', value=2.0), Parameter('max_sim_time_s', value=1.0),
              Parameter('min_subscribers', value=1)]
    executor = SingleThreadedExecutor(context=ctx)
    nodes = []
    try:
        sim = ArmSimNode(context=ctx, parameter_overrides=params)
        nodes.append(sim)
        executor.add_node(sim)
        _spin_until(executor, lambda: False, 0.3)
        assert sim.published == 0                      # waits for its subscriber
        lis = rclpy.create_node('arm_listener', context=ctx)
        nodes.append(lis)
        got = []
        lis.create_subscription(JointState, 'joint_states',
                                lambda m, info: got.append((info['source_timestamp'], m)),
                                QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE))
        executor.add_node(lis)
        _spin_until(executor, lambda: sim.done, 30)
        _spin_until(executor, lambda: len(got) >= 1000, 5)
        assert sim.done and sim.published == 1000
        assert len(got) == 1000                        # reliable: every one
        m = got[-1][1]
        assert list(m.name) == [f'panda_joint{i}' for i in range(1, 8)] + [
            'panda_finger_joint1', 'panda_finger_joint2']
        assert len(m.position) == len(m.velocity) == len(m.effort) == 9
        assert all(math.isfinite(v) for v in list(m.effort))
        stamps = [g[1].header.stamp.sec + 1e-9 * g[1].header.stamp.nanosec for g in got]
        assert all(b > a for a, b in zip(stamps, stamps[1:])) and stamps[-1] < 1.0
        wall = (got[-1][0] - got[0][0]) * 1e-9       # when they were published [s]
        assert 0.8 < wall < 1.5, wall                  # 1 s of stamps in about 1 s
    finally:
        for n in nodes:
            executor.remove_node(n)
            n.destroy_node()
        executor.shutdown()


@pytest.mark.parametrize('name, value', [('robot', 'kuka'), ('duration_s', 0.1),
                                         ('friction', 'lugre'), ('payload_kg', -2.0)])
def test_invalid_parameters_are_refused(ctx, name, value):
    with pytest.raises((ValueError, ParameterException)):
        ArmSimNode(context=ctx, parameter_overrides=[Parameter(name, value=value)]).destroy_node()

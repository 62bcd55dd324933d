"""
The closed-loop nodes (#32): lock-step, and the estimator SIGKILLed in the middle of a run.

* in one process (one context): the arm and the controller without compensation step for step
  equal the in-process run (``apps.loop_run``): lock-step makes the DDS path deterministic;
* three processes (``apps.loop_dds``): the estimator is SIGKILLed at the middle; the controller
  drops to no compensation (stale count), never raises, exits 0, and every step is commanded.
"""
import os
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('pinocchio')
from rclpy.executors import SingleThreadedExecutor  # noqa: E402,I100
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from dgp_ros.apps.loop_run import run_loop, score  # noqa: E402
from dgp_ros.dynamics.closed_loop import reference_path  # noqa: E402
from dgp_ros.nodes.arm_loop import ArmLoopNode  # noqa: E402
from dgp_ros.nodes.controller import ControllerNode  # noqa: E402

pytestmark = pytest.mark.ros
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture
def ctx():
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        context.try_shutdown()


def test_lock_step_nodes_equal_the_in_process_loop(ctx):
    ex = SingleThreadedExecutor(context=ctx)
    nodes = []
    try:
        arm = ArmLoopNode(context=ctx, parameter_overrides=[
            Parameter('robot', value='ur5'), Parameter('duration_s', value=0.3),
            Parameter('min_subscribers', value=2)])
        ctl = ControllerNode(context=ctx, parameter_overrides=[
            Parameter('robot', value='ur5'), Parameter('compensation', value='none')])
        lis = rclpy.create_node('loop_listener', context=ctx)
        nodes += [arm, ctl, lis]
        got = []
        lis.create_subscription(JointState, 'joint_states', got.append, QoSProfile(depth=1000))
        for n in nodes:
            ex.add_node(n)
        t_end = time.monotonic() + 60.0
        while not arm.done and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        for _ in range(50):
            ex.spin_once(timeout_sec=0.01)
        assert arm.done and arm.counts['timeouts'] == 0 and arm.counts['commands'] == 300
        assert ctl.counts['commands'] == 300 and len(got) == 300
        ref = run_loop('ur5', 'none', duration_s=0.3, learn_s=0.1, seed=0)
        q_nodes = np.array([m.position for m in got])
        # the in-process run's error at step n is that of the state it measured at step n
        q_ref = reference_path('ur5', seed=0)(ref['t'])[0]
        np.testing.assert_allclose(q_nodes, q_ref - ref['error'], rtol=0, atol=1e-12)
        assert np.abs(ref['error']).max() > 1e-4         # the arm moved off the path: not trivial
    finally:
        for n in nodes:
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown()


@pytest.mark.timeout(400)
def test_estimator_sigkilled_mid_run_controller_drops_compensation(tmp_path):
    from dgp_ros.apps.loop_dds import run_dds
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    r = run_dds('ur5', 'dgp', 1.5, str(tmp_path), env, kill_at_s=0.75, wall_limit_s=300.0)
    c = r['controller']
    assert r['exit']['controller'] == 0 and r['exit']['arm_loop'] == 0
    assert r['killed_at_s'] is not None and 0.75 <= r['killed_at_s'] < 0.9
    assert c['commands'] == 1500 and len(r['t']) == 1500       # every step commanded
    # it answered before the kill (750 steps): a suite under load saw 466, a quiet run > 600
    assert c['answers'] > 300 and c['nonpassive_answers'] == 0
    assert c['stale'] > 0 and c['waited_out'] >= 1              # dropped the dead estimator
    log = (tmp_path / 'controller.log').read_text()
    assert 'Traceback' not in log and 'Error' not in log
    # after the kill the arm runs without compensation: tracking as the none run's
    none = run_loop('ur5', 'none', duration_s=1.5, learn_s=0.5, seed=0)
    after = r['killed_at_s'] + 0.1
    sel = r['t'] >= after
    rms_killed = np.sqrt(np.mean(r['error'][sel] ** 2, axis=0))
    rms_none = score(none, after)[0]
    assert np.all(np.isfinite(rms_killed))
    assert rms_killed.mean() < 1.5 * rms_none.mean(), (rms_killed, rms_none)


@pytest.mark.parametrize('module', ['dgp_ros.nodes.arm_loop', 'dgp_ros.nodes.controller'])
def test_help_lists_the_parameters(module):
    p = subprocess.run([sys.executable, '-m', module, '--help'], cwd=REPO, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0 and 'robot' in p.stdout and 'parameters' in p.stdout

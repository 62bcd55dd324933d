"""Two processes over real DDS: the installed ``estimator`` console script and a test node."""
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402,I100
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

pytestmark = pytest.mark.ros
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def estimator_script():
    exe = os.path.join(os.path.dirname(sys.executable), 'estimator')
    return exe if os.path.exists(exe) else shutil.which('estimator')


def test_console_script_two_processes(tmp_path):
    exe = estimator_script()
    assert exe, 'console script missing: pip install --no-deps -e .'
    model = tmp_path / 'model.npz'
    proc = subprocess.Popen(
        [exe, '--ros-args', '--params-file', os.path.join(REPO, 'config', 'estimator.yaml'),
         '-p', 'buffer_size:=30', '-p', 'min_samples:=10', '-p', 'selection:=all',
         '-p', f'model_path:={model}', '-p', 'diagnostics_period_s:=0.2'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('two_proc_test', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    got, diag = [], {}

    def on_diag(msg):
        for st in msg.status:
            if st.name.startswith('dgp_estimator'):
                diag.update({kv.key: kv.value for kv in st.values})
    try:
        node.create_subscription(JointState, '/dgp_estimator/damping_force', got.append, 100)
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
        pub = node.create_publisher(JointState, 'generalized_state', 100)

        def spin_until(cond, timeout):
            end = time.monotonic() + timeout
            while time.monotonic() < end and not cond():
                ex.spin_once(timeout_sec=0.05)
                assert proc.poll() is None, proc.stdout.read()
            return cond()

        assert spin_until(lambda: pub.get_subscription_count() >= 1 and
                          node.count_publishers('/dgp_estimator/damping_force') >= 1, 30)
        for i in range(25):
            t = 0.1 * i
            q = np.array([np.sin(t), np.cos(0.5 * t), 2 + np.sin(0.2 * t)])
            m = JointState()
            m.header.stamp.sec, m.header.stamp.nanosec = int(t), int((t % 1) * 1e9)
            m.name = ['alpha', 'beta', 'airspeed']
            m.velocity, m.effort = q.tolist(), (1.5 * q).tolist()
            k = len(got)
            pub.publish(m)
            spin_until(lambda: len(got) > k, 5)
        assert len(got) >= 20
        assert list(got[-1].name) == ['alpha', 'beta', 'airspeed']
        cli = node.create_client(Trigger, '/dgp_estimator/refit')
        assert spin_until(cli.service_is_ready, 10)
        fut = cli.call_async(Trigger.Request())
        assert spin_until(fut.done, 60)
        assert fut.result().success or 'already running' in fut.result().message
        # the first fit done before Ctrl-C: beside another suite on 2 cores the niced learner's
        # first fit took longer than the node's 2 s wait at shutdown, and nothing was saved
        assert spin_until(lambda: diag.get('refits_ok', '0') not in ('0', ''), 240), diag
    finally:
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert proc.returncode == 0, out
    assert 'dgp_estimator' in out
    assert model.exists(), out                    # saved on refit / on shutdown

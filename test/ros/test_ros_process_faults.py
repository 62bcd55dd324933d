"""
Reliability: process faults (issue 8, item 3) with the real console scripts as children.

One scenario, in order: the estimator is started before the simulator; sim_bridge is killed and
restarted while the estimator runs (its stamps restart at 0: a documented time jump); the
estimator is SIGKILLed mid-run, the model file it left is complete and loads; a restarted
estimator with that model_path and learning off answers measurements exactly with the saved
model (learning on, its own probe messages reached the model through the long history of
prior=auto, which re-selects the structure and rebases: one run in three failed).
Every published estimate is checked: finite and qd^T tau_hat >= 0.
Children always get killed in ``finally``. DDS isolation comes from test/conftest.py.
"""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402,I100
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from dgp_ros.gp import load_model  # noqa: E402

pytestmark = pytest.mark.ros
BIN = os.path.dirname(sys.executable)
RESULTS = {}
PROBE_SEC = 10 ** 6      # probe stamps: far beyond any simulator stamp of this test
OLD_SIM_S = 20.0         # stamp time the first simulator runs before it is killed


def _stamp(m):
    return m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec


def _start(cmd, log):
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _kill(p, sig=signal.SIGKILL):
    if p is not None and p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=10)


def _estimator(model_path, extra=()):
    return [os.path.join(BIN, 'estimator'), '--ros-args',
            '-p', 'model:=diag', '-p', 'passivity:=paper', '-p', 'buffer_size:=60',
            '-p', 'min_samples:=20', '-p', 'refit_period_s:=1.0',
            '-p', 'optimize_every_n_refits:=0', '-p', 'diagnostics_period_s:=0.3',
            '-p', f'model_path:={model_path}', *extra]


def _sim(real_time_factor=4.0):
    return [os.path.join(BIN, 'sim_bridge'), '--ros-args',
            '-p', f'real_time_factor:={real_time_factor}',
            '-p', 'rate_hz:=60.0', '-p', 'loop:=true']


class Listener:
    def __init__(self, ctx):
        self.node = rclpy.create_node('rel_proc_listener', context=ctx)
        self.est, self.diag, self.bad = [], [], []
        self.node.create_subscription(JointState, '/dgp_estimator/damping_force', self._on, 1000)
        self.node.create_subscription(DiagnosticArray, '/diagnostics',
                                      lambda m: self.diag.append(
                                          {v.key: v.value for v in m.status[0].values}), 100)
        self.pub = self.node.create_publisher(
            JointState, 'generalized_state', QoSProfile(depth=100,
                                                        reliability=ReliabilityPolicy.RELIABLE))
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)

    def _on(self, m):
        qd, tau = np.array(m.velocity), np.array(m.effort)
        if not (np.all(np.isfinite(qd)) and np.all(np.isfinite(tau))) or float(qd @ tau) < 0:
            self.bad.append(m)
        self.est.append(m)

    def spin_until(self, cond, timeout, procs=()):
        t_end = time.monotonic() + timeout
        while not cond() and time.monotonic() < t_end:
            self.ex.spin_once(timeout_sec=0.05)
            for p in procs:
                assert p.poll() is None, f'child exited with {p.returncode}'
        return cond()


def test_estimator_first_sim_restart_sigkill_and_model_restart(tmp_path):
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    model_path = str(tmp_path / 'model.npz')
    logs = open(tmp_path / 'children.log', 'w')
    est = sim = est2 = None
    lis = Listener(ctx)
    try:
        # 1. estimator before the simulator
        est = _start(_estimator(model_path), logs)
        assert lis.spin_until(lambda: lis.diag, 60, [est]), 'no diagnostics from the estimator'
        assert int(lis.diag[-1]['messages_received']) == 0
        sim = _start(_sim(), logs)
        assert lis.spin_until(lambda: os.path.exists(model_path) and len(lis.est) > 100, 60,
                              [est, sim]), 'no model saved / no estimates'
        # 2. simulator killed and restarted while the estimator runs: its stamps restart at 0.
        #    The estimator sees a jump back only if a message of the new simulator with a stamp
        #    below the old one's last reaches it: the old simulator runs OLD_SIM_S of stamp time
        #    and the new one starts at real time, so discovery has ~OLD_SIM_S wall seconds.
        #    (Killed after 1.7 s at 4x, the new one passed that stamp in 0.4 s: under load,
        #    before discovery, and no jump was ever sent to the estimator.)
        assert lis.spin_until(lambda: _stamp(lis.est[-1]) >= OLD_SIM_S, 60, [est, sim])
        _kill(sim)
        n_old, last_old = len(lis.est), _stamp(lis.est[-1])
        sim = _start(_sim(real_time_factor=1.0), logs)

        def restarted_answers():
            return sum(_stamp(m) < last_old for m in lis.est[n_old:])
        assert lis.spin_until(lambda: restarted_answers() >= 50, 60, [est, sim]), (
            f'no answers to the restarted simulator: {restarted_answers()} answers below the '
            f'last old stamp {last_old}, {len(lis.est) - n_old} in all since the kill, last '
            f'stamps {[round(_stamp(m), 3) for m in lis.est[-5:]]}, diagnostics '
            f'{lis.diag[-1:]}')
        n_diag = len(lis.diag)
        assert lis.spin_until(lambda: len(lis.diag) > n_diag and
                              int(lis.diag[-1]['time_jumps_back']) >= 1, 30, [est, sim]), \
            lis.diag[-1:]
        # 3. SIGKILL the estimator mid-run, right after it rewrote the model file
        m0 = os.stat(model_path).st_mtime_ns
        assert lis.spin_until(lambda: os.stat(model_path).st_mtime_ns != m0, 30, [est, sim])
        lis.spin_until(lambda: False, 0.3)      # the scenario: a kill 0.3 s after a write
        _kill(est)
        _kill(sim)
        model = load_model(model_path)         # complete, loadable (atomic write)
        leftovers = [f for f in os.listdir(tmp_path) if f.startswith('.tmp-')]
        # 4. restart with model_path and learning off: the probes are not learned, so every
        #    estimate is the saved model's
        est2 = _start(_estimator(model_path, ['-p', 'learning:=false']), logs)
        assert lis.spin_until(lambda: lis.pub.get_subscription_count() > 0, 60, [est2])
        lis.est.clear()                         # (answers to the probes are told by stamp)
        lis.diag.clear()                        # only est2's diagnostics from here on (the
        #                                         killed node's last ones said learning: on)

        def answers():
            return {m.header.stamp.sec - PROBE_SEC: np.array(m.effort) for m in lis.est
                    if m.header.stamp.sec >= PROBE_SEC}
        X = np.asarray(model.X_train_)
        rng = np.random.default_rng(0)
        Qs = X[rng.choice(len(X), 15)] * (1 + 0.01 * rng.normal(size=(15, X.shape[1])))
        names = ['alpha', 'beta', 'airspeed']
        for k, q in enumerate(Qs):
            m = JointState()
            m.header.stamp.sec, m.header.stamp.nanosec = PROBE_SEC + k, 0
            m.name = names
            m.velocity = [float(x) for x in q]
            m.effort = [float(x) for x in q]        # any finite effort: not learnt
            # best-effort subscription (and the listener may not have matched est2's publisher
            # yet): resend until answered, within one bounded deadline
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                lis.pub.publish(m)
                if lis.spin_until(lambda: k in answers(), 1, [est2]):
                    break
        got = answers()
        assert sorted(got) == list(range(len(Qs)))
        ref = model.predict(Qs)
        diff = max(float(np.max(np.abs(got[k] - ref[k]))) for k in got)
        RESULTS['restart_max_abs_diff'] = diff
        print(f'restart equality: max |tau_hat_node - tau_hat_saved_model| = {diff:.3g}; '
              f'leftover temp files: {leftovers}')
        assert diff <= 1e-9 * max(1.0, float(np.abs(ref).max()))
        assert lis.spin_until(lambda: lis.diag and lis.diag[-1].get('load_error') == '' and
                              lis.diag[-1].get('trained') == 'True', 5, [est2])
        d = lis.diag[-1]
        assert d['learning'] == 'off' and d['samples_added'] == '0', d
        assert not lis.bad, f'{len(lis.bad)} non-finite/non-passive estimates'
    finally:
        for p in (est, sim, est2):
            _kill(p)
        logs.close()
        lis.node.destroy_node()
        ctx.try_shutdown()

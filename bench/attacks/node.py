"""
The ``estimator`` node process under attack, live over DDS (``bench/hostile.py``).

``Child`` starts the node (the console script) with its output in the sandbox and its peak RSS
measured by a small wrapper; ``Live`` is a DDS client in this process that publishes to it, sets
its parameters and reads its answers and diagnostics.
"""
from __future__ import annotations

import collections
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from typing import List, Optional

import numpy as np

from .base import EPS, proc_status


def estimator_exe() -> Optional[str]:
    exe = os.path.join(os.path.dirname(sys.executable), 'estimator')
    return exe if os.path.exists(exe) else shutil.which('estimator')


# Runs a command as its child and reports the child's peak RSS (ru_maxrss of wait4). The
# command is not started from this (large) process directly: Linux carries the parent's peak
# RSS over fork + exec into ru_maxrss, so the small wrapper forks it instead.
_RSS_WRAPPER = r"""
import json, os, signal, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
out, cmd = sys.argv[1], sys.argv[2:]
pid = os.fork()
if pid == 0:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.execv(cmd[0], cmd)
open(out + '.pid', 'w').write(str(pid))
_, status, ru = os.wait4(pid, 0)
rc = os.waitstatus_to_exitcode(status)
open(out, 'w').write(json.dumps({'rc': rc, 'maxrss_kb': ru.ru_maxrss}))
sys.exit(rc if rc >= 0 else 128 - rc)
"""


class Child:
    """A node process (through ``_RSS_WRAPPER``, so that its own peak RSS is known)."""

    def __init__(self, cmd, log_path):
        self.log_path = log_path
        self.rss_path = log_path + '.rss'
        self.logf = open(log_path, 'w')
        self.p = subprocess.Popen([sys.executable, '-c', _RSS_WRAPPER, self.rss_path] + cmd,
                                  stdout=self.logf, stderr=subprocess.STDOUT,
                                  start_new_session=True, env=dict(os.environ))
        self.t0 = time.monotonic()
        self.rc: Optional[int] = None
        self.maxrss_mib = float('nan')
        self.exit_s = float('nan')

    def alive(self) -> bool:
        if self.rc is not None:
            return False
        pid, status, ru = os.wait4(self.p.pid, os.WNOHANG)
        if pid == 0:
            return True
        self._reaped(status, ru)
        return False

    def _reaped(self, status, ru):
        self.rc = os.waitstatus_to_exitcode(status)
        self.p.returncode = self.rc
        self.exit_s = time.monotonic() - self.t0
        self.logf.close()
        try:
            r = json.load(open(self.rss_path))
            self.rc, self.maxrss_mib = r['rc'], r['maxrss_kb'] / 1024.0
        except (OSError, ValueError, KeyError):
            pass

    def hwm(self) -> float:
        """Peak RSS of the node (MiB): live from /proc while it runs, else from wait4."""
        if self.rc is None:
            try:
                return proc_status('VmHWM', int(open(self.rss_path + '.pid').read()))
            except (OSError, ValueError):
                return float('nan')
        return self.maxrss_mib

    def stop(self, timeout=20.0) -> int:
        if self.rc is None:
            try:
                os.killpg(self.p.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
            end = time.monotonic() + timeout
            while self.alive() and time.monotonic() < end:
                time.sleep(0.05)
            if self.rc is None:
                os.killpg(self.p.pid, signal.SIGKILL)
                _, status, ru = os.wait4(self.p.pid, 0)
                self._reaped(status, ru)
        return self.rc

    def text(self) -> str:
        try:
            return open(self.log_path, errors='replace').read()
        except OSError:
            return ''


class Live:
    """
    This process's side of the DDS trial.

    A publisher, the estimator's outputs, its diagnostics, its parameter services.
    """

    def __init__(self):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, Float64MultiArray
        self.JointState = JointState
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('hostile_driver', context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.bad = collections.Counter()
        self.got = collections.Counter()
        self.diag: List[dict] = []
        n = self.node
        n.create_subscription(JointState, '/dgp_estimator/damping_force', self._on_force, 10000)
        n.create_subscription(JointState, '/dgp_estimator/damping_force_stddev', self._on_std,
                              10000)
        n.create_subscription(Float64, '/dgp_estimator/dissipated_power', self._on_power, 10000)
        n.create_subscription(Float64MultiArray, '/dgp_estimator/damping_matrix', self._on_D,
                              10000)
        n.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.pub = n.create_publisher(JointState, 'generalized_state',
                                      QoSProfile(depth=1000,
                                                 reliability=ReliabilityPolicy.BEST_EFFORT))

    def _on_force(self, m):
        self.got['force'] += 1
        qd, tau = np.array(m.velocity), np.array(m.effort)
        if not (np.all(np.isfinite(qd)) and np.all(np.isfinite(tau))):
            self.bad['non-finite force'] += 1
        elif float(qd @ tau) < -8 * EPS * float(np.abs(qd) @ np.abs(tau)):
            self.bad['non-passive force'] += 1

    def _on_std(self, m):
        self.got['stddev'] += 1
        if not np.all(np.isfinite(np.array(m.effort))):
            self.bad['non-finite stddev'] += 1

    def _on_power(self, m):
        self.got['power'] += 1
        if not math.isfinite(m.data):
            self.bad['non-finite power'] += 1
        elif m.data < 0:
            self.bad['negative power'] += 1

    def _on_D(self, m):
        self.got['D'] += 1
        if not np.all(np.isfinite(np.array(m.data))):
            self.bad['non-finite D'] += 1

    def _on_diag(self, m):
        for st in m.status:
            if 'online D-GP estimator' in st.name:
                d = {v.key: v.value for v in st.values}
                d['_level'] = int.from_bytes(st.level, 'little') if isinstance(
                    st.level, bytes) else int(st.level)
                d['_message'] = st.message
                d['_t'] = time.monotonic()
                d['_node'] = st.hardware_id          # the node's fully qualified name
                self.diag.append(d)
                del self.diag[:-5]

    def spin(self, seconds: float, child: Optional[Child] = None):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))
            if child is not None and not child.alive():
                return False
        return True

    def settle(self, child=None, quiet: float = 0.3, limit: float = 5.0):
        """Spin until no estimate arrived for ``quiet`` seconds (at most ``limit``)."""
        end = time.monotonic() + limit
        last, t_last = self.got['force'], time.monotonic()
        while time.monotonic() < end and time.monotonic() - t_last < quiet:
            self.ex.spin_once(timeout_sec=0.02)
            if self.got['force'] != last:
                last, t_last = self.got['force'], time.monotonic()
            if child is not None and not child.alive():
                return

    def drain(self, budget: int = 2000):
        for _ in range(budget):
            self.ex.spin_once(timeout_sec=0)

    def spin_until(self, cond, timeout: float, child: Optional[Child] = None) -> bool:
        end = time.monotonic() + timeout
        while not cond() and time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.05)
            if child is not None and not child.alive():
                return cond()
        return cond()

    def fresh_diag(self, timeout=5.0, child=None) -> dict:
        t = time.monotonic()
        self.spin_until(lambda: self.diag and self.diag[-1]['_t'] > t + 0.05, timeout, child)
        return self.diag[-1] if self.diag else {}

    def msg(self, stamp, names, v, e):
        m = self.JointState()
        if isinstance(stamp, tuple):
            m.header.stamp.sec, m.header.stamp.nanosec = stamp
        else:
            sec = int(math.floor(stamp))
            m.header.stamp.sec = sec
            m.header.stamp.nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)
        m.name = list(names)
        m.velocity = [float(x) for x in np.ravel(v)]
        m.effort = [float(x) for x in np.ravel(e)]
        return m

    def send(self, msgs, rate: float = 1000.0, child: Optional[Child] = None):
        """Publish ``msgs`` at ``rate`` (0: as fast as possible), spinning in between."""
        t0 = time.perf_counter()
        for i, m in enumerate(msgs):
            if rate > 0:
                due = t0 + i / rate
                while time.perf_counter() < due:
                    self.ex.spin_once(timeout_sec=0)
                    if time.perf_counter() < due - 2e-4:
                        time.sleep(1e-4)
            self.pub.publish(m)
            if rate == 0 and i % 200 == 0:
                self.drain(50)
        self.drain(500)
        return time.perf_counter() - t0

    def close(self):
        import rclpy  # noqa: F401
        self.node.destroy_node()
        self.ex.shutdown()
        self.ctx.try_shutdown()


def counter(d: dict, key: str) -> int:
    try:
        return int(d.get(key, 0))
    except (TypeError, ValueError):
        return 0


def rejections(d: dict) -> collections.Counter:
    return collections.Counter({k.split('/', 1)[1]: counter(d, k) for k in d
                                if k.startswith('rejected/')})


def wait_future(live, fut, child, timeout=20.0):
    live.spin_until(fut.done, timeout, child)
    return fut.result() if fut.done() else None

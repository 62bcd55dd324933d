"""
What the processes of bench/arm_live.py share: the topics and the small helpers of a role.

``live_procs.py`` (player, listener, prober, estimator, hog, relay), ``soak_live.py``'s roles
and ``arm_live.py``'s killer import it.
"""
from __future__ import annotations

import json
import os
import signal
import threading
import time

from cpu_watch import proc_stat

__all__ = ['TOPIC_IN', 'TOPIC_OUT', 'FINGER', 'stop_event', 'thread_cpu', 'write_json',
           'panda_messages', 'ros_node', 'close', 'on_diagnostics', 'state_publisher', 'play']

TOPIC_IN = '/joint_states'
TOPIC_OUT = '/dgp_estimator/damping_force'
FINGER = 'panda_finger_joint1'


def stop_event():
    """Return an event set by SIGINT or SIGTERM (a role writes its results then)."""
    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.set())
    return stop


def thread_cpu() -> dict:
    """CPU seconds of each thread of this process so far, by thread name (summed per name)."""
    out: dict = {}
    for tid in os.listdir('/proc/self/task'):
        st = proc_stat(f'/proc/self/task/{tid}/stat')
        if st:
            name = 'main' if int(tid) == os.getpid() else st[0]
            out[name] = out.get(name, 0.0) + st[2]
    return out


def write_json(path: str, obj) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (a reader never sees half of it)."""
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        json.dump(obj, f)
    os.replace(tmp, path)


def panda_messages(d: dict) -> list:
    """
    Return ``simulate_arm('panda', ...)``'s samples ``d`` as a driver's JointState messages.

    The 7 joints and a finger joint (position 0.02, velocity 0, effort 0.1), unstamped.
    """
    from array import array

    import numpy as np
    from sensor_msgs.msg import JointState
    from dgp_ros.dynamics import ARM_JOINTS
    names = list(ARM_JOINTS['panda']) + [FINGER]
    msgs = []
    for q, v, e in zip(d['q'], d['qd'], d['effort']):
        m = JointState()
        m.name = names
        m.position = array('d', np.r_[q, 0.02].tolist())
        m.velocity = array('d', np.r_[v, 0.0].tolist())
        m.effort = array('d', np.r_[e, 0.1].tolist())
        msgs.append(m)
    return msgs


def ros_node(name: str, **init):
    """Return (context, node) of a role: an rclpy context of its own, no signal handlers."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO, **init)
    return ctx, rclpy.create_node(name, context=ctx)


def close(ctx, node, ex=None) -> None:
    """Shut the executor ``ex`` (if any), the node and its context down."""
    if ex is not None:
        ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()


def on_diagnostics(node, fn, depth: int = 50):
    """Subscribe /diagnostics: ``fn(status, {key: value})`` for each status of the estimator."""
    from diagnostic_msgs.msg import DiagnosticArray

    def on_diag(msg):
        for s in msg.status:
            if 'dgp_estimator' in s.name:
                fn(s, {kv.key: kv.value for kv in s.values})
    return node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, depth)


def state_publisher(node, stop, subscribers: int = 1, wait_s: float = 90.0, ready: str = ''):
    """
    Return a reliable JointState publisher on ``TOPIC_IN`` once ``subscribers`` have matched.

    Writes the file ``ready`` (if named) once it is made, waits at most ``wait_s`` s (or until
    ``stop``), then 0.5 s more for the discovery of the answers' direction.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    pub = node.create_publisher(JointState, TOPIC_IN,
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    if ready:
        open(ready, 'w').write('ok')
    deadline = time.monotonic() + wait_s
    while pub.get_subscription_count() < subscribers and time.monotonic() < deadline and \
            not stop.is_set():
        time.sleep(0.05)
    time.sleep(0.5)
    return pub


def play(pub, items, stop, on_late) -> tuple:
    """
    Publish each (message, offset s) of ``items`` at its deadline, stamped with it.

    The deadlines are 0.05 s from now plus the offset on the monotonic clock; each stamp is the
    deadline on the wall clock (an answer's age is then wall time minus stamp), ``frame_id``
    the message's number. ``on_late(n, late_s)`` after the n-th (its lateness, s). Returns
    (the wall time of offset 0, the messages published).
    """
    t0_wall, t0_mono = time.time() + 0.05, time.monotonic() + 0.05
    n = 0
    for m, off in items:
        if stop.is_set():
            break
        dl = t0_mono + off
        now = time.monotonic()
        if dl > now:
            time.sleep(dl - now)
        stamp = t0_wall + off
        m.header.stamp.sec = int(stamp)
        m.header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)
        m.header.frame_id = str(n)
        pub.publish(m)
        n += 1
        on_late(n, time.monotonic() - dl)
    return t0_wall, n

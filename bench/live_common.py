"""
What the processes of bench/arm_live.py share: the topics and the small helpers of a role.

``live_procs.py`` (player, listener, prober, estimator, hog) and ``live_relay.py`` (the relay)
import it; neither imports the other's helpers, so the two stay apart.
"""
from __future__ import annotations

import json
import os
import signal
import threading

from cpu_watch import proc_stat

__all__ = ['TOPIC_IN', 'TOPIC_OUT', 'FINGER', 'stop_event', 'thread_cpu', 'write_json',
           'panda_messages']

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

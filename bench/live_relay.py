"""
The floor of bench/arm_floor.py: relays, the role ``relay`` of ``live_procs.py``.

A relay answers each measurement with a JointState on the estimator's answer topic and does
nothing else: what any rclpy node pays per message. ``DGP_RELAY`` chooses which:

* '' (default): a bare rclpy node (message objects in and out, rclpy's SingleThreadedExecutor;
  ``DGP_EXECUTOR=waitset``: the estimator's wait-set loop instead);
* 'raw': the message's bytes in and out unchanged (``raw=True``; any executor);
* 'lean': the bytes in and out from a loop over a wait set of one subscription (no executor,
  no services served): the least an rclpy process can spend per message.
"""
from __future__ import annotations

import os

from live_common import close, ros_node, stop_event, thread_cpu, TOPIC_IN, write_json

__all__ = ['relay']


def relay(a) -> None:
    """
    Answer each JointState with a JointState from a bare rclpy node: the floor.

    Subscribes like the estimator (best effort, depth 1000), publishes on its answer topic (depth
    1024, as the estimator) header, names, velocity and effort of each measurement, spun by rclpy's
    own SingleThreadedExecutor: what any rclpy node pays per message, with nothing of ours
    (``DGP_EXECUTOR=waitset``: the node's wait-set loop instead; ``DGP_RELAY``: the module
    docstring).
    """
    stop = stop_event()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    ctx, node = ros_node('dgp_estimator')
    pub = node.create_publisher(JointState, '~/damping_force', 1024)

    def on_state(m):
        out = JointState()
        out.header = m.header
        out.name = m.name
        out.velocity = m.velocity
        out.effort = m.effort
        pub.publish(out)

    kind = os.environ.get('DGP_RELAY', '')
    if kind == 'lean':
        _lean_relay(node, pub, ctx, stop, a)
        return
    raw = kind == 'raw'                 # the bytes in and out, unchanged
    node.create_subscription(JointState, TOPIC_IN, pub.publish if raw else on_state,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT),
                             raw=raw)
    if os.environ.get('DGP_EXECUTOR') == 'waitset':      # the node's own loop instead
        from dgp_ros.nodes.executor import WaitSetExecutor
        ex = WaitSetExecutor(context=ctx)
    else:
        ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.1)
    if a.cpu_out:
        write_json(a.cpu_out, {'threads': thread_cpu()})
    close(ctx, node, ex)


def _lean_relay(node, pub, ctx, stop, a) -> None:
    """Take every raw message waiting after each wait, publish it as it came (``lean``)."""
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    sub = node.create_subscription(
        JointState, TOPIC_IN, lambda m: None,
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT), raw=True)
    h = sub.handle
    h.__enter__()
    ws = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, ctx.handle)
    inner = pub.handle
    take = h.take_message
    while not stop.is_set():
        ws.clear_entities()
        ws.add_subscription(h)
        ws.wait(100_000_000)
        while True:
            got = take(JointState, True)
            if got is None:
                break
            inner.publish_raw(got[0])
    if a.cpu_out:
        write_json(a.cpu_out, {'threads': thread_cpu()})
    h.__exit__(None, None, None)
    close(ctx, node)

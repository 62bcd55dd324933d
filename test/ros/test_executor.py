"""
``dgp_ros.nodes.executor.WaitSetExecutor``, the node's default executor, checked functionally.

Services and timers are served, a subscription with a batch handler gets its waiting messages
in one call with their message infos (publication sequence numbers), one without gets rclpy's
callbacks (message only, or message and info), entities created and destroyed while spinning
are picked up, and a node can be removed and destroyed; under a flood the batches stay capped
and a service is still answered. No timing is asserted.
"""
import time

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Int32  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from dgp_ros.nodes.executor import DeferredResponse, set_batch_handler, WaitSetExecutor  # noqa: E402,E501

pytestmark = pytest.mark.ros


@pytest.fixture
def ctx():
    c = rclpy.Context()
    rclpy.init(context=c)
    try:
        yield c
    finally:
        c.try_shutdown()


def spin_until(ex, cond, timeout=20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not cond():
        ex.spin_once(timeout_sec=0.05)
    return cond()


def test_batches_with_infos_services_timers_and_entity_changes(ctx):
    node = rclpy.create_node('batch_exec_test', context=ctx)
    peer = rclpy.create_node('batch_exec_peer', context=ctx)
    ex = WaitSetExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(peer)
    batches, plain, with_info, ticks = [], [], [], []
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    sub = node.create_subscription(Int32, 'batched', lambda m: None, qos)
    set_batch_handler(sub, lambda msgs, infos: batches.append((msgs, infos)), 4)
    node.create_subscription(Int32, 'plain', plain.append, qos)
    node.create_subscription(Int32, 'plain', lambda m, i: with_info.append((m, i)), qos)
    node.create_timer(0.01, lambda: ticks.append(1))

    def on_trigger(req, res):
        res.success, res.message = True, 'served'
        return res
    node.create_service(Trigger, 'trigger', on_trigger)
    pub_b = peer.create_publisher(Int32, 'batched', qos)
    pub_p = peer.create_publisher(Int32, 'plain', qos)
    assert spin_until(ex, lambda: pub_b.get_subscription_count() == 1 and
                      pub_p.get_subscription_count() == 2)
    for i in range(10):
        pub_b.publish(Int32(data=i))
        pub_p.publish(Int32(data=i))
    assert spin_until(ex, lambda: sum(len(m) for m, _ in batches) == 10 and
                      len(plain) == 10 and len(with_info) == 10)
    assert all(1 <= len(m) <= 4 for m, _ in batches)          # max_batch holds
    got = [m.data for msgs, _ in batches for m in msgs]
    seqs = [i['publication_sequence_number'] for _, infos in batches for i in infos]
    assert got == list(range(10)) and seqs == sorted(seqs) and len(set(seqs)) == 10
    assert [m.data for m in plain] == list(range(10))
    assert all('publication_sequence_number' in i for _, i in with_info)
    assert spin_until(ex, lambda: len(ticks) >= 3)
    cli = peer.create_client(Trigger, 'trigger')              # created while spinning
    assert spin_until(ex, cli.service_is_ready)
    fut = cli.call_async(Trigger.Request())
    assert spin_until(ex, fut.done) and fut.result().message == 'served'
    extra = []
    tmr = node.create_timer(0.01, lambda: extra.append(1))    # a new entity is picked up
    assert spin_until(ex, lambda: len(extra) >= 2)
    node.destroy_timer(tmr)                                   # and a destroyed one let go
    for _ in range(5):
        ex.spin_once(timeout_sec=0.02)
    n = len(extra)
    for _ in range(10):
        ex.spin_once(timeout_sec=0.02)
    assert len(extra) == n
    assert ex.stats['messages'] == 10 and ex.stats['batches'] >= 3
    for nd in (node, peer):
        ex.remove_node(nd)
        nd.destroy_node()
    ex.shutdown()
    ex.spin_once(timeout_sec=0.01)                            # a no-op after shutdown


def test_services_served_between_capped_batches_under_a_flood(ctx):
    """A publisher far faster than the handler: batches stay capped, the service is answered."""
    node = rclpy.create_node('flood_exec_test', context=ctx)
    peer = rclpy.create_node('flood_exec_peer', context=ctx)
    ex = WaitSetExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(peer)
    sizes = []

    def slow_batch(msgs, infos):
        sizes.append(len(msgs))
        time.sleep(0.002)               # the handler is the bottleneck
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    sub = node.create_subscription(Int32, 'flood', lambda m: None, qos)
    set_batch_handler(sub, slow_batch, 8)

    def on_trigger(req, res):
        res.success = True
        return res
    node.create_service(Trigger, 'trigger', on_trigger)
    pub = peer.create_publisher(Int32, 'flood', qos)
    cli = peer.create_client(Trigger, 'trigger')
    assert spin_until(ex, lambda: pub.get_subscription_count() == 1 and cli.service_is_ready())
    answered = 0
    for _ in range(3):
        fut = cli.call_async(Trigger.Request())
        for i in range(300):            # a burst far beyond what 8 per 2 ms take
            pub.publish(Int32(data=i))
        assert spin_until(ex, fut.done) and fut.result().success
        answered += 1
    assert answered == 3 and sizes and max(sizes) <= 8
    for nd in (node, peer):
        ex.remove_node(nd)
        nd.destroy_node()
    ex.shutdown()


def test_a_deferred_response_is_sent_later_while_messages_keep_flowing(ctx):
    """A service answered from another thread: the executor goes on with messages meanwhile."""
    import threading
    node = rclpy.create_node('defer_exec_test', context=ctx)
    peer = rclpy.create_node('defer_exec_peer', context=ctx)
    ex = WaitSetExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(peer)
    got = []
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    sub = node.create_subscription(Int32, 'during', lambda m: None, qos)
    set_batch_handler(sub, lambda msgs, infos: got.extend(m.data for m in msgs), 8)

    def on_trigger(req, res):
        later = DeferredResponse()

        def answer():
            time.sleep(0.3)
            res.success, res.message = True, 'later'
            later.send(res)
        threading.Thread(target=answer).start()
        return later
    node.create_service(Trigger, 'trigger', on_trigger)
    pub = peer.create_publisher(Int32, 'during', qos)
    cli = peer.create_client(Trigger, 'trigger')
    assert spin_until(ex, lambda: pub.get_subscription_count() == 1 and cli.service_is_ready())
    fut = cli.call_async(Trigger.Request())
    end = time.monotonic() + 10
    i = 0
    while not fut.done() and time.monotonic() < end:
        pub.publish(Int32(data=i))
        i += 1
        ex.spin_once(timeout_sec=0.01)
    assert fut.done() and fut.result().message == 'later'
    assert len(got) > 5                 # messages were handled while the answer was pending
    for nd in (node, peer):
        ex.remove_node(nd)
        nd.destroy_node()
    ex.shutdown()

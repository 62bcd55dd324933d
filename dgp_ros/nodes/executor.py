"""
The estimator node's executor: one rcl wait set, services and timers first, messages in batches.

rclpy's SingleThreadedExecutor spends 350 to 740 us of CPU per message on its own machinery at
1 kHz (it rebuilds its wait set on every ``spin_once`` and wraps each callback in a task); its
EventsExecutor queues one event per received message, unbounded, and serves timers and services
behind that queue (seconds late under a flood). :class:`WaitSetExecutor` is the loop the node
needs and nothing more (``nodes.runtime`` chooses it by default; ``DGP_EXECUTOR`` selects
another); docs/BENCHMARKS.md (``arm_live``) measures the three.
"""
from __future__ import annotations

from collections import deque
from contextlib import ExitStack
import time
from typing import Callable, List, Optional

from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.subscription import Subscription

__all__ = ['WaitSetExecutor', 'set_batch_handler', 'DeferredResponse']


class DeferredResponse:
    """
    A service response sent later: a service callback returns one to answer after it returned.

    ``send(response)`` may be called from any thread (a learner's reply arriving in its receiver
    thread), before or after the callback returned; the executor's own thread sends it. Only
    :class:`WaitSetExecutor` takes it (rclpy's executors need the response from the callback).
    """

    def __init__(self):
        import threading
        self._lock = threading.Lock()
        self._bound = None              # (executor, service, request header)
        self._response = None

    def send(self, response) -> None:
        """Send ``response`` (once; later calls are ignored)."""
        with self._lock:
            if self._response is not None:
                return
            self._response = response
            bound = self._bound
        if bound is not None:
            bound[0]._outbox_put(bound[1], bound[2], response)

    def _bind(self, executor, srv, header) -> None:
        with self._lock:
            self._bound = (executor, srv, header)
            response = self._response
        if response is not None:
            executor._outbox_put(srv, header, response)


def set_batch_handler(sub: Subscription, handler: Callable, max_batch: int) -> None:
    """
    Give ``sub`` a batch handler: ``handler(messages, infos)`` with every message waiting.

    At most ``max_batch`` messages per call (the subscription's KEEP_LAST depth bounds what
    waits); ``infos`` are their message infos (dicts: ``publication_sequence_number``,
    ``publisher_gid``, ...). Only :class:`WaitSetExecutor` calls it; rclpy's executors call the
    subscription's own callback, one message at a time.
    """
    sub.dgp_batch = (handler, max(1, int(max_batch)))


class WaitSetExecutor:
    """
    A loop over one rcl wait set for the nodes of one process (rclpy's executor interface).

    Built on rclpy's own primitives (``_rclpy.WaitSet``, ``take_message``,
    ``service_take_request``, ``call_timer``, the waitables API) without its task, generator
    and future machinery: callbacks are plain functions, called in this thread. Each wake-up,
    in this order:

    1. services (every request waiting), timers, guard conditions and clients, at most
       ``FULL_PERIOD_S`` after they became ready even under a flood: a wake-up within that time
       of the last full round waits for messages (and this executor's guard) only, which at
       1 kHz spares most of the wait set's cost per message; QoS event waitables (the
       default "incompatible QoS" handlers of every publisher, a subscription's message-lost
       event) at most every ``EVENT_PERIOD_S``: each costs a few us of Python per wake-up;
    2. the messages: a subscription with a batch handler (``set_batch_handler``) gets every
       message waiting (at most its ``max_batch``) in one call; any other one gets one message
       per callback, as in rclpy.

    A service callback may return a :class:`DeferredResponse` and answer later (from any
    thread): the response is sent at the next wake-up. The wait set and the entity handles are
    kept between wake-ups and rebuilt only when the
    nodes' entities change (rclpy calls ``wake`` on every create and destroy). An exception in a
    callback propagates out of ``spin_once``, as with rclpy's executors; a coroutine callback
    is not supported. ``stats``: wake-ups, messages and batches handed over, the largest batch.

    It depends on rclpy internals of the pinned Jazzy wheels (rclpy 7.1); the node tests run
    with it.
    """

    #: longest a QoS event waits to be served (s)
    EVENT_PERIOD_S = 0.1
    #: longest a service, timer or client waits for its turn while messages keep coming (s)
    FULL_PERIOD_S = 0.005

    def __init__(self, *, context=None):
        from rclpy.utilities import get_default_context
        self._context = get_default_context() if context is None else context
        self._nodes: List = []
        self._guard: Optional[GuardCondition] = GuardCondition(None, None, self._context)
        self._dirty = True
        self._stack: Optional[ExitStack] = None
        self._ws = None
        self._events_at = 0.0
        self._is_shutdown = False
        self._outbox: deque = deque()        # deferred responses (service, header, response)
        self.stats = {'spins': 0, 'messages': 0, 'batches': 0, 'max_batch': 0}

    @property
    def context(self):
        return self._context

    def add_node(self, node) -> bool:
        """Serve ``node``; True if it was not served yet."""
        if node in self._nodes:
            return False
        self._nodes.append(node)
        node.executor = self
        self.wake()
        return True

    def remove_node(self, node) -> None:
        """Stop serving ``node`` and let go of its entities (it may be destroyed next)."""
        if node in self._nodes:
            self._nodes.remove(node)
            self._release()
            self.wake()

    def get_nodes(self) -> list:
        return list(self._nodes)

    def wake(self) -> None:
        """Rebuild the wait set before the next wait (an entity was created or destroyed)."""
        self._dirty = True
        guard = self._guard
        if guard is not None:
            try:
                guard.trigger()
            except InvalidHandle:
                pass

    def shutdown(self, timeout_sec: Optional[float] = None) -> bool:
        """Let go of every entity; the executor cannot be used any more."""
        self._is_shutdown = True
        self._release()
        self._nodes.clear()
        guard, self._guard = self._guard, None
        if guard is not None:
            guard.destroy()
        return True

    def _release(self) -> None:
        stack, self._stack, self._ws = self._stack, None, None
        self._dirty = True
        if stack is not None:
            stack.close()

    def _rebuild(self) -> None:
        """Hold every entity of the nodes and make a wait set that fits them."""
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        self._release()
        stack = ExitStack()
        found = {k: [] for k in ('subs', 'timers', 'services', 'clients', 'guards', 'waits')}

        def hold(entity, handle, kind) -> None:
            try:
                stack.enter_context(handle)
            except InvalidHandle:           # destroyed meanwhile
                return
            found[kind].append(entity)

        for node in self._nodes:
            for e in node.subscriptions:
                hold(e, e.handle, 'subs')
            for e in node.timers:
                hold(e, e.handle, 'timers')
            for e in node.services:
                hold(e, e.handle, 'services')
            for e in node.clients:
                hold(e, e.handle, 'clients')
            for e in node.guards:
                hold(e, e.handle, 'guards')
            for e in node.waitables:
                hold(e, e, 'waits')
        n = dict.fromkeys(('subscriptions', 'guard_conditions', 'timers', 'clients', 'services',
                           'events'), 0)
        for w in found['waits']:
            ne = w.get_num_entities()
            for key in n:
                n[key] += getattr(ne, 'num_' + key)
        stack.enter_context(self._guard.handle)
        stack.enter_context(self._context.handle)
        self._ws = _rclpy.WaitSet(
            n['subscriptions'] + len(found['subs']),
            n['guard_conditions'] + len(found['guards']) + 1, n['timers'] + len(found['timers']),
            n['clients'] + len(found['clients']), n['services'] + len(found['services']),
            n['events'], self._context.handle)
        self._stack = stack
        # each wake-up adds the same handles and asks the wait set which of them are ready (by
        # pointer): a few calls per wake-up, not one per entity and kind
        self._subs = [(s, getattr(s, 'dgp_batch', None),
                       s._callback_type is Subscription.CallbackType.MessageOnly)
                      for s in found['subs']]
        self._timers, self._services = found['timers'], found['services']
        self._clients, self._guards, self._waitables = (found['clients'], found['guards'],
                                                        found['waits'])
        # between full rounds (at most every FULL_PERIOD_S) a wake-up waits for messages only
        self._ws_msgs = _rclpy.WaitSet(len(found['subs']), 1, 0, 0, 0, 0, self._context.handle)
        self._full_due = 0.0
        ws = self._ws
        self._adds = [(ws.add_subscription, [s.handle for s, _, _ in self._subs]),
                      (ws.add_timer, [t.handle for t in self._timers]),
                      (ws.add_service, [x.handle for x in self._services]),
                      (ws.add_client, [c.handle for c in self._clients]),
                      (ws.add_guard_condition,
                       [g.handle for g in self._guards] + [self._guard.handle])]
        self._by_ptr = {}
        for kind, items, handle in (('subscription', self._subs, lambda e: e[0].handle),
                                    ('timer', self._timers, lambda e: e.handle),
                                    ('service', self._services, lambda e: e.handle),
                                    ('client', self._clients, lambda e: e.handle),
                                    ('guard_condition', self._guards, lambda e: e.handle)):
            self._by_ptr[kind] = {handle(e).pointer: e for e in items}
        self._dirty = False

    def spin_once(self, timeout_sec: Optional[float] = None) -> None:
        """Wait for work (at most ``timeout_sec``; None: until there is some) and do it."""
        if self._is_shutdown or not self._context.ok():
            return
        self.stats['spins'] += 1
        self._spin_once(timeout_sec)

    def _flush_outbox(self) -> None:
        while self._outbox:
            srv, header, response = self._outbox.popleft()
            try:
                srv.send_response(response, header)
            except InvalidHandle:       # the service is gone: nobody to answer
                pass

    def _spin_once(self, timeout_sec: Optional[float]) -> None:
        if self._dirty:
            self._rebuild()
        if self._outbox:
            self._flush_outbox()
        now = time.monotonic()
        if now < self._full_due and self._subs:
            self._messages_only(timeout_sec, self._full_due - now)
            return
        self._full_due = now + self.FULL_PERIOD_S
        ws = self._ws
        ws.clear_entities()
        for add, handles in self._adds:
            for h in handles:
                add(h)
        now = time.monotonic()
        events = self._waitables if now - self._events_at >= self.EVENT_PERIOD_S else ()
        for w in events:
            w.add_to_wait_set(ws)
        if events:
            self._events_at = now
        timeout = self.EVENT_PERIOD_S if timeout_sec is None or timeout_sec < 0 else \
            min(float(timeout_sec), self.EVENT_PERIOD_S)
        ws.wait(int(timeout * 1e9))
        if self._dirty:
            return                      # entities changed (or shut down): rebuild first
        if self._outbox:
            self._flush_outbox()
        ready, by_ptr = ws.get_ready_entities, self._by_ptr
        if self._services:
            for p in ready('service'):
                self._serve(by_ptr['service'][p])
        if self._timers:
            for p in ready('timer'):
                t = by_ptr['timer'][p]
                try:
                    with t.handle:
                        t.handle.call_timer()
                except InvalidHandle:
                    continue
                t.callback()
        if self._guards:
            for p in ready('guard_condition'):
                g = by_ptr['guard_condition'].get(p)
                if g is not None:
                    g._executor_triggered = False
                    if g.callback is not None:
                        g.callback()
        if self._clients:
            for p in ready('client'):
                self._respond(by_ptr['client'][p])
        for w in events:
            if w.is_ready(ws):
                self._run_waitable(w)
        if self._outbox:
            self._flush_outbox()        # what a timer or a reply just answered: before a batch
        for p in ready('subscription'):
            s, batch, message_only = by_ptr['subscription'][p]
            if batch is None:
                self._take_one(s, message_only)
            else:
                self._take_batch(s, *batch)

    def _messages_only(self, timeout_sec: Optional[float], left: float) -> None:
        """Wait (at most until the next full round) for messages and this executor's guard."""
        ws = self._ws_msgs
        ws.clear_entities()
        for s, _, _ in self._subs:
            ws.add_subscription(s.handle)
        ws.add_guard_condition(self._guard.handle)
        timeout = left if timeout_sec is None or timeout_sec < 0 else \
            min(float(timeout_sec), left)
        ws.wait(int(timeout * 1e9))
        if self._dirty:
            return
        by_ptr = self._by_ptr['subscription']
        for p in ws.get_ready_entities('subscription'):
            s, batch, message_only = by_ptr[p]
            if batch is None:
                self._take_one(s, message_only)
            else:
                self._take_batch(s, *batch)

    def _serve(self, srv) -> None:
        """Answer every request waiting at ``srv`` (a ``DeferredResponse`` later)."""
        while True:
            try:
                with srv.handle:
                    request, header = srv.handle.service_take_request(srv.srv_type.Request)
            except InvalidHandle:
                return
            if header is None:
                return
            response = srv.callback(request, srv.srv_type.Response())
            if isinstance(response, DeferredResponse):
                response._bind(self, srv, header)
            else:
                srv.send_response(response, header)

    def _outbox_put(self, srv, header, response) -> None:
        """Queue a deferred response for this executor's thread and wake it."""
        self._outbox.append((srv, header, response))
        self.wake_only()

    def wake_only(self) -> None:
        """Wake the wait (without rebuilding the wait set)."""
        guard = self._guard
        if guard is not None:
            try:
                guard.trigger()
            except InvalidHandle:
                pass

    @staticmethod
    def _respond(client) -> None:
        try:
            with client.handle:
                header, response = client.handle.take_response(client.srv_type.Response)
        except InvalidHandle:
            return
        if header is None:
            return
        try:
            future = client.get_pending_request(header.request_id.sequence_number)
        except KeyError:               # the request was cancelled
            return
        future.set_result(response)

    @staticmethod
    def _run_waitable(w) -> None:
        coro = w.execute(w.take_data())
        try:
            coro.send(None)
        except StopIteration:
            return
        coro.close()
        raise RuntimeError(f'{type(w).__name__}.execute awaited: WaitSetExecutor runs plain '
                           'callbacks only')

    @staticmethod
    def _take_one(sub, message_only: bool) -> None:
        try:
            with sub.handle:
                got = sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:
            return
        if got is not None:
            sub.callback(got[0]) if message_only else sub.callback(*got)

    def _take_batch(self, sub, handler: Callable, max_batch: int) -> None:
        msgs, infos = [], []
        try:
            with sub.handle:
                take, msg_type, raw = sub.handle.take_message, sub.msg_type, sub.raw
                while len(msgs) < max_batch:
                    got = take(msg_type, raw)
                    if got is None:
                        break
                    msgs.append(got[0])
                    infos.append(got[1])
        except InvalidHandle:
            pass
        if msgs:
            st = self.stats
            st['messages'] += len(msgs)
            st['batches'] += 1
            if len(msgs) > st['max_batch']:
                st['max_batch'] = len(msgs)
            handler(msgs, infos)

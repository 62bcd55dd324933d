"""
Commands to the learner process and their replies, matched by id (no rclpy).

A part of :class:`~dgp_ros.online.process.LearnerProcess`. Every command carries an id; the
child answers with a ``reply`` of that id. ``call`` sends one and waits for its reply (bounded);
``call_async`` sends one and has ``done((ok, payload))`` called with its reply, from the
receiver thread, or with (False, why) when the child cannot be reached, dies first
(``fail_all``) or does not answer in time (``expire``). The part owns the ids, the replies
waited for, the callbacks and the condition variable the waiting threads sleep on.
"""
from __future__ import annotations

import itertools
import threading
import time
from typing import Callable

__all__ = ['Calls']


class Calls:
    """Commands and replies (module docstring); ``send(msg)`` writes one to the child."""

    def __init__(self, timeout_s: float):
        self.timeout_s = float(timeout_s)
        self._cv = threading.Condition(threading.Lock())
        self._ids = itertools.count(1)
        self._replies: dict = {}            # id -> (ok, payload), None while awaited
        self._callbacks: dict = {}          # id -> (done, deadline) of calls not waited for

    def call(self, send: Callable, kind: str, *args, timeout=None):
        """Send a command and wait for its reply: (ok, payload); (False, why) on a timeout."""
        i = next(self._ids)
        with self._cv:
            self._replies[i] = None
        try:
            send((kind, i) + args)
        except (OSError, ValueError) as exc:
            with self._cv:
                self._replies.pop(i, None)
            return False, f'the learner process is not reachable: {exc}'
        deadline = time.monotonic() + (self.timeout_s if timeout is None else timeout)
        with self._cv:
            while self._replies.get(i) is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    self._replies.pop(i, None)
                    return False, f'the learner did not answer {kind!r} in time'
                self._cv.wait(left)
            return self._replies.pop(i)

    def call_async(self, send: Callable, kind: str, done: Callable, *args, timeout=None) -> None:
        """Send a command without waiting: ``done((ok, payload))`` gets its reply (module doc)."""
        i = next(self._ids)
        deadline = time.monotonic() + (self.timeout_s if timeout is None else timeout)
        with self._cv:
            self._callbacks[i] = (done, deadline)
        try:
            send((kind, i) + args)
        except (OSError, ValueError) as exc:
            with self._cv:
                cb = self._callbacks.pop(i, None)
            if cb is not None:
                done((False, f'the learner process is not reachable: {exc}'))

    def deliver(self, i: int, ok: bool, payload) -> None:
        """Hand the reply with id ``i`` to whoever waits for it (the receiver thread)."""
        with self._cv:
            cb = self._callbacks.pop(i, None)
            # a reply nobody waits for any more (its call timed out or expired) is dropped:
            # kept, one per late reply, they would pile up for the life of the node
            if cb is None and i in self._replies:
                self._replies[i] = (ok, payload)
                self._cv.notify_all()
        if cb is not None:
            cb[0]((ok, payload))

    def held(self) -> int:
        """Return how many calls are open: waited for, or with a callback (none when idle)."""
        with self._cv:
            return len(self._replies) + len(self._callbacks)

    def fail_all(self, why: str) -> None:
        """Answer every call still open with (False, why): the child died."""
        with self._cv:                       # nobody waits forever on a dead child
            for i in list(self._replies):
                if self._replies[i] is None:
                    self._replies[i] = (False, why)
            self._cv.notify_all()
            orphans, self._callbacks = list(self._callbacks.values()), {}
        for done, _ in orphans:
            done((False, why))

    def expire(self) -> None:
        """Answer the calls not waited for whose reply is overdue."""
        now = time.monotonic()
        with self._cv:
            late = [i for i, (_, dl) in self._callbacks.items() if dl < now]
            late = [self._callbacks.pop(i) for i in late]
        for done, _ in late:
            done((False, 'the learner did not answer in time'))

"""
The learning clock: the time learning decisions use, from the message stamps (no rclpy).

A part of :class:`~dgp_ros.online.path.estimator.OnlineEstimator`, called under its lock. Learning
goes by the message stamps (a replay decides exactly as the live run did), unless stamps stop
advancing (``STALLED_STAMPS`` equal stamps in a row: a driver that leaves header.stamp at 0 or
constant); then by the arrival time, with a WARN, until they advance again for as many
messages. Answers keep the message's own stamp either way.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

__all__ = ['LearningClock', 'STALLED_STAMPS']

#: equal stamps in a row after which learning switches to arrival time (and advancing ones
#: after which it switches back)
STALLED_STAMPS = 20


class LearningClock:
    """The time learning decisions use (module docstring)."""

    def __init__(self):
        self._raw_last: Optional[float] = None   # the last message stamp (s)
        self._last_t: Optional[float] = None     # the last learning time (s)
        self._same = 0                           # equal stamps in a row
        self._advancing = 0                      # advancing stamps in a row (on arrival time)
        self._arrival_t0: Optional[float] = None     # set: learning uses arrival time

    @property
    def on_arrival(self) -> bool:
        """Tell whether learning uses the arrival time (the stamps do not advance)."""
        return self._arrival_t0 is not None

    @property
    def last(self) -> Optional[float]:
        """Return the last learning time given (s), None before any."""
        return self._last_t

    def time(self, stamp: float) -> float:
        """Return the learning time of a message stamped ``stamp``, in seconds."""
        advancing = self._raw_last is not None and stamp > self._raw_last
        self._raw_last = stamp
        if self._arrival_t0 is None:
            self._same = 0 if advancing else self._same + 1
            if self._same >= STALLED_STAMPS:
                self._arrival_t0 = time.monotonic() - (self._last_t or 0.0)
                self._advancing = 0
        else:
            self._advancing = self._advancing + 1 if advancing else 0
            if self._advancing >= STALLED_STAMPS:      # the stamps recovered
                self._arrival_t0 = None
                self._same = 0
        t = stamp if self._arrival_t0 is None else time.monotonic() - self._arrival_t0
        self._last_t = t
        return t

    def times(self, stamps: np.ndarray) -> np.ndarray:
        """Return ``time`` of each stamp (k,), in order (at once while the stamps advance)."""
        last = self._raw_last
        if self._arrival_t0 is None and last is not None and stamps[0] > last and \
                (stamps.size == 1 or bool((np.diff(stamps) > 0).all())):
            self._raw_last = self._last_t = float(stamps[-1])
            self._same = 0
            return stamps
        return np.array([self.time(s) for s in stamps.tolist()])

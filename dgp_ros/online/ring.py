"""
A bounded channel of float64 rows between two processes: a shared-memory ring (no rclpy).

One producer (the message path) appends rows, one consumer (the learner) takes every row waiting
in one copy. A full ring refuses the row (the producer counts it) instead of blocking: the
message path never waits for the learner. The two counters live in the same shared block; a
``multiprocessing.Lock`` around their updates orders the row writes before the counter (a
memory barrier on every architecture), held for a few array writes only. The producer waits
for it at most ``LOCK_TIMEOUT_S`` and refuses the row otherwise: a consumer killed while holding
it (SIGKILL) cannot stall the message path; the producer then makes a new ring for the next
consumer.
"""
from __future__ import annotations

from multiprocessing import shared_memory
from typing import Optional

import numpy as np

__all__ = ['SampleRing']

_HEADER = 2          # int64 counters: rows written, rows read (both ever)


class SampleRing:
    """
    Fixed-capacity ring of (capacity, width) float64 rows in shared memory.

    Parameters
    ----------
    width : int
        Floats per row.
    capacity : int
        Rows the ring holds; a push beyond it is refused.
    lock : multiprocessing lock
        Shared by both sides (passed to the child when it starts).
    name : str or None
        Attach to an existing ring (the consumer); None creates one (the producer, which owns
        and finally unlinks it).

    """

    def __init__(self, width: int, capacity: int, lock, name: Optional[str] = None):
        self.width, self.capacity = int(width), int(capacity)
        size = 8 * (_HEADER + self.width * self.capacity)
        self._owner = name is None
        self._shm = shared_memory.SharedMemory(name=name, create=self._owner, size=size)
        buf = self._shm.buf
        self._hdr = np.ndarray((_HEADER,), dtype=np.int64, buffer=buf)
        self._data = np.ndarray((self.capacity, self.width), dtype=np.float64, buffer=buf,
                                offset=8 * _HEADER)
        if self._owner:
            self._hdr[:] = 0
        self._lock = lock

    @property
    def name(self) -> str:
        return self._shm.name

    #: longest wait of ``push`` for the lock (s)
    LOCK_TIMEOUT_S = 0.002

    def push(self, row) -> bool:
        """Append one row (width,); False (nothing written) when the ring is full or stuck."""
        if not self._lock.acquire(timeout=self.LOCK_TIMEOUT_S):
            return False
        try:
            w, r = int(self._hdr[0]), int(self._hdr[1])
            if w - r >= self.capacity:
                return False
            self._data[w % self.capacity] = row
            self._hdr[0] = w + 1
        finally:
            self._lock.release()
        return True

    def pending(self, timeout: float = -1) -> Optional[int]:
        """Rows written and not yet taken; None if the lock is not free within ``timeout`` s."""
        if not self._lock.acquire(timeout=None if timeout < 0 else timeout):
            return None
        try:
            return int(self._hdr[0] - self._hdr[1])
        finally:
            self._lock.release()

    def take(self, max_rows: Optional[int] = None) -> np.ndarray:
        """Return a copy of the rows waiting (oldest first, at most ``max_rows``), (k, width)."""
        with self._lock:
            w, r = int(self._hdr[0]), int(self._hdr[1])
        k = w - r if max_rows is None else min(w - r, int(max_rows))
        if k <= 0:
            return np.empty((0, self.width))
        idx = (r + np.arange(k)) % self.capacity
        rows = self._data[idx]                      # fancy indexing: a copy
        with self._lock:
            self._hdr[1] = r + k
        return rows

    def close(self) -> None:
        """Detach (and unlink, on the side that created it)."""
        self._hdr = self._data = None
        try:
            self._shm.close()
            if self._owner:
                self._shm.unlink()
        except (FileNotFoundError, BufferError):
            pass

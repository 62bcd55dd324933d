"""
A bounded channel of float64 rows between two processes: a shared-memory ring (no rclpy).

One producer (the message path) appends rows, one consumer (the learner) takes every row waiting
in one copy. A full ring refuses the row (the producer counts it) instead of blocking: the
message path never waits for the learner. The two counters live in the same shared block; a
``multiprocessing.Lock`` around their updates orders the row writes before the counter (a
memory barrier on every architecture), held for a few array writes only. The producer never
waits for it: when the consumer holds it (a learner at idle priority can be preempted holding it
for as long as the node keeps the CPU busy, or be stopped, or killed), the row waits in a small
local backlog that the next push writes first (``BACKLOG_ROWS``; beyond it rows are refused), so
a stalled consumer costs the message path nothing and a preempted one loses no row; the producer
makes a new ring for the next consumer after a kill.
"""
from __future__ import annotations

from collections import deque
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
        self._backlog: deque = deque()
        self._skip = 0                  # the consumer passes over rows before this index

    @property
    def name(self) -> str:
        return self._shm.name

    #: rows kept on the producer's side while the lock is taken (about 1 s at 1 kHz)
    BACKLOG_ROWS = 1024
    #: longest wait of ``pending`` (the diagnostics) for the lock, by default (s)
    LOCK_TIMEOUT_S = 0.002

    def push(self, row) -> bool:
        """
        Append one row (width,) without waiting; False (nothing kept) when it cannot be kept.

        The ring full, or the lock taken with ``BACKLOG_ROWS`` rows already waiting here.
        """
        backlog = self._backlog
        if not self._lock.acquire(False):
            if len(backlog) >= self.BACKLOG_ROWS:
                return False
            backlog.append(np.array(row, dtype=np.float64))
            return True
        try:
            w, r = self._write_backlog(), int(self._hdr[1])
            if w - r >= self.capacity:
                return False
            self._data[w % self.capacity] = row
            self._hdr[0] = w + 1
        finally:
            self._lock.release()
        return True

    def push_rows(self, rows: np.ndarray) -> int:
        """
        Append rows (k, width) in order without waiting; return how many were kept (a prefix).

        ``push`` for each row, under one lock: the backlog first, then the rows that fit; with
        the lock taken they join the backlog as far as it has room.
        """
        backlog = self._backlog
        if not self._lock.acquire(False):
            room = max(0, min(len(rows), self.BACKLOG_ROWS - len(backlog)))
            backlog.extend(np.array(rows[:room], dtype=np.float64))
            return room
        try:
            hdr = self._hdr
            w = self._write_backlog() if backlog else int(hdr[0])
            kept = max(0, min(len(rows), self.capacity - (w - int(hdr[1]))))
            if kept == 1:
                self._data[w % self.capacity] = rows[0]
            elif kept:
                self._data[(w + np.arange(kept)) % self.capacity] = rows[:kept]
            hdr[0] = w + kept
        finally:
            self._lock.release()
        return kept

    def flush(self, timeout: float = 0.0) -> None:
        """
        Write the backlog into the ring if the lock is free within ``timeout`` s (0: now).

        A backlog is otherwise written by the next ``push``: when the stream pauses, the node
        calls this (``LearnerProcess``'s receiver, at each status of the learner) so that the
        last rows before a pause reach the learner too.
        """
        backlog = self._backlog
        if not backlog:
            return
        if not (self._lock.acquire(True, timeout) if timeout > 0 else self._lock.acquire(False)):
            return
        try:
            self._write_backlog()
        finally:
            self._lock.release()

    def _write_backlog(self) -> int:
        """With the lock held: write the backlog rows that fit, oldest first; the write index."""
        backlog, w, r = self._backlog, int(self._hdr[0]), int(self._hdr[1])
        while backlog and w - r < self.capacity:
            self._data[w % self.capacity] = backlog.popleft()
            w += 1
        self._hdr[0] = w
        return w

    @property
    def backlog(self) -> int:
        """Rows pushed and kept on the producer's side (the lock was taken at their push)."""
        return len(self._backlog)

    def pending(self, timeout: float = -1) -> Optional[int]:
        """
        Return the rows pushed and not yet taken; None if the lock is not free within ``timeout``.

        The producer's backlog is written first (the lock is held anyway), so that 0 means
        every row pushed reached the consumer: rows kept while it held the lock would otherwise
        wait for the next push, which does not come when the stream stops. What a full ring
        keeps back is counted too.
        """
        if not self._lock.acquire(timeout=None if timeout < 0 else timeout):
            return None
        try:
            w = self._write_backlog() if self._backlog else int(self._hdr[0])
            return int(w - self._hdr[1]) + len(self._backlog)
        finally:
            self._lock.release()

    def mark(self) -> int:
        """
        Return the producer's index after every row pushed so far (its backlog included).

        The consumer's ``skip_to(mark)`` then passes over them: a reset forgets the rows sent
        before it, though they reach the consumer after it (the ring and the commands are two
        channels, and the consumer reads its commands first).
        """
        with self._lock:
            return int(self._hdr[0]) + len(self._backlog)

    @property
    def taken(self) -> int:
        """Consumer: the producer index below which every row was read; cf. ``mark``."""
        return int(self._hdr[1])

    def skip_to(self, index: int) -> None:
        """Consumer: never take the rows before ``index`` (a producer's ``mark``)."""
        self._skip = max(self._skip, int(index))

    def take(self, max_rows: Optional[int] = None) -> np.ndarray:
        """Return a copy of the rows waiting (oldest first, at most ``max_rows``), (k, width)."""
        with self._lock:
            w, r = int(self._hdr[0]), int(self._hdr[1])
            if r < self._skip:          # rows a reset forgot (``skip_to``)
                r = min(self._skip, w)
                self._hdr[1] = r
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

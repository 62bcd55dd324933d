"""
Which measurements the online estimator learns from, and the buffer that keeps them.

Every accepted message is answered; only some are learned:

* a learning-rate limit in *stamp* time (at most one sample per ``min_sample_interval_s``), so a
  replay decides exactly as the live run did and a 1 kHz stream does not drown the O(n^2) update;
* novelty (``selection='novelty'``): a sample closer than ``selection_min_distance`` (in
  per-joint scales) to a buffered sample adds nothing but cost (a hovering state would fill the
  buffer with near-duplicates). The scale is ``selection_scale`` if given, else a robust spread
  of the buffered velocities (1.4826 x the median absolute deviation, which one wild sample
  cannot inflate), floored so that a constant joint does not make every wiggle novel;
* isolated outliers: a sample more than ``OUTLIER_Z`` robust scales from the buffer's median, in
  velocity or in force, is not learned unless ``OUTLIER_RUN`` (10, 0.1 s at the default learning
  rate) such samples come in a row (then the motion really changed and they are learned). One
  in-range spike (a velocity of 9999 in a stream of +-2) used to inflate the spread and make every
  later sample a near-duplicate.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

__all__ = ['Buffer', 'Selector']


class Buffer:
    """Fixed-capacity FIFO of (qd, tau) rows, numpy backed (oldest first on read)."""

    def __init__(self, capacity: int, N: int):
        self.capacity, self.N = int(capacity), int(N)
        self._q = np.zeros((self.capacity, self.N))
        self._t = np.zeros((self.capacity, self.N))
        self._start = 0
        self.size = 0

    def append(self, q, t) -> None:
        i = (self._start + self.size) % self.capacity
        self._q[i], self._t[i] = q, t
        if self.size < self.capacity:
            self.size += 1
        else:
            self._start = (self._start + 1) % self.capacity

    def velocities_unordered(self) -> np.ndarray:
        """Return the buffered velocities in storage order (no copy), (size, N)."""
        return self._q[:self.size] if self.size < self.capacity else self._q

    def rows_unordered(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return the buffered (Qd, Tau) in storage order (no copy), (size, N) each."""
        n = self.size
        return (self._q[:n], self._t[:n]) if n < self.capacity else (self._q, self._t)

    def arrays(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return copies of (Qd, Tau), (size, N) each, oldest first."""
        idx = (self._start + np.arange(self.size)) % self.capacity
        return self._q[idx].copy(), self._t[idx].copy()

    @classmethod
    def of(cls, capacity: int, Qd: np.ndarray, Tau: np.ndarray) -> 'Buffer':
        """Make a buffer holding the newest ``capacity`` rows of ``Qd`` and ``Tau``."""
        b = cls(capacity, Qd.shape[1])
        for q, t in zip(Qd[-capacity:], Tau[-capacity:]):
            b.append(q, t)
        return b


class Selector:
    """
    The learning decision for one sample (see the module docstring).

    Parameters are read from an ``EstimatorConfig`` at each call, so a reconfiguration applies
    at once.
    """

    OUTLIER_Z = 50.0
    OUTLIER_RUN = 10

    #: the robust statistics of the buffer are recomputed after this many additions (medians of
    #: the whole buffer on every candidate cost more than the rest of the selection)
    STATS_EVERY = 16

    def __init__(self):
        self.last_added_stamp: Optional[float] = None
        self._far_run = 0
        self._stats = None           # (buffer size, additions at computation, mq, sq, mt, st)
        self.additions = 0

    def rate_limited(self, config, stamp: float) -> bool:
        """
        Tell whether the sample is rate limited.

        True when the last sample offered for learning is less than ``min_sample_interval_s``
        older (a stamp that went back is never limited).
        """
        dt = config.min_sample_interval_s
        last = self.last_added_stamp
        return dt > 0 and last is not None and last <= stamp < last + dt * (1.0 - 1e-9)

    @staticmethod
    def robust_scale(A: np.ndarray) -> tuple:
        """(median, 1.4826 x median absolute deviation), floored; (N,) each."""
        if A.shape[0] == 0:
            return np.zeros(A.shape[1]), np.ones(A.shape[1])
        med = np.median(A, axis=0)
        mad = 1.4826 * np.median(np.abs(A - med), axis=0)
        floor = 1e-3 * (np.abs(A).mean(axis=0) + 1e-3)
        return med, np.maximum(mad, floor)

    def _robust_stats(self, buf: Buffer):
        st = self._stats
        if st is None or self.additions - st[1] >= self.STATS_EVERY or buf.size < st[0] or \
                buf.size < 2 * self.STATS_EVERY and buf.size != st[0]:
            Q, T = buf.rows_unordered()
            st = (buf.size, self.additions) + self.robust_scale(Q) + self.robust_scale(T)
            self._stats = st
        return st[2:]

    def scale(self, config, buf: Buffer) -> np.ndarray:
        """Return the per-joint novelty scale, (N,), velocity units."""
        if config.selection_scale:
            return np.asarray(config.selection_scale, dtype=float)
        return self._robust_stats(buf)[1]

    def outlier(self, config, buf: Buffer, qd: np.ndarray, target: np.ndarray) -> bool:
        """
        Return True for an isolated far outlier as defined in the module docstring.

        Never before ``min_samples``.
        """
        if buf.size < max(config.min_samples, 10):
            return False
        mq, sq, mt, st = self._robust_stats(buf)
        far = (np.max(np.abs(qd - mq) / sq) > self.OUTLIER_Z or
               np.max(np.abs(target - mt) / st) > self.OUTLIER_Z)
        if not far:
            self._far_run = 0
            return False
        self._far_run += 1
        return self._far_run < self.OUTLIER_RUN

    def novel(self, config, buf: Buffer, qd: np.ndarray) -> bool:
        """Return True unless ``qd`` is a near-duplicate of a buffered sample."""
        if config.selection != 'novelty' or buf.size == 0 or config.selection_min_distance <= 0:
            return True
        Q = buf.velocities_unordered()
        d2 = (((Q - qd) / self.scale(config, buf)) ** 2).sum(axis=1).min()
        return bool(d2 >= config.selection_min_distance ** 2)

    def added(self, stamp: float) -> None:
        """Record that the sample at ``stamp`` was offered for learning."""
        self.last_added_stamp = stamp

"""
Which measurements the online estimator learns from, and the buffer that keeps them.

Every accepted message is answered; only some are learned:

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

__all__ = ['Buffer', 'Selector', 'robust_scale']


def robust_scale(A: np.ndarray) -> tuple:
    """(median, 1.4826 x median absolute deviation), floored; (N,) each, of rows A (n, N)."""
    if A.shape[0] == 0:
        return np.zeros(A.shape[1]), np.ones(A.shape[1])
    med = np.median(A, axis=0)
    mad = 1.4826 * np.median(np.abs(A - med), axis=0)
    floor = 1e-3 * (np.abs(A).mean(axis=0) + 1e-3)
    return med, np.maximum(mad, floor)


class Buffer:
    """
    Fixed-capacity buffer of (qd, tau) rows, numpy backed, with optional per-row extras.

    ``policy='recency'``: a FIFO (the oldest row is replaced). ``policy='coverage'``: once full,
    a new row replaces one of the two closest rows (velocity distance in ``scale`` units, the
    one whose second-nearest neighbour is closer), so the buffer keeps the velocities that were
    visited, not the last seconds; O(capacity N) per row with a cached distance matrix.
    ``policy='even'``: rows spread evenly in time over the whole run, in bounded memory: every
    ``stride``-th row offered is kept; when full, every other row goes (oldest first) and the
    stride doubles (the sample the hyper-parameters and the elements of D are learned on:
    ``Window.even_arrays``). ``arrays`` reads the rows oldest first (the fit holds the newest
    out to choose the elements of D: ``gp.select``).
    Extras: the raw residual (N,) and the correction columns (N, C) of each row, kept so that
    the targets can be recomputed when the parametric part is refitted (``retarget``).
    """

    def __init__(self, capacity: int, N: int, policy: str = 'recency'):
        self.capacity, self.N = int(capacity), int(N)
        self.policy = policy
        self._q = np.zeros((self.capacity, self.N))
        self._t = np.zeros((self.capacity, self.N))
        self._r: Optional[np.ndarray] = None
        self._y: Optional[np.ndarray] = None
        self._start = 0
        self.size = 0
        self._age = np.zeros(self.capacity, np.int64)   # when each slot's row came (a count)
        self._count = 0
        self._d: Optional[np.ndarray] = None       # coverage: distances between slots
        self.scale: Optional[np.ndarray] = None    # coverage: velocity scale (N,), set when full
        self._stride, self._offered = 1, 0         # even: keep one row offered in ``_stride``

    def append(self, q, t, extra=None) -> int:
        """Store a row (replacing one when full, by the policy); return its slot (-1: not kept)."""
        if self.policy == 'even':
            self._offered += 1
            if self._offered % self._stride:
                return -1
            if self.size == self.capacity:
                self._halve()
        if self.size < self.capacity:
            i = (self._start + self.size) % self.capacity
            self.size += 1
        elif self.policy == 'coverage':
            i, dn = self._coverage_slot(np.asarray(q, float))
        else:
            i = self._start
            self._start = (self._start + 1) % self.capacity
        self._q[i], self._t[i] = q, t
        self._count += 1
        self._age[i] = self._count
        if extra is not None:
            self._store_extra(i, *extra)
        if self.policy == 'coverage' and self._d is not None:
            self._update_distances(i, dn)
        elif self.policy == 'coverage' and self.size == self.capacity:
            self._init_distances()
        return i

    def _halve(self) -> None:
        """Keep every other row, oldest first (the newest stays), and double the stride."""
        idx = (self._start + np.arange(self.size)) % self.capacity
        keep = idx[np.argsort(self._age[idx], kind='stable')][1::2]
        k = len(keep)
        for a in ('_q', '_t', '_r', '_y', '_age'):
            arr = getattr(self, a)
            if arr is not None:
                arr[:k] = arr[keep]
        self._start, self.size = 0, k
        self._stride *= 2

    def _store_extra(self, i: int, r, y) -> None:
        if self._r is None:
            self._r = np.zeros((self.capacity, self.N))
            if y is not None:
                self._y = np.zeros((self.capacity,) + np.shape(y))
        self._r[i] = r
        if self._y is not None and y is not None:
            self._y[i] = y

    def _init_distances(self) -> None:
        Q = self._q
        self.scale = robust_scale(Q)[1]
        Z = Q / self.scale
        sq = np.einsum('ij,ij->i', Z, Z)
        d = np.sqrt(np.maximum(sq[:, None] + sq[None, :] - 2.0 * Z @ Z.T, 0.0))
        np.fill_diagonal(d, np.inf)
        self._d = d
        # each row's nearest neighbour, kept up to date by _update_distances (a minimum over
        # the whole matrix per sample was a quarter of the learner's time at buffer 500)
        self._nn = np.argmin(d, axis=1)
        self._near = d[np.arange(len(d)), self._nn]

    def _update_distances(self, i: int, d: np.ndarray) -> None:
        """Row ``i`` was replaced; ``d`` (capacity,): the new row's distances to the old rows."""
        d[i] = np.inf
        self._d[i], self._d[:, i] = d, d
        near, nn = self._near, self._nn
        lost = np.flatnonzero(nn == i)          # their nearest was the row just replaced
        closer = d < near
        near[closer], nn[closer] = d[closer], i
        for j in lost:
            if not closer[j]:
                nn[j] = int(np.argmin(self._d[j]))
                near[j] = self._d[j, nn[j]]
        nn[i] = int(np.argmin(d))
        near[i] = d[nn[i]]

    def _coverage_slot(self, q: np.ndarray) -> tuple:
        """
        Return (the slot a new row replaces, the new row's distances to the rows (capacity,)).

        The slot is one of the closest pair (class docstring).
        """
        d = self._d
        near = self._near
        a = int(np.argmin(near))
        b = int(self._nn[a])
        # the new row itself may be the closest: then it replaces its nearest neighbour only if
        # that is closer to it than the closest pair is to each other
        dn = np.sqrt((((self._q - q) / self.scale) ** 2).sum(axis=1))
        k = int(np.argmin(dn))
        if dn[k] < near[a]:
            return k, dn
        da = np.partition(d[a], 1)[1]
        db = np.partition(d[b], 1)[1]
        return (a if da < db else b), dn

    def retarget(self, correction) -> None:
        """Recompute the targets as residual - ``correction(columns)`` (k, N) for every row."""
        if self._r is None or self.size == 0:
            return
        n = self.size
        y = None if self._y is None else self._y[:n]
        self._t[:n] = self._r[:n] - correction(y)

    def residuals_unordered(self):
        """Return the buffered raw residuals (size, N) and correction columns (or None)."""
        n = self.size
        if self._r is None or n == 0:
            return np.zeros((0, self.N)), None
        return self._r[:n], (None if self._y is None else self._y[:n])

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
        if self.policy != 'recency':
            idx = idx[np.argsort(self._age[idx], kind='stable')]
        return self._q[idx].copy(), self._t[idx].copy()

    @classmethod
    def of(cls, capacity: int, Qd: np.ndarray, Tau: np.ndarray,
           policy: str = 'recency') -> 'Buffer':
        """Make a buffer holding the newest ``capacity`` rows of ``Qd`` and ``Tau``."""
        b = cls(capacity, Qd.shape[1], policy)
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

    #: the robust statistics of the buffer are recomputed after this many additions, or a
    #: twentieth of the buffer if more (medians of the whole buffer on every candidate cost
    #: more than the rest of the selection)
    STATS_EVERY = 16

    def __init__(self):
        self._far_run = 0
        self._trust = 0              # samples for which far ones are learned (a regime change)
        self._stats = None           # (buffer size, additions at computation, mq, sq, mt, st)
        self.additions = 0

    def _robust_stats(self, buf: Buffer):
        st = self._stats
        every = max(self.STATS_EVERY, buf.capacity // 20)
        if st is None or self.additions - st[1] >= every or buf.size < st[0] or \
                buf.size < 2 * self.STATS_EVERY and buf.size != st[0]:
            Q, T = buf.rows_unordered()
            st = (buf.size, self.additions) + robust_scale(Q) + robust_scale(T)
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
            self._trust = max(0, self._trust - 1)
            return False
        self._far_run += 1
        if self._far_run >= self.OUTLIER_RUN:
            # the motion changed: trust far samples for a buffer's worth of samples (a coverage
            # buffer keeps the old regime, so its statistics lag the new one for long)
            self._trust = buf.capacity
        return self._far_run < self.OUTLIER_RUN and self._trust == 0

    def novel(self, config, buf: Buffer, qd: np.ndarray) -> bool:
        """Return True unless ``qd`` is a near-duplicate of a buffered sample."""
        if config.selection != 'novelty' or buf.size == 0 or config.selection_min_distance <= 0:
            return True
        Q = buf.velocities_unordered()
        d2 = (((Q - qd) / self.scale(config, buf)) ** 2).sum(axis=1).min()
        return bool(d2 >= config.selection_min_distance ** 2)

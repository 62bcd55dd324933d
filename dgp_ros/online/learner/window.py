"""
The window: the samples the GP is fitted on, in the order they were learned (no rclpy).

A part of :class:`~dgp_ros.online.learner.Learner`; it owns its state and is called under the
learner's lock. It holds

* the buffer (``selection.Buffer``: ``buffer_size`` rows, replaced by ``buffer_policy``) and the
  selection that decides what enters it (``selection.Selector``);
* the sequence number of every sample added (``seq``: samples ever added, so that the served
  model can say up to which sample it holds them) and the newest rows with their target
  generation (``rows``: what an append or a re-proof's catch-up takes);
* the generation of the targets (``target_gen``): the parametric part re-selected with
  ``prior='auto'`` retargets every buffered row (``retarget``), and a model fitted on targets of
  another generation cannot take the new rows by appending;
* what the health report reads off the stream: the power of the recent learned samples, the
  recent candidates and when a sample was last added.
"""
from __future__ import annotations

from collections import deque
from typing import Optional, Tuple

import numpy as np

from .selection import Buffer, Selector

__all__ = ['Window', 'POWER_WINDOW', 'POWER_MIN']

#: learned samples over which the negative-power warning is decided (and the least it needs)
POWER_WINDOW, POWER_MIN = 1000, 100


class Window:
    """
    The learned samples (module docstring).

    capacity : ``buffer_size``; policy : ``buffer_policy``. The buffer is made when the number
    of joints is known (``ensure``).
    """

    def __init__(self, capacity: int, policy: str):
        self.capacity, self.policy = int(capacity), policy
        self.buffer: Optional[Buffer] = None
        # the same samples spread evenly over the whole run (``even_arrays``)
        self.even: Optional[Buffer] = None
        self.selector = Selector()
        self.seq = 0                    # samples ever added (orders the appends)
        self.target_gen = 0             # bumped whenever the buffer's targets change
        # (seq, target generation, qd, target) of the newest samples: what appends take
        self.rows: deque = deque(maxlen=max(1, self.capacity))
        self.last_added_t: Optional[float] = None
        self.learned_power: deque = deque(maxlen=POWER_WINDOW)
        self.recent_q: deque = deque(maxlen=100)        # recent candidates (stall check)

    def ensure(self, N: int) -> None:
        """Make the buffer for N joints if there is none yet."""
        if self.buffer is None:
            self.buffer = Buffer(self.capacity, N, self.policy)
            self.even = Buffer(self.capacity, N, 'even')

    # ------------------------------------------------------------------ reading
    @property
    def size(self) -> int:
        """Return how many samples the buffer holds."""
        return 0 if self.buffer is None else self.buffer.size

    def arrays(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return copies of the buffered (Qd, Tau), (size, N) each, oldest first."""
        return self.buffer.arrays()

    def even_arrays(self) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return copies of (Qd, Tau) of the samples spread evenly over the run, oldest first.

        What the hyper-parameters and the elements of D are learned on (``gp.select``): the
        buffer keeps the velocities visited, and its hyper-parameters lost most of the box
        accuracy on coupled systems (docs/BENCHMARKS.md: 0.015 against 1.4e-4 for 200 samples
        spread in time, 4 axes).
        """
        return self.even.arrays()

    def rows_unordered(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return the buffered (Qd, Tau) in storage order (no copy)."""
        return self.buffer.rows_unordered()

    def residuals_unordered(self):
        """Return the buffered raw residuals (size, N) and correction columns (or None)."""
        return self.buffer.residuals_unordered()

    def run_of(self, lo: int, hi: int, gen: int) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """
        Return (Qd (k, n), targets (k, m)) of the samples ``lo < seq <= hi``, k = hi - lo.

        None unless every one of them is still kept with targets of generation ``gen``: what
        a model that holds the samples up to ``lo`` can append to hold them up to ``hi``
        (otherwise a rebase must take them).
        """
        rows = [r for r in self.rows if lo < r[0] <= hi]
        if len(rows) != hi - lo or any(r[1] != gen for r in rows):
            return None
        return np.array([r[2] for r in rows]), np.array([r[3] for r in rows])

    # ------------------------------------------------------------------ learning
    def offered(self, qd: np.ndarray, residual: np.ndarray) -> None:
        """Record a sample offered for learning (its power, its velocity)."""
        self.learned_power.append(float(qd @ residual))
        self.recent_q.append(qd)

    def outlier(self, config, qd: np.ndarray, residual: np.ndarray) -> bool:
        """Tell whether the sample is an isolated far outlier, as ``selection`` defines it."""
        return self.selector.outlier(config, self.buffer, qd, residual)

    def novel(self, config, qd: np.ndarray) -> bool:
        """Tell whether the sample is no near-duplicate of a buffered one (``selection``)."""
        return self.selector.novel(config, self.buffer, qd)

    def add(self, stamp: float, qd: np.ndarray, target: np.ndarray, extra=None) -> int:
        """Buffer one sample learned at ``stamp``; returns its sequence number."""
        self.last_added_t = stamp
        self.buffer.append(qd, target, extra)
        self.even.append(qd, target, extra)
        self.selector.additions += 1
        self.seq += 1
        self.rows.append((self.seq, self.target_gen, qd, target))
        return self.seq

    def retarget(self, correction) -> None:
        """Recompute every buffered target as residual - ``correction(columns)``."""
        if self.buffer is not None:
            self.buffer.retarget(correction)
            self.even.retarget(correction)
            self.target_gen += 1    # what a model holds is not appended to any more

    def adopt(self, Qd: np.ndarray, Tau: np.ndarray) -> int:
        """
        Hold the newest ``capacity`` rows of (Qd, Tau) instead (a model's training samples).

        The rows kept for appends are forgotten and the count restarts at the buffer's size
        (the model adopted with them holds them all); returns that count.
        """
        self.buffer = Buffer.of(self.capacity, Qd, Tau, policy=self.policy)
        self.even = Buffer.of(self.capacity, Qd, Tau, policy='even')
        self.seq = self.buffer.size
        self.rows = deque(maxlen=max(1, self.capacity))
        self.target_gen = 0
        return self.seq

    def refill(self, Qd: np.ndarray, Tau: np.ndarray) -> None:
        """Hold the newest ``capacity`` rows of (Qd, Tau) (a new structure on the same data)."""
        self.buffer = Buffer.of(self.capacity, Qd, Tau, policy=self.policy)
        self.even = Buffer.of(self.capacity, Qd, Tau, policy='even')

    def resumed(self, t: Optional[float]) -> None:
        """Learning resumes at ``t``: the pause is no stall."""
        self.last_added_t = t

    # ------------------------------------------------------------------ health
    def negative_power_fraction(self) -> Optional[float]:
        """Fraction of the recent learned samples with ``qd . target < 0`` (None: too few)."""
        p = self.learned_power
        if len(p) < POWER_MIN:
            return None
        return float(np.mean(np.asarray(p) < 0.0))

    def stalled_for(self, config, last_t: Optional[float], after_s: float) -> Optional[float]:
        """
        Return for how long (s) learning has stalled, None while it has not.

        Stalled: no sample added for ``after_s`` of learning time although the recent
        candidates spread over many novelty distances (not a hovering state).
        """
        if not config.learning or self.last_added_t is None or last_t is None or \
                self.buffer is None or last_t - self.last_added_t < after_s or \
                len(self.recent_q) < 10:
            return None
        Q = np.array(self.recent_q)
        spread = (Q.max(axis=0) - Q.min(axis=0)) / self.selector.scale(config, self.buffer)
        if spread.max() > 10.0 * max(config.selection_min_distance, 1e-3):
            return last_t - self.last_added_t
        return None

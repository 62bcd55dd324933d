"""
The per-joint element's part of the long history: its columns, its warp and its two halves.

A part of :class:`~dgp_ros.dynamics.history.LongHistory`, which calls it and owns the
statistics it adds to. The element (``dgp_ros.gp.joint_element``: a reduced-rank GP on each
joint's velocity, learned from every sample) needs three things the parametric part does not:

* **a velocity scale per joint**, fixed once: an arm starts slowly, and a warp fixed by its first
  second would squeeze the speeds it reaches later against the end of the basis. So the samples
  of the first ``START_S`` of learning time have zero element columns (they inform only the
  element fit's nuisance offset); then each joint's scale is fixed at ``HEADROOM`` x the largest
  speed it reached;
* **two interleaved halves of the run** (epochs of ``EPOCH_BLOCKS`` history blocks, alternately):
  an element that the halves learn differently is not a velocity curve the data hold
  (``gp.joint_element.agreement``) and is not served;
* **its fit**: from the statistics of all the samples, the history's cross-validation folds and
  the halves, each against what the parametric part leaves; and **the velocities it saw**, per
  joint the lowest and the highest, beyond which the element hands back to the parametric part
  (``JointElementMean(span=)``).

No rclpy.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import numpy as np

from dgp_ros.gp.joint_element import ElementFit, ElementFold, fit_elements, M_BASIS, \
    VelocityBasis

from .statistics import Stats

__all__ = ['ElementTrack', 'START_S', 'HEADROOM', 'EPOCH_BLOCKS']

#: the element starts after this much learning time (s), with its warp's velocity scale at
#: this many times each joint's largest speed by then
START_S, HEADROOM = 3.0, 2.0
#: the two halves of the run interleave epochs of this many history blocks
EPOCH_BLOCKS = 2


class ElementTrack:
    """
    The element's state in a long history (module docstring).

    N : joints; Lx : the statistics' columns (the parametric ones, then the element's M);
    M : the element's columns per joint (0: no element).
    """

    def __init__(self, N: int, Lx: int, M: int = M_BASIS):
        self.M = int(M)
        self.basis: Optional[VelocityBasis] = None
        self.vmax: Optional[np.ndarray] = None         # the largest speed of each joint
        #: the lowest and highest velocity of each joint: the element serves inside them
        self.vlo: Optional[np.ndarray] = None
        self.vhi: Optional[np.ndarray] = None
        self.t0: Optional[float] = None                # the first sample's stamp
        self.halves = [Stats(N, Lx), Stats(N, Lx)]
        self.half_samples = [0, 0]                     # samples with the element's columns
        self.closed = 0                                # history blocks closed so far
        self._block_samples = 0                        # ... in the block not closed yet

    def columns(self, V: np.ndarray, stamp: float) -> np.ndarray:
        """Return the element's columns of velocities V (k, N) learned by ``stamp``: (k, N, M)."""
        top = np.max(np.abs(V), axis=0)
        self.vmax = top if self.vmax is None else np.maximum(self.vmax, top)
        lo, hi = V.min(axis=0), V.max(axis=0)
        self.vlo = lo if self.vlo is None else np.minimum(self.vlo, lo)
        self.vhi = hi if self.vhi is None else np.maximum(self.vhi, hi)
        if self.t0 is None:
            self.t0 = stamp
        if self.basis is None:
            if not self.M or stamp - self.t0 < START_S:
                return np.zeros(V.shape + (self.M,))
            self.basis = VelocityBasis.for_velocities(HEADROOM * self.vmax[None], self.M)
        self._block_samples += V.shape[0]
        return self.basis.columns(V)

    def block_closed(self, block: Stats) -> None:
        """Add a closed history block to its half of the run."""
        half = (self.closed // EPOCH_BLOCKS) % 2
        self.halves[half] += block
        self.half_samples[half] += self._block_samples
        self._block_samples = 0
        self.closed += 1

    def copy(self) -> 'ElementTrack':
        c = ElementTrack.__new__(ElementTrack)
        c.__dict__.update(self.__dict__)
        c.halves = [h.copy() for h in self.halves]
        c.half_samples = list(self.half_samples)
        return c

    def fit(self, L: int, offset: int, thetas: Sequence[np.ndarray], total: Stats,
            folds: Sequence[Tuple[Stats, Sequence[np.ndarray], Stats]]) -> Optional[ElementFit]:
        """
        Fit each joint's element on what the parametric part leaves (``gp.joint_element``).

        L : the parametric columns (the element's follow); offset : the constant column;
        thetas : per joint the served parametric coefficients (L,); total : the statistics the
        parametric part was fitted on; folds : (training statistics, per joint the parametric
        coefficients fitted on them, the scored block) of the history's cross-validation.
        """
        if self.basis is None or total.n == 0:
            return None
        cols = L + np.arange(self.M)
        N = len(thetas)
        cv: List[List[ElementFold]] = [[] for _ in range(N)]
        for train, ths, block in folds:
            for j in range(N):
                fold = train.element_train(j, ths[j], L, cols, offset)
                fold.test = block.element_test(j, ths[j], L, cols)
                cv[j].append(fold)
        full = [total.element_train(j, thetas[j], L, cols, offset) for j in range(N)]
        halves = [[h.element_train(j, thetas[j], L, cols, offset) for h in self.halves]
                  for j in range(N)]
        fit = fit_elements(self.basis, full, cv, halves, self.half_samples)
        fit.span = (self.vlo.copy(), self.vhi.copy())
        return fit

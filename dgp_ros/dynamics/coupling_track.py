"""
The long history's persistent columns: which velocities never near zero, and their columns.

A part of :class:`~dgp_ros.dynamics.history.LongHistory`, which calls it and owns the statistics
it adds to. On a system without a rigid-body model (an aircraft, the paper's damping systems)
every velocity starts as a candidate column of :class:`~dgp_ros.gp.coupled.CouplingBasis`, its
reference speed the first sample's; a candidate stays one while its velocity keeps the first
sample's sign and never comes below :data:`PERSIST_LEVEL` times its RMS (an aircraft's airspeed,
85-101 m/s on an approach: 0.85 or more). A velocity that reverses or nears zero (an arm's joint,
a damping system's axis: within its first swing) is dropped for good, its columns with it; the
history deletes them from its statistics (:meth:`LongHistory._drop_columns`), so the rest stay
exact. No rclpy.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from dgp_ros.gp.coupled import CouplingBasis

__all__ = ['CouplingTrack', 'PERSIST_LEVEL', 'COUPLING_RIDGE']

#: a candidate column's velocity must stay at or above this fraction of its RMS
PERSIST_LEVEL = 0.5
#: the couplings' ridge: this many samples' worth of each feature's mean square (the constant
#: one has none: the first sample alone answers its own force). A feature may then explain
#: only what the data show of it: with a ridge of 1e-6 the first samples of an approach (3
#: samples, 12 features, beta within 1e-3 rad) answered -1.3e8 N of drag for 9e4
COUPLING_RIDGE = 1.0


class CouplingTrack:
    """
    The candidate persistent columns of a long history (module docstring).

    N : velocities. ``basis`` is the basis of the columns still candidates (None before the
    first sample or once none is left); ``K`` the number of its features (the statistics'
    coupling columns).
    """

    def __init__(self, N: int):
        self.N = int(N)
        self.sign: Optional[np.ndarray] = None     # each velocity's sign at the first sample
        self.vmin = np.full(self.N, np.inf)        # least signed speed s v so far
        self.lo = np.full(self.N, np.inf)          # the box of every velocity so far
        self.hi = np.full(self.N, -np.inf)
        self.ss = np.zeros(self.N)                 # sum of v^2
        self.sv = np.zeros(self.N)                 # sum of v
        self.n = 0
        self.cols: List[int] = list(range(self.N))
        self.vref = np.ones(self.N)
        self.basis: Optional[CouplingBasis] = None
        self.K = len(self.cols) * CouplingBasis.features_per_column(self.N)

    def observe(self, V: np.ndarray) -> List[int]:
        """
        Take velocities V (k, N) about to be learned; return the candidates they drop.

        Call before :meth:`columns` with the same rows, and drop the returned columns' features
        from the statistics first (``drop_slices``, with the basis as it was).
        """
        V = np.atleast_2d(np.asarray(V, float))
        if self.sign is None:
            first = V[0]
            self.sign = np.sign(first)
            self.vref = np.where(first != 0.0, np.abs(first), 1.0)
        S = V * self.sign
        self.vmin = np.minimum(self.vmin, S.min(axis=0))
        self.lo = np.minimum(self.lo, V.min(axis=0))
        self.hi = np.maximum(self.hi, V.max(axis=0))
        self.ss += np.einsum('kn,kn->n', V, V)
        self.sv += V.sum(axis=0)
        self.n += V.shape[0]
        rms = np.sqrt(self.ss / self.n)
        dead = [p for p in self.cols if not (self.sign[p] != 0.0 and
                                             self.vmin[p] >= PERSIST_LEVEL * rms[p])]
        return dead

    def serving(self) -> Optional[int]:
        """
        Return the index (among ``cols``) of the column whose couplings serve (None: none).

        The most persistent candidate: the least spread about its mean (``std / |mean|``; an
        approach's airspeed 3 %, an angle of attack that stayed positive for a while 10 % and
        more). One column: two persistent ones' features explain the same forces.
        """
        if not self.cols or not self.n:
            return None
        ms = self.ss[self.cols] / self.n
        mean = self.sv[self.cols] / self.n
        spread = np.sqrt(np.maximum(ms - mean * mean, 0.0)) / np.maximum(np.abs(mean), 1e-300)
        return int(np.argmin(spread))

    def drop_slices(self, dead: List[int]) -> np.ndarray:
        """Remove the columns ``dead``; return their feature indices (of the current K)."""
        if not dead:
            return np.zeros(0, int)
        size = CouplingBasis.features_per_column(self.N)
        idx = [c * size + k for c, p in enumerate(self.cols) if p in dead for k in range(size)]
        self.cols = [p for p in self.cols if p not in dead]
        self.K = len(self.cols) * CouplingBasis.features_per_column(self.N)
        self.basis = None
        return np.asarray(idx, int)

    def basis_now(self) -> CouplingBasis:
        """Return the basis of the columns still candidates (made once per set of columns)."""
        if self.basis is None:
            self.basis = CouplingBasis(self.N, self.cols, self.vref[self.cols])
        return self.basis

    def fitted_basis(self) -> CouplingBasis:
        """Return the basis a fit serves with: these columns, clipped to what was seen."""
        return self.basis_now().boxed(self.lo, self.hi)

    def columns(self, V: np.ndarray) -> np.ndarray:
        """Return the coupling columns of velocities V (k, N), shared by the outputs: (k, K)."""
        if not self.cols:
            return np.zeros((np.atleast_2d(V).shape[0], 0))
        return self.basis_now().columns(V)

    def copy(self) -> 'CouplingTrack':
        c = CouplingTrack.__new__(CouplingTrack)
        c.__dict__.update(self.__dict__)
        c.vmin, c.ss, c.sv, c.cols = self.vmin.copy(), self.ss.copy(), self.sv.copy(), \
            list(self.cols)
        c.lo, c.hi = self.lo.copy(), self.hi.copy()
        return c

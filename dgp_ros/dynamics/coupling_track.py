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

__all__ = ['CouplingTrack', 'PERSIST_LEVEL', 'CONFIRM_S', 'COUPLING_RIDGE',
           'COUPLING_RIDGES']

#: a candidate column's velocity must stay at or above this fraction of its RMS
PERSIST_LEVEL = 0.5
#: the long history serves a column's couplings (the D-GP's prior mean) only once its
#: candidates have been observed this long (s of learning time): every axis of the 20 synthetic
#: coupled systems of ``bench/dgp_family.py`` (4 seed sets) reversed or neared zero within 1.6 s,
#: and a prior coupled through one for that second moved their last second (one step ahead) by
#: up to 100x; the aircraft's first seconds are the stream part's (``online.stream_part``)
CONFIRM_S = 2.0
#: the couplings' ridge in the long history: this many samples' worth of each feature's mean
#: square (the constant one has none: the first sample alone answers its own force), chosen
#: at each selection among ``COUPLING_RIDGES`` by the CV blocks, ``COUPLING_RIDGE`` before.
#: Fixed, none was right everywhere: 1e-6 let the first samples of an approach (3 samples, 12
#: features, beta within 1e-3 rad) answer -1.3e8 N of drag for 9e4; 1.0 biased a noise-free
#: polynomial of 30 s to 3e-3 of the lift's variance held out (0.01: 4e-7); 0.01 took the
#: default flight's drag to 2.3e-3 one step ahead where 0.3 gave 2.8e-4 (the seed-20241 family
#: passed 24 of 24 with each of 0.01, 0.3 and 1.0)
COUPLING_RIDGES = (0.01, 0.1, 1.0, 10.0)
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
        self.t0: Optional[float] = None            # the first and last stamps observed
        self.t: Optional[float] = None
        self.cols: List[int] = list(range(self.N))
        self.vref = np.ones(self.N)
        self.basis: Optional[CouplingBasis] = None
        self._fitted: Optional[tuple] = None       # (key, basis) of the last fitted_basis
        self.K = len(self.cols) * CouplingBasis.features_per_column(self.N)

    def observe(self, V: np.ndarray, stamp: Optional[float] = None) -> List[int]:
        """
        Take velocities V (k, N) about to be learned; return the candidates they drop.

        stamp : the learning time of the newest of them (s), for ``serving(confirm_s)``.

        Call before :meth:`columns` with the same rows, and drop the returned columns' features
        from the statistics first (``drop_slices``, with the basis as it was).
        """
        V = np.atleast_2d(np.asarray(V, float))
        if stamp is not None:
            self.t0 = stamp if self.t0 is None else self.t0
            self.t = stamp
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

    def serving(self, confirm_s: float = 0.0) -> Optional[int]:
        """
        Return the index (among ``cols``) of the column whose couplings serve (None: none).

        The most persistent candidate: the least spread about its mean (``std / |mean|``; an
        approach's airspeed 3 %, an angle of attack that stayed positive for a while 10 % and
        more). One column: two persistent ones' features explain the same forces.
        ``confirm_s``: only once the candidates have been observed that long (s of stamps).
        """
        if not self.cols or not self.n:
            return None
        if confirm_s > 0.0 and (self.t is None or self.t - self.t0 < confirm_s):
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

    def fitted_basis(self, c: Optional[int] = None) -> CouplingBasis:
        """
        Return the basis a fit serves with, clipped to the velocities seen.

        c : the serving column's index among ``cols`` (its features alone), None: all of them.
        """
        key = (c, tuple(self.cols), self.lo.tobytes(), self.hi.tobytes())
        if self._fitted is not None and self._fitted[0] == key:
            return self._fitted[1]          # immutable: shared by the fits until the box grows
        if c is None:
            basis = self.basis_now().boxed(self.lo, self.hi)
        else:
            p = self.cols[c]
            basis = CouplingBasis(self.N, [p], [self.vref[p]]).boxed(self.lo, self.hi)
        self._fitted = (key, basis)
        return basis

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

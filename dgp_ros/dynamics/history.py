"""
The parametric part of a residual, fitted on the whole learned history, and its structure.

The residual the online learner sees (``effort - tau_rb`` on an arm, the force itself without a
rigid-body model) is explained per joint by linear parts (:mod:`~.parametric`): passive friction
columns of the joint's velocity, an offset, a conservative correction of the rigid-body model
(:mod:`~.conservative`), and without a rigid-body model the couplings of a velocity that never
nears zero (:mod:`~.coupling_track`).

The history is kept as sufficient statistics (the Gram matrix of the columns and their product
with the residual, per joint) in blocks of :data:`BLOCK_S` seconds of learning time: O(1) memory
and O(N C^2) per sample whatever the length of the run (:mod:`~.statistics`).

The structure (which friction family, offsets or not, the correction or not) is chosen by
forward-chaining cross-validation over the last blocks: fit on everything before a block, score on
the block, with the columns that are applied (a correction's training-only columns are not). The
score is the mean over joints of the pooled squared error over the residual's variance. Offsets
need a clear win (they drift with the pose on a real arm: learned on one part of a motion they are
wrong on the next, and adjacent blocks cannot show that), and the simplest structure close to the
best is taken. Offsets are then kept joint by joint (:mod:`~.joint_choice`): a joint keeps its
offset only where it cuts that joint's own score clearly (a real UR10's wrist 2 carries a 2.4 N m
offset that no other joint has: without it its held-out NMSE is 0.10, with it 0.016), and on an
arm a joint's friction may get a level per direction of motion by the same kind of rule.

Beside the whole history it keeps recent memories, in which a block's weight halves with every
:data:`HALF_LIVES_S` seconds of learning that follow it. Where the chosen structure fitted on
one of them predicts the scored blocks clearly better than fitted on all of it
(:data:`RECENT_MARGIN`), that memory serves: friction that drifts (a gearbox warming up, wear) is
followed, and steady friction keeps every sample.
"""
from __future__ import annotations

from collections import deque
import copy
from typing import List, Optional, Tuple

import numpy as np

from dgp_ros.gp.joint_element import ElementFit, M_BASIS

from .coupling_track import CONFIRM_S, COUPLING_RIDGE, COUPLING_RIDGES, CouplingTrack
from .element_track import ElementTrack
from .joint_choice import JointChoice
from .layout import TC, transmission_columns, Unknowns
from .parametric import F, FAMILIES, friction_columns, ParametricFit
from .statistics import Stats

__all__ = ['LongHistory', 'BLOCK_S', 'HALF_LIVES_S']

#: learning-time length of a statistics block (s), and the blocks scored by cross-validation
BLOCK_S = 1.5
FOLDS = 3
#: a cross-validation fold needs this fraction of the history before its test block
MIN_TRAIN_FRACTION = 0.4
#: offsets are selected only when they cut the CV score by more than this fraction
OFFSET_MARGIN = 0.1
#: the simplest structure within this fraction of the best CV score is chosen
SIMPLER_MARGIN = 0.05
#: recent memories: a block's weight halves with every this many seconds of learning time
#: (blocks of data) that follow it (friction that drifts: a gearbox warming up, wear); the
#: cross-validation chooses among them and the whole history
HALF_LIVES_S = (10.0, 30.0, 90.0)
#: a recent memory serves where it cuts the chosen structure's CV score by this fraction
RECENT_MARGIN = 0.3
#: where couplings serve, the friction family serving is kept unless another's CV score is
#: lower by more than this fraction
SWITCH_MARGIN = 0.1


class LongHistory(JointChoice):
    """
    Sufficient statistics of the learned history and the structure selection (module docstring).

    Parameters
    ----------
    N : int
        Joints (outputs).
    basis : conservative basis or None
        :func:`~dgp_ros.dynamics.conservative.correction_basis`; None without positions.
    default_family : str
        The friction family used until cross-validation can choose.
    offsets : bool
        Whether offsets are a candidate. Without a rigid-body model the effort *is* the damping
        force (an aircraft's aerodynamic force): there is no offset to set apart.
    elements : bool
        Whether each joint may carry an element of D learned from every sample
        (:mod:`~dgp_ros.dynamics.element_track`).
    couplings : bool
        Whether velocities that never near zero carry couplings (``gp.coupled``;
        :mod:`~dgp_ros.dynamics.coupling_track`): a system that is not an arm. Not with
        ``elements``.
    asymmetric : bool, optional
        Whether a joint's friction may have a level per direction of motion (``layout``): an
        arm's geared joints. None: as ``elements``.

    """

    def __init__(self, N: int, basis=None, default_family: str = 'friction',
                 offsets: bool = True, elements: bool = True, couplings: bool = False,
                 asymmetric: Optional[bool] = None, transmissions: Optional[bool] = None):
        if couplings and elements:
            raise ValueError('long history: couplings and elements are for different systems')
        self.N = int(N)
        self.basis = basis
        self.C = 0 if basis is None else int(basis.C)
        self.coupling = CouplingTrack(self.N) if couplings else None
        self.K = 0 if self.coupling is None else self.coupling.K
        self.ridge = COUPLING_RIDGE             # the couplings' ridge (CV chooses among RIDGES)
        #: per-direction friction (the friction columns' even twins): an arm's, whose geared
        #: joints differ between their directions (None: with the elements)
        self.asymmetric = bool(elements if asymmetric is None else asymmetric)
        self.FE = 2 * F if self.asymmetric else F
        #: coupled transmissions between adjacent joints (an arm's: None follows ``elements``)
        self.transmissions = bool(elements if transmissions is None else transmissions) and \
            self.N >= 2
        self.TC = TC if self.transmissions else 0
        self.L = self.FE + 1 + self.C + self.K + self.TC
        #: the statistics' columns: the parametric ones (friction, offset, correction,
        #: couplings), then the element's (module docstring)
        self.Lx = self.L + (M_BASIS if elements else 0)
        self.element = ElementTrack(self.N, self.Lx, self.Lx - self.L)
        self._last_t: Optional[float] = None
        self.default_family = default_family
        self.offsets = bool(offsets)
        self._older = Stats(self.N, self.Lx)
        self._recent = [Stats(self.N, self.Lx) for _ in HALF_LIVES_S]   # the older, decayed
        self._blocks: deque = deque()
        self._cur = Stats(self.N, self.Lx)
        self._rows: List[tuple] = []
        self._block_t0: Optional[float] = None
        self._layout()
        self.samples = 0

    def _layout(self) -> None:
        """Lay out the unknowns: friction per joint, offsets, the shared correction, couplings."""
        self.unknowns = Unknowns(self.N, self.C, self.K, self.asymmetric, self.transmissions)
        self.P = self.unknowns.P
        self._idx = self.unknowns.idx

    # ------------------------------------------------------------------ data
    def push(self, stamp: float, q, qd, qdd, r) -> Optional[np.ndarray]:
        """
        Add one sample (residual r (N,) at q, qd, qdd); return its correction columns (N, C).

        The training columns are returned so that the learner can subtract the fitted
        correction from the samples it keeps (None without a basis).
        """
        qd = np.asarray(qd, float)
        Ft = friction_columns(qd)[:, :self.FE]                 # (N, FE)
        one = np.ones((self.N, 1))
        Yt = Yd = None
        if self.basis is not None:
            Yt, Yd = self.basis.columns(np.asarray(q, float), qd, np.asarray(qdd, float))
            At = np.concatenate([Ft, one, Yt], axis=1)
            Ad = At if Yd is Yt else np.concatenate([Ft, one, Yd], axis=1)
        else:
            At = Ad = np.concatenate([Ft, one], axis=1)
        self._last_t = stamp
        if self._block_t0 is None:
            self._block_t0 = stamp
        elif not (0.0 <= stamp - self._block_t0 < BLOCK_S):
            self._close_block(stamp)
        self._rows.append((At, Ad, np.asarray(r, float), qd))
        self.samples += 1
        if len(self._rows) >= 64:
            self._flush()
        return Yt

    def _flush(self) -> None:
        if not self._rows:
            return
        rows, self._rows = self._rows, []
        V = np.array([v for *_, v in rows])
        E = self.element.columns(V, self._last_t)                                 # (k, N, M)
        if self.TC:
            E = np.concatenate([transmission_columns(V), E], axis=2)
        if self.coupling is not None:
            dead = self.coupling.observe(V, self._last_t)
            if dead:
                self._drop_columns(self.coupling.drop_slices(dead))
            Cc = self.coupling.columns(V)                                         # (k, K)
            E = np.concatenate([np.broadcast_to(Cc[:, None, :], (V.shape[0], self.N, self.K)),
                                E], axis=2)
        At = np.concatenate([np.array([a for a, *_ in rows]), E], axis=2)
        same = all(d is a for a, d, *_ in rows)        # training columns are the applied ones
        Ad = At if same else np.concatenate([np.array([d for _, d, *_ in rows]), E], axis=2)
        self._cur.add_rows(At, Ad, np.array([r for _, _, r, _ in rows]))

    def _drop_columns(self, idx: np.ndarray) -> None:
        """Delete coupling features ``idx`` (of the K) from every statistics block (exact)."""
        cols = self.FE + 1 + self.C + idx
        for st in [self._older, self._cur, *self._recent, *self._blocks, *self.element.halves]:
            st.drop(cols)
        self.K -= idx.size
        self.L -= idx.size
        self.Lx -= idx.size
        self._layout()

    def _close_block(self, stamp: float) -> None:
        self._flush()
        if self._cur.n:
            self.element.block_closed(self._cur)
            self._blocks.append(self._cur)
            while len(self._blocks) > FOLDS:
                b = self._blocks.popleft()
                self._older += b
                for r, h in zip(self._recent, HALF_LIVES_S):
                    r.decay(0.5 ** (BLOCK_S / h))
                    r += b
        self._cur = Stats(self.N, self.Lx)
        self._block_t0 = stamp

    def copy(self) -> 'LongHistory':
        """Duplicate the statistics (what a background fit works on)."""
        self._flush()
        c = copy.copy(self)
        c._older = self._older.copy()
        c._recent = [r.copy() for r in self._recent]
        c._blocks = deque(b.copy() for b in self._blocks)
        c._cur = self._cur.copy()
        c.element = self.element.copy()
        c.coupling = None if self.coupling is None else self.coupling.copy()
        c._rows = []
        return c

    # ------------------------------------------------------------------ fitting
    def _total(self, blocks, with_current: bool, memory: int = -1) -> Stats:
        """Add ``blocks`` to the whole history (memory -1) or to a recent one (its index)."""
        if with_current:
            self._flush()           # first: a flush may drop coupling columns everywhere
        t = (self._older if memory < 0 else self._recent[memory]).copy()
        for b in blocks:
            t += b
        if with_current:
            t += self._cur
        return t

    def _global(self, st: Stats) -> Tuple[np.ndarray, np.ndarray]:
        return self.unknowns.gram(st)

    def _mask(self, family: str, offsets, conservative: bool, asymmetric=False,
              transmission=()) -> np.ndarray:
        """
        Columns of a structure; ``offsets``, ``asymmetric``: a bool, or (N,) bools.

        transmission : the motors that serve, ((a, s), ...) (``layout.Unknowns.mask``).
        """
        c = None if self.coupling is None else self.coupling.serving(CONFIRM_S)
        # the most persistent column's couplings serve always
        coupling = None if c is None else (c, self.K // len(self.coupling.cols))
        return self.unknowns.mask(family, offsets, conservative, coupling, asymmetric,
                                  transmission)

    def _solve(self, G: np.ndarray, b: np.ndarray, mask: np.ndarray, n: int,
               ridge: Optional[float] = None) -> np.ndarray:
        """
        Bounded least squares from the statistics (``layout.Unknowns.solve``).

        ridge : the couplings' (``ridge`` samples' worth of each feature's mean square; None:
        the history's ``self.ridge``, chosen by CV).
        """
        return self.unknowns.solve(G, b, mask, n, getattr(self.basis, 'RIDGE', 0.0),
                                   self.ridge if ridge is None else float(ridge))

    def _sse(self, st: Stats, theta: np.ndarray) -> np.ndarray:
        """Squared error per joint of ``theta`` on ``st`` with the applied columns, (N,)."""
        return self.unknowns.sse(st, theta)

    def candidates(self) -> List[tuple]:
        """Every structure ``(family, offsets, conservative)`` there is to choose from."""
        cons = (False, True) if self.C else (False,)
        offs = (False, True) if self.offsets else (False,)
        return [(f, o, c) for f in FAMILIES for o in offs for c in cons]

    def select(self, current: Optional[str] = None) -> ParametricFit:
        """
        Choose the structure by forward-chaining CV (module docstring) and fit it on all.

        current : the friction family serving now: where couplings serve, another must beat
        it by ``SWITCH_MARGIN`` (the aircraft's family flipped none / viscous / friction
        nearly every second of its first minute, each flip a new prior).
        """
        total = self._total(self._blocks, True)
        scores = {}
        blocks = list(self._blocks)
        folds, at = [], []
        for i in range(len(blocks)):
            train = self._total(blocks[:i], False)
            # a fold trained on a short start extrapolates the pose parts wildly: score only
            # on blocks with at least MIN_TRAIN_FRACTION of the history before them
            if train.n >= MIN_TRAIN_FRACTION * total.n and blocks[i].n:
                folds.append((self._global(train), train.n, blocks[i]))
                at.append(i)
        if folds and total.n > 1:
            var = np.maximum(total.yy / total.n - (total.sy / total.n) ** 2, 1e-12)
            n_test = sum(b.n for *_, b in folds)
            per_joint = {}
            for cand in self.candidates():
                m = self._mask(*cand)
                sse = np.zeros(self.N)
                for (G, b), n, test in folds:
                    sse += self._sse(test, self._solve(G, b, m, n))
                per_joint[cand] = sse / (n_test * var)
                scores[cand] = float(np.mean(per_joint[cand]))
            best = self._choose(scores)
            keep = (current, best[1], best[2])
            if self._coupled() and current in FAMILIES and keep in scores and \
                    scores[keep] <= (1.0 + SWITCH_MARGIN) * scores[best]:
                best = keep
            best = (best[0], self._joint_offsets(per_joint, best), best[2])
            best = best + (self._joint_asymmetry(best, folds, total),)
            best = best + (self._joint_transmissions(best, folds),)
            k = self._memory(best, folds, at, n_test * var)
            if self._coupled():         # the couplings' ridge: the one the CV blocks favour
                self.ridge = min(COUPLING_RIDGES, key=lambda r: self._score(
                    best, folds, at, n_test * var, k, r))
            if k >= 0:
                return self._fit(self._total(self._blocks, True, k), best, scores, total.n, k)
        else:
            # the couplings alone where a column persists (an aircraft's: they carry its forces)
            family = 'none' if self._coupled() or not total.n else self.default_family
            best = (family, False, bool(self.C))
        return self._fit(total, best, scores)

    def _score(self, best: tuple, folds: list, at: list, scale: np.ndarray, memory: int,
               ridge: Optional[float] = None) -> float:
        """Return the CV score of ``best`` learned in ``memory`` (-1: all), couplings' ridge."""
        m, blocks = self._mask(*best), list(self._blocks)
        sse = np.zeros(self.N)
        for ((G, b), n, test), i in zip(folds, at):
            if memory >= 0:                     # the whole history's is the fold's own
                r = self._total(blocks[:i], False, memory)
                (G, b), n = self._global(r), r.n
            sse += self._sse(test, self._solve(G, b, m, n, ridge))
        return float(np.mean(sse / scale))

    def _memory(self, best: tuple, folds: list, at: list, scale: np.ndarray) -> int:
        """
        Return the recent memory that predicts the CV blocks clearly best, -1 for all of it.

        The chosen structure ``best``, fitted on everything before each scored block, on the
        whole history and on each recent one (``HALF_LIVES_S``): the recent memory with the
        lowest mean score serves only where that score is below ``1 - RECENT_MARGIN`` times the
        whole history's (friction that drifts; the couplings of a persistent column follow
        the air's density, +3 % over an approach: no margin). scale (N,): per joint, the scored
        samples times the residual's variance.
        """
        if self._recent[0].n >= 0.999 * self._older.n:
            return -1                           # nothing forgotten yet (the shortest forgets most)
        recent = [self._score(best, folds, at, scale, k) for k in range(len(HALF_LIVES_S))]
        k = int(np.argmin(recent))
        margin = 0.0 if self._coupled() else RECENT_MARGIN
        return k if recent[k] < (1.0 - margin) * self._score(best, folds, at, scale, -1) else -1

    def _coupled(self) -> bool:
        """Tell whether a persistent column's couplings serve (``coupling_track``)."""
        return self.coupling is not None and self.coupling.serving(CONFIRM_S) is not None

    def _choose(self, scores: dict) -> tuple:
        """
        Pick from the CV scores: offsets only on a clear win, then the simplest close one.

        Offsets must beat the best candidate without them by ``OFFSET_MARGIN``; among the
        candidates of the chosen offset setting, the one with the fewest columns within
        ``SIMPLER_MARGIN`` of the best is taken (three folds cannot resolve smaller
        differences; a simpler model extrapolates better).
        """
        free = {c: v for c, v in scores.items() if not c[1]}
        off = {c: v for c, v in scores.items() if c[1]}
        pool = free
        if off and min(off.values()) < (1.0 - OFFSET_MARGIN) * min(free.values()):
            pool = off
        top = min(pool.values())
        close = [c for c, v in pool.items() if v <= (1.0 + SIMPLER_MARGIN) * top]
        return min(close, key=lambda c: (int(self._mask(*c).sum()), pool[c]))

    def fit(self, family: str, offsets, conservative: bool, asymmetric=False,
            transmission=()) -> ParametricFit:
        """Fit one given structure on the whole history (``transmission``: ((a, s), ...))."""
        return self._fit(self._total(self._blocks, True),
                         (family, offsets, conservative, asymmetric, tuple(transmission)), {})

    def refit(self, fit: ParametricFit) -> ParametricFit:
        """
        Refit ``fit``'s structure and memory on the history as it is now (no selection).

        What keeps the couplings of a persistent column current between selections (they
        carry whole forces, and a selection comes only when the history grew by a quarter).
        """
        k = -1 if fit.memory == 'all' else \
            [f'{h:g} s' for h in HALF_LIVES_S].index(fit.memory)
        out = self._fit(self._total(self._blocks, True, k),
                        (fit.family, fit.offsets, fit.conservative,
                         False if fit.asymmetric is None else fit.asymmetric, fit.motors()),
                        fit.scores, None, k)
        out.samples = fit.samples               # the selection's growth counts from its own
        return out

    def _fit(self, total: Stats, cand: tuple, scores: dict, samples=None,
             memory: int = -1) -> ParametricFit:
        """Fit ``cand`` on ``total`` (the whole history, or recent memory ``memory``)."""
        G, b = self._global(total)
        mask = self._mask(*cand)
        theta = self._solve(G, b, mask, total.n)
        N, U = self.N, self.unknowns
        offs = np.broadcast_to(np.asarray(cand[1], bool), (N,)) & \
            (theta[U.off0:U.corr0] != 0.0)
        k0 = U.coup0
        coupling = None
        c = None if self.coupling is None else self.coupling.serving(CONFIRM_S)
        if c is not None and np.any(theta[k0:U.tr0]):
            size = self.K // len(self.coupling.cols)          # the serving column's features
            W = theta[k0:U.tr0].reshape(N, self.K)[:, c * size:(c + 1) * size].copy()
            coupling = (self.coupling.fitted_basis(c), W)
        coef, coef_neg = U.friction(theta)
        asym = np.broadcast_to(np.asarray(cand[3] if len(cand) > 3 else False, bool),
                               (N,)).copy()
        motors = [(a, s, theta[U.motor(a, s)]) for a, s in (cand[4] if len(cand) > 4 else ())]
        motors = [(a, s, c) for a, s, c in motors if np.any(c > 0.0)]
        transmission = None if not motors else (
            tuple((a, a + 1, int(s)) for a, s, _ in motors),
            np.maximum(np.array([c for *_, c in motors]), 0.0))
        return ParametricFit(cand[0], offs, bool(cand[2]), coef,
                             theta[U.off0:U.corr0].copy(), theta[U.corr0:k0].copy(),
                             self.basis, scores, total.n if samples is None else samples,
                             'all' if memory < 0 else f'{HALF_LIVES_S[memory]:g} s',
                             self._element(mask, theta, total, memory), coupling, coef_neg,
                             asym, transmission)

    def _element(self, mask: np.ndarray, theta: np.ndarray, total: Stats,
                 memory: int) -> Optional[ElementFit]:
        """
        Fit each joint's element on what the parametric part ``theta`` leaves (``element``).

        Its cross-validation folds are the structure's (the newest blocks, each with at least
        ``MIN_TRAIN_FRACTION`` of the history before it), each with the parametric part
        ``mask`` refitted on what precedes the block, in the same memory.
        """
        if self.element.basis is None or total.n == 0:
            return None
        blocks = list(self._blocks)
        n_all = self._total(blocks, True).n if memory >= 0 else total.n
        folds = []
        for i, block in enumerate(blocks):
            whole = self._total(blocks[:i], False)
            if whole.n >= MIN_TRAIN_FRACTION * n_all and block.n:
                train = whole if memory < 0 else self._total(blocks[:i], False, memory)
                th = self._solve(*self._global(train), mask, train.n)
                folds.append((train, [th[idx] for idx in self._idx], block))
        return self.element.fit(self.L, self.FE, [theta[idx] for idx in self._idx], total,
                                folds)

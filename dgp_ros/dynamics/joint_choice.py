"""
Per-joint parts of the chosen structure: which joints keep an offset, which a level per direction.

The long history (:mod:`~.history`) chooses one structure for all joints by cross-validation;
these rules then give or withhold a part joint by joint, each on that joint's own evidence: its
score on the newest blocks (forward chaining) and across the two interleaved halves of the run
(each fitted on one half, scored on the other). One joint's score is noisier than the mean over
joints, so a part needs a clear win (:data:`JOINT_OFFSET_MARGIN`). A coupled transmission
between adjacent joints is judged on the pair's evidence (:data:`MOTOR_MARGIN`).

:class:`JointChoice` is a mixin of :class:`~.history.LongHistory`: it reads the history's
``N``, ``asymmetric``, ``element.halves``, ``_idx`` and its ``_mask``, ``_solve``, ``_sse`` and
``_global``, and keeps no state of its own.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from dgp_ros.gp.joint_element import MIN_HALF_SAMPLES

from .parametric import F, FAMILIES
from .statistics import Stats

__all__ = ['JointChoice', 'JOINT_OFFSET_MARGIN', 'ASYM_AGREEMENT', 'MOTOR_MARGIN']

#: a joint keeps its offset only where it cuts that joint's own CV score by this fraction (one
#: joint's score is noisier than the mean over joints that ``OFFSET_MARGIN`` judges)
JOINT_OFFSET_MARGIN = 0.3
#: a joint's friction gets a level per direction only where two halves of the run differ on
#: that part by less than this times the part (they agree on its sign and size)
ASYM_AGREEMENT = 1.0
#: a coupled transmission serves where it cuts its two joints' summed squared error by this
#: fraction, on the newest blocks and across the halves of the run
MOTOR_MARGIN = 0.3


class JointChoice:
    """The per-joint rules of :class:`~.history.LongHistory` (module docstring)."""

    def _joint_offsets(self, per_joint: dict, best: tuple):
        """
        Return which joints of the chosen structure keep an offset, (N,) bools (module doc).

        A joint keeps one where the structure with offsets scores below
        (1 - JOINT_OFFSET_MARGIN) x the same structure's score without them, on that joint: on
        the newest blocks, or across the two halves of the run (each fitted on one half and
        scored on the other: the whole run's evidence, where the newest blocks may hold the
        joint moving one way only) and no worse on the newest blocks. While a half holds fewer
        than ``MIN_HALF_SAMPLES``, a structure chosen with offsets keeps them on every joint:
        the newest blocks cannot tell an offset from a joint that moved one way there (the
        real Panda at 30 Hz, 217 samples: its sixth joint turned mostly one way, then the other,
        and the part held out needed the offset the newest blocks refused).
        """
        family, _, cons = best
        with_ = per_joint.get((family, True, cons))
        without = per_joint.get((family, False, cons))
        if with_ is None or without is None:
            return np.zeros(self.N, bool)
        forward = with_ < (1.0 - JOINT_OFFSET_MARGIN) * without
        across = self._across((family, True, cons), (family, False, cons))
        if across is None:
            # too few samples for the halves: the newest blocks alone cannot tell an offset
            # from a joint that moved mostly one way there, so the structure's choice, made on
            # every block, stands (offsets on each joint where it chose them)
            return np.ones(self.N, bool) if best[1] else forward
        # no worse on the newest blocks (equal where the offset was no part of any fold)
        return forward | ((across[0] < (1.0 - JOINT_OFFSET_MARGIN) * across[1]) &
                          (with_ <= (1.0 + 1e-9) * without))

    def _across(self, *cands, grams: Optional[list] = None) -> Optional[List[np.ndarray]]:
        """
        Return each candidate's squared error per joint across the halves of the run, (N,).

        Fitted on each half and scored on the other; None while a half holds fewer than
        ``MIN_HALF_SAMPLES`` samples. ``grams``: the halves' ``_global`` where the caller scores
        many candidates (built here otherwise).
        """
        halves = self.element.halves
        if min(h.n for h in halves) < MIN_HALF_SAMPLES:
            return None
        G = [self._global(h) for h in halves] if grams is None else grams
        out = []
        for cand in cands:
            m = self._mask(*cand)
            out.append(sum(self._sse(halves[1 - k], self._solve(*G[k], m, halves[k].n))
                           for k in (0, 1)))
        return out

    def _joint_asymmetry(self, best: tuple, folds: list, total: Stats) -> np.ndarray:
        """
        Return which joints of the chosen structure get a friction per direction, (N,) bools.

        Like an offset (with which a direction's extra level is confounded on a joint that moved
        mostly one way), an extra part of one joint needs a clear win on that joint's own noisy
        score: the structure with every joint asymmetric must score below
        (1 - JOINT_OFFSET_MARGIN) x the symmetric one on that joint and lower on each scored
        block. And the two interleaved halves of the run, each of at least the element's
        ``MIN_HALF_SAMPLES``, must differ on it by less than ``ASYM_AGREEMENT`` times the part
        itself: a level per direction learned on a short start, where the joint passed its poses
        one way each, is the pose's load, not the direction's friction, and is wrong on the
        next motion.
        """
        none = np.zeros(self.N, bool)
        halves = self.element.halves
        if not self.asymmetric or not FAMILIES[best[0]] or \
                min(h.n for h in halves) < MIN_HALF_SAMPLES:
            return none
        per = []
        for asym in (False, True):
            m = self._mask(*best[:3], asym)
            per.append(np.array([self._sse(test, self._solve(G, b, m, n))
                                 for (G, b), n, test in folds]))        # (folds, N)
        win = (per[1].sum(axis=0) < (1.0 - JOINT_OFFSET_MARGIN) * per[0].sum(axis=0)) & \
            np.all(per[1] < per[0], axis=0)
        if not win.any():
            return none
        m = self._mask(*best[:3], True)
        full = self._solve(*self._global(total), m, total.n)
        th = [self._solve(*self._global(h), m, h.n) for h in halves]
        out = none.copy()
        for j in np.flatnonzero(win):
            e = self._idx[j][F:2 * F]                   # the joint's even (asymmetric) part
            G = total.Gt[j][F:2 * F, F:2 * F]
            d, w = th[0][e] - th[1][e], full[e]
            out[j] = d @ G @ d < ASYM_AGREEMENT ** 2 * max(w @ G @ w, 1e-300)
        return out

    def _joint_transmissions(self, best: tuple, folds: list) -> tuple:
        """
        Return the coupled transmissions that serve, ((a, s), ...) each on ``qd_a + s qd_{a+1}``.

        A motor shared by joints a and a + 1 (``gp.transmission``) serves where, added to the
        chosen structure ``best``, it cuts the pair's summed squared error by ``MOTOR_MARGIN``
        and neither joint's grows, both on the newest blocks (``folds``: each fitted on everything
        before it) and across the two interleaved halves of the run (each of at least
        ``MIN_HALF_SAMPLES``): a motor that one stretch of the run shows and the other does not
        is a pose's load. Where candidates share a joint, the one with the larger cut serves.
        A simulated wrist whose one motor drives its last two joints: that pair found on two arms
        and two seeds each, no motor on the same arms without it (``bench/coupled_wrist.py``).
        """
        halves = self.element.halves
        if not self.TC or not folds or min(h.n for h in halves) < MIN_HALF_SAMPLES:
            return ()

        grams = [self._global(h) for h in halves]       # once for every candidate

        def newest(motors):
            m = self._mask(*best[:4], motors)
            return sum(self._sse(test, self._solve(G, b, m, n)) for (G, b), n, test in folds)

        def across(motors):
            return self._across(best[:4] + (motors,), grams=grams)[0]
        scores = [(newest, newest(())), (across, across(()))]
        wins = []
        for a in range(self.N - 1):
            pair = [a, a + 1]
            for s in (1, -1):
                ratio = 0.0
                for score, e0 in scores:         # the halves only where the newest blocks win
                    e = score(((a, s),))
                    if not (e[pair].sum() < (1.0 - MOTOR_MARGIN) * e0[pair].sum() and
                            np.all(e[pair] <= e0[pair])):
                        break
                    ratio = max(ratio, e[pair].sum() / e0[pair].sum())
                else:
                    wins.append((ratio, a, s))
        out, used = [], set()
        for _, a, s in sorted(wins):
            if a not in used and a + 1 not in used:
                out.append((a, s))
                used.update((a, a + 1))
        return tuple(sorted(out))

"""
The blend of a damping answer toward its fallback, by earned gains: guarantees kept.

The online learner scores every answer one step ahead (``dgp_ros.online.grounds``) and keeps per
joint the model's weight ``w`` over the fallback ``a m_d(qd) qd`` (the passive prior times its
own gain ``a``), both in [0, 1]. A saved model carries them (``grounds_``), so that a model file
answers, in any process, as the node that learned it answered: where the model had not earned
its weight, toward what had.

With ``S = diag(sqrt(w))`` and ``F = diag((1 - w) a m_d(qd))`` the blended damping matrix is
``D' = S D S + F``. Where ``D``'s symmetric part is positive semi-definite (guarantee ``psd``)
so is ``D'`` (a congruence plus a non-negative diagonal); a diagonal ``D`` blends joint by joint,
``tau'_j = w_j tau_j + (1 - w_j) a_j p_j``. Under the other guarantees (a domain proof, a
projection: they hold for ``q^T D(q) q`` only) one scalar ``w = min_j w_j`` blends
``D' = w D + (1 - w) diag(a m_d)``: a convex combination of two passive answers.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ['blend', 'Grounds', 'GAINS']

#: the gains a model carries, in this order (``grounds_`` keys; the online learner's ``Skill``)
GAINS = ('model_weight', 'prior_gain', 'confidence')


def blend(Q: np.ndarray, tau: np.ndarray, D: Optional[np.ndarray], prior_diag: np.ndarray,
          w: np.ndarray, a: np.ndarray, per_joint: bool):
    """
    Blend answers toward the fallback (module docstring).

    Q, tau : (k, N) velocities and the model's answers; D : (k, N, N) its damping matrices (None:
    not computed; then ``per_joint`` must be False); prior_diag : (k, N) ``m_d(Q)`` >= 0; w, a :
    (N,) the model's weight and the prior's gain. ``per_joint``: the congruence blend (keeps a
    PSD symmetric part), else one scalar ``min(w)`` per answer (keeps ``q^T tau >= 0`` of a
    passive answer). Returns (tau', D' or None).
    """
    if per_joint and D is not None:
        s = np.sqrt(w)
        Db = D * (s[:, None] * s[None, :])
        idx = np.arange(Q.shape[1])
        Db[:, idx, idx] += prior_diag * ((1.0 - w) * a)
        return np.einsum('kij,kj->ki', Db, Q), Db
    ws = float(np.min(w))
    f = (1.0 - ws) * a * prior_diag                        # (k, N)
    tau_b = ws * tau + f * Q
    Db = None
    if D is not None:
        Db = ws * D
        idx = np.arange(Q.shape[1])
        Db[:, idx, idx] += f
    return tau_b, Db


class Grounds:
    """
    The earned gains of a model, as it applies them to its answers (module docstring).

    ``Grounds.of(record, N)``: from a model's ``grounds_`` record (``GAINS`` -> N numbers
    each), None when there is none or the model weight is 1 everywhere (nothing to blend).
    ``per_joint(guarantee)``: whether the congruence blend applies (guarantee ``psd``).
    """

    def __init__(self, w: np.ndarray, a: np.ndarray):
        self.w = np.clip(np.asarray(w, float), 0.0, 1.0)
        self.a = np.clip(np.asarray(a, float), 0.0, 1.0)

    @classmethod
    def of(cls, record: Optional[dict], N: int) -> Optional['Grounds']:
        if not record:
            return None
        try:
            w = np.asarray(record['model_weight'], float)
            a = np.asarray(record['prior_gain'], float)
        except (KeyError, TypeError, ValueError):
            raise ValueError('grounds: needs model_weight and prior_gain, N numbers each') \
                from None
        if w.shape != (N,) or a.shape != (N,) or not (np.all(np.isfinite(w)) and
                                                      np.all(np.isfinite(a))):
            raise ValueError(f'grounds: model_weight and prior_gain must be {N} finite numbers')
        g = cls(w, a)
        return None if bool(np.all(g.w >= 1.0)) else g

    @staticmethod
    def per_joint(guarantee: str) -> bool:
        return guarantee == 'psd'

    def apply(self, mean, Q: np.ndarray, tau: np.ndarray, D: Optional[np.ndarray],
              guarantee: str):
        """Blend (tau, D) at Q (k, N) toward ``a mean.diag(Q) Q``; returns (tau', D')."""
        dg = np.asarray(mean.diag(Q), float)
        return blend(Q, tau, D, dg, self.w, self.a,
                     self.per_joint(guarantee) and D is not None)

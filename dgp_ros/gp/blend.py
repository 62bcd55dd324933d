"""
The blend of a damping answer toward its fallback, by earned gains: guarantees kept.

The online learner scores every answer one step ahead (``online.learner.grounds``) and keeps per
joint the model's weight ``w`` over the fallback ``a m_d(qd) qd`` (the passive prior times its
own gain ``a``), both in [0, 1]. A saved model carries them (``grounds_``), so that a model file
answers, in any process, as the node that learned it answered: where the model had not earned
its weight, toward what had.

With ``S = diag(sqrt(w))`` and ``F = diag((1 - w) a m_d(qd))`` the blended damping matrix is
``D' = S D S + F``. Where ``D``'s symmetric part is positive semi-definite (guarantee ``psd``)
so is ``D'`` (a congruence plus a non-negative diagonal; over a prior that is its diagonal plus a
PSD part, a transmission, ``F = R M R`` with ``R = diag(sqrt((1 - w) a))``, PSD as well); a
diagonal ``D`` blends joint by joint,
``tau'_j = w_j tau_j + (1 - w_j) a_j p_j``. Under the other guarantees (a domain proof, a
projection: they hold for ``q^T D(q) q`` only) one scalar ``w = min_j w_j`` blends
``D' = w D + (1 - w) diag(a m_d)``: a convex combination of two passive answers.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ['blend', 'prior_answer', 'Grounds', 'GAINS']

#: the gains a model carries, in this order (``grounds_`` keys; the online learner's ``Skill``)
GAINS = ('model_weight', 'prior_gain', 'confidence')


def prior_answer(mean, Q: np.ndarray, a: Optional[np.ndarray] = None, want_D: bool = False):
    """
    Return (tau (k, N), D (k, N, N) or None): the fallback, the prior ``mean`` times its gains.

    a : (N,) gains in [0, 1] (None: 1). A diagonal prior gives ``diag(a m_d(Q)) Q``; one that is
    its diagonal plus a PSD part (a transmission, ``psd_over_diagonal``) the congruence
    ``R M(Q) R Q``, ``R = diag(sqrt(a))`` (the same where M is diagonal; PSD either way); a
    coupled one (``gp.coupled``) ``a * force`` row by row, projected onto ``q^T tau >= 0`` where
    the gains made it non-passive (its matrix gets the projection's ``lam I``): passive always.
    """
    Q = np.asarray(Q, float)
    if mean.is_diagonal:
        d = np.asarray(mean.diag(Q), float)
        if a is not None:
            d = d * a
        D = None
        if want_D:
            D = np.zeros(d.shape + (d.shape[-1],))
            D[:, np.arange(d.shape[-1]), np.arange(d.shape[-1])] = d
        return d * Q, D
    if mean.psd_over_diagonal:
        if a is None:
            return np.asarray(mean.force(Q), float), \
                (np.asarray(mean.matrix(Q), float) if want_D else None)
        r = np.sqrt(a)
        D = np.asarray(mean.matrix(Q), float) * (r[:, None] * r[None, :])
        return np.einsum('kij,kj->ki', D, Q), (D if want_D else None)
    from .policy import project_passive, projection_lambda
    tau = np.asarray(mean.force(Q), float)
    D = np.asarray(mean.matrix(Q), float) if want_D else None
    if a is not None:
        tau = tau * a
        lam = projection_lambda(Q, tau)
        tau = project_passive(Q, tau)
        if D is not None:
            D = D * a[:, None]
            D[:, np.arange(Q.shape[1]), np.arange(Q.shape[1])] += lam[:, None]
    return tau, D


def blend(Q: np.ndarray, tau: np.ndarray, D: Optional[np.ndarray], mean,
          w: np.ndarray, a: np.ndarray, per_joint: bool,
          prior_diag: Optional[np.ndarray] = None, prior_matrix: Optional[np.ndarray] = None):
    """
    Blend answers toward the fallback (module docstring).

    Q, tau : (k, N) velocities and the model's answers; D : (k, N, N) its damping matrices (None:
    not computed; then ``per_joint`` must be False); mean : the passive prior; w, a : (N,) the
    model's weight and the prior's gain. ``per_joint``: the congruence blend (keeps a PSD
    symmetric part; a diagonal prior only), else one scalar ``min(w)`` per answer (keeps
    ``q^T tau >= 0`` of a passive answer). ``prior_diag`` : (k, N) ``mean.diag(Q)`` where the
    caller has it already (a diagonal prior; the message path computes it once per answer);
    ``prior_matrix`` : (k, N, N) ``mean.matrix(Q)`` likewise (a diagonal-plus-PSD prior).
    Returns (tau', D' or None).
    """
    if not mean.is_diagonal and per_joint and D is not None and mean.psd_over_diagonal:
        # the congruence with the prior's whole matrix: S D S + R M R, R = diag(sqrt((1-w) a))
        s, r = np.sqrt(w), np.sqrt((1.0 - w) * a)
        M = np.asarray(mean.matrix(Q) if prior_matrix is None else prior_matrix, float)
        Db = D * (s[:, None] * s[None, :]) + M * (r[:, None] * r[None, :])
        return np.einsum('kij,kj->ki', Db, Q), Db
    if not mean.is_diagonal:
        # joint by joint, then projected: a coupled prior carries whole forces (an aircraft's
        # lift), and one scalar min(w) let a side force's weight of 0.1 pull the lift's answer
        # toward its fallback
        from .policy import project_passive, projection_lambda
        tp, Dp = prior_answer(mean, Q, a, D is not None)
        tb = w * tau + (1.0 - w) * tp
        Db = None
        if D is not None:
            lam = projection_lambda(Q, tb)
            Db = w[:, None] * D + (1.0 - w)[:, None] * Dp
            Db[:, np.arange(Q.shape[1]), np.arange(Q.shape[1])] += lam[:, None]
        return project_passive(Q, tb), Db
    if prior_diag is None:
        prior_diag = np.asarray(mean.diag(Q), float)
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
        """Blend (tau, D) at Q (k, N) toward ``a mean(Q)`` (``prior_answer``); (tau', D')."""
        return blend(Q, tau, D, mean, self.w, self.a,
                     self.per_joint(guarantee) and D is not None)

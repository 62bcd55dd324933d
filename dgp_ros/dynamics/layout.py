"""
The parametric part's unknowns over all joints, and their bounded least-squares solve.

The long history (:mod:`~.history`) keeps, per joint, the statistics of its local columns

    [friction F odd (then, on an arm, their F even twins |col|), offset 1, correction C,
     couplings K, transmissions TC]

(:mod:`~.parametric`); the unknowns of every joint are solved together because the correction
of the rigid-body model and a coupled transmission's motor are shared. :class:`Unknowns` lays
them out, says which columns a structure uses (``mask``), and solves from the statistics with
the friction kept passive:

* a **symmetric** family uses the odd columns with non-negative coefficients;
* an **asymmetric** joint (its family's even twins too) fits ``a_k f_k + b_k |f_k|``,
  solved as the coefficients of the column's positive and negative parts,
  ``c+ = a + b >= 0`` and ``c- = a - b >= 0`` (``f = f+ + f-``, ``|f| = f+ - f-``): each
  direction of motion its own Coulomb and viscous levels, each passive;
* a **transmission** between adjacent joints a, a + 1 (on an arm: ``transmissions``) is one
  motor turning at ``m = qd_a + s qd_{a+1}`` (``gp.transmission``): its non-negative Coulomb and
  viscous coefficients are shared by both joints, whose local columns are ``phi(m)`` and
  ``s phi(m)``. Joint j's TC = 8 local columns are the motors of pairs (j - 1, j) and (j, j + 1),
  each sign; the unknowns are laid out per pair ``p`` = 0..N (pair p joins joints p - 1 and p;
  pairs 0 and N have no second joint: their columns are zero and never masked).

No rclpy.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from dgp_ros.gp.transmission import FEATURES, motor_columns

from .parametric import F, FAMILIES
from .statistics import nonnegative_part

__all__ = ['Unknowns', 'REVERSAL', 'transmission_columns', 'TC']

#: an offset is identifiable once a joint's mean sign of velocity is within this of zero
REVERSAL = 0.8
#: a joint's transmission columns: two pairs, two signs, the motor's features
TC = 2 * 2 * FEATURES
_SIGNS = np.array([1.0, -1.0])


def transmission_columns(V: np.ndarray) -> np.ndarray:
    """
    Return every joint's transmission columns at velocities V (k, N): (k, N, TC).

    Joint j's: ``s phi(qd_{j-1} + s qd_j)`` for s = +1, -1 (zero for j = 0), then
    ``phi(qd_j + s qd_{j+1})`` (zero for the last joint); ``phi`` = ``gp.transmission``'s
    ``motor_columns``.
    """
    V = np.asarray(V, float)
    k, N = V.shape
    out = np.zeros((k, N, TC))
    if N < 2:
        return out
    phi = motor_columns(V[:, :-1, None] + _SIGNS * V[:, 1:, None])     # (k, N - 1, 2, FEAT)
    h = 2 * FEATURES
    out[:, 1:, :h] = (_SIGNS[:, None] * phi).reshape(k, N - 1, h)
    out[:, :-1, h:] = phi.reshape(k, N - 1, h)
    return out


class Unknowns:
    """
    The unknowns of N joints (module docstring).

    Per joint ``2F`` friction coefficients (odd, even), then the offsets, the shared correction
    (C), the couplings (K per joint) and with ``transmissions`` the motors (2 x FEATURES per
    pair 0..N). ``idx[j]`` lists joint j's unknowns in the order of its local statistics'
    columns.
    """

    def __init__(self, N: int, C: int, K: int, even: bool = True, transmissions: bool = False):
        self.N, self.C, self.K = int(N), int(C), int(K)
        self.even = bool(even)
        #: transmission columns per joint (0: none)
        self.TC = TC if transmissions and self.N >= 2 else 0
        #: friction columns per joint: the odd ones, and with ``even`` their twins
        self.FE = FE = 2 * F if self.even else F
        N = self.N
        self.off0 = N * FE
        self.corr0 = self.off0 + N
        self.coup0 = self.corr0 + self.C
        self.tr0 = self.coup0 + N * self.K
        self.P = self.tr0 + ((N + 1) * self.TC // 2 if self.TC else 0)
        twins = (lambda j: N * F + np.arange(j * F, (j + 1) * F)) if self.even else \
            (lambda j: np.zeros(0, int))
        self.idx = [np.r_[np.arange(j * F, (j + 1) * F), twins(j),
                          self.off0 + j, self.corr0 + np.arange(self.C),
                          self.coup0 + j * self.K + np.arange(self.K),
                          self.tr0 + j * self.TC // 2 + np.arange(self.TC)] for j in range(N)]
        #: the local column count of the parametric part
        self.L = FE + 1 + self.C + self.K + self.TC

    def motor(self, a: int, s: int) -> np.ndarray:
        """Return the unknowns of the motor on ``qd_a + s qd_{a+1}`` (FEATURES,)."""
        if not self.TC or not 0 <= a < self.N - 1:
            raise ValueError(f'no transmission between joints {a} and {a + 1}')
        return self.tr0 + (a + 1) * self.TC // 2 + (0 if s > 0 else FEATURES) + \
            np.arange(FEATURES)

    def mask(self, family: str, offsets, conservative: bool,
             coupling: Optional[Tuple[int, int]] = None, asymmetric=False,
             transmission=()) -> np.ndarray:
        """
        Return the unknowns of a structure, (P,) bools.

        offsets, asymmetric : a bool or (N,) bools; coupling : (serving column, features per
        column) of the couplings that serve, or None; transmission : the motors that serve,
        ((a, s), ...) each on ``qd_a + s qd_{a+1}``.
        """
        m = np.zeros(self.P, bool)
        cols = np.asarray(FAMILIES[family], int)
        offs = np.broadcast_to(np.asarray(offsets, bool), (self.N,))
        asym = np.broadcast_to(np.asarray(asymmetric, bool), (self.N,))
        for j in range(self.N):
            m[self.idx[j][cols]] = True
            if asym[j] and self.even:
                m[self.idx[j][F + cols]] = True
            m[self.off0 + j] = offs[j]
        if conservative and self.C:
            m[self.corr0:self.coup0] = True
        if coupling is not None:
            c, size = coupling
            for j in range(self.N):
                m[self.coup0 + j * self.K + c * size + np.arange(size)] = True
        for a, s in transmission:
            m[self.motor(a, s)] = True
        return m

    def identifiable(self, G: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """
        Return ``mask`` without the offsets of joints that have not moved both ways.

        While a joint has moved one way only, its Coulomb columns equal a constant on the data
        and its offset is not identifiable: least squares then trades a huge friction against a
        huge offset (a UR10's wrist 2, 3.5 s into its stream: +490 N m of Coulomb friction,
        -485 N m of offset). An offset needs at least ``(1 - REVERSAL) / 2`` of the samples on
        each side (from the Gram matrix: the mean of the sharpest Coulomb column).
        """
        mask = mask.copy()
        for j in range(self.N):
            k = self.off0 + j
            if mask[k] and G[k, k] > 0 and abs(G[k, self.idx[j][1]]) > REVERSAL * G[k, k]:
                mask[k] = False
        return mask

    def gram(self, st) -> Tuple[np.ndarray, np.ndarray]:
        """Return the global normal equations (P, P), (P,) of ``st`` (training columns)."""
        G = np.zeros((self.P, self.P))
        b = np.zeros(self.P)
        L = self.L
        for j, idx in enumerate(self.idx):
            G[np.ix_(idx, idx)] += st.Gt[j][:L, :L]
            b[idx] += st.bt[j][:L]
        return G, b

    def sse(self, st, theta: np.ndarray) -> np.ndarray:
        """Squared error per joint of ``theta`` on ``st`` with the applied columns, (N,)."""
        out = np.empty(self.N)
        L = self.L
        for j, idx in enumerate(self.idx):
            t = theta[idx]
            out[j] = st.yy[j] - 2.0 * t @ st.bd[j][:L] + t @ st.Gd[j][:L, :L] @ t
        return np.maximum(out, 0.0)

    def solve(self, G: np.ndarray, b: np.ndarray, mask: np.ndarray, n: int,
              corr_ridge: float = 0.0, coupling_ridge: float = 0.0) -> np.ndarray:
        """
        Bounded least squares from the normal equations: friction passive, the rest free.

        corr_ridge : the correction's ridge ((N m per unit)^2, the basis'); coupling_ridge : the
        couplings' (that many samples' worth of each feature's mean square; not on the constant
        feature of each column).
        """
        theta = np.zeros(self.P)
        idx = np.flatnonzero(self.identifiable(G, mask))
        if idx.size == 0 or n == 0:
            return theta
        # an asymmetric pair (odd k, even k) solved as its positive and negative parts
        odd = idx[idx < self.N * F]
        pairs = odd[np.isin(odd + self.N * F, idx)] if self.even else odd[:0]
        Gs, bs, T = G[np.ix_(idx, idx)].copy(), b[idx], None
        if pairs.size:
            T = np.eye(idx.size)
            po = np.searchsorted(idx, pairs)
            pe = np.searchsorted(idx, pairs + self.N * F)
            T[po, po], T[po, pe], T[pe, po], T[pe, pe] = 0.5, 0.5, 0.5, -0.5
            Gs, bs = T.T @ Gs @ T, T.T @ bs
        ridge = np.zeros(idx.size)
        ridge[(idx >= self.corr0) & (idx < self.coup0)] = corr_ridge
        d = np.diag(Gs).copy()
        is_k = (idx >= self.coup0) & (idx < self.tr0)
        if is_k.any():          # the couplings; not the constant feature
            first = (idx - self.coup0) % max(self.K, 1) == 0
            ridge[is_k & ~first] = coupling_ridge * d[is_k & ~first] / max(n, 1)
        dn = d[~is_k]
        Gs[np.diag_indices_from(Gs)] += ridge + 1e-9 * d + 1e-12 * (
            (dn.mean() if dn.size else 0.0) + 1e-300)
        bounded = (idx < self.off0) | (idx >= self.tr0)      # friction and motors: passive
        x = cho_solve(cho_factor(Gs), bs)
        if np.any(x[bounded] < 0.0):
            x = nonnegative_part(Gs, bs, bounded)
        theta[idx] = x if T is None else T @ x
        return theta

    def friction(self, theta: np.ndarray):
        """
        Return the friction of ``theta``: coef (N, F) for v >= 0, and coef_neg.

        coef_neg (N, F) is for v < 0, None where no joint is asymmetric; each >= 0.
        """
        N = self.N
        a = theta[:N * F].reshape(N, F)
        b = theta[N * F:2 * N * F].reshape(N, F) if self.even else np.zeros((N, F))
        if not np.any(b):
            return np.maximum(a, 0.0), None
        return np.maximum(a + b, 0.0), np.maximum(a - b, 0.0)

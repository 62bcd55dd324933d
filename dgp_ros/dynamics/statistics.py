"""
Sufficient statistics of a per-joint linear least-squares problem, and the bounded solve.

What the long history (:mod:`~dgp_ros.dynamics.history`) keeps of every sample: per joint the
Gram matrix of its columns and their product with the residual, in blocks that add up (and a
recent memory, where older blocks are decayed); and the least-squares solution from them with
the friction coefficients kept non-negative (passive). No rclpy.
"""
from __future__ import annotations

import copy

import numpy as np
from scipy.linalg import cho_factor, cho_solve, cholesky, solve_triangular
from scipy.optimize import nnls

__all__ = ['Stats', 'nonnegative_part']


def nonnegative_part(G: np.ndarray, b: np.ndarray, bounded: np.ndarray) -> np.ndarray:
    """
    Minimize ``x^T G x / 2 - b^T x`` with ``x[bounded] >= 0``, the rest free; G (P, P) PD.

    The free variables are eliminated (their optimum given the bounded ones, a Schur
    complement), and what remains is a non-negative least-squares problem in the bounded ones
    alone (``scipy.optimize.nnls``, Lawson-Hanson): a few ms where a bounded solver over every
    column (a potential basis of ~100 columns) took a quarter of a second per fit.
    """
    c, f = np.flatnonzero(bounded), np.flatnonzero(~bounded)
    x = np.zeros(b.size)
    if f.size:
        cf = cho_factor(G[np.ix_(f, f)])
        W = cho_solve(cf, G[np.ix_(f, c)])                      # G_ff^-1 G_fc
        S = G[np.ix_(c, c)] - G[np.ix_(c, f)] @ W
        r = b[c] - W.T @ b[f]
    else:
        S, r = G[np.ix_(c, c)], b[c]
    L = cholesky((S + S.T) / 2.0, lower=True)
    x[c] = nnls(L.T, solve_triangular(L, r, lower=True), maxiter=50 * c.size)[0]
    if f.size:
        x[f] = cho_solve(cf, b[f] - G[np.ix_(f, c)] @ x[c])
    return x


class Stats:
    """Per-joint sufficient statistics over local columns [friction F, offset 1, correction C]."""

    def __init__(self, N: int, L: int):
        self.Gt = np.zeros((N, L, L))       # training columns
        self.bt = np.zeros((N, L))
        self.Gd = np.zeros((N, L, L))       # applied columns (scoring)
        self.bd = np.zeros((N, L))
        self.yy = np.zeros(N)
        self.sy = np.zeros(N)
        self.n = 0

    def add_rows(self, At: np.ndarray, Ad: np.ndarray, y: np.ndarray) -> None:
        """Add k samples: At, Ad (k, N, L), y (k, N)."""
        # batched matrix products per joint (BLAS): einsum's loops took 7 ms per 64 rows
        y3 = y.T[:, :, None]                                  # (N, k, 1)
        AtT = At.transpose(1, 2, 0)                           # (N, L, k)
        self.Gt += AtT @ At.transpose(1, 0, 2)
        self.bt += (AtT @ y3)[..., 0]
        if Ad is At:
            self.Gd, self.bd = self.Gt, self.bt
        else:
            if self.Gd is self.Gt:
                self.Gd, self.bd = self.Gt.copy(), self.bt.copy()
            AdT = Ad.transpose(1, 2, 0)
            self.Gd += AdT @ Ad.transpose(1, 0, 2)
            self.bd += (AdT @ y3)[..., 0]
        self.yy += np.einsum('kn,kn->n', y, y)
        self.sy += y.sum(axis=0)
        self.n += y.shape[0]

    def decay(self, lam: float) -> None:
        """Weigh every sample so far by ``lam`` (0 < lam <= 1; ``n`` becomes a weight)."""
        shared = self.Gd is self.Gt
        self.Gt *= lam
        self.bt *= lam
        if not shared:
            self.Gd *= lam
            self.bd *= lam
        self.yy *= lam
        self.sy *= lam
        self.n *= lam

    def __iadd__(self, o: 'Stats') -> 'Stats':
        shared = self.Gd is self.Gt
        self.Gt += o.Gt
        self.bt += o.bt
        if not shared:
            self.Gd += o.Gd
            self.bd += o.bd
        self.yy += o.yy
        self.sy += o.sy
        self.n += o.n
        return self

    def copy(self) -> 'Stats':
        c = copy.copy(self)
        c.Gt, c.bt, c.yy, c.sy = self.Gt.copy(), self.bt.copy(), self.yy.copy(), self.sy.copy()
        if self.Gd is self.Gt:
            c.Gd, c.bd = c.Gt, c.bt
        else:
            c.Gd, c.bd = self.Gd.copy(), self.bd.copy()
        return c

    def drop(self, cols: np.ndarray) -> None:
        """Delete local columns ``cols`` (the others' statistics are unchanged: exact)."""
        shared = self.Gd is self.Gt
        self.Gt = np.delete(np.delete(self.Gt, cols, axis=1), cols, axis=2)
        self.bt = np.delete(self.bt, cols, axis=1)
        if shared:
            self.Gd, self.bd = self.Gt, self.bt
        else:
            self.Gd = np.delete(np.delete(self.Gd, cols, axis=1), cols, axis=2)
            self.bd = np.delete(self.bd, cols, axis=1)

    # ------------------------------------------------------------------ the element's part
    def element_train(self, j: int, theta: np.ndarray, L: int, cols: np.ndarray, offset: int):
        """
        Joint j's element equations on what ``theta`` leaves: ``ElementFold`` (no test part).

        ``cols``: the element's columns (past the first ``L``, the parametric ones:
        ``gp.joint_element``); column ``offset`` is the constant one, the element fit's
        nuisance offset. theta : (L,) the joint's parametric coefficients (training columns).
        """
        from dgp_ros.gp.joint_element import ElementFold
        G, b = self.Gt[j], self.bt[j]
        idx = np.r_[cols, offset]
        r = b[idx] - G[idx, :L] @ theta
        return ElementFold(G[np.ix_(idx, idx)].copy(), r)

    def element_test(self, j: int, theta: np.ndarray, L: int, cols: np.ndarray) -> tuple:
        """Joint j's scoring part of a block: (PhiPhi, Phi y, y y) on what ``theta`` leaves."""
        G, b = self.Gd[j], self.bd[j]
        yy = self.yy[j] - 2.0 * theta @ b[:L] + theta @ G[:L, :L] @ theta
        return G[np.ix_(cols, cols)].copy(), b[cols] - G[cols, :L] @ theta, max(float(yy), 0.0)

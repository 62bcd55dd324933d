"""
Friction priors of the damping force: Coulomb + viscous (+ Stribeck) per joint, passive.

* :class:`FrictionMean` -- ``m_d(v) v = F_v v + F_c tanh(v / eps) + F_s tanh(v / eps)
  exp(-(v / v_s)^2)`` with ``F >= 0`` (non-negative least squares), so ``m_d(v) >= 0`` and it is
  even and non-increasing in ``|v|``: its range over a box is read off the box corners nearest to
  and farthest from 0. The smoothing scales ``eps`` and ``v_s`` are chosen per joint from a small
  grid by the residual.
* :class:`BasisFrictionMean` -- the same family with several Coulomb scales and coefficients
  fitted elsewhere (the online learner's long history), optionally one set per direction of
  motion.

Velocities ``Qd`` (k, N), forces (k, N), in model units.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.optimize import lsq_linear

from .prior_mean import PriorMean

__all__ = ['FrictionMean', 'BasisFrictionMean']


def _tanh_over(v: np.ndarray, eps: np.ndarray) -> np.ndarray:
    """``tanh(v / eps) / v``, continuous at 0 (``1 / eps``); even, decreasing in ``|v|``."""
    a = np.abs(v)
    limit = 1e-6 * np.max(eps) if np.size(eps) else 0.0
    if limit > 0.0 and a.size and a.min() >= limit:
        # no speed is small (the usual case, every answer of the message path): the same
        # numbers as below, without the masks
        return np.tanh(a / eps) / a
    small = a < 1e-6 * eps
    with np.errstate(invalid='ignore', divide='ignore'):
        out = np.tanh(a / eps) / np.where(small, 1.0, a)
    return np.where(small, 1.0 / eps * np.ones_like(a), out)


def _friction_diag(a: np.ndarray, coef: np.ndarray, eps: np.ndarray,
                   vs: np.ndarray) -> np.ndarray:
    """
    ``m_d`` of smoothed Coulomb + viscous + Stribeck friction at speeds ``a = |v|`` (..., N).

    ``m_d(a) = F_v + sum_k F_k t(a, eps_k) + sum_s S_s t(a, eps_S) exp(-(a / vs_s)^2)`` with
    ``t(a, e) = tanh(a / e) / a``. coef (N, 1 + K + S): ``[F_v, F_1..F_K, S_1..S_S]`` (or
    (..., N, 1 + K + S): a joint's coefficients per query); eps
    (K + 1,) or (N, K + 1): the Coulomb smoothing velocities, then the Stribeck one ``eps_S``;
    vs (S,) or (N, S): the Stribeck velocities. Every ``t`` comes from one vectorized call (the
    message path evaluates this for every answer); the terms are added one at a time in this
    order, so the result is the same to the bit as adding them in a loop.
    """
    K = eps.shape[-1] - 1
    S = vs.shape[-1]
    out = np.zeros_like(a) + coef[..., 0]
    if K == 0 and not S:
        return out
    T = _tanh_over(a[..., None], eps)                                 # (..., N, K + 1)
    terms = coef[..., 1:1 + K] * T[..., :K]                            # each product once
    for k in range(K):
        out += terms[..., k]
    if S:
        G = np.exp(-(a[..., None] / vs) ** 2)                           # (..., N, S)
        terms = coef[..., 1 + K:1 + K + S] * T[..., K:K + 1] * G       # (c t) g, as written
        for s in range(S):
            out += terms[..., s]
    return out


class _SpeedDiag(PriorMean):
    """
    A prior whose diagonal depends on the speed ``|v|`` only and falls with it to ``coef[:, 0]``.

    Subclasses give ``_diag_at(a)`` (speeds ``a`` (..., N) -> ``m_d`` (..., N)) and ``coef``
    (N, k) with the viscous coefficient first: the diagonal, its bounds over a box and its infimum
    follow from them.
    """

    def diag(self, Qd):
        return self._diag_at(np.abs(Qd))

    def diag_bounds(self, lo, hi):
        amax = np.maximum(np.abs(lo), np.abs(hi))
        amin = np.where((lo <= 0) & (hi >= 0), 0.0, np.minimum(np.abs(lo), np.abs(hi)))
        return self._diag_at(amax), self._diag_at(amin)

    def diag_inf(self):
        return self.coef[:, 0].copy()


class FrictionMean(_SpeedDiag):
    """
    Coulomb + viscous (+ Stribeck) per joint; see the module docstring.

    Parameters
    ----------
    stribeck : bool
        Add the Stribeck term ``F_s tanh(v / eps) exp(-(v / v_s)^2)``.
    bias : bool
        Learn a per-joint constant bias jointly (reported apart from the damping force).

    """

    name = 'friction'
    _EPS_GRID = (0.003, 0.01, 0.03, 0.1)      # x RMS velocity of the joint
    _VS_GRID = (0.03, 0.1, 0.3)
    #: fraction of the samples each direction of motion needs before a joint's bias is learned
    BOTH_WAYS_FRACTION = 0.05
    #: fraction of the samples below the Stribeck velocity before a Stribeck term is fitted
    STRIBECK_EVIDENCE = 0.05

    def __init__(self, stribeck: bool = False, bias: bool = False):
        super().__init__(bias)
        self.stribeck = bool(stribeck)
        self.coef = None          # (N, 3): F_v, F_c, F_s (F_s = 0 without Stribeck)
        self.eps = None           # (N,) Coulomb smoothing velocity
        self.v_s = None           # (N,) Stribeck velocity

    def _basis(self, v, eps, vs):
        cols = [v, np.tanh(v / eps)]
        if self.stribeck:
            cols.append(np.tanh(v / eps) * np.exp(-(v / vs) ** 2))
        return np.stack(cols, axis=1)

    def fit(self, Qd, Tau) -> 'FrictionMean':
        n, N = Qd.shape
        rms = np.sqrt(np.mean(Qd ** 2, axis=0)) if n else np.ones(N)
        rms = np.where(rms > 0, rms, 1.0)
        self.coef = np.zeros((N, 3))
        self.eps = np.empty(N)
        self.v_s = np.empty(N)
        self.bias = np.zeros(N)
        vs_grid = self._VS_GRID if self.stribeck else (1.0,)
        for j in range(N):
            # a bias is told apart from Coulomb friction only by motion in both directions
            # (one way, tanh(v / eps) is a constant too): until then the joint gets none
            v = Qd[:, j]
            bias = self.bias_enabled and n > 0 and \
                min(np.mean(v > 0), np.mean(v < 0)) >= self.BOTH_WAYS_FRACTION
            # Coulomb and Stribeck forces bounded by the largest measured force: a Stribeck
            # term fitted where the joint never moved slowly explodes towards qd = 0 (128 N m
            # against data of 1 N m, seen), so it also needs samples in its regime (|v| < v_s)
            fmax = float(np.max(np.abs(Tau[:, j]))) if n else 0.0
            best = None
            for fe in self._EPS_GRID:
                for fv in vs_grid:
                    eps, vs = fe * rms[j], fv * rms[j]
                    A = self._basis(v, eps, vs)
                    if self.stribeck and (n == 0 or np.mean(np.abs(v) < vs) <
                                          self.STRIBECK_EVIDENCE):
                        A = A[:, :2]
                    c, b, res = _nnls_one(A, Tau[:, j], bias,
                                          np.r_[np.inf, fmax, fmax][:A.shape[1]])
                    if best is None or res < best[0] - 1e-12 * abs(best[0]):
                        best = (res, c, b, eps, vs)
            _, c, b, self.eps[j], self.v_s[j] = best
            self.coef[j, :c.size] = c
            self.bias[j] = b
        return self

    def _diag_at(self, a: np.ndarray) -> np.ndarray:
        """``m_d`` at speeds ``a = |v|`` (..., N): one Coulomb term and one Stribeck term."""
        vs = self.v_s[:, None] if self.stribeck else np.empty((self.coef.shape[0], 0))
        return _friction_diag(a, self.coef, np.stack((self.eps, self.eps), axis=1), vs)

    def diag_ref(self):
        return self._diag_at(self.eps * 10.0)

    def _params(self):
        return {'stribeck': self.stribeck, 'coef': self.coef.tolist(), 'eps': self.eps.tolist(),
                'v_s': self.v_s.tolist()}

    @classmethod
    def _from(cls, d):
        m = cls(stribeck=bool(d['stribeck']), bias=d.get('bias_enabled', False))
        m.coef = np.asarray(d['coef'], float)
        m.eps = np.asarray(d['eps'], float)
        m.v_s = np.asarray(d['v_s'], float)
        return m


class BasisFrictionMean(_SpeedDiag):
    """
    Friction with frozen coefficients, fitted elsewhere (the long history of the online learner).

    ``m_d(v) v = F_v v + sum_k F_k tanh(v / eps_k) + sum_s S_s tanh(v / eps_s) exp(-(v / vs_s)^2)``
    with every coefficient >= 0: non-negative and non-increasing in ``|v|`` on each side of rest
    like :class:`FrictionMean`, so passive and bounded on a box by its corners. With
    ``coef_neg`` the coefficients of ``v < 0`` are their own (a joint's friction that differs
    between its directions of motion); without, the diagonal is even. ``fit`` keeps the
    coefficients (the GP learns what they leave).

    Parameters
    ----------
    coef : (N, 1 + K + S) array
        ``[F_v, F_1..F_K, S_1..S_S]`` per joint, >= 0 (force per velocity unit, force), for
        ``v >= 0`` (and ``v < 0`` without ``coef_neg``).
    eps : (K,) Coulomb smoothing velocities; eps_s : Stribeck smoothing velocity;
    vs : (S,) Stribeck velocities (velocity units); coef_neg : like ``coef``, for ``v < 0``.

    """

    name = 'friction_basis'

    def __init__(self, coef=None, eps=(), eps_s: float = 0.01, vs=(), bias: bool = False,
                 coef_neg=None):
        super().__init__(bias)
        self.coef = None if coef is None else np.maximum(np.asarray(coef, float), 0.0)
        self.coef_neg = None if coef_neg is None else \
            np.maximum(np.asarray(coef_neg, float), 0.0)
        if self.coef_neg is not None and (self.coef is None or
                                          self.coef_neg.shape != self.coef.shape):
            raise ValueError('coef_neg must have the shape of coef')
        self.eps = np.asarray(eps, float)
        self.eps_s = float(eps_s)
        self.vs = np.asarray(vs, float)
        if self.coef is not None:
            self.bias = np.zeros(self.coef.shape[0])

    def fit(self, Qd, Tau) -> 'BasisFrictionMean':
        if self.coef is None:
            raise ValueError('BasisFrictionMean holds fitted coefficients; it cannot fit')
        if self.bias is None or self.bias.size != self.coef.shape[0]:
            self.bias = np.zeros(self.coef.shape[0])
        return self

    def _diag_at(self, a: np.ndarray, coef: Optional[np.ndarray] = None) -> np.ndarray:
        """``m_d`` at speeds ``a = |v|`` (..., N) with ``coef`` (default: ``v >= 0``'s)."""
        key = (self.eps, self.eps_s)
        cached = self.__dict__.get('_eps_all')
        if cached is None or cached[0][0] is not key[0] or cached[0][1] != key[1]:
            cached = self._eps_all = (key, np.append(self.eps, self.eps_s))
        return _friction_diag(a, self.coef if coef is None else coef, cached[1], self.vs)

    def diag(self, Qd):
        a = np.abs(Qd)
        if self.coef_neg is None:
            return self._diag_at(a)
        # each query's coefficients by its direction, one pass (the message path's cost)
        return self._diag_at(a, np.where((np.asarray(Qd) < 0.0)[..., None], self.coef_neg,
                                         self.coef))

    def diag_bounds(self, lo, hi):
        if self.coef_neg is None:
            return super().diag_bounds(lo, hi)
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        # each side of rest is non-increasing in the speed: its range is at its two ends
        pos, neg = hi >= 0.0, lo < 0.0
        p_hi = self._diag_at(np.maximum(lo, 0.0))
        p_lo = self._diag_at(np.maximum(hi, 0.0))
        n_hi = self._diag_at(np.maximum(-hi, 0.0), self.coef_neg)
        n_lo = self._diag_at(np.maximum(-lo, 0.0), self.coef_neg)
        dlo = np.where(pos & neg, np.minimum(p_lo, n_lo), np.where(pos, p_lo, n_lo))
        dhi = np.where(pos & neg, np.maximum(p_hi, n_hi), np.where(pos, p_hi, n_hi))
        return dlo, dhi

    def diag_inf(self):
        out = self.coef[:, 0].copy()
        return out if self.coef_neg is None else np.minimum(out, self.coef_neg[:, 0])

    def diag_ref(self):
        scale = np.full(self.coef.shape[0],
                        10.0 * (float(self.eps.max()) if self.eps.size else 1.0))
        ref = self._diag_at(scale)
        return ref if self.coef_neg is None else np.maximum(ref,
                                                            self._diag_at(scale, self.coef_neg))

    def _params(self):
        out = {'coef': self.coef.tolist(), 'eps': self.eps.tolist(), 'eps_s': self.eps_s,
               'vs': self.vs.tolist()}
        if self.coef_neg is not None:
            out['coef_neg'] = self.coef_neg.tolist()
        return out

    @classmethod
    def _from(cls, d):
        neg = d.get('coef_neg')
        return cls(np.asarray(d['coef'], float), d['eps'], float(d['eps_s']), d['vs'],
                   coef_neg=None if neg is None else np.asarray(neg, float))


def _nnls_one(A: np.ndarray, y: np.ndarray, bias: bool, ub: Optional[np.ndarray] = None):
    """
    Solve min |A c + b - y|^2 (+ 0.01 n b^2) with 0 <= c (<= ub) (and b free if ``bias``).

    Returns (c, b, residual^2). The weak ridge on ``b`` only matters where the data cannot tell
    a bias from Coulomb friction (a joint that moved one way only: ``tanh(v / eps)`` is then
    constant too); there it keeps ``b`` small instead of trading a large bias against a large
    Coulomb force.
    """
    k = A.shape[1]
    n = A.shape[0]
    if n == 0:
        return np.zeros(k), 0.0, 0.0
    yy = y
    if bias:
        A = np.column_stack([A, np.ones(n)])
        ridge = np.zeros((1, k + 1))
        ridge[0, k] = 0.1 * np.sqrt(n)
        A = np.vstack([A, ridge])
        yy = np.r_[y, 0.0]
    lb = np.r_[np.zeros(k), [-np.inf] if bias else []]
    hi = np.full(k, np.inf) if ub is None else np.maximum(np.asarray(ub, float), 1e-300)
    r = lsq_linear(A, yy, bounds=(lb, np.r_[hi, [np.inf] if bias else []]), method='bvls')
    c = np.clip(r.x[:k], 0.0, hi)
    b = float(r.x[k]) if bias else 0.0
    res = float(np.sum((A[:n, :k] @ c + b - y) ** 2))
    return c, b, res


def _nnls_with_bias(bases, Tau):
    coef, bias = [], np.zeros(Tau.shape[1])
    for j, A in enumerate(bases):
        c, b, _ = _nnls_one(A, Tau[:, j], True)
        coef.append(c)
        bias[j] = b
    return coef, bias

"""
The exact GP posterior of a D-GP: hyper-parameters, data, Cholesky factors and weights.

Units: public arguments are model units (``Qd`` (k, N) velocities, ``Tau`` (k, N) forces). Inside,
inputs are standardized ``x = qd / s_x`` and outputs ``y = (tau - m_tau(qd) - b) / s_y``, with
``s_x`` the RMS velocity and ``s_y`` the RMS of the residual after the prior mean; so rad vs m/s
or 1e5 N scales do not matter.

Structure (docs/ARCHITECTURE.md, "The model"): output ``m`` is an independent GP with the kernel
``k^(m)(x, x') = sum_{e in row m} phi_e(x) phi_e(x') k_e(x, x')`` (``kernels.Structure``). The
stacked ``nN x nN`` system is block diagonal, so fitting is ``N`` independent ``n x n`` Cholesky
factorizations and prediction ``N`` independent triangular solves.

The posterior splits into the prior and the GP *correction*:
``tau_hat(q) = m_tau(q) + w(q) C(q) q`` and ``D_hat(q) = diag(m_d(q)) + w(q) C(q)``, where the
correction weight ``w`` belongs to the passivity policy (1 when nothing is enforced).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
import math
from typing import Optional

import numpy as np
from scipy.linalg import LinAlgError
from scipy.linalg.blas import dsymv

from ._chol import (chol_jitter, cholesky_in_place, FrozenFactor, JITTER_STEPS,
                    WindowCholesky)
from .kernels import lower_se_sum, se_ard, Structure
from .means import PriorMean

__all__ = ['Hyper', 'Posterior', 'chol_jitter']

_LOG2PI = math.log(2.0 * math.pi)
# element kernels are kept while an output is factorized up to this n, so that the RKHS norms of
# the certificate cost one matrix-vector product each instead of a rebuild
_KEEP_PARTS = 2000


@dataclass
class Hyper:
    """
    Kernel hyper-parameters and standardization (standardized units, natural logs).

    log_sf2 : (E,) signal variances per element (``-inf`` = element switched off)
    log_ls : (E, N) lengthscales per element
    log_sn2 : (N,) noise variance per output
    sx, sy : (N,) input and output scales (model units)
    """

    log_sf2: np.ndarray
    log_ls: np.ndarray
    log_sn2: np.ndarray
    sx: np.ndarray
    sy: np.ndarray

    FIELDS = ('log_sf2', 'log_ls', 'log_sn2', 'sx', 'sy')

    def copy(self) -> 'Hyper':
        return Hyper(*(np.array(getattr(self, k), dtype=float) for k in self.FIELDS))

    def to_dict(self) -> dict:
        return {k: np.asarray(getattr(self, k), float).tolist() for k in self.FIELDS}

    @classmethod
    def from_dict(cls, d: dict, structure: Optional[Structure] = None) -> 'Hyper':
        """
        Make validated hyper-parameters from ``d``.

        Validated: finite where it must be, positive scales, exp() without overflow, and
        shapes that match ``structure`` when given. Raises ValueError naming the field.
        """
        missing = [k for k in cls.FIELDS if k not in d]
        if missing:
            raise ValueError(f'hyperparams is missing {missing}')
        try:
            hp = {k: np.array(d[k], dtype=float) for k in cls.FIELDS}
        except (TypeError, ValueError) as exc:
            raise ValueError(f'hyperparams: non-numeric values ({exc})') from None
        for k, v in hp.items():
            bad = np.isnan(v) | (v == np.inf) | ((v == -np.inf) & (k != 'log_sf2'))
            if np.any(bad):
                raise ValueError(f'hyperparams[{k!r}] has non-finite values')
        for k in ('sx', 'sy'):
            if np.any(hp[k] <= 0):
                raise ValueError(f'hyperparams[{k!r}] must be positive scales, got {hp[k]}')
        for k, lim in (('log_ls', 300.0), ('log_sf2', 300.0), ('log_sn2', 300.0)):
            v = hp[k][np.isfinite(hp[k])]
            if np.any(np.abs(v) > lim):
                raise ValueError(f'hyperparams[{k!r}] out of range (|value| > {lim:g}): '
                                 f'exp() would overflow or underflow')
        if structure is not None:
            N, E = structure.N, structure.E
            want = {'log_sf2': (E,), 'log_ls': (E, N), 'log_sn2': (N,), 'sx': (N,), 'sy': (N,)}
            for k, shape in want.items():
                if hp[k].shape != shape:
                    raise ValueError(f'hyperparams[{k!r}] has shape {hp[k].shape}, the '
                                     f'{structure.kind} model with N = {N} needs {shape}')
        return cls(**hp)


class Posterior:
    """
    Exact posterior of one D-GP (see the module docstring).

    Parameters
    ----------
    structure : kernels.Structure
    hyper : Hyper
    mean : means.PriorMean (fitted)
    Qd, Tau : (n, N) arrays, model units
    window : int or None
        ``update`` keeps at most this many samples (drops the oldest).
    keep_rkhs : bool
        Compute the RKHS norms of the correction during the factorization (the certificates
        need them; otherwise ``rkhs_sq`` rebuilds the kernels when first asked).

    Attributes
    ----------
    X : (n, N) standardized inputs;  R : (n, N) standardized residuals after the prior
    alpha : (n, N) weights ``(K^(m) + s_eps^2 I)^-1 R[:, m]``;  jitter : (N,) added jitter
    delta : (n, N) or None, a change of the weights made by a passivity repair (``repair``);
    weights : ``alpha + delta``, the weights of the posterior mean (the variance is unchanged)

    """

    def __init__(self, structure: Structure, hyper: Hyper, mean: PriorMean, Qd: np.ndarray,
                 Tau: np.ndarray, window: Optional[int] = None, keep_rkhs: bool = True):
        self.keep_rkhs = keep_rkhs
        self.structure = structure
        self.hyper = hyper
        self.mean = mean
        self.window = window
        self.X = Qd / hyper.sx
        self.R = (Tau - mean(Qd)) / hyper.sy
        self._factorize()

    # ------------------------------------------------------------------ construction
    @property
    def N(self) -> int:
        return self.structure.N

    @property
    def n(self) -> int:
        return self.X.shape[0]

    def _limit(self) -> Optional[int]:
        return None if self.window is None else self.window + 1

    def _factorize(self) -> None:
        """
        Factorize the kernel of every output in place.

        Per output: the kernel's lower triangle built in place in a factor buffer, Cholesky in
        place (LAPACK, no copy; bounded jitter escalation as ``chol_jitter``), adopted by a
        ``WindowCholesky``. The element kernels are kept while their output is factorized when
        the RKHS norms are wanted (``keep_rkhs``), so that each costs one matrix-vector
        product instead of a rebuild.
        """
        s, hp, X = self.structure, self.hyper, self.X
        n = X.shape[0]
        self.factors = []
        self.alpha = np.zeros((n, s.N))
        self.jitter = np.zeros(s.N)
        keep = self.keep_rkhs and n <= _KEEP_PARTS
        rkhs_sq = np.zeros(s.E)
        ls = np.exp(hp.log_ls)
        sf2 = np.exp(hp.log_sf2)
        for m in range(s.N):
            rows = s.rows[m]
            args = ([ls[e] for e in rows], [sf2[e] for e in rows],
                    [s.features(X, e) for e in rows])
            sn2 = math.exp(hp.log_sn2[m])
            A = WindowCholesky.workspace(n, self._limit())
            parts = [np.empty((n, n), order='F') for _ in rows] if keep else None
            lower_se_sum(X, *args, A, noise=sn2, parts=parts)
            d = A[np.arange(n), np.arange(n)]
            base = float(d.mean()) or 1.0
            if not (math.isfinite(base) and np.all(np.isfinite(d))):
                raise ValueError(f'kernel matrix of output {m} is not finite: hyper-parameters '
                                 f'or inputs out of range')
            for rel in JITTER_STEPS:
                j = rel * base
                if j:                                  # dpotrf overwrote the triangle: rebuild
                    lower_se_sum(X, *args, A, noise=sn2 + j)
                if cholesky_in_place(A, n) == 0:
                    break
            else:
                raise LinAlgError(f'kernel matrix not positive definite even with jitter '
                                  f'{JITTER_STEPS[-1]:g} x mean diagonal')
            wc = WindowCholesky.adopt(A, self.R[:, m], n=n, limit=self._limit())
            if not np.all(np.isfinite(wc.diag())):
                raise ValueError(f'kernel matrix of output {m} is not finite: hyper-parameters '
                                 f'or inputs out of range')
            self.factors.append(wc)
            self.jitter[m] = j
            self.alpha[:, m] = wc.alpha()
            for k, e in enumerate(rows if keep else ()):
                if sf2[e] > 0:
                    a = self.alpha[:, m]
                    rkhs_sq[e] = float(a @ dsymv(1.0, parts[k], a, lower=1))
            del parts
        self.delta = None
        self.weights = self.alpha
        self._rkhs = (self.weights, rkhs_sq) if keep else None

    def set_delta(self, delta: Optional[np.ndarray]) -> None:
        """Set the repair's change of the weights, (n, N) or None."""
        self.delta = None if delta is None or not np.any(delta) else np.array(delta, float)
        self.weights = self.alpha if self.delta is None else self.alpha + self.delta

    @classmethod
    def restore(cls, structure, hyper, mean, X, R, alpha, jitter, factors, z, window,
                delta=None):
        """Rebuild from saved arrays (``persistence``): no refactorization, bit-identical."""
        self = cls.__new__(cls)
        self.structure, self.hyper, self.mean, self.window = structure, hyper, mean, window
        self.keep_rkhs = True
        self.X, self.R, self.alpha, self.jitter = X, R, alpha, jitter
        self.factors = [WindowCholesky(factors[m], R[:, m], limit=self._limit(), z=z[m])
                        for m in range(structure.N)]
        self.set_delta(delta)
        self._rkhs = None
        return self

    def with_kernel(self, hyper: Hyper) -> 'Posterior':
        """Refactorize the same data under other kernel hyper-parameters (same ``sx``, ``sy``)."""
        if not (np.array_equal(hyper.sx, self.hyper.sx)
                and np.array_equal(hyper.sy, self.hyper.sy)):
            raise ValueError('with_kernel keeps the standardization: sx and sy must not change')
        p = copy.copy(self)
        p.hyper = hyper
        p._factorize()
        return p

    def copy(self) -> 'Posterior':
        """Return an independent copy; the refit worker updates copies off the message path."""
        return copy.deepcopy(self)

    def frozen(self, variance: bool = True) -> 'Posterior':
        """
        Return a predict-only copy (a model snapshot for another process).

        It shares the data arrays (``update`` and ``fit`` replace them, never write into
        them); the factors are compact read-only copies (``FrozenFactor``) when ``variance``,
        else absent (the variance is then NaN). ``update`` raises on it; saving refactorizes.
        """
        p = copy.copy(self)
        p.factors = [FrozenFactor(f.L) for f in self.factors] if variance and self.factors \
            else None
        p._rkhs = None
        return p

    @property
    def live(self) -> bool:
        """Tell whether this posterior can be updated (not a ``frozen`` copy)."""
        return self.factors is not None and all(isinstance(f, WindowCholesky)
                                                for f in self.factors)

    def ensure_factors(self) -> 'Posterior':
        """Return self if live, else a live copy: a frozen one is refactorized (O(n^3))."""
        if self.live:
            return self
        p = copy.copy(self)
        delta = self.delta
        p._factorize()
        p.set_delta(delta)
        return p

    # ------------------------------------------------------------------ data access
    @property
    def Qd(self) -> np.ndarray:
        """Training velocities, model units (n, N)."""
        return self.X * self.hyper.sx

    @property
    def Tau(self) -> np.ndarray:
        """Training forces, model units (n, N) (prior and bias added back)."""
        Q = self.Qd
        return self.R * self.hyper.sy + self.mean(Q)

    def log_marginal_likelihood(self) -> float:
        """Sum over outputs of the log marginal likelihood of the (standardized) residuals."""
        n = self.n
        tot = 0.0
        for m in range(self.N):
            tot += (-0.5 * self.R[:, m] @ self.alpha[:, m]
                    - np.log(self.factors[m].diag()).sum() - 0.5 * n * _LOG2PI)
        return float(tot)

    def rkhs_sq(self) -> np.ndarray:
        """
        Return the squared RKHS norm of every element correction.

        Per element ``|C_e|_H^2 = a^T K_e a`` (``a = x_n * alpha_m``, K_e with sf2), (E,):
        kept from the factorization, else rebuilt (one n x n kernel per element).
        """
        c = self._rkhs
        if c is not None and c[0] is self.weights:
            return c[1]
        s, hp = self.structure, self.hyper
        q = np.zeros(s.E)
        for m in range(s.N):
            for e, k in s.output_kernels(m, self.X, self.X, hp.log_ls, hp.log_sf2):
                q[e] = float(self.weights[:, m] @ (k @ self.weights[:, m]))
        self._rkhs = (self.weights, q)
        return q

    # ------------------------------------------------------------------ update
    def update(self, Qd: np.ndarray, Tau: np.ndarray) -> None:
        """
        Append k samples (k, N) in place.

        One kernel block and one triangular solve with k right-hand sides per output
        (``WindowCholesky.append_block``): O(n^2 k) per output. Beyond ``window`` the oldest
        samples are dropped, each by a rank-one update of every factor.
        """
        if not self.live:
            raise RuntimeError("a model snapshot is predict-only: update the learner's model")
        s, hp = self.structure, self.hyper
        sn2 = np.exp(hp.log_sn2)
        x, r = Qd / hp.sx, (Tau - self.mean(Qd)) / hp.sy
        Xk = np.vstack([self.X, x])
        Kel = se_ard(x, Xk, np.exp(hp.log_ls), np.exp(hp.log_sf2)) if s.E > 1 else None
        n, k = self.X.shape[0], x.shape[0]
        for m in range(s.N):
            c = s.output_kernel(m, x, Xk, hp.log_ls, hp.log_sf2, Kel)      # (k, n + k)
            floor = sn2[m] + self.jitter[m]
            self.factors[m].append_block(c[:, :n].T, c[:, n:] + floor * np.eye(k), floor,
                                         r[:, m])
        self.X, self.R = Xk, np.vstack([self.R, r])
        if self.delta is not None:
            self.delta = np.vstack([self.delta, np.zeros((k, s.N))])
        drop = 0 if self.window is None else max(0, self.X.shape[0] - self.window)
        for _ in range(drop):
            for f in self.factors:
                f.drop_first()
        if drop:
            self.X, self.R = self.X[drop:], self.R[drop:]
            if self.delta is not None:
                self.delta = self.delta[drop:]
        self.alpha = np.column_stack([f.alpha() for f in self.factors])
        self.set_delta(self.delta)

    def remean(self, mean: PriorMean) -> None:
        """
        Take another prior mean in place, the data and the factorization kept: O(n^2) an output.

        The residuals become ``(Tau - mean(Qd)) / sy`` and the weights follow by one triangular
        solve per output (``WindowCholesky.retarget``): the posterior the same kernel gives
        with that mean. What a prior that follows every sample (``gp.coupled``, refitted by the
        online learner) costs the model, instead of a refit.
        """
        if not self.live:
            raise RuntimeError("a model snapshot is predict-only: remean the learner's model")
        Q = self.Qd
        self.R = self.R + (self.mean(Q) - mean(Q)) / self.hyper.sy
        for m, f in enumerate(self.factors):
            f.retarget(self.R[:, m])
        self.mean = mean
        self.alpha = np.column_stack([f.alpha() for f in self.factors])
        self.set_delta(self.delta)

    # ------------------------------------------------------------------ prediction
    def element_kernels(self, Q: np.ndarray) -> Optional[np.ndarray]:
        """
        Build the raw element kernels for a few queries.

        All raw element kernels against the training set in one pass for a few queries
        (E, k, n), or None for batches (which build them per output).
        """
        X = Q / self.hyper.sx
        E = self.structure.E
        if E < 2 or X.shape[0] > 16 or X.shape[0] * self.n * E > 2_000_000:
            return None
        return se_ard(X, self.X, np.exp(self.hyper.log_ls), np.exp(self.hyper.log_sf2))

    def predict(self, Q: np.ndarray, weight: Optional[np.ndarray] = None,
                return_var: bool = False, Kel=None):
        """
        Damping force ``m_tau(q) + w(q) * correction`` (k, N) and its posterior variance.

        weight : (k,) correction weight ``w`` (None = 1). Kel : from ``element_kernels``.
        The variance is that of the GP (noise-free), in force units squared.
        """
        s, hp = self.structure, self.hyper
        X = Q / hp.sx
        if Kel is not None and not return_var:          # a few queries: one einsum
            G = self._element_weights(Kel)
            corr = G[:, :, 0] if s.kind == 'ard' else np.einsum('kmn,kn->km', G, X)
            if weight is not None:
                corr *= weight[:, None]
            return self.mean.force(Q) + corr * hp.sy, None
        corr = np.zeros_like(X)
        var = np.zeros_like(X) if return_var else None
        for m in range(s.N):
            Ks = s.output_kernel(m, X, self.X, hp.log_ls, hp.log_sf2, Kel)
            corr[:, m] = Ks @ self.weights[:, m]
            if return_var and self.factors is None:
                var[:, m] = np.nan
            elif return_var:
                v = self.factors[m].solve(Ks.T)
                var[:, m] = np.maximum(s.output_kdiag(m, X, hp.log_sf2)
                                       - np.einsum('ij,ij->j', v, v), 0.0)
        if weight is not None:
            corr *= weight[:, None]
        tau = self.mean.force(Q) + corr * hp.sy
        if return_var:
            var = var * hp.sy ** 2
        return tau, var

    def _element_weights(self, Kel: np.ndarray) -> np.ndarray:
        """
        Compute the element weights ``G`` from raw element kernels.

        ``G[k, m, n] = sum_j k_e(x_k, x_j) phi_n(x_j) w_jm`` for the elements ``e = (m, n)``
        that are on (the others 0), from raw element kernels ``Kel`` (E, k, n_train); ARD
        elements (phi = 1) sit in column 0. Output m's correction is ``sum_n G[:, m, n]
        phi_n(x)``; the damping entry (m, n) is ``G[:, m, n]`` (model units).
        """
        s, hp = self.structure, self.hyper
        rows = np.array([m for m, _ in s.elems])
        cols = np.array([0 if n is None else n for _, n in s.elems])
        ard = np.array([n is None for _, n in s.elems])
        on = np.exp(hp.log_sf2) > 0.0
        phi = np.where(ard[None, :], 1.0, self.X[:, cols])                   # (n_train, E)
        V = (phi * self.weights[:, rows]).T * on[:, None]                     # (E, n_train)
        G = np.zeros((Kel.shape[1], s.N, s.N))
        G[:, rows, cols] = np.einsum('ekj,ej->ke', Kel, V)
        return G

    def damping(self, Q: np.ndarray, weight: Optional[np.ndarray] = None, Kel=None) -> np.ndarray:
        """
        Compute the damping matrix.

        Damping matrix ``diag(m_d(q)) + w(q) C(q)`` (k, N, N), model units, with
        ``predict(q) = D(q) q``. Not defined for the ARD baseline.
        """
        s, hp = self.structure, self.hyper
        X = Q / hp.sx
        k = X.shape[0]
        if self.mean.is_diagonal:
            D = np.zeros((k, s.N, s.N))
            idx = np.arange(s.N)
            D[:, idx, idx] = self.mean.diag(Q)
        else:
            D = self.mean.matrix(Q)
        if Kel is not None:                             # a few queries: one einsum
            C = self._element_weights(Kel) * (hp.sy[:, None] / hp.sx[None, :])
            return D + (C if weight is None else weight[:, None, None] * C)
        ls = np.exp(hp.log_ls)
        for e, (m, n) in enumerate(s.elems):
            sf2 = math.exp(hp.log_sf2[e])
            if sf2 == 0.0:
                continue
            ke = se_ard(X, self.X, ls[e], sf2)
            c = (ke @ (self.X[:, n] * self.weights[:, m])) * (hp.sy[m] / hp.sx[n])
            D[:, m, n] += c if weight is None else weight * c
        return D

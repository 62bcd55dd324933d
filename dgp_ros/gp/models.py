"""Full-D-GP, Diag-D-GP and ARD-GP: one exact-inference implementation over per-output structure.

Units and shapes: inputs ``Qd`` (n, N) generalized velocities, outputs ``Tau`` (n, N) damping
forces, in any consistent units (rad, m/s, N...). Internally both are standardized per dimension
(``x = q / s_x`` with ``s_x`` the RMS of ``q``, ``y = tau / s_y`` with ``s_y`` the RMS of the
residual after the prior mean), so rad-vs-m/s or 1e5 N scales do not matter; every public method
takes and returns model units.

Structure (DESIGN "Method"): output ``m`` is an independent GP with kernel
``k^(m)(x, x') = sum_{e in row m} phi_e(x) phi_e(x') k_e(x, x')`` (kernels.element_layout). The
stacked ``nN x nN`` system is block diagonal, so fitting is ``N`` independent ``n x n`` Cholesky
factorizations, prediction ``N`` independent triangular solves. Nothing here builds the stacked
system (the tests do, to check this one against it).
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import tempfile
import time
import warnings
from typing import Optional

import numpy as np
from scipy.linalg import LinAlgError, cho_solve, cholesky
from scipy.optimize import minimize

from ._chol import WindowCholesky
from ._validation import as_matrix, as_pair
from .kernels import element_layout, se_ard
from .passivity import Certificate, copositivity_margin, project_passive, projection_lambda
from .verify import CorrectionTerms, verify_box

__all__ = ['ArdGP', 'DiagDGP', 'FullDGP', 'make_model', 'load_model', 'prior_mean_diag',
           'FORMAT_VERSION']

FORMAT_VERSION = 1
PASSIVITY_MODES = ('none', 'paper', 'certified', 'projected')
_LOG2PI = math.log(2.0 * math.pi)
_JITTER_STEPS = (0.0, 1e-10, 1e-8, 1e-6, 1e-4)   # relative to mean(diag K); bounded escalation
_MIN_NOISE_VAR = 1e-6                             # standardized units (noise std >= 1e-3 RMS)


def prior_mean_diag(Qd, Tau) -> np.ndarray:
    """Least-squares diagonal prior damping ``m_dn = <qd_n, tau_n> / <qd_n, qd_n>``, clamped at 0.

    Qd, Tau: (n, N) (n may be 0). Returns (N,), in units of tau per unit qd. A dimension with
    no excitation (``<qd_n, qd_n> = 0``) gets 0.
    """
    Qd = as_matrix(Qd, 'Qd', allow_empty=True)
    Tau = as_matrix(Tau, 'Tau', Qd.shape[1], allow_empty=True)
    if Qd.shape[0] != Tau.shape[0]:
        raise ValueError(f'Qd has {Qd.shape[0]} samples but Tau has {Tau.shape[0]}')
    num = np.einsum('ij,ij->j', Qd, Tau)
    den = np.einsum('ij,ij->j', Qd, Qd)
    out = np.zeros(Qd.shape[1])
    ok = den > 0
    out[ok] = num[ok] / den[ok]
    return np.maximum(out, 0.0)


def _rms(A: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(A * A, axis=0)) if A.shape[0] else np.zeros(A.shape[1])


def _chol_jitter(K: np.ndarray):
    """Lower Cholesky factor with bounded jitter escalation. Returns (L, jitter_added)."""
    base = float(np.mean(np.diag(K))) or 1.0
    for rel in _JITTER_STEPS:
        j = rel * base
        try:
            L = cholesky(K + j * np.eye(K.shape[0]) if j else K, lower=True, check_finite=False)
            return L, j
        except LinAlgError:
            continue
    raise LinAlgError(f'kernel matrix not positive definite even with jitter '
                      f'{_JITTER_STEPS[-1]:g} x mean diagonal')


class _BaseGP:
    """Shared exact inference. Subclasses only set ``_kind``. See module docstring.

    Parameters
    ----------
    passivity : 'none' | 'paper' | 'certified' | 'projected'
        How passivity ``q^T tau_hat(q) >= 0`` is guaranteed (DESIGN, docs/PASSIVITY.md).
    noise : float or (N,) array or None
        Fixed noise standard deviation per output, in force units; None = learn it.
    window : int or None
        Keep at most this many samples; ``update`` drops the oldest beyond it.
    n_restarts : int
        Extra random restarts of L-BFGS-B for the hyper-parameters.
    max_opt_samples : int
        Hyper-parameters are optimized on at most this many samples (random subset).
    domain_margin, blend_width : float
        'certified': the verified operating box is the data box grown by ``domain_margin`` of its
        range per side; the correction blends to the prior mean over a further ``blend_width``.
        If the proof fails there, the domain is shrunk (halved margins, then the data box with a
        quarter blend) before the correction itself is shrunk.
    max_boxes : int
        Branch-and-bound budget of the domain verification.
    operating_domain : ((N,), (N,)) or None
        'certified': a declared operating box ``(lo, hi)`` in model units (e.g. the flight
        envelope). The verified box is then the hull of it and the data box (grown by
        ``domain_margin``), so the full correction is kept wherever the system operates, also
        where no sample has been seen yet. If that cannot be proven, the data-derived domains
        are tried next. None: the data box only.
    projection_weights : (N,) or None
        Diagonal of ``W^-1`` for 'projected' (default ones, i.e. Euclidean in model units).
    hyperparams : dict or None
        Hyper-parameters from ``get_params()['hyperparams']`` to start from (or keep, with
        ``fit(optimize=False)``).
    random_state : int
        Seed for subsets and restarts (results are deterministic).
    """

    _kind: str = ''

    def __init__(self, passivity: str = 'none', noise=None, window: Optional[int] = None,
                 n_restarts: int = 2, max_opt_samples: int = 300, domain_margin: float = 0.1,
                 blend_width: float = 0.1, max_boxes: int = 50000, projection_weights=None,
                 hyperparams: Optional[dict] = None, random_state: int = 0,
                 operating_domain=None):
        if passivity not in PASSIVITY_MODES:
            raise ValueError(f'passivity must be one of {PASSIVITY_MODES}, got {passivity!r}')
        if self._kind == 'ard' and passivity in ('paper', 'certified'):
            raise ValueError("ArdGP has no damping structure to certify: use passivity 'none' "
                             "or 'projected'")
        if window is not None and (int(window) != window or window < 1):
            raise ValueError(f'window must be a positive integer or None, got {window!r}')
        for nm, v in (('n_restarts', n_restarts), ('max_opt_samples', max_opt_samples),
                      ('max_boxes', max_boxes)):
            if int(v) != v or v < (1 if nm != 'n_restarts' else 0):
                raise ValueError(f'{nm} must be a non-negative integer, got {v!r}')
        if not (domain_margin >= 0 and blend_width > 0):
            raise ValueError('domain_margin must be >= 0 and blend_width > 0')
        self.passivity = passivity
        self.noise = noise
        self.window = None if window is None else int(window)
        self.n_restarts = int(n_restarts)
        self.max_opt_samples = int(max_opt_samples)
        self.domain_margin = float(domain_margin)
        self.blend_width = float(blend_width)
        self.max_boxes = int(max_boxes)
        self.projection_weights = (None if projection_weights is None
                                   else np.asarray(projection_weights, float))
        if self.projection_weights is not None and np.any(self.projection_weights <= 0):
            raise ValueError('projection_weights must be positive')
        self.random_state = int(random_state)
        self.operating_domain = None
        if operating_domain is not None:
            try:
                lo, hi = (np.asarray(v, dtype=float).ravel() for v in operating_domain)
            except (TypeError, ValueError):
                raise ValueError('operating_domain must be a pair (lo, hi) of (N,) arrays') \
                    from None
            if lo.shape != hi.shape or lo.size == 0 or not (np.all(np.isfinite(lo)) and
                                                            np.all(np.isfinite(hi))):
                raise ValueError('operating_domain: lo and hi must be finite and of equal length')
            if np.any(hi <= lo):
                raise ValueError(f'operating_domain: need lo < hi in every dimension, got '
                                 f'lo={lo.tolist()}, hi={hi.tolist()}')
            self.operating_domain = (lo, hi)
        self._hp = None if hyperparams is None else self._hp_from_dict(hyperparams)
        self._fitted = False
        self._cert = None
        self._stale = False
        self._scale = 1.0
        self._leaves = None
        self.jitter_ = 0.0
        self.fit_info_ = {}

    # ------------------------------------------------------------------ parameters
    def get_params(self) -> dict:
        """Constructor arguments (sklearn-style), with the current hyper-parameters."""
        hp = None if self._hp is None else {k: np.asarray(v).tolist() for k, v in self._hp.items()}
        return dict(passivity=self.passivity, noise=self.noise, window=self.window,
                    n_restarts=self.n_restarts, max_opt_samples=self.max_opt_samples,
                    domain_margin=self.domain_margin, blend_width=self.blend_width,
                    max_boxes=self.max_boxes,
                    projection_weights=(None if self.projection_weights is None
                                        else self.projection_weights.tolist()),
                    hyperparams=hp, random_state=self.random_state,
                    operating_domain=(None if self.operating_domain is None else
                                      [v.tolist() for v in self.operating_domain]))

    def set_params(self, **kw):
        """Set constructor arguments; returns self. Takes effect at the next ``fit``."""
        p = self.get_params()
        unknown = set(kw) - set(p)
        if unknown:
            raise ValueError(f'unknown parameter(s): {sorted(unknown)}')
        p.update(kw)
        state = self.__dict__.copy()
        self.__init__(**p)
        for k in self._FITTED_STATE:
            if k in state:
                setattr(self, k, state[k])
        return self

    _FITTED_STATE = ('N', '_elist', '_rows', '_X', '_R', '_L', '_alpha', '_jit', '_fitted',
                     '_rkhs_cache',
                     '_cert', '_stale', '_scale', '_domain', '_data_box', '_leaves', 'jitter_',
                     'fit_info_')

    @staticmethod
    def _hp_from_dict(d: dict) -> dict:
        need = ('log_sf2', 'log_ls', 'log_sn2', 'sx', 'sy', 'mean')
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f'hyperparams is missing {missing}')
        hp = {k: np.array(d[k], dtype=float) for k in need}
        for k, v in hp.items():
            bad = np.isnan(v) | (v == np.inf) | ((v == -np.inf) & (k != 'log_sf2'))
            if np.any(bad):
                raise ValueError(f'hyperparams[{k!r}] has non-finite values')
        for k in ('sx', 'sy'):
            if np.any(hp[k] <= 0):
                raise ValueError(f'hyperparams[{k!r}] must be positive scales, got {hp[k]}')
        # exp() of these must neither overflow nor vanish (a kernel of NaN or of zeros)
        for k, lim in (('log_ls', 300.0), ('log_sf2', 300.0), ('log_sn2', 300.0)):
            v = hp[k][np.isfinite(hp[k])]
            if np.any(np.abs(v) > lim):
                raise ValueError(f'hyperparams[{k!r}] out of range (|value| > {lim:g}): '
                                 f'exp() would overflow or underflow')
        return hp

    # ------------------------------------------------------------------ structure helpers
    def _elems(self, N):
        return element_layout(self._kind, N)

    def _features(self, X, e):
        n = self._elist[e][1]
        return None if n is None else X[:, n]

    def _prior_std(self, X):
        """Prior mean in standardized units, (k, N)."""
        hp = self._hp
        if self._kind == 'ard':
            return np.broadcast_to(hp['mean'] / hp['sy'], X.shape)
        return X * (hp['mean'] * hp['sx'] / hp['sy'])

    def _kparts(self, m, X1, X2, hp=None, Kel=None):
        """Output m's element kernels ``phi_e(x1) phi_e(x2) k_e(x1, x2)``: yields (e, (a, b)),
        each a new array. ``Kel``: the raw element kernels from ``_cross_elems`` (X2 = the
        training inputs), used instead of building them."""
        hp = self._hp if hp is None else hp
        for e in self._rows[m]:
            sf2 = math.exp(hp['log_sf2'][e])
            if sf2 == 0.0:
                continue
            k = se_ard(X1, X2, np.exp(hp['log_ls'][e]), sf2) if Kel is None else Kel[e].copy()
            n = self._elist[e][1]
            if n is not None:
                k *= X1[:, n][:, None]
                k *= X2[:, n][None, :]
            yield e, k

    def _kmat(self, m, X1, X2, hp=None, Kel=None):
        """Output m's kernel k^(m)(X1, X2), standardized. (a, b)"""
        K = None
        for _, k in self._kparts(m, X1, X2, hp, Kel):
            if K is None:
                K = k
            else:
                K += k
        return np.zeros((X1.shape[0], X2.shape[0])) if K is None else K

    def _kdiag(self, m, X):
        hp = self._hp
        out = np.zeros(X.shape[0])
        for e in self._rows[m]:
            sf2 = math.exp(hp['log_sf2'][e])
            n = self._elist[e][1]
            out += sf2 * (1.0 if n is None else X[:, n] ** 2)
        return out

    def _setup_structure(self, N):
        self.N = N
        self._elist = self._elems(N)
        self._rows = [[e for e, (m, _) in enumerate(self._elist) if m == row] for row in range(N)]

    # ------------------------------------------------------------------ fitting
    def fit(self, Qd, Tau, optimize: bool = True):
        """Fit to samples. Qd, Tau: (n, N). Returns self.

        optimize=True: standardization, prior mean and kernel hyper-parameters are (re)estimated
        (log marginal likelihood, analytic gradients, L-BFGS-B with restarts).
        optimize=False: keeps the hyper-parameters the model has (from an earlier fit or the
        ``hyperparams`` argument); only a model without any estimates them from the data
        without optimizing the kernel.
        """
        t0 = time.perf_counter()
        Qd, Tau = as_pair(Qd, Tau)
        N = Qd.shape[1]
        if self._hp is not None and self._hp['sx'].size != N:
            if not optimize:
                raise ValueError(f'the kept hyper-parameters are for N = {self._hp["sx"].size}, '
                                 f'data has N = {N}')
            self._hp = None
        if self.operating_domain is not None and self.operating_domain[0].size != N:
            raise ValueError(f'operating_domain has {self.operating_domain[0].size} entries per '
                             f'bound, data has N = {N}')
        if self.projection_weights is not None and self.projection_weights.size != N:
            raise ValueError(f'projection_weights has {self.projection_weights.size} entries, '
                             f'data has N = {N}')
        self._setup_structure(N)
        if self.window is not None and Qd.shape[0] > self.window:
            Qd, Tau = Qd[-self.window:], Tau[-self.window:]
        if optimize or self._hp is None:
            hp = self._init_hp(Qd, Tau, keep_kernel=self._hp is not None)
            self._hp = hp
            if optimize:
                self._optimize(Qd, Tau)
        self._X = Qd / self._hp['sx']
        self._R = Tau / self._hp['sy'] - self._prior_std(self._X)
        self._data_box = self._box_of(Qd)
        self._domain = self._make_domain(self._hull(self._data_box), self.domain_margin,
                                         self.blend_width)
        self._scale = 1.0
        self._leaves = None
        self._stale = False
        self._factorize()
        self._fitted = True
        self._enforce()
        self.fit_info_['fit_seconds'] = time.perf_counter() - t0
        return self

    def _init_hp(self, Qd, Tau, keep_kernel: bool) -> dict:
        N = Qd.shape[1]
        if self._kind == 'ard':
            mean = Tau.mean(axis=0)
            resid = Tau - mean
        else:
            mean = prior_mean_diag(Qd, Tau)
            resid = Tau - Qd * mean
        sx = _rms(Qd)
        sx = np.where(sx > 0, sx, 1.0)
        sy = _rms(resid)
        fallback = _rms(Tau)
        sy = np.where(sy > 1e-12 * np.maximum(fallback, 1e-300), sy,
                      np.where(fallback > 0, fallback, 1.0))
        E = len(self._elist)
        if keep_kernel:
            hp = {k: v.copy() for k, v in self._hp.items()}
            hp.update(sx=sx, sy=sy, mean=mean)
            return hp
        X = Qd / sx
        spread = np.std(X, axis=0)
        spread = np.where(spread > 1e-6, spread, 1.0)
        per_row = np.array([len(r) for r in self._rows], float)
        log_sf2 = np.array([-math.log(per_row[m]) for m, _ in self._elist])
        log_ls = np.tile(np.log(np.maximum(spread, 1e-2)), (E, 1))
        log_sn2 = np.full(N, math.log(1e-2))
        hp = dict(log_sf2=log_sf2, log_ls=log_ls, log_sn2=log_sn2, sx=sx, sy=sy, mean=mean)
        self._apply_fixed_noise(hp, N)
        return hp

    def _apply_fixed_noise(self, hp, N):
        if self.noise is None:
            return
        nz = np.broadcast_to(np.asarray(self.noise, float), (N,))
        if np.any(nz <= 0) or not np.all(np.isfinite(nz)):
            raise ValueError('noise must be positive and finite')
        hp['log_sn2'] = np.log((nz / hp['sy']) ** 2)

    def _bounds(self, X, m):
        spread = np.std(X, axis=0)
        spread = np.where(spread > 1e-6, spread, 1.0)
        # standardized units: residual RMS 1 and |x| ~ 1, so sf2 ~ 1 and lengthscales of order
        # the data spread; the absolute floor 1e-2 (1 % of the RMS velocity) keeps a fit on a
        # short stretch of data from learning lengthscales nothing later can be compared with
        b = []
        for _ in self._rows[m]:
            b.append((math.log(1e-8), math.log(1e2)))
        for _ in self._rows[m]:
            for d in range(X.shape[1]):
                lo = max(0.02 * spread[d], 1e-2)
                b.append((math.log(lo), math.log(max(1e3 * spread[d], 10 * lo))))
        # noise floor: 1e-3 of the residual RMS. Lower floors let K + sn2 I reach condition
        # numbers near 1/eps when the data are poorly excited, and O(n^2) updates then amplify
        # rounding (seen on the first second of an approach).
        b.append((math.log(_MIN_NOISE_VAR), math.log(10.0)))
        return b

    def _optimize(self, Qd, Tau):
        """Per-output log-marginal-likelihood maximization (outputs are independent)."""
        hp = self._hp
        rng = np.random.default_rng(self.random_state)
        n = Qd.shape[0]
        idx = np.arange(n)
        if n > self.max_opt_samples:
            idx = np.sort(rng.choice(n, self.max_opt_samples, replace=False))
        X = Qd[idx] / hp['sx']
        Rall = Tau[idx] / hp['sy'] - self._prior_std(X)
        N = X.shape[1]
        D2 = np.stack([(X[:, d][:, None] - X[:, d][None, :]) ** 2 for d in range(N)])
        fix_noise = self.noise is not None
        info = []
        for m in range(N):
            rows = self._rows[m]
            Em = len(rows)
            feats = [None if self._elist[e][1] is None else np.outer(X[:, self._elist[e][1]],
                                                                     X[:, self._elist[e][1]])
                     for e in rows]
            theta0 = np.concatenate([hp['log_sf2'][rows], hp['log_ls'][rows].ravel(),
                                     [hp['log_sn2'][m]]])
            bounds = self._bounds(X, m)
            if fix_noise:
                bounds[-1] = (theta0[-1], theta0[-1])
            fun = _LmlObjective(Rall[:, m], feats, D2, Em, N)
            best = None
            starts = [theta0]
            for _ in range(self.n_restarts):
                t = theta0 + rng.uniform(-1.5, 1.5, theta0.size)
                if fix_noise:
                    t[-1] = theta0[-1]
                starts.append(t)
            for t in starts:
                t = np.clip(t, [b[0] for b in bounds], [b[1] for b in bounds])
                with warnings.catch_warnings():
                    warnings.simplefilter('ignore')
                    res = minimize(fun, t, jac=True, method='L-BFGS-B', bounds=bounds,
                                   options=dict(maxiter=200))
                if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
                    best = res
            if best is not None:
                th = best.x
                hp['log_sf2'][rows] = th[:Em]
                hp['log_ls'][rows] = th[Em:Em + Em * N].reshape(Em, N)
                hp['log_sn2'][m] = th[-1]
                info.append(float(-best.fun))
        self.fit_info_['lml_per_output'] = info

    def log_marginal_likelihood(self) -> float:
        """Sum over outputs of the log marginal likelihood of the training data (standardized)."""
        self._check_fitted()
        n = self._X.shape[0]
        tot = 0.0
        for m in range(self.N):
            tot += (-0.5 * self._R[:, m] @ self._alpha[:, m]
                    - np.log(self._L[m].diag()).sum() - 0.5 * n * _LOG2PI)
        return float(tot)

    def _chol_limit(self) -> Optional[int]:
        return None if self.window is None else self.window + 1

    _KEEP_PARTS = 2000

    def _rkhs_sq(self) -> np.ndarray:
        """Per element ``|C_e|_H^2 = a^T K_e a``, ``a = x_n * alpha_m`` (K_e with sf2), for the
        current alpha: cached from ``_factorize``, else built (one n x n kernel per element)."""
        c = getattr(self, '_rkhs_cache', None)
        if c is not None and c[0] is self._alpha:
            return c[1]
        q = np.zeros(len(self._elist))
        for m in range(self.N):
            self._rkhs_of_parts(m, self._kparts(m, self._X, self._X), q)
        self._rkhs_cache = (self._alpha, q)
        return q

    def _rkhs_of_parts(self, m, parts, out):
        """``out[e] = alpha_m^T K_e alpha_m`` for output m's element kernels ``(e, K_e)``."""
        for e, k in parts:
            out[e] = float(self._alpha[:, m] @ (k @ self._alpha[:, m]))

    def _factorize(self):
        X = self._X
        n = X.shape[0]
        self._L = []
        self._alpha = np.zeros((n, self.N))
        self._jit = np.zeros(self.N)
        # the element kernels are kept while their output is factorized (n <= _KEEP_PARTS) so that
        # the RKHS norms of the certificate cost one matrix-vector product each, not a rebuild
        keep = n <= self._KEEP_PARTS
        rkhs_sq = np.zeros(len(self._elist))
        for m in range(self.N):
            parts = list(self._kparts(m, X, X)) if keep else []
            if keep and parts:
                K = parts[0][1].copy()
                for _, k in parts[1:]:
                    K += k
            else:
                K = self._kmat(m, X, X)
            K[np.diag_indices(n)] += math.exp(self._hp['log_sn2'][m])
            if not math.isfinite(float(K.sum())):     # NaN/inf anywhere reach the sum
                raise ValueError(f'kernel matrix of output {m} is not finite: hyper-parameters '
                                 f'or inputs out of range')
            L, j = _chol_jitter(K)
            wc = WindowCholesky(L, self._R[:, m], limit=self._chol_limit())
            self._L.append(wc)
            self._jit[m] = j
            self._alpha[:, m] = wc.alpha()
            self._rkhs_of_parts(m, parts, rkhs_sq)
            del parts, K
        self._rkhs_cache = (self._alpha, rkhs_sq) if keep else None
        self.jitter_ = float(self._jit.max())

    # ------------------------------------------------------------------ online update
    def update(self, qd, tau):
        """Append samples without a refit: O(n^2) per sample per output.

        qd, tau: (N,) or (k, N). Extends each output's Cholesky factor by one row; beyond
        ``window`` the oldest sample is removed by a rank-one update of the factor. Hyper-
        parameters, standardization and prior mean stay as fitted. The passivity guarantee of
        the model is re-established afterwards (see ``certificate``). Returns self.
        """
        self._check_fitted()
        Q, T = as_pair(qd if np.ndim(qd) == 2 else np.atleast_2d(qd),
                       tau if np.ndim(tau) == 2 else np.atleast_2d(tau), self.N)
        hp = self._hp
        sn2 = np.exp(hp['log_sn2'])
        for q, t in zip(Q, T):
            x = (q / hp['sx'])[None, :]
            r = t / hp['sy'] - self._prior_std(x)[0]
            for m in range(self.N):
                c = self._kmat(m, self._X, x)[:, 0]
                floor = sn2[m] + self._jit[m]
                self._L[m].append(c, self._kdiag(m, x)[0] + floor, floor, r[m])
            self._X = np.vstack([self._X, x])
            self._R = np.vstack([self._R, r[None, :]])
            if self.window is not None and self._X.shape[0] > self.window:
                for m in range(self.N):
                    self._L[m].drop_first()
                self._X = self._X[1:]
                self._R = self._R[1:]
        self._alpha = np.column_stack([self._L[m].alpha() for m in range(self.N)])
        if self.passivity == 'certified':
            self._grow_domain(Q)
        self._enforce(after_update=True)
        return self

    # ------------------------------------------------------------------ prediction
    def _check_fitted(self):
        if not self._fitted:
            raise RuntimeError(f'{type(self).__name__} is not fitted: call fit() first')

    def _blend(self, Q):
        """Blend weight w(q) in [0, 1]: 1 on the verified domain, 0 outside the outer box."""
        if self._cert is None or self._cert.method != 'domain-bnb+blend':
            return None
        (ilo, ihi), (olo, ohi) = self._domain
        t_lo = np.clip((Q - olo) / np.maximum(ilo - olo, 1e-300), 0.0, 1.0)
        t_hi = np.clip((ohi - Q) / np.maximum(ohi - ihi, 1e-300), 0.0, 1.0)
        t = np.minimum(t_lo, t_hi)
        s = t * t * t * (t * (6.0 * t - 15.0) + 10.0)       # C2 smootherstep
        return np.prod(s, axis=1)

    def _corr_weight(self, Q):
        w = self._blend(Q)
        s = self._scale
        return np.full(Q.shape[0], s) if w is None else s * w

    # k * n * E up to which all element kernels of a few queries (k <= 16) are built in one pass
    _CROSS_AT_ONCE = 2_000_000

    def _cross_elems(self, X):
        """Element kernels ``k_e(X, X_train)`` of every element at once, (E, k, n), by exact
        differences and one exp (the per-message path: one query against the buffer); None for
        large batches, which take the per-element GEMM path of ``_kmat``."""
        E = len(self._elist)
        if X.shape[0] > 16 or X.shape[0] * self._X.shape[0] * E > self._CROSS_AT_ONCE:
            return None                     # batches: one GEMM per element is faster
        hp = self._hp
        diff = X[:, None, :] - self._X[None, :, :]               # (k, n, N)
        diff *= diff
        K = diff @ np.exp(-2.0 * hp['log_ls']).T                  # (k, n, E) scaled sq. dist.
        K *= -0.5
        np.exp(K, out=K)
        K *= np.exp(hp['log_sf2'])
        return np.moveaxis(K, 2, 0)

    def _raw_predict(self, Q, return_var, Kel=None):
        hp = self._hp
        X = Q / hp['sx']
        if Kel is None:
            Kel = self._cross_elems(X)
        mean = self._prior_std(X).copy()
        wq = self._corr_weight(Q)
        var = np.zeros_like(X) if return_var else None
        for m in range(self.N):
            Ks = self._kmat(m, X, self._X, Kel=Kel)
            mean[:, m] += wq * (Ks @ self._alpha[:, m])
            if return_var:
                v = self._L[m].solve(Ks.T)
                var[:, m] = np.maximum(self._kdiag(m, X) - np.einsum('ij,ij->j', v, v), 0.0)
        tau = mean * hp['sy']
        if return_var:
            var = var * hp['sy'] ** 2
        return tau, var

    def predict(self, Qs, return_var: bool = False):
        """Posterior mean damping force at Qs (k, N) (or (N,)): returns (k, N) [and variance].

        In 'projected' mode the mean is projected onto ``{q^T tau >= 0}``; in 'paper' and
        'certified' it is the certified posterior (passive by construction). The variance is the
        GP posterior variance of the force (noise-free), (k, N), in force units squared.
        """
        self._check_fitted()
        Q = as_matrix(Qs, 'Qs', self.N)
        tau, var = self._raw_predict(Q, return_var)
        tau = self._passive_tau(Q, tau)
        return (tau, var) if return_var else tau

    def predict_with_damping(self, Qs):
        """``predict(Qs, return_var=True)`` and ``damping_matrix(Qs)`` in one pass over the
        training set (the element kernels are built once): returns (tau, var, D), D (k, N, N)
        or None for ArdGP. Identical to the two separate calls."""
        self._check_fitted()
        Q = as_matrix(Qs, 'Qs', self.N)
        Kel = self._cross_elems(Q / self._hp['sx'])
        tau, var = self._raw_predict(Q, True, Kel)
        D = None
        if self._kind != 'ard':
            D = self._passive_damping(Q, self._damping_unprojected(Q, Kel=Kel))
        return self._passive_tau(Q, tau), var, D

    def _passive_tau(self, Q, tau):
        if self.passivity == 'projected':
            tau = project_passive(Q, tau, self.projection_weights)
        elif self._stale:
            bad = np.einsum('ij,ij->i', Q, tau) < 0
            if np.any(bad):
                tau[bad] = Q[bad] * self._hp['mean']
                self.fit_info_['pointwise_fallbacks'] = (
                    self.fit_info_.get('pointwise_fallbacks', 0) + int(bad.sum()))
        return tau

    def damping_matrix(self, Qs):
        """Posterior damping matrix D(q), (k, N, N), with ``predict(q) = D(q) q`` (model units)."""
        self._check_fitted()
        Q = as_matrix(Qs, 'Qs', self.N)
        return self._passive_damping(Q, self._damping_unprojected(Q))

    def _passive_damping(self, Q, D):
        if self._stale:
            bad = np.einsum('ki,kij,kj->k', Q, D, Q) < 0
            D[bad] = np.diag(self._hp['mean'])
        if self.passivity == 'projected':
            tau = np.einsum('kij,kj->ki', D, Q)
            lam = projection_lambda(Q, tau, self.projection_weights)
            wi = np.ones(self.N) if self.projection_weights is None else self.projection_weights
            D = D + lam[:, None, None] * np.diag(wi)[None]
        return D

    def _damping_unprojected(self, Q, weight=None, Kel=None):
        hp = self._hp
        X = Q / hp['sx']
        if Kel is None:
            Kel = self._cross_elems(X)
        k = X.shape[0]
        D = np.zeros((k, self.N, self.N))
        idx = np.arange(self.N)
        D[:, idx, idx] = hp['mean']
        wq = self._corr_weight(Q) if weight is None else weight
        for e, (m, n) in enumerate(self._elist):
            sf2 = math.exp(hp['log_sf2'][e])
            if sf2 == 0.0:
                continue
            ke = se_ard(X, self._X, np.exp(hp['log_ls'][e]), sf2) if Kel is None else Kel[e]
            D[:, m, n] += wq * (ke @ (self._X[:, n] * self._alpha[:, m])) * hp['sy'][m] / hp['sx'][n]
        return D

    # ------------------------------------------------------------------ passivity
    def certificate(self) -> Certificate:
        """The passivity certificate of the current model (see ``passivity.Certificate``).

        Re-proves it first when ``update`` left it stale (see ``recertify``)."""
        self._check_fitted()
        if self._stale:
            self.recertify()
        return self._cert

    @property
    def certificate_stale(self) -> bool:
        """True after an ``update`` whose new weights the cheap bound could not certify."""
        return bool(self._stale)

    def recertify(self) -> Certificate:
        """Re-prove the structural certificate for the current weights ('certified' mode):
        domain branch-and-bound from the last proven partition, shrinking the correction if
        needed. Costs milliseconds to seconds; a no-op when nothing is stale."""
        self._check_fitted()
        if self._stale:
            t0 = time.perf_counter()
            self._stale = False
            self._enforce_certified_full(after_update=True)
            d = dict(self._cert.details)
            d['seconds'] = time.perf_counter() - t0
            self._cert = Certificate(self._cert.certified, self._cert.margin, self._cert.method,
                                     self._cert.domain, self._cert.correction_scale, d)
        return self._cert

    def _norm_margin(self, B):
        md = self._hp['mean']
        A = np.diag(md) - B
        s = np.sqrt(np.maximum(md, 1e-12 * max(md.max(), 1e-300)))
        return copositivity_margin(A / s[:, None] / s[None, :])

    def _l1_bound(self, rkhs: bool = True):
        """A-posteriori bound B_mn >= sup_q |D_mn(q) - m_mn| (model units), current alpha.

        Per element the smaller of the L1 bound ``sf2 * sum_i |x_{n,i} alpha_{m,i}|`` and the RKHS
        bound ``|g|_H sqrt(sf2)``, ``|g|_H^2 = a^T K_e a`` (reproducing property and
        Cauchy-Schwarz); both hold for every q."""
        hp = self._hp
        B = np.zeros((self.N, self.N))
        for e, (m, n) in enumerate(self._elist):
            sf2 = math.exp(hp['log_sf2'][e])
            if sf2 == 0.0:
                continue
            a = self._X[:, n] * self._alpha[:, m]
            l1 = sf2 * np.abs(a).sum()
            if not rkhs:            # O(n): the per-update check
                B[m, n] = l1 * hp['sy'][m] / hp['sx'][n]
                continue
            rk = math.sqrt(max(float(self._rkhs_sq()[e]), 0.0) * sf2)
            B[m, n] = min(l1, rk) * hp['sy'][m] / hp['sx'][n]
        return B

    def _paper_bound(self):
        """Theorem 1 bound with the sf^2 kernel bound: sf2_mn * sqrt(n) |x|_inf |dy_m| / s_eps^2."""
        hp = self._hp
        n = self._X.shape[0]
        xinf = float(np.abs(self._X).max())
        B = np.zeros((self.N, self.N))
        for e, (m, nn) in enumerate(self._elist):
            c = math.sqrt(n) * xinf * np.linalg.norm(self._R[:, m]) / math.exp(hp['log_sn2'][m])
            B[m, nn] = math.exp(hp['log_sf2'][e]) * c * hp['sy'][m] / hp['sx'][nn]
        return B

    def _max_scale(self, B, hi=1.0):
        """Largest s in [0, hi] with diag(m_d) - s B copositive (bisection; B >= 0)."""
        if self._norm_margin(hi * B) >= 0:
            return hi
        lo_s, hi_s = 0.0, hi
        for _ in range(50):
            mid = 0.5 * (lo_s + hi_s)
            if self._norm_margin(mid * B) >= 0:
                lo_s = mid
            else:
                hi_s = mid
        return lo_s

    def _switch_off_uncertifiable(self):
        """Elements touching a dimension whose prior damping is 0 can never be certified."""
        md = self._hp['mean']
        dead = md <= 1e-12 * max(md.max(), 1e-300)
        changed = False
        for e, (m, n) in enumerate(self._elist):
            if (dead[m] or dead[n]) and self._hp['log_sf2'][e] > -np.inf:
                self._hp['log_sf2'][e] = -np.inf
                changed = True
        return changed

    def _enforce(self, after_update: bool = False):
        mode = self.passivity
        t0 = time.perf_counter()
        if mode == 'projected':
            self._cert = Certificate(True, 0.0, 'projection', None, 1.0,
                                     {'note': 'every prediction projected onto q^T tau >= 0'})
            return
        if self._kind == 'ard':
            self._cert = Certificate(False, -np.inf, 'none', None, 1.0,
                                     {'note': 'ARD-GP has no damping structure'})
            return
        if mode == 'none':
            m = self._norm_margin(self._l1_bound(rkhs=not after_update))
            self._cert = Certificate(bool(m >= 0), float(m), 'a-posteriori-bound (not enforced)')
            return
        if mode == 'paper':
            self._enforce_paper(after_update)
        else:
            self._enforce_certified(after_update)
        d = dict(self._cert.details)
        d['seconds'] = time.perf_counter() - t0
        self._cert = Certificate(self._cert.certified, self._cert.margin, self._cert.method,
                                 self._cert.domain, self._cert.correction_scale, d)

    def _enforce_paper(self, after_update):
        if not after_update:
            if self._switch_off_uncertifiable():
                self._factorize()
            B1 = self._paper_bound()
            g = self._max_scale(B1)
            if g < 1.0:
                # scale every hyper-variance by g (least conservative, found by bisection)
                with np.errstate(divide='ignore'):
                    self._hp['log_sf2'] = self._hp['log_sf2'] + (math.log(g * (1 - 1e-9))
                                                                 if g > 0 else -np.inf)
                self._factorize()
            self._scale = 1.0
            self._hyper_scale = g
        B = self._paper_bound()
        s = self._max_scale(B, 1.0)
        self._scale = min(self._scale, s) if after_update else s
        margin = self._norm_margin(self._scale * B)
        method = 'paper-theorem1' if self._scale == 1.0 else 'paper-theorem1+shrink'
        self._cert = Certificate(bool(margin >= 0), float(margin), method, None, self._scale,
                                 {'hypervariance_scale': float(getattr(self, '_hyper_scale', 1.0))})

    def _terms(self, scale):
        hp = self._hp
        coef = np.stack([self._X[:, n] * self._alpha[:, m] * scale for m, n in self._elist])
        sf2 = np.exp(hp['log_sf2'])
        with np.errstate(divide='ignore', invalid='ignore'):
            rk = np.where(sf2 > 0, np.sqrt(np.maximum(self._rkhs_sq(), 0.0) / sf2), 0.0)
        return CorrectionTerms(self._X, self._elist, sf2, np.exp(hp['log_ls']),
                               coef, hp['mean'], hp['sx'], hp['sy'],
                               lambda Q: self._damping_unprojected(Q, np.full(Q.shape[0], scale)),
                               rkhs=abs(scale) * rk)

    def _grow_domain(self, Q):
        """Samples outside the verified box would only ever see the prior mean: grow the domain
        to the data the model now holds and mark the certificate stale (predictions stay passive
        pointwise until the next proof on the grown domain)."""
        (ilo, ihi), _ = self._domain
        if np.all((Q >= ilo) & (Q <= ihi)):
            return
        self._data_box = self._box_of(self.X_train_)
        self._domain = self._make_domain(self._hull(self._data_box), self.domain_margin,
                                         self.blend_width)
        self._leaves = None
        if self._cert is not None and self._cert.method == 'domain-bnb+blend':
            self._stale = True

    @staticmethod
    def _box_of(Qd):
        lo, hi = Qd.min(axis=0), Qd.max(axis=0)
        return lo, hi, np.maximum(hi - lo, np.maximum(0.1 * _rms(Qd), 1e-9))

    def _hull(self, box):
        """The data box joined with the declared operating domain (if any)."""
        if self.operating_domain is None:
            return box
        lo = np.minimum(box[0], self.operating_domain[0])
        hi = np.maximum(box[1], self.operating_domain[1])
        return lo, hi, np.maximum(hi - lo, box[2])

    @staticmethod
    def _make_domain(box, margin, blend):
        """Inner (verified, w = 1) and outer (w = 0 beyond) boxes from the data box."""
        lo, hi, rng = box
        ilo, ihi = lo - margin * rng, hi + margin * rng
        olo, ohi = ilo - blend * rng, ihi + blend * rng
        return (ilo, ihi), (olo, ohi)

    def _enforce_certified(self, after_update):
        """Structural certificate: global L1 bound, else domain branch-and-bound + blend,
        else the largest correction scale that one of them proves (bisection).

        After ``update`` only the cheap global bound is tried; if it does not hold the model is
        marked *stale*: predictions stay passive pointwise (a query with negative power falls
        back to the prior mean there) until ``recertify()`` (or ``certificate()``) re-proves the
        structural certificate, which the estimator does off its message path."""
        start = self._scale if after_update else 1.0
        B = self._l1_bound(rkhs=not after_update)
        m = self._norm_margin(start * B)
        if m >= 0:
            self._scale = start
            self._leaves = None
            self._stale = False
            self._cert = Certificate(True, float(m), 'a-posteriori-bound', None, start)
            return
        if after_update:
            self._stale = True
            return
        self._enforce_certified_full(after_update=False)

    def _enforce_certified_full(self, after_update):
        start = self._scale if after_update else 1.0
        B = self._l1_bound()
        if after_update:
            domains = [self._domain]
        else:
            # declared operating domain first (if any), then the data box alone
            boxes = [self._hull(self._data_box)]
            if self.operating_domain is not None:
                boxes.append(self._data_box)
            domains = [self._make_domain(b, f_m, f_b) for b in boxes for f_m, f_b in
                       ((self.domain_margin, self.blend_width),
                        (0.5 * self.domain_margin, 0.5 * self.blend_width),
                        (0.0, 0.25 * self.blend_width))]
        res = None
        for k, dom in enumerate(domains):
            (ilo, ihi), (olo, ohi) = dom
            budget = self.max_boxes
            res = verify_box(self._terms(start), olo, ohi, max_boxes=budget,
                             leaves=self._leaves if after_update else None)
            if res.ok:
                self._domain = dom
                self._scale = start
                self._leaves = res.leaves
                self._cert = Certificate(True, res.margin, 'domain-bnb+blend', (ilo, ihi), start,
                                         {'boxes': res.boxes, 'bnb_seconds': res.seconds,
                                          'outer_box': [olo.tolist(), ohi.tolist()]})
                return
        # shrink the correction on the smallest domain: the global L1 scale is always provable;
        # bisect above it with the domain proof
        self._domain = dom = domains[-1]
        (ilo, ihi), (olo, ohi) = dom
        s_lo = self._max_scale(B, start)
        s_hi = start
        best = None
        for _ in range(6):
            if s_hi - s_lo <= 0.02 * start:
                break
            mid = 0.5 * (s_lo + s_hi)
            r = verify_box(self._terms(mid), olo, ohi, max_boxes=max(self.max_boxes // 8, 500))
            if r.ok:
                s_lo, best = mid, r
            else:
                s_hi = mid
        self._scale = s_lo
        if best is not None:
            self._leaves = best.leaves
            self._cert = Certificate(True, best.margin, 'domain-bnb+blend', (ilo, ihi), s_lo,
                                     {'boxes': best.boxes, 'bnb_seconds': best.seconds,
                                      'outer_box': [olo.tolist(), ohi.tolist()],
                                      'reason': res.reason})
        else:
            self._leaves = None
            mm = self._norm_margin(s_lo * B)
            self._cert = Certificate(bool(mm >= 0), float(mm),
                                     'a-posteriori-bound' if s_lo > 0 else 'prior-only', None, s_lo,
                                     {'reason': res.reason})

    # ------------------------------------------------------------------ data access
    @property
    def n_samples_(self) -> int:
        return 0 if not self._fitted else int(self._X.shape[0])

    @property
    def X_train_(self) -> np.ndarray:
        self._check_fitted()
        return self._X * self._hp['sx']

    @property
    def Y_train_(self) -> np.ndarray:
        self._check_fitted()
        return (self._R + self._prior_std(self._X)) * self._hp['sy']

    @property
    def mean_diag_(self) -> np.ndarray:
        self._check_fitted()
        if self._kind == 'ard':
            raise AttributeError('ArdGP has a constant prior mean, see get_params()')
        return self._hp['mean'].copy()

    # ------------------------------------------------------------------ persistence
    def save(self, path) -> None:
        """Write the model to ``path`` (npz of plain arrays + a JSON header; no pickle),
        atomically: a reader sees the old file or the new one, never a half-written one."""
        self._check_fitted()
        arrays = {'X': self._X, 'R': self._R, 'alpha': self._alpha, 'jit': self._jit}
        for m, L in enumerate(self._L):
            arrays[f'L{m}'] = L.L
            arrays[f'z{m}'] = L.z
        for k, v in self._hp.items():
            arrays['hp_' + k] = np.asarray(v, float)
        (ilo, ihi), (olo, ohi) = self._domain
        arrays.update(dom_ilo=ilo, dom_ihi=ihi, dom_olo=olo, dom_ohi=ohi)
        if self._leaves is not None:
            arrays['leaves_lo'], arrays['leaves_hi'] = self._leaves
        params = self.get_params()
        params['hyperparams'] = None
        header = {'format': 'dgp_ros.gp', 'format_version': FORMAT_VERSION, 'kind': self._kind,
                  'N': self.N, 'params': params, 'scale': self._scale, 'stale': bool(self._stale),
                  'certificate': self._cert.to_dict()}
        header['sha256'] = _digest(arrays, header)
        arrays['header'] = np.array(json.dumps(header))
        path = os.fspath(path)
        d = os.path.dirname(os.path.abspath(path))
        fd, tmp = tempfile.mkstemp(prefix='.tmp-', suffix='.npz', dir=d)
        try:
            with os.fdopen(fd, 'wb') as f:
                np.savez(f, **arrays)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path):
        """Read a model written by ``save``. Raises ValueError for a file that is not a dgp_ros
        model, from an incompatible format version, of another model kind, truncated or
        modified after writing."""
        model = load_model(path)
        if cls is not _BaseGP and not isinstance(model, cls):
            raise ValueError(f'{path}: holds a {type(model).__name__}, not a {cls.__name__}')
        return model


class _LmlObjective:
    """Negative log marginal likelihood of one output and its analytic gradient (log params)."""

    def __init__(self, y, feats, D2, Em, N):
        self.y, self.feats, self.D2, self.Em, self.N = y, feats, D2, Em, N

    def __call__(self, theta):
        y, Em, N = self.y, self.Em, self.N
        n = y.size
        log_sf2 = theta[:Em]
        log_ls = theta[Em:Em + Em * N].reshape(Em, N)
        sn2 = math.exp(theta[-1])
        parts = []
        K = np.zeros((n, n))
        for j in range(Em):
            s = np.tensordot(np.exp(-2.0 * log_ls[j]), self.D2, axes=1)
            k = math.exp(log_sf2[j]) * np.exp(-0.5 * s)
            if self.feats[j] is not None:
                k *= self.feats[j]
            parts.append(k)
            K += k
        K[np.diag_indices(n)] += sn2
        try:
            L, _ = _chol_jitter(K)
        except LinAlgError:
            return 1e25, np.zeros_like(theta)
        alpha = cho_solve((L, True), y, check_finite=False)
        nll = 0.5 * y @ alpha + np.log(np.diag(L)).sum() + 0.5 * n * _LOG2PI
        Kinv = cho_solve((L, True), np.eye(n), check_finite=False)
        W = np.outer(alpha, alpha) - Kinv            # dL/dK * 2
        g = np.zeros_like(theta)
        for j in range(Em):
            Wk = W * parts[j]
            g[j] = -0.5 * Wk.sum()
            il2 = np.exp(-2.0 * log_ls[j])
            g[Em + j * N:Em + (j + 1) * N] = -0.5 * np.tensordot(self.D2, Wk, axes=([1, 2], [0, 1])) * il2
        g[-1] = -0.5 * sn2 * np.trace(W)
        return float(nll), g


def _digest(arrays: dict, header: dict) -> str:
    """SHA-256 over every array (name, dtype, shape, bytes) and the header (minus the digest)."""
    h = hashlib.sha256()
    h.update(json.dumps({k: v for k, v in header.items() if k != 'sha256'},
                        sort_keys=True).encode())
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode())
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


class FullDGP(_BaseGP):
    """Full-D-GP: every element ``d_mn(q)`` of the damping matrix an independent SE-ARD GP."""
    _kind = 'full'


class DiagDGP(_BaseGP):
    """Diag-D-GP: diagonal damping matrix, ``d_n(q)`` independent SE-ARD GPs."""
    _kind = 'diag'


class ArdGP(_BaseGP):
    """Baseline: an independent SE-ARD GP per output on ``q`` (constant prior mean)."""
    _kind = 'ard'

    def damping_matrix(self, Qs):
        raise NotImplementedError('ArdGP models the force directly and has no damping matrix')


_KINDS = {'full': FullDGP, 'diag': DiagDGP, 'ard': ArdGP}


def make_model(kind: str, **kw) -> _BaseGP:
    """Construct a model by name: 'full' | 'diag' | 'ard'."""
    if kind not in _KINDS:
        raise ValueError(f"unknown model kind {kind!r}: expected 'full', 'diag' or 'ard'")
    return _KINDS[kind](**kw)


def load_model(path) -> _BaseGP:
    """Load any model written by ``save`` (see ``_BaseGP.load`` for the errors)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ValueError(f'{path}: no such model file')
    try:
        with open(path, 'rb') as f:
            raw = f.read()
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except ValueError as exc:
        raise ValueError(f'{path}: not a dgp_ros model file ({exc})') from None
    except Exception as exc:  # zipfile.BadZipFile, EOFError, OSError, zlib errors
        raise ValueError(f'{path}: unreadable or truncated model file '
                         f'({type(exc).__name__}: {exc})') from None
    if 'header' not in arrays:
        raise ValueError(f'{path}: not a dgp_ros model file (no header)')
    try:
        header = json.loads(str(arrays.pop('header')))
    except json.JSONDecodeError as exc:
        raise ValueError(f'{path}: corrupt header ({exc})') from None
    if header.get('format') != 'dgp_ros.gp':
        raise ValueError(f'{path}: not a dgp_ros model file')
    if header.get('format_version') != FORMAT_VERSION:
        raise ValueError(f'{path}: model format version {header.get("format_version")} is not '
                         f'supported by this dgp_ros (expects {FORMAT_VERSION}); refit and save '
                         f'again')
    if _digest(arrays, header) != header.get('sha256'):
        raise ValueError(f'{path}: checksum mismatch: the model file was modified or damaged')
    kind = header.get('kind')
    if kind not in _KINDS:
        raise ValueError(f'{path}: unknown model kind {kind!r}')
    model = _KINDS[kind](**header['params'])
    N = int(header['N'])
    model._setup_structure(N)
    model._hp = {k[3:]: arrays[k] for k in arrays if k.startswith('hp_')}
    model._X, model._R, model._alpha = arrays['X'], arrays['R'], arrays['alpha']
    model._jit = arrays['jit']
    model.jitter_ = float(model._jit.max())
    model._L = [WindowCholesky(arrays[f'L{m}'], model._R[:, m], limit=model._chol_limit(),
                               z=arrays.get(f'z{m}'))
                for m in range(N)]
    model._domain = ((arrays['dom_ilo'], arrays['dom_ihi']), (arrays['dom_olo'], arrays['dom_ohi']))
    model._leaves = ((arrays['leaves_lo'], arrays['leaves_hi']) if 'leaves_lo' in arrays
                     else None)
    model._data_box = _BaseGP._box_of(model._X * model._hp['sx'])
    model._scale = float(header['scale'])
    model._stale = bool(header.get('stale', False))
    model._cert = Certificate.from_dict(header['certificate'])
    model._fitted = True
    return model

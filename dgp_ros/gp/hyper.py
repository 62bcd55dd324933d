"""
Hyper-parameter learning: type-II maximum likelihood, one output at a time.

The outputs of a D-GP are independent GPs, so the log marginal likelihood is a sum over outputs
and each output's kernel parameters (``log sf2`` per element, ``log l`` per element and input
dimension, ``log s_eps^2``) are optimized on their own (L-BFGS-B, analytic gradients, restarts).
Data are standardized (``posterior``), so the bounds below are in units of the data spread.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence
import warnings

import numpy as np
from scipy.linalg.blas import dsymm, dsyr
from scipy.linalg.lapack import dpotrf, dpotri, dpotrs
from scipy.optimize import minimize

from ._chol import JITTER_STEPS
from .kernels import _EXP_FLOOR, Structure
from .means import make_mean, mean_from_dict, ViscousMean
from .posterior import Hyper

__all__ = ['LmlObjective', 'initial_hyper', 'learn_hyper', 'MIN_NOISE_VAR',
           'hyper_from_params']

_LOG2PI = math.log(2.0 * math.pi)
# noise floor, standardized units (noise std >= 1e-3 of the residual RMS). Lower floors let
# K + sn2 I reach condition numbers near 1/eps on poorly excited data, and O(n^2) updates then
# amplify rounding.
MIN_NOISE_VAR = 1e-6


def _rms(A: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(A * A, axis=0)) if A.shape[0] else np.zeros(A.shape[1])


def scales(Qd: np.ndarray, resid: np.ndarray, Tau: np.ndarray):
    """
    Standardization ``(s_x, s_y)``.

    RMS of the velocities and of the residual after the prior (falling back to the RMS of the
    force, then 1, where one is 0).
    """
    sx = _rms(Qd)
    sx = np.where(sx > 0, sx, 1.0)
    sy = _rms(resid)
    fallback = _rms(Tau)
    sy = np.where(sy > 1e-12 * np.maximum(fallback, 1e-300), sy,
                  np.where(fallback > 0, fallback, 1.0))
    return sx, sy


def initial_hyper(structure: Structure, Qd: np.ndarray, resid: np.ndarray, Tau: np.ndarray,
                  noise=None) -> Hyper:
    """
    Data-driven starting point.

    ``sf2 = 1 / (elements per output)``, lengthscales = input spread, noise variance 1e-2 (or the
    fixed ``noise`` std, force units, per output).
    """
    N = Qd.shape[1]
    sx, sy = scales(Qd, resid, Tau)
    X = Qd / sx
    spread = np.std(X, axis=0)
    spread = np.where(spread > 1e-6, spread, 1.0)
    per_row = np.array([len(r) for r in structure.rows], float)
    log_sf2 = np.array([-math.log(per_row[m]) for m, _ in structure.elems])
    log_ls = np.tile(np.log(np.maximum(spread, 1e-2)), (structure.E, 1))
    log_sn2 = np.full(N, math.log(1e-2))
    hp = Hyper(log_sf2, log_ls, log_sn2, sx, sy)
    apply_fixed_noise(hp, noise)
    return hp


def apply_fixed_noise(hp: Hyper, noise) -> None:
    """Set ``log_sn2`` from a fixed noise std (force units, scalar or (N,)); None: no change."""
    if noise is None:
        return
    nz = np.broadcast_to(np.asarray(noise, float), hp.sy.shape)
    if np.any(nz <= 0) or not np.all(np.isfinite(nz)):
        raise ValueError('noise must be positive and finite')
    hp.log_sn2 = np.log((nz / hp.sy) ** 2)


#: signal-variance floor (standardized units) of an element whose feature never came near zero
#: in the data; scaled by the square of its ``PERSISTENT_QUANTILE`` quantile (``_sf2_floor``)
PERSISTENT_SF2 = 1e-2
PERSISTENT_QUANTILE = 0.05


def _sf2_floor(structure: Structure, X: np.ndarray, e: int) -> float:
    """
    Least signal variance of element ``e`` (standardized units): how far it may be switched off.

    An element ``(m, n)`` contributes ``x_n f_mn(x)``: where ``x_n`` never comes near zero in the
    data (the airspeed of an aircraft, ``|x_n|`` at its 5 % quantile close to its RMS), it can
    carry a force the other elements of row ``m`` cannot carry where *their* features vanish,
    and data that never visited that place cannot tell the two apart. Switched off (``sf2 ->
    1e-8``; a warm start never brings it back, the gradient vanishes with ``sf2``), the model
    answers such a place by one element's feature times a weight that must explode: on an A320
    approach whose first seconds stayed at positive angles of attack, lift and drag carried by
    the alpha elements alone were off by up to a standard deviation, sample by sample, the first
    time alpha crossed zero. So such an element keeps ``PERSISTENT_SF2 q^2`` (``q`` = the
    quantile of ``|x_n|`` over its RMS): none for a joint velocity that reverses (an arm's), the
    full floor for one that never goes near zero. ARD elements (``phi = 1``) keep ``1e-8``.
    """
    n = structure.elems[e][1]
    if n is None or not X.shape[0]:
        return 1e-8
    a = np.abs(X[:, n])
    rms = float(np.sqrt(np.mean(a * a)))
    if rms <= 0.0:
        return 1e-8
    q = float(np.quantile(a, PERSISTENT_QUANTILE)) / rms
    return max(1e-8, PERSISTENT_SF2 * q * q)


def persistent(structure: Structure, X: np.ndarray, e: int) -> bool:
    """Tell whether element e's feature stays away from zero in X (``_sf2_floor``)."""
    return _sf2_floor(structure, X, e) >= PERSISTENT_SF2 * PERSISTENT_LEVEL ** 2


#: ``persistent`` at this fraction of the RMS in the quantile (every refit's buffer): arm joints
#: <= 0.48 (closed-loop Panda; 0.3 coupled it), 0.13 (real Panda), 0.53 (real UR10); A320 airspeed
#: >= 0.69 (0.7 dropped the 20 m/s flight's couplings at 33 s: NMSE 1.4e-3 -> 0.35)
PERSISTENT_LEVEL = 0.6


def _bounds(structure: Structure, X: np.ndarray, m: int, noise_floor: float = MIN_NOISE_VAR,
            rows: Optional[Sequence[int]] = None):
    """
    L-BFGS-B bounds of output m's parameter vector (see ``LmlObjective``).

    Standardized units: residual RMS 1 and |x| ~ 1, so sf2 ~ 1 and lengthscales of order the
    data spread; the absolute floor 1e-2 (1 % of the RMS velocity) keeps a fit on a short stretch
    of data from learning lengthscales nothing later can be compared with. The signal variance of
    an element whose feature stays away from zero has a floor (``_sf2_floor``). The noise variance
    is at least ``noise_floor`` (standardized units). ``rows``: the output's elements that are
    optimized (default all of them).
    """
    spread = np.std(X, axis=0)
    spread = np.where(spread > 1e-6, spread, 1.0)
    rows = structure.rows[m] if rows is None else rows
    b = [(math.log(_sf2_floor(structure, X, e)), math.log(1e2)) for e in rows]
    for _ in rows:
        for d in range(X.shape[1]):
            lo = max(0.02 * spread[d], 1e-2)
            b.append((math.log(lo), math.log(max(1e3 * spread[d], 10 * lo))))
    b.append((math.log(noise_floor), math.log(10.0)))
    return b


class LmlObjective:
    """
    Negative log marginal likelihood of one output and its analytic gradient.

    Parameters
    ----------
    X : (n, N) standardized inputs;  y : (n,) standardized residuals of the output
    elems : per element of the output, its feature column n (``phi_e = x_n``) or None
        (``phi = 1``, ARD)
    tied : bool
        One lengthscale vector shared by the output's elements.

    ``theta = [log sf2 (Em), log l (Em * N element-major, or N when tied), log s_eps^2]``;
    ``__call__(theta) -> (nll, grad)``, ``(1e25, zeros)`` when K is not positive definite even
    with the jitter of ``_chol.chol_jitter``.

    Per element one GEMM gives the exponent (centred inputs, clipped to [-600, log sf2]: no
    denormals), exponentiated in place and multiplied by the shared feature product; K is
    factored in place (``dpotrf``), ``K^-1`` by ``dpotri`` and ``W = alpha alpha^T - K^-1`` by one
    ``dsyr``. The gradient per element is one Hadamard product and one ``dsymm`` with
    ``[X, 1]``, using ``sum_ij A_ij (x_id - x_jd)^2 = 2 sum_i x_id^2 (A 1)_i - 2 (X^T A X)_dd``
    for the symmetric ``A = W o P_e``: no (N, n, n) tensor, no identity solve, preallocated
    buffers. Tied: one exponent per evaluation; ``K0 = (Phi diag(sf2) Phi^T) o k``.

    """

    def __init__(self, X: np.ndarray, y: np.ndarray, elems: Sequence[Optional[int]],
                 N: Optional[int] = None, tied: bool = False):
        X = np.ascontiguousarray(X, dtype=float)
        n, Nx = X.shape
        self.N = Nx if N is None else int(N)
        if self.N != Nx:
            raise ValueError(f'X has {Nx} columns, N = {self.N}')
        self.n, self.elems, self.tied = n, list(elems), bool(tied)
        self.Em = Em = len(self.elems)
        self.y = np.asarray(y, dtype=float).reshape(n)
        self.yF = np.asfortranarray(self.y.reshape(n, 1))
        Xc = X - X.mean(axis=0)
        self.Xc = Xc
        self.Xc2 = Xc * Xc
        self.X1 = np.asfortranarray(np.column_stack([Xc, np.ones(n)]))     # for dsymm
        self.h0 = np.einsum('ij,ij->i', Xc, Xc)
        self.Ua = np.empty((n, self.N + 2))
        self.VaT = np.empty((self.N + 2, n))
        self.K = np.empty((n, n), order='F')
        self.A = np.empty((n, n), order='F')
        feats = sorted({k for k in self.elems if k is not None})
        if not tied:
            # shared feature outer products x_n x_n^T (symmetric: any memory order)
            self.F = {k: np.outer(X[:, k], X[:, k]) for k in feats}
            self.P = np.empty((Em, n, n))            # element kernels, C-ordered (symmetric)
            self.n_params = Em + Em * self.N + 1
        else:
            self.Phi = np.asfortranarray(np.column_stack(
                [np.ones(n) if k is None else X[:, k] for k in self.elems]))
            self.k = np.empty((n, n))                 # exp(-d^2/2), symmetric
            self.F = np.empty((n, n))                 # Phi diag(sf2) Phi^T
            self.K0 = np.empty((n, n))
            self.n_params = Em + self.N + 1

    # ------------------------------------------------------------------ kernel pieces
    def _exponent(self, ls: np.ndarray, lsf2: float, out: np.ndarray) -> np.ndarray:
        """
        Compute out (n, n) = clip(lsf2 - |u_i - u_j|^2 / 2, floor, lsf2).

        With u = Xc / ls (one GEMM).
        """
        N = self.N
        U = self.Xc / ls
        h = -0.5 * np.einsum('ij,ij->i', U, U)
        Ua, VaT = self.Ua, self.VaT
        Ua[:, :N] = U
        Ua[:, N] = lsf2 + h
        Ua[:, N + 1] = 1.0
        VaT[:N] = U.T
        VaT[N] = 1.0
        VaT[N + 1] = h
        np.matmul(Ua, VaT, out=out)
        np.clip(out, _EXP_FLOOR, lsf2, out=out)
        return out

    def _factor(self, build_K, sn2: float):
        """
        Factor the kernel matrix with jitter.

        dpotrf of K + (sn2 + j) I with chol_jitter's escalation; build_K(Kbuf) writes the
        noise-free kernel (full square, symmetric). Returns (c, j) or (None, None).
        """
        K = self.K
        build_K(K)
        base = None
        for rel in JITTER_STEPS:
            if base is None:
                d = K.diagonal()
                base = float(np.mean(d)) + sn2
                base = base or 1.0
            else:
                build_K(K)
            j = rel * base
            K.flat[::self.n + 1] += sn2 + j
            c, info = dpotrf(K, lower=1, clean=0, overwrite_a=1)
            if info == 0:
                return c, j
        return None, None

    # ------------------------------------------------------------------ objective
    def __call__(self, theta: np.ndarray):
        theta = np.asarray(theta, dtype=float)
        return self._tied(theta) if self.tied else self._untied(theta)

    def _common(self, c, j):
        """nll, W (lower triangle, in c's storage) from the factor c."""
        n = self.n
        alpha, info = dpotrs(c, self.yF, lower=1)
        alpha = alpha[:, 0]
        nll = (0.5 * float(self.y @ alpha) + float(np.log(c.diagonal()).sum())
               + 0.5 * n * _LOG2PI)
        Kinv, info = dpotri(c, lower=1, overwrite_c=1)
        np.negative(Kinv, out=Kinv)
        W = dsyr(1.0, alpha, lower=1, a=Kinv, overwrite_a=1)      # alpha alpha^T - K^-1
        return nll, W

    def _untied(self, theta):
        Em, N = self.Em, self.N
        log_sf2 = theta[:Em]
        log_ls = theta[Em:Em + Em * N].reshape(Em, N)
        sn2 = math.exp(theta[-1])
        P = self.P
        for e in range(Em):
            self._exponent(np.exp(log_ls[e]), float(log_sf2[e]), P[e])
            np.exp(P[e], out=P[e])
            k = self.elems[e]
            if k is not None:
                P[e] *= self.F[k]

        def build(K):
            KT = K.T                                   # C view; K symmetric
            if Em == 1:
                np.copyto(KT, P[0])
            else:
                np.add(P[0], P[1], out=KT)
                for e in range(2, Em):
                    KT += P[e]

        c, j = self._factor(build, sn2)
        if c is None:
            return 1e25, np.zeros_like(theta)
        nll, W = self._common(c, j)
        g = np.empty_like(theta)
        A = self.A
        for e in range(Em):
            np.multiply(W, P[e].T, out=A)             # lower triangle valid
            G = dsymm(1.0, A, self.X1, lower=1)        # (n, N + 1): [A Xc, A 1]
            rs = G[:, N]
            g[e] = -0.5 * rs.sum()
            quad = 2.0 * (self.Xc2.T @ rs) - 2.0 * np.einsum('id,id->d', self.Xc, G[:, :N])
            g[Em + e * N:Em + (e + 1) * N] = -0.5 * quad * np.exp(-2.0 * log_ls[e])
        g[-1] = -0.5 * sn2 * float(W.diagonal().sum())
        return float(nll), g

    def _tied(self, theta):
        Em, N = self.Em, self.N
        sf2 = np.exp(theta[:Em])
        log_ls = theta[Em:Em + N]
        sn2 = math.exp(theta[-1])
        k, F, K0 = self.k, self.F, self.K0
        self._exponent(np.exp(log_ls), 0.0, k)
        np.exp(k, out=k)
        Phi = self.Phi
        np.matmul(Phi * sf2, Phi.T, out=F)
        np.multiply(F, k, out=K0)

        def build(K):
            np.copyto(K.T, K0)

        c, j = self._factor(build, sn2)
        if c is None:
            return 1e25, np.zeros_like(theta)
        nll, W = self._common(c, j)
        g = np.empty_like(theta)
        A = self.A
        np.multiply(W, k.T, out=A)                     # B = W o k (lower triangle)
        BPhi = dsymm(1.0, A, Phi, lower=1)
        g[:Em] = -0.5 * sf2 * np.einsum('ie,ie->e', Phi, BPhi)
        A *= F.T                                       # W o K0
        G = dsymm(1.0, A, self.X1, lower=1)
        rs = G[:, N]
        quad = 2.0 * (self.Xc2.T @ rs) - 2.0 * np.einsum('id,id->d', self.Xc, G[:, :N])
        g[Em:Em + N] = -0.5 * quad * np.exp(-2.0 * log_ls)
        g[-1] = -0.5 * sn2 * float(W.diagonal().sum())
        return float(nll), g


#: L-BFGS-B stops when the objective changes by less than this, relative: the final optimum
FTOL = 2.2e-9
#: ... and the starts, which only have to show which basin is best
FTOL_START = 1e-4


def _minimize(fun, theta, bounds, maxiter, ftol):
    theta = np.clip(theta, [b[0] for b in bounds], [b[1] for b in bounds])
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        return minimize(fun, theta, jac=True, method='L-BFGS-B', bounds=bounds,
                        options={'maxiter': maxiter, 'ftol': ftol})


def _best(fun, starts, bounds, maxiter, count, ftol=None):
    best = None
    for t in starts:
        res = _minimize(fun, t, bounds, maxiter, FTOL if ftol is None else ftol)
        count[0] += int(res.nfev)
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    return best


#: a lengthscale at or above this is pinned (not learned): the element ignores that velocity
#: (``select``: an output's own element that depends on its own velocity alone)
PINNED_LOG_LS = math.log(1e9)

#: floor of log sf2 while the untied parameters are refined after the tied warm-up, so that an
#: element the warm-up switched off (sf2 -> 0) can come back
UNTIE_LOG_SF2_FLOOR = -4.6


def learn_hyper(structure: Structure, hp: Hyper, Qd: np.ndarray, resid: np.ndarray, *,
                fix_noise: bool = False, n_restarts: int = 2, max_samples: int = 300,
                random_state: int = 0, maxiter: int = 200, warm: bool = False,
                schedule: str = 'untied', refine_iter: int = 200,
                noise_floor: float = MIN_NOISE_VAR) -> tuple:
    """
    Maximize the log marginal likelihood of each output, starting from ``hp``.

    Qd : (n, N) velocities; resid : (n, N) residuals after the prior mean (model units); at most
    ``max_samples`` random samples are used.

    Per output, L-BFGS-B from ``1 + n_restarts`` starts (``hp`` and random perturbations of it),
    each to a loose tolerance (``FTOL_START``); the best is then polished to ``FTOL``.
    ``warm``: ``hp`` is a previous optimum; refine it from there without restarts
    (``refine_iter`` iterations at most). ``schedule='tied'`` (outputs with several elements):
    the starts optimize one lengthscale vector shared by the output's elements (one exp per
    evaluation), then every element's own lengthscales are refined from the best of them
    (``log sf2 >= -4.6`` meanwhile, so a switched-off element can return); cheaper, but it
    reached a lower likelihood on the simulated arm (docs/BENCHMARKS.md). ``noise_floor``: the
    least noise variance, standardized units (``MIN_NOISE_VAR`` by default).

    Elements switched off (``log_sf2 = -inf``) stay off and are not optimized; lengthscales at
    ``PINNED_LOG_LS`` or above stay as they are (the element ignores that velocity). Returns
    ``(hyper, info)``; ``info`` holds the LML per output (standardized units) and the number of
    objective evaluations.
    """
    hp = hp.copy()
    rng = np.random.default_rng(random_state)
    n = Qd.shape[0]
    idx = np.arange(n)
    if n > max_samples:
        idx = np.sort(rng.choice(n, max_samples, replace=False))
    X = Qd[idx] / hp.sx
    Rall = resid[idx] / hp.sy
    N = X.shape[1]
    jobs = []
    for m in range(structure.N):
        # an element switched off (log sf2 = -inf: ``select``, or the paper's certificate)
        # stays off; an output with none left is its prior mean alone: nothing to learn
        rows = [e for e in structure.rows[m] if np.isfinite(hp.log_sf2[e])]
        if not rows:
            continue
        theta0 = np.concatenate([hp.log_sf2[rows], hp.log_ls[rows].ravel(), [hp.log_sn2[m]]])
        kicks = [rng.uniform(-1.5, 1.5, theta0.size) for _ in range(0 if warm else n_restarts)]
        jobs.append((m, rows, theta0, kicks))

    def optimize(job):
        m, rows, theta0, kicks = job
        Em = len(rows)
        elems = [structure.elems[e][1] for e in rows]
        fun = LmlObjective(X, Rall[:, m], elems, N)
        bounds = _bounds(structure, X, m, noise_floor, rows)
        pinned = np.flatnonzero(theta0[Em:-1] >= PINNED_LOG_LS - 1e-9)
        for i in pinned:                # a pinned lengthscale stays where it is
            bounds[Em + i] = (theta0[Em + i], theta0[Em + i])
            for k in kicks:
                k[Em + i] = 0.0
        if fix_noise:
            bounds[-1] = (theta0[-1], theta0[-1])
            for k in kicks:
                k[-1] = 0.0
        count = [0]
        if warm:
            best = _best(fun, [theta0], bounds, refine_iter, count)
        elif Em > 1 and schedule == 'tied':
            tied = LmlObjective(X, Rall[:, m], elems, N, tied=True)
            t0 = np.concatenate([theta0[:Em], theta0[Em:-1].reshape(Em, N).mean(axis=0),
                                 theta0[-1:]])
            tb = bounds[:Em] + bounds[Em:Em + N] + bounds[-1:]
            starts = [t0] + [t0 + np.concatenate([k[:Em], k[Em:Em + N], k[-1:]])
                             for k in kicks]
            bt = _best(tied, starts, tb, maxiter, count)
            start = theta0 if bt is None else np.concatenate(
                [np.maximum(bt.x[:Em], UNTIE_LOG_SF2_FLOOR), np.tile(bt.x[Em:Em + N], Em),
                 bt.x[-1:]])
            rb = [(max(lo, UNTIE_LOG_SF2_FLOOR), hi) for lo, hi in bounds[:Em]] + bounds[Em:]
            best = _best(fun, [start], rb, refine_iter, count)
        else:
            best = _best(fun, [theta0] + [theta0 + k for k in kicks], bounds, maxiter, count,
                         FTOL_START)
            if best is not None and FTOL_START > FTOL:
                best = _best(fun, [best.x], bounds, maxiter, count)
        return m, rows, best, count[0]

    results = [optimize(j) for j in jobs]
    lml, evals = [], 0
    for m, rows, best, count in results:
        evals += count
        if best is None:
            continue
        Em = len(rows)
        th = best.x
        hp.log_sf2[rows] = th[:Em]
        hp.log_ls[rows] = th[Em:Em + Em * N].reshape(Em, N)
        hp.log_sn2[m] = th[-1]
        lml.append(float(-best.fun))
    return hp, {'lml_per_output': lml, 'evaluations': evals}


def hyper_from_params(d: dict, kind: str):
    """(Hyper, PriorMean) from a ``hyperparams_`` dict; ValueError when malformed."""
    if not isinstance(d, dict):
        raise ValueError("hyperparams must be a dict (a fitted model's hyperparams_)")
    hp = Hyper.from_dict(d)
    m = d.get('mean')
    if isinstance(m, dict):
        mean = mean_from_dict(m, hp.sx.size)
    else:                       # a bare m_d vector (tests, hand-written starts)
        if m is None:
            raise ValueError("hyperparams is missing ['mean']")
        mean = make_mean('viscous', kind)
        arr = np.asarray(m, float)
        if isinstance(mean, ViscousMean):
            mean.m_d = arr
        else:
            mean.value = arr
        mean.bias = np.zeros(hp.sx.size)
    Structure.of(kind, hp.sx.size)
    Hyper.from_dict(d, Structure.of(kind, hp.sx.size))
    return hp, mean

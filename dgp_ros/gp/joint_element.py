"""
The per-joint element of D learned from every sample: a reduced-rank GP on the joint's velocity.

Each joint j may carry, beside its parametric friction, an element of its damping diagonal

    e_j(v) = s_j(v) g_j(v),   s_j(v) = tanh(v / eps_j),   g_j ~ GP(0, k_SE),

learned from the sufficient statistics of *all* the samples (the long history keeps them:
``dgp_ros.dynamics.history``), in bounded memory and constant time per sample. ``s`` makes the
element vanish at rest (a damping force), ``g`` may be asymmetric in the direction of motion.

**Basis** (Solin and Saerkkae, Statistics and Computing 2020: Hilbert-space reduced-rank GP).
``g`` is expanded in the Dirichlet eigenfunctions of ``[-1, 1]`` in a warped velocity
``u = v / sqrt(v^2 + vc^2)`` (``vc``: the joint's velocity scale, fixed when the history starts):

    g(v) = sum_k w_k sin(omega_k (u + 1)),   omega_k = pi k / 2,   k = 1..M,

with ``w_k ~ N(0, S(omega_k))``, ``S`` the SE spectral density. The warp maps every velocity into
the fixed domain, finest near rest where friction is most nonlinear; the basis vanishes at
``u = +-1``, i.e. as ``|v| -> inf``: beyond the velocities the data reached the element fades and
the parametric part answers alone. The columns do not depend on the hyper-parameters, so the
statistics ``Phi^T Phi`` and ``Phi^T y`` of every sample serve every candidate.

**Fit** (:func:`fit_elements`). The element learns what the parametric part leaves, with a free
offset per joint as a nuisance (fitted, never served: an offset is not damping, and without it
an offset the parametric part left out would be learned as a fake friction ``b sign(v)``). The
hyper-parameters (a lengthscale in ``u`` and the ratio of the prior variance to the noise
variance) are chosen from a small grid by forward-chaining cross-validation on the history's
blocks; a joint keeps its element only where it predicts those newest blocks better than the
parametric part alone (the score is reported: ``scores``).

**Passivity** (:class:`JointElementMean`). The element enters the D-GP's prior mean:
``m_d,j(v) = max(m_param,j(v) + e_j(v) / v, 0)``, so ``m_d >= 0`` everywhere: the prior stays
passive by construction (the paper's Assumption 2) and every certificate of the D-GP applies to
it, with rigorous interval bounds of ``m_d`` over boxes (``diag_bounds``) and its infimum
(``diag_inf``). Pure numpy/scipy; no rclpy.
"""
from __future__ import annotations

from typing import List, Optional, Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve, LinAlgError

from .means import mean_from_dict, PriorMean, register_mean

__all__ = ['M_BASIS', 'LENGTHSCALES', 'RATIOS', 'VelocityBasis', 'ElementFold', 'ElementFit',
           'fit_elements', 'agreement', 'JointElementMean', 'element_joints']

#: basis functions per joint
M_BASIS = 32
#: candidate lengthscales of g in the warped velocity u (domain [-1, 1])
LENGTHSCALES = (0.05, 0.1, 0.2, 0.4)
#: candidate peak prior variances of the weights over the noise variance of one sample
RATIOS = (0.01, 0.1, 1.0, 10.0, 100.0)
#: prior variance of the nuisance offset over the noise variance (nearly free)
OFFSET_RATIO = 1e6
#: the smoothing of the element's sign as a fraction of vc, and its ceiling (velocity units)
EPS_FRACTION, EPS_MAX = 0.05, 0.02
#: a joint keeps its element only where the two halves of the run disagree on it by less
#: than this (``agreement``), each half holding at least ``MIN_HALF_SAMPLES`` samples of it
AGREEMENT, MIN_HALF_SAMPLES = 0.7, 150
#: ... and where its error on the history's newest blocks is below this times the parametric
#: part's alone (1.05 let the real UR10's wrist 2 on: 1.29x worse held out)
CV_TOLERANCE = 1.0
#: sub-intervals of u in which ``diag_inf`` bounds the element
INF_CELLS = 512


class VelocityBasis:
    """
    The element's columns per joint (module docstring).

    vc : (N,) velocity scale of each joint's warp (> 0, velocity units); eps : (N,) smoothing
    of the sign (> 0); M : basis functions per joint.
    """

    def __init__(self, vc, eps=None, M: int = M_BASIS):
        self.vc = np.asarray(vc, float).copy()
        if self.vc.ndim != 1 or not np.all(np.isfinite(self.vc)) or np.any(self.vc <= 0):
            raise ValueError(f'vc must be (N,) finite and > 0, got {vc!r}')
        self.eps = np.minimum(EPS_FRACTION * self.vc, EPS_MAX) if eps is None else \
            np.asarray(eps, float).copy()
        if self.eps.shape != self.vc.shape or np.any(~(self.eps > 0)):
            raise ValueError('eps must be (N,) and > 0')
        self.M = int(M)
        self.omega = np.pi * np.arange(1, self.M + 1) / 2.0

    @classmethod
    def for_velocities(cls, V: np.ndarray, M: int = M_BASIS) -> 'VelocityBasis':
        """Make the basis from the first velocities seen, (k, N): ``vc`` their largest speed."""
        a = np.max(np.abs(np.asarray(V, float)), axis=0)
        top = float(a.max()) if a.size else 0.0
        # a joint that has not moved yet takes a tenth of the fastest one's scale (or 1)
        floor = 0.1 * top if top > 0 else 1.0
        return cls(np.where(a > 1e-9 * max(top, 1e-300), a, floor), M=M)

    @property
    def N(self) -> int:
        return self.vc.size

    def warp(self, V: np.ndarray) -> np.ndarray:
        """Warped velocities ``u`` in (-1, 1), shape of V (..., N)."""
        return V / np.sqrt(V * V + self.vc * self.vc)

    def sines(self, U: np.ndarray) -> np.ndarray:
        """``sin(omega_k (u + 1))`` of warped velocities U (..., N): (..., N, M)."""
        return np.sin(self.omega * (U[..., None] + 1.0))

    def columns(self, V: np.ndarray) -> np.ndarray:
        """Return the columns ``s(v) sin(omega_k (u + 1))`` at velocities V (k, N): (k, N, M)."""
        V = np.asarray(V, float)
        return np.tanh(V / self.eps)[..., None] * self.sines(self.warp(V))

    def spectrum(self, lengthscale: float) -> np.ndarray:
        """Prior variances of the weights, peak-normalized to 1, at a lengthscale in u: (M,)."""
        s = np.exp(-0.5 * (lengthscale * self.omega) ** 2)
        return s / s.max()

    def to_dict(self) -> dict:
        return {'vc': self.vc.tolist(), 'eps': self.eps.tolist(), 'M': self.M}

    @classmethod
    def from_dict(cls, d: dict) -> 'VelocityBasis':
        return cls(d['vc'], d['eps'], int(d['M']))


class ElementFold:
    """
    One joint's normal equations of a cross-validation fold (or of all of it, ``test`` None).

    G : (M + 1, M + 1) and b : (M + 1,) of the training part, columns ``[Phi, 1]`` against
    what the parametric part leaves; test : (PhiPhi (M, M), Phi y (M,), y y) of the scored
    block against what the same parametric fit leaves there (the offset is not applied).
    """

    __slots__ = ('G', 'b', 'test')

    def __init__(self, G: np.ndarray, b: np.ndarray, test: Optional[tuple] = None):
        self.G, self.b, self.test = G, b, test


class ElementFit:
    """
    The fitted elements of all joints: which are on, their weights and what decided it.

    W : (N, M) weights (rows of joints without an element are zero); on : (N,) bools;
    scores : (N,) the best CV error over the parametric part's alone on the newest blocks
    (NaN: no folds yet); lengthscale, ratio : (N,) the hyper-parameters chosen; agreement :
    (N,) how much two halves of the run disagree on the element (``agreement``; NaN while a
    half holds too few samples).
    """

    def __init__(self, basis: VelocityBasis, W, on, scores, lengthscale, ratio, agreement=None):
        self.basis = basis
        self.agreement = np.full(basis.N, np.nan) if agreement is None else \
            np.asarray(agreement, float)
        self.W = np.asarray(W, float)
        self.on = np.asarray(on, bool)
        self.scores = np.asarray(scores, float)
        self.lengthscale = np.asarray(lengthscale, float)
        self.ratio = np.asarray(ratio, float)
        #: ((N,), (N,)) the velocities the element was learned on (None: not known)
        self.span = None

    def label(self) -> str:
        """Say which joints carry an element, e.g. ``'elements on 0 3'`` ('' for none)."""
        on = np.flatnonzero(self.on)
        return ('elements on ' + ' '.join(str(j) for j in on)) if on.size else ''

    def summary(self) -> dict:
        """
        Return what decided each joint's element, for /diagnostics and replay summaries.

        ``on``: the joints that carry one; ``newest_blocks``: per joint the element's error on
        the history's newest blocks over the parametric part's alone (below 1 it helps);
        ``halves_disagree``: how much two halves of the run disagree on it (served below
        ``AGREEMENT``; None while a half holds too few samples).
        """
        def r(x):
            return [None if not np.isfinite(v) else round(float(v), 4) for v in x]
        return {'on': [int(j) for j in np.flatnonzero(self.on)],
                'newest_blocks': r(self.scores), 'halves_disagree': r(self.agreement)}

    def mean(self, base: PriorMean) -> PriorMean:
        """Return ``base`` with the elements that are on (``base`` itself when none is)."""
        if not self.on.any():
            return base
        return JointElementMean(base, self.basis, np.where(self.on[:, None], self.W, 0.0),
                                span=self.span)


def _solve(G: np.ndarray, b: np.ndarray, prior: np.ndarray) -> Optional[np.ndarray]:
    """Posterior mean weights of ``[Phi, 1]`` with prior variances ``prior`` (in noise units)."""
    A = G + np.diag(1.0 / prior)
    try:
        return cho_solve(cho_factor(A, check_finite=False), b, check_finite=False)
    except (LinAlgError, ValueError):
        return None


def _prior(basis: VelocityBasis, lengthscale: float, ratio: float) -> np.ndarray:
    """Prior variances (M + 1,) in noise units: the SE spectrum times ratio, a free offset."""
    lam = ratio * basis.spectrum(lengthscale)
    return np.r_[np.maximum(lam, 1e-10 * ratio), OFFSET_RATIO]


def fit_elements(basis: VelocityBasis, full: Sequence[ElementFold],
                 folds: Sequence[Sequence[ElementFold]],
                 halves: Optional[Sequence[Sequence[ElementFold]]] = None,
                 half_samples=(0, 0), lengthscales=LENGTHSCALES,
                 ratios=RATIOS) -> ElementFit:
    """
    Choose and fit every joint's element (module docstring).

    full[j] : joint j's normal equations of all the (memory's) samples; folds[j] : its CV
    folds (forward-chaining: each trained before its scored block); halves[j] : the normal
    equations of two interleaved halves of the run, holding ``half_samples`` samples of the
    element each (``agreement``). Per joint the lengthscale and ratio with the least summed
    test error are chosen; the joint keeps its element where that error is below the
    parametric part's alone and the two halves, each large enough, agree on it.
    """
    N, M = basis.N, basis.M
    W = np.zeros((N, M))
    on = np.zeros(N, bool)
    scores, agree = np.full(N, np.nan), np.full(N, np.nan)
    ls_, ra_ = np.full(N, np.nan), np.full(N, np.nan)
    for j in range(N):
        fj = [f for f in folds[j] if f.test is not None]
        base = sum(f.test[2] for f in fj)
        if not fj or not base > 0:
            continue
        best = None
        for ls in lengthscales:
            for r in ratios:
                sse = _cv_error(fj, _prior(basis, ls, r), M)
                if best is None or sse < best[0]:
                    best = (sse, ls, r)
        scores[j], ls_[j], ra_[j] = best[0] / base, best[1], best[2]
        prior = _prior(basis, ls_[j], ra_[j])
        w = _solve(full[j].G, full[j].b, prior)
        if w is None or not np.all(np.isfinite(w)):
            continue
        if halves is not None and min(half_samples) >= MIN_HALF_SAMPLES:
            agree[j] = agreement(full[j].G[:M, :M], w[:M], halves[j], prior)
        if scores[j] < CV_TOLERANCE and agree[j] < AGREEMENT:
            W[j], on[j] = w[:M], True
    return ElementFit(basis, W, on, scores, ls_, ra_, agree)


def agreement(G: np.ndarray, w: np.ndarray, halves: Sequence[ElementFold],
              prior: np.ndarray) -> float:
    """
    Return how much two halves of the run disagree on an element, over the element itself.

    The element fitted on each half (at the same prior), their difference and the element
    fitted on all, each as an RMS over every sample (G: the element's Gram of all of them,
    (M, M)); their ratio. A velocity curve the data hold is learned alike from either half
    (ratio well below 1); what a joint's residual holds besides (hysteresis that changes
    with the motion, forces of states the element does not see) is not (ratio near or
    above 1), and an element fitted to it predicts the next motion worse.
    """
    M = w.size
    ws = [_solve(h.G, h.b, prior) for h in halves]
    if any(x is None for x in ws):
        return np.inf
    d = ws[0][:M] - ws[1][:M]
    return float(np.sqrt(max(d @ G @ d, 0.0) / max(w @ G @ w, 1e-300)))


def _cv_error(folds: Sequence[ElementFold], prior: np.ndarray, M: int) -> float:
    """Return the summed test error of folds at one prior (the offset fitted, not applied)."""
    sse = 0.0
    for f in folds:
        w = _solve(f.G, f.b, prior)
        if w is None:
            return np.inf
        wp = w[:M]
        PP, Py, yy = f.test
        sse += max(yy - 2.0 * wp @ Py + wp @ PP @ wp, 0.0)
    return sse


@register_mean
class JointElementMean(PriorMean):
    """
    A passive prior: a base prior's damping plus each joint's element, floored at 0.

    ``m_d,j(v) = max(base_j(v) + t_j(v) g_j(v), 0)`` with ``t_j(v) = tanh(v / eps_j) / v`` (even,
    positive, decreasing in ``|v|``; ``1 / eps_j`` at rest). Parameters: base : a fitted
    :class:`~dgp_ros.gp.means.PriorMean` with a damping diagonal; basis : the
    :class:`VelocityBasis`; W : (N, M) element weights (zero rows: no element); span : ((N,),
    (N,)) the lowest and highest velocity each joint's element was learned on, or None: beyond
    them ``g`` keeps its value at the edge (``g_j(clip(v, lo_j, hi_j))``), so the element's part
    ``t_j(v) g_j`` fades as ``1 / |v|`` and the parametric part answers, instead of a sum of
    sines the data never constrained there (a simulated Panda's wrist: 2.0 N m at 10 % beyond
    its fastest speed, where its friction is 0.7).
    """

    name = 'joint_element'

    def __init__(self, base: PriorMean, basis: VelocityBasis, W, span=None):
        super().__init__(base.bias_enabled)
        self.base = base
        self.basis = basis
        self.W = np.asarray(W, float)
        if self.W.shape != (basis.N, basis.M):
            raise ValueError(f'W must be {(basis.N, basis.M)}, got {self.W.shape}')
        self.bias = base.bias
        self.span = None
        if span is not None:
            lo, hi = (np.asarray(x, float).copy() for x in span)
            if lo.shape != (basis.N,) or hi.shape != (basis.N,) or not np.all(lo <= hi):
                raise ValueError('span must be two (N,) arrays with lo <= hi')
            self.span = (lo, hi)
        self.active = np.flatnonzero(np.any(self.W != 0.0, axis=1))
        j = self.active
        # what every answer reads of the active joints, gathered once (the message path's cost)
        self._on = (self.W[j], basis.vc[j] ** 2, basis.eps[j],
                    None if self.span is None else (self.span[0][j], self.span[1][j]))
        # |g| <= sum |w| and |dg/du| <= sum |w| omega: the interval bounds' constants
        self._gmax = np.abs(self.W).sum(axis=1)
        self._lip = np.abs(self.W) @ basis.omega

    def fit(self, Qd, Tau) -> 'JointElementMean':
        """Keep everything (a frozen prior: the D-GP learns what it leaves); returns self."""
        self.base.fit(Qd, Tau)
        self.bias = self.base.bias
        return self

    # ------------------------------------------------------------------ values
    def _t(self, A: np.ndarray, eps: np.ndarray) -> np.ndarray:
        """``tanh(a / eps) / a`` at speeds A (..., n), continuous at 0."""
        if A.size and A.min() >= 1e-6 * eps.max():
            return np.tanh(A / eps) / A          # no speed near rest: the message path's case
        small = A < 1e-6 * eps
        with np.errstate(invalid='ignore', divide='ignore'):
            out = np.tanh(A / eps) / np.where(small, 1.0, A)
        return np.where(small, 1.0 / eps, out)

    def element_diag(self, Qd) -> np.ndarray:
        """Return the elements' part of ``m_d`` (before the floor), (k, N)."""
        Qd = np.asarray(Qd, float)
        out = np.zeros(Qd.shape)
        j = self.active
        if j.size:
            W, vc2, eps, span = self._on
            V = Qd[..., j]
            G = V if span is None else np.clip(V, span[0], span[1])
            U = G / np.sqrt(G * G + vc2)
            S = np.sin(self.basis.omega * (U[..., None] + 1.0))         # (..., n, M)
            S *= W
            out[..., j] = S.sum(axis=-1) * self._t(np.abs(V), eps)   # g(v) t(|v|)
        return out

    def element_force(self, Qd) -> np.ndarray:
        """Return what the elements add to the damping force, ``s(v) g(v)`` (k, N)."""
        return self.element_diag(Qd) * np.asarray(Qd, float)

    def diag(self, Qd):
        return np.maximum(self.base.diag(Qd) + self.element_diag(Qd), 0.0)

    # ------------------------------------------------------------------ bounds
    def _g_bounds(self, ulo: np.ndarray, uhi: np.ndarray, j: np.ndarray):
        """Rigorous range of ``g_j`` for u in [ulo, uhi] (..., len(j)): centre +- Lipschitz."""
        uc = 0.5 * (ulo + uhi)
        S = np.sin(self.basis.omega * (uc[..., None] + 1.0))
        gc = np.einsum('...nm,nm->...n', S, self.W[j])
        r = 0.5 * (uhi - ulo) * self._lip[j] * (1.0 + 1e-12) + 1e-15 * self._gmax[j]
        g = self._gmax[j]
        return np.maximum(gc - r, -g), np.minimum(gc + r, g)

    def _element_bounds(self, lo: np.ndarray, hi: np.ndarray):
        """Range of the elements' part of ``m_d`` over boxes [lo, hi] (B, N): (B, N) each."""
        elo = np.zeros(lo.shape)
        ehi = np.zeros(lo.shape)
        j = self.active
        if not j.size:
            return elo, ehi
        b = self.basis
        L, H = lo[..., j], hi[..., j]
        # g takes the velocities clipped into its span: a box maps to the clipped box
        GL, GH = (L, H) if self.span is None else \
            (np.clip(L, self.span[0][j], self.span[1][j]),
             np.clip(H, self.span[0][j], self.span[1][j]))
        glo, ghi = self._g_bounds(GL / np.sqrt(GL * GL + b.vc[j] ** 2),
                                  GH / np.sqrt(GH * GH + b.vc[j] ** 2), j)
        amax = np.maximum(np.abs(L), np.abs(H))
        amin = np.where((L <= 0) & (H >= 0), 0.0, np.minimum(np.abs(L), np.abs(H)))
        eps = b.eps[j]
        tlo = self._t(amax, eps) * (1.0 - 1e-12)
        thi = self._t(amin, eps) * (1.0 + 1e-12)
        cand = np.stack([glo * tlo, glo * thi, ghi * tlo, ghi * thi])
        elo[..., j], ehi[..., j] = cand.min(axis=0), cand.max(axis=0)
        return elo, ehi

    def diag_bounds(self, lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        blo, bhi = self.base.diag_bounds(lo, hi)
        elo, ehi = self._element_bounds(lo, hi)
        return np.maximum(blo + elo, 0.0), np.maximum(bhi + ehi, 0.0)

    def diag_inf(self):
        """Return a rigorous lower bound of ``inf_v m_d(v)`` per joint (>= 0), (N,)."""
        out = np.asarray(self.base.diag_inf(), float).copy()
        j = self.active
        if not j.size:
            return out
        # cells of u in [-1, 1]: each a velocity interval (the ends +-inf are the limits)
        e = np.linspace(-1.0, 1.0, INF_CELLS + 1)
        vc = self.basis.vc[j]
        with np.errstate(divide='ignore'):
            edges = vc * e[:, None] / np.sqrt(np.maximum(1.0 - e[:, None] ** 2, 0.0))
        lo, hi = np.clip(edges[:-1], -1e100, 1e100), np.clip(edges[1:], -1e100, 1e100)
        N = self.basis.N
        L = np.zeros((INF_CELLS, N))
        H = np.zeros((INF_CELLS, N))
        L[:, j], H[:, j] = lo, hi
        dlo, _ = self.diag_bounds(L, H)
        out[j] = np.maximum(dlo[:, j].min(axis=0), 0.0)
        return out

    def diag_ref(self):
        return self.base.diag_ref()

    # ------------------------------------------------------------------ persistence
    def _params(self):
        out = {'base': self.base.to_dict(), 'basis': self.basis.to_dict(),
               'W': self.W.tolist()}
        if self.span is not None:
            out['span'] = [self.span[0].tolist(), self.span[1].tolist()]
        return out

    @classmethod
    def _from(cls, d):
        base = mean_from_dict(d['base'])
        span = d.get('span')
        return cls(base, VelocityBasis.from_dict(d['basis']), np.asarray(d['W'], float),
                   span=None if span is None else (np.asarray(span[0], float),
                                                   np.asarray(span[1], float)))


def element_joints(mean) -> List[int]:
    """Return the joints whose element is on in a prior mean (none for other means)."""
    return [int(j) for j in getattr(mean, 'active', [])] if isinstance(
        mean, JointElementMean) else []

"""
Couplings through a persistent velocity: the prior's part that a diagonal cannot carry.

Where a velocity ``v_p`` never nears zero (an aircraft's airspeed), a force at the other
velocities' zero can only ride on ``v_p``'s column of ``D``: an aircraft's drag at zero angle of
attack, its lift. A diagonal prior ``diag(m_d(qd)) qd`` answers zero there. This part adds, for
each such column ``p`` and each output ``i``,

    tau_i += v_p^2 psi_p(x)^T W_p[i] / vref_p^2,   D[i, p] += v_p psi_p(x)^T W_p[i] / vref_p^2,

with ``psi_p`` low-order features of the other velocities ``x`` (``1``; ``x, |x|, x^2, x^3`` of
each; where there are at most three others, ``x_k x_l, x_k |x_l|, |x_k| x_l`` of each pair):
for an aircraft, dynamic pressure times a coefficient polynomial in alpha and beta, the model
of equation-error aerodynamic identification (Klein and Morelli, *Aircraft System
Identification*, ch. 5). ``vref_p`` (the first sample's ``|v_p|``) keeps the columns of order
one. The weights are linear, so the long history learns them from every sample in bounded
memory (``dgp_ros.dynamics.coupling_track``).

**Passivity.** ``qd^T`` of this part has no sign of its own. :class:`CoupledMean` therefore
answers the projected force ``f = f_raw + lam(qd) qd`` with ``lam = max(0, -qd^T f_raw) / |qd|^2``
(continuous; ``qd^T f = max(qd^T f_raw, 0) >= 0``), so the prior is passive at every velocity
by construction, and its matrix is ``M_raw(qd) + lam(qd) I``. A proof on a box may use the bounds
of ``M_raw`` (:meth:`CoupledMean.matrix_bounds`): ``lam |q|^2 >= 0`` only adds to the power.
The global certificates, which need a diagonal prior (``diag(m_inf) - B`` copositive), do not
apply to it (``PriorMean.is_diagonal``). Pure numpy; no rclpy.
"""
from __future__ import annotations

from itertools import combinations
from typing import List, Sequence

import numpy as np

from .means import mean_from_dict, PriorMean, register_mean
from .policy import project_passive, projection_lambda
from .prior_mean import OverDiagonalMean

__all__ = ['CouplingBasis', 'CoupledMean', 'MAX_PAIRED', 'BOX_MARGIN']

#: pair features (``x_k x_l``, ``x_k |x_l|``, ``|x_k| x_l``) only where a column has at most
#: this many other velocities (more: their number grows as the square)
MAX_PAIRED = 3
#: a fitted prior takes the other velocities clipped into the box they were learned on,
#: widened by this fraction of its range each side: a cubic fitted while the side-slip stayed
#: within 1e-4 rad, evaluated at 1e-3 half a second later, answered -586 kN of lift error
BOX_MARGIN = 0.5


class CouplingBasis:
    """
    The features of the persistent columns (module docstring); plain numbers, picklable.

    N : velocities; cols : the persistent columns ``p``; vref : (len(cols),) their reference
    speeds (> 0, velocity units); box : ((N,), (N,)) or None: the other velocities are clipped
    into it before the features are taken (a fitted prior's: the velocities its weights were
    learned on, widened by :data:`BOX_MARGIN` of their range each side; None for the
    statistics, which see every sample as it is).
    """

    def __init__(self, N: int, cols: Sequence[int], vref: Sequence[float], box=None):
        self.N = int(N)
        self.cols = tuple(int(p) for p in cols)
        self.vref = np.asarray(vref, float).reshape(len(self.cols))
        self.box = None if box is None else (np.asarray(box[0], float).reshape(self.N),
                                             np.asarray(box[1], float).reshape(self.N))
        if self.box is not None and not (np.all(np.isfinite(self.box[0])) and
                                         np.all(self.box[0] <= self.box[1])):
            raise ValueError('coupling basis: the box must be finite with lo <= hi')
        if not np.all(self.vref > 0) or not np.all(np.isfinite(self.vref)):
            raise ValueError('coupling basis: reference speeds must be positive and finite')
        if len(set(self.cols)) != len(self.cols) or any(not 0 <= p < self.N for p in self.cols):
            raise ValueError(f'coupling basis: columns {self.cols} are not distinct in 0..{N - 1}')
        self.others = [[k for k in range(self.N) if k != p] for p in self.cols]
        #: per column the box of its other velocities (lo, hi), when clipped
        self._clip = [] if self.box is None else \
            [(self.box[0][o], self.box[1][o]) for o in self.others]
        self.sizes = [self.features_per_column(self.N)] * len(self.cols)
        self.K = int(sum(self.sizes))

    @staticmethod
    def features_per_column(N: int) -> int:
        """Features of one column among N velocities (its N - 1 others)."""
        n = N - 1
        pairs = n * (n - 1) // 2 if n <= MAX_PAIRED else 0
        return 1 + 4 * n + 3 * pairs

    def boxed(self, box_lo, box_hi) -> 'CouplingBasis':
        """Return the same columns clipped to the velocities seen in [box_lo, box_hi] (N,)."""
        lo, hi = np.asarray(box_lo, float), np.asarray(box_hi, float)
        pad = BOX_MARGIN * (hi - lo)
        return CouplingBasis(self.N, self.cols, self.vref, (lo - pad, hi + pad))

    # ------------------------------------------------------------------ values
    def _others(self, Qd: np.ndarray, c: int) -> np.ndarray:
        X = Qd[:, self.others[c]]
        if self.box is None:
            return X
        lo, hi = self._clip[c]
        np.maximum(X, lo, out=X)
        return np.minimum(X, hi, out=X)

    def psi(self, Qd: np.ndarray, c: int) -> np.ndarray:
        """Features of column ``cols[c]`` at velocities Qd (k, N): (k, sizes[c])."""
        X = self._others(Qd, c)
        n = X.shape[1]
        out = np.empty((Qd.shape[0], self.sizes[c]))
        out[:, 0] = 1.0
        out[:, 1:1 + n] = X
        A = np.abs(X, out=out[:, 1 + n:1 + 2 * n])
        X2 = np.multiply(X, X, out=out[:, 1 + 2 * n:1 + 3 * n])
        np.multiply(X2, X, out=out[:, 1 + 3 * n:1 + 4 * n])
        if n <= MAX_PAIRED:
            at = 1 + 4 * n
            for k, m in combinations(range(n), 2):
                out[:, at] = X[:, k] * X[:, m]
                out[:, at + 1] = X[:, k] * A[:, m]
                out[:, at + 2] = A[:, k] * X[:, m]
                at += 3
        return out

    def columns(self, Qd: np.ndarray) -> np.ndarray:
        """Return the regressors of every output, ``(v_p / vref_p)^2 psi_p(x)`` (k, K)."""
        Qd = np.atleast_2d(np.asarray(Qd, float))
        out = [self.psi(Qd, c) * ((Qd[:, p] / self.vref[c]) ** 2)[:, None]
               for c, p in enumerate(self.cols)]
        return np.concatenate(out, axis=1) if out else np.zeros((Qd.shape[0], 0))

    def slices(self) -> List[slice]:
        """Each column's slice of the K features."""
        out, at = [], 0
        for s in self.sizes:
            out.append(slice(at, at + s))
            at += s
        return out

    # ------------------------------------------------------------------ bounds
    def psi_bounds(self, lo: np.ndarray, hi: np.ndarray, c: int):
        """Rigorous range of ``psi`` of column ``cols[c]`` over boxes (B, N): (B, sizes[c]) x2."""
        L, H = lo[:, self.others[c]], hi[:, self.others[c]]
        if self.box is not None:        # clipping is monotone: the clipped interval's ends
            o = self.others[c]
            L, H = np.clip(L, self.box[0][o], self.box[1][o]), \
                np.clip(H, self.box[0][o], self.box[1][o])
        amax = np.maximum(np.abs(L), np.abs(H))
        amin = np.where((L <= 0) & (H >= 0), 0.0, np.minimum(np.abs(L), np.abs(H)))
        one = np.ones((lo.shape[0], 1))
        los = [one, L, amin, amin * amin, L * L * L]
        his = [one, H, amax, amax * amax, H * H * H]
        if len(self.others[c]) <= MAX_PAIRED:
            for k, m in combinations(range(L.shape[1]), 2):
                for (al, ah), (bl, bh) in (((L[:, k], H[:, k]), (L[:, m], H[:, m])),
                                           ((L[:, k], H[:, k]), (amin[:, m], amax[:, m])),
                                           ((amin[:, k], amax[:, k]), (L[:, m], H[:, m]))):
                    plo, phi = _product(al, ah, bl, bh)
                    los.append(plo[:, None])
                    his.append(phi[:, None])
        return np.concatenate(los, axis=1), np.concatenate(his, axis=1)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        out = {'N': self.N, 'cols': list(self.cols), 'vref': self.vref.tolist()}
        if self.box is not None:
            out['box'] = [self.box[0].tolist(), self.box[1].tolist()]
        return out

    @classmethod
    def from_dict(cls, d: dict) -> 'CouplingBasis':
        return cls(int(d['N']), [int(p) for p in d['cols']], [float(v) for v in d['vref']],
                   d.get('box'))


def _product(al, ah, bl, bh):
    """Range of ``a b`` for ``a`` in [al, ah], ``b`` in [bl, bh] (arrays): (lo, hi)."""
    c = np.stack([al * bl, al * bh, ah * bl, ah * bh])
    return c.min(axis=0), c.max(axis=0)


def _widen(lo: np.ndarray, hi: np.ndarray):
    """Round an enclosure outward by a relative 1e-12 (floating-point sums)."""
    pad = 1e-12 * np.maximum(np.abs(lo), np.abs(hi)) + 1e-300
    return lo - pad, hi + pad


@register_mean
class CoupledMean(OverDiagonalMean):
    """
    A diagonal passive prior plus the couplings of the persistent columns, projected (module doc).

    base : a fitted diagonal prior (``is_diagonal``); basis : :class:`CouplingBasis`; W : (N, K)
    the weights of every output on the basis' features (force units).
    """

    name = 'coupled'

    def __init__(self, base: PriorMean, basis: CouplingBasis, W):
        super().__init__(base, 'coupled prior')
        self.basis = basis
        self.W = np.asarray(W, float)
        if self.W.shape != (basis.N, basis.K):
            raise ValueError(f'coupled prior: W must be {(basis.N, basis.K)}, got {self.W.shape}')
        # a base without friction (an aircraft's family 'none'): its force is 0, not computed
        coef = getattr(base, 'coef', None)
        self._no_base = coef is not None and not np.any(coef)

    # ------------------------------------------------------------------ values
    def raw_force(self, Qd) -> np.ndarray:
        """Return the unprojected force ``diag(m_d) qd + couplings`` (k, N)."""
        Qd = np.atleast_2d(np.asarray(Qd, float))
        key = Qd.tobytes() if Qd.shape[0] <= 4 else None
        last = self.__dict__.get('_last')
        if key is not None and last is not None and last[0] == key:
            return last[1].copy()           # the message path and the learner ask it twice
        f = self.basis.columns(Qd) @ self.W.T
        if not self._no_base:
            f = f + self.base.force(Qd)
        if key is not None:
            self._last = (key, f.copy())
        return f

    def force(self, Qd) -> np.ndarray:
        Qd = np.atleast_2d(np.asarray(Qd, float))
        return project_passive(Qd, self.raw_force(Qd))

    def raw_matrix(self, Qd) -> np.ndarray:
        """``M_raw(qd)`` (k, N, N): the base's diagonal and the persistent columns."""
        Qd = np.atleast_2d(np.asarray(Qd, float))
        k, N = Qd.shape
        M = np.zeros((k, N, N))
        if not self._no_base:
            M[:, np.arange(N), np.arange(N)] = self.base.diag(Qd)
        for c, (p, sl) in enumerate(zip(self.basis.cols, self.basis.slices())):
            g = self.basis.psi(Qd, c) @ self.W[:, sl].T                      # (k, N)
            M[:, :, p] += g * (Qd[:, p] / self.basis.vref[c] ** 2)[:, None]
        return M

    def matrix(self, Qd) -> np.ndarray:
        Qd = np.atleast_2d(np.asarray(Qd, float))
        M = self.raw_matrix(Qd)
        lam = projection_lambda(Qd, np.einsum('kij,kj->ki', M, Qd))
        if np.any(lam):
            M[:, np.arange(Qd.shape[1]), np.arange(Qd.shape[1])] += lam[:, None]
        return M

    def diag(self, Qd) -> np.ndarray:
        """Return the diagonal of :meth:`matrix` (k, N); the force is not ``diag * qd`` here."""
        M = self.matrix(Qd)
        return M[:, np.arange(M.shape[1]), np.arange(M.shape[1])]

    # ------------------------------------------------------------------ bounds
    def matrix_bounds(self, lo, hi):
        """
        Rigorous range of ``M_raw`` over boxes [lo, hi] (B, N): (B, N, N) each.

        ``lam I`` is left out: it only adds ``lam |q|^2 >= 0`` to the power, so a lower bound of
        ``q^T (M_raw + C) q`` is one of the published model's too.
        """
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        B, N = lo.shape
        Mlo, Mhi = np.zeros((B, N, N)), np.zeros((B, N, N))
        dlo, dhi = self.base.diag_bounds(lo, hi)
        Mlo[:, np.arange(N), np.arange(N)] = dlo
        Mhi[:, np.arange(N), np.arange(N)] = dhi
        for c, (p, sl) in enumerate(zip(self.basis.cols, self.basis.slices())):
            flo, fhi = self.basis.psi_bounds(lo, hi, c)                     # (B, K_p)
            Wp = self.W[:, sl]                                              # (N, K_p)
            pos, neg = np.maximum(Wp, 0.0), np.minimum(Wp, 0.0)
            glo = flo @ pos.T + fhi @ neg.T                                 # (B, N)
            ghi = fhi @ pos.T + flo @ neg.T
            glo, ghi = _widen(glo, ghi)
            s = 1.0 / self.basis.vref[c] ** 2
            vlo, vhi = lo[:, p:p + 1] * s, hi[:, p:p + 1] * s
            plo, phi = _product(glo, ghi, vlo, vhi)
            plo, phi = _widen(plo, phi)
            Mlo[:, :, p] += plo
            Mhi[:, :, p] += phi
        return Mlo, Mhi

    def diag_ref(self):
        """
        Return a typical ``|M_ii|`` per output (N,): the proofs' scale of the power.

        The base's, or where larger the raw matrix's diagonal at the persistent columns'
        reference speeds (the other velocities at the middle of the box): an aircraft's lift
        over its airspeed, where a prior without friction has none of its own.
        """
        q = np.zeros((1, self.basis.N))
        if self.basis.box is not None:
            q[0] = 0.5 * (self.basis.box[0] + self.basis.box[1])
        q[0, list(self.basis.cols)] = self.basis.vref
        d = np.abs(self.raw_matrix(q)[0][np.arange(self.basis.N), np.arange(self.basis.N)])
        return np.maximum(np.asarray(self.base.diag_ref(), float), d)

    # ------------------------------------------------------------------ persistence
    def _params(self):
        return {'base': self.base.to_dict(), 'basis': self.basis.to_dict(),
                'W': self.W.tolist()}

    @classmethod
    def _from(cls, d):
        return cls(mean_from_dict(d['base']), CouplingBasis.from_dict(d['basis']),
                   np.asarray(d['W'], float))

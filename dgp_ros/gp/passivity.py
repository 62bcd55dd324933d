"""Passivity tools: exact copositivity for small matrices, the projection, and the certificate record.

Passivity of a damping model ``tau_hat(q) = D(q) q`` means ``P(q) = q^T D(q) q >= 0``.
If ``|D_mn(q) - diag(m_d)_mn| <= B_mn`` for all ``q`` then, with ``z = |q|``,
``P(q) >= z^T (diag(m_d) - B) z`` and passivity holds for every ``q`` whenever
``A = diag(m_d) - B`` is *copositive* (``z^T A z >= 0`` for all ``z >= 0``).

Copositivity is checked exactly for the small ``N`` of damping problems by Kaplan's criterion
(Linear Algebra Appl. 2000): the minimum of ``z^T A z`` over ``{z >= 0, |z| = 1}`` is attained at
a point whose support ``S`` makes ``z_S`` a positive eigenvector of ``A_SS``; so the minimum equals
the least eigenvalue of any principal submatrix that owns a positive eigenvector. That minimum is
our *copositivity margin* (same units as ``A``); copositive iff margin >= 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Optional

import numpy as np

__all__ = ['Certificate', 'copositivity_margin', 'project_passive', 'projection_lambda']

_MAX_EXACT_N = 10


@dataclass(frozen=True)
class Certificate:
    """Outcome of a passivity check.

    certified: True when ``q^T D(q) q >= 0`` is proven for every ``q`` (for ``projected``: every
        published estimate, pointwise).
    margin: normalized slack of the proof (>= 0 when certified; dimensionless, see ``method``).
    method: which proof: 'paper-theorem1', 'a-posteriori-bound', 'domain-bnb+blend', 'projection',
        'prior-only', 'none'.
    domain: ``(lo, hi)`` arrays, (N,) each, in the model's input units, of the box on which the
        GP correction itself is verified; ``None`` when the proof holds on all of R^N without it.
        Outside ``domain`` the certified model blends smoothly to the prior mean.
    correction_scale: factor applied to the GP correction (1 = unchanged; < 1 = shrunk to certify;
        0 = prior mean only).
    details: free-form numbers for diagnostics (boxes, time, ...).
    """

    certified: bool
    margin: float
    method: str
    domain: Optional[tuple] = None
    correction_scale: float = 1.0
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {'certified': bool(self.certified), 'margin': float(self.margin), 'method': self.method,
             'correction_scale': float(self.correction_scale), 'details': dict(self.details)}
        d['domain'] = None if self.domain is None else [np.asarray(self.domain[0]).tolist(),
                                                        np.asarray(self.domain[1]).tolist()]
        return d

    @staticmethod
    def from_dict(d: dict) -> 'Certificate':
        dom = d.get('domain')
        if dom is not None:
            dom = (np.asarray(dom[0], float), np.asarray(dom[1], float))
        return Certificate(bool(d['certified']), float(d['margin']), str(d['method']), dom,
                           float(d.get('correction_scale', 1.0)), dict(d.get('details', {})))


def _subsets(N: int):
    for r in range(1, N + 1):
        yield from combinations(range(N), r)


def copositivity_margin(A: np.ndarray) -> np.ndarray:
    """Exact ``min { z^T sym(A) z : z >= 0, |z|_2 = 1 }`` for a stack of small matrices.

    A: (N, N) or (B, N, N). Returns a float (or (B,) array). Copositive iff the result >= 0.
    Exact by Kaplan's criterion (see module docstring); cost 2^N small eigen-problems, so it
    is limited to N <= 10.
    """
    A = np.asarray(A, dtype=float)
    single = A.ndim == 2
    if single:
        A = A[None]
    if A.ndim != 3 or A.shape[1] != A.shape[2]:
        raise ValueError(f'copositivity_margin expects (N, N) or (B, N, N), got {A.shape}')
    N = A.shape[1]
    if N > _MAX_EXACT_N:
        raise ValueError(f'exact copositivity is limited to N <= {_MAX_EXACT_N}, got N = {N}')
    S = 0.5 * (A + np.swapaxes(A, 1, 2))
    best = np.full(S.shape[0], np.inf)
    for sub in _subsets(N):
        idx = np.asarray(sub)
        Ss = S[:, idx[:, None], idx[None, :]]
        if len(idx) == 1:
            best = np.minimum(best, Ss[:, 0, 0])
            continue
        w, V = np.linalg.eigh(Ss)                       # (B, k), (B, k, k)
        # an eigenvector counts when it is strictly one-signed (interior of the face)
        pos = np.all(V > 0, axis=1) | np.all(V < 0, axis=1)   # (B, k)
        cand = np.where(pos, w, np.inf).min(axis=1)
        best = np.minimum(best, cand)
    return float(best[0]) if single else best


def projection_lambda(Q: np.ndarray, Tau: np.ndarray, w_inv: Optional[np.ndarray] = None
                      ) -> np.ndarray:
    """Multiplier ``lambda(q) = max(0, -q^T tau) / (q^T W^-1 q)`` of the passivity projection.

    Q, Tau: (k, N); w_inv: (N,) diagonal of ``W^-1`` (default ones). Returns (k,); 0 where q = 0.
    """
    wi = np.ones(Q.shape[1]) if w_inv is None else np.asarray(w_inv, float)
    p = np.einsum('ij,ij->i', Q, Tau)
    den = np.einsum('ij,ij->i', Q * wi, Q)
    lam = np.zeros_like(p)
    ok = (p < 0) & (den > 0)
    lam[ok] = -p[ok] / den[ok]
    return lam


def project_passive(Q: np.ndarray, Tau: np.ndarray, w_inv: Optional[np.ndarray] = None
                    ) -> np.ndarray:
    """Nearest point (in the ``W`` norm) of ``{tau : q^T tau >= 0}`` to each row of ``Tau``.

    Q, Tau: (k, N). Returns (k, N) with ``q^T tau_p = max(q^T tau, 0)`` row by row. The set is
    convex and contains every passive truth, so the projection never moves an estimate further
    from a passive true force (non-expansiveness of projections onto convex sets).
    """
    Q = np.asarray(Q, float)
    Tau = np.asarray(Tau, float)
    wi = np.ones(Q.shape[1]) if w_inv is None else np.asarray(w_inv, float)
    lam = projection_lambda(Q, Tau, wi)
    out = Tau + lam[:, None] * (Q * wi)
    # rounding can leave q^T tau_p at -1e-16 relative: step a few ulps further where it does
    for _ in range(4):
        p = np.einsum('ij,ij->i', Q, out)
        bad = p < 0
        if not np.any(bad):
            break
        qb = Q[bad] * wi
        den = np.einsum('ij,ij->i', qb, Q[bad])
        size = np.einsum('ij,ij->i', np.abs(Q[bad]), np.abs(out[bad]))
        out[bad] += ((-p[bad] + 8 * np.finfo(float).eps * size) / den)[:, None] * qb
    return out

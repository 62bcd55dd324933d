"""
Exact copositivity of small matrices and the margins the passivity proofs use.

``A`` is copositive when ``z^T A z >= 0`` for all ``z >= 0``. Kaplan's criterion (Linear Algebra
Appl. 2000): the minimum of ``z^T A z`` over ``{z >= 0, |z| = 1}`` is the least eigenvalue of a
principal submatrix that owns a positive eigenvector, so the minimum (the *copositivity margin*)
is exact for the small ``N`` of damping problems. A Z-matrix (no positive off-diagonal entry, as
``diag(m) - B`` with ``B >= 0`` of the a-posteriori bound always is) needs none of that: the least
eigenvalue of ``cI - A``'s Perron vector is non-negative, so the margin is the least eigenvalue.
"""
from __future__ import annotations

from itertools import combinations

import numpy as np

__all__ = ['copositivity_margin', 'norm_margin', 'max_scale']

_MAX_EXACT_N = 10


def copositivity_margin(A: np.ndarray) -> np.ndarray:
    """
    Exact ``min { z^T sym(A) z : z >= 0, |z|_2 = 1 }`` for a stack of small matrices.

    A: (N, N) or (B, N, N). Returns a float (or (B,) array). Copositive iff the result >= 0.
    Exact by Kaplan's criterion (module docstring); 2^N small eigen-problems, so N <= 10.
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
    bad = ~np.all(np.isfinite(S), axis=(1, 2))
    if np.any(bad):                 # not finite: no proof (eigh would not converge)
        S = np.where(bad[:, None, None], 0.0, S)
    off = S - np.einsum('bii->bi', S)[:, :, None] * np.eye(N)
    z = ~bad & np.all(off <= 0.0, axis=(1, 2))
    if np.all(z):                   # Z-matrices: the least eigenvalue (module docstring)
        return float(np.linalg.eigvalsh(S)[0, 0]) if single else np.linalg.eigvalsh(S)[:, 0]
    for r in range(1, N + 1):
        for sub in combinations(range(N), r):
            idx = np.asarray(sub)
            Ss = S[:, idx[:, None], idx[None, :]]
            if r == 1:
                best = np.minimum(best, Ss[:, 0, 0])
                continue
            w, V = np.linalg.eigh(Ss)
            # an eigenvector counts when it is strictly one-signed (interior of the face)
            pos = np.all(V > 0, axis=1) | np.all(V < 0, axis=1)
            best = np.minimum(best, np.where(pos, w, np.inf).min(axis=1))
    best[bad] = -np.inf
    return float(best[0]) if single else best


def norm_margin(m_inf: np.ndarray, B: np.ndarray) -> float:
    """Copositivity margin of ``diag(m_inf) - B``, normalized by ``sqrt(m_inf m_inf^T)``."""
    A = np.diag(m_inf) - B
    top = float(np.max(m_inf))
    # no prior damping at all (data that inject energy): the margin in model units
    s = np.sqrt(np.maximum(m_inf, 1e-12 * top)) if top > 0 else np.ones(len(m_inf))
    An = A / s[:, None] / s[None, :]
    if not np.all(np.isfinite(An)):
        return -np.inf
    return copositivity_margin(An)


def max_scale(m_inf: np.ndarray, B: np.ndarray, hi: float = 1.0) -> float:
    """Largest ``s`` in ``[0, hi]`` with ``diag(m_inf) - s B`` copositive (bisection; B >= 0)."""
    if norm_margin(m_inf, hi * B) >= 0:
        return hi
    lo_s, hi_s = 0.0, hi
    for _ in range(50):
        mid = 0.5 * (lo_s + hi_s)
        if norm_margin(m_inf, mid * B) >= 0:
            lo_s = mid
        else:
            hi_s = mid
    return lo_s

"""
Input checks and batching shared by the models.

Every failed check is a ValueError that names the problem.
"""
from __future__ import annotations

from typing import Optional

import numpy as np


def as_matrix(A, name: str, N: Optional[int] = None, allow_empty: bool = False) -> np.ndarray:
    """Return ``A`` as a finite float (k, N) array; a 1-D array of length N is one row."""
    try:
        A = np.asarray(A, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name} must be a numeric array: {exc}') from None
    if A.ndim == 1 and N is not None and A.size == N:
        A = A[None, :]
    if A.ndim != 2:
        raise ValueError(f'{name} must be 2-D (samples, dims), got shape {A.shape}')
    if A.shape[0] == 0 and not allow_empty:
        raise ValueError(f'{name} is empty: at least one sample is needed')
    if A.shape[1] == 0:
        raise ValueError(f'{name} has zero columns: at least one dimension is needed')
    if N is not None and A.shape[1] != N:
        raise ValueError(f'{name} has {A.shape[1]} columns, the model has N = {N} dimensions')
    if not np.all(np.isfinite(A)):
        bad = np.argwhere(~np.isfinite(A))[0]
        raise ValueError(f'{name} contains NaN or Inf (first at row {bad[0]}, column {bad[1]})')
    return A


def as_pair(Qd, Tau, N: Optional[int] = None):
    """Validate a training pair: same shape (n, N), finite, non-empty."""
    Qd = as_matrix(Qd, 'Qd', N)
    Tau = as_matrix(Tau, 'Tau', Qd.shape[1])
    if Qd.shape[0] != Tau.shape[0]:
        raise ValueError(f'Qd has {Qd.shape[0]} samples but Tau has {Tau.shape[0]}')
    return Qd, Tau


def as_box(box, N: int, name: str):
    """Return a pair ``(lo, hi)`` of (N,) float arrays with ``lo < hi``, finite, from ``box``."""
    try:
        lo, hi = (np.asarray(v, dtype=float).ravel() for v in box)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a pair (lo, hi) of (N,) arrays') from None
    if lo.shape != (N,) or hi.shape != (N,) or not (np.all(np.isfinite(lo)) and
                                                    np.all(np.isfinite(hi))):
        raise ValueError(f'{name}: lo and hi must be {N} finite numbers each '
                         f'(one per velocity), got {lo.size} and {hi.size}')
    if np.any(hi <= lo):
        raise ValueError(f'{name}: need lo < hi in every dimension, got '
                         f'lo={lo.tolist()}, hi={hi.tolist()}')
    return lo, hi


def in_chunks(Q: np.ndarray, n: int, fn, elements: int) -> tuple:
    """
    Apply ``fn`` to row chunks of Q (k, N) and concatenate its results.

    ``fn(Qc)`` returns a tuple of arrays (rows first) or Nones; a chunk has at most
    ``elements // n`` rows (at least 256), which bounds its (rows, n) kernel temporaries.
    """
    rows = max(256, elements // max(n, 1))
    if Q.shape[0] <= rows:
        return fn(Q)
    parts = [fn(Q[i:i + rows]) for i in range(0, Q.shape[0], rows)]
    return tuple(None if parts[0][j] is None else np.concatenate([pt[j] for pt in parts])
                 for j in range(len(parts[0])))

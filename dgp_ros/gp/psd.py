"""
A damping matrix made positive semi-definite where it is not, and left alone where it is.

For a posterior damping matrix ``D`` (k, N, N) with symmetric part ``S = V diag(lam) V^T`` and
antisymmetric part ``A`` (which does no work: ``v^T A v = 0``), the published matrix is

    D_psd = D + V diag(f(lam) - lam) V^T,   symmetric part V diag(f(lam)) V^T,

with the C^1 function (``delta > 0`` a smoothing width, damping units)

    f(lam) = lam                        for lam >= delta,
    f(lam) = delta (lam/delta + 1)^2 / 4  for -delta < lam < delta,
    f(lam) = 0                          for lam <= -delta.

``f >= max(lam, 0)`` everywhere (on the middle piece ``f - lam = delta (lam/delta - 1)^2 / 4``), so
every eigenvalue of the symmetric part of ``D_psd`` is ``>= 0``: ``v^T D_psd v >= 0`` for every
``v``, in particular ``q^T D_psd(q) q >= 0``. Where the least eigenvalue of ``S`` is at least
``delta``, ``D_psd = D`` exactly (the rows are not touched). Because ``f`` is C^1, the matrix
function ``S -> V f(lam) V^T`` is C^1 (Daleckii-Krein), so ``D_psd(q)`` is as smooth in ``q`` as
a C^1 function of the (smooth) posterior; it is also the identity plus a change of at most
``max(delta, -lam_min)`` in spectral norm. Floating point: the eigen-decomposition is accurate to
a few ``eps |S|``, so the symmetric part is PSD up to that rounding (the policy then projects the
published force onto ``q^T tau >= 0``, which moves it by a few ulps at most).
"""
from __future__ import annotations

import numpy as np

__all__ = ['psd_clip', 'smooth_floor']


def smooth_floor(lam: np.ndarray, delta: float) -> np.ndarray:
    """``f(lam) - lam >= 0`` of the module docstring, elementwise (same shape as ``lam``)."""
    x = lam / delta
    mid = 0.25 * delta * (x - 1.0) ** 2
    return np.where(x >= 1.0, 0.0, np.where(x <= -1.0, -lam, mid))


def psd_clip(D: np.ndarray, delta: float):
    """
    Return ``(D_psd, touched)`` for damping matrices D (k, N, N), any units; delta > 0 same units.

    ``touched`` (k,) marks the rows whose matrix changed. Rows whose symmetric part is shown to
    have all eigenvalues ``>= delta`` by Gershgorin's theorem (one vectorized pass) skip the
    eigen-decomposition; the others get one batched ``eigh``.
    """
    if not delta > 0:
        raise ValueError(f'delta must be positive, got {delta!r}')
    S = D + D.transpose(0, 2, 1)
    S *= 0.5
    d = np.diagonal(S, axis1=1, axis2=2)
    # Gershgorin: every eigenvalue >= d_n - sum_{m != n} |S_nm| for some n
    low = (d + np.abs(d) - np.abs(S).sum(axis=2)).min(axis=1)
    need = low < delta
    if not need.any():
        return D, need
    every = bool(need.all())            # (one answer of the message path: no gathering)
    cand = None if every else np.flatnonzero(need)
    lam, V = np.linalg.eigh(S if every else S[cand])
    g = smooth_floor(lam, delta)
    hit = g.max(axis=1) > 0.0
    if every and hit.all():
        return D + (V * g[:, None, :]) @ V.transpose(0, 2, 1), hit
    touched = np.zeros(D.shape[0], dtype=bool)
    if not hit.any():
        return D, touched
    rows = np.flatnonzero(hit) if every else cand[hit]
    out = D.copy()
    Vh = V[hit]
    out[rows] += (Vh * g[hit][:, None, :]) @ Vh.transpose(0, 2, 1)
    touched[rows] = True
    return out, touched

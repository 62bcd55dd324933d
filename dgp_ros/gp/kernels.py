"""Squared-exponential ARD kernel, its bound, and the element structure of the D-GP kernels.

Everything here works in *standardized* coordinates (see ``models._Standardizer``).

SE-ARD: ``k(x, x') = sf2 * exp(-0.5 * sum_d (x_d - x'_d)^2 / l_d^2)``; ``sup |k| = sf2``
(the bound the passivity certificates need, DESIGN "Passivity, paper bound").

A D-GP output ``m`` has the scalar kernel ``k^(m)(x, x') = sum_e phi_e(x) phi_e(x') k_e(x, x')``
over its *elements* ``e``: for Full-D-GP the elements of row ``m`` of ``D`` with
``phi_(m,n)(x) = x_n``; for Diag-D-GP the single element ``(m, m)``; for ARD-GP one element with
``phi = 1``.
"""
from __future__ import annotations

import numpy as np

__all__ = ['se_ard', 'sq_dist', 'element_layout', 'se_bound']


def _augment(X1: np.ndarray, X2: np.ndarray, ls: np.ndarray, c1: float, c2: float, c0: float):
    """Factors whose product is ``c0 + c1 * (|a|^2 + |b|^2) + c2 * a.b`` with ``a = x1 / l``,
    ``b = x2 / l``: one GEMM with inner dimension N + 2 (it writes the result once; no separate
    broadcast passes over the a x b matrix)."""
    A = X1 / ls
    B = X2 / ls
    a, N = A.shape
    b = B.shape[0]
    Aa = np.empty((a, N + 2))
    Aa[:, :N] = A
    Aa[:, N] = c1 * np.einsum('ij,ij->i', A, A) + c0
    Aa[:, N + 1] = 1.0
    Bb = np.empty((b, N + 2))
    Bb[:, :N] = c2 * B
    Bb[:, N] = 1.0
    Bb[:, N + 1] = c1 * np.einsum('ij,ij->i', B, B)
    return Aa, Bb


def sq_dist(X1: np.ndarray, X2: np.ndarray, ls: np.ndarray) -> np.ndarray:
    """Scaled squared distances ``sum_d ((x1_d - x2_d) / l_d)^2``.

    X1: (a, N), X2: (b, N), ls: (N,) positive lengthscales. Returns (a, b), clipped at 0.
    The expansion ``|a|^2 + |b|^2 - 2 a.b`` as one GEMM, the fast path for large a, b.
    """
    Aa, Bb = _augment(X1, X2, ls, 1.0, -2.0, 0.0)
    d2 = Aa @ Bb.T
    np.maximum(d2, 0.0, out=d2)
    return d2


def se_ard(X1: np.ndarray, X2: np.ndarray, ls: np.ndarray, sf2: float) -> np.ndarray:
    """SE-ARD kernel matrix, (a, b). See module docstring; ``sf2`` is the signal variance.

    The exponent ``log sf2 - d2 / 2`` comes out of one GEMM (``_augment``) and is clipped at
    ``log sf2`` (d2 >= 0), then exponentiated in place."""
    if sf2 == 0.0:
        return np.zeros((X1.shape[0], X2.shape[0]))
    lsf2 = float(np.log(sf2))
    Aa, Bb = _augment(X1, X2, ls, -0.5, 1.0, lsf2)
    E = Aa @ Bb.T
    np.minimum(E, lsf2, out=E)
    np.exp(E, out=E)
    return E


def se_bound(sf2: np.ndarray) -> np.ndarray:
    """``sup_{x,x'} |k(x, x')|`` for SE kernels: the signal variance itself."""
    return np.asarray(sf2, dtype=float)


def element_layout(kind: str, N: int) -> list[tuple[int, int | None]]:
    """Elements ``(m, n)`` of the damping matrix modelled by each kind.

    ``n is None`` marks an ARD element (feature ``phi = 1``). Output ``m`` owns the elements
    whose first index is ``m``.
    """
    if kind == 'full':
        return [(m, n) for m in range(N) for n in range(N)]
    if kind == 'diag':
        return [(n, n) for n in range(N)]
    if kind == 'ard':
        return [(m, None) for m in range(N)]
    raise ValueError(f"unknown model kind {kind!r}: expected 'full', 'diag' or 'ard'")

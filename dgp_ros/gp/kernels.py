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

__all__ = ['se_ard', 'element_layout', 'se_bound']


def se_ard(X1: np.ndarray, X2: np.ndarray, ls: np.ndarray, sf2: float) -> np.ndarray:
    """SE-ARD kernel matrix, (a, b). See module docstring; ``sf2`` is the signal variance.

    X1: (a, N), X2: (b, N), ls: (N,) positive lengthscales. With ``u = x1 / l``, ``v = x2 / l``
    the exponent ``log sf2 - |u|^2 / 2 - |v|^2 / 2 + u.v`` comes out of one GEMM with inner
    dimension N + 2 (written once, no broadcast passes over the a x b matrix), is clipped at
    ``log sf2`` (squared distance >= 0) and exponentiated in place."""
    if sf2 == 0.0:
        return np.zeros((X1.shape[0], X2.shape[0]))
    lsf2 = float(np.log(sf2))
    U = X1 / ls
    V = X2 / ls
    N = U.shape[1]
    Ua = np.empty((U.shape[0], N + 2))
    Ua[:, :N] = U
    Ua[:, N] = lsf2 - 0.5 * np.einsum('ij,ij->i', U, U)
    Ua[:, N + 1] = 1.0
    Va = np.empty((V.shape[0], N + 2))
    Va[:, :N] = V
    Va[:, N] = 1.0
    Va[:, N + 1] = -0.5 * np.einsum('ij,ij->i', V, V)
    E = Ua @ Va.T
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

"""
The squared-exponential ARD kernel (the one implementation) and the D-GP element structure.

Everything here works in *standardized* coordinates ``x = qd / s_x`` (see ``posterior``).

SE-ARD: ``k(x, x') = sf2 * exp(-0.5 * sum_d (x_d - x'_d)^2 / l_d^2)``, with ``sup |k| = sf2``
(the bound the passivity certificates need).

A D-GP output ``m`` has the scalar kernel ``k^(m)(x, x') = sum_e phi_e(x) phi_e(x') k_e(x, x')``
over its *elements* ``e``: for Full-D-GP the elements ``(m, n)`` of row ``m`` of ``D`` with
``phi_(m,n)(x) = x_n``; for Diag-D-GP the single element ``(m, m)``; for ARD-GP one element with
``phi = 1`` (marked ``n = None``).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import List, Optional, Tuple

import numpy as np

__all__ = ['se_ard', 'se_bound', 'lower_se_sum', 'Structure', 'KINDS']

KINDS = ('full', 'diag', 'ard')

# queries x training points x elements up to which all element kernels of a few queries are built
# from exact differences in one pass (the per-message path); larger batches use one GEMM each
_ONE_PASS_MAX = 2_000_000
_ONE_PASS_MAX_QUERIES = 16


def se_ard(X1: np.ndarray, X2: np.ndarray, ls: np.ndarray, sf2) -> np.ndarray:
    """
    SE-ARD kernel matrices between two sets of standardized inputs.

    Parameters
    ----------
    X1 : (a, N) array
        First set of inputs.
    X2 : (b, N) array
        Second set of inputs.
    ls : (N,) or (E, N) array
        Positive lengthscales, one row per element kernel.
    sf2 : float or (E,) array
        Signal variances (``sup |k|``).

    Returns
    -------
    (a, b) array for one lengthscale vector, else (E, a, b).

    Two evaluation orders of the same formula: for a few queries against many points and many
    elements (the message path) every exponent comes from exact differences in one pass; otherwise
    each element's exponent ``log sf2 - |u|^2/2 - |v|^2/2 + u.v`` (``u = x1 / l``) comes out of
    one GEMM with inner dimension N + 2, is clipped at ``log sf2`` (squared distance >= 0) and
    exponentiated in place.

    """
    ls = np.asarray(ls, dtype=float)
    single = ls.ndim == 1
    LS = ls[None, :] if single else ls
    SF2 = np.broadcast_to(np.asarray(sf2, dtype=float), (LS.shape[0],))
    E = LS.shape[0]
    a, b = X1.shape[0], X2.shape[0]
    if E > 1 and a <= _ONE_PASS_MAX_QUERIES and a * b * E <= _ONE_PASS_MAX:
        diff = X1[:, None, :] - X2[None, :, :]                # (a, b, N)
        diff *= diff
        K = diff @ (LS ** -2.0).T                            # (a, b, E) scaled squared distances
        K *= -0.5
        np.exp(K, out=K)
        K *= SF2
        return np.moveaxis(K, 2, 0)
    out = np.empty((E, a, b))
    for e in range(E):
        out[e] = _se_gemm(X1, X2, LS[e], float(SF2[e]))
    return out[0] if single else out


_EXP_FLOOR = -600.0    # exp() below this is 0 for every use here, and denormals are ~100x slower


def _augmented(X: np.ndarray, ls: np.ndarray, lsf2: float, centre: np.ndarray):
    """
    Factors of the SE exponent ``lsf2 - |u_i - v_j|^2 / 2 = Ua_i .

    Va_j`` (``u = (x - c) / l``, translation invariant, so centring only shrinks |u| and the GEMM's
    cancellation): ``Ua = [u, lsf2 - |u|^2/2, 1]``, ``Va = [u, 1, -|u|^2/2]``, both (k, N + 2).
    """
    U = (X - centre) / ls
    h = -0.5 * np.einsum('ij,ij->i', U, U)
    N = U.shape[1]
    Ua = np.empty((U.shape[0], N + 2))
    Ua[:, :N] = U
    Ua[:, N] = lsf2 + h
    Ua[:, N + 1] = 1.0
    Va = np.empty((U.shape[0], N + 2))
    Va[:, :N] = U
    Va[:, N] = 1.0
    Va[:, N + 1] = h
    return Ua, Va


def _se_gemm(X1, X2, ls, sf2) -> np.ndarray:
    if sf2 == 0.0:
        return np.zeros((X1.shape[0], X2.shape[0]))
    lsf2 = float(np.log(sf2))
    c = X2.mean(axis=0) if X2.shape[0] else 0.0
    Ua, _ = _augmented(X1, ls, lsf2, c)
    _, Va = _augmented(X2, ls, lsf2, c)
    E = Ua @ Va.T
    np.clip(E, _EXP_FLOOR, lsf2, out=E)
    np.exp(E, out=E)
    return E


def lower_se_sum(X: np.ndarray, ls_list, sf2_list, feats, out: np.ndarray, noise: float = 0.0,
                 parts=None, block: Optional[int] = None) -> np.ndarray:
    """
    Write the lower triangle of ``sum_e phi_e phi_e^T o k_e(X, X) + noise I`` in place.

    X : (n, N); ls_list : per element (N,) lengthscales; sf2_list : per element signal variance;
    feats : per element (n,) feature ``phi_e`` or None; out : F-ordered array with at least n
    rows and columns (a ``WindowCholesky.workspace``), of which only the lower triangle of the
    top-left n x n block is written (the rest is not touched: the in-place Cholesky reads the
    lower triangle only). parts : optional list of F-ordered (n, n) arrays that receive each
    element's lower triangle too (for the certificates' RKHS norms).

    The lower triangle of an F-ordered array is the upper triangle of its C-ordered transpose, so
    each row block is one GEMM written in place and the elementwise passes run on a cache-sized
    block: about half the work of the full square. Returns ``out``.
    """
    n = X.shape[0]
    outT = out.T
    c = X.mean(axis=0) if n else 0.0
    elems = [(e, float(sf2), f) for e, (sf2, f) in enumerate(zip(sf2_list, feats)) if sf2 > 0]
    augs = [_augmented(X, np.asarray(ls_list[e], float), math.log(sf2), c)
            for e, sf2, _ in elems]
    if block is None:
        block = max(16, min(256, (1 << 15) // max(n, 1)))
    S = np.empty(block * n)
    W = np.empty(block * n) if len(elems) > 1 else None
    for j0 in range(0, n, block):
        j1 = min(j0 + block, n)
        T = outT[j0:j1, j0:n]
        shape = (j1 - j0, n - j0)
        if not elems:
            T[...] = 0.0
        for k, ((e, sf2, f), (Ua, Va)) in enumerate(zip(elems, augs)):
            B = S[:shape[0] * shape[1]].reshape(shape) if k == 0 else \
                W[:shape[0] * shape[1]].reshape(shape)
            np.matmul(Ua[j0:j1], Va[j0:n].T, out=B)
            np.clip(B, _EXP_FLOOR, math.log(sf2), out=B)
            np.exp(B, out=B)
            if f is not None:
                B *= f[j0:j1, None]
                B *= f[None, j0:n]
            if parts is not None:
                parts[e].T[j0:j1, j0:n] = B
            if k > 0:
                S[:B.size].reshape(shape)[...] += B
        if elems:
            T[...] = S[:shape[0] * shape[1]].reshape(shape)
    if noise:
        idx = np.arange(n)
        out[idx, idx] += noise
    return out


def se_bound(sf2: np.ndarray) -> np.ndarray:
    """``sup_{x,x'} |k(x, x')|`` for SE kernels: the signal variance itself."""
    return np.asarray(sf2, dtype=float)


@dataclass(frozen=True)
class Structure:
    """
    Which damping-matrix elements a model kind has, and which output owns each.

    Attributes
    ----------
    kind : 'full' | 'diag' | 'ard'
    N : int
        Number of generalized velocities (= outputs).
    elems : list of (m, n)
        Element ``e`` models ``D[m, n]``; ``n is None`` marks an ARD element (``phi = 1``).
    rows : list of lists
        ``rows[m]``: the element indices of output ``m``.

    """

    kind: str
    N: int
    elems: Tuple[Tuple[int, Optional[int]], ...]
    rows: Tuple[Tuple[int, ...], ...]

    @classmethod
    def of(cls, kind: str, N: int) -> 'Structure':
        if kind == 'full':
            elems = [(m, n) for m in range(N) for n in range(N)]
        elif kind == 'diag':
            elems = [(n, n) for n in range(N)]
        elif kind == 'ard':
            elems = [(m, None) for m in range(N)]
        else:
            raise ValueError(f"unknown model kind {kind!r}: expected one of {', '.join(KINDS)}")
        rows = [tuple(e for e, (m, _) in enumerate(elems) if m == row) for row in range(N)]
        return cls(kind, int(N), tuple(elems), tuple(rows))

    @property
    def E(self) -> int:
        return len(self.elems)

    @property
    def has_damping(self) -> bool:
        """Return False for the ARD baseline, which models the force directly."""
        return self.kind != 'ard'

    def features(self, X: np.ndarray, e: int) -> Optional[np.ndarray]:
        """``phi_e(x)`` for the rows of X (k, N): (k,), or None for ``phi = 1``."""
        n = self.elems[e][1]
        return None if n is None else X[:, n]

    def output_kernels(self, m: int, X1: np.ndarray, X2: np.ndarray, log_ls: np.ndarray,
                       log_sf2: np.ndarray, Kel: Optional[np.ndarray] = None) -> List[tuple]:
        """
        Output m's element kernels ``phi_e(x1) phi_e(x2) k_e(x1, x2)`` as a list of (e, (a, b)).

        ``Kel``: raw element kernels ``k_e(X1, X2)`` of every element (E, a, b), used instead of
        building them. Elements with ``sf2 = 0`` (switched off) are left out.
        """
        out = []
        for e in self.rows[m]:
            sf2 = float(np.exp(log_sf2[e]))
            if sf2 == 0.0:
                continue
            k = _se_gemm(X1, X2, np.exp(log_ls[e]), sf2) if Kel is None else Kel[e].copy()
            n = self.elems[e][1]
            if n is not None:
                k *= X1[:, n][:, None]
                k *= X2[:, n][None, :]
            out.append((e, k))
        return out

    def output_kernel(self, m: int, X1, X2, log_ls, log_sf2, Kel=None) -> np.ndarray:
        """Output m's kernel ``k^(m)(X1, X2)``, (a, b)."""
        K = None
        for _, k in self.output_kernels(m, X1, X2, log_ls, log_sf2, Kel):
            if K is None:
                K = k
            else:
                K += k
        return np.zeros((X1.shape[0], X2.shape[0])) if K is None else K

    def output_kdiag(self, m: int, X: np.ndarray, log_sf2: np.ndarray) -> np.ndarray:
        """``k^(m)(x, x)`` for the rows of X, (k,)."""
        out = np.zeros(X.shape[0])
        for e in self.rows[m]:
            sf2 = float(np.exp(log_sf2[e]))
            n = self.elems[e][1]
            out += sf2 * (1.0 if n is None else X[:, n] ** 2)
        return out

"""Cholesky factor of a sliding-window kernel matrix, updated in place: O(n^2) per sample.

``WindowCholesky`` holds the lower factor ``L`` of ``K`` (n x n) in a preallocated column-major
buffer; the active block starts at element ``(s, s)``. LAPACK reads it through the leading
dimension (``trtrs`` with ``lda`` = capacity), so

* appending a sample writes one new row (one triangular solve, no copy of the factor);
* dropping the oldest sample folds its column into the rest with Givens rotations (BLAS
  ``drot`` on the buffer, in place) and moves the start to ``(s + 1, s + 1)``;
* the block is moved back to ``(0, 0)`` once every ``capacity - n`` drops (amortized O(n)).

It also carries ``z = L^-1 r`` for one right-hand side ``r`` (the training residual of one
output) through appends and rotations, so ``alpha = K^-1 r = L^-T z`` costs one triangular solve
per update instead of two.

Pure numpy/scipy; used by ``models._BaseGP`` (one instance per output).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
from scipy.linalg import LinAlgError
from scipy.linalg.blas import drot
from scipy.linalg.lapack import dtrtrs

__all__ = ['WindowCholesky']

_F8 = np.dtype(np.float64).itemsize


class WindowCholesky:
    """Lower Cholesky factor with in-place append and drop-oldest.

    Parameters
    ----------
    L : (n, n) array
        Lower Cholesky factor of the current kernel matrix (upper triangle ignored).
    r : (n,) array
        Right-hand side whose forward solve ``z = L^-1 r`` is kept up to date.
    z : (n,) array or None
        ``L^-1 r`` if already known (restoring a saved factor); computed if None.
    limit : int or None
        Largest number of samples the factor will ever hold at once (window + 1 during an
        update), or None for unbounded growth. Sizes the buffer: ``limit + slack`` when given
        (slack = max(8, limit // 8) drops between two moves of the block), else grown by 1.5x.
    """

    def __init__(self, L: np.ndarray, r: np.ndarray, limit: Optional[int] = None,
                 z: Optional[np.ndarray] = None):
        L = np.asarray(L, dtype=float)
        n = L.shape[0]
        if L.ndim != 2 or L.shape[1] != n or n < 1:
            raise ValueError(f'L must be a non-empty square matrix, got shape {L.shape}')
        self._limit = None if limit is None else max(int(limit), n)
        self._slack = 8 if limit is None else max(8, self._limit // 8)
        cap = n if limit is None else min(self._limit + self._slack, n + max(8, n // 2))
        self._alloc(cap)
        self._n = n
        self._view(n)[:n, :] = L
        # z as carried by an earlier instance (a saved model): bit-identical continuation
        self._z = (self.solve(np.asarray(r, dtype=float)) if z is None
                   else np.array(z, dtype=float).reshape(n))

    # ------------------------------------------------------------------ storage
    def _alloc(self, cap: int) -> None:
        self._cap = int(cap)
        # one extra column: the (cap, n) LAPACK view of a block starting at (s, s) runs up to
        # s + cap * (s + n) elements into the buffer
        self._buf = np.zeros(self._cap * (self._cap + 1))
        self._s = 0

    def _view(self, ncols: int, s: Optional[int] = None) -> np.ndarray:
        """Column-major (capacity, ncols) view whose top-left element is (s, s): rows 0..n-1 of
        it are the factor. F-contiguous, so f2py hands it to LAPACK without a copy."""
        s = self._s if s is None else s
        return np.ndarray((self._cap, ncols), dtype=float, buffer=self._buf,
                          offset=_F8 * (s + s * self._cap), strides=(_F8, _F8 * self._cap))

    def _make_room(self) -> None:
        """Ensure row/column s + n exists (for one more sample): move the block to (0, 0), or
        grow the buffer."""
        n = self._n
        if self._s + n + 1 <= self._cap:
            return
        block = self._view(n)[:n, :].copy(order='F')
        need = n + 1
        if need > self._cap - self._slack // 2:            # nearly full: grow (up to the limit)
            cap = max(need + self._slack, int(1.5 * self._cap))
            if self._limit is not None:
                cap = min(cap, self._limit + self._slack)
            cap = max(cap, need)
            if cap != self._cap:
                self._alloc(cap)
        self._s = 0
        self._view(n)[:n, :] = block

    # ------------------------------------------------------------------ read access
    @property
    def n(self) -> int:
        return self._n

    @property
    def capacity(self) -> int:
        return self._cap

    @property
    def L(self) -> np.ndarray:
        """The factor as a new (n, n) lower-triangular array."""
        return np.tril(self._view(self._n)[:self._n, :])

    def diag(self) -> np.ndarray:
        v = self._view(self._n)
        return v[np.arange(self._n), np.arange(self._n)].copy()

    @property
    def z(self) -> np.ndarray:
        """``L^-1 r`` for the carried right-hand side, (n,)."""
        return self._z.copy()

    def solve(self, B: np.ndarray, trans: bool = False) -> np.ndarray:
        """``L^-1 B`` (or ``L^-T B`` with trans). B: (n,) or (n, k); returns the same shape."""
        B = np.asarray(B, dtype=float)
        vec = B.ndim == 1
        if B.shape[0] != self._n:
            raise ValueError(f'right-hand side has {B.shape[0]} rows, factor is {self._n} x '
                             f'{self._n}')
        b = np.array(B.reshape(self._n, -1), dtype=float, order='F', copy=True)
        x, info = dtrtrs(self._view(self._n), b, lower=1, trans=1 if trans else 0,
                         overwrite_b=1)
        if info != 0:
            raise LinAlgError(f'triangular solve failed (info={info}): singular factor')
        return x[:, 0] if vec else x

    def alpha(self) -> np.ndarray:
        """``K^-1 r = L^-T z``, (n,)."""
        return self.solve(self._z, trans=True)

    # ------------------------------------------------------------------ updates
    def append(self, c: np.ndarray, d: float, floor: float, r_new: float) -> None:
        """Add a sample: ``c`` (n,) its kernel column against the current samples, ``d`` its
        kernel diagonal (noise and jitter included), ``r_new`` its right-hand-side entry.

        The Schur complement ``d - l^T l`` of ``K + floor I`` is at least ``floor`` exactly;
        rounding below it (a near-duplicate sample) is clamped there."""
        l = self.solve(c)
        lnn = math.sqrt(max(d - float(l @ l), floor))
        self._make_room()
        n = self._n
        v = self._view(n + 1)
        v[n, :n] = l
        v[n, n] = lnn
        self._z = np.append(self._z, (r_new - float(l @ self._z)) / lnn)
        self._n = n + 1

    def drop_first(self) -> None:
        """Remove the oldest sample: ``K[1:, 1:] = L21 L21^T + L22 L22^T``, a rank-one update
        of ``L22`` by Givens rotations (in place, BLAS drot per column), applied to ``z`` too."""
        n, cap, s, buf = self._n, self._cap, self._s, self._buf
        if n < 2:
            raise ValueError('cannot drop the only sample')
        o0 = s + s * cap
        x = buf[o0 + 1:o0 + n].copy()          # L[1:, 0]
        z = self._z[1:].tolist()
        zc = float(self._z[0])
        xitem, bitem, hypot = x.item, buf.item, math.hypot
        for k in range(n - 1):
            xk = xitem(k)
            if xk == 0.0:
                continue
            j = s + 1 + k
            o = j + j * cap                     # flat index of the diagonal element (j, j)
            lkk = bitem(o)
            rr = hypot(lkk, xk)
            c, sn = lkk / rr, xk / rr
            drot(buf, x, c, sn, n=n - 1 - k, offx=o, offy=k, overwrite_x=1, overwrite_y=1)
            zk = z[k]
            z[k] = c * zk + sn * zc
            zc = c * zc - sn * zk
        z = np.array(z)
        self._s = s + 1
        self._n = n - 1
        self._z = z

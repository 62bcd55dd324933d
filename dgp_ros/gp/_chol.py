"""
Cholesky factor of a sliding-window kernel matrix, updated in place: O(n^2) per sample.

``WindowCholesky`` holds the lower factor ``L`` of ``K`` (n x n) in a preallocated column-major
buffer (leading dimension = ``capacity``); the active block starts at row ``r0``, column 0.
LAPACK reads it in place through the leading dimension, so

* appending a sample writes one new row (one triangular solve, no copy of the factor);
* dropping the oldest sample is a rank-one update ``L' L'^T = L22 L22^T + x x^T``
  (``x = L[1:, 0]``) done as the LQ factorization of the lower-Hessenberg
  ``N = L[1:, :] = [x | L22]`` by adjacent plane rotations. All rotations follow in O(n) from
  ``p = L22^-1 x`` (one triangular solve): with ``t_k = 1 + p_0^2 + ... + p_k^2``, rotation ``k``
  (columns ``k, k+1`` of ``N``) has ``c_k = (-1)^k p_k / sqrt(t_k)``, ``s_k = sqrt(t_(k-1) / t_k)``
  (Gill, Golub, Murray, Saunders 1974). They are applied by LAPACK ``dlasr`` (a compiled loop over
  a whole sequence of rotations, no Python per column) in panels of ``_PANEL`` columns, each to the
  rows at or below the panel. ``[L' 0] = N Q``: the new factor is ``N``'s first n-1 columns, i.e.
  the block moves down one row;
* the block is moved back to row 0 once every ``capacity - n`` drops (amortized O(n)).

If ``p`` is not finite (a singular factor), or scipy's Cython LAPACK is not reachable, the drop
falls back to the same LQ with data-driven Givens rotations (one BLAS ``drot`` per column, ~2x
slower at n = 1000), which never divide by the diagonal.

Only the lower triangle of the block is meaningful, and nothing outside it is ever read into it
(LAPACK reads the lower triangle only; a row's rotations ``k <= i`` touch columns ``<= i + 1``
only), so the rest of the buffer may hold anything, even NaN: the upper triangle of the kernel a
factor was computed in place from, or uninitialized memory (buffers are ``np.empty``).

It also carries ``z = L^-1 r`` for one right-hand side ``r`` (the training residual of one
output): ``z`` rides as one extra row under ``N`` through the same rotations, so
``alpha = K^-1 r = L^-T z`` costs one triangular solve per update instead of two.

Pure numpy/scipy: ``dlasr`` and ``dpotrf`` are taken from scipy's public Cython LAPACK
(``scipy.linalg.cython_lapack``) through ctypes, because scipy's f2py wrappers of them take no
leading dimension (they would copy the block). Used by ``models._BaseGP`` (one instance per
output).
"""
from __future__ import annotations

import ctypes
import math
from typing import Optional

import numpy as np
from scipy.linalg import cholesky, LinAlgError
from scipy.linalg.blas import drot
import scipy.linalg.cython_lapack as _cython_lapack
from scipy.linalg.lapack import dpotrf, dtrtrs

__all__ = ['WindowCholesky', 'FrozenFactor', 'cholesky_in_place', 'chol_jitter',
           'JITTER_STEPS']

_F8 = np.dtype(np.float64).itemsize
_PANEL = 64         # columns of N per dlasr call (rows above the panel are skipped)
#: jitter tried in turn, relative to mean(diag K): a bounded escalation
JITTER_STEPS = (0.0, 1e-10, 1e-8, 1e-6, 1e-4)


def _lapack(name: str, nargs: int):
    """C function pointer of ``scipy.linalg.cython_lapack.<name>`` (all arguments pointers)."""
    cap = _cython_lapack.__pyx_capi__[name]
    get_name = ctypes.pythonapi.PyCapsule_GetName
    get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
    get_ptr = ctypes.pythonapi.PyCapsule_GetPointer
    get_ptr.restype, get_ptr.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    return ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * nargs))(get_ptr(cap, get_name(cap)))


try:
    _dlasr = _lapack('dlasr', 9)    # side pivot direct m n c s a lda
    _dpotrf = _lapack('dpotrf', 5)  # uplo n a lda info
except (AttributeError, KeyError, TypeError, ValueError):     # no usable Cython LAPACK capsules:
    _dlasr = _dpotrf = None         # Givens drops (one drot per column), dpotrf through f2py
_CH = {k: ctypes.c_char_p(k.encode()) for k in 'RVFL'}
_VP = ctypes.c_void_p


def cholesky_in_place(A: np.ndarray, n: Optional[int] = None) -> int:
    """
    Factor the top-left block of ``A`` in place (lower Cholesky).

    Lower Cholesky factor of the top-left ``n x n`` block of the F-ordered 2-D array ``A``
    (LAPACK ``dpotrf``, leading dimension ``A.shape[0]``), written over its lower triangle; the
    strict upper triangle is left as it was. No copy. Returns LAPACK's ``info`` (0: success,
    ``k > 0``: the leading minor of order k is not positive definite).
    """
    if A.dtype != np.float64 or A.ndim != 2 or not A.flags.f_contiguous:
        raise ValueError('A must be an F-ordered 2-D float64 array')
    n = A.shape[1] if n is None else int(n)
    if not 0 <= n <= min(A.shape):
        raise ValueError(f'n = {n} does not fit in an array of shape {A.shape}')
    if n == 0:
        return 0
    if _dpotrf is None:
        c, info = dpotrf(A[:n, :n], lower=1, clean=0, overwrite_a=1)
        if not np.shares_memory(c, A):
            A[:n, :n] = c
        return int(info)
    nn, lda, info = ctypes.c_int(n), ctypes.c_int(A.shape[0]), ctypes.c_int(0)
    _dpotrf(_CH['L'], ctypes.byref(nn), _VP(A.ctypes.data), ctypes.byref(lda),
            ctypes.byref(info))
    return int(info.value)


def chol_jitter(K: np.ndarray):
    """
    Return the lower Cholesky factor of K (n, n) with bounded jitter escalation.

    Returns (L (n, n), jitter added to the diagonal); LinAlgError beyond ``JITTER_STEPS``.
    """
    base = float(np.mean(np.diag(K))) or 1.0
    for rel in JITTER_STEPS:
        j = rel * base
        try:
            L = cholesky(K + j * np.eye(K.shape[0]) if j else K, lower=True, check_finite=False)
            return L, j
        except LinAlgError:
            continue
    raise LinAlgError(f'kernel matrix not positive definite even with jitter '
                      f'{JITTER_STEPS[-1]:g} x mean diagonal')


class WindowCholesky:
    """
    Lower Cholesky factor with in-place append and drop-oldest.

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
        update), or None for unbounded growth. Sizes the buffer: ``limit + slack`` rows when
        given (slack = max(8, limit // 8) drops between two moves of the block), else grown by
        1.5x.

    """

    def __init__(self, L: np.ndarray, r: np.ndarray, limit: Optional[int] = None,
                 z: Optional[np.ndarray] = None):
        L = np.asarray(L, dtype=float)
        n = L.shape[0]
        if L.ndim != 2 or L.shape[1] != n or n < 1:
            raise ValueError(f'L must be a non-empty square matrix, got shape {L.shape}')
        self._set_limit(limit, n)
        rows, cols = self._sizes(n)
        self._alloc(rows, cols)
        self._n = n
        self._view(n)[:n, :] = L                  # upper triangle: see the module docstring
        self._finish(r, z)

    @classmethod
    def workspace(cls, n: int, limit: Optional[int] = None) -> np.ndarray:
        """
        Return a buffer for an ``n``-sample kernel, factored in place.

        An (uninitialized) F-ordered buffer in which an ``n``-sample kernel can be built (its
        lower triangle in the top-left ``n x n`` block is enough), factored with
        ``cholesky_in_place`` and handed to ``adopt`` without any copy, with the room ``limit``
        asks for (see the class parameters).
        """
        self = cls.__new__(cls)
        self._set_limit(limit, n)
        rows, cols = self._sizes(n)
        return np.empty((rows, cols + 1), order='F')

    @classmethod
    def adopt(cls, A: np.ndarray, r: np.ndarray, n: Optional[int] = None,
              limit: Optional[int] = None, z: Optional[np.ndarray] = None) -> 'WindowCholesky':
        """
        Take ownership of a buffer holding the factor.

        Take ownership of an F-ordered buffer whose top-left ``n x n`` lower triangle holds the
        factor (e.g. after ``cholesky_in_place``); everything else may hold anything. No copy if
        ``A`` is F-contiguous float64 with at least ``n + 1`` rows and ``n + 1`` columns
        (``workspace`` makes such buffers); otherwise the factor is copied into a new buffer.
        The caller must not use ``A`` afterwards.
        """
        n = A.shape[0] if n is None else int(n)
        if A.ndim != 2 or n < 1 or n > min(A.shape):
            raise ValueError(f'cannot adopt a {n} x {n} factor from an array of shape {A.shape}')
        self = cls.__new__(cls)
        self._set_limit(limit, n)
        if (A.dtype == np.float64 and A.flags.f_contiguous and A.shape[0] > n
                and A.shape[1] > n):
            self._cap, self._cols = A.shape[0], A.shape[1] - 1
            self._buf = A.reshape(-1, order='F')
            self._r0 = 0
        else:
            rows, cols = self._sizes(n)
            self._alloc(rows, cols)
            self._view(n)[:n, :] = A[:n, :n]
        self._n = n
        self._finish(r, z)
        return self

    # ------------------------------------------------------------------ storage
    def _set_limit(self, limit, n):
        self._limit = None if limit is None else max(int(limit), n)
        self._slack = 8 if limit is None else max(8, self._limit // 8)

    def _sizes(self, n):
        """
        Return the buffer size for n samples.

        (rows, columns) of a buffer for n samples: rows = capacity, columns = the most
        samples it can hold.
        """
        if self._limit is None:
            cols = n + max(8, n // 2)
            return cols + self._slack, cols
        return self._limit + self._slack, self._limit

    def _alloc(self, rows: int, cols: int) -> None:
        self._cap, self._cols = int(rows), int(cols)
        # one extra column: the (cap, ncols) LAPACK view of a block starting at row r0 runs
        # r0 elements past column ncols - 1
        self._buf = np.empty(self._cap * (self._cols + 1))
        self._r0 = 0

    def _finish(self, r, z):
        n = self._n
        d = self._diag_view()
        neg = d < 0                                 # the rotations keep a positive diagonal
        if np.any(neg):
            v = self._view(n)[:n, :]
            v[:, neg] *= -1.0
        self._z = (self.solve(np.asarray(r, dtype=float)) if z is None
                   else np.array(z, dtype=float).reshape(n))
        if z is not None and np.any(neg):
            self._z[neg] *= -1.0
        self._cs = np.empty(0)

    def _view(self, ncols: int, r0: Optional[int] = None) -> np.ndarray:
        """
        Column-major (capacity, ncols) view whose top-left element is (r0, 0).

        Rows 0..n-1 of it are the factor. F-contiguous, so f2py hands it to LAPACK without a copy.
        """
        r0 = self._r0 if r0 is None else r0
        return np.ndarray((self._cap, ncols), dtype=float, buffer=self._buf,
                          offset=_F8 * r0, strides=(_F8, _F8 * self._cap))

    def _diag_view(self) -> np.ndarray:
        n, cap = self._n, self._cap
        return self._buf[self._r0:self._r0 + n * (cap + 1):cap + 1][:n]

    def _make_room(self, column: bool = True, k: int = 1) -> None:
        """
        Ensure rows r0 + n .. r0 + n + k - 1 exist, and columns n .. n + k - 1 with ``column``.

        The columns are for k more samples; a drop only needs the row, for z. Move the block to
        row 0, or grow the buffer.
        """
        n = self._n
        if self._r0 + n + k <= self._cap and (n + k <= self._cols or not column):
            return
        block = self._view(n)[:n, :].copy(order='F')
        need = n + k
        if (column and need > self._cols) or need > self._cap - self._slack // 2:   # grow
            cols = max(need + self._slack, int(1.5 * self._cols))
            if self._limit is not None:
                cols = min(cols, self._limit)
            cols = max(cols, need)
            self._alloc(cols + self._slack, cols)
        else:
            self._r0 = 0
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
        """Get the factor as a new (n, n) lower-triangular array (F-ordered)."""
        L = self._view(self._n)[:self._n, :].copy(order='F')
        L[np.triu_indices(self._n, 1)] = 0.0
        return L

    def diag(self) -> np.ndarray:
        return self._diag_view().copy()

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

    def retarget(self, r: np.ndarray) -> None:
        """Carry another right-hand side ``r`` (n,): ``z = L^-1 r`` (one triangular solve)."""
        self._z = self.solve(np.asarray(r, dtype=float).reshape(self._n))

    # ------------------------------------------------------------------ updates
    def append(self, c: np.ndarray, d: float, floor: float, r_new: float) -> None:
        """
        Add a sample.

        ``c`` (n,) its kernel column against the current samples, ``d`` its kernel diagonal (noise
        and jitter included), ``r_new`` its right-hand-side entry.

        The Schur complement ``d - l^T l`` of ``K + floor I`` is at least ``floor`` exactly;
        rounding below it (a near-duplicate sample) is clamped there.
        """
        l_row = self.solve(c)
        lnn = math.sqrt(max(d - float(l_row @ l_row), floor))
        self._make_room()
        n, cap = self._n, self._cap
        o = self._r0 + n
        row = self._buf[o:o + cap * n + 1:cap]      # row r0 + n, columns 0..n
        row[:n] = l_row
        row[n] = lnn
        self._z = np.append(self._z, (r_new - float(l_row @ self._z)) / lnn)
        self._n = n + 1

    def append_block(self, C: np.ndarray, Dkk: np.ndarray, floor: float,
                     r_new: np.ndarray) -> None:
        """
        Add k samples at once: one triangular solve with k right-hand sides.

        ``C`` (n, k) their kernel columns against the current samples, ``Dkk`` (k, k) their
        kernel among themselves (noise and jitter on the diagonal), ``r_new`` (k,) their
        right-hand-side entries. The new rows are ``[L21 | L22]`` with ``L21 = (L^-1 C)^T`` and
        ``L22`` the Cholesky factor of the Schur complement ``Dkk - L21 L21^T`` (at least
        ``floor I`` exactly); if rounding makes it indefinite (near-duplicate samples), the
        samples are appended one by one, each clamped as ``append`` does.
        """
        C = np.asarray(C, dtype=float)
        r_new = np.asarray(r_new, dtype=float)
        k = C.shape[1]
        if k == 1:
            self.append(C[:, 0], float(Dkk[0, 0]), floor, float(r_new[0]))
            return
        L21t = self.solve(C)                        # (n, k)
        S = np.array(Dkk, dtype=float) - L21t.T @ L21t
        L22, info = dpotrf(S, lower=1, clean=1, overwrite_a=1)
        if info != 0 or not np.all(np.diag(L22) >= math.sqrt(floor) * (1.0 - 1e-12)):
            for j in range(k):                      # one by one: each Schur term clamped
                c = np.concatenate([C[:, j], Dkk[:j, j]]) if j else C[:, j]
                self.append(c, float(Dkk[j, j]), floor, float(r_new[j]))
            return
        self._make_room(k=k)
        n = self._n
        rows = self._view(n + k)[n:n + k, :]        # rows r0 + n .. r0 + n + k - 1
        rows[:, :n] = L21t.T
        rows[:, n:n + k] = L22
        zk, info = dtrtrs(L22, r_new - L21t.T @ self._z, lower=1)
        if info != 0:
            raise LinAlgError(f'triangular solve failed (info={info}): singular factor')
        self._z = np.concatenate([self._z, zk])
        self._n = n + k

    def drop_first(self) -> None:
        """
        Remove the oldest sample.

        ``K[1:, 1:] = L21 L21^T + L22 L22^T``, a rank-one update of ``L22`` (see the module
        docstring), applied to ``z`` too.
        """
        n = self._n
        if n < 2:
            raise ValueError('cannot drop the only sample')
        self._make_room(column=False)               # row r0 + n carries z through the rotations
        cap, r0, buf = self._cap, self._r0, self._buf
        m = n - 1
        zrow = buf[r0 + n:r0 + n + cap * (n - 1) + 1:cap]
        zrow[:] = self._z
        cs = self._rotations(m) if _dlasr is not None else None
        if cs is None:
            self._drop_givens(m)
        else:
            ci = [ctypes.c_int(0) for _ in range(3)]
            base = buf.ctypes.data
            cp, sp = cs.ctypes.data, cs.ctypes.data + _F8 * cs.shape[1]
            ci[2].value = cap
            for j0 in range(0, m, _PANEL):
                w = min(_PANEL, m - j0)
                ci[0].value = n - j0                # rows j0..m-1 of N and the z row
                ci[1].value = w + 1                 # columns j0..j0+w of N
                _dlasr(_CH['R'], _CH['V'], _CH['F'], ctypes.byref(ci[0]), ctypes.byref(ci[1]),
                       _VP(cp + _F8 * j0), _VP(sp + _F8 * j0),
                       _VP(base + _F8 * ((r0 + 1 + j0) + j0 * cap)), ctypes.byref(ci[2]))
        self._z = zrow[:m].copy()
        self._r0 = r0 + 1
        self._n = m

    def _rotations(self, m: int) -> Optional[np.ndarray]:
        """
        Compute the drop's rotations.

        (2, m) array of the drop's rotations (c, s) from ``p = L22^-1 x``, or None if p is
        not finite (singular or overflowing).
        """
        cap, r0, buf = self._cap, self._r0, self._buf
        L22 = np.ndarray((cap, m), dtype=float, buffer=buf, offset=_F8 * (r0 + 1 + cap),
                         strides=(_F8, _F8 * cap))
        x = np.array(buf[r0 + 1:r0 + 1 + m]).reshape(m, 1)
        p, info = dtrtrs(L22, x, lower=1, overwrite_b=1)
        if info != 0:
            return None
        p = p[:, 0]
        if self._cs.shape != (2, m):
            self._cs = np.empty((2, m))
        c, s = self._cs
        t = np.cumsum(p * p)
        t += 1.0
        if not math.isfinite(t[-1]):
            return None
        np.divide(p, np.sqrt(t), out=c)
        c[1::2] *= -1.0                             # the carried column flips sign each step
        np.divide(t[:-1], t[1:], out=s[1:])
        s[0] = 1.0 / t[0]
        np.sqrt(s, out=s)
        return self._cs

    def _drop_givens(self, m: int) -> None:
        """Fallback: the same LQ with rotations computed from the data, column by column."""
        cap, r0, buf = self._cap, self._r0, self._buf
        item, hypot = buf.item, math.hypot
        for k in range(m):
            o = (r0 + 1 + k) + k * cap              # N[k, k], the carried column at row k
            a, b = item(o), item(o + cap)
            rr = hypot(a, b)
            if rr == 0.0:
                continue
            # rows k..m-1 of N and the z row: m - k + 1 entries of columns k and k + 1
            drot(buf, buf, a / rr, b / rr, n=m - k + 1, offx=o, offy=o + cap,
                 overwrite_x=1, overwrite_y=1)
            buf[o + cap] = 0.0


class FrozenFactor:
    """
    A read-only copy of a ``WindowCholesky``'s factor: just ``L`` (n, n), compact to pickle.

    What a predict-only model snapshot needs for the posterior variance (``solve``); it cannot
    be updated. ``L`` is lower triangular with zeros above the diagonal.
    """

    def __init__(self, L: np.ndarray):
        self._L = np.asfortranarray(L, dtype=float)
        self._n = self._L.shape[0]

    @property
    def n(self) -> int:
        return self._n

    @property
    def L(self) -> np.ndarray:
        return self._L.copy(order='F')

    def diag(self) -> np.ndarray:
        return np.diag(self._L).copy()

    def solve(self, B: np.ndarray, trans: bool = False) -> np.ndarray:
        """``L^-1 B`` (or ``L^-T B`` with trans). B: (n,) or (n, k); returns the same shape."""
        B = np.asarray(B, dtype=float)
        vec = B.ndim == 1
        b = np.array(B.reshape(self._n, -1), dtype=float, order='F', copy=True)
        x, info = dtrtrs(self._L, b, lower=1, trans=1 if trans else 0, overwrite_b=1)
        if info != 0:
            raise LinAlgError(f'triangular solve failed (info={info}): singular factor')
        return x[:, 0] if vec else x

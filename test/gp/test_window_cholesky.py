"""
WindowCholesky: in-place append / drop-oldest against fresh factorizations of the same window.

The kernels here are built with plain numpy (independent of dgp_ros.gp.kernels); every check
compares with scipy's Cholesky of the exact window, or with the window's kernel itself.
"""
import copy

import numpy as np
import pytest
from scipy.linalg import cho_solve, cholesky

from dgp_ros.gp import _chol
from dgp_ros.gp._chol import cholesky_in_place, WindowCholesky


def _se(X, ls, sf2=1.0):
    U = X / ls
    d2 = ((U[:, None, :] - U[None, :, :]) ** 2).sum(-1)
    return sf2 * np.exp(-0.5 * d2)


def _stream(total, ls, sn2, seed=0, dup=0.0, jitter_dup=0.0):
    """
    Make the inputs, kernel (noise included) and right-hand sides of a sample stream.

    ``dup``: share of samples that repeat the previous one (up to ``jitter_dup``).
    """
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (total, 2))
    if dup:
        idx = np.nonzero(rng.random(total) < dup)[0]
        idx = idx[idx > 0]
        X[idx] = X[idx - 1] + jitter_dup * rng.standard_normal((idx.size, 2))
    K = _se(X, np.asarray(ls, float)) + sn2 * np.eye(total)
    return X, K, rng.standard_normal(total)


def _check_against_fresh(wc, K, r, lo, hi, tol=1e-10):
    L = cholesky(K[lo:hi, lo:hi], lower=True)
    assert wc.n == hi - lo
    assert np.max(np.abs(wc.L - L)) <= tol * np.abs(L).max()
    assert np.allclose(wc.diag(), np.diag(L), rtol=tol, atol=0)
    z = np.linalg.solve(L, r[lo:hi])
    assert np.max(np.abs(wc.z - z)) <= 1e3 * tol * np.abs(z).max()
    a = cho_solve((L, True), r[lo:hi])
    assert np.max(np.abs(wc.alpha() - a)) <= 1e3 * tol * np.abs(a).max()


@pytest.mark.parametrize('k,dup', [(1, 0.0), (5, 0.0), (40, 0.0), (12, 0.5)])
def test_append_block_matches_a_fresh_factorization(k, dup):
    """
    Check ``append_block`` of k samples against scipy's Cholesky of all of them.

    ``dup``: half the new samples repeat the one before (to rounding).
    """
    n = 30
    sn2 = 1e-3
    X, K, r = _stream(n + 3 * k, [0.4, 0.7], sn2, seed=k, dup=dup, jitter_dup=1e-13)
    wc = WindowCholesky(cholesky(K[:n, :n], lower=True), r[:n], limit=None)
    for b in range(3):
        lo, hi = n + b * k, n + (b + 1) * k
        wc.append_block(K[:lo, lo:hi], K[lo:hi, lo:hi], sn2, r[lo:hi])
        _check_against_fresh(wc, K, r, 0, hi, tol=1e-8 if dup else 1e-10)


def test_append_block_below_the_floor_is_the_one_by_one_appends():
    # a Schur complement below the floor (repeated samples, floor above the noise): the block
    # falls back to single appends, each clamped at the floor, and gives exactly their result
    n, k, sn2 = 20, 8, 1e-4
    _, K, r = _stream(n + k, [0.4, 0.7], sn2, seed=3, dup=1.0)
    floor = 10 * sn2
    L0 = cholesky(K[:n, :n], lower=True)
    block, single = WindowCholesky(L0, r[:n]), WindowCholesky(L0, r[:n])
    block.append_block(K[:n, n:], K[n:, n:], floor, r[n:])
    for j in range(k):
        single.append(K[:n + j, n + j], float(K[n + j, n + j]), floor, float(r[n + j]))
    np.testing.assert_array_equal(block.L, single.L)
    np.testing.assert_array_equal(block.z, single.z)
    assert np.min(np.diag(block.L)[n:]) == pytest.approx(np.sqrt(floor))


@pytest.mark.parametrize('window', [2, 3, 17, 150])
def test_append_drop_cycles_match_a_fresh_factorization(window):
    """
    Check append and drop cycles against scipy's Cholesky of the window.

    3 x window append + drop cycles (several block moves back to row 0, several dlasr panels
    for the largest window): factor, z and alpha against scipy's Cholesky of the window.
    """
    total = window + 3 * window + 5
    _, K, r = _stream(total, [0.4, 0.7], 1e-3, seed=window)
    wc = WindowCholesky(cholesky(K[:window, :window], lower=True), r[:window], limit=window + 1)
    lo, hi = 0, window
    caps = set()
    for i in range(window, total):
        wc.append(K[lo:hi, i], K[i, i], 1e-3, r[i])
        hi += 1
        assert wc.n == window + 1
        wc.drop_first()
        lo += 1
        caps.add(wc.capacity)
        if (i - window) % max(1, window // 3) == 0 or i == total - 1:
            _check_against_fresh(wc, K, r, lo, hi)
    # memory stays bounded: limit + slack rows, never regrown
    assert caps == {window + 1 + max(8, (window + 1) // 8)}


def test_growth_without_limit_and_drops_in_between():
    _, K, r = _stream(260, [0.4, 0.7], 1e-3, seed=1)
    wc = WindowCholesky(cholesky(K[:3, :3], lower=True), r[:3])
    lo, hi = 0, 3
    caps = set()
    for i in range(3, 260):
        wc.append(K[lo:hi, i], K[i, i], 1e-3, r[i])
        hi += 1
        if i % 5 == 0:                    # the window grows, with a drop now and then
            wc.drop_first()
            lo += 1
        caps.add(wc.capacity)
        if i % 37 == 0 or i == 259:
            _check_against_fresh(wc, K, r, lo, hi)
    assert len(caps) > 3


def test_several_drops_in_a_row_and_down_to_one_sample():
    _, K, r = _stream(90, [0.5, 0.5], 1e-3, seed=2)
    wc = WindowCholesky(cholesky(K[:90, :90], lower=True), r[:90], limit=91)
    for lo in range(1, 90):
        wc.drop_first()
        if lo % 11 == 0 or lo == 89:
            _check_against_fresh(wc, K, r, lo, 90)
    assert wc.n == 1
    with pytest.raises(ValueError, match='only sample'):
        wc.drop_first()


@pytest.mark.parametrize('sn2, ls, dup, jitter', [(1e-6, [1.5, 2.0], 0.0, 0.0),
                                                  (1e-6, [0.3, 0.5], 0.3, 0.0),
                                                  (1e-8, [3.0, 3.0], 0.2, 1e-9)])
def test_ill_conditioned_windows_keep_a_small_backward_error(sn2, ls, dup, jitter):
    """
    Near-singular windows (tiny noise, long lengthscales, exact and near duplicates).

    After 3n cycles L L^T still reproduces the window's kernel and L z its right-hand side to
    rounding level (a forward comparison would only measure the condition number).
    """
    n = 120
    _, K, r = _stream(n + 3 * n, ls, sn2, seed=3, dup=dup, jitter_dup=jitter)
    wc = WindowCholesky(cholesky(K[:n, :n], lower=True), r[:n], limit=n + 1)
    lo, hi = 0, n
    for i in range(n, n + 3 * n):
        wc.append(K[lo:hi, i], K[i, i], sn2, r[i])
        hi += 1
        wc.drop_first()
        lo += 1
    L = wc.L
    assert np.max(np.abs(L @ L.T - K[lo:hi, lo:hi])) <= 1e-13
    assert np.max(np.abs(L @ wc.z - r[lo:hi])) <= 1e-10 * np.abs(r).max()
    assert np.all(wc.diag() > 0)


def test_exact_duplicate_is_clamped_and_can_be_dropped():
    X = np.array([[0.0, 0.0], [1.0, 0.5]])
    sn2 = 1e-6
    K = _se(X, np.ones(2)) + sn2 * np.eye(2)
    wc = WindowCholesky(cholesky(K, lower=True), np.array([1.0, 2.0]), limit=3)
    c = _se(np.vstack([X, X[:1]]), np.ones(2))[:2, 2]
    wc.append(c, 1.0 + sn2, sn2, 1.0)           # the first sample again: Schur complement ~ 0
    d = wc.diag()
    assert d[-1] >= np.sqrt(sn2) * (1 - 1e-12)
    assert np.all(np.isfinite(wc.alpha()))
    # the clamped factor is the exact factor of the window with the floor on the last diagonal
    Kc = _se(np.vstack([X, X[:1]]), np.ones(2)) + sn2 * np.eye(3)
    L = wc.L
    Kc[2, 2] = L[2] @ L[2]
    assert np.allclose(L @ L.T, Kc, atol=1e-12)
    wc.drop_first()                               # now the duplicate pair is samples 1, 2 -> 0, 1
    L2 = cholesky(Kc[1:, 1:], lower=True)
    assert np.max(np.abs(wc.L - L2)) <= 1e-10
    with pytest.raises(ValueError, match='rows'):
        wc.solve(np.ones(5))


def test_fallback_givens_path_gives_the_same_factor(monkeypatch):
    """The data-driven Givens fallback (used when p is not finite) against the same reference."""
    _, K, r = _stream(200, [0.4, 0.7], 1e-3, seed=5)
    monkeypatch.setattr(WindowCholesky, '_rotations', lambda self, m: None)
    n = 80
    wc = WindowCholesky(cholesky(K[:n, :n], lower=True), r[:n], limit=n + 1)
    lo, hi = 0, n
    for i in range(n, 200):
        wc.append(K[lo:hi, i], K[i, i], 1e-3, r[i])
        hi += 1
        wc.drop_first()
        lo += 1
    _check_against_fresh(wc, K, r, lo, hi)


def test_singular_factor_falls_back_instead_of_failing():
    """
    A zero pivot below the dropped sample.

    p = L22^-1 x does not exist; the Givens fallback still folds the column in (the window's kernel
    is kept exactly).
    """
    L = np.array([[1.0, 0, 0], [0.5, 0.0, 0], [0.2, 0.3, 0.8]])
    wc = WindowCholesky(L, np.array([1.0, 0.5, 0.7]), limit=4, z=np.zeros(3))
    wc.drop_first()
    K = L @ L.T
    Ln = wc.L
    assert np.allclose(Ln @ Ln.T, K[1:, 1:], atol=1e-14)
    assert np.all(np.isfinite(Ln))


def test_negative_diagonal_input_and_given_z_are_normalized():
    _, K, r = _stream(40, [0.5, 0.8], 1e-2, seed=6)
    L = cholesky(K[:30, :30], lower=True)
    z = np.linalg.solve(L, r[:30])
    flip = np.ones(30)
    flip[::3] = -1.0
    wc = WindowCholesky(L * flip[None, :], r[:30], limit=31, z=z * flip)
    assert np.allclose(wc.L, L, rtol=0, atol=1e-15)
    assert np.allclose(wc.z, z, rtol=0, atol=1e-12)
    for i in range(30, 40):
        wc.append(K[i - 30:i, i], K[i, i], 1e-2, r[i])
        wc.drop_first()
    _check_against_fresh(wc, K, r, 10, 40)


def test_adopt_takes_the_buffer_without_copy():
    """
    Check that adopt takes the buffer without a copy.

    workspace -> kernel in its top-left block (upper triangle too) -> cholesky_in_place ->
    adopt: the factor is used where it was computed, and stays correct through the window's
    append/drop cycles.
    """
    n = 70
    _, K, r = _stream(n + 100, [0.4, 0.7], 1e-3, seed=7)
    A = WindowCholesky.workspace(n, limit=n + 1)
    assert A.flags.f_contiguous and A.shape[0] > n and A.shape[1] > n
    A[:n, :n] = K[:n, :n]
    assert cholesky_in_place(A, n) == 0
    assert np.allclose(A[:n, :n][np.triu_indices(n, 1)], K[:n, :n][np.triu_indices(n, 1)])
    wc = WindowCholesky.adopt(A, r[:n], n=n, limit=n + 1)
    assert np.shares_memory(wc._buf, A)
    _check_against_fresh(wc, K, r, 0, n)
    lo, hi = 0, n
    for i in range(n, n + 100):
        wc.append(K[lo:hi, i], K[i, i], 1e-3, r[i])
        hi += 1
        wc.drop_first()
        lo += 1
    _check_against_fresh(wc, K, r, lo, hi)
    assert wc.capacity == A.shape[0]              # never reallocated


def test_adopt_of_a_tight_array_copies_and_in_place_reports_failure():
    _, K, r = _stream(30, [0.4, 0.7], 1e-3, seed=8)
    A = np.asfortranarray(K[:30, :30])
    assert cholesky_in_place(A) == 0
    wc = WindowCholesky.adopt(A, r[:30], limit=31)          # no spare row/column: copied
    assert not np.shares_memory(wc._buf, A)
    _check_against_fresh(wc, K, r, 0, 30)
    bad = np.asfortranarray(-np.eye(4))
    assert cholesky_in_place(bad) == 1
    with pytest.raises(ValueError, match='F-ordered'):
        cholesky_in_place(np.eye(3))                         # C order
    with pytest.raises(ValueError):
        WindowCholesky.adopt(np.zeros((3, 3), order='F'), np.ones(4), n=4)


def test_copies_are_independent():
    _, K, r = _stream(60, [0.4, 0.7], 1e-3, seed=9)
    wc = WindowCholesky(cholesky(K[:40, :40], lower=True), r[:40], limit=41)
    other = copy.deepcopy(wc)
    for i in range(40, 60):
        wc.append(K[i - 40:i, i], K[i, i], 1e-3, r[i])
        wc.drop_first()
    _check_against_fresh(wc, K, r, 20, 60)
    _check_against_fresh(other, K, r, 0, 40)


def test_panel_width_does_not_change_the_result(monkeypatch):
    """Panels of 1, 7 and 64 columns (the dlasr calls restrict rows per panel)."""
    _, K, r = _stream(260, [0.4, 0.7], 1e-3, seed=10)
    out = []
    for w in (1, 7, 64):
        monkeypatch.setattr(_chol, '_PANEL', w)
        wc = WindowCholesky(cholesky(K[:200, :200], lower=True), r[:200], limit=201)
        for i in range(200, 260):
            wc.append(K[i - 200:i, i], K[i, i], 1e-3, r[i])
            wc.drop_first()
        _check_against_fresh(wc, K, r, 60, 260)
        out.append(wc.L)
    assert np.max(np.abs(out[0] - out[2])) <= 1e-12


def test_nothing_outside_the_lower_triangle_is_read():
    """
    A workspace full of NaN except the kernel's lower triangle.

    Factor, cycles and solves are unaffected (the buffers are np.empty; the kernel's upper triangle
    stays where it was).
    """
    n = 90
    _, K, r = _stream(n + 200, [0.4, 0.7], 1e-3, seed=11)
    A = WindowCholesky.workspace(n, limit=n + 1)
    A[...] = np.nan
    A[:n, :n][np.tril_indices(n)] = K[:n, :n][np.tril_indices(n)]
    assert cholesky_in_place(A, n) == 0
    wc = WindowCholesky.adopt(A, r[:n], n=n, limit=n + 1)
    lo, hi = 0, n
    for i in range(n, n + 200):
        wc.append(K[lo:hi, i], K[i, i], 1e-3, r[i])
        hi += 1
        wc.drop_first()
        lo += 1
        if i % 50 == 0:
            _check_against_fresh(wc, K, r, lo, hi)
    _check_against_fresh(wc, K, r, lo, hi)
    assert np.all(np.isfinite(wc.L)) and np.all(np.isfinite(wc.solve(np.ones(n))))


def test_without_cython_lapack_the_fallbacks_give_the_same_results(monkeypatch):
    """No ctypes access to scipy's Cython LAPACK: Givens drops and f2py dpotrf (with a copy)."""
    monkeypatch.setattr(_chol, '_dlasr', None)
    monkeypatch.setattr(_chol, '_dpotrf', None)
    n = 60
    _, K, r = _stream(n + 80, [0.4, 0.7], 1e-3, seed=12)
    A = WindowCholesky.workspace(n, limit=n + 1)
    A[:n, :n] = K[:n, :n]
    assert cholesky_in_place(A, n) == 0
    assert np.allclose(np.tril(A[:n, :n]), cholesky(K[:n, :n], lower=True), rtol=0, atol=1e-14)
    assert cholesky_in_place(np.asfortranarray(-np.eye(3))) == 1
    wc = WindowCholesky.adopt(A, r[:n], n=n, limit=n + 1)
    lo, hi = 0, n
    for i in range(n, n + 80):
        wc.append(K[lo:hi, i], K[i, i], 1e-3, r[i])
        hi += 1
        wc.drop_first()
        lo += 1
    _check_against_fresh(wc, K, r, lo, hi)

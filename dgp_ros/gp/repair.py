"""
Local passivity repair of a D-GP posterior.

The smallest change of its weights that makes the dissipated power non-negative at given velocities
(cutting planes for the certified policy).

The posterior mean is linear in its weights ``w = alpha + delta``: at a velocity ``z``,

    P(z) = z^T D(z) z = z^T M(z) z + sum_m G_m(z) . w_m,
    G_m(z)_i = s(z) sum_{n : (m, n) elements} z_m z_n k_mn(z, x_i) x_{n,i} s_y,m / s_x,n,

with ``s(z)`` the correction weight of the policy (the certified policy cuts the unblended
posterior: ``s = 1``). Requiring ``P(z_j) >= eps_j`` at the counterexamples ``z_j`` is a set of
linear inequalities in ``delta``. The change with the least ``sum_m |A_m delta_m|^2``
(``A_m = K_m + s_eps,m^2 I``: the change of the mean at the training velocities, in least
squares) follows from the dual, a small QP over one multiplier per counterexample:
``delta_m = A_m^-2 G_m^T lambda``, ``lambda >= 0`` minimizing ``0.5 lambda^T H lambda -
b^T lambda`` with ``H = sum_m G_m A_m^-2 G_m^T``. So the mean changes only near the
counterexamples, by kernel bumps centred on the training points. ``PowerProbe`` keeps the rows
of a fixed set of velocities, so repeated rounds cost matrix-vector products, not kernels.
"""
from __future__ import annotations

import math
from typing import Tuple
import warnings

import numpy as np
from scipy.optimize import minimize

from .kernels import se_ard

__all__ = ['power_rows', 'repair', 'PowerProbe', 'probe_points', 'most_negative']


def power_rows(post, Z: np.ndarray, weight: np.ndarray) -> Tuple[np.ndarray, list]:
    """
    Return the rows of the power constraints at velocities Z.

    (prior power (J,), [G_m (J, n) for each output]) of the velocities Z (J, N), model units;
    ``weight`` (J,) is the correction weight ``s(z)``.
    """
    s, hp = post.structure, post.hyper
    X = Z / hp.sx
    p0 = np.einsum('jn,jn->j', post.mean.raw_force(Z), Z)
    G = [np.zeros((Z.shape[0], post.n)) for _ in range(s.N)]
    ls = np.exp(hp.log_ls)
    for e, (m, n) in enumerate(s.elems):
        sf2 = math.exp(hp.log_sf2[e])
        if sf2 == 0.0:
            continue
        k = se_ard(X, post.X, ls[e], sf2)                       # (J, n)
        f = (weight * Z[:, m] * Z[:, n]) * (hp.sy[m] / hp.sx[n])
        G[m] += (k * post.X[:, n][None, :]) * f[:, None]
    return p0, G


def repair(post, rows: Tuple[np.ndarray, list], margin: np.ndarray) -> Tuple[np.ndarray, dict]:
    """
    Find the least change of the weights (n, N) with ``p0_j + sum_m G_m[j] .

    w_m >= margin_j``.

    ``rows``: (p0 (J,), [G_m (J, n)]) from ``power_rows`` (the dissipated power at the
    counterexamples) or ``diagonal_rows``. Returns ``(delta_change, info)``; info: constraints,
    active constraints, dual iterations, whether every constraint holds afterwards.
    """
    p0, G = rows
    P = p0 + sum(G[m] @ post.weights[:, m] for m in range(post.N))
    b = margin - P
    # metric (K_m + s^2 I)^2: the change of the mean at the training velocities, in least
    # squares (an RKHS-norm metric let a smooth output absorb the fix far from the violations)
    U = [f.solve(f.solve(G[m].T), trans=True) for m, f in enumerate(post.factors)]
    H = sum(u.T @ u for u in U)
    J = p0.shape[0]
    scale = float(np.max(np.abs(np.diag(H)))) or 1.0

    def dual(lam):
        g = H @ lam
        return float(0.5 * lam @ g - b @ lam) / scale, (g - b) / scale

    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        res = minimize(dual, np.zeros(J), jac=True, method='L-BFGS-B',
                       bounds=[(0.0, None)] * J, options={'maxiter': 2000, 'ftol': 1e-15,
                                                          'gtol': 1e-12})
    lam = np.maximum(res.x, 0.0)
    delta = np.column_stack([f.solve(f.solve(U[m] @ lam), trans=True)
                             for m, f in enumerate(post.factors)])
    after = P + sum(G[m] @ delta[:, m] for m in range(post.N))
    tol = 1e-9 * (np.abs(p0) + np.abs(P) + 1e-300)
    return delta, {'constraints': J, 'active': int(np.sum(lam > 0)), 'iterations': int(res.nit),
                   'holds': bool(np.all(after >= margin - tol))}


class PowerProbe:
    """
    The dissipated power at a fixed set of velocities, linear in the weights.

    ``Z`` (J, N) velocities, model units; ``weight`` (J,) the correction weight there. The rows
    (``power_rows``) are built once, so each repair round evaluates ``P(Z)`` for new weights by
    N matrix-vector products instead of rebuilding E kernel matrices (J x n each).
    """

    def __init__(self, post, Z: np.ndarray, weight: np.ndarray):
        self.Z = Z
        self.weight = weight
        self.rows = power_rows(post, Z, weight)

    def power(self, weights: np.ndarray) -> np.ndarray:
        """``P(Z)`` (J,) for the posterior weights (n, N)."""
        p0, G = self.rows
        return p0 + sum(G[m] @ weights[:, m] for m in range(weights.shape[1]))

    def take(self, idx: np.ndarray) -> Tuple[np.ndarray, list]:
        """Return the rows of the velocities ``Z[idx]`` (for ``repair``)."""
        p0, G = self.rows
        return p0[idx], [g[idx] for g in G]


def probe_points(post, lo: np.ndarray, hi: np.ndarray, rng, k: int = 400) -> np.ndarray:
    """
    Velocities where violations are looked for, (J, N), model units.

    A grid of the box ``[lo, hi]`` with its corners (5 points per side up to N = 3, the corners
    only above), ``k`` uniform in the box, ``k`` near the training velocities (violations sit
    where non-passive samples pulled the posterior; Gaussian steps of a third of the shortest
    lengthscale per dimension, clipped to the box) and up to ``k`` training velocities in the box.
    """
    Qd = post.Qd
    N = lo.size
    ls = np.exp(post.hyper.log_ls).min(axis=0) * post.hyper.sx     # shortest lengthscales
    near = Qd[rng.integers(0, len(Qd), k)] + rng.normal(size=(k, N)) * ls / 3.0
    inside = Qd[np.all((Qd >= lo) & (Qd <= hi), axis=1)]
    if len(inside) > k:
        inside = inside[rng.choice(len(inside), k, replace=False)]
    t = np.linspace(0.0, 1.0, 5 if N <= 3 else 2)
    grid = np.stack(np.meshgrid(*([t] * N), indexing='ij'), axis=-1).reshape(-1, N)
    return np.vstack([lo + grid * (hi - lo), rng.uniform(lo, hi, (k, N)),
                      np.clip(near, lo, hi), inside])


def most_negative(P: np.ndarray, keep: int) -> np.ndarray:
    """Return the indices of the ``keep`` most negative entries of P below 0 (worst first)."""
    bad = np.flatnonzero(P < 0)
    return bad[np.argsort(P[bad])[:keep]]

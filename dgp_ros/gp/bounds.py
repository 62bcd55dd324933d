"""
Bounds of a posterior's correction ``C(q)`` that hold for every ``q``: what the certificates prove.

``correction_terms`` hands the correction to ``verify.verify_box`` (branch and bound on boxes),
``l1_bound`` is the a-posteriori L1 / RKHS bound of each element, ``paper_bound`` the paper's
Theorem 1 bound. All in model units, (N, N) unless said.
"""
from __future__ import annotations

import math

import numpy as np

from .posterior import Posterior
from .verify import CorrectionTerms

__all__ = ['correction_terms', 'l1_bound', 'paper_bound']


def correction_terms(post: Posterior, scale: float) -> CorrectionTerms:
    """Return the correction in the form ``verify.verify_box`` proves (scaled by ``scale``)."""
    s, hp = post.structure, post.hyper
    coef = np.stack([post.X[:, n] * post.weights[:, m] * scale for m, n in s.elems])
    sf2 = np.exp(hp.log_sf2)
    with np.errstate(divide='ignore', invalid='ignore'):
        rk = np.where(sf2 > 0, np.sqrt(np.maximum(post.rkhs_sq(), 0.0) / sf2), 0.0)
    return CorrectionTerms(post.X, list(s.elems), sf2, np.exp(hp.log_ls), coef, post.mean,
                           hp.sx, hp.sy,
                           lambda Q: post.damping(Q, np.full(Q.shape[0], scale)),
                           rkhs=abs(scale) * rk)


def l1_bound(post: Posterior, rkhs: bool = True) -> np.ndarray:
    """
    A-posteriori bound ``B_mn >= sup_q |C_mn(q)|`` (N, N), model units.

    Per element the smaller of the L1 bound ``sf2 * sum_i |x_{n,i} alpha_{m,i}|`` and the
    RKHS bound ``|g|_H sqrt(sf2)`` (reproducing property and Cauchy-Schwarz); both hold for
    every q. ``rkhs=False``: the O(n) L1 form only (the per-update check).
    """
    s, hp = post.structure, post.hyper
    B = np.zeros((s.N, s.N))
    rk = post.rkhs_sq() if rkhs else None
    for e, (m, n) in enumerate(s.elems):
        sf2 = math.exp(hp.log_sf2[e])
        if sf2 == 0.0:
            continue
        a = post.X[:, n] * post.weights[:, m]
        b = sf2 * np.abs(a).sum()
        if rkhs:
            b = min(b, math.sqrt(max(float(rk[e]), 0.0) * sf2))
        B[m, n] = b * hp.sy[m] / hp.sx[n]
    return B


def paper_bound(post: Posterior) -> np.ndarray:
    """
    Theorem 1 bound with the sf^2 kernel bound.

    (N, N) model units: ``sf2_mn * sqrt(n) |x|_inf |dy_m| / s_eps^2``.
    """
    s, hp = post.structure, post.hyper
    xinf = float(np.abs(post.X).max())
    B = np.zeros((s.N, s.N))
    for e, (m, nn) in enumerate(s.elems):
        c = (math.sqrt(post.n) * xinf * np.linalg.norm(post.R[:, m])
             / math.exp(hp.log_sn2[m]))
        B[m, nn] = math.exp(hp.log_sf2[e]) * c * hp.sy[m] / hp.sx[nn]
    return B

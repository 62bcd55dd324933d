"""
The base layer of the passivity policies: certificate record, projection, policy interface.

Every policy module (``passivity`` for the simple ones and the registry, ``certified`` for the
structural certificate) builds on this module and nothing here imports them, so the registry can
import every policy without an import circle.

A damping model ``tau_hat(q) = D(q) q`` is *passive* when ``P(q) = q^T D(q) q >= 0``; each policy
declares which guarantee its certificates give (``PassivityPolicy.guarantee``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

__all__ = ['Certificate', 'project_passive', 'projection_lambda', 'passive_tolerance',
           'PolicyOptions', 'PassivityPolicy', 'diag_embed', 'GUARANTEES']


# ---------------------------------------------------------------------------- the record
#: What a certificate can guarantee, weakest first (``Certificate.guarantee``).
GUARANTEES = {
    'none': 'nothing',
    'pointwise': 'every published force has q^T tau >= 0 (projection; D itself not proven)',
    'passive-on-domain': 'q^T D(q) q >= 0 for every q: proven for the posterior on a box, which '
                         'blends to the passive prior outside it',
    'psd': 'the symmetric part of D(q) is positive semi-definite for every q in R^N',
}


@dataclass(frozen=True)
class Certificate:
    """
    Outcome of a passivity proof: a cheap record, read without any computation.

    certified : True when the model's damping matrix itself is proven passive as it is now
        (``guarantee`` says how); for ``projected``: every published estimate, pointwise.
    margin : normalized slack of the proof (>= 0 when certified; dimensionless).
    method : which proof: 'paper-theorem1', 'a-posteriori-bound', 'domain-bnb+blend',
        'psd-clip', 'projection', 'none' (see docs/PASSIVITY.md).
    domain : ``(lo, hi)`` arrays (N,), model units, of the box on which the GP correction itself
        is verified; None when the proof holds on all of R^N. Outside it the certified model
        blends smoothly to the prior mean.
    correction_scale : factor applied to the GP correction (1 = unchanged, 0 = prior only).
    details : numbers for diagnostics (boxes, seconds, ...).
    stale : True after ``update`` changed the weights so that the last proof no longer covers
        them; ``certified`` is then False, the published estimates are projected onto
        ``q^T tau >= 0`` (``guarantee`` 'pointwise'), and only ``recertify()`` (the estimator's
        refit worker) re-proves it.
    guarantee : the guarantee that holds *now*, a key of ``GUARANTEES``: 'psd',
        'passive-on-domain', 'pointwise' (pending, failed or ``projected``) or 'none'.
    """

    certified: bool
    margin: float
    method: str
    domain: Optional[tuple] = None
    correction_scale: float = 1.0
    details: dict = field(default_factory=dict)
    stale: bool = False
    guarantee: str = 'none'

    def to_dict(self) -> dict:
        d = {'certified': bool(self.certified), 'margin': float(self.margin),
             'method': self.method, 'correction_scale': float(self.correction_scale),
             'details': dict(self.details), 'stale': bool(self.stale),
             'guarantee': self.guarantee}
        d['domain'] = None if self.domain is None else [np.asarray(self.domain[0]).tolist(),
                                                        np.asarray(self.domain[1]).tolist()]
        return d

    @staticmethod
    def from_dict(d: dict) -> 'Certificate':
        dom = d.get('domain')
        if dom is not None:
            dom = (np.asarray(dom[0], float), np.asarray(dom[1], float))
        g = str(d.get('guarantee', 'none'))
        return Certificate(bool(d['certified']), float(d['margin']), str(d['method']), dom,
                           float(d.get('correction_scale', 1.0)), dict(d.get('details', {})),
                           bool(d.get('stale', False)), g if g in GUARANTEES else 'none')

    def with_details(self, **kw) -> 'Certificate':
        return replace(self, details={**self.details, **kw})

    def made_stale(self) -> 'Certificate':
        """Return the record, no longer proven: estimates are projected until re-proven."""
        return replace(self, certified=False, stale=True, guarantee='pointwise')


# ---------------------------------------------------------------------------- numerics
#: ``8 eps`` of float64: the rounding of a sum of products, relative to the sum of magnitudes
_ROUNDING = 8.0 * np.finfo(float).eps


def passive_tolerance(Q: np.ndarray, Tau: np.ndarray) -> np.ndarray:
    """
    Return the rounding tolerance of ``q^T tau`` per row, (k,): ``8 eps sum_n |q_n| |tau_n|``.

    A computed power in ``[-tol, 0)`` is rounding, not a violation; the decisions that replace an
    estimate use ``P < -tol``.
    """
    return _ROUNDING * np.einsum('ij,ij->i', np.abs(Q), np.abs(Tau))


def projection_lambda(Q: np.ndarray, Tau: np.ndarray, w_inv: Optional[np.ndarray] = None
                      ) -> np.ndarray:
    """
    Multiplier ``lambda(q) = max(0, -q^T tau) / (q^T W^-1 q)`` of the passivity projection.

    Q, Tau: (k, N); w_inv: (N,) diagonal of ``W^-1`` (default ones). Returns (k,); 0 where q = 0.
    """
    wi = np.ones(Q.shape[1]) if w_inv is None else np.asarray(w_inv, float)
    p = np.einsum('ij,ij->i', Q, Tau)
    den = np.einsum('ij,ij->i', Q * wi, Q)
    lam = np.zeros_like(p)
    ok = (p < 0) & (den > 0)
    lam[ok] = -p[ok] / den[ok]
    return lam


def project_passive(Q: np.ndarray, Tau: np.ndarray, w_inv: Optional[np.ndarray] = None
                    ) -> np.ndarray:
    """
    Nearest point (in the ``W`` norm) of ``{tau : q^T tau >= 0}`` to each row of ``Tau``.

    Q, Tau: (k, N). Returns (k, N) with ``q^T tau_p = max(q^T tau, 0)`` row by row. The set is
    convex and contains every passive truth, so the projection never moves an estimate further
    from a passive true force (non-expansiveness of projections onto convex sets).
    """
    Q = np.asarray(Q, float)
    Tau = np.asarray(Tau, float)
    if (np.einsum('ij,ij->i', Q, Tau) >= 0.0).all():
        return Tau.copy()       # already passive (the usual case: every answer goes through)
    wi = np.ones(Q.shape[1]) if w_inv is None else np.asarray(w_inv, float)
    lam = projection_lambda(Q, Tau, wi)
    out = Tau + lam[:, None] * (Q * wi)
    # rounding can leave q^T tau_p at -1e-16 relative: step a few ulps further where it does
    for _ in range(4):
        p = np.einsum('ij,ij->i', Q, out)
        bad = p < 0
        if not np.any(bad):
            break
        qb = Q[bad] * wi
        den = np.einsum('ij,ij->i', qb, Q[bad])
        size = np.einsum('ij,ij->i', np.abs(Q[bad]), np.abs(out[bad]))
        out[bad] += ((-p[bad] + 8 * np.finfo(float).eps * size) / den)[:, None] * qb
    return out


# ---------------------------------------------------------------------------- policies
@dataclass
class PolicyOptions:
    """Model arguments the policies read (see ``models`` for their meaning)."""

    domain_margin: float = 0.1
    blend_width: float = 0.1
    max_boxes: int = 50000
    operating_domain: Optional[tuple] = None
    projection_weights: Optional[np.ndarray] = None


class PassivityPolicy:
    """
    Base policy: how one mode makes a model's estimates passive.

    Class attributes (the registry's rules):
    name : the mode name; summary : one line for --help, parameter descriptions and docs;
    kinds : model kinds it applies to; certifies : True when the model itself is proven, so a
    refit that cannot be proven must not replace a proven model; guarantee : the strongest
    ``GUARANTEES`` key its certificates can give.
    """

    name = ''
    summary = ''
    kinds = ('full', 'diag', 'ard')
    certifies = False
    guarantee = 'none'
    needs_rkhs = False          # the fit computes the RKHS norms of the correction for it
    #: ``finalize`` needs the damping matrix of every answer (the model computes it)
    needs_damping = False

    def __init__(self, options: PolicyOptions):
        self.options = options
        self.cert: Optional[Certificate] = None

    # life cycle -------------------------------------------------------------
    def enforce(self, post):
        """After a fit: establish the guarantee; may return a refactorized posterior."""
        raise NotImplementedError  # pragma: no cover

    def defer(self, post):
        """After a fit whose expensive proof is left to ``recertify`` (the cheap ones here)."""
        return self.enforce(post)

    def after_update(self, post, Q_new: np.ndarray) -> None:
        """After ``update``: a cheap re-check (never a branch-and-bound)."""
        self.enforce(post)

    def recertify(self, post) -> Certificate:
        """Re-prove a stale certificate (may take seconds: refit worker only)."""
        return self.cert

    def reprove(self, post):
        """Prove from scratch unless the certificate holds (``recertify(full=True)``); post."""
        self.recertify(post)
        return post

    def restore_certificate(self, post, saved: Optional[Certificate]) -> None:
        """
        Re-derive the certificate after loading a model.

        After loading a model: re-derive the certificate (cheap proofs are recomputed,
        expensive ones are marked stale); ``saved`` (the file's record) is never trusted.
        """
        self.enforce(post)

    # estimates ---------------------------------------------------------------
    def weight(self, Q: np.ndarray) -> Optional[np.ndarray]:
        """Correction weight ``w(q)`` (k,) or None for 1."""
        return None

    def finalize(self, post, Q, tau, D):
        """
        Make the estimate passive (the one place in the model); tau (k, N), D (k, N, N) or None.

        Returns (tau, D).
        """
        return tau, D

    # persistence -------------------------------------------------------------
    def state(self) -> tuple:
        """(json-able dict, dict of arrays) of the policy's state besides the certificate."""
        return {}, {}

    def load_state(self, meta: dict, arrays: dict, post) -> None:
        """Inverse of ``state``; validates shapes against ``post``."""

    def _project(self, Q, tau, D, DQ=None):
        """
        Project each estimate onto ``q^T tau >= 0`` (``projected``'s finalize).

        The ``W``-norm projection of the force and the matching ``D + lambda W^-1``; a no-op (up
        to a few ulps) where the power is already non-negative. ``DQ``: ``D q`` per row when the
        caller has it (the same ``einsum``); ``tau`` itself then (every answer of the message
        path): one power per answer decides that nothing moves.
        """
        w_inv = self.options.projection_weights
        if D is None or DQ is tau:
            # the usual case: every power >= 0, so lambda = 0 (D unchanged) and the force is
            # returned as it is (what projection_lambda and project_passive would find)
            if (np.einsum('ij,ij->i', Q, tau) >= 0.0).all():
                return tau.copy(), D
        if D is not None:
            DQ = np.einsum('kij,kj->ki', D, Q) if DQ is None else DQ
            lam = projection_lambda(Q, DQ, w_inv)
            if np.any(lam > 0):
                wi = np.ones(Q.shape[1]) if w_inv is None else w_inv
                D = D + lam[:, None, None] * np.diag(wi)[None]
        return project_passive(Q, tau, w_inv), D


def diag_embed(d: np.ndarray) -> np.ndarray:
    """(k, N) -> (k, N, N) diagonal matrices."""
    out = np.zeros(d.shape + (d.shape[-1],))
    idx = np.arange(d.shape[-1])
    out[..., idx, idx] = d
    return out

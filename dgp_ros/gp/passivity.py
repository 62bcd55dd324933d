"""
Passivity: the policy registry, the certificate record, copositivity and the projection.

A damping model ``tau_hat(q) = D(q) q`` is *passive* when ``P(q) = q^T D(q) q >= 0``. If
``|D_mn(q) - M_mn(q)| <= B_mn`` with the prior ``M(q) = diag(m_d(q))``, ``m_d >= m_inf``, then with
``z = |q|``: ``P(q) >= z^T (diag(m_inf) - B) z``, so passivity holds for every ``q`` when
``A = diag(m_inf) - B`` is *copositive* (``z^T A z >= 0`` for all ``z >= 0``). Copositivity is
decided exactly for the small ``N`` of damping problems (Kaplan's criterion, Linear Algebra Appl.
2000: the minimum of ``z^T A z`` over ``{z >= 0, |z| = 1}`` is the least eigenvalue of a principal
submatrix that owns a positive eigenvector); that minimum is the *copositivity margin*.

**The registry.** ``POLICIES`` maps each mode name to its policy class; ``PASSIVITY_MODES`` is
its key tuple, and every layer (models, estimator, node, CLIs, benchmarks) reads the mode list,
the one-line documentation and the rules (which model kinds, whether a refit must be proven
before it is swapped in) from here. A policy instance belongs to one fitted model and holds its
passivity state (certificate, correction scale, verified domain). Within the model the policy is
the one place that makes an estimate passive (``finalize``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
import time
from typing import Optional

import numpy as np

from .copositive import copositivity_margin, max_scale, norm_margin

__all__ = ['Certificate', 'copositivity_margin', 'project_passive', 'projection_lambda',
           'passive_tolerance', 'POLICIES', 'PASSIVITY_MODES', 'policy_class', 'modes_for',
           'check_mode', 'PolicyOptions', 'PassivityPolicy']


# ---------------------------------------------------------------------------- the record
@dataclass(frozen=True)
class Certificate:
    """
    Outcome of a passivity proof: a cheap record, read without any computation.

    certified : True when ``q^T D(q) q >= 0`` is proven for the model as it is now (for
        ``projected``: every published estimate, pointwise).
    margin : normalized slack of the proof (>= 0 when certified; dimensionless).
    method : which proof: 'paper-theorem1', 'a-posteriori-bound', 'domain-bnb+blend',
        'projection', 'prior-only', 'none' (see docs/PASSIVITY.md).
    domain : ``(lo, hi)`` arrays (N,), model units, of the box on which the GP correction itself
        is verified; None when the proof holds on all of R^N. Outside it the certified model
        blends smoothly to the prior mean.
    correction_scale : factor applied to the GP correction (1 = unchanged, 0 = prior only).
    stale : True after ``update`` changed the weights so that the last proof no longer covers
        them; ``certified`` is then False, the published estimates stay passive pointwise (a
        query with negative power falls back to the prior), and only ``recertify()`` (the
        estimator's refit worker) re-proves it.
    details : numbers for diagnostics (boxes, seconds, ...).
    """

    certified: bool
    margin: float
    method: str
    domain: Optional[tuple] = None
    correction_scale: float = 1.0
    details: dict = field(default_factory=dict)
    stale: bool = False

    def to_dict(self) -> dict:
        d = {'certified': bool(self.certified), 'margin': float(self.margin),
             'method': self.method, 'correction_scale': float(self.correction_scale),
             'details': dict(self.details), 'stale': bool(self.stale)}
        d['domain'] = None if self.domain is None else [np.asarray(self.domain[0]).tolist(),
                                                        np.asarray(self.domain[1]).tolist()]
        return d

    @staticmethod
    def from_dict(d: dict) -> 'Certificate':
        dom = d.get('domain')
        if dom is not None:
            dom = (np.asarray(dom[0], float), np.asarray(dom[1], float))
        return Certificate(bool(d['certified']), float(d['margin']), str(d['method']), dom,
                           float(d.get('correction_scale', 1.0)), dict(d.get('details', {})),
                           bool(d.get('stale', False)))

    def with_details(self, **kw) -> 'Certificate':
        return replace(self, details={**self.details, **kw})


# ---------------------------------------------------------------------------- numerics
def passive_tolerance(Q: np.ndarray, Tau: np.ndarray) -> np.ndarray:
    """
    Return the rounding tolerance of ``q^T tau`` per row, (k,): ``8 eps sum_n |q_n| |tau_n|``.

    A computed power in ``[-tol, 0)`` is rounding, not a violation; the decisions that replace an
    estimate use ``P < -tol``.
    """
    return 8.0 * np.finfo(float).eps * np.einsum('ij,ij->i', np.abs(Q), np.abs(Tau))


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
    refit that cannot be proven must not replace a proven model.
    """

    name = ''
    summary = ''
    kinds = ('full', 'diag', 'ard')
    certifies = False
    needs_rkhs = False          # the fit computes the RKHS norms of the correction for it

    def __init__(self, options: PolicyOptions):
        self.options = options
        self.cert: Optional[Certificate] = None

    # life cycle -------------------------------------------------------------
    def enforce(self, post):
        """After a fit: establish the guarantee; may return a refactorized posterior."""
        raise NotImplementedError  # pragma: no cover

    def after_update(self, post, Q_new: np.ndarray) -> None:
        """After ``update``: a cheap re-check (never a branch-and-bound)."""
        self.enforce(post)

    def recertify(self, post) -> Certificate:
        """Re-prove a stale certificate (may take seconds: refit worker only)."""
        return self.cert

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

    def _stale_fallback(self, post, Q, tau, D):
        """
        Apply the pointwise guarantee of a stale certificate.

        Pointwise guarantee of a stale certificate: a query whose power is negative beyond
        rounding gets the prior mean there.
        """
        if self.cert is None or not self.cert.stale:
            return tau, D
        bad = np.einsum('ij,ij->i', Q, tau) < -passive_tolerance(Q, tau)
        if D is not None:
            bad_d = np.einsum('ki,kij,kj->k', Q, D, Q) < -passive_tolerance(Q, tau)
            bad = bad | bad_d
        if np.any(bad):
            tau = tau.copy()
            tau[bad] = post.mean.force(Q[bad])
            if D is not None:
                D = D.copy()
                D[bad] = diag_embed(post.mean.diag(Q[bad]))
        return tau, D


def diag_embed(d: np.ndarray) -> np.ndarray:
    """(k, N) -> (k, N, N) diagonal matrices."""
    out = np.zeros(d.shape + (d.shape[-1],))
    idx = np.arange(d.shape[-1])
    out[..., idx, idx] = d
    return out


class NonePolicy(PassivityPolicy):
    needs_rkhs = True
    name = 'none'
    summary = ('nothing enforced; certificate() reports whether the a-posteriori bound happens '
               'to hold')

    def enforce(self, post, rkhs: bool = True):
        if not post.structure.has_damping:
            self.cert = Certificate(False, -np.inf, 'none', None, 1.0,
                                    {'note': 'ARD-GP has no damping structure'})
            return post
        m = norm_margin(post.mean.diag_inf(), post.l1_bound(rkhs=rkhs))
        self.cert = Certificate(bool(m >= 0), float(m), 'a-posteriori-bound (not enforced)')
        return post

    def after_update(self, post, Q_new):
        self.enforce(post, rkhs=False)


class ProjectedPolicy(PassivityPolicy):
    name = 'projected'
    summary = ('every estimate projected onto qd^T tau >= 0 (exact, pointwise, never less '
               'accurate where the truth is passive)')

    def enforce(self, post):
        self.cert = Certificate(True, 0.0, 'projection', None, 1.0,
                                {'note': 'every prediction projected onto q^T tau >= 0'})
        return post

    def after_update(self, post, Q_new):
        pass

    def finalize(self, post, Q, tau, D):
        w_inv = self.options.projection_weights
        if D is not None:
            lam = projection_lambda(Q, np.einsum('kij,kj->ki', D, Q), w_inv)
            wi = np.ones(Q.shape[1]) if w_inv is None else w_inv
            D = D + lam[:, None, None] * np.diag(wi)[None]
        return project_passive(Q, tau, w_inv), D


class PaperPolicy(PassivityPolicy):
    """Theorem 1 / Corollary 1 of the paper with the sf^2 kernel bound (docs/PASSIVITY.md)."""

    name = 'paper'
    summary = "the paper's Theorem 1 enforced on the hyper-parameters (proven on all of R^N)"
    kinds = ('full', 'diag')
    certifies = True

    def __init__(self, options):
        super().__init__(options)
        self.scale = 1.0
        self.hyper_scale = 1.0

    def enforce(self, post):
        t0 = time.perf_counter()
        m_inf = post.mean.diag_inf()
        hp = post.hyper.copy()
        changed = False
        dead = m_inf <= 1e-12 * max(m_inf.max(), 1e-300)
        for e, (m, n) in enumerate(post.structure.elems):
            # an element touching a dimension without prior damping can never be certified
            if (dead[m] or dead[n]) and hp.log_sf2[e] > -np.inf:
                hp.log_sf2[e] = -np.inf
                changed = True
        if changed:
            post = post.with_kernel(hp)
        g = max_scale(m_inf, post.paper_bound())
        if g < 1.0:
            hp = post.hyper.copy()
            with np.errstate(divide='ignore'):
                hp.log_sf2 = hp.log_sf2 + (math.log(g * (1 - 1e-9)) if g > 0 else -np.inf)
            post = post.with_kernel(hp)
        self.hyper_scale = g
        self.scale = 1.0
        self._check(post, after_update=False)
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)
        return post

    def _check(self, post, after_update):
        m_inf = post.mean.diag_inf()
        B = post.paper_bound()
        s = max_scale(m_inf, B, 1.0)
        self.scale = min(self.scale, s) if after_update else s
        margin = norm_margin(m_inf, self.scale * B)
        method = 'paper-theorem1' if self.scale == 1.0 else 'paper-theorem1+shrink'
        self.cert = Certificate(bool(margin >= 0), float(margin), method, None, self.scale,
                                {'hypervariance_scale': float(self.hyper_scale)})

    def after_update(self, post, Q_new):
        t0 = time.perf_counter()
        self._check(post, after_update=True)
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)

    def weight(self, Q):
        return np.full(Q.shape[0], self.scale)

    def restore_certificate(self, post, saved):
        self._check(post, after_update=True)

    def state(self):
        return {'scale': self.scale, 'hyper_scale': self.hyper_scale}, {}

    def load_state(self, meta, arrays, post):
        self.scale = float(meta['scale'])
        self.hyper_scale = float(meta.get('hyper_scale', 1.0))
        if not (0.0 <= self.scale <= 1.0 and 0.0 <= self.hyper_scale <= 1.0):
            raise ValueError('paper model: correction scales must lie in [0, 1]')


def policy_class(mode: str):
    """Return the policy class of a mode; ValueError naming the choices."""
    check_mode(mode)
    return POLICIES[mode]


def check_mode(mode: str, kind: Optional[str] = None) -> None:
    """Raise ValueError unless ``mode`` is a passivity mode (that applies to model ``kind``)."""
    if mode not in POLICIES:
        raise ValueError(f'passivity must be one of {", ".join(PASSIVITY_MODES)}, got {mode!r}')
    cls = POLICIES[mode]
    if kind is not None and kind not in cls.kinds:
        raise ValueError(f'passivity {mode!r} does not apply to model {kind!r} (it has no '
                         f'damping structure to certify): use one of '
                         f'{", ".join(modes_for(kind))}')


def modes_for(kind: str) -> tuple:
    """Return the passivity modes that apply to a model kind, in registry order."""
    return tuple(m for m in PASSIVITY_MODES if kind in policy_class(m).kinds)


def describe_modes() -> str:
    """One line per mode (for --help texts and parameter descriptions)."""
    return '; '.join(f'{m}: {policy_class(m).summary}' for m in PASSIVITY_MODES)


from .certified import CertifiedPolicy  # noqa: E402,I100  (it builds on the classes above)

#: The registry: mode name -> policy class, in the order modes are listed everywhere.
POLICIES = {'none': NonePolicy, 'paper': PaperPolicy, 'certified': CertifiedPolicy,
            'projected': ProjectedPolicy}
PASSIVITY_MODES = tuple(POLICIES)

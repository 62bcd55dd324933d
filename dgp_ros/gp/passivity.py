"""
Passivity: the policy registry and the simple policies (none, projected, paper).

The certificate record, the projection and the policy interface are the layer below
(``policy``); the structural certificate is ``certified``. This module imports both and neither
imports it.

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

import math
import time
from typing import Optional

import numpy as np

from .bounds import l1_bound, paper_bound
from .certified import CertifiedPolicy
from .copositive import copositivity_margin, max_scale, norm_margin
from .policy import (Certificate, passive_tolerance, PassivityPolicy, PolicyOptions,
                     project_passive, projection_lambda)

__all__ = ['Certificate', 'copositivity_margin', 'project_passive', 'projection_lambda',
           'passive_tolerance', 'POLICIES', 'PASSIVITY_MODES', 'policy_class', 'modes_for',
           'check_mode', 'PolicyOptions', 'PassivityPolicy']


class NonePolicy(PassivityPolicy):
    guarantee = 'none'
    needs_rkhs = True
    name = 'none'
    summary = ('nothing enforced; certificate() reports whether the a-posteriori bound happens '
               'to hold')

    def enforce(self, post, rkhs: bool = True):
        if not post.structure.has_damping:
            self.cert = Certificate(False, -np.inf, 'none', None, 1.0,
                                    {'note': 'ARD-GP has no damping structure'})
            return post
        if not post.mean.psd_over_diagonal:
            self.cert = Certificate(False, -np.inf, 'none', None, 1.0,
                                    {'note': 'the prior carries couplings: no global bound'})
            return post
        m = norm_margin(post.mean.diag_inf(), l1_bound(post, rkhs=rkhs))
        self.cert = Certificate(bool(m >= 0), float(m), 'a-posteriori-bound (not enforced)',
                                guarantee='psd' if m >= 0 else 'none')
        return post

    def after_update(self, post, Q_new):
        self.enforce(post, rkhs=False)


class ProjectedPolicy(PassivityPolicy):
    name = 'projected'
    summary = ('every estimate projected onto qd^T tau >= 0 (exact, pointwise, never less '
               'accurate where the truth is passive)')
    guarantee = 'pointwise'

    def enforce(self, post):
        self.cert = Certificate(True, 0.0, 'projection', None, 1.0,
                                {'note': 'every prediction projected onto q^T tau >= 0'},
                                guarantee='pointwise')
        return post

    def after_update(self, post, Q_new):
        pass

    def finalize(self, post, Q, tau, D):
        return self._project(Q, tau, D)


class PaperPolicy(PassivityPolicy):
    """Theorem 1 / Corollary 1 of the paper with the sf^2 kernel bound (docs/PASSIVITY.md)."""

    name = 'paper'
    summary = "the paper's Theorem 1 enforced on the hyper-parameters (proven on all of R^N)"
    kinds = ('full', 'diag')
    certifies = True
    guarantee = 'psd'

    def __init__(self, options):
        super().__init__(options)
        self.scale = 1.0
        self.hyper_scale = 1.0

    def enforce(self, post):
        if not post.mean.is_diagonal:
            raise ValueError("passivity 'paper' needs a diagonal prior mean (Theorem 1); a "
                             "prior with couplings (gp.coupled) is for 'certified' and "
                             "'projected'")
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
        g = max_scale(m_inf, paper_bound(post))
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
        B = paper_bound(post)
        s = max_scale(m_inf, B, 1.0)
        self.scale = min(self.scale, s) if after_update else s
        margin = norm_margin(m_inf, self.scale * B)
        method = 'paper-theorem1' if self.scale == 1.0 else 'paper-theorem1+shrink'
        self.cert = Certificate(bool(margin >= 0), float(margin), method, None, self.scale,
                                {'hypervariance_scale': float(self.hyper_scale)},
                                guarantee='psd' if margin >= 0 else 'none')

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


#: The registry: mode name -> policy class, in the order modes are listed everywhere.
POLICIES = {'none': NonePolicy, 'paper': PaperPolicy, 'certified': CertifiedPolicy,
            'projected': ProjectedPolicy}
PASSIVITY_MODES = tuple(POLICIES)

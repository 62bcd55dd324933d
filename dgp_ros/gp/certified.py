"""
The ``certified`` passivity policy: a structural certificate of the posterior ``D_hat`` itself.

Three proofs, tried in order (docs/PASSIVITY.md):

1. ``a-posteriori-bound`` (global): with the weights known, ``|C_mn(q)| <= B_mn`` for every q
   (``Posterior.l1_bound``); ``diag(m_inf) - B`` copositive proves passivity on all of R^N.
2. ``domain-bnb+blend``: branch-and-bound (``verify.verify_box``) proves ``q^T D_hat(q) q >= 0``
   on an outer box ``Omega'`` around the data (and the declared operating domain); the published
   model is ``M(q) + w(q) C(q)`` with a C2 blend ``w`` that is 1 on the inner box ``Omega`` and 0
   outside ``Omega'``, a convex combination of two passive models, so passive everywhere.
3. If (2) fails, smaller domains, then a smaller correction scale ``s`` (bisection between the
   largest scale (1) proves and 1).

After ``update`` only the O(n) form of (1) is re-checked; if it fails the certificate becomes
*stale* (estimates stay passive pointwise) until ``recertify`` re-runs (2), which the online
estimator does only in its refit worker.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .copositive import max_scale, norm_margin
from .policy import Certificate, PassivityPolicy
from .repair import diagonal_rows, find_violations, power_rows, repair
from .verify import verify_box
from .verify import verify_diagonal

__all__ = ['CertifiedPolicy']


def _box_of(Qd: np.ndarray):
    """(lo, hi, range) of the samples, range floored at 10 % of the RMS (a flat dimension)."""
    lo, hi = Qd.min(axis=0), Qd.max(axis=0)
    rms = np.sqrt(np.mean(Qd * Qd, axis=0))
    return lo, hi, np.maximum(hi - lo, np.maximum(0.1 * rms, 1e-9))


def _make_domain(box, margin, blend):
    """Inner (verified, w = 1) and outer (w = 0 beyond) boxes from a data box."""
    lo, hi, rng = box
    ilo, ihi = lo - margin * rng, hi + margin * rng
    olo, ohi = ilo - blend * rng, ihi + blend * rng
    return (ilo, ihi), (olo, ohi)


def _blend(Q: np.ndarray, domain) -> np.ndarray:
    """C2 smootherstep weight (k,): 1 on the inner box, 0 outside the outer box."""
    (ilo, ihi), (olo, ohi) = domain
    t_lo = np.clip((Q - olo) / np.maximum(ilo - olo, 1e-300), 0.0, 1.0)
    t_hi = np.clip((ohi - Q) / np.maximum(ohi - ihi, 1e-300), 0.0, 1.0)
    t = np.minimum(t_lo, t_hi)
    s = t * t * t * (t * (6.0 * t - 15.0) + 10.0)
    return np.prod(s, axis=1)


class CertifiedPolicy(PassivityPolicy):
    """See the module docstring."""

    name = 'certified'
    summary = ('the posterior damping matrix itself proven passive (global bound, else '
               'branch-and-bound on a box around the data blended to the prior outside)')
    kinds = ('full', 'diag')
    certifies = True
    needs_rkhs = True
    #: cutting-plane rounds of the repair before the correction is shrunk instead
    REPAIR_ROUNDS = 4
    #: above this many velocities the element-wise proof (diagonal dominance) replaces the joint
    #: branch-and-bound, whose boxes must be small in every dimension at once
    JOINT_MAX_N = 3

    def __init__(self, options):
        super().__init__(options)
        self.scale = 1.0
        self.domain = None          # ((ilo, ihi), (olo, ohi)) model units
        self.leaves = None          # proven partition of the outer box, reused by recertify
        self.data_box = None

    # ---------------------------------------------------------------- domains
    def _hull(self, box):
        """Return the data box joined with the declared operating domain (if any)."""
        od = self.options.operating_domain
        if od is None:
            return box
        lo = np.minimum(box[0], od[0])
        hi = np.maximum(box[1], od[1])
        return lo, hi, np.maximum(hi - lo, box[2])

    def _candidate_domains(self):
        o = self.options
        boxes = [self._hull(self.data_box)]
        if o.operating_domain is not None:
            boxes.append(self.data_box)
        return [_make_domain(b, f_m, f_b) for b in boxes for f_m, f_b in
                ((o.domain_margin, o.blend_width), (0.5 * o.domain_margin, 0.5 * o.blend_width),
                 (0.0, 0.25 * o.blend_width))]

    # ---------------------------------------------------------------- life cycle
    def enforce(self, post):
        t0 = time.perf_counter()
        self.data_box = _box_of(post.Qd)
        o = self.options
        self.domain = _make_domain(self._hull(self.data_box), o.domain_margin, o.blend_width)
        self.scale = 1.0
        self.leaves = None
        m_inf = post.mean.diag_inf()
        m = norm_margin(m_inf, post.l1_bound(rkhs=True))
        if m >= 0:
            self.cert = Certificate(True, float(m), 'a-posteriori-bound', None, 1.0)
        else:
            self._prove(post, self._candidate_domains(), start=1.0, reuse=False)
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)
        return post

    def after_update(self, post, Q_new):
        """
        Check the O(n) global bound at the current scale.

        Else grow the domain to the data and mark the certificate stale.
        """
        t0 = time.perf_counter()
        m = norm_margin(post.mean.diag_inf(), self.scale * post.l1_bound(rkhs=False))
        if m >= 0:
            self.leaves = None
            self.cert = Certificate(True, float(m), 'a-posteriori-bound', None, self.scale,
                                    {'seconds': time.perf_counter() - t0})
            return
        (ilo, ihi), _ = self.domain
        Qd = post.Qd
        if not np.all((Qd >= ilo) & (Qd <= ihi)):
            # samples outside the verified box would only ever see the prior: grow the domain
            self.data_box = _box_of(Qd)
            o = self.options
            self.domain = _make_domain(self._hull(self.data_box), o.domain_margin,
                                       o.blend_width)
            self.leaves = None
        if not self.cert.stale:
            self.cert = Certificate(False, self.cert.margin, self.cert.method, self.cert.domain,
                                    self.cert.correction_scale, dict(self.cert.details), True)

    def recertify(self, post) -> Certificate:
        """
        Re-prove a stale certificate.

        A global certificate is first re-checked with the (tighter than per-update) RKHS bound; a
        domain certificate by branch-and-bound on its domain, starting from the last proven
        partition.
        """
        if self.cert is None or not self.cert.stale:
            return self.cert
        t0 = time.perf_counter()
        m = -np.inf
        if self.cert.method != 'domain-bnb+blend':
            m = norm_margin(post.mean.diag_inf(), self.scale * post.l1_bound(rkhs=True))
        if m >= 0:
            self.leaves = None
            self.cert = Certificate(True, float(m), 'a-posteriori-bound', None, self.scale)
        else:
            self._prove(post, [self.domain], start=self.scale, reuse=True)
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)
        return self.cert

    def restore_certificate(self, post, saved):
        """
        Distrust a loaded certificate.

        It is stale until ``recertify`` proves it again (the saved proof partition is dropped too;
        the blend keeps the saved domain meanwhile).
        """
        self.leaves = None
        method = saved.method if saved is not None else 'a-posteriori-bound'
        if method not in ('a-posteriori-bound', 'domain-bnb+blend', 'prior-only'):
            method = 'a-posteriori-bound'
        dom = self.domain[0] if method == 'domain-bnb+blend' else None
        self.cert = Certificate(False, float('nan'), method, dom, self.scale,
                                {'note': 'loaded from a file: not proven yet'}, stale=True)

    def _prove(self, post, domains, start: float, reuse: bool) -> None:
        """
        Prove on each domain in turn (with repairs of real counterexamples on the first).

        Else shrink the correction (module doc). Up to ``JOINT_MAX_N`` velocities the joint
        branch-and-bound (``verify_box``), above it the element-wise proof (diagonal dominance),
        whose boxes need to be small only along one element's short lengthscales.
        """
        joint = post.N <= self.JOINT_MAX_N
        res = None
        reason = ''
        for k, dom in enumerate(domains):
            (ilo, ihi), (olo, ohi) = dom
            if not joint:
                if self._prove_elementwise(post, dom, start, repair_rounds=self.REPAIR_ROUNDS
                                           if k == 0 else 0, budget=self.options.max_boxes):
                    return
                reason = self.cert_reason
                continue
            res = verify_box(post.correction_terms(start), olo, ohi,
                             max_boxes=self.options.max_boxes,
                             leaves=self.leaves if reuse else None)
            extra = {}
            if not res.ok and k == 0 and res.witness is not None:
                res, extra = self._repair(post, dom, start, res)
            if res.ok:
                self.domain, self.scale, self.leaves = dom, start, res.leaves
                self.cert = Certificate(True, res.margin, 'domain-bnb+blend', (ilo, ihi), start,
                                        {'boxes': res.boxes, 'bnb_seconds': res.seconds,
                                         'outer_box': [olo.tolist(), ohi.tolist()], **extra})
                return
            reason = res.reason
        # shrink the correction on the smallest domain: the global bound's scale is always
        # provable; bisect above it with the domain proof
        self.domain = dom = domains[-1]
        (ilo, ihi), (olo, ohi) = dom
        m_inf = post.mean.diag_inf()
        B = post.l1_bound(rkhs=True)
        s_lo, s_hi, best = max_scale(m_inf, B, start), start, None
        budget = max(self.options.max_boxes // 8, 500)
        for _ in range(6):
            if s_hi - s_lo <= 0.02 * start:
                break
            mid = 0.5 * (s_lo + s_hi)
            if joint:
                r = verify_box(post.correction_terms(mid), olo, ohi, max_boxes=budget)
                ok = r.ok
            else:
                ok = r = self._prove_elementwise(post, dom, mid, repair_rounds=0, budget=budget)
                cert = self.cert
            if ok:
                s_lo, best = mid, r
            else:
                s_hi = mid
        self.scale = s_lo
        if best is not None and joint:
            self.leaves = best.leaves
            self.cert = Certificate(True, best.margin, 'domain-bnb+blend', (ilo, ihi), s_lo,
                                    {'boxes': best.boxes, 'bnb_seconds': best.seconds,
                                     'outer_box': [olo.tolist(), ohi.tolist()],
                                     'reason': reason})
        elif best is not None:
            self.cert = cert.with_details(reason=reason)
            self.domain, self.scale = dom, s_lo
        else:
            self.leaves = None
            mm = norm_margin(m_inf, s_lo * B)
            self.cert = Certificate(bool(mm >= 0), float(mm),
                                    'a-posteriori-bound' if s_lo > 0 else 'prior-only', None,
                                    s_lo, {'reason': reason})

    def _prove_elementwise(self, post, dom, start, repair_rounds: int, budget: int) -> bool:
        """
        Diagonal dominance on the domain.

        ``D_nn >= sum_{m != n} (B_nm + B_mn) / 2`` for each n by ``verify.verify_diagonal``
        (low-dimensional searches, one shared box budget), the off-diagonal elements by their
        global bounds ``B``. Each round first searches for velocities that break an inequality
        (sampling; the search's own counterexamples too) and repairs them (cutting planes), then
        proves; up to ``REPAIR_ROUNDS`` rounds. Sets the certificate and returns True on success.
        """
        (ilo, ihi), (olo, ohi) = dom
        N = post.N
        rng = np.random.default_rng(1)
        old = None if post.delta is None else post.delta.copy()
        Zs = [np.zeros((0, N)) for _ in range(N)]
        boxes, t0 = 0, time.perf_counter()
        witnesses = {}

        def weight(Q):
            return start * _blend(Q, dom)

        self.cert_reason = ''
        for rounds in range(repair_rounds + 1):
            B = start * post.l1_bound(rkhs=True)
            beta = 0.5 * (B.sum(axis=0) + B.sum(axis=1)) - np.diag(B)
            if rounds < repair_rounds:
                rows, margins = [], []
                for n in range(N):
                    def dnn(Q, n=n):
                        return post.damping(Q, weight(Q))[:, n, n] - beta[n]
                    Z = find_violations(dnn, post, olo, ohi, rng, k=5000 * (rounds + 1),
                                        keep=100)
                    if n in witnesses:
                        Z = np.vstack([witnesses.pop(n)[None, :], Z])
                    if len(Z) == 0:
                        continue
                    Zs[n] = np.vstack([Zs[n], Z])
                    rows.append(diagonal_rows(post, Zs[n], weight(Zs[n]), n))
                    margins.append(beta[n] + 0.05 * post.mean.diag(Zs[n])[:, n])
                if rows:
                    delta, _ = repair(post, (np.concatenate([r[0] for r in rows]),
                                             [np.vstack([r[1][m] for r in rows])
                                              for m in range(N)]), np.concatenate(margins))
                    post.set_delta(delta if post.delta is None else post.delta + delta)
                    B = start * post.l1_bound(rkhs=True)
                    beta = 0.5 * (B.sum(axis=0) + B.sum(axis=1)) - np.diag(B)
            T = post.correction_terms(start)
            ok = True
            for n in range(N):
                r = verify_diagonal(T, n, olo, ohi, float(beta[n]),
                                    max_boxes=max(budget - boxes, 1))
                boxes += r.boxes
                if not r.ok:
                    ok = False
                    self.cert_reason = r.reason
                    if r.witness is not None:
                        witnesses[n] = r.witness
                    break
            if ok:
                rep = {} if post.delta is None else {
                    'repaired_points': int(sum(len(z) for z in Zs)), 'repair_rounds': rounds}
                self.cert = Certificate(True, 0.0, 'elementwise-bnb+blend', (ilo, ihi), start,
                                        {'boxes': boxes, 'bnb_seconds': time.perf_counter() - t0,
                                         'outer_box': [olo.tolist(), ohi.tolist()], **rep})
                self.domain, self.scale, self.leaves = dom, start, None
                return True
            if boxes >= budget:
                break
        post.set_delta(old)
        return False

    def _repair(self, post, dom, start, res):
        """
        Repair the weights by cutting planes.

        Cutting planes: make the power non-negative (with a 5 % margin of the prior's) at the
        counterexamples found so far by the least change of the weights, re-verify, repeat.
        Returns the last verification and the repair's record for the certificate.
        """
        (ilo, ihi), (olo, ohi) = dom
        rng = np.random.default_rng(0)
        old = None if post.delta is None else post.delta.copy()

        def weight(Q):
            return start * _blend(Q, dom)

        def power(Q):
            return np.einsum('ki,kij,kj->k', Q, post.damping(Q, weight(Q)), Q)

        data = post.Qd
        lo, hi = data.min(axis=0), data.max(axis=0)
        probe = np.vstack([data, rng.uniform(lo, hi, (4000, lo.size))])
        before = post.predict(probe, weight(probe))[0]
        Zall = np.zeros((0, olo.size))
        rounds = 0
        for rounds in range(1, self.REPAIR_ROUNDS + 1):
            Z = find_violations(power, post, olo, ohi, rng)
            if res.witness is not None:
                Z = np.vstack([res.witness[None, :], Z])
            if len(Z) == 0:
                break
            Zall = np.vstack([Zall, Z])
            margin = 0.05 * np.einsum('jn,jn->j', Zall * post.mean.diag(Zall), Zall)
            delta, info = repair(post, power_rows(post, Zall, weight(Zall)), margin)
            post.set_delta(delta if post.delta is None else post.delta + delta)
            res = verify_box(post.correction_terms(start), olo, ohi,
                             max_boxes=self.options.max_boxes)
            if res.ok:
                break
        if not res.ok:
            post.set_delta(old)             # no proof: the shrinking below starts from the fit
            return res, {}
        change = np.abs(post.predict(probe, weight(probe))[0] - before).max(axis=0)
        return res, {'repaired_points': int(len(Zall)), 'repair_rounds': rounds,
                     'repair_max_change_in_data_box': change.tolist()}

    # ---------------------------------------------------------------- estimates
    def weight(self, Q):
        """
        Return the correction weight.

        ``s * w(q)``: the correction scale times the C2 smootherstep blend that is 1 on the
        verified box and 0 outside the outer box (only for a domain certificate).
        """
        if self.cert is None or self.cert.domain is None or self.domain is None:
            return np.full(Q.shape[0], self.scale)
        return self.scale * _blend(Q, self.domain)

    def finalize(self, post, Q, tau, D):
        return self._project(Q, tau, D) if self.cert is not None and self.cert.stale else (tau, D)

    # ---------------------------------------------------------------- persistence
    def state(self):
        (ilo, ihi), (olo, ohi) = self.domain
        arrays = {'dom_ilo': ilo, 'dom_ihi': ihi, 'dom_olo': olo, 'dom_ohi': ohi}
        if self.leaves is not None:
            arrays['leaves_lo'], arrays['leaves_hi'] = self.leaves
        return {'scale': self.scale}, arrays

    def load_state(self, meta, arrays, post):
        N = post.N
        for k in ('dom_ilo', 'dom_ihi', 'dom_olo', 'dom_ohi'):
            if k not in arrays or arrays[k].shape != (N,):
                raise ValueError(f'certified model: {k} missing or not of shape ({N},)')
        self.scale = float(meta['scale'])
        if not 0.0 <= self.scale <= 1.0:
            raise ValueError(f'certified model: correction scale {self.scale} not in [0, 1]')
        self.domain = ((arrays['dom_ilo'], arrays['dom_ihi']),
                       (arrays['dom_olo'], arrays['dom_ohi']))
        lv: Optional[tuple] = None
        if 'leaves_lo' in arrays:
            lv = (arrays['leaves_lo'], arrays['leaves_hi'])
            if lv[0].ndim != 2 or lv[0].shape != lv[1].shape or lv[0].shape[1] != N:
                raise ValueError('certified model: malformed proof partition')
        self.leaves = lv
        self.data_box = _box_of(post.Qd)

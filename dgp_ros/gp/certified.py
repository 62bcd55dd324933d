"""
The ``certified`` passivity policy: a certificate of the published damping matrix ``D`` itself.

In order (docs/PASSIVITY.md):

1. ``a-posteriori-bound`` (any N, global, PSD): with the weights known, ``|C_mn(q)| <= B_mn`` for
   every q (``bounds.l1_bound``); ``diag(m_inf) - B`` copositive proves that the symmetric
   part of ``D(q)`` is PSD for every q in R^N. Nothing is changed. It holds over a prior that
   is its diagonal plus a PSD part (``PriorMean.psd_over_diagonal``: a transmission's motors)
   as over a diagonal one; not over ``gp.coupled``'s.
2. Up to ``JOINT_MAX_N`` velocities, ``domain-bnb+blend`` (passive on a domain): branch-and-bound
   (``verify.verify_box``) proves ``q^T D(q) q >= 0`` on an outer box ``Omega'`` around the data
   (and a declared operating domain). Counterexamples are repaired *locally* first: the least
   change of the weights that makes the power non-negative at them (cutting planes,
   ``repair``), with the kernel rows of a fixed probe set built once for all rounds. The
   published model is ``M(q) + w(q) C(q)`` with a C2 blend ``w`` that is 1 on the inner box
   ``Omega`` and 0 outside ``Omega'``: a convex combination of two passive models. If no proof is
   found within the budget, nothing is certified and every answer is projected onto
   ``q^T tau >= 0`` (``guarantee`` 'pointwise', the ``projected`` mode's answers).
3. Above ``JOINT_MAX_N`` velocities, ``psd-clip`` (PSD everywhere): the symmetric part of
   ``D(q)`` gets the smooth eigenvalue floor of ``psd`` at the queries where it is not positive
   definite, and is left exactly as fitted where it is. (A branch-and-bound over a 7-D box
   with 49 element GPs does not finish in minutes, and diagonal dominance with global
   off-diagonal bounds shrank the whole correction: docs/PASSIVITY.md.)

After ``update`` only the O(n) form of (1) is re-checked. A ``psd-clip`` certificate holds for any
weights, so it never goes stale; a domain certificate becomes *stale* (answers projected) until
``recertify`` re-runs (2), which the online estimator does only in its refit worker.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .bounds import correction_terms, l1_bound
from .copositive import norm_margin
from .policy import Certificate, PassivityPolicy
from .psd import psd_clip
from .repair import most_negative, power_rows, PowerProbe, probe_points, repair
from .verify import BoxResult, verify_box

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
    summary = ('the damping matrix itself proven passive: a global bound, else (up to 3 '
               'velocities) branch-and-bound on a box around the data after local repairs, '
               'else (more velocities) made positive semi-definite where it is not')
    kinds = ('full', 'diag')
    certifies = True
    guarantee = 'psd'
    needs_rkhs = True
    #: cutting-plane rounds of the local repair before the proof is given up (answers projected)
    REPAIR_ROUNDS = 6
    #: counterexamples added per round (the most negative power first)
    CUTS_PER_ROUND = 100
    #: up to this many velocities the joint branch-and-bound proves passivity on a domain;
    #: above it the smooth eigenvalue floor makes D PSD
    JOINT_MAX_N = 3
    #: boxes of the first, unrepaired proof attempt (before the probe set is built)
    FIRST_BOXES = 1000
    #: halvings of the blend zone on a side where counterexamples lie beyond the kept box
    BLEND_HALVINGS = 4
    #: smoothing width of the eigenvalue floor, relative to the largest s_y / s_x (the scale of
    #: the GP correction, damping units)
    PSD_DELTA = 1e-3
    #: training velocities at most used for the psd-clip's diagnostics
    DIAG_SAMPLES = 200

    def __init__(self, options):
        super().__init__(options)
        self.scale = 1.0            # correction scale (1; below 1 only in files of older fits)
        self.domain = None          # ((ilo, ihi), (olo, ohi)) model units
        self.leaves = None          # proven partition of the outer box, reused by recertify
        self.data_box = None
        self.blend_on = False       # the published correction is blended to the domain
        self.clip = False           # the smooth eigenvalue floor is applied to every answer

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
        """
        Return the domains to prove, in order.

        With a declared operating domain: its hull with the data box (the user says where the
        system operates: no margin beyond it), then the data box with the margin; else the data
        box with the margin. Each blends to the prior over ``blend_width`` of its range.
        """
        o = self.options
        out = []
        if o.operating_domain is not None:
            out.append(_make_domain(self._hull(self.data_box), 0.0, o.blend_width))
        out.append(_make_domain(self.data_box, o.domain_margin, o.blend_width))
        return out

    def _delta(self, post) -> float:
        """Smoothing width of the eigenvalue floor, damping units (kept per hyper-parameters)."""
        hp = post.hyper
        last = self.__dict__.get('_delta_of')
        if last is None or last[0] is not hp:
            last = self._delta_of = (hp, self.PSD_DELTA * float(np.max(hp.sy / hp.sx)))
        return last[1]

    # ---------------------------------------------------------------- life cycle
    def enforce(self, post, prove: bool = True):
        """
        Establish the certificate of a fit (module docstring).

        ``prove=False`` (``defer``): the cheap certificates only; up to ``JOINT_MAX_N``
        velocities the domain proof is left pending (stale: every answer projected) on the
        domain of the new data for ``recertify``.
        """
        t0 = time.perf_counter()
        self.data_box = _box_of(post.Qd)
        self.domain = self._candidate_domains()[0]
        self.scale, self.leaves, self.blend_on, self.clip = 1.0, None, False, False
        if not self._global(post, rkhs=True):
            if post.N > self.JOINT_MAX_N:
                self._clip_on(post, diagnostics=prove)
            elif prove:
                self._prove(post, self._candidate_domains(), reuse=False)
            else:
                self.cert = Certificate(False, float('nan'), 'projection', None, self.scale,
                                        {'note': 'proof pending: every answer is projected'},
                                        stale=True, guarantee='pointwise')
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)
        return post

    def defer(self, post):
        """Establish the cheap certificates only (``enforce(post, prove=False)``)."""
        return self.enforce(post, prove=False)

    def _global(self, post, rkhs: bool) -> bool:
        """Certificate (1); True when it holds (then nothing is blended or clipped)."""
        if not post.mean.psd_over_diagonal:
            return False            # the lemma needs diag(m_inf) under M (``gp.coupled``: none)
        m = norm_margin(post.mean.diag_inf(), self.scale * l1_bound(post, rkhs=rkhs))
        if m < 0:
            return False
        self.leaves, self.blend_on, self.clip = None, False, False
        self.cert = Certificate(True, float(m), 'a-posteriori-bound', None, self.scale,
                                guarantee='psd')
        return True

    def _clip_on(self, post, diagnostics: bool) -> None:
        """Certificate (3): the smooth eigenvalue floor on every answer (module docstring)."""
        self.leaves, self.blend_on, self.clip = None, False, True
        delta = self._delta(post)
        details = {'delta': delta}
        if diagnostics:
            Q = post.Qd
            if len(Q) > self.DIAG_SAMPLES:
                Q = Q[np.linspace(0, len(Q) - 1, self.DIAG_SAMPLES).round().astype(int)]
            D = post.damping(Q, np.full(len(Q), self.scale))
            Dp, touched = psd_clip(D, delta)
            change = np.abs(np.einsum('kij,kj->ki', Dp - D, Q)).max(axis=0)
            details.update(touched_fraction_of_samples=float(touched.mean()),
                           max_change_at_samples=change.tolist())
        self.cert = Certificate(True, 0.0, 'psd-clip', None, self.scale, details,
                                guarantee='psd')

    def after_update(self, post, Q_new):
        """
        Check the O(n) global bound.

        Else: above ``JOINT_MAX_N`` the eigenvalue floor (valid for any weights); up to it, grow
        the domain to the data and mark the certificate stale: the answers are then those of the
        ``projected`` mode (the posterior itself, every answer projected; no blend and no repair
        of the last proof, which were made for other weights) until ``recertify`` proves again.
        """
        t0 = time.perf_counter()
        if self._global(post, rkhs=False):
            pass
        elif post.N > self.JOINT_MAX_N:
            self._clip_on(post, diagnostics=False)
        else:
            (ilo, ihi), _ = self.domain
            Qd = post.Qd
            if not np.all((Qd >= ilo) & (Qd <= ihi)):
                # samples outside the verified box would only ever see the prior: grow it
                self.data_box = _box_of(Qd)
                self.domain = self._candidate_domains()[0]
                self.leaves = None
            if not self.cert.stale:
                self.cert = self.cert.made_stale()
            post.set_delta(None)
            return
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)

    def recertify(self, post) -> Certificate:
        """
        Re-prove a stale certificate.

        First the global bound, then branch-and-bound (with repairs) on the current domain,
        starting from the last proven partition.
        """
        if self.cert is None or not self.cert.stale:
            return self.cert
        t0 = time.perf_counter()
        if not self._global(post, rkhs=True):
            self._prove(post, [self.domain], reuse=True)
        self.cert = self.cert.with_details(seconds=time.perf_counter() - t0)
        return self.cert

    def reprove(self, post):
        """
        Prove as a fit does (``enforce``), unless the certificate holds now; returns ``post``.

        Every candidate domain of the current data from scratch, with local repairs: also a
        model whose last proof failed (on the data it had then) or was never made.
        """
        if self.cert is not None and self.cert.certified:
            return post
        return self.enforce(post, prove=True)

    def restore_certificate(self, post, saved):
        """
        Distrust a loaded certificate: re-derive it.

        The global bound and the eigenvalue floor are re-established at once; a domain proof is
        stale until ``recertify`` runs it again (answers projected meanwhile; the blend keeps the
        saved domain).
        """
        self.leaves = None
        if self._global(post, rkhs=True):
            return
        if post.N > self.JOINT_MAX_N:
            self._clip_on(post, diagnostics=False)
            return
        method = 'domain-bnb+blend' if self.blend_on else 'projection'
        dom = self.domain[0] if self.blend_on else None
        self.cert = Certificate(False, float('nan'), method, dom, self.scale,
                                {'note': 'loaded from a file: not proven yet'}, stale=True,
                                guarantee='pointwise')

    def _prove(self, post, domains, reuse: bool) -> None:
        """
        Certificate (2) on each domain in turn; if none holds, no certificate (projected).

        Each domain gets the local repairs; a failed domain leaves the fitted weights unchanged.
        """
        reason = ''
        for dom in domains:
            res, extra = self._prove_on(post, dom, self.leaves if reuse else None)
            if res.ok:
                (ilo, ihi), (olo, ohi) = dom = (dom[0], self._outer)
                self.domain, self.leaves, self.blend_on, self.clip = dom, res.leaves, True, False
                self.cert = Certificate(True, res.margin, 'domain-bnb+blend', (ilo, ihi),
                                        self.scale,
                                        {'boxes': res.boxes, 'bnb_seconds': res.seconds,
                                         'outer_box': [olo.tolist(), ohi.tolist()], **extra},
                                        guarantee='passive-on-domain')
                return
            reason = res.reason
        self.domain, self.leaves, self.blend_on, self.clip = domains[0], None, False, False
        self.cert = Certificate(False, -np.inf, 'projection', None, self.scale,
                                {'reason': f'no proof: {reason}; every answer is projected'},
                                guarantee='pointwise')

    def _prove_on(self, post, dom, leaves):
        """
        Repair counterexamples on ``dom`` locally, then prove by branch-and-bound; repeat.

        A proof with a small budget comes first (most fits need nothing else). Then a fixed probe
        set of the outer box (grid with its corners, uniform, near the data; its kernel rows built
        once) is checked before each proof. Each round adds its most negative
        powers and the verifier's last witness to the cutting planes, finds the least change of
        the weights that makes every cut's power at least 5 % of the prior's there
        (``repair.repair``) and runs the proof again. The cuts are on the *unblended* posterior,
        which is what the proof is about (the blend is a convex combination with the prior).
        Returns (``BoxResult``, record of the repair for the certificate); without a proof the
        weights are left as they were.
        """
        (ilo, ihi), (olo, ohi) = dom
        # most fits are proven at once: try that (small budget) before building the probe
        res = verify_box(correction_terms(post, self.scale), olo, ohi,
                         max_boxes=min(self.FIRST_BOXES, self.options.max_boxes), leaves=leaves)
        if res.ok:
            self._outer = (olo, ohi)
            return res, {}
        old = None if post.delta is None else post.delta.copy()
        Z = probe_points(post, olo, ohi, np.random.default_rng(0))
        w = np.full(len(Z), self.scale)
        probe = PowerProbe(post, Z, w)
        before = None
        cut_p0, cut_G = np.zeros(0), [np.zeros((0, post.n)) for _ in range(post.N)]
        witness, repairs, halvings = res.witness, 0, 0
        res = None
        for _ in range(self.REPAIR_ROUNDS + self.BLEND_HALVINGS + 1):
            P = probe.power(post.weights)
            P[np.any((Z < olo) | (Z > ohi), axis=1)] = np.inf     # outside the proof's box
            idx = most_negative(P, self.CUTS_PER_ROUND)
            bad = Z[idx] if witness is None else np.vstack([witness[None, :], Z[idx]])
            out_lo, out_hi = np.any(bad < ilo, axis=0), np.any(bad > ihi, axis=0)
            if (np.any(out_lo) or np.any(out_hi)) and halvings < self.BLEND_HALVINGS:
                # counterexamples in the blend zone, beyond the box the correction is kept on:
                # narrow the blend on those sides instead of changing the model inside
                olo = np.where(out_lo, ilo - 0.5 * (ilo - olo), olo)
                ohi = np.where(out_hi, ihi + 0.5 * (ohi - ihi), ohi)
                halvings += 1
                witness = None
                res = None
                continue
            if len(idx) or witness is not None:
                if repairs == self.REPAIR_ROUNDS:
                    break
                if before is None:
                    before = self._force_sample(post, Z, w)
                p0, G = probe.take(idx)
                if witness is not None:
                    pw, Gw = power_rows(post, witness[None, :], w[:1])
                    p0, G = np.r_[pw, p0], [np.vstack([a, b]) for a, b in zip(Gw, G)]
                cut_p0 = np.r_[cut_p0, p0]
                cut_G = [np.vstack([a, b]) for a, b in zip(cut_G, G)]
                delta, _ = repair(post, (cut_p0, cut_G), 0.05 * np.maximum(cut_p0, 0.0))
                post.set_delta(delta if post.delta is None else post.delta + delta)
                repairs += 1
            res = verify_box(correction_terms(post, self.scale), olo, ohi,
                             max_boxes=self.options.max_boxes,
                             leaves=leaves if repairs == halvings == 0 else None)
            if res.ok or res.witness is None:
                break
            witness = res.witness
        self._outer = (olo, ohi)
        if res is None or not res.ok:
            post.set_delta(old)
            reason = res.reason if res is not None else 'violations left after the repairs'
            return (res if res is not None else
                    BoxResult(False, -np.inf, None, 0, 0.0, reason=reason)), {}
        if before is None:
            return res, {}
        change = np.abs(self._force_sample(post, Z, w) - before).max(axis=0)
        return res, {'repaired_points': int(len(cut_p0)), 'repair_rounds': repairs,
                     'repair_max_change_in_domain': change.tolist()}

    @staticmethod
    def _force_sample(post, Z, w):
        """Return the posterior's force at (at most 1000 of) the probe velocities (the record)."""
        k = min(len(Z), 1000)
        return post.predict(Z[:k], w[:k])[0]

    # ---------------------------------------------------------------- estimates
    @property
    def needs_damping(self) -> bool:
        """Tell whether ``finalize`` needs every answer's damping matrix (eigenvalue floor)."""
        return self.clip

    def weight(self, Q):
        """
        Return the correction weight.

        ``s * w(q)``: the correction scale times the C2 smootherstep blend that is 1 on the
        verified box and 0 outside the outer box (only while a domain certificate holds: a stale
        one guarantees nothing beyond the projection of each answer); None (1) otherwise.
        """
        if self.blend_on and self.domain is not None and not (self.cert is not None and
                                                              self.cert.stale):
            return self.scale * _blend(Q, self.domain)
        return None if self.scale == 1.0 else np.full(Q.shape[0], self.scale)

    def finalize(self, post, Q, tau, D):
        """
        Apply the eigenvalue floor (``psd-clip``), then the projection.

        The projection is the guarantee while nothing is proven (stale or failed) and a
        rounding-level safeguard otherwise (it moves an estimate by a few ulps at most).
        """
        if self.clip:
            if D is None:
                raise ValueError('certified (psd-clip): finalize needs the damping matrix')
            D, _ = psd_clip(D, self._delta(post))
            tau = np.einsum('kij,kj->ki', D, Q)
            return self._project(Q, tau, D, DQ=tau)
        return self._project(Q, tau, D)

    # ---------------------------------------------------------------- persistence
    def state(self):
        (ilo, ihi), (olo, ohi) = self.domain
        arrays = {'dom_ilo': ilo, 'dom_ihi': ihi, 'dom_olo': olo, 'dom_ohi': ohi}
        if self.leaves is not None:
            arrays['leaves_lo'], arrays['leaves_hi'] = self.leaves
        return {'scale': self.scale, 'blend': self.blend_on}, arrays

    def load_state(self, meta, arrays, post):
        N = post.N
        for k in ('dom_ilo', 'dom_ihi', 'dom_olo', 'dom_ohi'):
            if k not in arrays or arrays[k].shape != (N,):
                raise ValueError(f'certified model: {k} missing or not of shape ({N},)')
        self.scale = float(meta['scale'])
        if not 0.0 <= self.scale <= 1.0:
            raise ValueError(f'certified model: correction scale {self.scale} not in [0, 1]')
        self.blend_on = bool(meta.get('blend', True))
        self.domain = ((arrays['dom_ilo'], arrays['dom_ihi']),
                       (arrays['dom_olo'], arrays['dom_ohi']))
        lv: Optional[tuple] = None
        if 'leaves_lo' in arrays:
            lv = (arrays['leaves_lo'], arrays['leaves_hi'])
            if lv[0].ndim != 2 or lv[0].shape != lv[1].shape or lv[0].shape[1] != N:
                raise ValueError('certified model: malformed proof partition')
        self.leaves = lv
        self.data_box = _box_of(post.Qd)

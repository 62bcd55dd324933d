"""
The message path's predictor: a snapshot's mean answers in one lean pass (no rclpy).

A model answers a few velocities through ``predict_with_damping``: the element kernels of every
(query, training point, element) triple by one ``exp`` each, then per-call bookkeeping (element
rows and columns, basis values times weights). For a 7-joint Full-D-GP at buffer 200 that is
9,800 ``exp`` per answer, most of them of arguments so negative that numpy takes its slow
underflow path, and it was most of the node's own CPU per message at 1 kHz.

An :class:`AnswerPlan` is built once per snapshot (what it caches depends only on the training
inputs, the weights and the hyper-parameters, which a fit or an update replaces and never writes
into) and computes the same mean:

* the scaled squared distances of the queries to every training point, for every element, in one
  product (float64, exact differences as ``kernels.se_ard`` does for a few queries);
* ``exp`` of every exponent clamped at ``EXP_FLOOR`` (out of numpy's slow underflow path), the
  ones below it zeroed (the kernel there is < 1e-260: it adds nothing a float64 answer can
  hold), summed per element;
* the prior, the correction weight ``w(q)`` and the passivity policy's ``finalize`` (projection,
  eigenvalue floor) are the model's own, called as the model calls them, in float64: an answer is
  exactly as passive as the model's.

A plan checks itself against the model (``predict_with_damping`` at a few training velocities)
when the kind of model, prior or policy is new and every ``VERIFY_EVERY`` builds; a plan that
disagrees is not used (the model answers) and the disagreement is counted (``mismatches``), so a
change of the model's formulas elsewhere turns the lean pass off instead of changing answers.
The posterior variance is not planned: answers that want it take the model's path.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dgp_ros.gp.means import PriorMean

__all__ = ['AnswerPlan', 'PlanCache', 'EXP_FLOOR']

#: exponents below this contribute nothing (exp < 1e-260); exp() of them is the slow path
EXP_FLOOR = -600.0
#: queries per pass (bounds the (k, n, E) exponent array: 16 x 500 x 49 x 8 B = 3 MB)
CHUNK = 16


class AnswerPlan:
    """The mean of one model at a few velocities, precomputed (module docstring)."""

    def __init__(self, model):
        p = model.posterior_
        s, hp = p.structure, p.hyper
        self.model, self.post, self.policy = model, p, model.policy_
        self.key = (p, p.X, p.weights, hp)
        self.kind, self.N, self.E = s.kind, s.N, s.E
        self.has_damping = s.has_damping
        # only the elements switched on (``gp.select`` leaves an arm's outputs one element or
        # none of the 49): the others contribute nothing and cost an exponent each
        on = np.flatnonzero(np.exp(np.asarray(hp.log_sf2, float)) > 0.0)
        self.rows = np.array([s.elems[e][0] for e in on], dtype=np.intp)
        self.cols = np.array([0 if s.elems[e][1] is None else s.elems[e][1] for e in on],
                             dtype=np.intp)
        ard = np.array([s.elems[e][1] is None for e in on], dtype=bool)
        sf2 = np.exp(np.asarray(hp.log_sf2, float))[on]
        phi = np.where(ard[None, :], 1.0, p.X[:, self.cols])                  # (n, E on)
        V = (phi * p.weights[:, self.rows]).T                                 # (E on, n)
        self.V = np.ascontiguousarray((V * sf2[:, None]).T)                  # (n, E on)
        self.W = np.ascontiguousarray(-0.5 * np.exp(-2.0 * np.asarray(hp.log_ls, float)[on]).T)
        self.X = p.X
        self.sx, self.sy = np.asarray(hp.sx, float), np.asarray(hp.sy, float)
        self.dscale = self.sy[:, None] / self.sx[None, :]
        self.mean = p.mean
        # the generic force (diag(m_d) qd) is computed from the diagonal once when D is built
        self.force_is_diag = type(self.mean).force is PriorMean.force
        # a full model's elements in row-major order: the element weights are G itself
        N = self.N
        self.grid = len(on) == N * N and np.array_equal(self.rows, np.repeat(np.arange(N), N)) \
            and np.array_equal(self.cols, np.tile(np.arange(N), N))

    def current(self, model) -> bool:
        """Tell whether the plan still describes ``model`` (nothing it caches was replaced)."""
        p = model.posterior_
        k = self.key
        return model is self.model and p is k[0] and p.X is k[1] and p.weights is k[2] and \
            p.hyper is k[3] and model.policy_ is self.policy

    def signature(self) -> tuple:
        """Return what decides the formulas (a plan with a new one is verified)."""
        return (type(self.model), type(self.policy), type(self.mean), self.kind, self.E,
                self.rows.size)

    def _weights(self, X: np.ndarray) -> np.ndarray:
        """Element weights G (k, N, N) at standardized queries X (k, N): ``_element_weights``."""
        k = X.shape[0]
        if not self.rows.size:
            return np.zeros((k, self.N, self.N))
        d = X[:, None, :] - self.X[None, :, :]                      # (k, n, N)
        d *= d
        A = d @ self.W                                              # (k, n, E) exponents
        # dense: on a 7-joint arm 92 % of the exponents are above the floor, and one exp over
        # all of them (clamped out of the slow underflow path, the rest zeroed) took half the
        # time of gathering the few that matter
        keep = A > EXP_FLOOR
        np.maximum(A, EXP_FLOOR, out=A)
        np.exp(A, out=A)
        A *= keep
        A *= self.V                                                  # (n, E), each query
        Gf = A.sum(axis=1)                                          # (k, E)
        if self.grid:
            return Gf.reshape(k, self.N, self.N)
        G = np.zeros((k, self.N, self.N))
        G[:, self.rows, self.cols] = Gf
        return G

    def answers(self, Q: np.ndarray, want_D: bool, prior_diag: Optional[np.ndarray] = None,
                prior_matrix: Optional[np.ndarray] = None):
        """
        Return (tau (k, N), D (k, N, N) or None) at velocities Q, as the model answers them.

        ``model.predict_with_damping(Q, False, want_D)`` up to rounding. ``prior_diag`` : (k, N)
        the diagonal prior's ``diag(Q)``, ``prior_matrix`` : (k, N, N) a non-diagonal prior's
        ``matrix(Q)``, where the caller has it already (the gate's blend needs it too), else
        computed here.
        """
        if Q.shape[0] > CHUNK:
            dg, pm = prior_diag, prior_matrix
            parts = [self.answers(Q[i:i + CHUNK], want_D,
                                  None if dg is None else dg[i:i + CHUNK],
                                  None if pm is None else pm[i:i + CHUNK])
                     for i in range(0, Q.shape[0], CHUNK)]
            D = None if parts[0][1] is None else np.concatenate([d for _, d in parts])
            return np.concatenate([t for t, _ in parts]), D
        pol = self.policy
        X = Q / self.sx
        G = self._weights(X)
        w = pol.weight(Q)
        need_D = self.has_damping and (want_D or pol.needs_damping)
        D = None
        if need_D:
            C = G * self.dscale
            D = C if w is None else w[:, None, None] * C
            if self.mean.is_diagonal:
                dg = self.mean.diag(Q) if prior_diag is None else prior_diag
                D.reshape(len(D), self.N * self.N)[:, ::self.N + 1] += dg     # the diagonal
            else:
                D = D + (self.mean.matrix(Q) if prior_matrix is None else prior_matrix)
        if D is not None and pol.needs_damping:
            tau = np.einsum('kij,kj->ki', D, Q)
        else:
            corr = G[:, :, 0] if self.kind == 'ard' else np.einsum('kmn,kn->km', G, X)
            if w is not None:
                corr *= w[:, None]
            if need_D and self.force_is_diag:
                prior = dg * Q
            elif prior_matrix is not None:      # the caller's matrix: its force, to rounding
                prior = np.einsum('kij,kj->ki', prior_matrix, Q)
            else:
                prior = self.mean.force(Q)
            tau = prior + corr * self.sy
        tau, D = pol.finalize(self.post, Q, tau, D)
        return tau, D if want_D else None

    def verify(self, Q: np.ndarray, rtol: float = 1e-9) -> bool:
        """Compare with ``model.predict_with_damping`` at Q (force and damping matrix)."""
        tau, D = self.answers(Q, self.has_damping)
        t_ref, _, D_ref = self.model.predict_with_damping(Q, False, self.has_damping)
        scale = max(float(np.abs(t_ref).max()), 1e-300)
        ok = np.allclose(tau, t_ref, rtol=rtol, atol=rtol * scale)
        if D is not None and D_ref is not None:
            ok = ok and np.allclose(D, D_ref, rtol=rtol,
                                    atol=rtol * max(float(np.abs(D_ref).max()), 1e-300))
        return bool(ok)


class PlanCache:
    """
    The plan of the snapshot being answered from (one at a time), built and checked on first use.

    ``prepare(model)`` builds and checks the plan of a model before it is answered from (a learner
    process's receiver thread calls it for every new snapshot, so that the message path only
    picks it up; a learner process sends the plan it built with the snapshot, ``build``, and the
    receiver only takes it); ``get(model)`` builds it itself when nothing was prepared. ``built``,
    ``verified`` and ``mismatches`` count plans; a plan that failed its check is not used for its
    model (the model answers).
    """

    VERIFY_EVERY = 50

    def __init__(self):
        self._plan: Optional[AnswerPlan] = None
        self._ok = False
        self._verified_sig = None
        self._ready = None                  # (plan, ok) prepared for the next model
        self.built = self.verified = self.mismatches = 0
        self.last_error = ''

    def prepare(self, model, built: Optional[tuple] = None) -> None:
        """
        Build and check the plan of ``model`` now (another thread), for ``get`` to pick up.

        ``built``: (plan, usable) as ``build`` returned it where the model was made (a learner
        process, in the snapshot): taken as it is when it describes ``model``.
        """
        if model is None:
            return
        plan = self._plan
        if plan is not None and plan.current(model):
            return
        if built is not None and built[0] is not None and built[0].current(model):
            self._ready = built
            if not built[1]:
                self.mismatches += 1            # checked there, and it disagreed
            return
        self._ready = self.build(model)

    def get(self, model) -> Optional[AnswerPlan]:
        """Return the plan of ``model`` (None: answer through the model)."""
        plan = self._plan
        if plan is not None and plan.current(model):
            return plan if self._ok else None
        ready = self._ready
        if ready is not None and ready[0] is not None and ready[0].current(model):
            self._plan, self._ok = ready
            return ready[0] if ready[1] else None
        plan, ok = self.build(model)
        self._plan, self._ok = plan, ok
        return plan if ok else None

    def build(self, model) -> tuple:
        """Return (plan or None, usable) for ``model``, checked as the module docstring says."""
        try:
            plan = AnswerPlan(model)
        except Exception as exc:      # noqa: BLE001 - a model without the pieces: its own path
            self.last_error = f'{type(exc).__name__}: {exc}'
            return None, False
        self.built += 1
        ok = True
        if plan.signature() != self._verified_sig or self.built % self.VERIFY_EVERY == 1:
            ok = self._check(plan)
        return plan, ok

    def _check(self, plan: AnswerPlan) -> bool:
        Qd = getattr(plan.post, 'Qd', None)
        if Qd is None or not len(Qd):
            return True
        idx = np.unique(np.linspace(0, len(Qd) - 1, 3).round().astype(int))
        Q = np.vstack([Qd[idx], -Qd[idx[:1]]])
        try:
            ok = plan.verify(Q)
        except Exception as exc:      # noqa: BLE001 - counted as a mismatch
            self.last_error = f'{type(exc).__name__}: {exc}'
            ok = False
        self.verified += 1
        if ok:
            self._verified_sig = plan.signature()
        else:
            self.mismatches += 1
            self._verified_sig = None
        return ok

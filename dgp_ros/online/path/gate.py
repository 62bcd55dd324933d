"""
The output gate: every answer of the message path is computed and checked here (no rclpy).

:func:`answer` predicts at k velocities from a learner snapshot (one vectorized call) and checks
each answer: non-finite or non-passive estimates (beyond rounding) are replaced by the passive
prior, and an estimate larger than what was learned is clipped to it joint by joint
(``BOUND_FACTOR`` x the largest learned force per joint, or the prior's own force where that is
larger), or scaled down as a whole where clipping would make the computed ``qd . tau_hat``
negative or leave it within rounding of 0 (a scaling by a power of two is exact: the power keeps
its sign however it is summed); each case is counted in the message path's ``Health``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, List, Optional

import numpy as np

from dgp_ros.gp import passive_tolerance

from dgp_ros.gp.blend import prior_answer

from ..learner.grounds import blend
from ..learner.plan import PlanCache
from ..learner.snapshot import Snapshot

__all__ = ['answer', 'Estimate', 'BOUND_FACTOR', 'RESIDUAL_FACTOR']

#: answers are bounded by this factor times the largest force learned per joint
BOUND_FACTOR = 1.5
#: and, where known, by this factor times the largest residual learned (before corrections)
RESIDUAL_FACTOR = 1.8


@dataclass
class Estimate:
    """
    The estimate answering one measurement (model units; N joints).

    qd, tau : (N,) the measured velocity and effort; tau_hat : (N,) the damping force estimate at
    qd; stddev : (N,) its posterior standard deviation (NaN when not computed); D : (N, N)
    damping matrix (None for the ARD baseline or when not computed); power : ``qd^T tau_hat``;
    measured_power : ``qd^T tau``; source : 'model' | 'prior' | 'fallback'; added : the sample
    was offered for learning (with inverse dynamics its residual is learned once the filter's
    window is complete); processing_time_s : wall time spent; residuals : friction residual
    samples (``dynamics.ResidualSample``) the learner completed since the last answer (each
    trails its message by the filter's half window), which is what the model learns;
    confidence : (N,) how much of tau_hat a controller may use, in [0, 1] (``grounds``: its
    one-step-ahead gain; 0 before the model has earned any, and where the answer is the
    fallback alone).
    """

    stamp_s: float
    names: List[str]
    qd: np.ndarray
    tau: np.ndarray
    tau_hat: np.ndarray
    stddev: np.ndarray
    D: Optional[np.ndarray]
    power: float
    measured_power: float
    source: str
    added: bool
    processing_time_s: float
    residuals: list = dataclasses.field(default_factory=list)
    confidence: Optional[np.ndarray] = None


def answer(snap: Optional[Snapshot], Q: np.ndarray, want_stddev: bool, want_damping: bool,
           passivity: str, health, note_error: Callable[[str], None],
           plans: Optional[PlanCache] = None):
    """
    Answer velocities Q (k, N) from ``snap`` through the gate (module docstring).

    Returns (tau_hat (k, N), std (k, N), D (k, N, N) or None, source (k,) of 'model' |
    'prior' | 'fallback', confidence (k, N)); ``std`` is NaN where not wanted, ``D`` None where
    not wanted. A model's answers are blended toward the fallback by the snapshot's gains
    (``grounds.blend``); ``confidence`` is the snapshot's confidence of the blended answer (0
    where the answer is the fallback alone).
    ``health`` counts what the gate did; ``note_error`` records a failed prediction. With
    ``plans``, answers without the variance come from the snapshot's ``plan.AnswerPlan`` (the
    same mean in one lean pass).
    """
    k, N = Q.shape
    source = np.array(['prior'] * k, dtype=object)
    conf = np.zeros((k, N))
    tau = std = D = None
    if snap is not None and snap.model is not None:
        w = snap.model_weight
        mix = w is not None and snap.prior is not None and not bool(np.all(w >= 1.0))
        per_joint = mix and snap.per_joint
        try:
            plan = None if want_stddev or plans is None else plans.get(snap.model)
            # the blend's prior is the plan's mean (the learner's): its diagonal, or the matrix
            # of a diagonal-plus-PSD one (the congruence blend), computed once
            dg = pm = None
            if mix and plan is not None and plan.mean is snap.prior:
                if snap.prior.is_diagonal:
                    dg = np.asarray(snap.prior.diag(Q), float)
                elif per_joint and snap.prior.psd_over_diagonal:
                    pm = np.asarray(snap.prior.matrix(Q), float)
            if plan is not None:
                (tau, D), var = plan.answers(Q, want_damping or per_joint, dg, pm), None
            else:
                tau, var, D = snap.model.predict_with_damping(Q, want_stddev,
                                                              want_damping or per_joint)
            std = (np.sqrt(np.maximum(var, 0.0)) if var is not None
                   else np.full((k, N), np.nan))
            source[:] = 'model'
            conf[:] = 1.0 if snap.confidence is None else snap.confidence
            if mix:
                tau, D = blend(Q, tau, D, snap.prior, w, snap.prior_gain, per_joint, dg, pm)
                if not want_damping:
                    D = None
        except Exception as exc:        # noqa: BLE001 - the answer falls back to the prior
            health.nonfinite_outputs += k
            note_error(f'predict failed: {type(exc).__name__}: {exc}')
            source[:] = 'fallback'
            conf[:] = 0.0
            tau = None
    if tau is None:
        tau, std, D = _prior(snap, Q, want_damping, want_stddev)
    tau, std, D, source = _gate(snap, Q, tau, std, D, source, want_stddev, want_damping,
                                passivity, health)
    conf[source != 'model'] = 0.0
    return tau, std, D, source, conf


def _prior(snap: Optional[Snapshot], Q: np.ndarray, want_damping: bool,
           want_stddev: bool = True):
    """
    (tau, std, D) of the fallback: the passive prior times its gain (``blend.prior_answer``).

    Zero before any snapshot, and where the prior has earned no gain yet (``grounds``).
    """
    k, N = Q.shape
    if not want_stddev:
        std = np.full((k, N), np.nan)           # not computed: nobody subscribes
    if snap is None or snap.prior is None:
        if want_stddev:
            std = np.zeros((k, N))
        tau, D = np.zeros((k, N)), (np.zeros((k, N, N)) if want_damping else None)
    else:
        tau, D = prior_answer(snap.prior, Q, snap.prior_gain, want_damping)
        if want_stddev:
            std = np.broadcast_to(snap.prior_std, (k, N)).copy()
    if not np.isfinite(tau).all():
        bad = ~np.isfinite(tau).all(axis=1)
        tau[bad] = 0.0
        if D is not None:
            D[bad] = 0.0
    return tau, std, D


def _gate(snap, Q, tau, std, D, source, want_stddev, want_damping, passivity, health):
    """
    Check the answers (the one place this is done); see the module docstring.

    Returns (tau_hat, std, D, source) row by row: finite, passive beyond rounding (unless
    passivity is 'none') and bounded by what was learned.
    """
    h = health
    finite = np.isfinite(tau).all(axis=1)
    if want_stddev:
        finite &= np.isfinite(std).all(axis=1)
    if D is not None:
        finite &= np.isfinite(D).all(axis=(1, 2))
    bad = ~finite
    every = bool(finite.all())                  # the usual case: nothing to replace
    if not every:
        h.nonfinite_outputs += int(bad.sum())
    if passivity != 'none':
        safe = tau if every else np.where(finite[:, None], tau, 0.0)
        power = np.einsum('ij,ij->i', Q, safe)
        negative = power < -passive_tolerance(Q, safe)
        if not every:
            negative &= finite
        if negative.any():
            h.passivity_fallbacks += int(negative.sum())
            bad |= negative
            every = False
    if not every:
        pt, ps, pD = _prior(snap, Q[bad], want_damping)
        tau, std = tau.copy(), std.copy()
        tau[bad] = pt
        if want_stddev:
            std[bad] = np.where(np.isfinite(ps), ps, 0.0)
        if D is not None:
            D = D.copy()
            D[bad] = pD if pD is not None else 0.0
        source = source.copy()
        source[bad] = 'fallback'
    if snap is not None and snap.velocity_box is not None:
        tau, D = _bound(snap, Q, tau, D, health, passivity)
    return tau, std, D, source


def _power_in_order(Q: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Return ``q . tau`` per row (k,), summed joint after joint (as the C++ export does)."""
    p = Q[:, 0] * T[:, 0]
    for i in range(1, Q.shape[1]):
        p = p + Q[:, i] * T[:, i]
    return p


_LIMIT = (None, None)       # (the last snapshot, its learned limit): read and set as one


def _limit(snap: Snapshot) -> np.ndarray:
    """Return ``BOUND_FACTOR`` x the learned force, within ``RESIDUAL_FACTOR`` x the residual."""
    global _LIMIT
    last = _LIMIT
    if last[0] is snap:
        return last[1]
    limit = BOUND_FACTOR * np.maximum(snap.force_bound, 1e-12)
    if snap.residual_bound is not None:
        # targets a correction enlarged (up to CORRECTION_INFLATION x the residual) do not
        # carry the answers further than RESIDUAL_FACTOR x the largest residual learned
        limit = np.minimum(limit, RESIDUAL_FACTOR * np.maximum(snap.residual_bound, 1e-12))
    _LIMIT = (snap, limit)
    return limit


def _bound(snap: Snapshot, Q, tau, D, health, passivity: str):
    """
    Clip answers beyond ``BOUND_FACTOR`` x the learned force (or the prior's), joint by joint.

    The prior's force raises the limit as far as it goes inside the learned velocity box
    (``velocity_box``: the query clipped into it): a prior fitted to a few samples may
    extrapolate to many times the data (7.9x the residual's range on a Panda joint 3 s into a
    1 kHz stream), and an answer stays within what was learned until data reach that region.
    Also before the first fit: the answers are then the prior's. Where the learner knows the
    largest residual it learned (``residual_bound``), the prior raises the limit at most to
    ``BOUND_FACTOR`` x it, and no answer goes beyond ``RESIDUAL_FACTOR`` x it.
    """
    limit = _limit(snap)
    worst = (np.abs(tau) / limit).max(axis=1)
    big = worst > 1.0
    if snap.prior is not None and big.any():
        # the prior's own force raises the limit: evaluated only where the learned one is
        # exceeded (a larger limit never makes an answer within the learned one big)
        Qb = np.clip(Q[big], snap.velocity_box[0], snap.velocity_box[1])
        with np.errstate(invalid='ignore'):
            prior = np.abs(prior_answer(snap.prior, Qb)[0])
        prior = np.where(np.isfinite(prior), prior, 0.0)
        if snap.residual_bound is not None:
            # and never beyond what the data ever reached (a prior fitted to the first second
            # of a stream reached 2.1x the whole stream's residual inside the learned box)
            prior = np.minimum(prior, BOUND_FACTOR * snap.residual_bound)
        lb = np.maximum(limit, prior)
        worst[big] = (np.abs(tau[big]) / lb).max(axis=1)
        limit = np.broadcast_to(limit, tau.shape).copy()
        limit[big] = lb
    big = worst > 1.0
    if np.any(big):
        health.answers_bounded += int(big.sum())
        # each joint beyond its limit is clipped to it: one joint whose learned force is still
        # tiny (the A320's side force before the cross-wind builds up) must not scale down the
        # others; where that would leave the power below its rounding tolerance (a projected
        # answer lies on qd . tau = 0: clipped, it came out at -1e-16 relative), the whole
        # answer is scaled instead, by the power of two 2^-e at or below 1 / worst: exact, so
        # its power keeps its sign however it is summed
        tb = tau[big]
        s = np.minimum(1.0, np.broadcast_to(limit, tau.shape)[big] /
                       np.maximum(np.abs(tb), 1e-300))
        if passivity != 'none':
            Qb = Q[big]
            neg = _power_in_order(Qb, tb * s) < passive_tolerance(Qb, tb * s)
            s[neg] = np.ldexp(1.0, -np.frexp(worst[big][neg])[1])[:, None]
        tau = tau.copy()
        tau[big] = tb * s
        if D is not None:
            D = D.copy()
            D[big] *= s[:, :, None]
    return tau, D


def guarantee(snap: Optional[Snapshot], passivity: str) -> str:
    """
    Return the guarantee the answers from ``snap`` are served under (``gp.GUARANTEES`` key).

    The served model's certificate as it is (a record, read at no cost); before the first fit
    the prior's: ``diag(m_d)``, ``m_d >= 0``, or that plus a PSD part (a transmission): 'psd' (as
    the learner's status says); a prior with couplings (``gp.coupled``) is passive by its
    projection: 'pointwise'.
    """
    if passivity == 'none':
        return 'none'
    model = None if snap is None else snap.model
    if model is None:
        prior = None if snap is None else snap.prior
        return 'psd' if prior is None or prior.psd_over_diagonal else 'pointwise'
    try:
        return str(model.certificate().guarantee)
    except Exception:       # noqa: BLE001 - an unfitted model: its answers fall back to the prior
        return 'psd'

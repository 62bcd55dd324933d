"""
The message path for a batch of like messages, as arrays: validate, learn, answer (no rclpy).

A driver sends the same joint names and array lengths in every message, so a batch of its
messages is a few arrays: (k,) stamps and (k, n) positions, velocities, efforts
(``cdr.JointStateRun``). :func:`validate` decides, for all of them at once, what
``OnlineEstimator._validate`` and ``_accept`` decide one message at a time (the same reasons, in
the same order, counted alike); :class:`Answers` holds the answers of the accepted ones as
arrays, where ``process_batch`` makes an ``Estimate`` per message. The estimator
(``OnlineEstimator.process_arrays``) ties them together and falls back to the per-message path
for whatever this path does not cover (the first message, ``sync``).

What is learned and answered is exactly what ``process_batch`` learns and answers for the same
messages; only the Python objects per message are gone.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Optional

import numpy as np

from .answer import Estimate

__all__ = ['Answers', 'answers_of', 'ArrayPath', 'validate']


@dataclass
class Answers:
    """
    The answers to the accepted messages of a batch (model units; k answers, N joints).

    rows : (k,) indices of the accepted messages in the batch; names : the estimator's joint
    names (the answers' order); stamp_s : (k,); qd, tau : (k, N) measured velocity and effort;
    q : (k, N) position or None (not used by the learner); tau_hat : (k, N) damping force
    estimates; stddev : (k, N) (NaN when not computed); D : (k, N, N) or None; power :
    (k,) ``qd . tau_hat``; measured_power : (k,) ``qd . tau``; source : (k,) 'model' | 'prior'
    | 'fallback'; processing_time_s : wall time of the batch; residuals : friction residual
    samples the learner completed since the last answer (``Estimate.residuals``); confidence :
    (k, N) how much of each answer a controller may use (``Estimate.confidence``), or None.
    """

    rows: np.ndarray
    names: tuple
    stamp_s: np.ndarray
    qd: np.ndarray
    tau: np.ndarray
    q: Optional[np.ndarray]
    tau_hat: np.ndarray
    stddev: np.ndarray
    D: Optional[np.ndarray]
    power: np.ndarray
    measured_power: np.ndarray
    source: np.ndarray
    processing_time_s: float
    residuals: list = field(default_factory=list)
    confidence: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.rows)


def answers_of(estimates, names: tuple = ()) -> Answers:
    """
    Return ``process_batch``'s estimates (None: rejected) as one ``Answers``.

    ``names``: the messages' own names, for answers that carry none (unnamed joints).
    """
    rows = [i for i, e in enumerate(estimates) if e is not None]
    got = [estimates[i] for i in rows]
    if not got:
        e = np.zeros((0, 0))
        return Answers(np.zeros(0, dtype=np.intp), tuple(names), np.zeros(0), e, e, None, e, e,
                       None, np.zeros(0), np.zeros(0), np.zeros(0, dtype=object), 0.0, [])
    D = None if any(e.D is None for e in got) else np.array([e.D for e in got])
    source = np.empty(len(got), dtype=object)
    source[:] = [e.source for e in got]
    conf = None if any(e.confidence is None for e in got) else \
        np.array([e.confidence for e in got])
    return Answers(np.array(rows, dtype=np.intp), tuple(got[-1].names or names),
                   np.array([e.stamp_s for e in got]), np.array([e.qd for e in got]),
                   np.array([e.tau for e in got]), None, np.array([e.tau_hat for e in got]),
                   np.array([e.stddev for e in got]), D, np.array([e.power for e in got]),
                   np.array([e.measured_power for e in got]), source,
                   got[-1].processing_time_s, [r for e in got for r in e.residuals], conf)


def validate(est, sec: np.ndarray, nsec: np.ndarray, names: tuple, velocity: np.ndarray,
             effort: np.ndarray, position: Optional[np.ndarray]):
    """
    Validate k like messages for ``est`` (an ``OnlineEstimator`` that has seen its joints).

    ``names`` (n,) non-empty, ``velocity`` and ``effort`` (k, n), ``position`` (k, n) or None.
    Returns (reasons (k,) of '' (accepted) or the rejection reason, or None when every message
    is accepted; stamps (k,) [s]; the accepted rows' (qd, tau, q) in the estimator's joint
    order); counts nothing (the caller does, in message order). The stamp is
    ``sec + 1e-9 * nanosec`` as ``stamp_seconds`` computes it (the same float).
    """
    k = len(sec)
    stamps = sec.astype(np.float64)
    stamps += 1e-9 * nsec.astype(np.float64)
    reason = _content(est, names, position)
    if isinstance(reason, str):
        return np.full(k, reason, dtype=object), stamps, None
    idx = reason
    if idx is not None:             # (take: rows stay contiguous, as the message path's)
        velocity, effort = velocity.take(idx, axis=1), effort.take(idx, axis=1)
    p = None
    if est._learner.needs_position:
        p = position if idx is None else position.take(idx, axis=1)
    cfg = est.config
    # the usual case, for the whole batch at once: every value finite and in range (the largest
    # magnitude is NaN if any is, and NaN compares False), every stamp after the epoch
    if np.abs(velocity).max() <= cfg.max_abs_velocity and \
            np.abs(effort).max() <= cfg.max_abs_effort and sec.min() >= 0 and \
            (p is None or np.isfinite(p).all()):
        return None, stamps, (velocity, effort, p)
    fine = (np.abs(velocity) <= cfg.max_abs_velocity).all(axis=1) & \
        (np.abs(effort) <= cfg.max_abs_effort).all(axis=1)
    if p is not None:
        fine &= np.isfinite(p).all(axis=1)
    finite = np.isfinite(velocity).all(axis=1) & np.isfinite(effort).all(axis=1)
    if p is not None:
        finite &= np.isfinite(p).all(axis=1)
    reasons = np.full(k, '', dtype=object)
    reasons[~finite] = 'non_finite'
    reasons[finite & ~fine] = 'out_of_range'
    bad_stamp = ~(np.isfinite(stamps) & (stamps >= 0.0))
    reasons[(reasons == '') & bad_stamp] = 'bad_stamp'
    ok = reasons == ''
    return reasons, stamps, (velocity[ok], effort[ok], None if p is None else p[ok])


def _content(est, names: tuple, position):
    """Return the reason every message is rejected for, or the joint order (None: as is)."""
    cached = est._order
    known = cached is not None and cached[0] == names       # (their names had no duplicate)
    if not known and len(set(names)) != len(names):
        return 'duplicate_name'
    if est._learner.needs_position and position is None:
        return 'missing_position'
    if known:
        idx = cached[1]
    else:
        pos = {n: i for i, n in enumerate(names)}
        try:
            idx = np.array([pos[n] for n in est._names], dtype=np.intp)
        except KeyError:
            return 'missing_joint'
        est._order = (names, idx)
    if idx.size != est._N:
        return 'dimension_mismatch'
    cached = est._order
    if len(cached) < 3:             # None: the messages' order is the estimator's (as they are)
        same = idx.size == len(names) and bool((idx == np.arange(idx.size)).all())
        cached = est._order = cached[:2] + (None if same else idx,)
    return cached[2]


class ArrayPath:
    """
    ``OnlineEstimator.process_arrays`` (a mixin of the estimator: it uses its state).

    Learning times, the hand-over to the learner and the health counters of a batch at once.
    """

    def process_arrays(self, sec: np.ndarray, nsec: np.ndarray, names: tuple,
                       velocity: np.ndarray, effort: np.ndarray,
                       position: Optional[np.ndarray] = None) -> Optional[Answers]:
        """
        ``process_batch`` for k messages with the same names and array lengths, as arrays.

        sec, nsec : (k,) integer stamps (``header.stamp``); names : (n,) the messages' joint
        names; velocity, effort : (k, n); position : (k, n) or None (the messages have none).
        Returns the answers of the accepted messages (their ``rows``); None when the batch
        must take the per-message path (nothing was counted or learned then): ``sync`` (one
        answer per model), before the first accepted message (the joints are not known yet),
        messages without names or with arrays of other lengths.
        """
        t0 = time.perf_counter()
        n = len(names)
        if self.config.refit_mode == 'sync' or self._N is None or self._names is None or \
                not n or velocity.shape[1] != n or effort.shape[1] != n or \
                (position is not None and position.shape[1] != n):
            return None
        with self._lock:
            reasons, stamps, acc = validate(self, sec, nsec, names, velocity, effort, position)
            if reasons is None:                 # every message accepted (the usual case)
                ok = None
                rows = np.arange(len(stamps))
            else:
                ok = reasons == ''
                rows = np.flatnonzero(ok)
                stamps = stamps[ok]
            self._count(reasons, stamps)
            qd, tau, q = acc if acc is not None else (np.zeros((0, self._N)),) * 2 + (None,)
            if not rows.size:
                e = np.zeros((0, self._N))
                return Answers(rows, tuple(self._names), stamps[:0], e, e, None, e, e, None,
                               np.zeros(0), np.zeros(0), np.zeros(0, dtype=object),
                               time.perf_counter() - t0, [])
            pred = self._estimate(self._learner.snapshot(self._want_stddev), qd)
            self._learn_rows(self._learning_times(stamps), qd, tau, q)
            return self._answers(rows, stamps, qd, tau, q, pred, t0)

    def _count(self, reasons, stamps) -> None:
        """
        Count the batch in ``health`` as ``_accept`` counts each message, in order.

        reasons : None (every message accepted) or (k,) ('' accepted); stamps : the accepted
        messages' stamps.
        """
        h = self.health
        if reasons is None:
            k = len(stamps)
            h.messages_received += k
            h.messages_accepted += k
            h.recent_ok.extend([True] * k)
        else:
            h.messages_received += len(reasons)
            for r in reasons:
                if r:
                    h.reject(r)
                else:
                    h.accept()
        note = h.gaps.note
        for s in stamps.tolist():
            note(s)

    def _learning_times(self, stamps: np.ndarray) -> np.ndarray:
        """``_learning_time`` of each stamp, in order (at once while the stamps advance)."""
        last = self._raw_last_stamp
        if self._arrival_t0 is None and last is not None and stamps[0] > last and \
                (stamps.size == 1 or bool((np.diff(stamps) > 0).all())):
            self._raw_last_stamp = self._last_t = float(stamps[-1])
            self._same_stamps = 0
            return stamps
        return np.array([self._learning_time(s) for s in stamps.tolist()])

    def _learn_rows(self, t: np.ndarray, qd, tau, q) -> None:
        """Hand the accepted rows to the learner (a learner process: in one push)."""
        many = getattr(self._learner, 'learn_many', None)
        if many is not None:
            many(t, qd, tau, q)
            return
        for j in range(len(t)):
            self._learner.learn(float(t[j]), qd[j], tau[j], None if q is None else q[j])

    def _answers(self, rows, stamps, qd, tau, q, pred, t0) -> Answers:
        tau_hat, std, D, source, conf = pred
        # each as process_batch computes it (the same floats): one dot product per answer
        power = np.array([a @ b for a, b in zip(qd, tau_hat)])
        if self.config.passivity != 'none':
            np.maximum(power, 0.0, out=power)      # rounding only (the gate replaced the others)
        measured = np.array([a @ b for a, b in zip(qd, tau)])
        residuals = self._learner.take_residuals()
        dt = time.perf_counter() - t0
        a = Answers(rows, tuple(self._names), stamps, qd, tau, q, tau_hat, std, D, power,
                    measured, source, dt, residuals, conf)
        self.health.latencies.extend([dt] * len(rows))
        self._last_est = a
        return a

    @staticmethod
    def last_estimate(last) -> Optional[Estimate]:
        """Return the newest answer as an ``Estimate`` (``_last_est`` may hold Answers)."""
        if not isinstance(last, Answers):
            return last
        j = len(last) - 1
        return Estimate(float(last.stamp_s[j]), list(last.names), last.qd[j], last.tau[j],
                        last.tau_hat[j], last.stddev[j], None if last.D is None else last.D[j],
                        float(last.power[j]), float(last.measured_power[j]), last.source[j],
                        True, last.processing_time_s, [],
                        None if last.confidence is None else last.confidence[j])

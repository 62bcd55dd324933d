"""
Health of the online estimator: counters, recent history, and the status they imply.

``Health`` only records; ``status`` turns the record (plus the estimator's state) into a level
and a message: each condition a user should act on is a WARN (or an ERROR) with its reason.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np

__all__ = ['Health', 'LearnerHealth', 'GapCounter', 'REJECT_REASONS', 'OK', 'WARN', 'ERROR']

# Reasons a message can be rejected for (one counter each).
# ``undecodable``: bytes that are not a JointState (the node's raw subscription; a bag's reader);
# ``bad_text``: a frame_id or joint name that is not UTF-8 text.
REJECT_REASONS = ('empty', 'length_mismatch', 'bad_names', 'duplicate_name', 'missing_joint',
                  'dimension_mismatch', 'too_many_joints', 'non_finite', 'out_of_range',
                  'bad_stamp', 'missing_position', 'undecodable', 'bad_text')
# Status levels (the values of diagnostic_msgs/DiagnosticStatus OK/WARN/ERROR).
OK, WARN, ERROR = 0, 1, 2

#: recent-message window for the "many rejected samples" status, and its threshold
REJECT_WINDOW = 200
REJECT_WARN_FRACTION = 0.1
#: consecutive failed refits that make the status ERROR (one failure is a WARN)
REFIT_FAIL_ERROR = 3
#: missing messages (estimated from stamp gaps) above this fraction of the recent stream: WARN
MISSING_WARN_FRACTION = 0.01
#: refits the failure rate is judged over, and the rate that makes a WARN (never 'ok' while a
#: third of them fail: a UR10 whose 4 refits of 9 failed said 'ok')
RECENT_REFITS, REFIT_FAIL_WARN_FRACTION = 9, 1.0 / 3.0


class GapCounter:
    """
    Messages missing from a regular stream, estimated from the gaps between their stamps.

    A best-effort subscription drops what does not fit its queue without telling anyone (the
    DDS "message lost" event does not fire for a full history), and a recorder can drop too. The
    nominal period is the median of the last 101 stamp gaps (recomputed every 32 messages, so a
    new publishing rate is learned within about 100 messages and drops up to half of the stream
    do not move it); a gap longer than 1.5 periods counts the ``round(gap / period) - 1``
    messages that should have filled it. Longer silences (over ``max(1 s, 20 periods)``: the
    publisher paused, a bag loops) and stamps that go back are not drops.
    """

    FACTOR = 1.5
    WINDOW = 1000          # recent received messages the fraction is taken over

    def __init__(self):
        self.missing = 0
        self._last: Optional[float] = None
        self._gaps: deque = deque(maxlen=101)
        self._period: Optional[float] = None
        self._n = 0
        self._recent: deque = deque(maxlen=self.WINDOW)     # missing before each message
        self._recent_sum = 0

    def note(self, stamp: float) -> None:
        """One received message's stamp (s)."""
        last, self._last = self._last, stamp
        k = 0
        if last is not None and stamp > last:
            gap = stamp - last
            p = self._period
            if p is not None and self.FACTOR * p < gap <= max(1.0, 20.0 * p):
                k = int(round(gap / p)) - 1
            self._gaps.append(gap)        # all of them: a new publishing rate is learned
            self._n += 1
            if len(self._gaps) >= 20 and (p is None or self._n % 32 == 0):
                self._period = float(np.median(self._gaps))
        self.missing += k
        if len(self._recent) == self._recent.maxlen:
            self._recent_sum -= self._recent[0]
        self._recent.append(k)
        self._recent_sum += k

    @property
    def recent_fraction(self) -> float:
        """Missing / (missing + received) over the recent window."""
        n = len(self._recent)
        return self._recent_sum / (n + self._recent_sum) if n else 0.0


@dataclass
class LearnerHealth:
    """Counters of the learner (``Learner.reset`` starts a new one)."""

    samples_added: int = 0
    samples_skipped: int = 0          # near-duplicates (novelty selection)
    samples_thinned: int = 0          # left out by a learner behind its stream (one in k kept)
    samples_rate_limited: int = 0
    samples_outliers: int = 0         # isolated far outliers not learned
    inverse_dynamics_errors: int = 0  # samples the inverse dynamics could not process
    samples_awaiting_model: int = 0   # not learned: the robot model (URDF) has not come yet
    samples_not_learned: int = 0      # not learned: learning is off (serve only)
    time_jumps_back: int = 0
    time_jumps_forward: int = 0
    refits_started: int = 0
    refits_ok: int = 0
    refits_failed: int = 0
    refits_rejected: int = 0          # candidates the sanity check refused
    novelty_refits: int = 0           # optimizing refits asked for by data in new territory
    recertifications: int = 0
    appends: int = 0                  # samples appended to the served model as they came
    absorbs: int = 0                  # rebases: refits on the buffer at fixed hyper-parameters
    absorbs_rejected: int = 0         # rebases that failed (non-finite): the samples wait
    last_absorb_error: str = ''
    proofs_failed: int = 0            # models served unproven (every answer projected)
    proofs_failed_in_a_row: int = 0   # re-proofs wait longer after each (Absorber._proof_gap)
    last_proof_error: str = ''
    proven_at: Optional[float] = None     # learning time of the last model proven (s)
    consecutive_refit_failures: int = 0
    last_refit_error: str = ''
    last_refit_stamp: Optional[float] = None
    last_refit_wall_time: Optional[float] = None
    last_refit_duration_s: Optional[float] = None
    last_fit_wall_s: float = float('nan')     # the last refit's fit: wall time (s) ...
    last_fit_cpu_s: float = float('nan')      # ... and its own computing time (s)
    last_refit_optimized: Optional[bool] = None
    refit_durations: deque = field(default_factory=lambda: deque(maxlen=1000))
    recent_refits: deque = field(default_factory=lambda: deque(maxlen=RECENT_REFITS))  # ok?
    structure: str = ''               # prior='auto': the chosen friction / offsets / correction
    structure_scores: dict = field(default_factory=dict)   # its best CV scores
    joint_elements: dict = field(default_factory=dict)     # the elements from every sample
    elements: str = ''                # elements='auto': each joint's elements of D (gp.select)
    elements_scores: dict = field(default_factory=dict)    # their CV errors per choice
    correction_basis: str = ''        # what the conservative correction is built from
    corrections_refused: int = 0      # corrections that would inflate the targets: not applied

    def proof_done(self, why_not: str, stamp: Optional[float] = None) -> None:
        """
        Count a proof attempt of a served model: ``why_not`` '' when it holds.

        stamp : the learning time of the newest sample the proven model held (s): the status
        says since when the served model was last proven.
        """
        if why_not:
            self.proofs_failed += 1
            self.proofs_failed_in_a_row += 1
        else:
            self.proofs_failed_in_a_row = 0
            if stamp is not None:
                self.proven_at = float(stamp)
        self.last_proof_error = why_not

    def refit_done(self, ok: bool, seconds: float, stamp, optimized: bool, error: str,
                   wall_time: float, fit_wall_s: float = float('nan'),
                   fit_cpu_s: float = float('nan')) -> None:
        """Record a refit: its outcome, and the fit's wall and computing time (s)."""
        self.last_refit_duration_s = seconds
        self.last_fit_wall_s, self.last_fit_cpu_s = fit_wall_s, fit_cpu_s
        self.refit_durations.append(seconds)
        self.last_refit_wall_time = wall_time
        self.last_refit_stamp = stamp
        self.last_refit_optimized = optimized
        self.recent_refits.append(bool(ok))
        if ok:
            self.refits_ok += 1
            self.consecutive_refit_failures = 0
            self.last_refit_error = ''
        else:
            self.refits_failed += 1
            self.consecutive_refit_failures += 1
            self.last_refit_error = error

    def counters(self) -> dict:
        return {
            'samples_added': self.samples_added, 'samples_skipped': self.samples_skipped,
            'samples_thinned': self.samples_thinned,
            'samples_rate_limited': self.samples_rate_limited,
            'samples_outliers': self.samples_outliers,
            'refits_started': self.refits_started, 'refits_ok': self.refits_ok,
            'refits_failed': self.refits_failed, 'refits_rejected': self.refits_rejected,
            'novelty_refits': self.novelty_refits,
            'consecutive_refit_failures': self.consecutive_refit_failures,
            'last_refit_error': self.last_refit_error,
            'last_refit_stamp': self.last_refit_stamp,
            'last_refit_wall_time': self.last_refit_wall_time,
            'last_refit_duration_s': self.last_refit_duration_s,
            'last_refit_optimized': self.last_refit_optimized,
            'inverse_dynamics_errors': self.inverse_dynamics_errors,
            'samples_awaiting_model': self.samples_awaiting_model,
            'samples_not_learned': self.samples_not_learned,
            'time_jumps_back': self.time_jumps_back, 'time_jumps_forward': self.time_jumps_forward,
            'recertifications': self.recertifications, 'appends': self.appends,
            'absorbs': self.absorbs, 'absorbs_rejected': self.absorbs_rejected,
            'last_absorb_error': self.last_absorb_error, 'proofs_failed': self.proofs_failed,
            'last_proof_error': self.last_proof_error, 'proven_at_s': self.proven_at,
            'refit_durations': list(self.refit_durations),
            'recent_refits': len(self.recent_refits),
            'recent_refits_failed': self.recent_refits.count(False),
        }


@dataclass
class Health:
    """Counters of the message path (``OnlineEstimator.reset`` starts a new one)."""

    rejected: Dict[str, int] = field(default_factory=lambda: {r: 0 for r in REJECT_REASONS})
    messages_received: int = 0
    messages_accepted: int = 0
    passivity_fallbacks: int = 0      # estimates replaced because their power was negative
    nonfinite_outputs: int = 0        # estimates replaced because they were not finite
    answers_bounded: int = 0          # estimates scaled down to the learned force range
    messages_lost: int = 0            # reported lost by the middleware (its message-lost event)
    #: answers by the guarantee of the certificate they were served under (``GUARANTEES`` keys)
    answers_by_guarantee: Dict[str, int] = field(default_factory=dict)
    #: where the messages come from: 'live' (a subscription) or 'bag' (a recorded log: a gap in
    #: its stamps is a hole in the data, no queue or network dropped anything)
    source: str = 'live'
    recent_ok: deque = field(default_factory=lambda: deque(maxlen=REJECT_WINDOW))
    latencies: deque = field(default_factory=lambda: deque(maxlen=1000))
    gaps: GapCounter = field(default_factory=GapCounter)   # messages missing from the stream
    _dropped_seen: int = 0            # the learner's samples_dropped at the last status

    def answered(self, guarantee: str, k: int) -> None:
        """Count ``k`` answers served under ``guarantee`` (a ``gp.GUARANTEES`` key)."""
        self.answers_by_guarantee[guarantee] = self.answers_by_guarantee.get(guarantee, 0) + k

    @property
    def certified_share(self) -> float:
        """
        Return the share of the answers served under a proven certificate (NaN before any).

        Proven: the guarantee 'psd' or 'passive-on-domain' (``gp.policy.GUARANTEES``), which
        the served model's certificate gave when the answer was computed; not 'pointwise' (a
        projection of each answer) nor 'none'. The prior's answers (before the first fit) count
        as 'psd': ``diag(m_d)`` with ``m_d >= 0`` is positive semi-definite by construction.
        """
        a = self.answers_by_guarantee
        total = sum(a.values())
        if not total:
            return float('nan')
        return (a.get('psd', 0) + a.get('passive-on-domain', 0)) / total

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        self.recent_ok.append(False)

    def accept(self) -> None:
        self.messages_accepted += 1
        self.recent_ok.append(True)

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    @property
    def recent_rejected_fraction(self) -> float:
        r = self.recent_ok
        return (r.count(False) / len(r)) if r else 0.0

    def count_batch(self, reasons, stamps) -> None:
        """
        Count a batch of messages as ``OnlineEstimator._accept`` counts each, in order.

        reasons : None (every message accepted) or (k,) ('' accepted); stamps : the accepted
        messages' stamps.
        """
        h = self
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

    def counters(self) -> dict:
        lat = np.array(self.latencies) if self.latencies else None
        return {
            'messages_received': self.messages_received,
            'messages_accepted': self.messages_accepted,
            'messages_missing': self.gaps.missing,
            'recent_missing_fraction': round(self.gaps.recent_fraction, 6),
            'rejected': dict(self.rejected), 'rejected_total': self.rejected_total,
            'recent_rejected_fraction': self.recent_rejected_fraction,
            'passivity_fallbacks': self.passivity_fallbacks,
            'nonfinite_outputs': self.nonfinite_outputs,
            'answers_bounded': self.answers_bounded,
            'messages_lost': self.messages_lost,
            'certified_share': round(self.certified_share, 6),
            'answers_by_guarantee': dict(self.answers_by_guarantee),
            'latency_median_s': float(np.median(lat)) if lat is not None else float('nan'),
            'latency_p99_s': float(np.percentile(lat, 99)) if lat is not None else float('nan'),
        }

    def status(self, learner: dict, state: dict) -> tuple:
        """
        Return the health status as (level, message).

        ``learner``: the learner's counters (``LearnerHealth.counters``); ``state`` (keys:
        trained, fill, min_samples, certifies, certified, stale, load_error, warnings).
        """
        reasons, level = [], OK
        if not state['trained']:
            if state['fill'] < state['min_samples']:
                reasons.append(f'not yet trained ({state["fill"]}/{state["min_samples"]} '
                               'samples)')
            elif learner.get('refits_failed') and state['certifies']:
                reasons.append('not certified: no certified model yet, publishing prior mean')
            else:
                reasons.append('not yet trained (first fit running)')
            level = WARN
        elif state.get('learning') == 'stopping':
            reasons.append('learning stopping: the model is being proven and saved')
        elif state['stale']:
            at = learner.get('proven_at_s')
            reasons.append('every answer passive (each projected onto qd . tau >= 0); the model '
                           + ('not proven passive yet' if at is None else
                              f'last proven passive on the visited velocities as learned at '
                              f'{at:.1f} s, the samples since not yet'))
        elif state['certifies'] and state['certified'] and learner.get('proven_at_s') is not None:
            reasons.append('every answer passive; the model proven passive on the visited '
                           f'velocities, as learned at {learner["proven_at_s"]:.1f} s')
        elif state['certifies'] and not state['certified']:
            why = learner.get('last_proof_error', '')
            reasons.append('not certified' + (f' ({why})' if why else '') +
                           ': every estimate projected onto qd^T tau >= 0' +
                           ('; re-proven after new samples' if state.get('learning', 'on') ==
                            'on' else ''))
            level = WARN
        if state.get('learning') == 'off':
            reasons.append(f'learning off: serving the frozen model (guarantee '
                           f'{learner.get("guarantee", "")})')
        if self.recent_rejected_fraction > REJECT_WARN_FRACTION:
            reasons.append(f'many rejected samples ({100 * self.recent_rejected_fraction:.0f}% '
                           'of recent)')
            level = max(level, WARN)
        if self.gaps.recent_fraction > MISSING_WARN_FRACTION:
            frac = f'{100 * self.gaps.recent_fraction:.1f}% of recent'
            if self.source == 'bag':
                reasons.append(f'gaps in the recorded stamps ({frac} expected messages '
                               'missing): the log itself has holes (the logger skipped samples)')
            elif self.messages_lost:
                reasons.append(f'messages missing from the stream ({frac}, from stamp gaps); '
                               f'the middleware reported {self.messages_lost} lost: the input '
                               'queue (queue_depth) overflowed or the network dropped them')
            else:
                reasons.append(f'gaps in the message stamps ({frac} expected messages '
                               'missing); the middleware reported none lost: the publisher '
                               'skipped them, or a network dropped them unseen')
            level = max(level, WARN)
        failures = learner.get('consecutive_refit_failures', 0)
        error = learner.get('last_refit_error', '')
        n, bad = learner.get('recent_refits', 0), learner.get('recent_refits_failed', 0)
        if failures and 'sanity check' in error:
            reasons.append(f'model rejected ({error}); the previous one serves')
            level = max(level, WARN)
        elif failures:
            reasons.append(f'refit failing ({failures} in a row: {error})')
            level = max(level, ERROR if failures >= REFIT_FAIL_ERROR else WARN)
        if n >= 3 and bad >= REFIT_FAIL_WARN_FRACTION * n and not failures:
            reasons.append(f'{bad} of the last {n} refits failed or were rejected (the model '
                           'serves from the others)')
            level = max(level, WARN)
        dropped = learner.get('samples_dropped') or 0
        if dropped > self._dropped_seen:
            reasons.append(f'the learner fell behind: {dropped - self._dropped_seen} samples '
                           f'dropped since the last report ({dropped} in all; its queue was '
                           'full): it gets too little CPU, and learns from fewer samples')
            level = max(level, WARN)
        self._dropped_seen = dropped
        if learner.get('last_absorb_error'):
            reasons.append(f'new samples not absorbed ({learner["last_absorb_error"]}); the '
                           'previous model serves')
            level = max(level, WARN)
        if state['load_error']:
            reasons.append('model file not used')
            level = max(level, WARN)
        for w in state.get('warnings', ()):
            reasons.append(w)
            level = max(level, WARN)
        return level, ('; '.join(reasons) if reasons else 'ok')

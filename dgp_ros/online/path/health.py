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

__all__ = ['Health', 'GapCounter', 'REJECT_REASONS', 'OK', 'WARN', 'ERROR']

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
#: the rate of failed refits (over the learner's last ``RECENT_REFITS``) that makes a WARN (never
#: 'ok' while a third of them fail: a UR10 whose 4 refits of 9 failed said 'ok')
REFIT_FAIL_WARN_FRACTION = 1.0 / 3.0


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

"""
Counters of the learner: what it learned, skipped and refitted (no rclpy).

Only records; the message path's ``Health.status`` (``online.path.health``) and the
learner's report (``online.learner.report``) turn them into a level and a message.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Optional

__all__ = ['LearnerHealth', 'RECENT_REFITS']

#: refits the failure rate is judged over (the status's WARN, ``online.path.health``)
RECENT_REFITS = 9


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
    proofs_failed_in_a_row: int = 0   # re-proofs wait longer after each (Refits.proof_gap)
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

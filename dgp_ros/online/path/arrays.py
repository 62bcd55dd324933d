"""
The answers to a batch of accepted messages, as arrays (no rclpy).

A driver sends the same joint names and array lengths in every message, so a batch of its
messages is a few arrays: (k,) stamps and (k, n) positions, velocities, efforts
(``cdr.JointStateRun``). :class:`Answers` holds the answers of the accepted ones as arrays. Every
entry point of the estimator answers through one step that makes them
(``OnlineEstimator._respond``): ``process_arrays`` (the node; the batch checked at once by
``intake.Intake.check_batch``) returns them, ``process_batch`` (``process``, ``dgp-replay``,
and the node for what the array path does not cover: the first message, ``sync``) checks
message by message (``Intake.check``) and gives each accepted message the ``Estimate`` of its
row. :func:`answers_of` turns such estimates back into one ``Answers`` (the node publishes
Answers), :func:`last_estimate` the newest answer into an ``Estimate`` (diagnostics).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .gate import Estimate

__all__ = ['Answers', 'answers_of', 'last_estimate']


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

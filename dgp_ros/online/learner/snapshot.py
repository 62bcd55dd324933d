"""
What the message path answers from: an immutable snapshot of the learner's state (no rclpy).

The learner publishes a :class:`Snapshot` whenever what it learned changes; the message path
swaps it in with one reference assignment and answers every message from the one it holds, so an
answer never waits for a fit, a proof or a rebuild. Across processes a snapshot is pickled: its
model is then a predict-only copy (``model.snapshot()``: training inputs, weights, scales, prior,
passivity state, and the Cholesky factors only when the variance is wanted).

:class:`Snapshots` is the learner's part that makes them (and keeps the last one: a snapshot is
asked for tens of times a second); :class:`SwapLog` is what installing them cost the node.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ['Snapshot', 'Snapshots', 'SwapLog']


@dataclass(frozen=True)
class Snapshot:
    """
    One immutable view of the learner (model units; N joints).

    version : the learner's version it was taken at (increasing within one learner run).
    model : the fitted model (a predict-only copy when ``frozen``), None before the first fit.
    prior : the passive prior mean fitted to the buffer (``means.PriorMean``): the answer before
        the first fit and the fallback of the output gate.
    prior_std : (N,) RMS of the buffer's residual after the prior (the fallback's stddev).
    force_bound : (N,) largest |force| learned per joint (bounds the answers, see the estimator).
    velocity_box : ((N,), (N,)) the smallest and largest velocity learned per joint, None before
        any sample: where the prior's own force may raise the answers' bound (``path.gate``).
    residual_bound : (N,) largest |residual| learned per joint, before any correction (None
        after a reload): how far the prior may raise that bound at most.
    learned_through : learning time of the newest sample the learner had seen (s), or None.
    model_weight, prior_gain, confidence : (N,) the model's weight in the blend, the prior's
        gain and the confidence of the blended answer, earned one step ahead (``grounds``), None
        before any sample.
    per_joint : the model's guarantee is ``psd``: the blend may weigh joints apart.
    frozen : a self-contained copy (another process); variance : the posterior variance is
        available.
    plan : (``plan.AnswerPlan`` or None, usable) of ``model``, built where the snapshot was
        taken (a learner process builds and checks it, so that the node only unpickles it), or
        None: the message path builds it.
    """

    version: int
    model: object
    prior: object
    prior_std: np.ndarray
    force_bound: np.ndarray
    learned_through: Optional[float]
    frozen: bool = False
    variance: bool = True
    velocity_box: Optional[tuple] = None
    residual_bound: Optional[np.ndarray] = None
    model_weight: Optional[np.ndarray] = None
    prior_gain: Optional[np.ndarray] = None
    confidence: Optional[np.ndarray] = None
    per_joint: bool = False
    plan: Optional[tuple] = None


class Snapshots:
    """
    A part of the learner: it makes the snapshots, and keeps the last one (under its lock).

    The parts a snapshot is taken of (the window, the prior, the gains, the served model) are
    passed in each ``take``, not kept. The last snapshot is handed out again while the served
    model's ``version`` is the same; gains that moved without a new model (a sample the buffer
    skips) travel in a copy of its fields (``Grounds.seq`` tells).
    """

    def __init__(self):
        self._last: Optional[Snapshot] = None
        self._gains = -1                  # the grounds' seq the last snapshot carries

    def forget(self) -> None:
        """Make the next snapshot anew (what it carries changed: gains, a residual bound)."""
        self._last = None

    def take(self, parts, N: Optional[int], learned_through: Optional[float],
             variance: bool = True, frozen: bool = False) -> Optional[Snapshot]:
        """
        Return what a prediction needs now (None before the first sample).

        parts : the learner's parts now (``parts.Parts``: settings, window, structure, grounds,
        served are read); N : the number of joints (None: not known yet); learned_through : the
        newest sample's learning time (s). variance : include what the posterior variance needs
        (the Cholesky factors). frozen : a self-contained copy for another process
        (``process.proxy``); else the snapshot refers to the live model (in-line use: the caller
        learns and answers in turn).
        """
        win, structure, grounds, served = parts.window, parts.structure, parts.grounds, \
            parts.served
        learning = parts.settings().learning
        if N is None or win.buffer is None:
            return None
        s = self._last
        if s is not None and s.version == served.version and \
                (s.frozen, s.variance) == (frozen, variance or not frozen):
            self._last = self._with_gains(s, grounds, learning)     # the gains earned since
            return self._last
        mean, std = structure.prior(win, N, parts.health)
        model = served.model
        if model is not None and model.posterior_.structure.has_damping:
            # a model answers with its own prior and bounds: the same after a reload
            mean, bound = model.mean_, np.abs(model.Y_train_).max(axis=0)
            Q = model.X_train_
        else:
            Q, T = win.rows_unordered()
            bound = np.abs(T).max(axis=0) if win.size else np.zeros(N)
        box = (Q.min(axis=0), Q.max(axis=0)) if len(Q) else None
        per_joint = model is not None and model.posterior_.structure.has_damping and \
            model.certificate().guarantee == 'psd'
        if model is not None and frozen:
            model = model.snapshot(variance=variance)
        self._last = self._with_gains(Snapshot(
            version=served.version, model=model, prior=mean, prior_std=std, force_bound=bound,
            velocity_box=box, residual_bound=structure.residual_bound,
            learned_through=learned_through, frozen=frozen, variance=variance or not frozen,
            per_joint=per_joint), grounds, learning)
        return self._last

    def _with_gains(self, snap: Snapshot, grounds, learning: bool) -> Snapshot:
        """
        Return ``snap`` carrying the gains of ``grounds`` as they are now.

        The last snapshot is returned as it is while no sample moved the gains; otherwise a
        copy of its fields (not of its model) with the new gains.
        """
        if snap is self._last and self._gains == grounds.seq:
            return snap
        self._gains = grounds.seq
        return dataclasses.replace(snap, **grounds.fields(learning))


class SwapLog:
    """
    What receiving and installing the last snapshots cost the node process (no rclpy).

    ``note(version, receive_s, prepare_s)`` records one swap: ``receive_s`` reading and unpickling
    it, ``prepare_s`` building what the answers need (``plan.PlanCache.prepare``), both in the
    receiver thread, off the message path; the install itself is one reference assignment.
    ``summary()`` is what /diagnostics shows: swaps counted, the longest and the last costs (ms).
    """

    KEEP = 256

    def __init__(self):
        from collections import deque
        self.swaps = 0
        self._recent = deque(maxlen=self.KEEP)      # (version, receive_s, prepare_s)
        self.max_receive_s = self.max_prepare_s = 0.0

    def note(self, version: int, receive_s: float, prepare_s: float) -> None:
        self.swaps += 1
        self._recent.append((int(version), float(receive_s), float(prepare_s)))
        self.max_receive_s = max(self.max_receive_s, float(receive_s))
        self.max_prepare_s = max(self.max_prepare_s, float(prepare_s))

    def recent(self) -> list:
        """Return the last ``KEEP`` swaps, oldest first: (version, receive_s, prepare_s)."""
        return list(self._recent)

    def summary(self) -> dict:
        if not self.swaps:
            return {'snapshot_swaps': 0}
        _, r, p = self._recent[-1]
        return {'snapshot_swaps': self.swaps,
                'snapshot_receive_max_ms': round(self.max_receive_s * 1e3, 3),
                'snapshot_prepare_max_ms': round(self.max_prepare_s * 1e3, 3),
                'snapshot_prepare_last_ms': round(p * 1e3, 3)}

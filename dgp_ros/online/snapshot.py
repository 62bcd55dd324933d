"""
What the message path answers from: an immutable snapshot of the learner's state (no rclpy).

The learner publishes a :class:`Snapshot` whenever what it learned changes; the message path
swaps it in with one reference assignment and answers every message from the one it holds, so an
answer never waits for a fit, a proof or a rebuild. Across processes a snapshot is pickled: its
model is then a predict-only copy (``model.snapshot()``: training inputs, weights, scales, prior,
passivity state, and the Cholesky factors only when the variance is wanted).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ['Snapshot']


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
        any sample: where the prior's own force may raise the answers' bound (``answer``).
    residual_bound : (N,) largest |residual| learned per joint, before any correction (None
        after a reload): how far the prior may raise that bound at most.
    learned_through : learning time of the newest sample the learner had seen (s), or None.
    frozen : a self-contained copy (another process); variance : the posterior variance is
        available.
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

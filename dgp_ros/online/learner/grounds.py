"""
The grounds of an answer: what the model has earned, measured online, and the blend (no rclpy).

A controller takes the estimate as a feed-forward at full weight. Where the model has no
grounds (before it has learned, or where the system goes where it has not been) a confident
answer can be worse than no answer: a 7-joint arm's first models, fitted on 20 to 200 samples,
doubled its tracking error in closed loop. So every answer carries a per-joint *confidence* and
is blended toward what has proven itself.

**What has proven itself** is measured where the learner sees it: each learned sample is
answered by the served model *before* the sample is learned (one step ahead, as the message path
answered it), and by the parametric part alone (the passive prior ``diag(m_d(qd)) qd``).
:class:`Skill` keeps exponentially weighted sums of these answers against the learned target,
per joint, over the last ``GAIN_HALF_LIFE_S`` of learning time (at least ``GAIN_HALF_LIFE_SAMPLES``
samples), and gives two gains by shrunken least squares:

* ``a`` (N,): the prior's gain, ``argmin_a E[(t - a p)^2]`` clipped to [0, 1]: the fallback is
  ``f = a p`` (the parametric part where it has skill, zero where it has none);
* ``w`` (N,): the model's gain over that fallback, ``argmin_w E[(t - f - w (tau - f))^2]``,
  clipped to [0, 1], used as ``min(1, w / FULL_GAIN)`` (a gain of 0.8 is a model that is right up
  to a 20 % overestimate);

and it scores the answer so blended, ``y = f + w (tau - f)``, the same way: its gain over zero,
``g``, gives the *confidence* published beside every answer, ``c = min(1, g / FULL_GAIN)``:
how much of the published answer a controller can use (a feed-forward gain ``k c``). A prior
that explains the force with a model that adds little has ``w`` near 0 but ``c`` near 1.

A gain measured over a second of 100 samples is less evidence than it looks: the one-step
errors along a smooth motion are correlated over about half a second, so a second holds a few
independent ones, and the first seconds of a 7-joint arm's learning move through new territory
where the model that earned its gain on the last second is wrong again. So the confidence (not
the force) also needs ``EVIDENCE_S`` of learning time over which the model was scored: it is
multiplied by a smoothstep of that time from 0 to 1 (a learner restarted from a model keeps
the evidence it had). With 2 s, a simulated Panda in closed loop still had a joint's error
peak at 3.3x that with no compensation in its first 2 s; with 3 s, 1.2x on another seed; with
4 s, 1.054x on the ledger's Panda run; with 5 s, 1.035x.

All gains are shrunk toward 0 by ``PSEUDO_SAMPLES`` samples' worth of their own error variance (a
Bayesian regression with a unit prior on the gain): with no evidence yet the gain is 0 (no
answer is better than one without grounds), and it grows as fast as the data's signal to noise
allows: an aircraft's forces (known to 1e-3) earn full weight within a few samples, a noisy
joint torque within tens. The prior's gain takes its first sample as it is (an aircraft's prior
fitted on one sample answers the next to 1e-4); the model's needs two.

**The floor.** The gains move by one sample's weight of a second's memory: a model that goes
wrong at once kept its weight for 1.5 to 3 s at 30 Hz. So a faster memory (``skill._Floor``,
0.3 s, at least 4 samples) scores the answers as they were used, the fallback ``a p`` and the
blend ``f + w (u - f)``, against no answer, and scales the prior's gain and the model's weight
by factors that go toward 0 where that answer did worse than answering nothing (by at most
0.05 a sample: no step in the published force): within a second at any rate, no part that does
worse than no answer stays in the answer, and the status names the outputs.

**The blend** (:func:`dgp_ros.gp.blend.blend`, where a saved model applies it too) keeps
every guarantee the answer had. With ``S = diag(sqrt(w))``
and ``F = diag((1 - w) a m_d(qd))``, the published damping matrix is ``D' = S D S + F``: where
``D``'s symmetric part is positive semi-definite (guarantee ``psd``) so is ``D'`` (a congruence
plus a non-negative diagonal), and a diagonal ``D`` blends joint by joint,
``tau'_j = w_j tau_j + (1 - w_j) a_j p_j``. Other guarantees (a domain proof, a projection)
hold for ``q^T D(q) q`` only, so there one scalar ``w = min_j w_j`` blends
``D' = w D + (1 - w) diag(a m_d)``: a convex combination of two passive answers. Gains move by
one sample's weight at a time, so the published force has no step when they change.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dgp_ros.gp.blend import blend, GAINS

from .skill import EVIDENCE_S, Skill, SKILL_WARN_MARGIN

__all__ = ['Grounds', 'blend', 'GAINS']


class Grounds:
    """
    The learner's part that scores every learned sample and carries the gains (module doc).

    A part of :class:`~dgp_ros.online.learner.Learner`, called under its lock. It owns the
    :class:`Skill` (made at the first scored sample) and ``seq``, a number that changes whenever
    the gains do, so that a snapshot can carry them without a new model. ``seq``: where to start
    counting (a new learner state continues the last one's count); skill : a record to start
    from (None: made at the first scored sample).
    """

    def __init__(self, seq: int = 0, skill: Optional[Skill] = None):
        self._skill = skill
        self._seq = int(seq)

    @property
    def seq(self) -> int:
        """Return a number that changes whenever the gains do (every scored sample)."""
        return self._seq

    def touch(self) -> None:
        """Count a change of what the gains fields say (learning switched: another memory)."""
        self._seq += 1

    @property
    def evidence_s(self) -> float:
        """Return the learning time (s) over which the model was scored (0 before any)."""
        return 0.0 if self._skill is None else self._skill.evidence_s

    def note(self, stamp: float, qd: np.ndarray, target: np.ndarray, prior, residual: np.ndarray,
             q, model) -> float:
        """
        Score the served ``model`` and ``prior`` on one sample before it is learned.

        ``prior``: the prior the answers came from before the sample entered the history
        (None: nothing answered it but zero, nothing to score); ``residual``, ``q``: the
        sample's residual and pose, for the confidence of the damping force plus the
        conservative correction (``Skill.note``). Returns the model's error on the sample in
        units of its recent RMS error, largest over the joints (0: not scored).
        """
        if prior is None:
            return 0.0
        if self._skill is None:
            self._skill = Skill(qd.size)
        pose = q
        try:
            x = qd[None, :]
            p = np.asarray(prior.force(x), float)[0]
            u = None if model is None else np.asarray(model.predict(x), float)[0]
            full = cons = None
            corr = getattr(model, 'correction_', None)
            if corr is not None:
                full = residual - corr.offsets
                cons = corr.conservative(pose[None, :])[0] if pose is not None and \
                    corr.needs_position else np.zeros_like(qd)
        except Exception:           # noqa: BLE001 - a sample the model cannot answer: no score
            return 0.0
        self._skill.note(target, u, p, full, cons, stamp)
        self._seq += 1
        return self._skill.surprise

    # ------------------------------------------------------------------ the gains
    def gains(self):
        """Return (model weight, prior gain, confidence), (N,) each; Nones before any sample."""
        s = self._skill
        return (None, None, None) if s is None else s.gains()

    def saved_gains(self):
        """Return the gains a saved model carries (``Skill.long_gains``); Nones before any."""
        s = self._skill
        return (None, None, None) if s is None else s.long_gains()

    def fields(self, learning: bool) -> dict:
        """
        Return a snapshot's gains fields as they are now.

        With learning off the answers are blended by the gains a saved model carries (the long
        memory, ``saved_gains``: nothing is scored any more), as that model's own ``predict``
        is (``switch``).
        """
        weight, gain, conf = self.gains() if learning else self.saved_gains()
        return {'model_weight': weight, 'prior_gain': gain, 'confidence': conf}

    def restore(self, model_weight, prior_gain, confidence, live=None) -> bool:
        """
        Start from the gains a previous learner earned (a restarted learner, a model file).

        (w, a, c), (N,) each, seed both memories; ``live``: a saved model's record of the gains
        its learner answered with (``GAINS`` -> N numbers), which seed the short memory, so that
        a node that loads the file and learns on answers as the one that saved it. Returns
        whether anything was taken.
        """
        if model_weight is None or prior_gain is None or confidence is None:
            return False
        w = np.asarray(model_weight, float)
        if self._skill is None:
            self._skill = Skill(w.size)
        self._skill.seed(w, prior_gain, confidence)
        if live:
            self._skill.short.seed(*(live[k] for k in GAINS), self._skill.seed_samples)
        return True

    @staticmethod
    def record_gains(record: Optional[dict], N: int) -> tuple:
        """
        Return the arguments of ``restore`` from a model file's ``grounds_`` record.

        None (a file without one) means full weight: the user gave the model.
        """
        g = record or {}
        live = g.get('live')
        ok = isinstance(live, dict) and all(np.shape(live.get(k)) == (N,) for k in GAINS)
        return tuple(g.get(k, np.ones(N)) for k in GAINS) + (live if ok else None,)

    def record(self) -> Optional[dict]:
        """
        Return what a saved model carries of the gains (``grounds_``), None before any.

        ``GAINS`` -> the long memory's (``saved_gains``: what the model answers with, frozen or
        loaded anywhere), and ``live`` -> the gains the learner answers with now (a node that
        loads the file and learns on starts from them).
        """
        gains, live = self.saved_gains(), self.gains()
        if gains[0] is None:
            return None
        record = {k: [float(x) for x in v] for k, v in zip(GAINS, gains)}
        record['live'] = {k: [float(x) for x in v] for k, v in zip(GAINS, live)}
        return record

    # ------------------------------------------------------------------ report
    def summary(self) -> dict:
        """Return the per-joint figures of /diagnostics (``Skill.summary``), {} before any."""
        return {} if self._skill is None else self._skill.summary()

    def worse_than_nothing(self, names) -> list:
        """Return the names of the outputs whose model did worse than no answer just now."""
        s = self._skill
        if s is None:
            return []
        return [names[j] for j in np.flatnonzero(s.worse_than_nothing())]

    def trailing(self, names) -> list:
        """
        Return the names of the joints whose answers trail their parametric part.

        By more than ``SKILL_WARN_MARGIN`` of one-step skill over the last seconds, once the
        model was scored for ``EVIDENCE_S``; ``names`` (N,).
        """
        s = self._skill
        if s is None or s.evidence_s < EVIDENCE_S:
            return []
        sm = s.summary()
        return [names[j] for j, (m, p) in enumerate(zip(sm['skill_model'], sm['skill_prior']))
                if m is not None and p is not None and m < p - SKILL_WARN_MARGIN]

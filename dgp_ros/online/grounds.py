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
per joint, over the last ``HALF_LIFE_S`` of learning time (at least ``HALF_LIFE_SAMPLES``
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

import dataclasses
import math
from typing import Optional

import numpy as np

from dgp_ros.gp.blend import blend, GAINS

__all__ = ['Skill', 'SkillMixin', 'blend', 'GAINS', 'HALF_LIFE_S', 'HALF_LIFE_SAMPLES',
           'LONG_HALF_LIFE_S',
           'PSEUDO_SAMPLES', 'FULL_GAIN', 'EVIDENCE_S', 'SURPRISE_SIGNAL']


#: learning time (s) over which the skill is measured: a sample's weight halves after it ...
HALF_LIFE_S = 1.0
#: ... or after this many samples, if that is longer: a gain needs samples as well as seconds
#: (an A320 at 60 Hz with 60 samples: its one-step NMSE 1.2-1.4x worse on a flight of the
#: family; 100 samples are 1 s of an arm learning every 10 ms, 1.7 s at 60 Hz, 3.3 s at 30 Hz;
#: a model that goes wrong by three times the force falls back below a weight of 0.3 in 0.8 s
#: at 100 Hz, 1.2 s at 60 Hz, 2.7 s at 30 Hz: test_online_grounds)
HALF_LIFE_SAMPLES = 100
#: the memory of the gains a saved model carries (a frozen model answers with them for good:
#: the last second's gains of a noisy joint scaled a real Panda joint's friction by 0.54)
LONG_HALF_LIFE_S = 30.0
#: a pause in learning time counts as at most this step (s)
MAX_STEP_S = 0.1
#: shrinkage of the gains toward 0: this many samples' worth of their own error variance
PSEUDO_SAMPLES = 20.0
#: learning time (s) over which the model's answers must have been scored before its confidence
#: is full: the confidence is multiplied by a smoothstep from 0 to 1 over it (``Skill.note``)
EVIDENCE_S = 5.0
#: a gain at least this large counts in full (a gain of 0.8 is an answer that is right up to a
#: 20 % overestimate on the recent samples)
FULL_GAIN = 0.8
#: a sample's error counts toward ``Skill.surprise`` (new territory: ``jobs``) only where it is
#: more than this fraction of the force's recent RMS (the zero answer's error): far above the
#: model's own recent error but small against the force, as on a real arm's well-learned joint,
#: it is no reason to re-learn the hyper-parameters (docs/BENCHMARKS.md, "Issue 36, measured
#: by hand": the real Panda's split 0.545 with it, 0.567 without; on 22 A320 flights 0.05-0.7
#: keep the Panda at 0.545, 0.1-0.2 every flight within the family's limits, 0.3 not)
SURPRISE_SIGNAL = 0.1


class _Memory:
    """
    One memory of the skill: exponentially weighted sums and the gains they give (module doc).

    ``half_life_s``: learning time after which a sample's weight halves. ``a``, ``w``: the
    prior's gain and the model's weight; ``g``: the blended answer's gain over zero, as a
    fraction of ``FULL_GAIN`` (the confidence before the evidence smoothstep).
    """

    def __init__(self, N: int, half_life_s: float):
        self.half_life_s = float(half_life_s)
        z = np.zeros
        # prior: sums of t p, p p, t t ; model over the fallback: e d, d d, e e
        self.tp, self.pp, self.tt = z(N), z(N), z(N)
        self.ed, self.dd, self.ee = z(N), z(N), z(N)
        self.ty, self.yy, self.ttm = z(N), z(N), z(N)   # the blended answer, t t of its samples
        self.n_prior = self.n_model = 0.0            # effective sample counts
        # mean squared errors (exponentially weighted): zero, prior, model answers, fallback
        self.mse0, self.msep, self.msem, self.msef = z(N), z(N), z(N), z(N)
        self.a, self.w, self.g = z(N), z(N), z(N)

    def decay(self, dt: float) -> float:
        """Return the weight left to the past after one sample ``dt`` s after the last one."""
        return 0.5 ** min(dt / self.half_life_s, self.half_life_s / HALF_LIFE_S /
                          HALF_LIFE_SAMPLES)

    def note_prior(self, t: np.ndarray, p: np.ndarray, g: float) -> None:
        self.tp = g * self.tp + t * p
        self.pp = g * self.pp + p * p
        self.tt = g * self.tt + t * t
        self.n_prior = g * self.n_prior + 1.0
        self.a = _gain(self.tp, self.pp, self.tt, self.n_prior)
        self.mse0 = g * self.mse0 + (1.0 - g) * t * t
        self.msep = g * self.msep + (1.0 - g) * (t - p) ** 2

    def note_model(self, t, u, p, full, corr, g: float) -> np.ndarray:
        """Take the model's answer ``u``; return its error on the sample, (N,)."""
        f = self.a * p                       # the fallback as it is now
        e, d = t - f, u - f
        y = f + self.w * d                   # the answer as it was published (per joint)
        if full is not None:
            t, y = full, y + corr
        self.ed = g * self.ed + e * d
        self.dd = g * self.dd + d * d
        self.ee = g * self.ee + e * e
        self.msem = g * self.msem + (1.0 - g) * (e - d) ** 2
        self.msef = g * self.msef + (1.0 - g) * e * e
        self.ty = g * self.ty + t * y
        self.yy = g * self.yy + y * y
        self.ttm = g * self.ttm + t * t
        self.n_model = g * self.n_model + 1.0
        n = self.n_model
        self.w = np.minimum(1.0, _gain(self.ed, self.dd, self.ee, n, False) / FULL_GAIN)
        self.g = np.minimum(1.0, _gain(self.ty, self.yy, self.ttm, n, False) / FULL_GAIN)
        return np.abs(e - d)

    def seed(self, w, a, c, n: float) -> None:
        """Write ``n`` noise-free samples of unit size that give exactly these gains."""
        def raw(x):
            x = np.clip(np.asarray(x, float), 0.0, 1.0)
            return x, np.where(x >= 1.0, 1.0, x * FULL_GAIN)
        a = np.clip(np.asarray(a, float), 0.0, 1.0)
        (w, bw), (c, bc) = raw(w), raw(c)
        one = np.full(a.size, float(n))
        self.pp, self.tp, self.tt = one.copy(), a * n, a * a * n
        self.dd, self.ed, self.ee = one.copy(), bw * n, bw * bw * n
        self.yy, self.ty, self.ttm = one.copy(), bc * n, bc * bc * n
        self.n_prior = self.n_model = float(n)
        self.a, self.w, self.g = a.copy(), w.copy(), c.copy()
        # errors that say what the gains say (``Skill.long_gains``: a part at full gain did no
        # worse than its fallback), until samples move them
        one = np.ones(a.size)
        self.mse0, self.msef = one.copy(), one.copy()
        self.msep = np.where(a >= 1.0, 0.5, 2.0)
        self.msem = np.where(w >= 1.0, 0.5, 2.0)


class Skill:
    """
    One-step-ahead skill of the model and of the parametric part, per joint (module docstring).

    ``note(target, model, prior)``: (N,) each, in force units: the learned target, the model's
    answer before learning it (None when there is no model yet) and the parametric part's.
    ``gains()`` -> (w, a, c): the model's weight in the blend, the prior's gain and the
    confidence of the blended answer, (N,) each in [0, 1], over the last ``HALF_LIFE_S`` of
    learning time; ``long_gains()`` the same over ``LONG_HALF_LIFE_S`` (what a saved model
    carries).
    """

    def __init__(self, N: int, half_life_s: float = HALF_LIFE_S,
                 long_half_life_s: float = LONG_HALF_LIFE_S):
        self.N = int(N)
        self.short = _Memory(N, half_life_s)
        self.long = _Memory(N, long_half_life_s)
        self.samples = 0
        self.surprise = 0.0                        # the last sample's error / recent RMS error
        self.evidence_s = 0.0                      # learning time the model was scored over
        self._stamp = None
        self._dt = 1.0 / 100.0                     # the last step (s): the decay of a sample

    def note(self, target: np.ndarray, model: Optional[np.ndarray], prior: np.ndarray,
             full_target: Optional[np.ndarray] = None,
             correction: Optional[np.ndarray] = None, stamp: Optional[float] = None) -> None:
        """
        Take one learned sample (module docstring); non-finite answers are not taken.

        ``full_target``, ``correction`` (N,): what the confidence scores instead, when the
        model has a correction a controller adds beside the damping force (the residual
        without the offsets, against the blended answer plus the correction). ``stamp``: the
        sample's learning time (s): the decay and the evidence (``EVIDENCE_S``) go by it.
        """
        t = np.asarray(target, float)
        p = np.asarray(prior, float)
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            return
        step = self._step(stamp)
        gs, gl = self.short.decay(step), self.long.decay(step)
        self.samples += 1
        self.short.note_prior(t, p, gs)
        self.long.note_prior(t, p, gl)
        self.surprise = 0.0
        if model is None:
            return
        u = np.asarray(model, float)
        if not np.all(np.isfinite(u)):
            return
        full = corr = None
        if full_target is not None and correction is not None and \
                np.all(np.isfinite(full_target)) and np.all(np.isfinite(correction)):
            full, corr = np.asarray(full_target, float), np.asarray(correction, float)
        m = self.short
        scored = m.n_model >= 2.0
        err = m.note_model(t, u, p, full, corr, gs)
        self.long.note_model(t, u, p, full, corr, gl)
        if scored:
            # the model's error on this sample in units of its recent RMS error (this sample
            # included), where the error is more than SURPRISE_SIGNAL of the force's RMS
            z = err / np.sqrt(np.maximum(m.msem, 1e-300))
            self.surprise = float(np.max(np.where(
                err > SURPRISE_SIGNAL * np.sqrt(m.mse0), z, 0.0)))
        if stamp is not None and self._stamp_moved:
            self.evidence_s += step

    def _step(self, stamp: Optional[float]) -> float:
        """Return the learning time since the last sample (a pause counts as ``MAX_STEP_S``)."""
        last = self._stamp
        self._stamp_moved = False
        if stamp is not None:
            self._stamp = float(stamp)
            if last is not None and 0.0 < stamp - last:
                self._dt = min(stamp - last, MAX_STEP_S)
                self._stamp_moved = True
        return self._dt

    def _confidence(self, m: _Memory) -> np.ndarray:
        x = min(1.0, self.evidence_s / EVIDENCE_S) if EVIDENCE_S > 0 else 1.0
        return m.g * (x * x * (3.0 - 2.0 * x))

    def gains(self):
        """Return (w, a, c): model weight, prior gain, confidence, (N,) copies (class doc)."""
        m = self.short
        return m.w.copy(), m.a.copy(), self._confidence(m)

    def long_gains(self):
        """
        Return the gains a saved model carries: (w, a, c) of the long memory, where they did.

        A frozen model answers with them for good, so they say whether each part earned its
        place over the run, not by how much it was off in its worst stretch: the model keeps
        full weight on a joint where its one-step error over the long memory was below its
        fallback's, the prior full gain where its error was below no answer's; elsewhere the
        long memory's least-squares gains (toward the fallback, or zero). The last second's
        gains of a real Panda at 30 Hz scaled a joint's friction by 0.33 for good and cost 5 %
        of its held-out accuracy; the prior had been right all along.
        """
        m = self.long
        w = np.where((m.n_model > 0) & (m.msem <= m.msef), 1.0, m.w)
        a = np.where((m.n_prior > 0) & (m.msep <= m.mse0), 1.0, m.a)
        return w, a, self._confidence(m)

    def seed(self, w: np.ndarray, a: np.ndarray, c: np.ndarray, n: Optional[float] = None):
        """
        Start from gains earned before (w, a, c as ``gains`` returns them, (N,) each).

        Written into both memories as ``n`` noise-free samples of unit size that give exactly
        these gains (default ``seed_samples``); new samples move them as they would have moved
        the earned ones.
        """
        n = self.seed_samples if n is None else float(n)
        self.short.seed(w, a, c, n)
        self.long.seed(w, a, c, n)
        self.evidence_s = EVIDENCE_S

    @property
    def seed_samples(self) -> float:
        """Return the samples' worth a seed is written as (half a short half-life at 100 Hz)."""
        return 0.5 * 100.0 * self.short.half_life_s

    def summary(self) -> dict:
        """Per-joint figures for /diagnostics: confidence, gains and skills (1 - MSE / MSE(0))."""
        m = self.short
        z = np.maximum(m.mse0, 1e-300)
        skill_m = np.where(m.n_model > 0, 1.0 - m.msem / z, np.nan)
        return {'confidence': _round(self._confidence(m)), 'model_weight': _round(m.w),
                'prior_gain': _round(m.a),
                'skill_model': _round(skill_m), 'skill_prior': _round(1.0 - m.msep / z),
                'skill_samples': self.samples}


def _gain(xy, xx, yy, n, first: bool = True):
    """
    Shrunken least-squares gain ``b`` of ``y ~ b x`` from weighted sums, clipped to [0, 1].

    The shrinkage is ``PSEUDO_SAMPLES`` times the error variance per sample of the unshrunk fit
    (a Bayesian regression with a N(0, 1) prior on ``b``, the noise variance estimated). One
    sample fits exactly: ``first`` False shrinks it as if its error were all it has.
    """
    if n <= 0.0:
        return np.zeros_like(xy)
    b = xy / np.maximum(xx, 1e-300)
    s2 = np.maximum(yy - b * xy, 0.0) / n
    if not first and n < 1.5:
        s2 = np.maximum(s2, yy / n)
    return np.clip(xy / np.maximum(xx + PSEUDO_SAMPLES * s2, 1e-300), 0.0, 1.0)


def _round(a) -> list:
    return [None if not math.isfinite(float(v)) else round(float(v), 4) for v in a]


class SkillMixin:
    """
    Mixin of :class:`~dgp_ros.online.learner.Learner`: its :class:`Skill` (module docstring).

    Uses the learner's ``_N``, ``_model``, ``_buf``, ``_history``, ``_fitted_prior``; the
    snapshot carries ``skill_gains()``.
    """

    _skill: Optional[Skill] = None

    def _skill_prior(self):
        """Return the prior the answers come from now (before the next sample), or None."""
        model = self._model
        h = self._history
        if model is None and (self._buf is None or not self._buf.size) and \
                (h is None or not h.samples):
            return None             # fitted on nothing: the answer was zero, not the prior's
        try:
            if model is not None and model.posterior_.structure.has_damping:
                return model.mean_
            return self._fitted_prior()[0]
        except Exception:           # noqa: BLE001 - no prior yet (degenerate buffer)
            return None

    def _note_skill(self, stamp: float, qd: np.ndarray, target: np.ndarray, prior,
                    residual: np.ndarray, q=None) -> float:
        """
        Score the served model and ``prior`` on one sample before it is learned.

        ``prior``: what ``_skill_prior`` returned before the sample entered the history;
        ``residual``, ``q``: the sample's residual and pose, for the confidence of the damping
        force plus the conservative correction (``Skill.note``). Returns the model's error on the
        sample in units of its recent RMS error, largest over the joints (0: not scored).
        """
        if prior is None:
            return 0.0              # nothing answered this sample but zero: nothing to score
        if self._skill is None:
            self._skill = Skill(self._N)
        model, pose = self._model, q
        try:
            q = qd[None, :]
            p = np.asarray(prior.diag(q), float)[0] * qd
            u = None if model is None else np.asarray(model.predict(q), float)[0]
            full = cons = None
            corr = getattr(model, 'correction_', None)
            if corr is not None:
                full = residual - corr.offsets
                cons = corr.conservative(pose[None, :])[0] if pose is not None and \
                    corr.needs_position else np.zeros_like(qd)
        except Exception:           # noqa: BLE001 - a sample the model cannot answer: no score
            return 0.0
        self._skill.note(target, u, p, full, cons, stamp)
        self._gains_seq += 1
        return self._skill.surprise

    @property
    def gains_seq(self) -> int:
        """Return a number that changes whenever the gains do (every scored sample)."""
        return self._gains_seq

    def snapshot_gains(self) -> dict:
        """
        Return the snapshot's gains fields as they are now (locked by the caller).

        With learning off the answers are blended by the gains a saved model carries (the long
        memory, ``saved_gains``: nothing is scored any more), as that model's own ``predict``
        is (switch.py).
        """
        weight, gain, conf = self.skill_gains() if self.config.learning else self.saved_gains()
        return {'model_weight': weight, 'prior_gain': gain, 'confidence': conf}

    def _with_gains(self, snap):
        """
        Return ``snap`` carrying the gains as they are now (locked by the caller).

        The cached snapshot is returned as it is while no sample moved the gains; otherwise a
        copy of its fields (not of its model) with the new gains: a sample the buffer skips
        moves the gains without a new version.
        """
        if snap is self._snap and self._snap_gains == self._gains_seq:
            return snap
        self._snap_gains = self._gains_seq
        return dataclasses.replace(snap, **self.snapshot_gains())

    def skill_gains(self):
        """Return (model weight, prior gain, confidence), (N,) each; Nones before any sample."""
        s = self._skill
        return (None, None, None) if s is None else s.gains()

    def saved_gains(self):
        """Return the gains a saved model carries (``Skill.long_gains``); Nones before any."""
        s = self._skill
        return (None, None, None) if s is None else s.long_gains()

    def restore_gains(self, model_weight, prior_gain, confidence, live=None) -> None:
        """
        Start from the gains a previous learner earned (a restarted learner, a model file).

        (w, a, c), (N,) each, seed both memories; ``live``: a saved model's record of the gains
        its learner answered with (``GAINS`` -> N numbers), which seed the short memory, so that
        a node that loads the file and learns on answers as the one that saved it.
        """
        if model_weight is None or prior_gain is None or confidence is None:
            return
        with self._lock:
            w = np.asarray(model_weight, float)
            if self._skill is None:
                self._skill = Skill(w.size)
            self._skill.seed(w, prior_gain, confidence)
            if live:
                self._skill.short.seed(*(live[k] for k in GAINS), self._skill.seed_samples)
            self._snap = None

    def grounds_record(self) -> Optional[dict]:
        """
        Return what a saved model carries of the gains (``grounds_``), None before any.

        ``GAINS`` -> the long memory's (``saved_gains``: what the model answers with, frozen or
        loaded anywhere), and ``live`` -> the gains the learner answers with now (a node that
        loads the file and learns on starts from them).
        """
        gains, live = self.saved_gains(), self.skill_gains()
        if gains[0] is None:
            return None
        record = {k: [float(x) for x in v] for k, v in zip(GAINS, gains)}
        record['live'] = {k: [float(x) for x in v] for k, v in zip(GAINS, live)}
        return record

    def restore_grounds(self, record: Optional[dict], N: int) -> None:
        """Start from a model file's ``grounds_`` record (None: full weight, the user's model)."""
        g = record or {}
        live = g.get('live')
        ok = isinstance(live, dict) and all(np.shape(live.get(k)) == (N,) for k in GAINS)
        self.restore_gains(*(g.get(k, np.ones(N)) for k in GAINS), live=live if ok else None)

    def skill_summary(self) -> dict:
        return {} if self._skill is None else self._skill.summary()

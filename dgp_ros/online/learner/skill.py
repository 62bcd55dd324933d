"""
The one-step skill of the model and of its parametric part, and the gains it gives (no rclpy).

:class:`Skill` keeps exponentially weighted sums of the one-step answers of the model and of the
parametric part against the learned target, per joint, and gives the model's weight, the prior's
gain and the confidence of the blended answer (``grounds`` says what they are for and how they
are used; :class:`~dgp_ros.online.learner.grounds.Grounds` is the learner's part that feeds it).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

__all__ = ['Skill', 'GAIN_HALF_LIFE_S', 'GAIN_HALF_LIFE_SAMPLES', 'LONG_HALF_LIFE_S', 'MAX_STEP_S',
           'PSEUDO_SAMPLES', 'FULL_GAIN', 'EVIDENCE_S', 'SURPRISE_SIGNAL', 'SKILL_WARN_MARGIN',
           'FLOOR_S', 'FLOOR_SAMPLES', 'FLOOR_MIN', 'FLOOR_STEP']


#: learning time (s) over which the skill is measured: a sample's weight halves after it ...
GAIN_HALF_LIFE_S = 1.0
#: ... or after this many samples, if that is longer: a gain needs samples as well as seconds
#: (an A320 at 60 Hz with 60 samples: its one-step NMSE 1.2-1.4x worse on a flight of the
#: family; 100 samples are 1 s of an arm learning every 10 ms, 1.7 s at 60 Hz, 3.3 s at 30 Hz;
#: a model that goes wrong by three times the force falls back below a weight of 0.3 in 0.8 s
#: at 100 Hz, 1.2 s at 60 Hz, 2.7 s at 30 Hz: test_online_grounds)
GAIN_HALF_LIFE_SAMPLES = 100
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
#: a sample's error counts toward ``Skill.surprise`` (new territory: ``jobs.refits``) only where
#: it is more than this fraction of the force's recent RMS (the zero answer's error): far above the
#: model's own recent error but small against the force, as on a real arm's well-learned joint,
#: it is no reason to re-learn the hyper-parameters (docs/BENCHMARKS.md, "Issue 36, measured
#: by hand": the real Panda's split 0.545 with it, 0.567 without; on 22 A320 flights 0.05-0.7
#: keep the Panda at 0.545, 0.1-0.2 every flight within the family's limits, 0.3 not)
SURPRISE_SIGNAL = 0.1
#: the floor of the answers (``_Floor``): over about this much learning time (s), or at least
#: ``FLOOR_SAMPLES`` samples, a part whose one-step error exceeds no answer's is not used
FLOOR_S = 0.3
FLOOR_SAMPLES = 4
#: ... once this many samples' worth of its answers were scored, its factor moving at most this
#: much per sample
FLOOR_MIN = 3.0
FLOOR_STEP = 0.05
#: one-step skill (1 - MSE / MSE of no answer) by which the model may trail its parametric part
#: on a joint, over the last seconds, before the status says so (``Grounds.trailing``)
SKILL_WARN_MARGIN = 0.1


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
        return 0.5 ** min(dt / self.half_life_s, self.half_life_s / GAIN_HALF_LIFE_S /
                          GAIN_HALF_LIFE_SAMPLES)

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


class _Floor:
    """
    The last fraction of a second of one-step errors: no answer's, the fallback's, the blend's.

    The short memory's gains need a second (100 samples: 3.3 s at 30 Hz) to turn away from a
    model that just went wrong. The floor keeps errors over ``FLOOR_S`` (at least
    ``FLOOR_SAMPLES`` samples) and a factor per output for the model's weight and one for the
    prior's gain: each goes toward 1 where its answer as used (the fallback ``a p``; the blend
    ``f + w (u - f)``) did no worse than answering nothing, toward 0 where its error reached
    twice no answer's (linearly between), by at most ``FLOOR_STEP`` per sample, so that the
    published force has no step and a part that does worse than no answer is out within a few
    tenths of a second at any stream rate.
    """

    def __init__(self, N: int):
        z = np.zeros
        self.e0, self.ef, self.ey = z(N), z(N), z(N)
        self.n_prior = self.n_model = 0.0
        self.fm, self.fp = np.ones(N), np.ones(N)      # the factors of model and prior

    @staticmethod
    def decay(dt: float) -> float:
        return 0.5 ** min(dt / FLOOR_S, 1.0 / FLOOR_SAMPLES)

    def note(self, t, f, y, g: float) -> None:
        """Take the target ``t``, the fallback's answer ``f`` and the blend's ``y`` (or None)."""
        self.e0 = g * self.e0 + (1.0 - g) * t * t
        self.ef = g * self.ef + (1.0 - g) * (t - f) ** 2
        self.n_prior = g * self.n_prior + 1.0
        if y is not None:
            self.ey = g * self.ey + (1.0 - g) * (t - y) ** 2
            self.n_model = g * self.n_model + 1.0
        self.fp = self._move(self.fp, self.ef, self.n_prior)
        self.fm = self._move(self.fm, self.ey, self.n_model)

    def _move(self, factor, err, n):
        e0 = np.maximum(self.e0, 1e-300)
        target = np.where(n >= FLOOR_MIN, np.clip(2.0 - err / e0, 0.0, 1.0), 1.0)
        return factor + np.clip(target - factor, -FLOOR_STEP, FLOOR_STEP)

    def below(self) -> np.ndarray:
        """Return per output whether the blend's recent answers did worse than nothing."""
        return (self.n_model >= FLOOR_MIN) & (self.ey > self.e0)


class Skill:
    """
    One-step-ahead skill of the model and of the parametric part, per joint (module docstring).

    ``note(target, model, prior)``: (N,) each, in force units: the learned target, the model's
    answer before learning it (None when there is no model yet) and the parametric part's.
    ``gains()`` -> (w, a, c): the model's weight in the blend, the prior's gain and the
    confidence of the blended answer, (N,) each in [0, 1], over the last ``GAIN_HALF_LIFE_S`` of
    learning time; ``long_gains()`` the same over ``LONG_HALF_LIFE_S`` (what a saved model
    carries).
    """

    def __init__(self, N: int, half_life_s: float = GAIN_HALF_LIFE_S,
                 long_half_life_s: float = LONG_HALF_LIFE_S):
        self.N = int(N)
        self.short = _Memory(N, half_life_s)
        self.long = _Memory(N, long_half_life_s)
        self.floor = _Floor(N)
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
        m = self.short
        f = m.a * p                                # fallback and blend as they answered it
        u = None if model is None else np.asarray(model, float)
        if u is not None and not np.all(np.isfinite(u)):
            u = None
        self.floor.note(t, f, None if u is None else f + m.w * (u - f), _Floor.decay(step))
        self.short.note_prior(t, p, gs)
        self.long.note_prior(t, p, gl)
        self.surprise = 0.0
        if u is None:
            return
        full = corr = None
        if full_target is not None and correction is not None and \
                np.all(np.isfinite(full_target)) and np.all(np.isfinite(correction)):
            full, corr = np.asarray(full_target, float), np.asarray(correction, float)
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
        """
        Return (w, a, c): model weight, prior gain, confidence, (N,) copies (class doc).

        Each times its factor of the floor (``_Floor``): toward 0 where that part's last answers
        did worse than no answer; the confidence times the larger of the two (none where both
        did).
        """
        m, fl = self.short, self.floor
        return (m.w * fl.fm, m.a * fl.fp,
                self._confidence(m) * np.maximum(fl.fm, fl.fp))

    def worse_than_nothing(self) -> np.ndarray:
        """Return per output whether the blended answers just now did worse than no answer."""
        return self.floor.below()

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

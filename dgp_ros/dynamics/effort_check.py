"""
Does each joint's effort behave as joint torque? Its gain against the rigid-body model's torque.

Where the rigid-body model explains a joint's effort (gravity and inertia on an arm's shoulder
and elbow), the measured torque follows the model's torque ``tau_rb`` at a gain near 1: the
shared real logs give 0.94-1.04 (UR10 shoulder and elbow) and 0.99-1.22 (Panda joints 1-6).
An effort that is no torque in N m shows there first: a motor current follows it at
``1 / (torque constant x gear ratio)`` (about 0.08 on a UR10: the UR driver publishes currents
unless ``use_currents_as_efforts`` is false), a reversed sign convention at -1, a joint order
that differs from the URDF's at anything. :class:`EffortCheck` keeps per joint the running
regression of the effort on ``tau_rb`` (with an intercept: offsets) and judges only joints the
model explains (correlation at least :data:`MIN_CORRELATION`, after :data:`MIN_SAMPLES` samples
over :data:`MIN_SPAN_S` s): on a joint whose friction dominates the model explains nothing and
says nothing of the unit, and the first second of a motion that starts from rest can show a
torque's gain near 3 (a simulated Panda's shoulder, 1.75 s in).

Pure numpy; O(N) memory and per sample. A part of the learner's front end
(``online.learner.sampling``).
"""
from __future__ import annotations

from typing import List, Optional, Sequence

import numpy as np

__all__ = ['EffortCheck', 'MIN_SAMPLES', 'MIN_SPAN_S', 'MIN_CORRELATION', 'GAIN_RANGE']

#: samples, and stamp time they span (s), before a joint is judged
MIN_SAMPLES = 150
MIN_SPAN_S = 2.5
#: a joint is judged only where the effort correlates with ``tau_rb`` at least this much
MIN_CORRELATION = 0.8
#: gains of the effort on ``tau_rb`` that torque in N m may show (an identified model's masses
#: are off by tens of percent, a payload adds more; a current is at about 0.1, a sign at -1)
GAIN_RANGE = (1.0 / 3.0, 3.0)


class EffortCheck:
    """
    Running regression of each joint's effort on the rigid-body torque (module docstring).

    ``learn_one(stamp, tau_rb, effort)`` takes one sample at ``stamp`` (s), (N,) each, in N m;
    ``gains()`` returns the gain and correlation per joint; ``warning(names, scale)`` the
    sentence a user acts on, '' when every judged joint behaves as torque.
    """

    def __init__(self):
        self.n = 0
        self._span = (0.0, 0.0)                        # the first and last stamps (s)
        self._origin: Optional[np.ndarray] = None      # (2, N): the first sample (stability)
        self._sums: Optional[np.ndarray] = None        # (5, N): x, y, xx, xy, yy about it

    def learn_one(self, stamp: float, tau_rb: np.ndarray, effort: np.ndarray) -> None:
        """Take one sample at ``stamp`` (s): the model's torque and the effort (N,), in N m."""
        x, y = np.asarray(tau_rb, float), np.asarray(effort, float)
        if self._origin is None or self._origin.shape[1] != x.size:
            self._origin = np.stack([x, y])
            self._sums = np.zeros((5, x.size))
            self.n = 0
            self._span = (float(stamp), float(stamp))
        self._span = (self._span[0], max(self._span[1], float(stamp)))
        dx, dy = x - self._origin[0], y - self._origin[1]
        self._sums += (dx, dy, dx * dx, dx * dy, dy * dy)
        self.n += 1

    def gains(self):
        """
        Return (gain, correlation), (N,) each: the effort's regression slope on ``tau_rb``.

        NaN before :data:`MIN_SAMPLES` samples over :data:`MIN_SPAN_S` s, and where ``tau_rb``
        or the effort did not vary.
        """
        if self._sums is None or self.n < MIN_SAMPLES or \
                self._span[1] - self._span[0] < MIN_SPAN_S:
            N = 0 if self._sums is None else self._sums.shape[1]
            return np.full(N, np.nan), np.full(N, np.nan)
        sx, sy, sxx, sxy, syy = self._sums / self.n
        vx, vy, cxy = sxx - sx * sx, syy - sy * sy, sxy - sx * sy
        with np.errstate(invalid='ignore', divide='ignore'):
            ok = (vx > 0) & (vy > 0)
            gain = np.where(ok, cxy / np.where(ok, vx, 1.0), np.nan)
            corr = np.where(ok, cxy / np.sqrt(np.where(ok, vx * vy, 1.0)), np.nan)
        return gain, corr

    def judged(self) -> np.ndarray:
        """Return which joints the model explains well enough to judge, (N,) bools."""
        _, corr = self.gains()
        return np.abs(np.nan_to_num(corr)) >= MIN_CORRELATION

    def warning(self, names: Sequence[str], scale: Sequence[float] = ()) -> str:
        """
        Say which judged joints' effort is no joint torque, and the fix; '' when none.

        names : the joint names (N,); scale : the ``effort_scale`` in use ([] = 1), which the
        suggested scale multiplies.
        """
        gain, corr = self.gains()
        judged = self.judged()
        lo, hi = GAIN_RANGE
        bad = judged & ~((gain >= lo) & (gain <= hi))
        if not bad.any():
            return ''
        s = np.broadcast_to(np.asarray(scale, float) if len(scale) else np.ones(1),
                            gain.shape)
        idx = np.flatnonzero(bad)
        joints = _listing([str(names[j]) if j < len(names) else str(j) for j in idx])
        gains = _listing([f'{gain[j]:.3g}x' for j in idx])
        rs = _listing([f'{abs(corr[j]):.2f}' for j in idx])
        fix = _listing([f'{s[j] / gain[j]:.3g}' for j in idx])
        cause = ('the opposite sign: the driver and the URDF disagree on the sign convention '
                 '(or the joint order)' if np.all(gain[idx] < 0) else
                 'another unit or scale: a motor current (the UR driver publishes currents '
                 'unless use_currents_as_efforts is false) or a gear stage')
        return (f'the effort does not behave as joint torque on {joints}: it follows the '
                f"rigid-body model's torque at {gains} (correlation {rs}), where torque in "
                f'N m follows it at about 1x; {cause}. What is learned is not friction: set '
                f'effort_scale (torque per effort unit; here about {fix}), or check the URDF '
                'and the joint order')


def _listing(items: List[str]) -> str:
    """Join ``items`` with commas."""
    return ', '.join(items)

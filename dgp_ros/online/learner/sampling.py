"""
The learner's front end: from a validated measurement to the samples it learns (no rclpy).

A part of :class:`~dgp_ros.online.learner.Learner`, called under its lock. It owns

* the rate limit in stamp time: at most one sample per ``min_sample_interval_s`` is offered for
  learning, so a replay decides exactly as the live run did and a 1 kHz stream does not drown
  the O(n^2) update (a stamp that went back is never limited);
* with ``inverse_dynamics``: the residual front end (``dynamics.FrictionResidual``): every
  message enters the acceleration filter, and the friction residual ``effort - tau_rb(q, qd,
  qdd)`` of a sample the rate limit let through is complete half a filter window later. A plugin
  that fails is counted, its message still answered;
* with ``inverse_dynamics``: the check that the effort behaves as joint torque against
  ``tau_rb`` (``dynamics.effort_check``), fed with every completed residual sample.
"""
from __future__ import annotations

from typing import List, Optional, Tuple

import numpy as np

from dgp_ros.dynamics import AccelFilter, FrictionResidual, make_inverse_dynamics
from dgp_ros.dynamics.effort_check import EffortCheck

__all__ = ['Front']


class Front:
    """
    The front end (module docstring).

    config : the learner's configuration when the part is made (its filter window: structural);
    inverse : the rigid-body model, None without one (the effort is then what is learned).
    """

    def __init__(self, config, inverse):
        self.inverse = inverse
        self.residual = FrictionResidual(
            inverse, AccelFilter(config.accel_half_window_s) if inverse is not None else None)
        #: does the effort behave as torque against the rigid-body model (None without one)
        self.effort = EffortCheck() if inverse is not None else None
        self._last_stamp: Optional[float] = None    # the last sample offered for learning
        self._thin_i = 0                # samples given while thinning (``thin``)

    @staticmethod
    def inverse_dynamics(config):
        """Build the rigid-body model of ``config`` (None: without one, or the URDF is awaited)."""
        if config.awaits_urdf:
            return None
        return make_inverse_dynamics(config.inverse_dynamics,
                                     robot_description=config.robot_description,
                                     urdf_file=config.urdf_file, joints=config.joints)

    def rate_limited(self, config, stamp: float) -> bool:
        """Tell whether a sample at ``stamp`` comes too soon after the last one offered."""
        dt = config.min_sample_interval_s
        last = self._last_stamp
        return dt > 0 and last is not None and last <= stamp < last + dt * (1.0 - 1e-9)

    def offer(self, config, health, stamp: float, qd: np.ndarray, tau: np.ndarray,
              q) -> Tuple[bool, list, List[tuple]]:
        """
        Take one validated measurement at learning time ``stamp`` (s).

        Returns (offered for learning, the residual samples completed, the samples to learn:
        (stamp, qd, residual, q, qdd) each, finite). Counts what it does not offer in
        ``health``.
        """
        if config.awaits_urdf:                  # no rigid-body model yet: nothing to learn
            health.samples_awaiting_model += 1
            return False, [], []
        want = not self.rate_limited(config, stamp)
        if want:
            self._last_stamp = stamp
        else:
            health.samples_rate_limited += 1
        if self.inverse is None:
            return want, [], [(stamp, qd, tau, q, None)] if want else []
        try:
            done = self.residual.push(stamp, q, qd, tau, want=want)
        except Exception as exc:        # a plugin that fails: the message is still answered
            health.last_refit_error = f'inverse dynamics failed: {type(exc).__name__}: {exc}'
            health.inverse_dynamics_errors += 1
            return False, [], []
        take = [(r.stamp_s, r.qd, r.residual, r.q, r.qdd) for r in done
                if np.all(np.isfinite(r.residual))]
        for r in done:
            if np.all(np.isfinite(r.residual)):
                self.effort.learn_one(r.stamp_s, r.tau_rb, r.effort)
        return want, done, take

    def thin(self, take: List[tuple], k: int, health) -> Tuple[List[tuple], List[tuple]]:
        """
        Keep one in ``k`` of the samples given, over the calls; count the rest as thinned.

        Returns (kept, thinned): a thinned sample may still feed what costs little per sample
        (``Learner._learn``: the long history of a system without a rigid-body model).
        """
        kept, thinned = [], []
        for sample in take:
            self._thin_i = (self._thin_i + 1) % k
            (kept if self._thin_i == 0 else thinned).append(sample)
        health.samples_thinned += len(thinned)
        return kept, thinned

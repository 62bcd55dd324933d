"""
What the estimator accepts: the joints, their order, and the checks of every message (no rclpy).

A part of :class:`~.estimator.OnlineEstimator`, called under its lock. It owns the
joint names the estimator answers in (``joints``, else the first named message's), their number
and the order of the last names seen, and checks one message (``check``) or a batch of like
messages given as arrays (``check_batch``: a driver sends the same names and lengths in every
message, so a batch is a few arrays) by the same rules, giving the same rejection reasons
(``health.REJECT_REASONS``) in the same order. It counts nothing: the estimator's ``Health``
does, in message order. An accepted message's effort leaves as joint torque: times
``effort_scale`` where the driver publishes another unit (a motor current); the range check
reads the effort as published.
"""
from __future__ import annotations

from typing import Callable, List, Optional

import numpy as np

__all__ = ['Intake']


class Intake:
    """
    The accepted joints and the checks (module docstring).

    settings : returns the estimator's configuration as it is now (the joints, the limits);
    names : the joint names the learner selects (``joints``, else the URDF's; [] = the first
    named message's order); positions : whether messages must carry positions (the learner's
    inverse dynamics).
    """

    def __init__(self, settings: Callable, names: List[str], positions: bool):
        self._settings = settings
        self._names: Optional[List[str]] = list(names) or None
        self._N: Optional[int] = len(names) or None
        self._positions = bool(positions)
        # (a message's names, their configured order[, None when they are in that order])
        self._order = None

    @property
    def names(self) -> Optional[List[str]]:
        """Return a copy of the joint names the answers are in, None before they are known."""
        return None if self._names is None else list(self._names)

    @property
    def N(self) -> Optional[int]:
        """Return the number of joints, None before the first accepted message."""
        return self._N

    def admit(self, qd: np.ndarray, names) -> Optional[str]:
        """
        Take the first accepted message's dimension and names; the rejection reason or None.

        A message of another joint count than the per-joint parameters is 'dimension_mismatch'.
        Returns None when the message is accepted.
        """
        if self._N is None:
            try:
                self._settings().check_dimension(qd.size)
            except ValueError:              # per-joint parameters for another joint count
                return 'dimension_mismatch'
            self._N = qd.size
        return None

    def name(self, names) -> bool:
        """Take the joint names of an accepted message if none are known; True if taken."""
        if self._names is None and names:
            self._names = list(names)
            return True
        return False

    # ------------------------------------------------------------------ one message
    def check(self, names, velocity, effort, position):
        """
        Check one message.

        Returns (names, qd, tau, q) in the configured joint order (``q`` None unless the
        learner uses positions), or the rejection reason (a string).
        """
        cfg = self._settings()
        if velocity is None or effort is None:
            return 'empty'
        try:
            v = np.asarray(velocity, dtype=float).ravel()
            e = np.asarray(effort, dtype=float).ravel()
            p = None
            if self._positions:
                p = np.asarray([] if position is None else position, dtype=float).ravel()
        except (TypeError, ValueError, OverflowError):
            return 'non_finite'
        try:
            names = list(names) if names is not None else []
            if len(set(names)) != len(names):
                return 'duplicate_name'
        except TypeError:                      # not iterable, or unhashable entries
            return 'bad_names'
        if not all(isinstance(n, str) for n in names):
            return 'bad_names'
        if v.size == 0 or e.size == 0:
            return 'empty'
        if p is not None and p.size == 0:
            return 'missing_position'
        if v.size != e.size or (names and len(names) != v.size) or \
                (p is not None and p.size != v.size):
            return 'length_mismatch'
        if self._names is not None and names:
            idx = self._joint_order(tuple(names))
            if idx is None:
                return 'missing_joint'
            v, e, names = v[idx], e[idx], list(self._names)
            p = None if p is None else p[idx]
        elif self._names is not None and not names and cfg.joints:
            return 'missing_joint'
        if self._N is None and v.size > cfg.max_joints:
            return 'too_many_joints'
        if self._N is not None and v.size != self._N:
            return 'dimension_mismatch'
        if not (np.isfinite(v).all() and np.isfinite(e).all() and
                (p is None or np.isfinite(p).all())):
            return 'non_finite'
        if (np.abs(v) > cfg.max_abs_velocity).any() or (np.abs(e) > cfg.max_abs_effort).any():
            return 'out_of_range'
        if cfg.effort_scale:
            e = e * _scale(cfg)
        return names, v, e, p

    # ------------------------------------------------------------------ a batch
    def batch_ready(self, names: tuple, velocity, effort, position) -> bool:
        """Tell whether a batch can be checked as arrays (joints known, lengths alike)."""
        n = len(names)
        return self._N is not None and self._names is not None and bool(n) and \
            velocity.shape[1] == n and effort.shape[1] == n and \
            (position is None or position.shape[1] == n)

    def check_batch(self, sec: np.ndarray, nsec: np.ndarray, names: tuple, velocity: np.ndarray,
                    effort: np.ndarray, position: Optional[np.ndarray]):
        """
        Check k like messages (``batch_ready``) as ``check`` checks each.

        ``names`` (n,) non-empty, ``velocity`` and ``effort`` (k, n), ``position`` (k, n) or
        None. Returns (reasons (k,) of '' (accepted) or the rejection reason, or None when every
        message is accepted; stamps (k,) [s]; the accepted rows' (qd, tau, q) in the joint
        order). The stamp is ``sec + 1e-9 * nanosec`` as ``stamp_seconds`` computes it (the same
        float).
        """
        k = len(sec)
        stamps = sec.astype(np.float64)
        stamps += 1e-9 * nsec.astype(np.float64)
        reason = self._content(names, position)
        if isinstance(reason, str):
            return np.full(k, reason, dtype=object), stamps, None
        idx = reason
        if idx is not None:             # (take: rows stay contiguous, as the message path's)
            velocity, effort = velocity.take(idx, axis=1), effort.take(idx, axis=1)
        p = None
        if self._positions:
            p = position if idx is None else position.take(idx, axis=1)
        cfg = self._settings()
        # the usual case, for the whole batch at once: every value finite and in range (the
        # largest magnitude is NaN if any is, and NaN compares False), every stamp after the
        # epoch
        if np.abs(velocity).max() <= cfg.max_abs_velocity and \
                np.abs(effort).max() <= cfg.max_abs_effort and sec.min() >= 0 and \
                (p is None or np.isfinite(p).all()):
            return None, stamps, (velocity, _torque(effort, cfg), p)
        fine = (np.abs(velocity) <= cfg.max_abs_velocity).all(axis=1) & \
            (np.abs(effort) <= cfg.max_abs_effort).all(axis=1)
        if p is not None:
            fine &= np.isfinite(p).all(axis=1)
        finite = np.isfinite(velocity).all(axis=1) & np.isfinite(effort).all(axis=1)
        if p is not None:
            finite &= np.isfinite(p).all(axis=1)
        reasons = np.full(k, '', dtype=object)
        reasons[~finite] = 'non_finite'
        reasons[finite & ~fine] = 'out_of_range'
        bad_stamp = ~(np.isfinite(stamps) & (stamps >= 0.0))
        reasons[(reasons == '') & bad_stamp] = 'bad_stamp'
        ok = reasons == ''
        return reasons, stamps, (velocity[ok], _torque(effort[ok], cfg),
                                 None if p is None else p[ok])

    def _joint_order(self, names: tuple):
        """
        Return where the estimator's joints are in ``names`` (int array, shape (N,)), or None.

        None: one of them is missing. The last name list's answer is kept (``_order``): a
        driver sends the same names in every message.
        """
        cached = self._order
        if cached is not None and cached[0] == names:
            return cached[1]
        pos = {n: i for i, n in enumerate(names)}
        try:
            idx = np.array([pos[n] for n in self._names], dtype=np.intp)
        except KeyError:
            return None
        self._order = (names, idx)
        return idx

    def _content(self, names: tuple, position):
        """Return the reason every message is rejected for, or the joint order (None: as is)."""
        cached = self._order
        known = cached is not None and cached[0] == names       # (their names had no duplicate)
        if not known and len(set(names)) != len(names):
            return 'duplicate_name'
        if self._positions and position is None:
            return 'missing_position'
        idx = self._joint_order(names)
        if idx is None:
            return 'missing_joint'
        if idx.size != self._N:
            return 'dimension_mismatch'
        cached = self._order
        if len(cached) < 3:             # None: the messages' order is the estimator's (as is)
            same = idx.size == len(names) and bool((idx == np.arange(idx.size)).all())
            cached = self._order = cached[:2] + (None if same else idx,)
        return cached[2]


def _scale(cfg) -> np.ndarray:
    """Return ``effort_scale`` as an array: (1,) for every joint, or (N,) per joint."""
    return np.asarray(cfg.effort_scale, float)


def _torque(effort: np.ndarray, cfg) -> np.ndarray:
    """Return the accepted efforts (k, N) as joint torque (``effort_scale``; as is without)."""
    return effort * _scale(cfg) if cfg.effort_scale else effort

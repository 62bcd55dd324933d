"""
The friction residual ``effort - tau_rb(q, qd, qdd_hat)`` of a joint-state stream.

This is what the estimator learns on a real arm (docs/CONTRACTS.md, "Robot front end"): the
measured joint torque minus the rigid-body torque, i.e. friction plus sensor bias plus noise.
``qdd_hat`` comes from :class:`~dgp_ros.dynamics.filter.AccelFilter`, centred on the sample, so
the residual of a sample is delayed by the filter's half window but not smeared over time.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from .filter import AccelFilter

__all__ = ['FrictionResidual', 'ResidualSample']


class ResidualSample(NamedTuple):
    """One residual sample; arrays (N,) in the selected joint order."""

    stamp_s: float
    """Stamp of the sample [s]."""
    q: np.ndarray | None
    """Measured positions [rad] (None if none were given without inverse dynamics)."""
    qd: np.ndarray
    """Measured velocities [rad/s]."""
    qdd: np.ndarray | None
    """Estimated accelerations [rad/s^2]; None without inverse dynamics (not needed)."""
    effort: np.ndarray
    """Measured joint torques [N m]."""
    tau_rb: np.ndarray
    """Rigid-body torque ``M qdd + C qd + g`` at (q, qd, qdd) [N m]; zeros without inverse
    dynamics."""
    residual: np.ndarray
    """``effort - tau_rb`` [N m]: friction + bias + noise."""


class FrictionResidual:
    """
    Streaming friction residual of ``(stamp, q, qd, effort)`` samples.

    Parameters
    ----------
    inverse_dynamics : callable or None
        ``f(q, qd, qdd) -> tau_rb`` with shapes (N,) / (k, N) (see
        :func:`~dgp_ros.dynamics.inverse.make_inverse_dynamics`). None: the effort already is the
        damping force; samples pass through at once with ``residual = effort``.
    filter : AccelFilter, optional
        Acceleration filter (default ``AccelFilter()``); unused without inverse dynamics.

    Notes
    -----
    Counters: ``samples_in``, ``samples_out``, ``negative_power`` (output samples with
    ``qd . residual < 0``: friction is passive, so more than a few percent of these means a wrong
    model, a torque bias or a sign convention problem), and from the filter ``restarts`` and
    ``dropped``.

    """

    def __init__(self, inverse_dynamics: Callable | None = None,
                 filter: AccelFilter | None = None):  # noqa: A002 - the brief's name
        self.inverse_dynamics = inverse_dynamics
        self.filter = None if inverse_dynamics is None else (
            filter if filter is not None else AccelFilter())
        self.samples_in = self.samples_out = self.negative_power = 0

    @property
    def delay_s(self) -> float:
        """How long outputs trail inputs [s]: 0 without inverse dynamics, else the filter's."""
        return 0.0 if self.filter is None else self.filter.delay_s

    @property
    def restarts(self) -> int:
        """Filter restarts: backwards stamps and gaps."""
        return 0 if self.filter is None else self.filter.restarts

    @property
    def dropped(self) -> int:
        """Wanted samples that got no residual (see :class:`AccelFilter`)."""
        return 0 if self.filter is None else self.filter.dropped

    @property
    def negative_power_fraction(self) -> float:
        """``negative_power / samples_out`` (0 before the first output)."""
        return self.negative_power / self.samples_out if self.samples_out else 0.0

    def push(self, stamp_s: float, q, qd, effort, want: bool = True) -> list[ResidualSample]:
        """
        Add one joint-state sample; return the residual samples that are complete.

        Parameters
        ----------
        stamp_s : float
            Stamp [s].
        q, qd, effort : array_like, (N,)
            Positions [rad], velocities [rad/s], joint torques [N m], selected joint order.
            ``q`` may be None when there is no inverse dynamics.
        want : bool
            Whether this sample's residual is needed; the others only feed the filter.

        Returns
        -------
        list of ResidualSample
            Zero or more samples, stamps increasing, each ``delay_s`` (or a little more) old;
            without inverse dynamics this sample itself if wanted.

        """
        self.samples_in += 1
        if not want:   # only feeds the filter's windows (which checks qd)
            out = [] if self.filter is None else self._residuals(
                self.filter.push(stamp_s, qd, want=False))
        else:
            qd = np.array(qd, dtype=float)
            effort = np.array(effort, dtype=float)
            if effort.shape != qd.shape or qd.ndim != 1:
                raise ValueError(f'qd and effort must have one shape (N,), got {qd.shape} and '
                                 f'{effort.shape}')
            if self.filter is None:
                q = None if q is None else np.array(q, dtype=float)
                out = [ResidualSample(float(stamp_s), q, qd, None, effort, np.zeros_like(effort),
                                      effort)]
            elif q is None:
                raise ValueError('q (joint positions) is needed for the inverse dynamics')
            else:
                out = self._residuals(self.filter.push(
                    stamp_s, qd, want=True, payload=(np.array(q, dtype=float), effort)))
        self.samples_out += len(out)
        self.negative_power += sum(float(s.qd @ s.residual) < 0.0 for s in out)
        return out

    def _residuals(self, acc: list) -> list[ResidualSample]:
        """
        Residual samples of the filter outputs ``acc`` (payload = (q, effort)).

        One batched inverse-dynamics call.
        """
        if not acc:
            return []
        Q = np.array([a.payload[0] for a in acc])
        QD = np.array([a.qd for a in acc])
        QDD = np.array([a.qdd for a in acc])
        tau = self.inverse_dynamics(Q, QD, QDD)
        return [ResidualSample(a.t, Q[i], QD[i], QDD[i], a.payload[1], tau[i],
                               a.payload[1] - tau[i]) for i, a in enumerate(acc)]

"""
The simulated arm in closed loop: a reference path, the arm integrated forward, a tracking law.

Pure numpy and pinocchio; no ROS (the nodes ``arm_loop`` and ``controller`` wrap these, and
``apps.loop_run`` runs them in one process).

* :func:`reference_path`: the smooth exciting path the controller tracks: per joint a Fourier
  series (5 harmonics of ``1 / cycle_s``) inside the URDF limits with a common standstill every
  ``1 / (2 pause_hz)`` s, as the open-loop arm's (``arm_sim.simulate_arm``), analytic q, qd, qdd.
* :class:`ClosedLoopArm`: the true arm (the example-robot-data URDF **with** the payload it lacks
  and the realistic friction outside the estimator's prior family) integrated at ``dt`` (1 ms) by
  a linearly implicit Euler step: ``(M + dt B) dqd = dt (tau - h(q, qd) - f(qd, q))``, ``B`` the
  friction's slope ``df/dqd`` (diagonal, >= 0, so the stiff smooth sign of the Coulomb term
  neither oscillates nor needs a smaller step), then ``q += dt qd``. The measurement it returns
  is the driver's: ``q`` exact (encoders), ``qd`` + white noise, effort = the joint torque applied
  during the last step + the sensor bias + white noise (as ``simulate_arm``'s effort).
* :class:`TrackingController`: the example controller's law, joint space,
  ``tau = tau_rb_urdf(q_r, qd_r, qdd_r) + M_urdf(q) (w^2 (q_r - q) + 2 zeta w (qd_r - qd))
  + k * comp``: the URDF's RNEA at the reference (no payload) plus a PD whose gains are the
  URDF's mass matrix times a critically damped ``w = 2 pi bandwidth_hz`` (diagonal gains on a
  7-joint arm whose mass matrix has eigenvalues from 0.006 to 4 kg m^2 are unstable at 1 kHz
  for any useful stiffness), with ``comp`` from :class:`HeldEstimate` (zero-order hold of the
  newest answer, matched by joint name, ignored when older than a timeout, counted).

Units: rad, rad/s, rad/s^2, N m, s. Arrays (N,) per sample, joints in ``ARM_JOINTS`` order.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from .arm_sim import (_exciting_coefficients, _warp, ARM_JOINTS, example_robot_urdf,
                      fourier_trajectory, FRICTION_TABLES, SIGN_VELOCITY)
from .inverse import UrdfInverseDynamics
from .realistic import (DEFAULT_PAYLOAD_KG, payload_inverse_dynamics, PAYLOAD_MOUNT,
                        realistic_friction)

__all__ = ['reference_path', 'ClosedLoopArm', 'HeldEstimate', 'TrackingController',
           'DT']

DT = 1e-3
"""Integration and control period [s] (1 kHz)."""


class reference_path:                                          # noqa: N801 - used as a function
    """
    The reference the controller tracks: ``ref(t) -> (q, qd, qdd)``, (N,) each (module doc).

    Parameters
    ----------
    robot : str
        ``'panda'`` or ``'ur5'``.
    seed : int
        The path's coefficients (the same draw as ``simulate_arm``'s trajectory stream).
    cycle_s : float
        Period of the path [s].
    pause_hz : float
        Standstills (``simulate_arm``'s ``pause_hz``); 0 = none.

    """

    def __init__(self, robot: str = 'panda', seed: int = 0, cycle_s: float = 10.0,
                 pause_hz: float = 0.2, harmonics: int = 5):
        dyn = UrdfInverseDynamics(urdf_file=example_robot_urdf(robot), joints=ARM_JOINTS[robot])
        rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[0])
        vmax = np.minimum(2.0, 0.7 * dyn.velocity_limit) / (2.0 if pause_hz > 0 else 1.0)
        self.base_hz, self.pause_hz = 1.0 / cycle_s, pause_hz
        self.coef, self.q0 = _exciting_coefficients(rng, dyn.lower, dyn.upper, vmax,
                                                    self.base_hz, harmonics)

    def __call__(self, t):
        """Return q, qd, qdd at times ``t`` (scalar or (k,)) [s]: (N,) or (k, N) each."""
        tt = np.atleast_1d(np.asarray(t, dtype=float))
        s, ds, dds = _warp(tt, self.pause_hz)
        q, qs, qss = fourier_trajectory(s, self.coef, self.q0, self.base_hz)
        qd = qs * ds[:, None]
        qdd = qss * (ds ** 2)[:, None] + qs * dds[:, None]
        if np.ndim(t) == 0:
            return q[0], qd[0], qdd[0]
        return q, qd, qdd


class ClosedLoopArm:
    """
    The true arm, stepped by joint torque commands (module docstring).

    Parameters
    ----------
    robot : str
        ``'panda'`` or ``'ur5'``.
    q0, qd0 : array_like, (N,)
        Initial state [rad], [rad/s].
    seed : int
        Sensor noise stream.
    payload_kg : float, optional
        Mass at the flange the URDF lacks [kg]; None = ``DEFAULT_PAYLOAD_KG[robot]``.
    friction : str
        ``'realistic'`` (outside the prior family), ``'table'`` (the prior's family) or
        ``'none'``.
    bias : bool
        Add ``FRICTION_TABLES``' per-joint sensor bias to the measured effort.
    noise_sd, velocity_noise_sd : float
        White noise of the measured torque [N m] and velocity [rad/s].
    dt : float
        Step [s].

    """

    def __init__(self, robot: str, q0, qd0=None, seed: int = 0,
                 payload_kg: Optional[float] = None, friction: str = 'realistic',
                 bias: bool = True, noise_sd: float = 0.3, velocity_noise_sd: float = 0.003,
                 dt: float = DT):
        names = ARM_JOINTS[robot]
        self.robot, self.names, self.dt = robot, names, float(dt)
        mass = DEFAULT_PAYLOAD_KG[robot] if payload_kg is None else float(payload_kg)
        frame, offset = PAYLOAD_MOUNT[robot]
        self._dyn = payload_inverse_dynamics(example_robot_urdf(robot), names, frame, mass,
                                             offset)
        import pinocchio as pin
        self._pin = pin
        self._idx = self._dyn._idx_v
        self.payload_kg = mass
        self.friction = friction
        self.bias = FRICTION_TABLES[robot][:, 4].copy() if bias else np.zeros(len(names))
        self.noise_sd, self.velocity_noise_sd = float(noise_sd), float(velocity_noise_sd)
        self._rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
        self.q = np.array(q0, dtype=float)
        self.qd = np.zeros(len(names)) if qd0 is None else np.array(qd0, dtype=float)
        self.t, self.steps = 0.0, 0
        self.tau = np.zeros(len(names))          # the torque applied during the last step
        self.last_friction = np.zeros(len(names))

    def _friction(self, qd, grav) -> np.ndarray:
        if self.friction == 'realistic':
            return realistic_friction(self.robot, qd, grav, SIGN_VELOCITY)
        if self.friction == 'table':
            from .arm_sim import friction_truth
            return friction_truth(self.robot, qd)
        return np.zeros_like(qd)

    def _rigid(self, q, qd):
        """Return M (N, N), the bias forces h = C qd + g (N,) and g (N,) at (q, qd)."""
        pin, model, data, idx = self._pin, self._dyn.model, self._dyn.data, self._idx
        v = np.zeros(model.nv)
        v[idx] = qd
        pin.computeAllTerms(model, data, self._dyn._config(q), v)
        M = np.triu(data.M) + np.triu(data.M, 1).T
        return M[np.ix_(idx, idx)], np.array(data.nle)[idx], np.array(data.g)[idx]

    def step(self, tau) -> None:
        """Apply ``tau`` (N,) [N m] for one step ``dt`` (linearly implicit Euler, module doc)."""
        tau = np.asarray(tau, dtype=float)
        M, h, g = self._rigid(self.q, self.qd)
        eps = 1e-6
        # the friction and its slope df/dqd (each joint's depends on its own velocity only)
        f3 = self._friction(self.qd + np.array([[0.0], [eps], [-eps]]), np.tile(g, (3, 1)))
        f, slope = f3[0], (f3[1] - f3[2]) / (2 * eps)
        L = np.linalg.cholesky(M + self.dt * np.diag(np.maximum(slope, 0.0)))
        dqd = np.linalg.solve(L.T, np.linalg.solve(L, self.dt * (tau - h - f)))
        self.qd = self.qd + dqd
        self.q = self.q + self.dt * self.qd
        self.steps += 1
        # the stamp a message carries, read back as the message path reads it (messages.py):
        # the same float in process and over DDS
        sec, nsec = divmod(int(round(self.steps * self.dt * 1e9)), 1_000_000_000)
        self.t = sec + 1e-9 * nsec
        self.tau = tau.copy()
        self.last_friction = f

    def measure(self):
        """Return the sample now: t [s], q (N,), measured qd (N,), measured effort (N,)."""
        n = len(self.names)
        qd = self.qd + self._rng.normal(0.0, self.velocity_noise_sd, n)
        effort = self.tau + self.bias + self._rng.normal(0.0, self.noise_sd, n)
        return self.t, self.q.copy(), qd, effort


class HeldEstimate:
    """
    Zero-order hold of a per-joint estimate, matched by name, dropped when stale.

    Parameters
    ----------
    names : sequence of str
        The controller's joints (N,).
    timeout_s : float
        An estimate older than this [s of the controller's clock] is not used.

    ``update(stamp_s, names, values)`` keeps the newest (an older stamp than the held one is
    ignored); a message that lacks one of the controller's joints or has a non-finite value is
    refused and counted (``refused``). ``value(now_s)`` returns the held values (N,) in the
    controller's order, or zeros when there is none or it is stale (``stale`` counts those calls).

    """

    def __init__(self, names: Sequence[str], timeout_s: float):
        self.names = list(names)
        self.timeout_s = float(timeout_s)
        self._index = {}
        self.stamp: Optional[float] = None
        self.values = np.zeros(len(self.names))
        self.received = self.refused = self.stale = self.used = 0

    def update(self, stamp_s: float, names: Sequence[str], values) -> bool:
        """Take an answer; True if it is now the held one."""
        self.received += 1
        key = tuple(names)
        order = self._index.get(key)
        if order is None:
            pos = {n: i for i, n in enumerate(names)}
            if not all(n in pos for n in self.names):
                self.refused += 1
                return False
            order = self._index[key] = np.array([pos[n] for n in self.names])
        v = np.asarray(values, dtype=float)
        if v.shape != (len(names),) or not np.all(np.isfinite(v)):
            self.refused += 1
            return False
        if self.stamp is not None and stamp_s < self.stamp:
            return False
        self.stamp, self.values = float(stamp_s), v[order]
        return True

    def value(self, now_s: float) -> np.ndarray:
        """Return the held values (N,) if fresh at ``now_s`` [s], else zeros (``stale``)."""
        if self.stamp is None:
            return np.zeros(len(self.names))
        if now_s - self.stamp > self.timeout_s:
            self.stale += 1
            return np.zeros(len(self.names))
        self.used += 1
        return self.values


class TrackingController:
    """
    The example controller's law (module docstring).

    Parameters
    ----------
    robot : str
        ``'panda'`` or ``'ur5'``: the URDF (without payload) of the feed-forward, joint order.
    bandwidth_hz : float
        ``w / (2 pi)`` of the PD [Hz].
    damping_ratio : float
        ``zeta`` of the PD.
    k : float
        Gain of the compensation feed-forward (1 = the estimate as is).
    effort_limit : array_like (N,), optional
        Commands are clipped to +-this [N m]; None = the URDF's effort limits.

    """

    def __init__(self, robot: str, bandwidth_hz: float = 4.0, damping_ratio: float = 1.0,
                 k: float = 1.0, effort_limit=None):
        self.names = ARM_JOINTS[robot]
        self._dyn = UrdfInverseDynamics(urdf_file=example_robot_urdf(robot), joints=self.names)
        import pinocchio as pin
        self._pin = pin
        w = 2.0 * np.pi * float(bandwidth_hz)
        self.kp, self.kd = w * w, 2.0 * float(damping_ratio) * w
        self.k = float(k)
        lim = self._dyn.effort_limit if effort_limit is None else effort_limit
        self.limit = np.where(np.asarray(lim, float) > 0, lim, np.inf)
        self.injected_j = 0.0       # energy the compensation put in: sum dt qd . k comp [J]
        self.clipped = 0

    def feedforward(self, q_r, qd_r, qdd_r) -> np.ndarray:
        """Return the URDF's rigid-body torque at the reference (N,) [N m]."""
        return self._dyn(q_r, qd_r, qdd_r)

    def mass(self, q) -> np.ndarray:
        """Return the URDF's mass matrix at ``q`` (N, N) [kg m^2]."""
        d, idx = self._dyn, self._dyn._idx_v
        M = np.array(self._pin.crba(d.model, d.data, d._config(np.asarray(q, float))))
        M = np.triu(M) + np.triu(M, 1).T
        return M[np.ix_(idx, idx)]

    def command(self, q, qd, ref, comp=None, dt: float = DT) -> np.ndarray:
        """
        Return the torque (N,) [N m] for the measured q, qd (N,) and ``ref`` (q, qd, qdd).

        ``comp`` (N,) [N m] is added times ``k`` (None: no compensation); the energy it injects
        over the step, ``dt qd . k comp`` [J], is summed in ``injected_j``.
        """
        q_r, qd_r, qdd_r = ref
        pd = self.mass(q) @ (self.kp * (q_r - q) + self.kd * (qd_r - qd))
        tau = self.feedforward(q_r, qd_r, qdd_r) + pd
        if comp is not None:
            c = self.k * np.asarray(comp, float)
            tau = tau + c
            self.injected_j += dt * float(qd @ c)
        out = np.clip(tau, -self.limit, self.limit)
        self.clipped += int(np.any(out != tau))
        return out

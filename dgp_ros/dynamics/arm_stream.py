"""
The robot demo's arm as a real driver's ``/joint_states`` stream (pure numpy; no ROS).

:func:`demo_arm` simulates the arm of ``dgp-demo --robot``: realistic friction outside the
estimator's prior family, a payload its URDF does not have, the sensor bias, torque and velocity
noise and jittered 1 kHz stamps (:func:`~dgp_ros.dynamics.arm_sim.simulate_arm`). The arm
repeats a task cycle: a Fourier path of base frequency ``base_hz`` (default 0.1 Hz: a 10 s
cycle) with a common standstill every 5 s. ``base_hz = 1 / duration`` makes the whole run one
path that never repeats: the last part of the run is then a part of the path the arm has not
travelled yet (and partly at velocities it has not reached).

:class:`DriverStream` lays the samples out as the arm's driver publishes them: every joint of
the robot by name, the Panda's with its two finger joints appended (franka_ros order), the UR5's
in the ``ur_robot_driver`` order (``shoulder_pan_joint`` last); the estimator selects and orders
them with its ``joints`` parameter. :meth:`DriverStream.due` says which samples are due at a
wall-clock time: a publisher streams the precomputed run at real time (or faster) in batches.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .arm_sim import ARM_JOINTS, simulate_arm
from .realistic import DEFAULT_PAYLOAD_KG

__all__ = ['DRIVER_EXTRA', 'driver_order', 'demo_arm', 'DriverStream']

DRIVER_EXTRA = {'panda': ('panda_finger_joint1', 'panda_finger_joint2'), 'ur5': ()}
"""Joints a driver publishes besides the arm's (the Panda's gripper fingers)."""

_FINGER = (0.02, 0.0, 0.1)       # a closed gripper holding the part: position [m], v, effort [N]


def driver_order(robot: str) -> list:
    """Return the joint names in the order the robot's driver publishes them."""
    names = list(ARM_JOINTS[robot])
    if robot == 'ur5':               # ur_robot_driver publishes shoulder_pan_joint last
        return names[1:] + names[:1]
    return names + list(DRIVER_EXTRA[robot])


def demo_arm(robot: str, duration_s: float, seed: int = 0, payload_kg: Optional[float] = None,
             friction: str = 'realistic', rate_hz: float = 1000.0,
             base_hz: float = 0.1, coupled_wrist: float = 0.0) -> dict:
    """
    Simulate the robot demo's run (module docstring).

    Parameters
    ----------
    robot : str
        ``'panda'`` or ``'ur5'``.
    duration_s : float
        The whole run [s] (learned part and held-out part).
    seed : int
        Trajectory, jitter and noise.
    payload_kg : float, optional
        Payload at the flange [kg]; None = :data:`~dgp_ros.dynamics.realistic.DEFAULT_PAYLOAD_KG`.
    friction : str
        ``'realistic'`` or ``'table'`` (the estimator's prior family), see ``simulate_arm``.
    rate_hz : float
        Sample rate [Hz].
    base_hz : float
        Base frequency of the path [Hz] (> 0): the task cycle is ``1 / base_hz`` s.
    coupled_wrist : float
        Coulomb level [N m] of a motor driving the last two joints together (``simulate_arm``).

    Returns
    -------
    dict
        ``simulate_arm``'s output (arrays (k, N) in ``ARM_JOINTS`` order, stamps ``t`` (k,) [s]
        from 0) with ``base_hz`` [Hz] added.

    """
    if not duration_s > 0:
        raise ValueError(f'duration_s must be > 0, got {duration_s!r}')
    if not base_hz > 0:
        raise ValueError(f'base_hz must be > 0, got {base_hz!r}')
    if payload_kg is None:
        payload_kg = DEFAULT_PAYLOAD_KG[robot]
    d = simulate_arm(robot, duration_s, rate_hz=rate_hz, seed=seed, friction=friction,
                     payload_kg=payload_kg, base_hz=base_hz, coupled_wrist=coupled_wrist)
    d['base_hz'] = base_hz
    return d


class DriverStream:
    """
    A simulated run in the driver's message layout, streamed by wall-clock time.

    Parameters
    ----------
    sim : dict
        :func:`demo_arm` (or ``simulate_arm``) output.
    until_s : float, optional
        Stream only the samples stamped before this [s] (None: all).

    Attributes
    ----------
    names : list of str
        Joint names of every message (:func:`driver_order`), M of them.
    stamps : numpy.ndarray, (k,)
        Stamps [s].
    position, velocity, effort : numpy.ndarray, (k, M)
        [rad], [rad/s], [N m] (finger joints: [m], [m/s], [N]).

    """

    def __init__(self, sim: dict, until_s: Optional[float] = None):
        robot = sim['robot']
        arm = list(sim['names'])
        self.names = driver_order(robot)
        k = len(sim['t']) if until_s is None else int(np.searchsorted(sim['t'], until_s))
        self.stamps = np.asarray(sim['t'][:k], dtype=float)
        cols = [arm.index(n) if n in arm else -1 for n in self.names]

        def lay(a, fill):
            out = np.full((k, len(cols)), fill, dtype=float)
            for c, i in enumerate(cols):
                if i >= 0:
                    out[:, c] = a[:k, i]
            return out
        self.position = lay(sim['q'], _FINGER[0])
        self.velocity = lay(sim['qd'], _FINGER[1])
        self.effort = lay(sim['effort'], _FINGER[2])
        self.sent = 0

    def __len__(self) -> int:
        """Return the number of samples k."""
        return self.stamps.size

    @property
    def finished(self) -> bool:
        """Every sample has been taken by :meth:`due`."""
        return self.sent >= len(self)

    def due(self, elapsed_s: float, real_time_factor: float = 1.0) -> range:
        """
        Take the samples due after ``elapsed_s`` wall seconds of streaming.

        Parameters
        ----------
        elapsed_s : float
            Wall time since the stream started [s].
        real_time_factor : float
            Stamp seconds per wall second; 0 = all at once.

        Returns
        -------
        range
            Indices of the samples not taken before whose stamp (from the first) is due.

        """
        if real_time_factor <= 0:
            end = len(self)
        else:
            t = self.stamps[0] + elapsed_s * real_time_factor if len(self) else 0.0
            end = int(np.searchsorted(self.stamps, t, side='right'))
        first, self.sent = self.sent, max(self.sent, end)
        return range(first, self.sent)

"""
Simulated joint states of a real arm (Panda, UR5) with known friction: test data and demo.

What a user's ``/joint_states`` looks like: the effort is the measured joint torque

    effort = M(q) qdd + C(q, qd) qd + g(q) + friction(qd) + bias + noise,

so gravity and inertia dominate it and its raw power ``qd . effort`` is negative on a large part
of the samples, while the residual after the rigid-body torque is passive up to the bias and the
noise. The rigid-body part is pinocchio's RNEA on the example-robot-data URDF (the same
computation as ``inverse_dynamics="urdf"``; an independent check of it is in the tests).

Friction per joint (smooth sign ``tanh(v / SIGN_VELOCITY)``, passive by construction:
``v * f(v) >= 0``)::

    f(v) = (coulomb + stribeck * exp(-(v / v_stribeck)^2)) * tanh(v / SIGN_VELOCITY) + viscous * v

with the per-joint values of :data:`FRICTION_TABLES` (fixed per robot, magnitudes of a Panda's
identified friction) and an optional constant sensor bias per joint (last column). This is the
estimator's prior family; ``friction='realistic'`` is friction outside it (direction asymmetry,
sub-linear viscous, pose-dependent) and ``payload_kg`` a mass at the flange that the URDF does
not have (both in ``realistic.py``); ``coupled_wrist`` a motor that drives the last two joints
together (:func:`coupled_wrist_friction`: friction on their velocities' sum, in both torques).

Trajectories: per joint a 5-harmonic Fourier series of base frequency 0.1 Hz with random
coefficients (by seed), scaled so that the position stays inside the URDF limits with a 15 %
margin (and within +-2.5 rad of the centre) and the velocity peaks at
min(2, 0.7 x the URDF velocity limit) rad/s unless the position bound is reached first;
q, qd, qdd are analytic. With ``pause_hz > 0`` the path is followed in warped time
``s(t) = t - sin(2 pi f t) / (2 pi f)`` (``ds/dt = 1 - cos(2 pi f t)``): every ``1 / f`` seconds
all joints slow down to a standstill together and speed up again, as in pick-and-place cycles. Near
those stops the torque noise outweighs the friction power, which gives the few percent of
non-passive samples a real friction log has.
"""
from __future__ import annotations

import glob
import os
import site
import sys

import numpy as np

from .inverse import UrdfInverseDynamics
from .realistic import payload_inverse_dynamics, PAYLOAD_MOUNT, realistic_friction

__all__ = ['ARM_JOINTS', 'FRICTION_TABLES', 'SIGN_VELOCITY', 'coupled_wrist_friction',
           'example_robot_urdf',
           'friction_truth', 'fourier_trajectory', 'negative_power_fraction', 'simulate_arm']

ARM_JOINTS = {
    'panda': tuple(f'panda_joint{i}' for i in range(1, 8)),
    'ur5': ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
            'wrist_2_joint', 'wrist_3_joint'),
}
_FALLBACK_PREFIXES = ('/opt/openrobots',)   # robotpkg installs
_URDF = {'panda': 'panda_description/urdf/panda.urdf',
         'ur5': 'ur_description/urdf/ur5_robot.urdf'}

SIGN_VELOCITY = 0.015
"""Velocity scale of the smooth sign of the Coulomb and Stribeck terms [rad/s]."""

# columns: coulomb [N m], stribeck excess [N m], stribeck velocity [rad/s],
#          viscous [N m s/rad], sensor bias [N m]
FRICTION_TABLES = {
    'panda': np.array([
        [0.80, 0.40, 0.08, 0.50, -0.17],   # panda_joint1
        [1.30, 0.50, 0.07, 0.60, -0.49],   # panda_joint2
        [0.70, 0.35, 0.08, 0.40, 0.06],    # panda_joint3
        [1.00, 0.45, 0.06, 0.45, -0.12],   # panda_joint4
        [0.45, 0.25, 0.10, 0.20, 0.04],    # panda_joint5
        [0.40, 0.20, 0.09, 0.15, -0.05],   # panda_joint6
        [0.30, 0.20, 0.05, 0.10, 0.03],    # panda_joint7
    ]),
    'ur5': np.array([
        [1.20, 0.45, 0.07, 0.55, -0.20],   # shoulder_pan_joint
        [1.30, 0.50, 0.06, 0.60, -0.45],   # shoulder_lift_joint
        [1.00, 0.40, 0.07, 0.45, 0.15],    # elbow_joint
        [0.45, 0.25, 0.09, 0.20, -0.05],   # wrist_1_joint
        [0.40, 0.20, 0.10, 0.15, 0.04],    # wrist_2_joint
        [0.30, 0.20, 0.08, 0.10, -0.03],   # wrist_3_joint
    ]),
}
"""Per robot, one row per joint of :data:`ARM_JOINTS`: coulomb, stribeck, v_stribeck, viscous,
bias (units above)."""


def _robot(robot: str) -> str:
    if robot not in ARM_JOINTS:
        raise ValueError(f'robot must be one of {sorted(ARM_JOINTS)}, got {robot!r}')
    return robot


def example_robot_urdf(robot: str = 'panda') -> str:
    """
    Path of the example-robot-data URDF of ``robot`` (``'panda'`` or ``'ur5'``).

    Searched in ``<site-packages>/cmeel.prefix/share/example-robot-data/robots`` (the pip wheel)
    of ``sys.prefix`` and the site directories, then ``<prefix>/share/example-robot-data/robots``
    for each prefix of ``AMENT_PREFIX_PATH`` (the ROS package) and ``/opt/openrobots``.

    Raises
    ------
    FileNotFoundError
        The package is not installed (the message says how to install it).

    """
    rel = _URDF[_robot(robot)]
    sub = os.path.join('share', 'example-robot-data', 'robots')
    roots = [os.path.join(d, 'cmeel.prefix', sub) for d in
             [*glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages')),
              *site.getsitepackages(), site.getusersitepackages()]]
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    roots += [os.path.join(p, sub) for p in [*prefixes, *_FALLBACK_PREFIXES]]
    for root in roots:
        path = os.path.join(root, rel)
        if os.path.isfile(path):
            return path
    raise FileNotFoundError(f'example-robot-data ({rel}) not found: pip install '
                            'example-robot-data (or apt install ros-jazzy-example-robot-data)')


def friction_truth(robot: str, qd) -> np.ndarray:
    """
    Return the simulated (passive) friction torque at velocities ``qd``, without the bias.

    Parameters
    ----------
    robot : str
        ``'panda'`` or ``'ur5'``.
    qd : array_like, (N,) or (k, N)
        Joint velocities [rad/s] in :data:`ARM_JOINTS` order.

    Returns
    -------
    numpy.ndarray, shape of ``qd``
        Friction torque [N m]; ``qd * f >= 0`` element-wise.

    """
    table = FRICTION_TABLES[_robot(robot)]
    v = np.asarray(qd, dtype=float)
    if v.shape[-1:] != (table.shape[0],):
        raise ValueError(f'qd must have shape (N,) or (k, N) with N = {table.shape[0]} for '
                         f'{robot}, got {v.shape}')
    fc, fs, vs, fv = table[:, 0], table[:, 1], table[:, 2], table[:, 3]
    return (fc + fs * np.exp(-(v / vs) ** 2)) * np.tanh(v / SIGN_VELOCITY) + fv * v


def coupled_wrist_friction(qd, coulomb: float) -> np.ndarray:
    """
    Friction of one motor driving an arm's last two joints together, as joint torques.

    The motor turns at ``m = qd[-2] + qd[-1]`` (a coupled transmission of ratio one); its
    friction ``f(m) = (c + 0.5 c exp(-(m / 0.08)^2)) tanh(m / SIGN_VELOCITY) + 0.5 c m``
    (c = ``coulomb`` [N m]) reaches both joints: ``tau = T^T f(T qd)``, T = [0 .. 0 1 1].
    Passive: ``qd . tau = m f(m) >= 0``, though neither joint's share is a function of its own
    velocity.

    qd : (N,) or (k, N) joint velocities [rad/s]; returns the torques [N m], shape of ``qd``.
    """
    v = np.asarray(qd, dtype=float)
    m = v[..., -2] + v[..., -1]
    c = float(coulomb)
    f = (c + 0.5 * c * np.exp(-(m / 0.08) ** 2)) * np.tanh(m / SIGN_VELOCITY) + 0.5 * c * m
    out = np.zeros_like(v)
    out[..., -2] = f
    out[..., -1] = f
    return out


def negative_power_fraction(qd, force) -> float:
    """Fraction of samples with ``qd . force < 0`` (rows of (k, N) arrays)."""
    return float(np.mean(np.einsum('kn,kn->k', np.atleast_2d(qd), np.atleast_2d(force)) < 0.0))


def fourier_trajectory(t, coef: np.ndarray, q0: np.ndarray, base_hz: float):
    """
    Positions, velocities, accelerations of a Fourier-series trajectory.

    ``qd_j(t) = sum_l a_jl cos(l w t) + b_jl sin(l w t)``, ``w = 2 pi base_hz``, ``q`` its integral
    plus ``q0`` and ``qdd`` its derivative.

    Parameters
    ----------
    t : array_like, (k,)
        Times [s].
    coef : numpy.ndarray, (2, N, L)
        ``a`` and ``b`` [rad/s] for N joints and L harmonics.
    q0 : numpy.ndarray, (N,)
        Position offsets [rad].
    base_hz : float
        Base frequency [Hz].

    Returns
    -------
    q, qd, qdd : numpy.ndarray, (k, N) each
        [rad], [rad/s], [rad/s^2].

    """
    a, b = coef
    w = 2.0 * np.pi * base_hz * np.arange(1, a.shape[1] + 1)       # (L,) [rad/s]
    phase = np.asarray(t, dtype=float)[:, None] * w                  # (k, L)
    c, s = np.cos(phase), np.sin(phase)
    q = q0 + (s / w) @ a.T - (c / w) @ b.T
    qd = c @ a.T + s @ b.T
    qdd = (-s * w) @ a.T + (c * w) @ b.T
    return q, qd, qdd


def _warp(t: np.ndarray, pause_hz: float):
    """Warped time ``s(t)`` and its first two derivatives (module docstring)."""
    if pause_hz <= 0.0:
        return t, np.ones_like(t), np.zeros_like(t)
    w = 2.0 * np.pi * pause_hz
    return t - np.sin(w * t) / w, 1.0 - np.cos(w * t), w * np.sin(w * t)


def _exciting_coefficients(rng, lower, upper, vmax, base_hz, harmonics, margin=0.15,
                           max_amplitude=2.5):
    """Random Fourier coefficients (2, N, L) and offsets (N,) scaled to the limits (module doc)."""
    n = lower.shape[0]
    coef = rng.standard_normal((2, n, harmonics))
    grid = np.linspace(0.0, 1.0 / base_hz, 4001)                     # one period
    q, qd, _ = fourier_trajectory(grid, coef, np.zeros(n), base_hz)
    lo, hi = q.min(axis=0), q.max(axis=0)
    centre = np.where(np.isfinite(lower) & np.isfinite(upper), 0.5 * (lower + upper), 0.0)
    half = np.minimum(0.5 * (upper - lower) * (1.0 - margin), max_amplitude)
    scale = np.minimum(half / (0.5 * (hi - lo)), vmax / np.abs(qd).max(axis=0))
    return coef * scale[:, None], centre - scale * 0.5 * (hi + lo)


def _friction_kind(friction) -> str:
    """``simulate_arm``'s ``friction`` argument as 'table', 'realistic' or 'none'."""
    if friction is True or friction == 'table':
        return 'table'
    if friction is False or friction in ('none', None):
        return 'none'
    if friction == 'realistic':
        return 'realistic'
    raise ValueError(f"friction must be True/'table', 'realistic' or False/'none', got "
                     f'{friction!r}')


def simulate_arm(robot: str = 'panda', duration_s: float = 20.0, rate_hz: float = 1000.0,
                 seed: int = 0, bias: bool = True, noise_sd: float = 0.3,
                 velocity_noise_sd: float = 0.003, jitter_sd_s: float = 50e-6,
                 friction=True, t0_s: float = 0.0, base_hz: float = 0.1,
                 harmonics: int = 5, pause_hz: float = 0.2, payload_kg: float = 0.0,
                 coupled_wrist: float = 0.0) -> dict:
    """
    Joint states of an arm following an exciting trajectory, with ground truth.

    Parameters
    ----------
    robot : str
        ``'panda'`` (7 joints) or ``'ur5'`` (6 joints), see :data:`ARM_JOINTS`.
    duration_s, rate_hz : float
        Length [s] and nominal sample rate [Hz].
    seed : int
        Trajectory, stamp jitter and noise (independent streams: the trajectory does not depend
        on the duration).
    bias : bool
        Add the per-joint sensor bias of :data:`FRICTION_TABLES` to the effort.
    noise_sd : float
        Torque-sensor noise, white Gaussian [N m].
    velocity_noise_sd : float
        Measured-velocity noise, white Gaussian [rad/s] (order of a differentiated encoder).
    jitter_sd_s : float
        Sampling-instant jitter [s], clipped to +-0.4 periods (stamps strictly increase). The
        signals are sampled at the stamps.
    friction : bool or str
        ``True`` or ``'table'``: the friction of :func:`friction_truth` (Coulomb + Stribeck +
        viscous, the estimator's prior family); ``'realistic'``: that of
        :func:`~dgp_ros.dynamics.realistic.realistic_friction` (direction asymmetry, ``|v|^0.6``
        viscous, exponential Stribeck, growing with the joint's true gravity torque: outside the
        prior family, and pose-dependent); ``False`` or ``'none'``: none.
    t0_s : float
        Nominal first stamp [s].
    base_hz : float
        Base frequency of the trajectory [Hz].
    harmonics : int
        Number of harmonics.
    pause_hz : float
        Rate of the common standstills [Hz] (0: none); see the module docstring. The peak
        velocity target is halved with pauses, since ``ds/dt`` reaches 2.
    payload_kg : float
        A payload at the flange [kg] (``realistic.PAYLOAD_MOUNT``) that the URDF does not have:
        it is in the measured effort (gravity and inertia), not in ``tau_rb_urdf``.
    coupled_wrist : float
        Coulomb level [N m] of a wrist motor that drives the last two joints together (a
        coupled transmission, :func:`coupled_wrist_friction`): its friction rides on their
        velocities' sum and shows in both joints' torques, beside their own (0: none).

    Returns
    -------
    dict
        ``robot`` (str), ``names`` (tuple of N joint names), ``rate_hz``; arrays ``t`` (k,) [s],
        ``q`` (k, N) [rad], ``qd`` (k, N) measured [rad/s], ``qd_true``, ``qdd`` (k, N) true
        [rad/s^2], ``effort`` (k, N) measured [N m], ``tau_rb`` (k, N) true rigid-body torque
        (with the payload), ``tau_rb_urdf`` (k, N) that of the URDF (without it), ``payload``
        (k, N) their difference and ``payload_gravity`` (k, N) its gravity part [N m] (zeros
        without a payload), ``friction`` (k, N) at the true velocity (and pose), ``bias`` (N,)
        [N m]; ``friction_model`` ('table', 'realistic' or 'none'), ``payload_kg``; and
        ``nonpassive_fraction`` (samples with ``qd . (effort - tau_rb) < 0``, measured ``qd``)
        and ``raw_negative_power_fraction`` (samples with ``qd . effort < 0``);
        ``nonpassive_fraction_per_joint`` (N,) (samples with ``qd_j (effort_j - tau_rb_j) < 0``:
        with several joints moving at once the sum rarely goes negative, a single joint does near
        its velocity reversals).

    """
    names = ARM_JOINTS[_robot(robot)]
    dyn = UrdfInverseDynamics(urdf_file=example_robot_urdf(robot), joints=names)
    traj_rng, jitter_rng, noise_rng = (np.random.default_rng(s)
                                       for s in np.random.SeedSequence(seed).spawn(3))
    vmax = np.minimum(2.0, 0.7 * dyn.velocity_limit) / (2.0 if pause_hz > 0 else 1.0)
    coef, q0 = _exciting_coefficients(traj_rng, dyn.lower, dyn.upper, vmax, base_hz, harmonics)
    k = int(round(duration_s * rate_hz))
    period = 1.0 / rate_hz
    jitter = np.clip(jitter_rng.normal(0.0, jitter_sd_s, k), -0.4 * period, 0.4 * period)
    jitter[0] = abs(jitter[0])             # no stamp before t0_s (a negative one is invalid)
    t = t0_s + np.arange(k) * period + jitter
    tau_s, ds, dds = _warp(t - t0_s, pause_hz)
    q, qs, qss = fourier_trajectory(tau_s, coef, q0, base_hz)
    qd_true = qs * ds[:, None]
    qdd = qss * (ds ** 2)[:, None] + qs * dds[:, None]
    kind = _friction_kind(friction)
    n = len(names)
    tau_rb_urdf = dyn(q, qd_true, qdd)
    tau_rb, pay_g, grav = tau_rb_urdf, np.zeros((k, n)), None
    if payload_kg or kind == 'realistic':
        frame, offset = PAYLOAD_MOUNT[robot]
        true = payload_inverse_dynamics(example_robot_urdf(robot), names, frame,
                                        float(payload_kg), offset)
        zero = np.zeros_like(q)
        grav = true(q, zero, zero)                      # the joints' true gravity torque
        if payload_kg:
            tau_rb = true(q, qd_true, qdd)
            pay_g = grav - dyn(q, zero, zero)
    if kind == 'table':
        fric = friction_truth(robot, qd_true)
    elif kind == 'realistic':
        fric = realistic_friction(robot, qd_true, grav, SIGN_VELOCITY)
    else:
        fric = np.zeros((k, n))
    if coupled_wrist:
        fric = fric + coupled_wrist_friction(qd_true, coupled_wrist)
    b = FRICTION_TABLES[robot][:, 4].copy() if bias else np.zeros(n)
    effort = tau_rb + fric + b + noise_rng.normal(0.0, noise_sd, (k, n))
    qd = qd_true + noise_rng.normal(0.0, velocity_noise_sd, (k, n))
    return {
        'robot': robot, 'names': names, 'rate_hz': float(rate_hz), 't': t, 'q': q, 'qd': qd,
        'qd_true': qd_true, 'qdd': qdd, 'effort': effort, 'tau_rb': tau_rb,
        'tau_rb_urdf': tau_rb_urdf, 'payload': tau_rb - tau_rb_urdf, 'payload_gravity': pay_g,
        'friction': fric, 'bias': b, 'friction_model': kind, 'payload_kg': float(payload_kg),
        'coupled_wrist': float(coupled_wrist),
        'nonpassive_fraction': negative_power_fraction(qd, effort - tau_rb),
        'nonpassive_fraction_per_joint': np.mean(qd * (effort - tau_rb) < 0.0, axis=0),
        'raw_negative_power_fraction': negative_power_fraction(qd, effort),
    }

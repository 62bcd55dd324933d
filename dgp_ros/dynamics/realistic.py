"""
What a real arm has that the estimator's prior family does not: realistic friction and a payload.

The estimator's prior is per joint Coulomb + viscous + Stribeck, symmetric in the direction of
motion and linear in the velocity (``friction+stribeck``). Measured joint friction of geared arms
is not (e.g. Bittencourt & Gunnarsson 2012 for the load, Gaz et al. 2019 for the Panda):

* **direction asymmetry**: the Coulomb and the viscous levels differ between positive and
  negative motion (``F_c+ != F_c-``, ``F_v+ != F_v-``);
* **non-linear viscous** friction, sub-linear in the speed (``sign(v) |v|^0.6``, lubricant
  shear thinning);
* a Stribeck dip with an **exponential** shape ``exp(-|v| / v_s)`` (the prior's is Gaussian);
* **load-dependent** friction in the gears: the Coulomb level grows with the torque the joint
  carries, here its gravity torque ``|g_j(q)|``, so the friction depends on the pose.

Per joint (``s(v) = tanh(v / SIGN_VELOCITY)``, a smooth sign)::

    f(v, q) = (c(v) + F_s exp(-|v| / v_s) + mu |g_j(q)|) s(v) + d(v) v (v^2 + v_e^2)^((a - 1) / 2)
    c(v)    = (F_c+ + F_c-) / 2 + (F_c+ - F_c-) / 2 * s(v)
    d(v)    = (F_v+ + F_v-) / 2 + (F_v+ - F_v-) / 2 * s(v)

which is passive, ``v f(v, q) >= 0`` for every pose: each bracket is positive and multiplies a
term of the sign of ``v``. ``v_e = SIGN_VELOCITY`` keeps the viscous term smooth at rest.

The **payload** is a mass at the flange (an object in the Panda's gripper, a tool on the UR5)
that the URDF the estimator is given does not have: the measured torque carries its gravity
(a conservative, pose-dependent torque) and its inertia, both part of the residual the
estimator learns. :func:`payload_inverse_dynamics` is the URDF model with the payload appended
(pinocchio ``appendBodyToJoint``).

Pure numpy (pinocchio only inside :func:`payload_inverse_dynamics`); no ROS.
"""
from __future__ import annotations

import numpy as np

from .inverse import UrdfInverseDynamics

__all__ = ['REALISTIC_TABLES', 'PAYLOAD_MOUNT', 'DEFAULT_PAYLOAD_KG', 'realistic_friction',
           'payload_inverse_dynamics']

# columns: F_c+, F_c- [N m], F_s [N m], v_s [rad/s], F_v+, F_v- [N m at 1 rad/s],
#          viscous exponent a [-], load coefficient mu [N m per N m of gravity torque]
REALISTIC_TABLES = {
    'panda': np.array([
        [0.960, 0.640, 0.400, 0.080, 0.625, 0.375, 0.600, 0.050],   # panda_joint1
        [1.560, 1.040, 0.500, 0.070, 0.750, 0.450, 0.600, 0.050],   # panda_joint2
        [0.840, 0.560, 0.350, 0.080, 0.500, 0.300, 0.600, 0.050],   # panda_joint3
        [1.200, 0.800, 0.450, 0.060, 0.562, 0.338, 0.600, 0.050],   # panda_joint4
        [0.540, 0.360, 0.250, 0.100, 0.250, 0.150, 0.600, 0.050],   # panda_joint5
        [0.480, 0.320, 0.200, 0.090, 0.188, 0.112, 0.600, 0.050],   # panda_joint6
        [0.360, 0.240, 0.200, 0.050, 0.125, 0.075, 0.600, 0.050],   # panda_joint7
    ]),
    'ur5': np.array([
        [1.440, 0.960, 0.450, 0.070, 0.688, 0.413, 0.600, 0.050],   # shoulder_pan_joint
        [1.560, 1.040, 0.500, 0.060, 0.750, 0.450, 0.600, 0.050],   # shoulder_lift_joint
        [1.200, 0.800, 0.400, 0.070, 0.562, 0.338, 0.600, 0.050],   # elbow_joint
        [0.540, 0.360, 0.250, 0.090, 0.250, 0.150, 0.600, 0.050],   # wrist_1_joint
        [0.480, 0.320, 0.200, 0.100, 0.188, 0.112, 0.600, 0.050],   # wrist_2_joint
        [0.360, 0.240, 0.200, 0.080, 0.125, 0.075, 0.600, 0.050],   # wrist_3_joint
    ]),
}
"""Per robot, one row per joint of ``ARM_JOINTS``: the parameters of the module docstring's
``f(v, q)``: the magnitudes of ``FRICTION_TABLES`` with +20 / -20 % Coulomb and +25 / -25 %
viscous friction between the directions of motion."""

PAYLOAD_MOUNT = {'panda': ('panda_hand_tcp', (0.0, 0.0, 0.0)),
                 'ur5': ('tool0', (0.0, 0.0, 0.08))}
"""Per robot: the frame the payload hangs on and its centre of mass in that frame [m]."""

DEFAULT_PAYLOAD_KG = {'panda': 0.5, 'ur5': 1.0}
"""The payload the robot demo carries [kg]: a part in the Panda's gripper (a sixth of its 3 kg
rating), a gripper on the UR5 (a fifth of its 5 kg)."""

_PAYLOAD_RADIUS = 0.04       # [m] the payload is a solid sphere of this radius


def realistic_friction(robot: str, qd, load_torque=None,
                       sign_velocity: float = 0.015) -> np.ndarray:
    """
    Realistic joint friction (module docstring) at velocities ``qd`` and joint loads.

    Parameters
    ----------
    robot : str or numpy.ndarray
        ``'panda'`` or ``'ur5'`` (its :data:`REALISTIC_TABLES` row per joint), or an (N, 8)
        table of the same columns.
    qd : array_like, (N,) or (k, N)
        Joint velocities [rad/s].
    load_torque : array_like, shape of ``qd``, optional
        The torque each joint carries [N m] (its gravity torque); None = unloaded.
    sign_velocity : float
        Velocity scale of the smooth sign and of the viscous term's smoothing [rad/s] (that of
        ``arm_sim.SIGN_VELOCITY``).

    Returns
    -------
    numpy.ndarray, shape of ``qd``
        Friction torque [N m]; ``qd * f >= 0`` element-wise.

    """
    if isinstance(robot, str):
        if robot not in REALISTIC_TABLES:
            raise ValueError(f'robot must be one of {sorted(REALISTIC_TABLES)}, got {robot!r}')
        robot = REALISTIC_TABLES[robot]
    table = np.asarray(robot, dtype=float)
    v = np.asarray(qd, dtype=float)
    if table.ndim != 2 or table.shape[1] != 8 or v.shape[-1:] != (table.shape[0],):
        raise ValueError(f'table must be (N, 8) and qd (N,) or (k, N); got {table.shape} and '
                         f'{v.shape}')
    load = np.zeros_like(v) if load_torque is None else np.asarray(load_torque, dtype=float)
    if load.shape != v.shape:
        raise ValueError(f'load_torque must have the shape of qd {v.shape}, got {load.shape}')
    fcp, fcn, fs, vs, fvp, fvn, a, mu = table.T
    s = np.tanh(v / sign_velocity)
    coulomb = 0.5 * (fcp + fcn) + 0.5 * (fcp - fcn) * s
    viscous = 0.5 * (fvp + fvn) + 0.5 * (fvp - fvn) * s
    level = coulomb + fs * np.exp(-np.abs(v) / vs) + mu * np.abs(load)
    return level * s + viscous * v * (v ** 2 + sign_velocity ** 2) ** (0.5 * (a - 1.0))


def payload_inverse_dynamics(urdf_file: str, joints, frame: str, mass_kg: float,
                             offset=(0.0, 0.0, 0.0)) -> UrdfInverseDynamics:
    """
    Return the URDF's inverse dynamics with a payload at a frame (the true arm of the demo).

    Parameters
    ----------
    urdf_file : str
        URDF path.
    joints : sequence of str
        Selected joints (as :class:`UrdfInverseDynamics`).
    frame : str
        Frame of the URDF the payload is attached to (e.g. ``panda_hand_tcp``).
    mass_kg : float
        Payload mass [kg], >= 0; a solid sphere of radius 4 cm.
    offset : sequence of 3 float
        Centre of mass of the payload in ``frame`` [m].

    Returns
    -------
    UrdfInverseDynamics
        ``tau_rb(q, qd, qdd)`` of the arm carrying the payload (same joints and shapes).

    Raises
    ------
    ValueError
        Negative mass or unknown frame (the message lists the frames of the last joint).

    """
    if not mass_kg >= 0.0:
        raise ValueError(f'mass_kg must be >= 0, got {mass_kg!r}')
    dyn = UrdfInverseDynamics(urdf_file=urdf_file, joints=joints)
    if mass_kg == 0.0:
        return dyn
    pin = dyn._pin
    model = dyn.model
    if not model.existFrame(frame):
        names = [f.name for f in model.frames]
        raise ValueError(f'frame {frame!r} not in the URDF; frames: {names[-8:]} (last 8)')
    fr = model.frames[model.getFrameId(frame)]
    parent = fr.parentJoint if hasattr(fr, 'parentJoint') else fr.parent
    at = fr.placement * pin.SE3(np.eye(3), np.asarray(offset, dtype=float))
    body = pin.Inertia.FromSphere(float(mass_kg), _PAYLOAD_RADIUS)
    model.appendBodyToJoint(parent, body, at)
    dyn.data = model.createData()
    return dyn

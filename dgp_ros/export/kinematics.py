"""
The gravity part of a URDF regressor correction as plain kinematics (no pinocchio at run time).

A :class:`~dgp_ros.dynamics.conservative.RegressorBasis` applies ``Y(q, 0, 0) theta``: the joint
torques that hold the links' masses and first moments ``theta`` (pinocchio's 10 inertial
parameters per joint, of which gravity sees the mass ``m`` and the first moment ``h = m c``, in
the joint's frame) against gravity. With the joint frames' poses ``(R_k, p_k)`` from forward
kinematics and the world axis ``z_i`` of revolute joint ``i``,

    tau_i = z_i . ((sum_{k in subtree(i)} (m_k p_k + R_k h_k) - p_i sum m_k) x (-g)),

which :func:`gravity_torque` evaluates in numpy and the generated header in C++.
:func:`chain_of` reads the constants (joint placements, axes, parents, gravity) from the
basis's reduced pinocchio model; joints other than revolute ones (aligned or not, bounded or
continuous) are refused with the joint's name and type. The export checks the result against
``basis.deploy`` at random poses before it writes a header.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

import numpy as np

from .errors import ExportError

__all__ = ['Chain', 'chain_of', 'gravity_torque', 'axis_rotation']

_AXES = {'X': (1.0, 0.0, 0.0), 'Y': (0.0, 1.0, 0.0), 'Z': (0.0, 0.0, 1.0)}


@dataclass
class Chain:
    """
    Kinematic tree of revolute joints, in pinocchio's joint order (parents before children).

    parent : (J,) index of each joint's parent joint, -1 for the base; coord : (J,) the model
    coordinate (0..N-1, the joint-name order of the model) of each joint; R0 (J, 3, 3), p0
    (J, 3): each joint's placement in its parent's frame [m]; axis (J, 3): unit rotation axis in
    the joint's frame; gravity (3,) [m/s^2] in the base frame.
    """

    parent: np.ndarray
    coord: np.ndarray
    R0: np.ndarray
    p0: np.ndarray
    axis: np.ndarray
    gravity: np.ndarray
    names: List[str]


def _axis_of(jm, name: str) -> np.ndarray:
    """Return the unit axis of a revolute joint model, or ExportError naming the joint type."""
    short = jm.shortname()
    for prefix in ('JointModelRUB', 'JointModelR'):
        if short.startswith(prefix) and short[len(prefix):] in _AXES:
            return np.array(_AXES[short[len(prefix):]])
    if short in ('JointModelRevoluteUnaligned', 'JointModelRevoluteUnboundedUnaligned'):
        a = np.asarray(jm.extract().axis, float).reshape(3)
        return a / np.linalg.norm(a)
    raise ExportError(f'joint {name!r} is a {short}: the header carries the gravity of '
                      'revolute joints only; export with --no-correction (the damping force '
                      'alone) and add the correction in your controller')


def chain_of(basis) -> Chain:
    """Read the :class:`Chain` of a ``RegressorBasis`` (its reduced pinocchio model)."""
    inv = basis._inv
    model = inv.model
    J = model.njoints - 1
    if basis.C != 10 * J:
        raise ExportError(f'the regressor has {basis.C} columns, not 10 per joint ({J})')
    v_to_coord = {int(v): j for j, v in enumerate(inv._idx_v)}
    parent, coord, R0, p0, axis, names = [], [], [], [], [], []
    for i in range(1, model.njoints):
        jm = model.joints[i]
        name = str(model.names[i])
        axis.append(_axis_of(jm, name))
        if jm.nv != 1 or int(jm.idx_v) not in v_to_coord:
            raise ExportError(f'joint {name!r} is not one of the model joints')
        parent.append(int(model.parents[i]) - 1)
        coord.append(v_to_coord[int(jm.idx_v)])
        M = model.jointPlacements[i]
        R0.append(np.array(M.rotation, float))
        p0.append(np.array(M.translation, float))
        names.append(name)
    return Chain(np.array(parent), np.array(coord), np.array(R0), np.array(p0),
                 np.array(axis), np.array(model.gravity.linear, float), names)


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) of ``angle`` [rad] about the unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    t = 1.0 - c
    return np.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])


def gravity_torque(chain: Chain, theta: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Return ``Y(q, 0, 0) theta`` at poses Q (k, N): (k, N) [N m] (module docstring)."""
    Q = np.atleast_2d(np.asarray(Q, float))
    J = chain.parent.size
    th = np.asarray(theta, float).reshape(J, 10)
    out = np.zeros(Q.shape)
    for row, q in enumerate(Q):
        R, p = np.zeros((J, 3, 3)), np.zeros((J, 3))
        for i in range(J):
            Rp, pp = (np.eye(3), np.zeros(3)) if chain.parent[i] < 0 else \
                (R[chain.parent[i]], p[chain.parent[i]])
            Rj = Rp @ chain.R0[i]
            p[i] = pp + Rp @ chain.p0[i]
            R[i] = Rj @ axis_rotation(chain.axis[i], q[chain.coord[i]])
        mass = th[:, 0].copy()
        mom = np.array([th[i, 0] * p[i] + R[i] @ th[i, 1:4] for i in range(J)])
        for i in range(J - 1, -1, -1):        # children after parents: accumulate upwards
            if chain.parent[i] >= 0:
                mass[chain.parent[i]] += mass[i]
                mom[chain.parent[i]] += mom[i]
        for i in range(J):
            z = R[i] @ chain.axis[i]
            out[row, chain.coord[i]] = z @ np.cross(mom[i] - p[i] * mass[i], -chain.gravity)
        del R, p
    return out

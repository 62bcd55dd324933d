"""
Conservative corrections of a rigid-body model: forces ``dV/dq`` of a learned potential V(q).

What a real arm's friction residual holds besides friction is mostly a rigid-body model error:
a gravity (mass, centre of mass, payload) error, the gradient of a potential, hence conservative:
it neither dissipates nor injects energy over a closed path, and it is learned *beside* the
damping force so that it never touches its passivity. Two bases, both linear in their
parameters ``theta`` (so they are fitted by least squares over the whole history, see
:mod:`~dgp_ros.dynamics.history`):

* :class:`RegressorBasis`: pinocchio's joint-torque regressor of a URDF (10 inertial parameters
  per link). Training uses the full regressor ``Y(q, qd, qdd)`` (its inertial and Coriolis
  columns absorb the identified model's mass-matrix error instead of biasing the gravity and
  friction fits); the correction that is *applied* is its gravity part ``Y(q, 0, 0) theta``,
  the gradient of the links' potential energy: conservative by construction.
* :class:`PotentialBasis`: model free, for a ``python:`` inverse-dynamics plugin without a URDF:
  the potential is a trigonometric polynomial of order 2 in the joint angles, its gradient the
  features. It is weighted by a strong ridge (a GP prior on V), because generic pose features
  extrapolate badly to poses not visited.

Every basis maps one sample to ``(train, deploy)``, two (N, C) arrays in N m per unit theta.
"""
from __future__ import annotations

import itertools
from typing import Optional, Sequence, Tuple

import numpy as np

from dgp_ros.gp.persistence import register_correction

__all__ = ['RegressorBasis', 'PotentialBasis', 'correction_basis', 'basis_from_dict',
           'Correction']


class RegressorBasis:
    """
    Gravity-model error of a URDF arm (see the module docstring).

    Parameters
    ----------
    inverse : UrdfInverseDynamics
        The reduced pinocchio model of the selected joints.
    source : str
        What the URDF is (reported on /diagnostics and in a saved model).
    urdf : str
        The URDF text, kept so that a saved model can rebuild the basis.

    """

    kind = 'regressor'
    #: ridge on theta, relative to nothing: (N m per unit)^2; results were flat from 1e-3 to 100
    RIDGE = 1e-3

    def __init__(self, inverse, source: str = '', urdf: str = ''):
        self._inv = inverse
        self.source = source
        self.urdf = urdf
        self.joints = list(inverse.joint_names)
        self.C = 10 * (inverse.model.njoints - 1)

    def _regressor(self, q, v, a) -> np.ndarray:
        inv, pin = self._inv, self._inv._pin
        idx = inv._idx_v
        vv, aa = np.zeros(inv.nv), np.zeros(inv.nv)
        vv[idx], aa[idx] = v, a
        Y = pin.computeJointTorqueRegressor(inv.model, inv.data, inv._config(q), vv, aa)
        return np.asarray(Y)[idx]

    def columns(self, q, qd, qdd) -> Tuple[np.ndarray, np.ndarray]:
        """Return the training and applied matrices of one sample, (N, C) each (see the module)."""
        z = np.zeros(len(self.joints))
        return self._regressor(q, qd, qdd), self._regressor(q, z, z)

    def deploy(self, Q: np.ndarray) -> np.ndarray:
        """Return the applied columns ``Y(q, 0, 0)`` for poses Q (k, N): (k, N, C)."""
        z = np.zeros(len(self.joints))
        return np.array([self._regressor(q, z, z) for q in np.atleast_2d(Q)])

    def to_dict(self) -> dict:
        return {'kind': self.kind, 'urdf': self.urdf, 'joints': self.joints,
                'source': self.source}

    def __deepcopy__(self, memo):
        return self                 # immutable once built (pinocchio's model is not copied)

    def __reduce__(self):
        return basis_from_dict, (self.to_dict(),)


class PotentialBasis:
    """Model-free potential: trigonometric polynomial of order 2 in q (module docstring)."""

    kind = 'potential'
    #: ridge on theta: a GP prior of variance 1 / RIDGE (N m)^2 per feature
    RIDGE = 100.0

    def __init__(self, N: int):
        self.N = int(N)
        self.source = 'trigonometric potential of order 2 in q (no URDF)'
        self.terms = []
        for order in (1, 2):
            for S in itertools.combinations(range(self.N), order):
                for fs in itertools.product((0, 1), repeat=order):
                    self.terms.append((S, fs))
        self.C = len(self.terms)

    def deploy(self, Q: np.ndarray) -> np.ndarray:
        """Return ``dV_k/dq`` at poses Q (k, N): (k, N, C)."""
        Q = np.atleast_2d(np.asarray(Q, float))
        s, c = np.sin(Q), np.cos(Q)
        G = np.zeros((Q.shape[0], self.N, self.C))
        for k, (S, fs) in enumerate(self.terms):
            val = [s[:, i] if f == 0 else c[:, i] for i, f in zip(S, fs)]
            der = [c[:, i] if f == 0 else -s[:, i] for i, f in zip(S, fs)]
            for a, i in enumerate(S):
                p = der[a].copy()
                for b, v in enumerate(val):
                    if b != a:
                        p *= v
                G[:, i, k] = p
        return G

    def columns(self, q, qd, qdd) -> Tuple[np.ndarray, np.ndarray]:
        """Return the training and applied matrices of one sample, (N, C) each: both dV/dq at q."""
        G = self.deploy(q)[0]
        return G, G

    def to_dict(self) -> dict:
        return {'kind': self.kind, 'N': self.N, 'source': self.source}


def _example_robot_for(names: Sequence[str]) -> Optional[str]:
    """URDF path of the example-robot-data arm whose movable joints include ``names``."""
    from .arm_sim import ARM_JOINTS, example_robot_urdf
    for robot in sorted(ARM_JOINTS):
        try:
            path = example_robot_urdf(robot)
            with open(path, encoding='utf-8') as f:
                text = f.read()
        except Exception:                       # noqa: BLE001 - not installed: no match
            continue
        if all(f'name="{n}"' in text for n in names):
            return path
    return None


def correction_basis(inverse, names: Sequence[str]):
    """
    Choose the conservative basis for a rigid-body model and joint names.

    A URDF inverse dynamics gives its regressor. Otherwise, when every joint name is a joint of
    a URDF of ``example-robot-data`` (a Panda's ``panda_joint1..7``, a UR's
    ``shoulder_pan_joint..``), that URDF's kinematics give the regressor (its inertial values
    are what is corrected, so they need not be the robot's); else the model-free
    :class:`PotentialBasis`. Returns None without inverse dynamics (no positions are learned).
    """
    if inverse is None or not names:
        return None
    from .inverse import UrdfInverseDynamics
    if isinstance(inverse, UrdfInverseDynamics):
        return RegressorBasis(inverse, 'regressor of the URDF of the rigid-body model',
                              getattr(inverse, 'urdf_text', ''))
    try:
        path = _example_robot_for(names)
        if path is not None:
            with open(path, encoding='utf-8') as f:
                text = f.read()
            inv = UrdfInverseDynamics(urdf=text, joints=list(names))
            return RegressorBasis(inv, f'regressor of {path.rsplit("/", 1)[-1]} '
                                       '(example-robot-data, joint names match)', text)
    except Exception:                           # noqa: BLE001 - fall back to model-free
        pass
    return PotentialBasis(len(names))


def basis_from_dict(d: dict):
    """Rebuild a basis written by ``to_dict`` (a saved model); ValueError if impossible."""
    kind = d.get('kind')
    if kind == 'potential':
        return PotentialBasis(int(d['N']))
    if kind == 'regressor':
        from .inverse import UrdfInverseDynamics
        inv = UrdfInverseDynamics(urdf=d['urdf'], joints=list(d['joints']))
        return RegressorBasis(inv, d.get('source', ''), d['urdf'])
    raise ValueError(f'unknown conservative basis {kind!r}')


class Correction:
    """
    What the residual holds besides the damping force: ``dV/dq(q) + offsets`` (N m).

    ``basis`` None: offsets only. ``theta`` (C,), ``offsets`` (N,). A saved model carries it
    as a record of ``kind``, which this module registers with ``dgp_ros.gp``'s model files.
    """

    kind = 'conservative'

    def __init__(self, basis, theta: np.ndarray, offsets: np.ndarray):
        self.basis = basis
        self.theta = np.asarray(theta, float)
        self.offsets = np.asarray(offsets, float)

    @property
    def needs_position(self) -> bool:
        return self.basis is not None and self.theta.size > 0 and bool(np.any(self.theta))

    def __call__(self, Q=None) -> np.ndarray:
        """Return the correction at poses Q (k, N) (Q may be None without a basis): (k, N)."""
        if not self.needs_position:
            k = 1 if Q is None else np.atleast_2d(Q).shape[0]
            return np.broadcast_to(self.offsets, (k, self.offsets.size)).copy()
        if Q is None:
            raise ValueError('this model corrects the rigid-body model in the pose: pass q=')
        return np.einsum('knc,c->kn', self.basis.deploy(Q), self.theta) + self.offsets

    def conservative(self, Q) -> np.ndarray:
        """
        Return the conservative part ``dV/dq`` alone at poses Q (k, N): (k, N) N m.

        What a controller adds to its rigid-body model (the payload's gravity): the offsets are
        left out (on a torque-sensing arm they are the sensor's bias, no torque the motors must
        make). Zeros without a basis.
        """
        Q = np.atleast_2d(np.asarray(Q, float))
        if not self.needs_position:
            return np.zeros((Q.shape[0], self.offsets.size))
        return np.einsum('knc,c->kn', self.basis.deploy(Q), self.theta)

    def to_dict(self) -> dict:
        return {'kind': self.kind, 'basis': None if self.basis is None else self.basis.to_dict(),
                'theta': self.theta.tolist(), 'offsets': self.offsets.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> 'Correction':
        basis = None if d.get('basis') is None else basis_from_dict(d['basis'])
        return cls(basis, np.asarray(d['theta'], float), np.asarray(d['offsets'], float))


# a model file's correction of this kind is rebuilt here (dgp_ros.gp imports no layer above it)
register_correction(Correction.kind, Correction.from_dict)

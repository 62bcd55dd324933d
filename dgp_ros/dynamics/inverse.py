"""
Rigid-body inverse dynamics ``tau_rb(q, qd, qdd)`` of an arm, in the estimator's joint order.

The measured joint torque of a real arm is ``M(q) qdd + C(q, qd) qd + g(q)`` plus friction, sensor
bias and noise; the estimator learns what is left after subtracting the first part
(docs/CONTRACTS.md, "Robot front end"). Two sources of ``tau_rb``, chosen by the estimator
parameter ``inverse_dynamics``:

- ``"urdf"``: :class:`UrdfInverseDynamics`, pinocchio's RNEA on the kinematic/inertial model of a
  URDF (the ``robot_description`` string or a file). Only the model is built, never the geometry,
  so mesh files need not exist. pinocchio is imported when such an object is built, so this
  module (and ``dgp_ros.dynamics``) imports without it.
- ``"python:<module>:<function>"``: :class:`PluginInverseDynamics`, any user function
  ``f(q, qd, qdd) -> tau_rb``.

Both take and return arrays of shape (N,) for one sample or (k, N) for k samples, joints in the
order of ``joints`` (the estimator's order); units rad, rad/s, rad/s^2 and N m (m, m/s, m/s^2 and
N for prismatic joints).
"""
from __future__ import annotations

import importlib
from typing import Callable, Sequence
from xml.etree import ElementTree

import numpy as np

__all__ = ['UrdfInverseDynamics', 'PluginInverseDynamics', 'make_inverse_dynamics',
           'INVERSE_DYNAMICS_CHOICES', 'PINOCCHIO_HINT']

INVERSE_DYNAMICS_CHOICES = ('', 'urdf', 'python:<module>:<function>')
PINOCCHIO_HINT = ('inverse_dynamics=urdf needs pinocchio: pip install pin '
                  '(or apt install ros-jazzy-pinocchio)')


def _import_pinocchio():
    """pinocchio, or ValueError with the install hint (it is optional for everything else)."""
    try:
        import pinocchio
    except ImportError as exc:
        raise ValueError(f'{PINOCCHIO_HINT} ({exc})') from None
    return pinocchio


def _urdf_reason(text: str) -> str:
    """
    One-line reason why ``text`` is not a URDF robot, or '' if the XML looks like one.

    pinocchio only says "does not contain a valid URDF model" (urdfdom prints the detail on
    stderr), so the XML is checked here first to name the line and column.
    """
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as exc:
        return f'not well-formed XML ({exc})'
    if root.tag != 'robot':
        return f"the root element is <{root.tag}>, a URDF's is <robot>"
    return ''


def _check_shapes(q, qd, qdd, n: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three float arrays of one shape, (N,) or (k, N) (N = ``n`` if given), or ValueError."""
    arrs = [np.asarray(x, dtype=float) for x in (q, qd, qdd)]
    shape = arrs[0].shape
    if any(a.shape != shape for a in arrs) or len(shape) not in (1, 2) or (
            n is not None and shape[-1] != n):
        want = f'(N,) or (k, N) with N = {n}' if n is not None else '(N,) or (k, N)'
        raise ValueError(f'q, qd, qdd must share one shape {want}; got '
                         f'{[a.shape for a in arrs]}')
    return arrs[0], arrs[1], arrs[2]


class UrdfInverseDynamics:
    """
    pinocchio RNEA of a URDF arm, reduced to the selected joints.

    Parameters
    ----------
    urdf : str, optional
        URDF XML text (the ROS ``robot_description`` convention). Wins over ``urdf_file``.
    urdf_file : str, optional
        Path of a URDF file.
    joints : sequence of str
        Selected joint names, in the estimator's order (N of them). Every other movable joint of
        the URDF is locked at its neutral value (clipped into its position limits) with
        ``pinocchio.buildReducedModel``, so e.g. the Panda's finger joints ride along as rigid mass
        of the hand. Empty: all movable joints, in the URDF's tree order.

    Raises
    ------
    ValueError
        No URDF given, the URDF does not parse (one-line reason), an unknown joint name (the
        message lists the URDF's movable joints), a selected joint that is not a 1-DOF joint, or
        pinocchio is missing (:data:`PINOCCHIO_HINT`).

    Notes
    -----
    Revolute and prismatic joints take their coordinate as is; continuous (unbounded revolute)
    joints, stored by pinocchio as (cos, sin), take the angle in rad and map it. Gravity is
    pinocchio's default, -9.81 m/s^2 along the base z axis. The joint ``damping``/``friction``
    attributes of the URDF are not part of the RNEA (that is what the estimator learns).

    """

    def __init__(self, urdf: str | None = None, urdf_file: str | None = None,
                 joints: Sequence[str] = ()):
        if isinstance(joints, str):
            raise ValueError(f'joints must be a sequence of joint names, got the string '
                             f'{joints!r}')
        pin = _import_pinocchio()
        self._pin = pin
        full = self._build(pin, urdf, urdf_file)
        self.urdf_text = urdf or ''
        if not self.urdf_text and urdf_file:
            with open(urdf_file, encoding='utf-8') as f:
                self.urdf_text = f.read()      # a saved correction rebuilds from it
        movable = [full.names[j] for j in range(1, full.njoints) if full.joints[j].nv > 0]
        joints = list(joints) or movable
        if not joints:
            raise ValueError('the URDF has no movable joints')
        unknown = [name for name in joints if name not in movable]
        if unknown or len(set(joints)) != len(joints):
            what = f'unknown joints {unknown}' if unknown else f'repeated joints in {joints}'
            raise ValueError(f"{what}; the URDF's movable joints are {movable}")
        q_ref = np.clip(pin.neutral(full), full.lowerPositionLimit, full.upperPositionLimit)
        q_ref = np.where(np.isfinite(q_ref), q_ref, pin.neutral(full))
        lock = [full.getJointId(name) for name in movable if name not in joints]
        self.model = pin.buildReducedModel(full, lock, q_ref) if lock else full
        self.data = self.model.createData()
        self.joint_names = tuple(joints)
        self._q0 = np.array(pin.neutral(self.model))
        idx_q, self._idx_v, cont = self._slots(self.model, joints)
        self._lin_q, self._lin_sel = idx_q[~cont], np.flatnonzero(~cont)   # coordinate as is
        self._cos_q, self._cos_sel = idx_q[cont], np.flatnonzero(cont)      # (cos, sin) pairs
        self._n = len(joints)
        # continuous joints have no position limits; the others' are where their q sits
        lo = np.asarray(self.model.lowerPositionLimit)[idx_q]
        hi = np.asarray(self.model.upperPositionLimit)[idx_q]
        self.lower = np.where(cont, -np.inf, lo)
        """Position lower limits of the selected joints (N,) [rad or m]; -inf if continuous."""
        self.upper = np.where(cont, np.inf, hi)
        """Position upper limits (N,) [rad or m]; +inf if continuous."""
        self.velocity_limit = np.asarray(self.model.velocityLimit)[self._idx_v]
        """Velocity limits (N,) [rad/s or m/s] as in the URDF."""
        self.effort_limit = np.asarray(self.model.effortLimit)[self._idx_v]
        """Effort limits (N,) [N m or N] as in the URDF."""

    @staticmethod
    def _slots(model, joints: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Per selected joint: first q index, v index, and whether it is continuous (nq = 2).

        In the reduced model every velocity belongs to a selected joint, so the v indices are a
        permutation of 0..N-1.
        """
        slots = []
        for name in joints:
            jm = model.joints[model.getJointId(name)]
            if jm.nv != 1 or jm.nq not in (1, 2):
                raise ValueError(f'joint {name!r} ({jm.shortname()}) has {jm.nv} velocities; '
                                 'only 1-DOF joints can be selected')
            slots.append((jm.idx_q, jm.idx_v, jm.nq == 2))
        idx_q, idx_v, cont = (np.array(col) for col in zip(*slots))
        return idx_q, idx_v, cont.astype(bool)

    @staticmethod
    def _build(pin, urdf: str | None, urdf_file: str | None):
        """Build the full pinocchio model (no root joint: the base is fixed) or ValueError."""
        if urdf:
            text, what = urdf, 'robot_description'
        elif urdf_file:
            what = f'urdf_file {urdf_file!r}'
            try:
                with open(urdf_file, encoding='utf-8') as f:
                    text = f.read()
            except OSError as exc:
                raise ValueError(f'{what} cannot be read: {exc}') from None
        else:
            raise ValueError('UrdfInverseDynamics needs urdf (XML text) or urdf_file (a path)')
        reason = _urdf_reason(text)
        if reason:
            raise ValueError(f'{what} is not a URDF: {reason}')
        try:
            return pin.buildModelFromXML(text)
        except (ValueError, RuntimeError) as exc:
            raise ValueError(f'{what} is not a URDF pinocchio can read: {exc}') from None

    @property
    def nv(self) -> int:
        """Get the number of selected joints N."""
        return self._n

    def _config(self, q: np.ndarray) -> np.ndarray:
        """Return the pinocchio configuration vector (nq,) from the selected coordinates (N,)."""
        qp = self._q0.copy()
        qp[self._lin_q] = q[self._lin_sel]
        if self._cos_q.size:
            angle = q[self._cos_sel]
            qp[self._cos_q] = np.cos(angle)
            qp[self._cos_q + 1] = np.sin(angle)
        return qp

    def __call__(self, q, qd, qdd) -> np.ndarray:
        """
        Rigid-body joint torque ``M(q) qdd + C(q, qd) qd + g(q)``.

        Parameters
        ----------
        q, qd, qdd : array_like, (N,) or (k, N)
            Positions [rad or m], velocities [rad/s or m/s] and accelerations [rad/s^2 or m/s^2]
            of the selected joints, in ``joint_names`` order.

        Returns
        -------
        numpy.ndarray, same shape as ``q``
            Joint torques [N m] (forces [N] for prismatic joints), selected order.

        Notes
        -----
        One RNEA per sample in a Python loop. Measured for the 7-DOF Panda: 6.5 to 9 us for a
        call with one sample (mostly the argument checks), 2.4 us per sample in a batch.

        """
        q, qd, qdd = _check_shapes(q, qd, qdd, self._n)
        single = q.ndim == 1
        q2, qd2, qdd2 = np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(qdd)
        out = np.empty_like(q2)
        v = np.empty(self._n)
        a = np.empty(self._n)
        rnea, model, data, idx = self._pin.rnea, self.model, self.data, self._idx_v
        for i in range(q2.shape[0]):
            v[idx] = qd2[i]
            a[idx] = qdd2[i]
            out[i] = rnea(model, data, self._config(q2[i]), v, a)[idx]
        return out[0] if single else out


class PluginInverseDynamics:
    """
    A user's inverse dynamics ``f(q, qd, qdd) -> tau_rb``, named "python:<module>:<function>".

    Parameters
    ----------
    spec : str
        ``"python:<module>:<function>"``; ``<module>`` is imported (dotted names allowed, it must
        be on ``sys.path``) and ``<function>`` is an attribute of it (dotted for a nested
        attribute).

    Raises
    ------
    ValueError
        Malformed spec, module that does not import (with the reason), missing or non-callable
        function; on a call, output of the wrong shape.

    Notes
    -----
    The function gets float arrays (N,) or (k, N) in the selected joint order and must return the
    same shape (N m). The shape is checked on every call (a tuple comparison).

    """

    def __init__(self, spec: str):
        prefix = 'python:'
        parts = spec[len(prefix):].split(':') if spec.startswith(prefix) else []
        if len(parts) != 2 or not all(p.strip() for p in parts):
            raise ValueError(f'inverse dynamics plugin {spec!r}: expected '
                             '"python:<module>:<function>", e.g. "python:my_robot.dyn:tau_rb"')
        mod_name, func_name = (p.strip() for p in parts)
        try:
            obj = importlib.import_module(mod_name)
        except Exception as exc:  # noqa: BLE001 - any import failure is a config error here
            raise ValueError(f'inverse dynamics plugin {spec!r}: cannot import {mod_name!r}: '
                             f'{type(exc).__name__}: {exc}') from None
        for attr in func_name.split('.'):
            if not hasattr(obj, attr):
                raise ValueError(f'inverse dynamics plugin {spec!r}: {mod_name!r} has no '
                                 f'attribute {func_name!r}')
            obj = getattr(obj, attr)
        if not callable(obj):
            raise ValueError(f'inverse dynamics plugin {spec!r}: {func_name!r} is not callable '
                             f'(a {type(obj).__name__})')
        self.spec = spec
        self._f: Callable = obj

    def __call__(self, q, qd, qdd) -> np.ndarray:
        """``f(q, qd, qdd)`` as float array of the input's shape, (N,) or (k, N) [N m]."""
        q, qd, qdd = _check_shapes(q, qd, qdd, None)
        out = np.asarray(self._f(q, qd, qdd), dtype=float)
        if out.shape != q.shape:
            raise ValueError(f'inverse dynamics plugin {self.spec!r} returned shape {out.shape} '
                             f'for inputs of shape {q.shape}; it must return {q.shape}')
        return out


def make_inverse_dynamics(spec: str, *, robot_description: str = '', urdf_file: str = '',
                          joints: Sequence[str] = ()) -> Callable | None:
    """
    Make the inverse dynamics named by the estimator parameter ``inverse_dynamics``.

    Parameters
    ----------
    spec : str
        ``""`` (the effort already is the damping force: None), ``"urdf"`` or
        ``"python:<module>:<function>"``.
    robot_description : str
        URDF XML text; for ``"urdf"`` it wins over ``urdf_file``.
    urdf_file : str
        URDF path, used for ``"urdf"`` when ``robot_description`` is empty.
    joints : sequence of str
        Selected joint names in the estimator's order (see :class:`UrdfInverseDynamics`).

    Returns
    -------
    callable or None
        ``f(q, qd, qdd) -> tau_rb`` with shapes (N,) or (k, N), or None for ``""``.

    Raises
    ------
    ValueError
        Unknown spec (the message lists :data:`INVERSE_DYNAMICS_CHOICES`), ``"urdf"`` without a
        URDF (the message names both parameters), or the constructors' errors.

    """
    spec = (spec or '').strip()
    if not spec:
        return None
    if spec == 'urdf':
        if robot_description:
            return UrdfInverseDynamics(urdf=robot_description, joints=joints)
        if urdf_file:
            return UrdfInverseDynamics(urdf_file=urdf_file, joints=joints)
        raise ValueError('inverse_dynamics=urdf needs a URDF: set the parameter '
                         'robot_description (URDF text) or urdf_file (a path)')
    if spec.startswith('python:'):
        return PluginInverseDynamics(spec)
    raise ValueError(f'inverse_dynamics={spec!r} is not one of {list(INVERSE_DYNAMICS_CHOICES)}')

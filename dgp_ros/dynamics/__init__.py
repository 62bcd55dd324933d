"""
Robot front end (docs/CONTRACTS.md, "Robot front end"; docs/ARCHITECTURE.md, "Layers").

From raw ``/joint_states`` to the friction residual the estimator learns. Pure numpy; no ROS import
anywhere in this package, and pinocchio only when a URDF model is built.

- ``inverse``: rigid-body inverse dynamics ``tau_rb(q, qd, qdd)`` from a URDF (pinocchio) or a
  user plugin, chosen by the ``inverse_dynamics`` parameter (:func:`make_inverse_dynamics`);
- ``filter``: :class:`AccelFilter`, the acceleration of the measured velocity, centred on the
  sample it is paired with (no lag; the output trails the input by the half window);
- ``residual``: :class:`FrictionResidual`, ``effort - tau_rb`` per wanted sample;
- ``arm_sim``: simulated Panda / UR5 data with known friction and bias (tests, demo);
- ``realistic``: friction outside the estimator's prior family and a payload the URDF lacks;
- ``conservative``: the correction of the rigid-body model learned beside the damping force;
  importing this package registers it with ``dgp_ros.gp``, which rebuilds it from model files.
"""
from . import conservative  # noqa: F401 - registers the correction kind a saved model may carry
from .arm_sim import (ARM_JOINTS, example_robot_urdf, FRICTION_TABLES, friction_truth,
                      negative_power_fraction, simulate_arm)
from .filter import AccelFilter, AccelSample, DEFAULT_HALF_WINDOW_S
from .inverse import (INVERSE_DYNAMICS_CHOICES, make_inverse_dynamics, PINOCCHIO_HINT,
                      PluginInverseDynamics, UrdfInverseDynamics)
from .realistic import (DEFAULT_PAYLOAD_KG, payload_inverse_dynamics, realistic_friction,
                        REALISTIC_TABLES)
from .residual import FrictionResidual, ResidualSample

__all__ = ['UrdfInverseDynamics', 'PluginInverseDynamics', 'make_inverse_dynamics',
           'INVERSE_DYNAMICS_CHOICES', 'PINOCCHIO_HINT', 'AccelFilter', 'AccelSample',
           'DEFAULT_HALF_WINDOW_S', 'FrictionResidual', 'ResidualSample', 'simulate_arm',
           'friction_truth', 'example_robot_urdf', 'negative_power_fraction', 'ARM_JOINTS',
           'FRICTION_TABLES', 'realistic_friction', 'payload_inverse_dynamics',
           'REALISTIC_TABLES', 'DEFAULT_PAYLOAD_KG']

"""
controller ROS 2 node (``dgp-controller``): joint-space tracking with the estimator's friction.

The example controller of the closed-loop demo (thin wrapper of
``dgp_ros.dynamics.closed_loop``): for every ``joint_states`` message (stamp ``t``) it publishes
one ``std_msgs/Float64MultiArray`` on ``/effort_controller/commands`` (joint order ``joints``)::

    tau = tau_rb_urdf(q_r, qd_r, qdd_r) + M_urdf(q) (w^2 (q_r - q) + 2 zeta w (qd_r - qd))
          + k * c * (tau_hat + correction)

with the reference path ``(q_r, qd_r, qdd_r)(t)`` of ``seed`` and ``cycle_s``, ``tau_hat`` the
newest answer on ``<estimator>/damping_force`` (``compensation`` dgp or dgp_damping_only),
``correction`` the newest on ``<estimator>/rigid_body_correction`` (dgp only) and ``c`` the
per-joint confidence on ``<estimator>/damping_force_confidence`` (``use_confidence``: the
compensation fades in as the model earns it and out where it has no grounds; 0 until one
arrives). Each is held (zero-order hold), matched by joint name and dropped when older than
``timeout_s`` of the messages' (simulated) time; those steps are counted (``stale``).

**Lock-step.** With a compensation, the command for ``t`` waits for the answer stamped ``t`` (the
estimator answers each state at once) at most ``wait_for_answer_s`` of wall time; after a wait
that ran out it does not wait again until an answer arrives (the estimator is gone or late): the
arm (``dgp-arm-loop``) then gets its commands at once, and no compensation once the held answer
is older than ``timeout_s`` of simulated time. At exit (SIGINT/SIGTERM) the
counts are logged and, with ``summary_path``, written as JSON.
"""
import json
import sys
import time

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from dgp_ros.dynamics.closed_loop import HeldEstimate, reference_path, TrackingController
from dgp_ros.nodes.runtime import checked_parameters, help_text, run
from dgp_ros.params import ParamSpec

SPECS = [
    ParamSpec('robot', 'str', 'panda', 'the arm: its URDF (feed-forward, mass matrix) and joints',
              choices=('panda', 'ur5')),
    ParamSpec('compensation', 'str', 'dgp', 'feed-forward: none, dgp (damping force + '
              'correction) or dgp_damping_only', choices=('none', 'dgp', 'dgp_damping_only')),
    ParamSpec('k', 'float', 1.0, 'gain of the compensation feed-forward', low=0.0, high=2.0),
    ParamSpec('use_confidence', 'bool', True, "scale k by the estimator's per-joint confidence "
              '(~/damping_force_confidence)'),
    ParamSpec('bandwidth_hz', 'float', 4.0, 'PD bandwidth w / 2 pi (Hz)', low=0.1, high=50.0),
    ParamSpec('damping_ratio', 'float', 1.0, 'PD damping ratio', low=0.1, high=5.0),
    ParamSpec('timeout_s', 'float', 0.05, 'answers older than this (s of message time) are not '
              'used', low=0.001, high=10.0),
    ParamSpec('wait_for_answer_s', 'float', 0.05, 'wall time the command for t waits for the '
              'answer stamped t while answers are fresh', low=0.0, high=600.0),
    ParamSpec('estimator', 'str', '/dgp_estimator', "namespace of the estimator's topics"),
    ParamSpec('seed', 'int', 0, 'reference path', low=0, high=2 ** 31 - 1),
    ParamSpec('cycle_s', 'float', 10.0, 'period of the reference path (s)', low=1.0,
              high=3600.0),
    ParamSpec('joints', 'str[]', [], "joint order of the commands ([] = the robot's order)"),
    ParamSpec('summary_path', 'str', '', 'write the counts here as JSON at exit'),
]
PARAMETERS = {p.name: p for p in SPECS}


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


class ControllerNode(Node):
    """Tracking controller with the estimator's compensation (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__('controller', **kwargs)
        p = self.params = checked_parameters(self, SPECS)
        self.law = TrackingController(p['robot'], p['bandwidth_hz'], p['damping_ratio'], p['k'])
        self.ref = reference_path(p['robot'], seed=p['seed'], cycle_s=p['cycle_s'])
        self.names = list(self.law.names)
        order = list(p['joints']) or self.names
        if sorted(order) != sorted(self.names):
            raise ValueError(f'joints must be a permutation of {self.names}, got {order}')
        self.out_index = [self.names.index(n) for n in order]
        self.comp = p['compensation']
        self.held_d = HeldEstimate(self.names, p['timeout_s'])
        self.held_c = HeldEstimate(self.names, p['timeout_s'])
        self.held_k = HeldEstimate(self.names, p['timeout_s'])
        self.counts = {'states': 0, 'commands': 0, 'waited_out': 0, 'answers': 0,
                       'nonpassive_answers': 0, 'refused_states': 0}
        self.pub = self.create_publisher(Float64MultiArray, '/effort_controller/commands',
                                         QoSProfile(depth=100))
        self.create_subscription(JointState, 'joint_states', self._on_state,
                                 QoSProfile(depth=100))
        ns = p['estimator'].rstrip('/')
        if self.comp != 'none':
            self.create_subscription(JointState, ns + '/damping_force', self._on_force,
                                     QoSProfile(depth=100))
        if self.comp == 'dgp':
            self.create_subscription(JointState, ns + '/rigid_body_correction',
                                     self._on_correction, QoSProfile(depth=100))
        if self.comp != 'none' and p['use_confidence']:
            self.create_subscription(JointState, ns + '/damping_force_confidence',
                                     self._on_confidence, QoSProfile(depth=100))
        self._pending = None             # (t, q, qd, since) of a state waiting for its answer
        self._expect = True              # answers are coming: wait for them
        self.create_timer(0.001, self._on_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'{p["robot"]}: compensation {self.comp} (k={p["k"]:g}), PD '
                               f'{p["bandwidth_hz"]:g} Hz, timeout {p["timeout_s"]:g} s')

    def _on_state(self, msg: JointState) -> None:
        self.counts['states'] += 1
        pos = {n: i for i, n in enumerate(msg.name)}
        if not all(n in pos for n in self.names) or len(msg.velocity) != len(msg.name):
            self.counts['refused_states'] += 1
            return
        idx = [pos[n] for n in self.names]
        q = np.asarray(msg.position, dtype=float)[idx]
        qd = np.asarray(msg.velocity, dtype=float)[idx]
        t = _stamp(msg)
        if self._pending is not None:            # a newer state: the older one goes now
            self._command(*self._pending[:3])
        self._pending = (t, q, qd, time.monotonic())
        self._try()

    def _on_force(self, msg: JointState) -> None:
        self.counts['answers'] += 1
        v, f = np.asarray(msg.velocity), np.asarray(msg.effort)
        if v.shape == f.shape and float(v @ f) < 0.0:
            self.counts['nonpassive_answers'] += 1
        self.held_d.update(_stamp(msg), msg.name, msg.effort)
        self._expect = True
        self._try()

    def _on_correction(self, msg: JointState) -> None:
        self.held_c.update(_stamp(msg), msg.name, msg.effort)

    def _on_confidence(self, msg: JointState) -> None:
        self.held_k.update(_stamp(msg), msg.name, msg.effort)

    def _try(self) -> None:
        """Command the pending state if its answer is in, no compensation waits, or it is stale."""
        if self._pending is None:
            return
        held = self.held_d.stamp
        if self.comp == 'none' or not self._expect or (held is not None and
                                                       held >= self._pending[0]):
            self._command(*self._pending[:3])

    def _on_timer(self) -> None:
        if self._pending is not None and \
                time.monotonic() - self._pending[3] > self.params['wait_for_answer_s']:
            self.counts['waited_out'] += 1
            self._expect = False
            self._command(*self._pending[:3])

    def _command(self, t, q, qd) -> None:
        self._pending = None
        comp = None
        if self.comp != 'none':
            comp = self.held_d.value(t) + (self.held_c.value(t) if self.comp == 'dgp' else 0.0)
            if self.params['use_confidence']:
                comp = self.held_k.value(t) * comp
        tau = self.law.command(q, qd, self.ref(t), comp)
        m = Float64MultiArray()
        m.data = [float(tau[i]) for i in self.out_index]
        self.pub.publish(m)
        self.counts['commands'] += 1

    def summary(self) -> dict:
        return dict(self.counts, stale=self.held_d.stale, correction_stale=self.held_c.stale,
                    refused_answers=self.held_d.refused + self.held_c.refused,
                    injected_j=self.law.injected_j, clipped=self.law.clipped)

    def shutdown(self) -> None:
        s = self.summary()
        self.get_logger().info(f'counts: {s}')
        if self.params['summary_path']:
            with open(self.params['summary_path'], 'w') as f:
                json.dump(s, f)


HELP = help_text('dgp-controller', 'Example joint-space tracking controller (PD + URDF '
                 "feed-forward) adding the estimator's damping force and rigid-body correction "
                 'as a feed-forward; commands on /effort_controller/commands.', SPECS)


def main(args=None) -> int:
    return run('dgp-controller', lambda ctx: ControllerNode(context=ctx), HELP, args)


if __name__ == '__main__':
    sys.exit(main())

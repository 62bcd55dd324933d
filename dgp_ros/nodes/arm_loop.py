"""
arm_loop ROS 2 node (``dgp-arm-loop``): the simulated Panda or UR5 in closed loop (thin wrapper).

The arm (``dgp_ros.dynamics.closed_loop.ClosedLoopArm``: the example-robot-data URDF with the
payload it lacks, realistic friction, torque-sensor bias and noise) is integrated at 1 kHz from
the joint torque commands it receives, taken the way ros2_control's effort controllers take them:
``std_msgs/Float64MultiArray`` on ``/effort_controller/commands``, one value per joint in the
order of the ``joints`` parameter.

**Lock-step through simulated time.** The node owns the simulated clock: it publishes ``/clock``
and ``joint_states`` (``sensor_msgs/JointState`` stamped with the simulated time: position,
measured velocity, measured joint torque as effort) at ``t``, then waits for one command, applies
it for one 1 ms step and publishes ``t + 1 ms``. A command that does not arrive within
``step_timeout_s`` of wall time is replaced by the last one (counted: ``timeouts``). So the run
does not depend on how fast the machine is (reproducible on a loaded 2-core machine, as far as
the other nodes' answers are), and the other nodes run with ``use_sim_time``. The stream starts
once ``min_subscribers`` joint_states subscriptions and a command publisher have matched; at
``duration_s`` the node logs its counts and exits 0.
"""
import sys
import time

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from dgp_ros.dynamics.closed_loop import ClosedLoopArm, reference_path
from dgp_ros.nodes.runtime import checked_parameters, help_text, run
from dgp_ros.params import ParamSpec

SPECS = [
    ParamSpec('robot', 'str', 'panda', 'simulated arm (example-robot-data URDF)',
              choices=('panda', 'ur5')),
    ParamSpec('duration_s', 'float', 10.0, 'simulated time of the run (s)', low=0.01,
              high=3600.0),
    ParamSpec('seed', 'int', 0, 'start pose (the reference path of this seed) and sensor noise',
              low=0, high=2 ** 31 - 1),
    ParamSpec('cycle_s', 'float', 10.0, 'period of the reference path whose start is the start '
              'pose (s)', low=1.0, high=3600.0),
    ParamSpec('payload_kg', 'float', -1.0, 'payload at the flange the URDF does not have (kg); '
              '-1 = the robot default (Panda 0.5, UR5 1.0)', low=-1.0, high=20.0),
    ParamSpec('friction', 'str', 'realistic', "joint friction: realistic, table (the estimator's "
              'prior family) or none', choices=('realistic', 'table', 'none')),
    ParamSpec('joints', 'str[]', [], "joint order of the commands ([] = the robot's "
              'ARM_JOINTS order)'),
    ParamSpec('step_timeout_s', 'float', 0.5, 'wall time to wait for a command before the '
              'last one is applied again (counted)', low=0.001, high=600.0),
    ParamSpec('min_subscribers', 'int', 1, 'joint_states subscriptions to wait for before '
              'the first step', low=0, high=100),
    ParamSpec('wait_for_subscribers_s', 'float', 60.0, 'longest wait for the subscribers and '
              'the command publisher (s)', low=0.0, high=3600.0),
]
PARAMETERS = {p.name: p for p in SPECS}


class ArmLoopNode(Node):
    """Closed-loop simulated arm, lock-step (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__('arm_loop', **kwargs)
        p = self.params = checked_parameters(self, SPECS)
        ref = reference_path(p['robot'], seed=p['seed'], cycle_s=p['cycle_s'])
        q0, qd0, _ = ref(0.0)
        self.arm = ClosedLoopArm(p['robot'], q0, qd0, seed=p['seed'],
                                 payload_kg=None if p['payload_kg'] < 0 else p['payload_kg'],
                                 friction=p['friction'])
        names = list(self.arm.names)
        order = list(p['joints']) or names
        if sorted(order) != sorted(names):
            raise ValueError(f'joints must be a permutation of {names}, got {order}')
        self.order = [order.index(n) for n in names]       # command index of each arm joint
        self.names = names
        self.steps = int(round(p['duration_s'] / self.arm.dt))
        self.counts = {'steps': 0, 'commands': 0, 'timeouts': 0, 'refused': 0}
        self.pub_clock = self.create_publisher(ClockMsg, '/clock', 10)
        self.pub = self.create_publisher(JointState, 'joint_states', QoSProfile(depth=100))
        self.sub = self.create_subscription(Float64MultiArray, '/effort_controller/commands',
                                            self._on_command, QoSProfile(depth=100))
        self.done = False
        self._started = False
        self._since = time.monotonic()
        self._last = None
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        self.timer = self.create_timer(0.002, self._on_timer, clock=wall)
        self.get_logger().info(f'{p["robot"]}: closed loop, {p["friction"]} friction, payload '
                               f'{self.arm.payload_kg:g} kg, {self.steps} steps of 1 ms; '
                               f'commands on /effort_controller/commands in order {order}')

    def _publish_state(self) -> None:
        t, q, qd, effort = self.arm.measure()
        c = ClockMsg()
        c.clock.sec, c.clock.nanosec = divmod(int(round(t * 1e9)), 1_000_000_000)
        self.pub_clock.publish(c)
        m = JointState()
        m.header.stamp = c.clock
        m.name = self.names
        m.position, m.velocity, m.effort = q.tolist(), qd.tolist(), effort.tolist()
        self.pub.publish(m)
        self._since = time.monotonic()

    def _advance(self, tau) -> None:
        self.arm.step(tau)
        self.counts['steps'] += 1
        if self.counts['steps'] >= self.steps:
            self.done = True
            self.get_logger().info(f'finished: {self.counts}')
            return
        self._publish_state()

    def _on_command(self, msg: Float64MultiArray) -> None:
        if not self._started or self.done:
            return
        if len(msg.data) != len(self.names):
            self.counts['refused'] += 1
            return
        self.counts['commands'] += 1
        tau = [msg.data[i] for i in self.order]
        self._last = tau
        self._advance(tau)

    def _on_timer(self) -> None:
        if self.done:
            return
        now = time.monotonic()
        if not self._started:
            ready = (self.pub.get_subscription_count() >= self.params['min_subscribers'] and
                     self.sub.get_publisher_count() > 0)
            if not ready and now - self._since < self.params['wait_for_subscribers_s']:
                return
            if not ready:
                self.get_logger().warn('starting without the expected subscribers')
            self._started = True
            time.sleep(0.5)              # discovered is not yet matched: let the readers match
            self._publish_state()
            return
        if now - self._since > self.params['step_timeout_s']:
            self.counts['timeouts'] += 1
            self._advance(self._last if self._last is not None else self.arm.tau)


HELP = help_text('dgp-arm-loop', 'A simulated Panda or UR5 in closed loop: joint torque '
                 'commands on /effort_controller/commands (Float64MultiArray), joint_states '
                 'with the measured torque as effort, lock-step with /clock.', SPECS)


def main(args=None) -> int:
    return run('dgp-arm-loop', lambda ctx: ArmLoopNode(context=ctx), HELP, args)


if __name__ == '__main__':
    sys.exit(main())

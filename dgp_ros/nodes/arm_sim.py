"""
arm_sim ROS 2 node: a simulated Panda or UR5 publishing raw ``/joint_states`` (thin wrapper).

The run is simulated at start (``dgp_ros.dynamics.arm_stream.demo_arm``: pinocchio RNEA of the
example-robot-data URDF, realistic friction, a payload the URDF lacks, sensor bias and noise,
jittered 1 kHz stamps from 0) and streamed at ``real_time_factor``: every 5 ms of wall time the
samples that are due are published, one ``sensor_msgs/JointState`` each (name, position,
velocity, effort of every joint in the driver's order, the Panda's finger joints included).

Topic: ``joint_states`` (reliable, depth 100; remappable). Parameters: ``--help``. With
``min_subscribers`` > 0 the stream waits (at most ``wait_for_subscribers_s``) until that many
subscriptions have matched. When the run (or ``max_sim_time_s`` of it) is published, the node
exits 0.
"""
import math
import sys
import time

from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState

from dgp_ros.dynamics.arm_stream import demo_arm, DriverStream
from dgp_ros.nodes.runtime import checked_parameters, help_text, run
from dgp_ros.params import ParamSpec

SPECS = [
    ParamSpec('robot', 'str', 'panda', 'simulated arm (example-robot-data URDF)',
              choices=('panda', 'ur5')),
    ParamSpec('duration_s', 'float', 60.0, 'length of the simulated run (s)', low=1.0,
              high=3600.0),
    ParamSpec('cycle_s', 'float', 10.0, 'period of the task cycle the arm repeats (s): a '
              'Fourier path with a standstill every 5 s; set it to duration_s for a path that '
              'never repeats', low=1.0, high=3600.0),
    ParamSpec('max_sim_time_s', 'float', 0.0, 'publish only the samples stamped before this (s); '
              '0 = the whole run', low=0.0, high=3600.0),
    ParamSpec('seed', 'int', 0, 'trajectory, stamp jitter and noise', low=0, high=2 ** 31 - 1),
    ParamSpec('payload_kg', 'float', -1.0, 'payload at the flange the URDF does not have (kg); '
              '-1 = the robot default (Panda 0.5, UR5 1.0)', low=-1.0, high=20.0),
    ParamSpec('friction', 'str', 'realistic', 'joint friction: realistic (asymmetric, |v|^0.6 '
              "viscous, load-dependent) or table (the estimator's prior family)",
              choices=('realistic', 'table')),
    ParamSpec('real_time_factor', 'float', 1.0, 'stamp seconds per wall second; 0 = as fast as '
              'possible', low=0.0, high=1000.0),
    ParamSpec('min_subscribers', 'int', 0, 'wait until this many subscriptions match before '
              'streaming', low=0, high=100),
    ParamSpec('wait_for_subscribers_s', 'float', 30.0, 'longest wait for min_subscribers (s); '
              'then stream anyway', low=0.0, high=3600.0),
]
PARAMETERS = {p.name: p for p in SPECS}
TICK_S = 0.005          # wall seconds between publishing batches


def _to_time(t: float) -> Time:
    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


class ArmSimNode(Node):
    """Publishes a precomputed simulated arm run as raw joint states, at real time."""

    def __init__(self, **kwargs):
        super().__init__('arm_sim', **kwargs)
        p = self.params = checked_parameters(self, SPECS)
        self.pub = self.create_publisher(JointState, 'joint_states', QoSProfile(depth=100))
        t0 = time.perf_counter()
        sim = demo_arm(p['robot'], p['duration_s'], seed=p['seed'], friction=p['friction'],
                       payload_kg=None if p['payload_kg'] < 0 else p['payload_kg'],
                       base_hz=1.0 / p['cycle_s'])
        until = p['max_sim_time_s'] if p['max_sim_time_s'] > 0 else None
        self.stream = DriverStream(sim, until)
        self.done = False
        self.published = 0
        self._start = None
        self._waiting_since = time.monotonic()
        self.get_logger().info(
            f'{p["robot"]}: {len(self.stream)} samples ({sim["friction_model"]} friction, '
            f'payload {sim["payload_kg"]:g} kg) simulated in {time.perf_counter() - t0:.1f} s; '
            f'streaming at real-time factor {p["real_time_factor"]:g}')
        self.timer = self.create_timer(TICK_S, self._on_timer)

    def _on_timer(self):
        if self.done:
            return
        now = time.monotonic()
        if self._start is None:
            enough = self.pub.get_subscription_count() >= self.params['min_subscribers']
            if not enough and now - self._waiting_since < self.params['wait_for_subscribers_s']:
                return
            if not enough:
                self.get_logger().warn('streaming without the expected subscribers')
            self._start = now
        s = self.stream
        for i in s.due(now - self._start, self.params['real_time_factor']):
            m = JointState()
            m.header.stamp = _to_time(float(s.stamps[i]))
            m.name = s.names
            m.position = s.position[i].tolist()
            m.velocity = s.velocity[i].tolist()
            m.effort = s.effort[i].tolist()
            self.pub.publish(m)
            self.published += 1
        if s.finished:
            self.done = True
            self.timer.cancel()
            self.get_logger().info(f'published {self.published} joint states in '
                                   f'{now - self._start:.1f} s')


HELP = help_text('dgp-arm-sim', 'A simulated Panda or UR5 (realistic friction, a payload the URDF '
                 'lacks, noise, jittered 1 kHz stamps) publishing raw joint_states like its '
                 'driver (the robot demo: dgp-demo --robot).', SPECS)


def main(args=None) -> int:
    return run('dgp-arm-sim', lambda ctx: ArmSimNode(context=ctx), HELP, args)


if __name__ == '__main__':
    sys.exit(main())

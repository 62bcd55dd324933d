"""
sim_bridge ROS 2 node: publishes the simulated A320 approach (thin wrapper, see simulator.py).

Topics: ``generalized_state`` (sensor_msgs/JointState: name, velocity = q, effort = tau),
``aero_wrench`` (geometry_msgs/WrenchStamped in frame ``wind``: the aerodynamic force vector
[-drag, side, -lift] in wind axes, torque zero), ``/clock`` (rosgraph_msgs/Clock) if
``publish_clock``.  All stamps are simulation time (monotonic across looped approaches).
Parameters: see config/sim_bridge.yaml.  Changes accepted at run time take effect at the next
approach (``loop``), except ``real_time_factor`` which applies at once.  With ``min_subscribers``
the approach starts once that many subscriptions of ``generalized_state`` matched (a recorder
that must see the first sample, as the demo's).
"""
import math
import sys
import time

from builtin_interfaces.msg import Time
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from dgp_ros.nodes.runtime import (check_unknown_overrides, declare_parameters, help_text,
                                   reject_unknown, run)
from dgp_ros.params import ParamSpec

from .config import DEFAULT_WIND_AMPLITUDE, DEFAULT_WIND_FREQUENCY, DEFAULT_WIND_PHASE, SimConfig
from .simulator import ApproachSimulator

SPECS = [
    ParamSpec('rate_hz', 'float', 60.0, 'publish rate in simulated time (Hz)', low=1.0,
              high=1000.0),
    ParamSpec('real_time_factor', 'float', 1.0, 'simulated s per wall s; 0 = as fast as '
              'possible', low=0.0, high=1000.0),
    ParamSpec('wind_amplitude', 'float[]', list(DEFAULT_WIND_AMPLITUDE),
              'wind amplitude north, east, down (m/s, |A| <= 25)', max_len=3),
    ParamSpec('wind_frequency', 'float[]', list(DEFAULT_WIND_FREQUENCY),
              'wind frequency north, east, down (Hz)', max_len=3),
    ParamSpec('wind_phase', 'float[]', list(DEFAULT_WIND_PHASE),
              'wind phase north, east, down (rad)', max_len=3),
    ParamSpec('coordinates', 'str', 'angle', "'angle' (alpha, beta, airspeed) or 'body' "
              '(u, v, w)', choices=('angle', 'body')),
    ParamSpec('loop', 'bool', True, 'restart the approach after touch-down; false = shut down'),
    ParamSpec('aircraft', 'str', 'A320', 'JSBSim aircraft model name'),
    ParamSpec('publish_clock', 'bool', False, 'publish simulation time on /clock (start-up only)'),
    ParamSpec('max_sim_time_s', 'float', 0.0, 'stop after this much simulated time (s); '
              '0 = unlimited', low=0.0, high=1e9),
    ParamSpec('min_subscribers', 'int', 0, 'wait until this many subscriptions of '
              'generalized_state match before the approach starts (start-up only)', low=0,
              high=100),
    ParamSpec('wait_for_subscribers_s', 'float', 30.0, 'longest wait for min_subscribers (s); '
              'then fly anyway', low=0.0, high=3600.0),
]
PARAMETERS = {p.name: p for p in SPECS}
CONFIG_KEYS = ('rate_hz', 'wind_amplitude', 'wind_frequency', 'wind_phase', 'coordinates',
               'aircraft')


def _to_time(t: float) -> Time:
    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def check_values(values: dict) -> SimConfig:
    """Validate node parameter values; return the SimConfig or raise ValueError (clear message)."""
    rtf = values['real_time_factor']
    if not isinstance(rtf, (int, float)) or not math.isfinite(rtf) or rtf < 0:
        raise ValueError(f'real_time_factor must be >= 0 (0 = as fast as possible), got {rtf!r}')
    mst = values['max_sim_time_s']
    if not isinstance(mst, (int, float)) or not math.isfinite(mst) or mst < 0:
        raise ValueError(f'max_sim_time_s must be >= 0 (0 = unlimited), got {mst!r}')
    return SimConfig(**{k: values[k] for k in CONFIG_KEYS}).validate()


class SimBridgeNode(Node):
    """Steps ApproachSimulator on a timer and publishes each sample."""

    def __init__(self, **kwargs):
        super().__init__('sim_bridge', allow_undeclared_parameters=True, **kwargs)
        declare_parameters(self, SPECS)
        check_unknown_overrides(self)
        self.cfg = check_values(self._values())        # raises ValueError on bad start values
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.state_pub = self.create_publisher(JointState, 'generalized_state', 10)
        self.wrench_pub = self.create_publisher(WrenchStamped, 'aero_wrench', 10)
        self.clock_pub = (self.create_publisher(Clock, '/clock', 10)
                          if self.get_parameter('publish_clock').value else None)
        self.done = False
        self.published = 0
        self._t_offset = 0.0
        self.sim = ApproachSimulator(self.cfg)
        self._first = self.sim.reset()      # published once the subscribers are there
        self._waiting_since = time.monotonic()
        self.timer = None
        self._make_timer()
        self.get_logger().info(
            f'A320 approach trimmed at {self.sim.trim_speed_kts:.0f} kt '
            f'({self.sim.trim_airspeed_mps:.1f} m/s), coordinates={self.cfg.coordinates}, '
            f'rate={self.cfg.rate_hz} Hz, wind amplitude={self.cfg.wind_amplitude} m/s')

    # ------------------------------------------------------------------ parameters
    def _values(self, overrides=()):
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        values.update({p.name: p.value for p in overrides})
        return values

    def _on_set_parameters(self, params):
        bad = reject_unknown(self, params)
        if bad is not None:
            return bad
        try:
            for p in params:
                if p.name == 'publish_clock' and \
                        p.value != self.get_parameter('publish_clock').value:
                    raise ValueError('publish_clock can only be set at start-up')
            check_values(self._values(params))
        except (ValueError, TypeError) as exc:
            self.get_logger().error(f'rejected parameter change: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        if any(p.name == 'real_time_factor' for p in params):
            rtf = [p.value for p in params if p.name == 'real_time_factor'][-1]
            self._make_timer(rtf)
        return SetParametersResult(successful=True)

    def _make_timer(self, rtf=None):
        if rtf is None:
            rtf = self.get_parameter('real_time_factor').value
        if self.timer is not None:
            self.destroy_timer(self.timer)
        period = 1.0 / (self.cfg.rate_hz * rtf) if rtf > 0 else 0.0
        self.timer = self.create_timer(period, self._on_timer)

    # ------------------------------------------------------------------ stepping
    def _on_timer(self):
        if self.done:
            return
        if self._first is not None:
            want = self.get_parameter('min_subscribers').value
            enough = self.state_pub.get_subscription_count() >= want
            if not enough and time.monotonic() - self._waiting_since < \
                    self.get_parameter('wait_for_subscribers_s').value:
                return
            if not enough:
                self.get_logger().warn('flying without the expected subscribers')
            self._publish(self._first)
            self._first = None
            return
        if self.sim.touched_down:
            if not self.get_parameter('loop').value:
                self._finish('touch-down')
                return
            self._t_offset += self.sim.t + 1.0 / self.cfg.rate_hz
            self.cfg = check_values(self._values())
            self.sim = ApproachSimulator(self.cfg)
            self._publish(self.sim.reset())
            return
        s = self.sim.step()
        self._publish(s)
        limit = self.get_parameter('max_sim_time_s').value
        if limit > 0 and self._t_offset + s.t >= limit - 1e-9:
            self._finish(f'max_sim_time_s={limit}')

    def _finish(self, why):
        self.done = True
        if self.timer is not None:
            self.timer.cancel()
        self.get_logger().info(f'approach finished ({why}) after {self.published} samples')

    def _publish(self, s):
        stamp = _to_time(self._t_offset + s.t)
        js = JointState()
        js.header.stamp = stamp
        js.name = list(self.cfg.joint_names)
        js.velocity = [float(v) for v in s.q]
        js.effort = [float(v) for v in s.tau]
        self.state_pub.publish(js)
        w = WrenchStamped()
        w.header.stamp = stamp
        w.header.frame_id = 'wind'
        w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = (float(v) for v in s.force_wind)
        self.wrench_pub.publish(w)
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=stamp))
        self.published += 1


HELP = help_text('sim_bridge', 'JSBSim A320 approach in periodic wind, published as generalized '
                 'velocities [alpha, beta, airspeed] and aerodynamic forces (see the README).',
                 SPECS)


def main(args=None) -> int:
    return run('sim_bridge', lambda ctx: SimBridgeNode(context=ctx), HELP, args)


if __name__ == '__main__':
    sys.exit(main())

"""``dgp_estimator``: the online D-GP estimator node (console script ``estimator``).

A thin rclpy wrapper around :class:`dgp_ros.online.OnlineEstimator` (all numerics and policies
live there, so that bag replay does exactly what the node does).

Interface (DESIGN.md, "ROS interface"):

- subscribes ``generalized_state`` (sensor_msgs/JointState; best-effort subscription, so both
  best-effort and reliable publishers match)
- publishes, from the same callback, for every accepted measurement:
  ``~/damping_force`` (JointState: the measurement's header.stamp and names, velocity = qd,
  effort = tau_hat), ``~/damping_force_stddev`` (JointState, effort = posterior stddev),
  ``~/damping_matrix`` (Float64MultiArray, N x N row-major, layout dims rows/cols; not for
  model=ard), ``~/dissipated_power`` (Float64, qd^T tau_hat)
- ``/diagnostics`` (DiagnosticArray) every ``diagnostics_period_s`` (node clock)
- services ``~/refit``, ``~/reset``, ``~/save_model`` (std_srvs/Trigger)

Parameters: the fields of :class:`EstimatorConfig` (same names and defaults as
``config/estimator.yaml``) plus ``diagnostics_period_s``. Validated at start (invalid -> the node
exits with status 2 and says why) and on every change (a rejected change says why in
SetParametersResult.reason). ``use_sim_time`` is the standard rclpy parameter.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import List

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from dgp_ros.online import ERROR, OK, WARN, EstimatorConfig, OnlineEstimator

NODE_NAME = 'dgp_estimator'

_DESCRIPTIONS = {
    'model': 'full | diag | ard',
    'passivity': 'none | paper | certified | projected',
    'buffer_size': 'samples kept in the GP (window)',
    'min_samples': 'prior-mean estimate until this many samples are buffered',
    'refit_period_s': 'message-stamp seconds between refits (0 = only first fit and on request)',
    'optimize_every_n_refits': 'hyper-parameters re-optimized every n-th refit (0 = first only)',
    'selection': 'all | novelty (skip near-duplicate samples)',
    'selection_min_distance': 'novelty threshold in standardized units',
    'selection_scale': 'per-joint scale for novelty ([] = buffer std)',
    'min_sample_interval_s': 'learn at most one sample per this much stamp time (0 = every '
                             'sample); every message still gets an estimate',
    'joints': 'joint names to select and order ([] = message order)',
    'model_path': 'npz model: loaded at start, saved on refit, shutdown and ~/save_model',
    'refit_mode': 'async (background thread) | sync (in the callback; tests only)',
    'max_abs_velocity': '|velocity| above this is rejected',
    'max_abs_effort': '|effort| above this is rejected',
    'operating_domain': "certified: declared operating box [lo_1..lo_N, hi_1..hi_N] in the "
                        "joints' units, proven with the data box ([] = data box only)",
}

_ARRAY_TYPES = {'joints': Parameter.Type.STRING_ARRAY,
                'selection_scale': Parameter.Type.DOUBLE_ARRAY,
                'operating_domain': Parameter.Type.DOUBLE_ARRAY}


def damping_matrix_msg(D) -> Float64MultiArray:
    """N x N row-major Float64MultiArray with dims rows/cols (size and stride)."""
    n_rows, n_cols = D.shape
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label='rows', size=n_rows, stride=n_rows * n_cols),
                      MultiArrayDimension(label='cols', size=n_cols, stride=n_cols)]
    msg.layout.data_offset = 0
    msg.data = [float(x) for x in D.ravel()]
    return msg


class EstimatorNode(Node):
    """Node ``dgp_estimator``; see the module docstring."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        defaults = EstimatorConfig()
        for f in dataclasses.fields(EstimatorConfig):
            desc = ParameterDescriptor(description=_DESCRIPTIONS.get(f.name, ''))
            if f.name in _ARRAY_TYPES:
                p = self.declare_parameter(f.name, _ARRAY_TYPES[f.name], desc)
                if p.type_ == Parameter.Type.NOT_SET:
                    self.set_parameters([Parameter(f.name, _ARRAY_TYPES[f.name], [])])
            else:
                self.declare_parameter(f.name, getattr(defaults, f.name), desc)
        self.declare_parameter('diagnostics_period_s', 1.0, ParameterDescriptor(
            description='period of /diagnostics (node clock)'))

        config = self._config_from({})          # raises ValueError (main exits with the reason)
        if not self.get_parameter('diagnostics_period_s').value > 0:
            raise ValueError('diagnostics_period_s must be > 0')
        self.estimator = OnlineEstimator(config)
        if self.estimator.load_error:
            self.get_logger().warning(self.estimator.load_error)
        elif self.estimator.trained:
            self.get_logger().info(f'loaded model from {config.model_path}')
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)

        qos_in = QoSProfile(depth=50, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.BEST_EFFORT)
        self.sub = self.create_subscription(JointState, 'generalized_state', self._on_state, qos_in)
        self.pub_force = self.create_publisher(JointState, '~/damping_force', 10)
        self.pub_std = self.create_publisher(JointState, '~/damping_force_stddev', 10)
        self.pub_D = self.create_publisher(Float64MultiArray, '~/damping_matrix', 10)
        self.pub_power = self.create_publisher(Float64, '~/dissipated_power', 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/refit', self._srv_refit)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.create_service(Trigger, '~/save_model', self._srv_save)
        self._diag_timer = self.create_timer(
            float(self.get_parameter('diagnostics_period_s').value), self._publish_diagnostics)
        self._last_msg_time = None
        self.get_logger().info(
            f'{NODE_NAME}: model={config.model} passivity={config.passivity} '
            f'buffer={config.buffer_size} selection={config.selection} '
            f'joints={config.joints or "(message order)"}')

    # ---------------------------------------------------------- parameters
    def _config_from(self, overrides: dict) -> EstimatorConfig:
        values = {}
        for f in dataclasses.fields(EstimatorConfig):
            v = overrides[f.name] if f.name in overrides else self.get_parameter(f.name).value
            if v is None and f.name in _ARRAY_TYPES:
                v = []
            if isinstance(v, (list, tuple)) or type(v).__name__ == 'array':
                v = list(v)
            values[f.name] = v
        return EstimatorConfig.from_dict(values).validate()

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        overrides = {}
        for p in params:
            if p.name == 'diagnostics_period_s':
                if not (isinstance(p.value, (int, float)) and p.value > 0):
                    return SetParametersResult(successful=False,
                                               reason='diagnostics_period_s must be > 0')
            elif p.name in {f.name for f in dataclasses.fields(EstimatorConfig)}:
                overrides[p.name] = [] if (p.value is None and p.name in _ARRAY_TYPES) else p.value
        if not overrides:
            return SetParametersResult(successful=True)
        try:
            self._config_from(overrides)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _post_set_parameters(self, params: List[Parameter]) -> None:
        names = {p.name for p in params}
        if not hasattr(self, 'estimator'):
            return
        if 'diagnostics_period_s' in names:
            self._diag_timer.cancel()
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(
                float(self.get_parameter('diagnostics_period_s').value), self._publish_diagnostics)
        if names - {'diagnostics_period_s', 'use_sim_time'}:
            what = self.estimator.reconfigure(self._config_from({}))
            self.get_logger().info(f'parameters {sorted(names)}: {what}')

    # -------------------------------------------------------------- topics
    def _on_state(self, msg: JointState) -> None:
        self._last_msg_time = self.get_clock().now()
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        est = self.estimator.process(stamp, msg.name, msg.velocity, msg.effort)
        if est is None:
            return
        names = list(est.names) if est.names else list(msg.name)
        out = JointState()
        out.header.stamp = msg.header.stamp
        out.header.frame_id = msg.header.frame_id
        out.name = names
        out.velocity = est.qd.tolist()
        out.effort = est.tau_hat.tolist()
        self.pub_force.publish(out)
        sd = JointState()
        sd.header = out.header
        sd.name = names
        sd.velocity = est.qd.tolist()
        sd.effort = est.stddev.tolist()
        self.pub_std.publish(sd)
        if est.D is not None:
            self.pub_D.publish(damping_matrix_msg(est.D))
        self.pub_power.publish(Float64(data=float(est.power)))

    def diagnostic_status(self) -> DiagnosticStatus:
        d = self.estimator.diagnostics()
        if self._last_msg_time is None:
            d['message'] = 'no measurements received yet; ' + d['message']
            d['level'] = max(d['level'], WARN)
        st = DiagnosticStatus()
        st.level = {OK: DiagnosticStatus.OK, WARN: DiagnosticStatus.WARN,
                    ERROR: DiagnosticStatus.ERROR}[d['level']]
        st.name = f'{self.get_name()}: online D-GP estimator'
        st.hardware_id = self.get_fully_qualified_name()
        st.message = d['message']
        values = []
        for k, v in d.items():
            if k in ('level', 'message'):
                continue
            if k == 'rejected':
                values.extend(KeyValue(key=f'rejected/{r}', value=str(c)) for r, c in v.items())
                continue
            values.append(KeyValue(key=k, value='' if v is None else str(v)))
        st.values = values
        return st

    def _publish_diagnostics(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostic_status()]
        self.pub_diag.publish(arr)

    # ------------------------------------------------------------ services
    def _srv_refit(self, request, response):
        response.success, response.message = self.estimator.request_refit()
        return response

    def _srv_reset(self, request, response):
        self.estimator.reset()
        response.success, response.message = True, 'estimator reset: model, buffer and counters'
        return response

    def _srv_save(self, request, response):
        try:
            path = self.estimator.save()
            response.success, response.message = True, f'saved to {path}'
        except (ValueError, RuntimeError, OSError) as exc:
            response.success, response.message = False, str(exc)
        return response

    def shutdown(self) -> None:
        """Save the current model if model_path is set. A refit still running is not waited
        for beyond a moment (its thread is a daemon; the current model is the one saved)."""
        self.estimator.close(timeout=2.0)
        if self.estimator.config.model_path and self.estimator.trained:
            try:
                path = self.estimator.save()
                self.get_logger().info(f'model saved to {path}')
            except Exception as exc:  # shutdown must not raise
                self.get_logger().error(f'could not save model: {exc}')


def main(args=None):
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = EstimatorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:                    # invalid parameters at start
        print(f'[{NODE_NAME}] invalid parameters: {exc}', file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            node.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())

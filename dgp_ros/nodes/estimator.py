"""
``dgp_estimator``: the online D-GP estimator node (console script ``estimator``).

A thin rclpy wrapper around :class:`dgp_ros.online.OnlineEstimator`: every decision is made
there, so that bag replay does exactly what the node does. ``estimator --help`` lists the
parameters (``dgp_ros.online.config``).

Subscribes ``generalized_state`` (sensor_msgs/JointState, best effort, depth ``queue_depth``) and
publishes, for every accepted measurement, stamped like it:

- ``~/damping_force`` (JointState: names, velocity = qd, effort = tau_hat) and
  ``~/damping_force_stddev`` (effort = posterior standard deviation; computed and published
  only while it has subscribers, as are the two damping matrix topics);
- ``~/damping_matrix_stamped`` (JointState: the measurement's stamp and joint names, velocity =
  qd, effort = D(qd) row-major, N * N entries) and ``~/damping_matrix`` (Float64MultiArray, the
  same N x N row-major, for consumers of the unstamped array); not for model=ard;
- ``~/damping_force_confidence`` (JointState: velocity = qd, effort = the per-joint confidence
  in [0, 1] of the force and the correction, earned one step ahead: a controller's gain on them;
  only while subscribed, published just before the force);
- ``~/dissipated_power`` (Float64, qd^T tau_hat);
- ``~/friction_residual`` (JointState, with inverse_dynamics): what is learned, each sample
  stamped with its own (earlier) time: position, velocity, effort = effort - tau_rb;
- ``~/bias`` (JointState, with bias=true once trained): the learned per-joint bias;
- ``~/rigid_body_correction`` (JointState: position = q, effort = dV/dq(q)): the learned
  conservative correction of the rigid-body model (the payload's gravity the URDF lacks), at the
  message's pose, only while subscribed and when the model has one (docs/CONTRACTS.md).

``/diagnostics`` every ``diagnostics_period_s``; services ``~/refit``, ``~/reset``,
``~/save_model`` (std_srvs/Trigger). SIGINT/SIGTERM: the model is saved (``model_path``) and the
process exits 0 (``nodes.runtime``).
"""
from __future__ import annotations

import dataclasses
import os
import sys
import threading
import time
from typing import List

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray, String
from std_srvs.srv import Trigger

from dgp_ros.nodes.answers import MessagePath
from dgp_ros.nodes.executor import DeferredResponse, WaitSetExecutor
from dgp_ros.nodes.outputs import joint_state
from dgp_ros.nodes.runtime import (check_unknown_overrides, declare_parameters, help_text,
                                   reject_unknown, run, set_batch_handler)
from dgp_ros.online import ERROR, EstimatorConfig, OK, OnlineEstimator, WARN
from dgp_ros.online.config import NODE_PARAMS, PARAMS
from dgp_ros.online.memtrace import start_from_env as trace_memory

NODE_NAME = 'dgp_estimator'
_CONFIG_FIELDS = {f.name for f in dataclasses.fields(EstimatorConfig)}


def _process_cpu_ns() -> int:
    t = os.times()
    return int((t.user + t.system) * 1e9)


class EstimatorNode(Node):
    """Node ``dgp_estimator``; see the module docstring."""

    #: most messages answered per wake-up (timers and services are served between batches)
    MAX_BATCH = 64
    #: history depth of the per-message outputs (module docstring of the publishers)
    ANSWER_HISTORY = 1024

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, allow_undeclared_parameters=True, **kwargs)
        declare_parameters(self, list(PARAMS.values()) + list(NODE_PARAMS.values()))
        check_unknown_overrides(self)
        self._topic_urdf = ''                   # the URDF received on /robot_description
        self._urdf_error = ''
        config = self._config_from({})          # ValueError: main exits 2 with the reason
        self.estimator = OnlineEstimator(config)
        if self.estimator.load_error:
            self.get_logger().warning(self.estimator.load_error)
        elif self.estimator.trained:
            self.get_logger().info(f'loaded model from {config.model_path}')
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)

        depth = int(self.get_parameter('queue_depth').value)
        qos_in = QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.BEST_EFFORT)
        self.sub = self._subscribe_state(qos_in)
        # the wait-set executor (nodes.runtime) hands over every message waiting at once
        set_batch_handler(self.sub, self._on_states, self.MAX_BATCH)
        # a wake-up answers up to MAX_BATCH messages at once: the history of every per-message
        # output holds a second of a 1 kHz stream (a reliable reader gets all of them): after a
        # stall of the whole machine the node answers what waited in back-to-back bursts,
        # faster than a reader stalled with it acknowledges (at 4 x MAX_BATCH, 2.4 % of the
        # answers were lost to a 0.26 s stall of every process, bench/arm_floor.py)
        out = self.ANSWER_HISTORY
        self.pub_force = self.create_publisher(JointState, '~/damping_force', out)
        self.pub_std = self.create_publisher(JointState, '~/damping_force_stddev', out)
        self.pub_conf = self.create_publisher(JointState, '~/damping_force_confidence', out)
        self.pub_D = self.create_publisher(Float64MultiArray, '~/damping_matrix', out)
        self.pub_D_stamped = self.create_publisher(JointState, '~/damping_matrix_stamped', out)
        self.pub_power = self.create_publisher(Float64, '~/dissipated_power', out)
        self.pub_residual = self.create_publisher(JointState, '~/friction_residual', out)
        self.pub_bias = self.create_publisher(JointState, '~/bias', 10)
        self.pub_corr = self.create_publisher(JointState, '~/rigid_body_correction', out)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/refit', self._srv_refit)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.create_service(Trigger, '~/save_model', self._srv_save)
        self._diag_timer = self.create_timer(
            float(self.get_parameter('diagnostics_period_s').value), self._publish_diagnostics)
        if config.awaits_urdf:
            # the ROS convention (robot_state_publisher, ros2_control): the robot model is
            # published once, transient local, on /robot_description
            self.sub_urdf = self.create_subscription(
                String, '/robot_description', self._on_robot_description,
                QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL))
            self.get_logger().info('inverse_dynamics=urdf without robot_description or '
                                   'urdf_file: waiting for the URDF on /robot_description')
        self._service_lock = threading.Lock()    # ~/save_model and ~/reset, one at a time
        self._last_msg_time = None
        self.path = MessagePath(self)         # raw messages in, answers out (nodes.answers)
        # CPU of the message path: this thread's CPU in the message callbacks, against its
        # whole CPU and the process's since the first message (/diagnostics)
        self._cpu = {'msgs': 0, 'cb_ns': 0, 'thread0': None, 'proc0': None}
        self.get_logger().info(
            f'{NODE_NAME}: model={config.model} passivity={config.passivity} '
            f'prior={config.prior} buffer={config.buffer_size} queue_depth={depth} '
            f'inverse_dynamics={config.inverse_dynamics or "none"} '
            f'joints={config.joints or "(message order)"}')

    def _subscribe_state(self, qos):
        """
        Subscribe to the measurements, with the middleware's message-lost event where it has one.

        Losses are then counted where they happen (``messages_lost``); an RMW without the event
        leaves only the stamp gaps to estimate them (``messages_missing``).
        """
        from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
        events = SubscriptionEventCallbacks(
            message_lost=lambda info: self.estimator.note_lost(info.total_count_change))
        try:
            return self.create_subscription(JointState, 'generalized_state', self._on_state,
                                            qos, event_callbacks=events, raw=True)
        except UnsupportedEventTypeError:
            self.get_logger().info('the middleware reports no lost messages: they are '
                                   'estimated from stamp gaps')
            return self.create_subscription(JointState, 'generalized_state', self._on_state,
                                            qos, raw=True)

    def _on_robot_description(self, msg: String) -> None:
        """Build the rigid-body model from a URDF on /robot_description (again on a new one)."""
        if msg.data == self._topic_urdf:
            return
        try:
            what = self.estimator.reconfigure(dataclasses.replace(
                self.estimator.config, robot_description=msg.data))
        except ValueError as exc:
            self._urdf_error = (f'the URDF on /robot_description is not usable ({exc}); '
                                'waiting for another one')
            self.get_logger().error(self._urdf_error)
            return
        self._topic_urdf, self._urdf_error = msg.data, ''
        self.get_logger().info(f'robot model from /robot_description ({len(msg.data)} bytes, '
                               f'joints {self.estimator.learner.joint_names()}): {what}')

    # ---------------------------------------------------------- parameters
    def _config_from(self, overrides: dict) -> EstimatorConfig:
        values = {}
        for name in _CONFIG_FIELDS:
            v = overrides[name] if name in overrides else self.get_parameter(name).value
            if v is None and PARAMS[name].type.endswith('[]'):
                v = []
            if isinstance(v, (list, tuple)) or type(v).__name__ == 'array':
                v = list(v)
            values[name] = v
        if self._topic_urdf and not (values['robot_description'] or values['urdf_file']):
            values['robot_description'] = self._topic_urdf      # what the topic gave
        return EstimatorConfig.from_dict(values).validate()

    def _on_set_parameters(self, params: List) -> SetParametersResult:
        bad = reject_unknown(self, params)
        if bad is not None:
            return bad
        overrides = {p.name: p.value for p in params if p.name in _CONFIG_FIELDS}
        if not overrides or not hasattr(self, 'estimator'):
            return SetParametersResult(successful=True)
        try:
            cfg = self._config_from(overrides)
            if self.estimator.names:
                cfg.check_dimension(len(self.estimator.names))
            self.estimator.check_reconfigure(cfg)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _post_set_parameters(self, params: List) -> None:
        names = {p.name for p in params}
        if not hasattr(self, 'estimator'):
            return
        if 'diagnostics_period_s' in names:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(
                float(self.get_parameter('diagnostics_period_s').value), self._publish_diagnostics)
        if 'queue_depth' in names:
            self.get_logger().warning('queue_depth applies at the next start')
        if names & _CONFIG_FIELDS:
            what = self.estimator.reconfigure(self._config_from({}))
            self.get_logger().info(f'parameters {sorted(names)}: {what}')

    # -------------------------------------------------------------- topics
    def _take_waiting(self, first: bytes) -> List[bytes]:
        """``first`` and every message already waiting in the subscription (at most MAX_BATCH)."""
        msgs = [first]
        sub = self.sub
        try:
            with sub.handle:
                while len(msgs) < self.MAX_BATCH:
                    got = sub.handle.take_message(sub.msg_type, sub.raw)
                    if got is None:
                        break
                    msgs.append(got[0])
        except Exception:       # noqa: BLE001 - a destroyed handle at shutdown: answer these
            pass
        return msgs

    def _on_state(self, raw: bytes) -> None:
        """Answer one message and every one waiting behind it (rclpy's executors)."""
        self._on_states(self._take_waiting(raw), None)

    def _on_states(self, raws: List[bytes], infos=None) -> None:
        """
        Answer serialized messages together: one vectorized prediction for k queries.

        The wait-set executor hands over every message waiting (at most ``MAX_BATCH``) with their
        message infos. The codec reads them into arrays; a run of like messages is answered as
        one batch (``OnlineEstimator.process_arrays``), anything else message by message.
        """
        t0 = time.thread_time_ns()
        c = self._cpu
        if c['thread0'] is None:
            c['thread0'], c['proc0'] = t0, _process_cpu_ns()
        clock = self.get_clock()
        # the node's clock: the wall clock unless simulated time runs (use_sim_time)
        now = clock.now().nanoseconds if getattr(clock, 'ros_time_is_active', True) \
            else time.time_ns()
        self._last_msg_time = now
        self.path.answer(raws, now)
        c['msgs'] += len(raws)
        c['cb_ns'] += time.thread_time_ns() - t0

    def cpu_per_message(self) -> dict:
        """
        CPU per message since the first one (us): the message path and the rest.

        ``message_path``: in the message callbacks (validate, hand over, answer, publish);
        ``executor``: the rest of this thread (waiting, taking, dispatching; the few timer and
        service callbacks too); ``process``: every thread (DDS, the snapshot receiver too).
        Empty before the first message.
        """
        c = self._cpu
        if c['thread0'] is None or not c['msgs']:
            return {}
        n = c['msgs']
        thread = time.thread_time_ns() - c['thread0']
        return {'cpu_message_path_us_per_msg': round(c['cb_ns'] / n * 1e-3, 1),
                'cpu_executor_us_per_msg': round((thread - c['cb_ns']) / n * 1e-3, 1),
                'cpu_process_us_per_msg': round((_process_cpu_ns() - c['proc0']) / n * 1e-3, 1)}

    def diagnostic_status(self) -> DiagnosticStatus:
        d = self.estimator.diagnostics()
        if self._last_msg_time is None:
            d['message'] = 'no measurements received yet; ' + d['message']
            d['level'] = max(d['level'], WARN)
        if self._urdf_error:
            d['message'] = self._urdf_error + '; ' + d['message']
            d['level'] = ERROR
        if self.path.age:
            a = np.array(self.path.age)
            d['stamp_to_answer_median_s'] = float(np.median(a))
            d['stamp_to_answer_p99_s'] = float(np.percentile(a, 99))
        if d.get('bias') is None:
            d.pop('bias', None)
        d.update(self.cpu_per_message())
        d['messages_fallback'] = self.path.fallback
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
        model = self.estimator.model
        if model is not None and self.estimator.config.bias and self.estimator.names:
            self.pub_bias.publish(joint_state(arr.header, self.estimator.names, (), (),
                                              model.bias_.tolist()))

    # ------------------------------------------------------------ services
    def _srv_refit(self, request, response):
        if not isinstance(self.executor, WaitSetExecutor):    # rclpy's: the answer, now
            response.success, response.message = self.estimator.request_refit()
            return response
        # the learner's reply answers it later: the message path does not wait for the learner;
        # a learner busy for longer than REFIT_REPLY_S (a child at lower priority under a
        # flood took 170-630 ms) gets the request queued, and the caller an answer saying so
        later = DeferredResponse()

        def done(result):
            response.success, response.message = result
            later.send(response)

        def busy():
            timer.cancel()
            self.destroy_timer(timer)
            queued = type(response)()       # not the learner's: that one may be on its way
            queued.success = True
            queued.message = ('refit requested: the learner is busy and will take it up; '
                              '/diagnostics reports it (refits_started, last_refit_error)')
            later.send(queued)
        timer = self.create_timer(self.REFIT_REPLY_S, busy)
        self.estimator.request_refit_async(done)
        return later

    #: longest wait for the learner's reply to ~/refit before answering that it is queued [s]
    REFIT_REPLY_S = 0.02

    def _srv_reset(self, request, response):
        return self._in_thread(response, self._reset)

    def _reset(self, response):
        self.estimator.reset()
        response.success, response.message = True, 'estimator reset: model, buffer and counters'

    def _srv_save(self, request, response):
        return self._in_thread(response, self._save)

    def _save(self, response):
        try:
            path = self.estimator.save()
            response.success, response.message = True, f'saved to {path}'
        except (ValueError, RuntimeError, OSError) as exc:
            response.success, response.message = False, str(exc)

    def _in_thread(self, response, work):
        """
        Run a service's ``work(response)`` in a thread of its own and answer when it is done.

        A save or a reset waits for the learner process (a save writes the file there, a refit
        may be running): the executor's thread goes on answering messages and serving the other
        services meanwhile. One at a time (a second waits for the first). With rclpy's
        executors the work runs in the callback.
        """
        if not isinstance(self.executor, WaitSetExecutor):
            work(response)
            return response
        later = DeferredResponse()

        def run():
            with self._service_lock:
                try:
                    work(response)
                except Exception as exc:    # noqa: BLE001 - the caller gets the reason
                    response.success, response.message = False, f'{type(exc).__name__}: {exc}'
            later.send(response)
        threading.Thread(target=run, name='dgp_service', daemon=True).start()
        return later

    def shutdown(self) -> None:
        """
        Save the current model if ``model_path`` is set.

        A refit still running is waited for at most 2 s; the current model is the one saved. Never
        raises.
        """
        try:
            self.estimator.wait_for_refit(2.0)
            if self.estimator.config.model_path and self.estimator.trained:
                # no catching up first: ros2 launch sends SIGTERM 5 s after SIGINT
                path = self.estimator.save(learn_waiting=False)
                self.get_logger().info(f'model saved to {path}')
            elif self.estimator.config.model_path:
                self.get_logger().warning(
                    f'no model saved to {self.estimator.config.model_path}: none was trained '
                    'yet (the first fit had not finished; a loaded computer makes it slower)')
        except Exception as exc:  # noqa: BLE001 - shutdown must not raise
            self.get_logger().error(f'could not save model: {exc}')
        finally:
            self.estimator.close(timeout=1.0)


HELP = help_text(
    'estimator', 'The online D-GP estimator node (dgp_estimator): learns the damping force '
    'tau_d(qd) = D(qd) qd from sensor_msgs/JointState on generalized_state and publishes passive '
    'estimates (see the README).', list(PARAMS.values()) + list(NODE_PARAMS.values()),
    remaps='remap the input: --ros-args -r generalized_state:=/joint_states')


#: the node's GIL switch interval (s): a thread holding the GIL (the snapshot receiver
#: unpickling and preparing a model, a save) gives it to the message path within this time
#: (Python's default is 5 ms)
SWITCH_INTERVAL_S = 0.0005


def main(args=None) -> int:
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    trace_memory('node')         # a soak's tracemalloc (DGP_TRACEMALLOC), else none
    return run('estimator', lambda ctx: EstimatorNode(context=ctx), HELP, args)


if __name__ == '__main__':
    sys.exit(main())

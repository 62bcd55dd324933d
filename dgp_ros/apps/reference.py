"""
The ROS reference from the code: ``python -m dgp_ros.apps.reference > docs/REFERENCE.md``.

What the estimator node declares, read off the node itself: every parameter (the tables of
``online.config`` and of each node: name, type, default, range, what it does), every topic and
service the estimator creates with its type and QoS (introspected from a node made in this
process, with ``inverse_dynamics=urdf`` awaiting ``/robot_description`` so that every one
exists), and every key its ``/diagnostics`` status carries (from a node that answered a few
messages). What a topic is for is written here (:data:`TOPICS`): a topic without a line, or a
line without a topic, is an error, so the reference cannot drift from the node;
``test/test_reference.py`` keeps docs/REFERENCE.md equal to this output.
"""
from __future__ import annotations

import sys
from typing import List

__all__ = ['reference', 'TOPICS', 'main']

#: what each of the estimator's topics and services is for (its name as the node resolves it)
TOPICS = {
    '/generalized_state': 'the measurements: velocity and effort (position with '
                          '`inverse_dynamics`); remap it to your `/joint_states`; message-lost '
                          'events counted where the RMW has them',
    '/robot_description': 'only with `inverse_dynamics=urdf` and neither `robot_description` '
                          'nor `urdf_file`: the URDF (robot_state_publisher publishes it); a new '
                          'one reconfigures',
    '/dgp_estimator/damping_force': 'per accepted message: its header and names, velocity = qd, '
                                    'effort = tau_hat [N m], passive (qd . tau_hat >= 0)',
    '/dgp_estimator/damping_force_confidence': 'effort = per-joint confidence in [0, 1] of the '
                                               'force, earned one step ahead; only while '
                                               'subscribed, just before the force of the same '
                                               'stamp',
    '/dgp_estimator/damping_force_stddev': 'effort = posterior standard deviation; computed '
                                           'only while subscribed',
    '/dgp_estimator/damping_matrix_stamped': 'effort = D(qd) row-major (N N), velocity = qd; '
                                             'only while subscribed; not for `model=ard`',
    '/dgp_estimator/damping_matrix': 'the same N x N row-major, unstamped (dims `rows`, '
                                     '`cols`); only while subscribed',
    '/dgp_estimator/dissipated_power': 'qd^T tau_hat per answer [W]',
    '/dgp_estimator/friction_residual': 'with `inverse_dynamics`: what is learned, each '
                                        'stamped with its own (earlier) time; effort = effort '
                                        '- tau_rb; only while subscribed',
    '/dgp_estimator/rigid_body_correction': 'effort = the learned correction of the rigid-body '
                                            "model at the message's pose (dV/dq(q): a payload's "
                                            'gravity); while subscribed, once learned',
    '/dgp_estimator/bias': 'with `bias=true` once trained, every `diagnostics_period_s`: effort '
                           '= the learned per-joint bias',
    '/diagnostics': 'every `diagnostics_period_s`: level, message and the keys below',
    '/dgp_estimator/refit': "refit now (the learner's answer, or after 20 ms that the request "
                            'is queued to a busy learner)',
    '/dgp_estimator/reset': 'forget the model, the buffer and the counters',
    '/dgp_estimator/save_model': 'save the model to `model_path`, once it has learned every '
                                 'sample sent before the call',
}

#: keys the node adds once messages arrived over DDS (the stamp-to-answer age, the CPU a
#: message costs)
NODE_KEYS = ('stamp_to_answer_median_s', 'stamp_to_answer_p99_s', 'cpu_message_path_us_per_msg',
             'cpu_executor_us_per_msg', 'cpu_process_us_per_msg')
#: what rclpy gives every node (its parameter services, parameter events, the log): not listed
_RCLPY_TOPICS = ('/parameter_events', '/rosout')
#: services rclpy gives every node (parameters): listed apart, not described
_PARAMETER_SERVICES = ('describe_parameters', 'get_parameter_types', 'get_parameters',
                       'list_parameters', 'set_parameters', 'set_parameters_atomically',
                       'get_type_description')


def _type(t) -> str:
    mod = t.__module__.split('.')[0]
    return f'{mod}/{t.__name__}'


def _qos(q) -> str:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    rel = 'reliable' if q.reliability == ReliabilityPolicy.RELIABLE else 'best effort'
    dur = ', transient local' if q.durability == DurabilityPolicy.TRANSIENT_LOCAL else ''
    return f'{rel}, depth {q.depth}{dur}'


def _table(headers: List[str], rows: List[list]) -> List[str]:
    out = ['| ' + ' | '.join(headers) + ' |', '|' + '---|' * len(headers)]
    return out + ['| ' + ' | '.join(str(c).replace('|', '\\|') for c in r) + ' |' for r in rows]


def _params(specs) -> List[str]:
    import json
    rows = []
    for s in specs:
        rng = s.range_text()
        rows.append([f'`{s.name}`', s.type, f'`{json.dumps(s.default)}`',
                     rng + (' (start-up only)' if s.read_only else ''), s.description])
    return _table(['name', 'type', 'default', 'range', 'what it does'], rows)


def _estimator_node():
    """Make the estimator node with every topic (a URDF awaited), and feed it a few messages."""
    import rclpy
    from rclpy.parameter import Parameter
    from dgp_ros.nodes.estimator import EstimatorNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = EstimatorNode(context=ctx, parameter_overrides=[
        Parameter('inverse_dynamics', Parameter.Type.STRING, 'urdf')])
    return ctx, node


def _diagnostic_keys() -> List[str]:
    """Return the keys of a trained estimator's status as the node publishes them (no traffic)."""
    import numpy as np
    import rclpy
    from dgp_ros.nodes.estimator import EstimatorNode
    from rclpy.parameter import Parameter
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    # in line: no learner process, the same keys at every run
    node = EstimatorNode(context=ctx, parameter_overrides=[
        Parameter('refit_mode', Parameter.Type.STRING, 'sync')])
    try:
        est = node.estimator
        rng = np.random.default_rng(0)
        for i in range(60):
            qd = rng.normal(size=2)
            est.process(0.01 * i, ['a', 'b'], qd, 2.0 * qd)
        node._last_msg_time = 0.0
        keys = [kv.key for kv in node.diagnostic_status().values]
        import inspect
        src = inspect.getsource(EstimatorNode)
        missing = [k for k in NODE_KEYS if f"'{k}'" not in src]
        if missing:
            raise ValueError(f'reference: the node no longer publishes {missing}')
        return keys + [k for k in NODE_KEYS if k not in keys]
    finally:
        node.shutdown()
        node.destroy_node()
        ctx.try_shutdown()


def reference() -> str:
    """Return the text of docs/REFERENCE.md (module docstring)."""
    from dgp_ros.nodes import arm_loop, arm_sim, controller
    from dgp_ros.online.config import NODE_PARAMS, PARAMS
    from sim_bridge import node as sim_node
    lines = ['# dgp_ros reference: the ROS interface', '',
             'Generated from the code by `python -m dgp_ros.apps.reference > docs/REFERENCE.md` '
             '(`test/test_reference.py` fails when it drifts). Topic names are the defaults, '
             "all remappable (`--ros-args -r from:=to`); `~` is the node's name, "
             '`dgp_estimator`.', '',
             '## estimator (node `dgp_estimator`)', '', '### Topics and services', '']
    ctx, node = _estimator_node()
    try:
        rows, seen = [], set()
        for kind, items in (('sub', node.subscriptions), ('pub', node.publishers)):
            for x in sorted(items, key=lambda x: x.topic_name):
                if x.topic_name in _RCLPY_TOPICS:
                    continue
                seen.add(x.topic_name)
                rows.append([kind, f'`{x.topic_name}`', f'`{_type(x.msg_type)}`',
                             _qos(x.qos_profile), _describe(x.topic_name)])
        for name, t in sorted((node.resolve_service_name(s.srv_name), s.srv_type)
                              for s in node.services):
            if name.rsplit('/', 1)[-1] in _PARAMETER_SERVICES:
                continue
            seen.add(name)
            rows.append(['srv', f'`{name}`', f'`{_type(t)}`', '', _describe(name)])
    finally:
        node.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    stale = sorted(set(TOPICS) - seen)
    if stale:
        raise ValueError(f'reference: described but not created by the node: {stale}')
    lines += _table(['', 'name', 'type', 'QoS', 'what it carries'], rows)
    lines += ['', 'Besides, the parameter services every rclpy node has (`~/get_parameters`, '
              '`~/set_parameters`, ...).', '', '### Parameters', '',
              '`estimator --help` prints the same; `config/estimator.yaml` holds every default. '
              'A change at run time is checked before it is accepted.', '']
    lines += _params(list(PARAMS.values()) + list(NODE_PARAMS.values()))
    keys = _diagnostic_keys()
    lines += ['', '### `/diagnostics` keys', '',
              'One `DiagnosticStatus` named `dgp_estimator: online D-GP estimator`: level (OK, '
              'WARN with the reason and the fix, ERROR), message, and these keys (a trained '
              "estimator's; `rejected/<reason>` once per reason of `online.health."
              'REJECT_REASONS`):', '', ', '.join(f'`{k}`' for k in keys), '']
    for title, specs in (('sim_bridge', sim_node.SPECS), ('dgp-arm-sim', arm_sim.SPECS),
                         ('dgp-arm-loop', arm_loop.SPECS), ('dgp-controller', controller.SPECS)):
        lines += [f'## {title}: parameters', ''] + _params(specs) + ['']
    return '\n'.join(lines).rstrip() + '\n'


def _describe(name: str) -> str:
    if name not in TOPICS:
        raise ValueError(f'reference: the node creates {name!r}, which TOPICS does not describe')
    return TOPICS[name]


def main(argv=None) -> int:
    sys.stdout.write(reference())
    return 0


if __name__ == '__main__':
    sys.exit(main())

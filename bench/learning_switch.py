#!/usr/bin/env python3
"""
The learning switch live: a node learning the real Panda stream, switched off and on.

The real Panda's friction residual (``live_procs.real_stream``: the shared log's first 7.5 s,
looped at the logger's own timing, ~1 kHz, 7 joints; read there, never copied) is played into
an ``estimator`` node with its defaults (``model_path`` set), over DDS (localhost, a domain of
its own). Two ways to stop learning, each scored the same way:

* ``parameter``: the node learns for ``--learn`` s, then ``learning`` is set to false at run
  time (``/dgp_estimator/set_parameters``, what ``ros2 param set`` calls); once /diagnostics
  says ``learning: off`` the stream goes on for ``--off`` s; then ``learning`` is set to true
  again for ``--on`` s;
* ``command line``: a new node started with ``--ros-args -p learning:=false -p
  model_path:=<the file the first one saved>`` serves the same stream for ``--off`` s.

Scored: samples added after the switch took effect (``samples_added`` on /diagnostics), every
answer received from 0.5 s after ``learning: off`` against ``load_model(model_path).predict`` of
its velocity (one query per call; equal bits counted, the largest difference beside), the
guarantee, ``certified`` and ``certificate_stale`` while off, and whether learning resumed.

Usage: bench/learning_switch.py [--quick] [--out DIR] [--data DIR] [--learn S] [--off S]
[--on S]
"""
from __future__ import annotations

import os
import shutil
import signal
import sys
import tempfile
import time

import numpy as np

import common as C  # noqa: E402
from certification import panda_dir  # noqa: E402,I100

NAME = 'learning_switch'
TITLE = 'The learning switch live: the real Panda stream, learning off and on'
BIN = os.path.dirname(sys.executable)
PROCS = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'live_procs.py')
NAMES = [f'panda_joint{j}' for j in range(1, 8)]


def _extra(p):
    p.add_argument('--data', default=None, help="the real Panda log's folder")
    p.add_argument('--learn', type=float, default=20.0, help='seconds learning first')
    p.add_argument('--off', type=float, default=10.0, help='seconds served with learning off')
    p.add_argument('--on', type=float, default=5.0, help='seconds learning again')
    p.add_argument('--keep', default='', help="keep the children's logs in this folder")


class Watch:
    """An rclpy node of this process: /diagnostics and a parameter client (answers: listener)."""

    def __init__(self):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rcl_interfaces.srv import SetParameters
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('learning_switch_watch', context=self.ctx)
        self.diags = []
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        self.cli = self.node.create_client(SetParameters, '/dgp_estimator/set_parameters')
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)

    def _on_diag(self, m):
        for st in m.status:
            if 'estimator' in st.name:
                d = {v.key: v.value for v in st.values}
                d['_t'] = time.monotonic()
                d['_wall'] = time.time()
                d['_message'] = st.message
                self.diags.append(d)

    def spin(self, seconds: float, until=None, procs=()) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if until is not None and until():
                return True
            self.ex.spin_once(timeout_sec=0.02)
            for p in procs:
                if p.poll() is not None:
                    raise RuntimeError(f'{p.args[0]} exited with {p.returncode}')
        return until is not None and until()

    def last(self, key, default=''):
        return self.diags[-1].get(key, default) if self.diags else default

    def set_learning(self, on: bool) -> tuple:
        """Set the node's parameter learning at run time; (successful, reason, seconds)."""
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters
        if not self.cli.wait_for_service(timeout_sec=30.0):
            return False, 'no set_parameters service', 0.0
        req = SetParameters.Request()
        req.parameters = [Parameter(name='learning', value=ParameterValue(
            type=ParameterType.PARAMETER_BOOL, bool_value=bool(on)))]
        t0 = time.monotonic()
        fut = self.cli.call_async(req)
        self.spin(60.0, fut.done)
        if not fut.done():
            return False, 'no answer', time.monotonic() - t0
        r = fut.result().results[0]
        return bool(r.successful), r.reason, time.monotonic() - t0

    def close(self):
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _estimator(model_path, extra=()):
    return [os.path.join(BIN, 'estimator'), '--ros-args', '-r', 'generalized_state:=/joint_states',
            '-p', f'joints:={NAMES!r}'.replace("'", '"'), '-p', f'model_path:={model_path}',
            '-p', 'diagnostics_period_s:=0.25', *extra]


def _player(data, seconds, work, tag):
    return [sys.executable, PROCS, 'player', '--stream', data, '--seconds', f'{seconds:g}',
            '--out', os.path.join(work, f'player_{tag}.json'),
            '--ready', os.path.join(work, f'player_{tag}.ready'), '--min-subscribers', '2',
            '--wait', '60']


def _listener(work, tag):
    return [sys.executable, PROCS, 'listener', '--out', os.path.join(work, f'answers_{tag}.npz'),
            '--ready', os.path.join(work, f'listener_{tag}.ready')]


def _answers(work, tag):
    """Return (stamps s, velocities, efforts) of the answers the listener ``tag`` received."""
    z = np.load(os.path.join(work, f'answers_{tag}.npz'), allow_pickle=False)
    return z['ans'][:, 0] * 1e-9, z['velocity'], z['effort']


def _score_answers(answers, t_from: float, t_to: float, model_path: str) -> dict:
    """
    Compare the answers to the messages stamped in [t_from, t_to] with the saved model's.

    The player stamps each message with its wall-clock deadline: the answers are selected by the
    stamp of the message they answer (the listener, a process of its own, takes them all).
    """
    from dgp_ros.gp import load_model
    m = load_model(model_path)
    stamps, V, E = answers
    keep = (stamps >= t_from) & (stamps <= t_to)
    got = list(zip(V[keep], E[keep]))
    if not got:
        return {'answers': 0}
    ref = np.array([m.predict(qd[None])[0] for qd, _ in got])
    tau = np.array([t for _, t in got])
    diff = np.abs(tau - ref)
    same = np.all(tau == ref, axis=1)
    cert = m.certificate()
    batch = m.predict(np.array([qd for qd, _ in got]))
    return {'answers': len(got), 'bit_identical': int(same.sum()),
            'predict_one_vs_batch_rel': float(np.abs(batch - ref).max() /
                                              max(np.abs(ref).max(), 1e-300)),
            'max_abs_diff': float(diff.max()),
            'max_rel_diff': float(diff.max() / max(np.abs(ref).max(), 1e-300)),
            'file_guarantee': cert.guarantee, 'file_method': cert.method}


def run_parameter(a, data, work, env, log) -> dict:
    """Run the ``parameter`` case (module docstring); returns its record."""
    model_path = os.path.join(work, 'friction.npz')
    total = a.learn + a.off + a.on + 150.0      # stopped at the end (SIGTERM)
    w = Watch()
    est = pl = li = None
    r = {'case': 'parameter (ros2 param set learning false / true)'}
    try:
        est = C.start(_estimator(model_path), log, env)
        li = C.start(_listener(work, 'p'), log, env)
        pl = C.start(_player(data, total, work, 'p'), log, env)
        if not w.spin(120.0, lambda: w.last('trained') == 'True', [est]):
            raise RuntimeError('the estimator never trained')
        w.spin(a.learn, procs=[est, pl])
        before = dict(w.diags[-1])
        ok, reason, secs = w.set_learning(False)
        r.update(set_off_ok=ok, set_off_reason=reason, set_off_call_s=secs)
        t_req = time.monotonic()
        if not w.spin(120.0, lambda: w.last('learning') == 'off', [est, pl]):
            raise RuntimeError(f'learning never off: {w.last("learning")}')
        off = dict(w.diags[-1])
        r['freeze_s'] = off['_t'] - t_req
        w.spin(a.off, procs=[est, pl])
        end = dict(w.diags[-1])
        t_end = time.time()
        r.update(added_before_request=int(before['samples_added']),
                 added_at_off=int(off['samples_added']), added_at_end=int(end['samples_added']),
                 not_learned=int(end.get('samples_not_learned', 0)),
                 refits_at_off=int(off['refits_started']),
                 refits_at_end=int(end['refits_started']),
                 guarantee=end['guarantee'], certified=end['certified'],
                 stale=end['certificate_stale'], message=end['_message'],
                 accepted_off=int(end['messages_accepted']) - int(off['messages_accepted']),
                 certified_share_off=end.get('certified_share'))
        window = (off['_wall'] + 0.5, t_end)
        frozen_path = os.path.join(work, 'frozen.npz')
        shutil.copyfile(model_path, frozen_path)    # the file as learning stopped (scored below)
        ok, reason, _ = w.set_learning(True)
        r['set_on_ok'] = ok
        t_on = time.monotonic()
        w.spin(a.on, procs=[est, pl])
        again = dict(w.diags[-1])
        r.update(learning_after_on=again['learning'],
                 added_after_on=int(again['samples_added']) - int(end['samples_added']),
                 on_s=again['_t'] - t_on)
    finally:
        C.stop(pl, signal.SIGTERM, group=True)
        C.stop(li, wait=180.0, group=True)       # it deserializes every answer before it writes
        C.stop(est, group=True)
        w.close()
    r['scored'] = _score_answers(_answers(work, 'p'), *window, frozen_path)
    r['model_path'] = model_path
    return r


def run_command_line(a, data, work, env, log, model_path) -> dict:
    """Run the ``command line`` case: a node started with learning:=false and the model."""
    w = Watch()
    est = pl = li = None
    r = {'case': 'command line (--ros-args -p learning:=false -p model_path:=...)'}
    try:
        est = C.start(_estimator(model_path, ['-p', 'learning:=false']), log, env)
        li = C.start(_listener(work, 'c'), log, env)
        pl = C.start(_player(data, a.off + 150.0, work, 'c'), log, env)
        if not w.spin(120.0, lambda: w.last('trained') == 'True' and
                      int(w.last('messages_received', '0')) > 0, [est]):
            raise RuntimeError('the frozen estimator never answered')
        first = dict(w.diags[-1])
        w.spin(a.off, procs=[est, pl])
        end = dict(w.diags[-1])
        t_end = time.time()
        r.update(learning=end['learning'], added_at_start=int(first['samples_added']),
                 added_at_end=int(end['samples_added']),
                 not_learned=int(end.get('samples_not_learned', 0)),
                 refits_at_end=int(end['refits_started']), guarantee=end['guarantee'],
                 certified=end['certified'], stale=end['certificate_stale'],
                 load_error=end.get('load_error', ''), message=end['_message'],
                 accepted_off=int(end['messages_accepted']))
    finally:
        C.stop(pl, signal.SIGTERM, group=True)
        C.stop(li, wait=180.0, group=True)       # it deserializes every answer before it writes
        C.stop(est, group=True)
        w.close()
    r['scored'] = _score_answers(_answers(work, 'c'), first['_wall'] + 0.5, t_end, model_path)
    return r


def section(a, runs, wall) -> str:
    rows = []
    for r in runs:
        s = r.get('scored', {})
        added = (f"{r['added_at_end'] - r['added_at_off']} (at off {r['added_at_off']}, "
                 f"{r['added_at_off'] - r['added_before_request']} between the request and "
                 'off)' if 'added_at_off' in r else
                 f"{r.get('added_at_end', '-')} (loaded model)")
        rows.append([r['case'], added, r.get('accepted_off', '-'),
                     f"{s.get('bit_identical', '-')} / {s.get('answers', '-')}",
                     f"{C.fmt(s.get('max_rel_diff'))} (predict, one query against a batch: "
                     f"{C.fmt(s.get('predict_one_vs_batch_rel'))})",
                     f"{r.get('guarantee')} (certified {r.get('certified')}, stale "
                     f"{r.get('stale')})",
                     C.fmt(r.get('freeze_s')) if 'freeze_s' in r else '-',
                     (f"{r.get('learning_after_on')}: +{r.get('added_after_on')} samples in "
                      f"{r.get('on_s', 0):.1f} s") if 'learning_after_on' in r else '-'])
    body = C.header_lines(TITLE, 'bench/learning_switch.py', a.quick, wall) + (
        f"\nThe real Panda's friction residual (the shared log's first 7.5 s looped at its own "
        f'timing, 7 joints) into `estimator` with its defaults over DDS; learning {a.learn:g} s, '
        f'then off for {a.off:g} s, then on for {a.on:g} s (module docstring of the script). '
        'Answers to the messages stamped from 0.5 s after `learning: off` compared with '
        "`load_model(model_path).predict(qd)`, one query per call (the model's predict itself "
        'differs by a few ulps between one query and a batch: bit-identical counts exact '
        'equality, the largest difference is relative to the largest answer).\n\n') + C.md_table(
        ['case', 'samples added while off', 'messages answered while off',
         'answers bit-identical / scored',
         'largest difference, relative', 'guarantee while off', 'switch to off (s)',
         'switched on again'], rows)
    return body


def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv, _extra)
    data = panda_dir(a.data)
    if data is None:
        C.log('learning_switch: the real Panda log is not here (--data): nothing to run')
        return 0
    if a.quick:
        a.learn, a.off, a.on = 8.0, 4.0, 3.0
    env = C.dds_env(120, 200)
    env['ROS_DOMAIN_ID'] = os.environ.get('ROS_DOMAIN_ID') or env['ROS_DOMAIN_ID']
    os.environ.update({k: env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    t0 = time.perf_counter()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        work = a.keep or tmp
        os.makedirs(work, exist_ok=True)
        with open(os.path.join(work, 'children.log'), 'w') as log:
            r = run_parameter(a, data, work, env, log)
            C.log(f'learning_switch: {r}')
            runs.append(r)
            r2 = run_command_line(a, data, work, env, log, r['model_path'])
            C.log(f'learning_switch: {r2}')
            runs.append(r2)
    C.write_section(a.out, NAME, section(a, runs, time.perf_counter() - t0))
    import json
    with open(os.path.join(C.plot_dir(a.out), 'learning_switch_runs.json'), 'w') as f:
        json.dump(runs, f, indent=1, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""
The processes of bench/arm_live.py, one role each: player, listener, prober, estimator, hog.

* ``player``: a simulated Panda's raw /joint_states (7 joints and a finger joint, like a driver)
  published at absolute deadlines in phases ``RATE:SECONDS,...``; each phase samples the
  trajectory at its own rate, and every stamp is the message's deadline on the wall clock (the
  answers' age is then wall time minus stamp). ``frame_id`` is the sequence number.
* ``listener``: receives the measurements and the answers (raw CDR; stamps and the answers'
  effort and velocity deserialized after the run) and /diagnostics. ``prober``: the same
  without the streams, probing services under the stream from a process that has nothing
  else to do (a client's first call, which also waits for DDS to match its reply reader, is
  saved apart as ``first``):
  ``/dgp_estimator/get_parameters`` (served by the executor alone) and ``~/refit`` (served by
  the learner). It uses the node's own wait-set executor (``dgp_ros.nodes.executor``) with batch
  handlers, about 30 us of Python per message, so that it is not the bottleneck it would be with
  rclpy's SingleThreadedExecutor (0.5 ms per message, two messages per answer).
* ``estimator``: ``dgp_ros.nodes.estimator.main`` (``dgp_ros.estimator_node`` in older trees)
  of whatever tree PYTHONPATH names, with the message callbacks timed (thread CPU, re-entry
  counted once): at exit it writes its main thread's CPU and the process's from the first
  message callback to the end of the last, and the callbacks' share, as JSON (``--cpu-out``):
  the same split for the code before and after a change.
* ``hog``: one busy loop (another process keeping a core busy).
* ``relay``: the floor of bench/arm_floor.py (issue 33), a bare rclpy node answering each
  measurement with a JointState on the estimator's answer topic (``DGP_RELAY``: which relay).
  ``player --stream DIR`` plays the real Panda's residual (``real_stream``) instead of the
  simulation.

Each writes its results when it gets SIGINT or SIGTERM (``--out``), and ``--ready`` once set up.
"""
from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import time

from live_common import close, FINGER, on_diagnostics, panda_messages, play, ros_node, \
    state_publisher, stop_event, thread_cpu, TOPIC_IN, TOPIC_OUT, write_json


# ----------------------------------------------------------------------------- player
def player(a) -> None:
    """Publish the phases' (or the real stream's) messages at their deadlines; --out: lateness."""
    import numpy as np
    stop = stop_event()
    from dgp_ros.dynamics import ARM_JOINTS, simulate_arm
    names = list(ARM_JOINTS['panda']) + [FINGER]
    phases = [(float(r), float(s)) for r, s in (p.split(':') for p in a.phases.split(','))]
    from sensor_msgs.msg import JointState
    from array import array
    # the messages first (the publishing loop only stamps and publishes)
    msgs, offsets = [], []
    t_sim = 0.0
    if a.stream:                                 # the real Panda's residual (real_stream)
        phases = []
        for t, q, v, e in real_stream(a.stream, a.seconds):
            m = JointState()
            m.name = names[:7]
            m.position, m.velocity, m.effort = (array('d', x.tolist()) for x in (q, v, e))
            msgs.append(m)
            offsets.append(float(t))
    for rate, secs in phases:
        d = simulate_arm('panda', secs, rate_hz=rate, seed=a.seed, t0_s=t_sim)
        msgs += panda_messages(d)
        offsets += [float(t) for t in d['t']]
        t_sim += secs
    ctx, node = ros_node('arm_live_player')
    pub = state_publisher(node, stop, a.min_subscribers, a.wait, a.ready)
    late = []
    t0_wall, n = play(pub, zip(msgs, offsets), stop, lambda n, s: late.append(s))
    late = np.array(late) if late else np.zeros(1)
    write_json(a.out, {'published': n, 't0_wall': t0_wall, 'phases': phases,
                       'late_p50_ms': float(np.percentile(late, 50) * 1e3),
                       'late_p99_ms': float(np.percentile(late, 99) * 1e3),
                       'late_max_ms': float(late.max() * 1e3),
                       'seconds': float(offsets[n - 1]) if n else 0.0})
    close(ctx, node)


#: the real Panda's log: its first REAL_SPLIT_S s are played (looped), the rest is held out
REAL_SPLIT_S = 7.5


def real_stream(path: str, seconds: float):
    """
    Yield (t, q, qd, residual) of the real Panda's log for ``seconds`` s at its own timing.

    ``panda_log_train.npz`` of ``path`` (read there, never copied): its part before
    ``REAL_SPLIT_S`` s (the rest is held out), looped, at the logger's own jittered intervals
    (0.7 to 15 ms, median 1 ms); effort = the friction residual ``tau_friction_offline``
    (what the estimator learns with its defaults, no inverse dynamics).
    """
    import numpy as np
    z = np.load(os.path.join(path, 'panda_log_train.npz'), allow_pickle=False)
    t = z['t'] - z['t'][0]
    keep = t < REAL_SPLIT_S
    t, q, qd, r = t[keep], z['q'][keep], z['qd'][keep], z['tau_friction_offline'][keep]
    period = t[-1] + float(np.median(np.diff(t)))
    k = 0
    while True:
        for i in range(len(t)):
            ti = k * period + t[i]
            if ti > seconds:
                return
            yield ti, q[i], qd[i], r[i]
        k += 1


# ----------------------------------------------------------------------------- listener
def _stamp_ns(raw: bytes) -> int:
    sec, nsec = struct.unpack_from('<iI', raw, 4)
    return sec * 1_000_000_000 + nsec


def listener(a) -> None:
    import numpy as np
    stop = stop_event()
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rcl_interfaces.srv import GetParameters
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    from dgp_ros.nodes.executor import set_batch_handler, WaitSetExecutor
    ctx, node = ros_node(f'arm_live_{a.role}')
    meas, ans, raws, diags = [], [], [], []
    probes = {'get_parameters': [], 'refit': []}
    first = {}
    now = time.time

    def on_meas(msgs, infos):
        t = now()
        meas.extend((_stamp_ns(r), t) for r in msgs)

    def on_ans(msgs, infos):
        t = now()
        for r in msgs:
            ans.append((_stamp_ns(r), t))
            raws.append(r)

    def on_diag(st, d):
        diags.append(dict(d, message=st.message, t=now()))

    if a.role == 'listener':
        # the prober (the same role without the streams) calls the services from a process
        # that has nothing else to do: a round trip is then the node's, not a busy caller's
        qos_be = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
        s_in = node.create_subscription(JointState, TOPIC_IN, lambda m: None, qos_be, raw=True)
        set_batch_handler(s_in, on_meas, 1000)
        s_out = node.create_subscription(JointState, TOPIC_OUT, lambda m: None,
                                         QoSProfile(depth=1000), raw=True)
        set_batch_handler(s_out, on_ans, 1000)
        on_diagnostics(node, on_diag)
    clients = {}
    if a.probe_period > 0:
        clients['get_parameters'] = (node.create_client(GetParameters,
                                                        '/dgp_estimator/get_parameters'),
                                     lambda: GetParameters.Request(names=['buffer_size']),
                                     a.probe_period)
    if a.refit_period > 0:
        clients['refit'] = (node.create_client(Trigger, '/dgp_estimator/refit'),
                            Trigger.Request, a.refit_period)
    pending = {}

    def probe(kind):
        cli, req, _ = clients[kind]
        if kind in pending or not cli.service_is_ready():
            return
        t0 = time.monotonic()
        fut = cli.call_async(req())
        pending[kind] = (fut, t0)

    for kind, (_, _, period) in clients.items():
        node.create_timer(period, lambda k=kind: probe(k))
    ex = WaitSetExecutor(context=ctx)
    ex.add_node(node)
    open(a.ready, 'w').write('ok')
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.02)
        for kind, (fut, t0) in list(pending.items()):
            if fut.done():
                # a client's first call also waits for DDS to match its reply reader with the
                # service (0.75 s once): kept apart
                (probes[kind] if kind in first else first.setdefault(kind, [])).append(
                    (now(), time.monotonic() - t0))
                del pending[kind]
    for kind, (fut, t0) in pending.items():          # unanswered (in flight at the end: not)
        if time.monotonic() - t0 > 1.0:
            probes[kind].append((now(), float('inf')))
    from rclpy.serialization import deserialize_message
    msgs = [deserialize_message(r, JointState) for r in raws]
    efforts = np.array([m.effort for m in msgs]) if msgs else np.zeros((0, 0))
    velocities = np.array([m.velocity for m in msgs]) if msgs else np.zeros((0, 0))
    np.savez(a.out, meas=np.array(meas, dtype=float).reshape(-1, 2),
             ans=np.array(ans, dtype=float).reshape(-1, 2), effort=efforts,
             velocity=velocities,
             diags=json.dumps(diags), probes=json.dumps(probes), first=json.dumps(first))
    close(ctx, node, ex)


# ----------------------------------------------------------------------------- estimator
def estimator(a, ros_args) -> int:
    """Run the node of the tree on PYTHONPATH with its message callbacks timed."""
    try:
        from dgp_ros.nodes import estimator as E
    except ImportError:             # a --before-rev tree from before the nodes/ folder
        from dgp_ros import estimator_node as E
    st = {'cb_ns': 0, 'calls': 0, 'depth': 0, 'node': None, 'main0': None, 'proc0': None,
          'main1': 0, 'proc1': 0.0}
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

    def proc_s():
        t = os.times()
        return t.user + t.system

    def timed(fn):
        def wrapper(*args, **kw):
            if st['depth']:
                return fn(*args, **kw)
            st['depth'] += 1
            t0 = time.thread_time_ns()
            if st['main0'] is None:
                st['main0'], st['proc0'] = t0, proc_s()
                st['threads0'] = thread_cpu()
            try:
                return fn(*args, **kw)
            finally:
                st['cb_ns'] += time.thread_time_ns() - t0
                st['calls'] += 1
                st['depth'] -= 1
        return wrapper

    profiled = os.environ.get('DGP_PATH_PROFILE', '') == '1'
    if profiled:                    # the path's stages, thread CPU (bench/path_profile.py)
        import path_profile
        path_profile.install()
    shutdown = E.EstimatorNode.shutdown

    def at_shutdown(self):
        # the end of the stream: before the model is saved and the threads end
        st['main1'], st['proc1'] = time.thread_time_ns(), proc_s()
        th0, th1 = st.get('threads0') or {}, thread_cpu()
        st['threads'] = {k: v - th0.get(k, 0.0) for k, v in th1.items()}
        if profiled and st['main0'] is not None:
            n = int(self.estimator.health.messages_received) or 1
            st['profile'] = path_profile.report((st['main1'] - st['main0']) * 1e-9, n,
                                                st['threads'])
        return shutdown(self)
    E.EstimatorNode.shutdown = at_shutdown

    for name in ('_on_state', '_on_states'):
        if hasattr(E.EstimatorNode, name):
            setattr(E.EstimatorNode, name, timed(getattr(E.EstimatorNode, name)))
    # where the long stalls come from: the slowest callbacks (wall) and garbage collections
    slow, gcs = [], []

    def walled(name, fn):
        def wrapper(*args, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                dt = time.perf_counter() - t0
                if dt > 0.02:
                    slow.append((name, round(dt * 1e3, 1), round(time.time(), 3)))
        return wrapper
    diag_t = []
    if hasattr(E.EstimatorNode, '_publish_diagnostics'):
        pd = E.EstimatorNode._publish_diagnostics

        def noted(self, *args, **kw):
            diag_t.append(time.time())
            return pd(self, *args, **kw)
        E.EstimatorNode._publish_diagnostics = noted
    for name in ('_on_state', '_on_states', '_publish_diagnostics', '_srv_refit', '_srv_reset',
                 '_srv_save'):
        if hasattr(E.EstimatorNode, name):
            setattr(E.EstimatorNode, name, walled(name, getattr(E.EstimatorNode, name)))
    import gc
    gc_t = {}

    def on_gc(phase, info):
        if phase == 'start':
            gc_t['t'] = time.perf_counter()
        elif 't' in gc_t:
            dt = time.perf_counter() - gc_t.pop('t')
            if dt > 0.005:
                gcs.append((info.get('generation'), round(dt * 1e3, 1), round(time.time(), 3)))
    gc.callbacks.append(on_gc)
    # model swaps as the message path sees them: the first answer from each new snapshot
    swaps = []
    try:
        from dgp_ros.online.path import estimator as OE
        est_fn = OE.OnlineEstimator._estimate

        def estimate(self, snap, Q):
            v = getattr(snap, 'version', None)
            if v is not None and (not swaps or swaps[-1][1] != v):
                swaps.append((time.time(), v, getattr(snap, 'model', None) is not None))
            return est_fn(self, snap, Q)
        OE.OnlineEstimator._estimate = estimate
    except (ImportError, AttributeError):
        pass
    init = E.EstimatorNode.__init__

    def keep(self, *args, **kw):
        init(self, *args, **kw)
        st['node'] = self
    E.EstimatorNode.__init__ = keep
    prof_path = os.environ.get('DGP_CPROFILE', '')
    if prof_path:                   # a deterministic profile of the main thread
        import cProfile
        prof = cProfile.Profile(time.thread_time_ns, 1e-9)     # CPU, not wall
        code = prof.runcall(E.main, ['estimator'] + ros_args)
        prof.dump_stats(prof_path)
    else:
        code = E.main(['estimator'] + ros_args)
    node = st['node']
    received = None
    if node is not None:
        try:
            received = int(node.estimator.health.messages_received)
        except Exception:       # noqa: BLE001 - an older tree
            received = None
    # from the first message callback to the end of the last one
    write_json(a.cpu_out, {'main_thread_s': (st['main1'] - (st['main0'] or 0)) * 1e-9,
                           'callbacks_s': st['cb_ns'] * 1e-9, 'calls': st['calls'],
                           'process_s': st['proc1'] - (st['proc0'] or 0.0),
                           'received': received,
                           'executor': os.environ.get('DGP_EXECUTOR', ''),
                           'slow_callbacks': slow[-200:], 'gc_pauses': gcs[-200:],
                           'diag_times': diag_t, 'swaps': swaps[-5000:],
                           'threads': st.get('threads', {}), 'profile': st.get('profile')})
    return code


# ----------------------------------------------------------------------------- relay (the floor)
def relay(a) -> None:
    """
    Answer each JointState with a JointState from a bare rclpy node: the floor.

    Subscribes like the estimator (best effort, depth 1000), publishes on its answer topic (depth
    1024, as the estimator) header, names, velocity and effort of each measurement, spun by rclpy's
    own SingleThreadedExecutor: what any rclpy node pays per message, with nothing of ours
    ``DGP_RELAY`` chooses which: '' (default) message objects in and out, rclpy's
    SingleThreadedExecutor (``DGP_EXECUTOR=waitset``: the node's wait-set loop instead); 'raw':
    the message's bytes in and out unchanged (``raw=True``; either executor); 'lean': the bytes
    in and out from a loop over a wait set of one subscription (``_lean_relay``: no executor,
    no services served), the least an rclpy process can spend per message.
    """
    stop = stop_event()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    ctx, node = ros_node('dgp_estimator')
    pub = node.create_publisher(JointState, '~/damping_force', 1024)

    def on_state(m):
        out = JointState()
        out.header = m.header
        out.name = m.name
        out.velocity = m.velocity
        out.effort = m.effort
        pub.publish(out)

    kind = os.environ.get('DGP_RELAY', '')
    if kind == 'lean':
        _lean_relay(node, pub, ctx, stop, a)
        return
    raw = kind == 'raw'                 # the bytes in and out, unchanged
    node.create_subscription(JointState, TOPIC_IN, pub.publish if raw else on_state,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT),
                             raw=raw)
    if os.environ.get('DGP_EXECUTOR') == 'waitset':      # the node's own loop instead
        from dgp_ros.nodes.executor import WaitSetExecutor
        ex = WaitSetExecutor(context=ctx)
    else:
        ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.1)
    if a.cpu_out:
        write_json(a.cpu_out, {'threads': thread_cpu()})
    close(ctx, node, ex)


def _lean_relay(node, pub, ctx, stop, a) -> None:
    """Take every raw message waiting after each wait, publish it as it came (``lean``)."""
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    sub = node.create_subscription(
        JointState, TOPIC_IN, lambda m: None,
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT), raw=True)
    h = sub.handle
    h.__enter__()
    ws = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, ctx.handle)
    inner = pub.handle
    take = h.take_message
    while not stop.is_set():
        ws.clear_entities()
        ws.add_subscription(h)
        ws.wait(100_000_000)
        while True:
            got = take(JointState, True)
            if got is None:
                break
            inner.publish_raw(got[0])
    if a.cpu_out:
        write_json(a.cpu_out, {'threads': thread_cpu()})
    h.__exit__(None, None, None)
    close(ctx, node)


def hog(a) -> None:
    while True:
        pass


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('role', choices=['player', 'listener', 'prober', 'estimator', 'hog',
                                    'relay'])
    p.add_argument('--out', default='')
    p.add_argument('--ready', default='')
    p.add_argument('--phases', default='1000:20')
    p.add_argument('--seed', type=int, default=7)
    p.add_argument('--wait', type=float, default=30.0)
    p.add_argument('--min-subscribers', type=int, default=2)
    p.add_argument('--probe-period', type=float, default=0.0)
    p.add_argument('--refit-period', type=float, default=0.0)
    p.add_argument('--cpu-out', default='')
    p.add_argument('--stream', default='',
                   help="player: the real Panda log's folder (real_stream) instead of --phases")
    p.add_argument('--seconds', type=float, default=20.0, help='player: length of --stream')
    argv = sys.argv[1:]
    ros = []
    if '--ros-args' in argv:
        i = argv.index('--ros-args')
        argv, ros = argv[:i], argv[i:]
    a = p.parse_args(argv)
    if a.role == 'player':
        player(a)
    elif a.role in ('listener', 'prober'):
        listener(a)
    elif a.role == 'estimator':
        return estimator(a, ros)
    elif a.role == 'relay':
        relay(a)
    else:
        hog(a)
    return 0


if __name__ == '__main__':
    sys.exit(main())

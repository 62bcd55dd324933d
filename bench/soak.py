#!/usr/bin/env python3
"""
Soak / load test of the online estimator.

Drives :class:`dgp_ros.online.OnlineEstimator` in-process with a paced stream (default 1 kHz for
60 s, buffer 1000, async refits), and optionally the ``dgp_estimator`` node over DDS (``--node``:
the node runs as a child process, this process publishes and listens).

Reports (JSON on stdout, also written to ``--json PATH``):

* ``backlog``: messages due (wall clock x rate) but not yet processed; max and at the end, and
  the slope of the backlog over the second half of the run (msgs/s; > 0 = falling behind);
* ``rss``: VmRSS (``/proc/<pid>/status``) after warm-up and at the end, growth in MiB;
* ``refits``: started / ok / failed, durations, and deadline misses (a refit that took longer
  than ``refit_period_s``, i.e. the next one was due before it finished);
* ``latency``: per-message processing time (process() call) and end-to-end lateness against the
  schedule, p50 / p99 / max;
* ``invariant``: estimates that were non-finite or had ``qd^T tau_hat < 0`` (must be 0 unless
  passivity is 'none').

Exit status: 0, or 1 if the invariant was violated or an exception escaped.

``--quick`` runs ~10 s (test/online/test_online_load.py). No numbers are asserted here;
this is a measurement tool.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO not in sys.path:
    sys.path.insert(0, REPO)

JOINTS = ['alpha', 'beta', 'airspeed']


def rss_mib(pid='self') -> float:
    with open(f'/proc/{pid}/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    return float('nan')


def log(*a):
    print('[soak]', *a, file=sys.stderr, flush=True)


class Stream:
    """Deterministic smooth 3-joint trajectory + passive nonlinear damping force + noise."""

    def __init__(self, seed=0):
        self.rng = np.random.default_rng(seed)

    def sample(self, t):
        qd = np.array([0.05 + 0.08 * np.sin(0.7 * t) + 0.02 * np.sin(5.3 * t),
                       0.04 * np.sin(1.1 * t + 1.0) + 0.01 * np.sin(7.1 * t),
                       70.0 + 8.0 * np.sin(0.23 * t) + 2.0 * np.sin(2.9 * t)])
        qd = qd + self.rng.normal(scale=[0.002, 0.001, 0.1])
        d = np.array([2.0 + 0.5 * np.sin(3 * qd[0]), 1.0 + qd[1] ** 2,
                      0.3 + 0.01 * abs(qd[2] - 70.0)])
        tau = d * qd + self.rng.normal(scale=0.01, size=3)
        return qd, tau


def pct(a, q):
    return float(np.percentile(a, q)) if len(a) else float('nan')


def run_inprocess(args) -> dict:
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    cfg = EstimatorConfig(model=args.model, passivity=args.passivity, buffer_size=args.buffer,
                          min_samples=min(50, args.buffer), refit_period_s=args.refit_period,
                          optimize_every_n_refits=args.optimize_every, selection=args.selection,
                          min_sample_interval_s=args.min_sample_interval,
                          joints=list(JOINTS), refit_mode='async')
    est = OnlineEstimator(cfg)
    stream = Stream(args.seed)
    n_total = int(args.duration * args.rate)
    period = 1.0 / args.rate
    proc_t = np.zeros(n_total)
    late = np.zeros(n_total)
    backlog_trace = []          # (wall s since start, backlog msgs)
    bad_finite = bad_passive = 0
    sources = {}
    rss0 = None
    warm = max(1, int(n_total * 0.2))
    t0 = time.perf_counter()
    next_report = 1.0
    for i in range(n_total):
        due = t0 + i * period
        now = time.perf_counter()
        if now < due:
            time.sleep(due - now)
        stamp = i * period
        qd, tau = stream.sample(stamp)
        a = time.perf_counter()
        e = est.process(stamp, JOINTS, qd, tau)
        b = time.perf_counter()
        proc_t[i] = b - a
        late[i] = b - due
        if e is not None:
            sources[e.source] = sources.get(e.source, 0) + 1
            if not (np.all(np.isfinite(e.tau_hat)) and np.all(np.isfinite(e.stddev)) and
                    np.isfinite(e.power)):
                bad_finite += 1
            if args.passivity != 'none' and float(e.qd @ e.tau_hat) < 0:
                bad_passive += 1
        el = b - t0
        backlog = max(0.0, el * args.rate - (i + 1))
        if i % 100 == 0:
            backlog_trace.append((el, backlog))
        if i == warm:
            rss0 = rss_mib()
        if el >= next_report:
            d = est.diagnostics()
            log(f't={el:5.1f}s msgs={i + 1} backlog={backlog:.0f} buffer={d["buffer_fill"]} '
                f'refits ok/failed={d["refits_ok"]}/{d["refits_failed"]} '
                f'running={d["refit_running"]} rss={rss_mib():.1f}MiB')
            next_report += 1.0 if args.duration <= 15 else 5.0
    wall = time.perf_counter() - t0
    rss1 = rss_mib()
    d = est.diagnostics()
    durations = est.refit_durations()
    running_at_end = bool(d['refit_running'])
    pending_at_end = d['pending_samples']
    est.close(timeout=args.close_timeout)      # the refit thread is a daemon: do not hang
    tr = np.array(backlog_trace)
    half = tr[tr[:, 0] >= tr[-1, 0] / 2] if len(tr) else tr
    slope = float(np.polyfit(half[:, 0], half[:, 1], 1)[0]) if len(half) > 3 else float('nan')
    misses = sum(1 for x in durations if x > args.refit_period) if args.refit_period > 0 else 0
    expected_refits = int(args.duration / args.refit_period) if args.refit_period > 0 else 1
    return {
        'mode': 'inprocess', 'messages': n_total, 'wall_s': wall,
        'achieved_rate_hz': n_total / wall,
        'backlog': {'max': float(tr[:, 1].max()) if len(tr) else 0.0,
                    'end': float(tr[-1, 1]) if len(tr) else 0.0, 'slope_msgs_per_s': slope},
        'rss': {'after_warmup_mib': rss0, 'end_mib': rss1, 'growth_mib': rss1 - rss0},
        'refits': {'started': d['refits_started'], 'ok': d['refits_ok'],
                   'failed': d['refits_failed'],
                   'expected_by_period': expected_refits,
                   'deadline_misses': misses + (1 if running_at_end and not durations else 0),
                   'running_at_end': running_at_end, 'pending_samples_at_end': pending_at_end,
                   'durations_s': [round(x, 4) for x in durations],
                   'max_s': max(durations) if durations else float('nan'),
                   'last_error': d['last_refit_error']},
        'latency': {'process_p50_ms': 1e3 * pct(proc_t, 50),
                    'process_p99_ms': 1e3 * pct(proc_t, 99),
                    'process_max_ms': 1e3 * float(proc_t.max()),
                    'lateness_p50_ms': 1e3 * pct(late, 50), 'lateness_p99_ms': 1e3 * pct(late, 99),
                    'lateness_max_ms': 1e3 * float(late.max())},
        'buffer_fill': d['buffer_fill'], 'samples_added': d['samples_added'],
        'samples_skipped': d['samples_skipped'],
        'samples_rate_limited': d['samples_rate_limited'], 'sources': sources,
        'invariant': {'non_finite': bad_finite, 'non_passive': bad_passive,
                      'passivity_fallbacks': d['passivity_fallbacks']},
        'config': cfg.to_dict()}


def run_node(args) -> dict:
    """
    Run the estimator node as a child process.

    This process publishes at ``rate`` and listens.
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64

    exe = os.path.join(os.path.dirname(sys.executable), 'estimator')
    cmd = [exe, '--ros-args', '-p', f'model:={args.model}', '-p', f'passivity:={args.passivity}',
           '-p', f'buffer_size:={args.buffer}',
           '-p', f'refit_period_s:={float(args.refit_period)}',
           '-p', f'optimize_every_n_refits:={args.optimize_every}',
           '-p', f'selection:={args.selection}', '-p', 'diagnostics_period_s:=1.0',
           '-p', f'min_sample_interval_s:={float(args.min_sample_interval)}']
    child = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             start_new_session=True)
    rclpy.init()
    node = rclpy.create_node('soak_driver')
    stream = Stream(args.seed)
    sent_stamp = {}
    lat, got = [], [0]
    bad = {'non_finite': 0, 'non_passive': 0}
    diags = []

    def on_force(m):
        s = m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
        key = round(s, 6)
        if key in sent_stamp:
            lat.append(time.perf_counter() - sent_stamp.pop(key))
        got[0] += 1
        tau, qd = np.array(m.effort), np.array(m.velocity)
        if not (np.all(np.isfinite(tau)) and np.all(np.isfinite(qd))):
            bad['non_finite'] += 1
        elif args.passivity != 'none' and float(qd @ tau) < 0:
            bad['non_passive'] += 1

    def on_power(m):
        if not np.isfinite(m.data):
            bad['non_finite'] += 1

    node.create_subscription(JointState, '/dgp_estimator/damping_force', on_force, 1000)
    node.create_subscription(Float64, '/dgp_estimator/dissipated_power', on_power, 1000)
    node.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    pub = node.create_publisher(JointState, 'generalized_state',
                                QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    try:
        t_end = time.monotonic() + 20
        while pub.get_subscription_count() < 1 and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        if pub.get_subscription_count() < 1:
            raise RuntimeError('estimator node not discovered')
        time.sleep(0.5)
        rss_trace = []
        n_total = int(args.duration * args.rate)
        period = 1.0 / args.rate
        t0 = time.perf_counter()
        for i in range(n_total):
            due = t0 + i * period
            while time.perf_counter() < due:
                ex.spin_once(timeout_sec=0)
                if time.perf_counter() < due - 2e-4:
                    time.sleep(1e-4)
            stamp = 1.0 + i * period
            qd, tau = stream.sample(stamp)
            m = JointState()
            m.header.stamp.sec = int(stamp)
            m.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9)) % 1_000_000_000
            m.name = JOINTS
            m.velocity = qd.tolist()
            m.effort = tau.tolist()
            sent_stamp[round(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec, 6)] = \
                time.perf_counter()
            pub.publish(m)
            if i % int(args.rate) == 0:
                rss_trace.append((time.perf_counter() - t0, rss_mib(child.pid)))
                if child.poll() is not None:
                    raise RuntimeError(f'estimator exited with {child.returncode}')
        t_end = time.monotonic() + 3
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        kv = {v.key: v.value for v in diags[-1].status[0].values} if diags else {}
        r = np.array([x for _, x in rss_trace])
        w = max(1, len(r) // 5)
        return {'mode': 'node', 'messages': n_total, 'received_estimates': got[0],
                'estimator_messages_received': int(kv.get('messages_received', -1)),
                'dropped_frac': 1 - got[0] / n_total,
                'rss': {'after_warmup_mib': float(r[w]) if len(r) > w else float('nan'),
                        'end_mib': float(r[-1]),
                        'growth_mib': float(r[-1] - r[min(w, len(r) - 1)])},
                'latency': {'e2e_p50_ms': 1e3 * pct(lat, 50), 'e2e_p99_ms': 1e3 * pct(lat, 99)},
                'refits': {'ok': int(kv.get('refits_ok', -1)),
                           'failed': int(kv.get('refits_failed', -1)),
                           'last_duration_s': kv.get('last_refit_duration_s')},
                'node_latency_p99_s': kv.get('latency_p99_s'),
                'invariant': bad}
    finally:
        try:
            os.killpg(child.pid, signal.SIGINT)
            child.wait(timeout=20)
        except Exception:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
        node.destroy_node()
        rclpy.try_shutdown()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--quick', action='store_true', help='~10 s run (the test)')
    p.add_argument('--duration', type=float, default=None, help='seconds (default 60, quick 10)')
    p.add_argument('--rate', type=float, default=1000.0, help='input rate, Hz')
    p.add_argument('--buffer', type=int, default=1000)
    p.add_argument('--model', default='full')
    p.add_argument('--passivity', default='paper')
    p.add_argument('--selection', default='novelty')
    p.add_argument('--refit-period', type=float, default=5.0, help='stamp seconds')
    p.add_argument('--min-sample-interval', type=float, default=0.01,
                   help='learning rate limit, stamp seconds (estimator default 0.01; 0 = learn '
                        'every message)')
    p.add_argument('--optimize-every', type=int, default=0)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--close-timeout', type=float, default=5.0,
                   help='wait this long for a running refit at the end')
    p.add_argument('--node', action='store_true', help='also drive the node over DDS')
    p.add_argument('--json', default='', help='write the report here too')
    args = p.parse_args(argv)
    if args.duration is None:
        args.duration = 10.0 if args.quick else 60.0
    report = {'args': vars(args)}
    code = 0
    try:
        report['inprocess'] = run_inprocess(args)
        inv = report['inprocess']['invariant']
        if inv['non_finite'] or inv['non_passive']:
            code = 1
        if args.node:
            report['node'] = run_node(args)
            if any(report['node']['invariant'].values()):
                code = 1
    except Exception as exc:  # report, do not hide
        report['error'] = f'{type(exc).__name__}: {exc}'
        code = 1
    out = json.dumps(report, indent=2, default=str)
    print(out)
    if args.json:
        with open(args.json, 'w') as f:
            f.write(out + '\n')
    return code


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""
An hour at 1 kHz over DDS: the node as a user starts it, its memory against time.

Three processes besides this one, DDS isolated (a random ``ROS_DOMAIN_ID``, localhost only):

* a player publishing a simulated Panda's raw ``/joint_states`` (7 joints and a finger joint,
  stamps on the wall clock) at absolute deadlines, its 10 s task cycle built once and looped
  for ``--duration`` s (a one-hour stream held in memory would itself be 3.6 million messages);
* the ``estimator`` node as the README starts it on an arm (``inverse_dynamics=urdf``, the
  URDF, ``joints``, ``model_path``; defaults otherwise), Ctrl-C at the end (it saves);
* a listener keeping running statistics only (counts, an age histogram, the negative power,
  the last /diagnostics), written every 10 s, so that its own memory stays flat.

Every ``--sample-s`` (60; quick 5) this process reads the resident memory (VmRSS) of every
process: the player, the listener, the node and its learner process (the fork server's child).
With ``--tracemalloc`` the node and its learner also write tracemalloc's top growers every
period (``dgp_ros.online.memtrace``); tracing slows every allocation, so the RSS figures of the
section come from a run without it. Writes the section ``soak_live`` of docs/BENCHMARKS.md and
``docs/bench/soak_memory.png``: RSS against time, the growth over the last 40 minutes (the last
two thirds of shorter runs) per process, the answered share, the answers' age.

    python bench/soak_live.py                 # one hour (about 62 min)
    python bench/soak_live.py --quick         # 60 s
    python bench/soak_live.py --duration 600 --tracemalloc
"""
from __future__ import annotations

import json
import os
import signal
import sys
import time

import numpy as np

import common as C  # noqa: E402
from cpu_watch import learner_pids  # noqa: E402

from live_common import (close, on_diagnostics, panda_messages, play, ros_node,  # noqa: E402,I100
                         state_publisher, stop_event, TOPIC_OUT, write_json)

SECTION = 'soak_live'
TITLE = 'An hour at 1 kHz: memory against time'
CYCLE_S = 10.0                      # the simulated arm's task cycle (s)
#: the answers' age histogram: bin edges (ms)
AGE_EDGES_MS = np.r_[0.0, np.geomspace(0.05, 2000.0, 60), np.inf]
#: the /diagnostics keys the listener records once a period (what the served model is)
TIMELINE_KEYS = ('structure', 'elements', 'joint_elements', 'buffer_fill', 'refits_ok',
                 'memory', 'answers_by_guarantee')


def _extra(p):
    p.add_argument('--duration', type=float, default=3600.0, help='seconds of stream (quick 60)')
    p.add_argument('--sample-s', type=float, default=60.0, help='RSS sampling period (quick 5)')
    p.add_argument('--rate', type=float, default=1000.0, help='messages a second')
    p.add_argument('--tracemalloc', action='store_true',
                   help="the node's and learner's top growers each period (slower)")
    p.add_argument('--keep', default='', help="keep every process's files in this directory")
    p.add_argument('--role', default='', help=__import__('argparse').SUPPRESS)
    p.add_argument('--file', default='', help=__import__('argparse').SUPPRESS)


# ----------------------------------------------------------------------------- player
def player(a) -> None:
    """Publish the simulated Panda's task cycle, looped, for --duration s; --file: lateness."""
    stop = stop_event()
    from dgp_ros.dynamics import simulate_arm
    d = simulate_arm('panda', CYCLE_S, rate_hz=a.rate, seed=7)
    msgs = panda_messages(d)
    offs = d['t'] - d['t'][0]
    ctx, node = ros_node('soak_player')
    pub = state_publisher(node, stop)          # the node subscribes (the listener does not)
    late = {'max': 0.0, 'over_1ms': 0}

    def items():
        for k in range(int(a.duration // CYCLE_S) + 1):
            for m, off in zip(msgs, k * CYCLE_S + offs):
                if off > a.duration:
                    return
                yield m, off

    def noted(n, s, done=False):
        late['max'], late['over_1ms'] = max(late['max'], s), late['over_1ms'] + int(s > 1e-3)
        if done or n % 10000 == 0:
            write_json(a.file, {'published': n, 'late_max_ms': late['max'] * 1e3,
                                'late_over_1ms': late['over_1ms'], 'done': done})
    _, n = play(pub, items(), stop, noted)
    noted(n, 0.0, True)
    close(ctx, node)


# ----------------------------------------------------------------------------- listener
def listener(a) -> None:
    stop = stop_event()
    from rclpy.qos import QoSProfile
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from dgp_ros.nodes.executor import set_batch_handler, WaitSetExecutor
    ctx, node = ros_node('soak_listener')
    st = {'answers': 0, 'negative_power': 0, 'non_finite': 0, 'max_gap_s': 0.0,
          'diagnostics': 0, 'warn_periods': 0, 'last_diag': {}, 'warn_kinds': {},
          'timeline': []}
    hist = np.zeros(len(AGE_EDGES_MS) - 1, np.int64)
    last = [None]

    def on_ans(raws, infos):
        now = time.time()
        for r in raws:
            m = deserialize_message(r, JointState)
            age_ms = (now - (m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec)) * 1e3
            hist[np.searchsorted(AGE_EDGES_MS, age_ms, side='right') - 1] += 1
            v, e = np.asarray(m.velocity), np.asarray(m.effort)
            if not (np.isfinite(v).all() and np.isfinite(e).all()):
                st['non_finite'] += 1
            elif v @ e < -1e-12 * (np.abs(v) @ np.abs(e)):
                st['negative_power'] += 1
        if last[0] is not None:
            st['max_gap_s'] = max(st['max_gap_s'], now - last[0])
        last[0] = now
        st['answers'] += len(raws)

    def on_diag(s, values):
        st['diagnostics'] += 1
        level = s.level[0] if isinstance(s.level, bytes) else int(s.level)
        st['warn_periods'] += int(level == 1)
        kinds = st['warn_kinds']
        if level == 1 and (len(kinds) < 20 or s.message[:50] in kinds):
            kinds[s.message[:50]] = kinds.get(s.message[:50], 0) + 1
        st['last_diag'] = d = dict(values, message=s.message, level=level)
        tl = st['timeline']
        if not tl or time.time() - tl[-1]['t'] >= a.sample_s:
            # what the learner serves, a period at a time (bounded: one per period)
            tl.append(dict({k: d.get(k) for k in TIMELINE_KEYS}, t=time.time()))

    sub = node.create_subscription(JointState, TOPIC_OUT, lambda m: None,
                                   QoSProfile(depth=1000), raw=True)
    set_batch_handler(sub, on_ans, 1000)
    on_diagnostics(node, on_diag)
    ex = WaitSetExecutor(context=ctx)
    ex.add_node(node)
    t_write = time.monotonic()
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.02)
        if time.monotonic() - t_write > 10.0:
            write_json(a.file, dict(st, age_hist=hist.tolist()))
            t_write = time.monotonic()
    write_json(a.file, dict(st, age_hist=hist.tolist(), done=True))
    close(ctx, node, ex)


# ----------------------------------------------------------------------------- the run
def _proc_mib(pid: int, field: str = 'VmRSS:', where: str = 'status') -> float:
    """
    Return a memory figure of process ``pid`` from ``/proc/PID/<where>`` (MiB; NaN: gone).

    ``VmRSS:`` of ``status``: the resident memory; ``Anonymous:`` of ``smaps_rollup``: its
    heap and arenas, not mapped files.
    """
    try:
        with open(f'/proc/{pid}/{where}') as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')


def _anon_parts(pid: int) -> dict:
    """
    Return the anonymous memory of process ``pid`` by kind of mapping (MiB; {} when gone).

    ``heap``: the main heap (``[heap]``, glibc's main arena); ``large``: anonymous mappings of
    8 MiB or more (glibc's thread arenas reserve 64 MiB each, OpenBLAS its 32 MiB buffers);
    ``small``: the other anonymous mappings (numpy's large arrays, Python's 256 KiB arenas,
    thread stacks).
    """
    out = {'heap': 0.0, 'large': 0.0, 'small': 0.0}
    size, name = 0.0, ''
    try:
        with open(f'/proc/{pid}/smaps') as f:
            for line in f:
                head = line.split(None, 5)
                if not head[0].endswith(':'):       # a mapping's line: 'lo-hi perms ... name'
                    lo, hi = head[0].split('-')
                    size = (int(hi, 16) - int(lo, 16)) / 2.0 ** 20
                    name = head[5].strip() if len(head) > 5 else ''
                elif head[0] == 'Anonymous:' and (not name or name == '[heap]'):
                    kind = 'heap' if name else 'large' if size >= 8.0 else 'small'
                    out[kind] += int(head[1]) / 1024.0
    except OSError:
        return {}
    return out


def run(a, work: str) -> dict:
    from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf
    env = C.dds_env(**C.CHILD_ENV)
    f = lambda n: os.path.join(work, n)  # noqa: E731
    est_env = dict(env)
    if a.tracemalloc:
        est_env.update(DGP_TRACEMALLOC=f('trace'), DGP_TRACEMALLOC_S=str(a.sample_s))
    names = list(ARM_JOINTS['panda'])
    ros = ['--ros-args', '-r', 'generalized_state:=/joint_states',
           '-p', 'inverse_dynamics:=urdf', '-p', f'urdf_file:={example_robot_urdf("panda")}',
           '-p', f'joints:={json.dumps(names)}', '-p', f'model_path:={f("soak.npz")}']
    me = [sys.executable, os.path.abspath(__file__)]
    # a SIGTERM to the harness stops its processes too (they run in sessions of their own)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    procs = {}
    logs = [open(f(n + '.log'), 'w') for n in ('estimator', 'listener', 'player')]
    procs['node'] = C.start([sys.executable, '-m', 'dgp_ros.nodes.estimator'] + ros, logs[0],
                            est_env, work)
    procs['listener'] = C.start(me + ['--role', 'listener', '--file', f('lis.json'),
                                      '--sample-s', str(a.sample_s)], logs[1], env, work)
    time.sleep(2.0)
    procs['player'] = C.start(me + ['--role', 'player', '--file', f('player.json'), '--duration',
                                    str(a.duration), '--rate', str(a.rate)], logs[2], env, work)
    samples, t0 = [], time.monotonic()
    try:
        while procs['player'].poll() is None:
            if procs['node'].poll() is not None:
                raise RuntimeError(f'the node ended (see {f("estimator.log")})')
            learners = learner_pids(procs['node'].pid)
            row = {'t': time.monotonic() - t0}
            for key, fig in (('learner', ('VmRSS:', 'status')),
                             ('learner_anon', ('Anonymous:', 'smaps_rollup'))):
                row[key] = sum(_proc_mib(p, *fig) for p in learners) if learners \
                    else float('nan')
            if learners:                # the first learner's, by kind of mapping
                row.update({f'learner_{k}': v for k, v in _anon_parts(learners[0]).items()})
            row.update({k: _proc_mib(p.pid) for k, p in procs.items()})
            samples.append(row)
            C.log(f'{SECTION}: {row["t"]:.0f} s ' + ' '.join(
                f'{k} {v:.1f}' for k, v in row.items() if k != 't') + ' MiB')
            end = time.monotonic() + a.sample_s
            while time.monotonic() < end and procs['player'].poll() is None:
                time.sleep(0.5)
        time.sleep(2.0)
    finally:
        # the stream first (if interrupted), the node last
        out = {k + '_rc': C.stop(procs[k], sig, 60) for k, sig in (
            ('player', signal.SIGTERM), ('listener', signal.SIGTERM), ('node', signal.SIGINT))}
        for lg in logs:
            lg.close()
    log = open(f('estimator.log')).read()
    out.update(samples=samples, player=json.load(open(f('player.json'))),
               listener=json.load(open(f('lis.json'))), tracebacks=log.count('Traceback'),
               saved=os.path.exists(f('soak.npz')), trace={})
    for name in sorted(os.listdir(work)):
        if name.startswith('trace.') and name.endswith('.jsonl'):
            lines = open(f(name)).read().splitlines()
            if lines:
                out['trace'][name.split('.')[1]] = [json.loads(x) for x in lines]
    return out


# ----------------------------------------------------------------------------- the report
def growth(samples: list, key: str, last_s: float) -> tuple:
    """Return (max - min MiB, slope MiB/h) of ``key`` over the last ``last_s`` s of samples."""
    t = np.array([s['t'] for s in samples])
    y = np.array([s.get(key, np.nan) for s in samples], float)
    keep = (t >= t[-1] - last_s) & np.isfinite(y)
    if keep.sum() < 2:
        return float('nan'), float('nan')
    return float(np.ptp(y[keep])), float(np.polyfit(t[keep], y[keep], 1)[0] * 3600.0)


def age_percentile(hist: list, q: float) -> float:
    h = np.asarray(hist, float)
    if not h.sum():
        return float('nan')
    k = int(np.searchsorted(np.cumsum(h), q / 100.0 * h.sum()))
    return float(AGE_EDGES_MS[min(k + 1, len(AGE_EDGES_MS) - 1)])


def report(a, r: dict, wall: float) -> str:
    s = r['samples']
    span = s[-1]['t'] if s else 0.0
    last = 2400.0 if span >= 3000.0 else 2.0 * span / 3.0
    pub, lis = r['player']['published'], r['listener']
    rows = []
    for key, label in (('node', 'the node'), ('learner', 'its learner process'),
                       ('listener', 'the listener'), ('player', 'the player')):
        first = next((x[key] for x in s if np.isfinite(x[key])), float('nan'))
        rng, slope = growth(s, key, last)
        rows.append([label, C.fmt(first), C.fmt(s[-1][key]), C.fmt(rng), C.fmt(slope)])
    plt = C.plt()
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    t = np.array([x['t'] for x in s]) / 60.0
    for key in ('node', 'learner', 'listener', 'player'):
        ax.plot(t, [x[key] for x in s], marker='.', label=key)
    ax.set_xlabel('minutes')
    ax.set_ylabel('RSS (MiB)')
    ax.set_title(f'{a.rate:g} Hz for {a.duration / 60:g} min: resident memory')
    ax.grid(alpha=0.3)
    ax.legend()
    png = C.savefig(fig, a.out, 'soak_memory.png')
    body = [C.header_lines(TITLE, 'bench/soak_live.py', a.quick, wall), '',
            "The simulated Panda's raw `/joint_states` (7 joints and a finger) at "
            f'{a.rate:g} Hz '
            f'for {a.duration:g} s over DDS into the node as the README starts it on an arm '
            '(`inverse_dynamics:=urdf`, the URDF, `joints`, `model_path`; defaults otherwise), a '
            'listener with running statistics; RSS of every process every '
            f'{a.sample_s:g} s{" (tracemalloc on: slower)" if a.tracemalloc else ""}.', '',
            f'Answered {lis["answers"]} of {pub} published '
            f'({100.0 * lis["answers"] / max(pub, 1):.2f} %); '
            f'negative power {lis["negative_power"]}, non-finite {lis["non_finite"]}; the '
            "answers' age (publish to receipt) p50 <= "
            f'{C.fmt(age_percentile(lis["age_hist"], 50))} ms, '
            f'p99 <= {C.fmt(age_percentile(lis["age_hist"], 99))} ms; the longest silence '
            f'{C.fmt(lis["max_gap_s"] * 1e3)} ms; /diagnostics at WARN in '
            f'{lis["warn_periods"]} of {lis["diagnostics"]} periods; the node exited '
            f'{r.get("node_rc")} and saved its model: {"yes" if r["saved"] else "no"}; '
            f'tracebacks {r["tracebacks"]}; the player late by over 1 ms '
            f'{r["player"]["late_over_1ms"]} times.', '',
            f'Resident memory (MiB), at the first sample, at the end, and over the last '
            f'{last / 60:.0f} minutes (max - min, and the fitted slope):', '',
            C.md_table(['process', 'first', 'end', f'range, last {last / 60:.0f} min',
                        'slope (MiB/h)'], rows), '',
            f'![memory]({C.rel(png, a.out)})', '']
    kinds = [k for k in ('learner_anon', 'learner_heap', 'learner_large', 'learner_small')
             if any(k in x for x in s)]
    if kinds:
        parts = []
        for k in kinds:
            v = [x.get(k, float('nan')) for x in s]
            parts.append(f'{k.removeprefix("learner_")} {C.fmt(v[0])} -> {C.fmt(v[-1])} '
                         f'(range over the last {last / 60:.0f} min '
                         f'{C.fmt(growth(s, k, last)[0])})')
        body += ["The learner's anonymous memory by kind of mapping, MiB (`_anon_parts`: heap "
                 "= glibc's main arena, large = mappings of 8 MiB or more: thread arenas and "
                 'OpenBLAS buffers, small = the rest): ' + '; '.join(parts) + '.', '']
    for role, lines in r['trace'].items():
        top = lines[-1]['top'][:6]
        body += [f'tracemalloc, {role} at {lines[-1]["t"]:.0f} s (traced '
                 f'{lines[-1]["traced_mib"]:.1f} MiB): the top growers since the first period: '
                 + '; '.join(f'`{os.path.relpath(w, C.REPO) if w.startswith(C.REPO) else w}` '
                             f'{kb:+.0f} KiB ({n:+d})' for w, kb, n in top), '']
    if lis.get('warn_kinds'):
        body += ['The WARN periods, by the start of their message: ' + '; '.join(
            f'"{k}..." {n}' for k, n in sorted(lis['warn_kinds'].items(), key=lambda x: -x[1])),
            '']
    diag = lis.get('last_diag', {})
    if diag:
        body += [f'The last /diagnostics: level {diag.get("level")}, '
                 f'"{diag.get("message", "")[:300]}".']
    return '\n'.join(body)


def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv, _extra)
    if a.role == 'player':
        player(a)
        return 0
    if a.role == 'listener':
        listener(a)
        return 0
    if a.quick:
        a.duration, a.sample_s = min(a.duration, 60.0), min(a.sample_s, 5.0)
    import tempfile
    t0 = time.perf_counter()
    work = a.keep or tempfile.mkdtemp(prefix='dgp_soak_')
    os.makedirs(work, exist_ok=True)
    r = run(a, work)
    text = report(a, r, time.perf_counter() - t0)
    C.write_section(a.out, SECTION, text)
    print(text)
    ok = r['saved'] and not r['tracebacks'] and r['listener']['negative_power'] == 0
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())

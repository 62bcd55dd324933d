#!/usr/bin/env python3
"""
A 7-joint arm at 1 kHz, live: a player, the estimator node and a listener over real DDS (issue 23).

Every scenario is its own set of processes (``live_procs.py``): a player publishing a simulated
Panda's raw /joint_states (7 joints and a finger joint, stamps on the wall clock) at absolute
deadlines, the ``estimator`` node (defaults, ``inverse_dynamics=urdf``, ``--passivity``
(certified: the certification runs beside the refits), ``diagnostics_period_s`` 0.5 s) with its
message callbacks timed, and a listener receiving the measurements, the answers and /diagnostics
and probing services. DDS is isolated per run (a random ``ROS_DOMAIN_ID``, localhost discovery).
Scenarios, each a flag (none: all of them) and a row of the section's table:

* ``--khz``: 1 kHz for ``--duration`` s (20), refits and certification running; the saved model
  then predicts the held-out rest of the trajectory (and a sigmoid friction model fitted to the
  same residual, as before);
* ``--hz500``: the same at 500 Hz;
* ``--hog``: 1 kHz with another process keeping one core busy (a busy loop), services probed;
* ``--services``: 1 kHz, then a flood at 10 kHz, then 1 kHz again, with ``get_parameters`` (the
  executor alone) probed every 0.2 s and ``~/refit`` (the learner's reply) every 2 s, and the
  /diagnostics period;
* ``--kill``: 1 kHz while the learner process is SIGKILLed mid-refit 10 times (a ``~/refit``
  first, the kill 0.2 s after its reply): the longest silence of the answers, the time until a
  new learner is forked and until /diagnostics shows it back, tracebacks in the estimator's log;
* ``--learn-all``: every message learned (``selection=all``, ``min_sample_interval_s=0``,
  ``buffer_size=500``) at 1 kHz: learned samples per second end to end, and which process
  carries the cost;
* ``--cpu-split``: CPU per message of the message path, split into the executor (the rest of
  the node's main thread) and ours (the message callbacks), for rclpy's SingleThreadedExecutor
  and EventsExecutor and the node's wait-set loop, and for the code of ``--before-rev`` (its
  own executor).

Background: the CPU the machine spent outside this benchmark's processes during each run
(``/proc/stat`` minus our process trees), in cores of the 2; the load average at the end.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common as C  # noqa: E402

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, simulate_arm  # noqa: E402

SECTION = 'arm_live'
HERE = os.path.dirname(os.path.abspath(__file__))
PROCS = os.path.join(HERE, 'live_procs.py')
CLK = os.sysconf('SC_CLK_TCK')


@dataclass
class Scenario:
    """One run: what plays, how the estimator is set up, what else runs beside it."""

    name: str
    label: str
    phases: str                                  # player phases 'RATE:SECONDS,...'
    params: Dict[str, str] = field(default_factory=dict)
    executor: str = ''                           # DGP_EXECUTOR ('' = the node's default)
    tree: str = ''                               # source tree of the estimator ('' = this one)
    hog: bool = False
    probe_period: float = 0.0
    refit_period: float = 0.0
    kills: int = 0
    heldout: bool = False


def _extra(p):
    p.add_argument('--duration', type=float, default=20.0,
                   help='seconds of each 1 kHz / 500 Hz stream (quick: 4)')
    p.add_argument('--passivity', default='certified',
                   help="estimator passivity ('' = the node's default)")
    p.add_argument('--queue-depth', type=int, default=None)
    p.add_argument('--before-rev', default='',
                   help='git revision whose code is the "before" row of --cpu-split')
    for flag in ('khz', 'hz500', 'hog', 'services', 'kill', 'learn-all', 'cpu-split'):
        p.add_argument('--' + flag, action='store_true')
    p.add_argument('--repeat', type=int, default=1, help='runs per scenario (rows each)')
    p.add_argument('--keep', default='', help="keep every process's files in this directory")


# ----------------------------------------------------------------------------- CPU accounting
def _proc_table():
    """{pid: (ppid, cpu seconds)} of every process now."""
    out = {}
    for d in os.listdir('/proc'):
        if not d.isdigit():
            continue
        try:
            with open(f'/proc/{d}/stat') as f:
                s = f.read()
        except OSError:
            continue
        rest = s[s.rfind(')') + 2:].split()
        out[int(d)] = (int(rest[1]), (int(rest[11]) + int(rest[12])) / CLK)
    return out


def _machine_busy() -> float:
    with open('/proc/stat') as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return (sum(v) - v[3] - v[4]) / CLK


def _descendants(table, root) -> List[int]:
    kids: Dict[int, list] = {}
    for pid, (ppid, _) in table.items():
        kids.setdefault(ppid, []).append(pid)
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        for k in kids.get(p, ()):
            out.append(k)
            todo.append(k)
    return out


class CpuWatch:
    """
    CPU of this benchmark's processes and of the machine over a window (sampled every 0.25 s).

    ``report()``: background cores (the machine's busy time minus ours, over the wall time), and
    per tracked process (``track``): its own CPU seconds (``cpu_NAME_s``) and its descendants'
    (``cpu_NAME_kids_s``) within the window. A process that ended between two samples loses at
    most its last 0.25 s.
    """

    def __init__(self):
        self.seen: Dict[int, float] = {}
        self.first: Dict[int, float] = {}
        self.roots: Dict[str, int] = {}
        self.kids: Dict[str, set] = {}
        self._stop = threading.Event()
        self._t = None

    def track(self, name: str, pid: int) -> None:
        self.roots[name] = pid
        self.kids.setdefault(name, set())

    def start(self) -> None:
        self.b0, self.w0 = _machine_busy(), time.monotonic()
        self._sample(first=True)
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _sample(self, first: bool = False) -> None:
        table = _proc_table()
        me = os.getpid()
        for name, root in self.roots.items():
            self.kids[name].update(_descendants(table, root))
        for pid in set(_descendants(table, me)) | {me}:
            cpu = table[pid][1]
            if pid not in self.first:
                self.first[pid] = cpu if first else 0.0     # born during the window: from 0
            self.seen[pid] = max(self.seen.get(pid, 0.0), cpu)

    def _run(self) -> None:
        while not self._stop.wait(0.25):
            self._sample()

    def report(self) -> dict:
        self._sample()
        self._stop.set()
        self._t.join()
        wall = time.monotonic() - self.w0
        busy = _machine_busy() - self.b0

        def cpu(pids):
            return sum(self.seen.get(p, 0.0) - self.first.get(p, 0.0) for p in pids)
        ours = cpu(self.seen)
        out = {'wall_s': wall, 'bg_cores': max(0.0, (busy - ours) / wall),
               'machine_cores': busy / wall, 'ours_cores': ours / wall,
               'load': os.getloadavg()[0]}
        for name, root in self.roots.items():
            out[f'cpu_{name}_s'] = cpu([root])
            out[f'cpu_{name}_kids_s'] = cpu(self.kids[name])
        return out


# ----------------------------------------------------------------------------- one run
def _learner_pids(est_pid: int) -> List[int]:
    """Return the learner processes: children of the estimator's fork server."""
    table = _proc_table()
    out = []
    for pid in _descendants(table, est_pid):
        try:
            cmd = open(f'/proc/{pid}/cmdline', 'rb').read()
        except OSError:
            continue
        if b'forkserver' in cmd:
            out.extend(k for k in _descendants(table, pid))
    return out


def _killer(est_pid: int, sc: Scenario, t_start: float, seconds: float, ros_env: dict,
            out: list, stop: threading.Event) -> None:
    """SIGKILL the learner mid-refit ``sc.kills`` times; notes kill, fork and back times."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from std_srvs.srv import Trigger
    from diagnostic_msgs.msg import DiagnosticArray
    from dgp_ros.nodes.executor import WaitSetExecutor
    ctx = rclpy.Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO,
               domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = rclpy.create_node('arm_live_killer', context=ctx)
    cli = node.create_client(Trigger, '/dgp_estimator/refit')
    last = {}

    def on_diag(msg):
        for st in msg.status:
            if 'dgp_estimator' in st.name:
                last.clear()
                last.update({kv.key: kv.value for kv in st.values})
                last['t'] = time.time()
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    ex = WaitSetExecutor(context=ctx)
    ex.add_node(node)

    def spin_for(s, until=None):
        end = time.monotonic() + s
        while time.monotonic() < end and not stop.is_set():
            ex.spin_once(timeout_sec=0.005)
            if until is not None and until():
                return True
        return False
    # the kills begin once a model is trained (a kill before it only restarts the first fit)
    spin_for(max(0.0, t_start - time.time()))
    spin_for(seconds, lambda: last.get('trained') == 'True')
    t0 = time.time()
    period = max(1.5, (seconds - (t0 - t_start)) / (sc.kills + 1))
    for k in range(sc.kills):
        if stop.is_set():
            break
        t_next = time.time() + period
        rec = {'k': k, 'trained': last.get('trained')}
        if cli.service_is_ready():
            fut = cli.call_async(Trigger.Request())
            spin_for(5.0, fut.done)
            rec['refit_reply'] = fut.result().message if fut.done() else 'no reply'
        spin_for(0.2)
        rec['refit_running'] = last.get('refit_running', '?')
        restarts = int(last.get('learner_restarts', '0') or 0)
        pids = _learner_pids(est_pid)
        t_kill = time.time()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        rec.update(t_kill=t_kill, killed=pids)
        while time.time() - t_kill < 10 and not stop.is_set():
            new = [p for p in _learner_pids(est_pid) if p not in pids]
            if new:
                rec['t_fork'] = time.time() - t_kill
                break
            time.sleep(0.002)
        spin_for(10.0, lambda: int(last.get('learner_restarts', '0') or 0) > restarts
                 and last.get('learner_alive') == 'True')
        if int(last.get('learner_restarts', '0') or 0) > restarts:
            rec['t_back'] = last['t'] - t_kill
        out.append(rec)
        spin_for(max(0.0, t_next - time.time()))
    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()


def run_one(sc: Scenario, a, work: str, urdf: str, names: List[str]) -> dict:
    """Run one scenario; returns its raw results."""
    d = os.path.join(work, sc.name + f'_{random.randint(0, 1 << 30)}')
    os.makedirs(d)
    env = dict(os.environ, PYTHONUNBUFFERED='1', ROS_DOMAIN_ID=str(random.randint(150, 230)),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', OPENBLAS_NUM_THREADS='1',
               PYTHONPATH=C.REPO)
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.pop('DGP_EXECUTOR', None)
    # the estimator runs the scenario's code and executor; the other processes this tree's
    est_env = dict(env, PYTHONPATH=sc.tree or C.REPO)
    if sc.executor:
        est_env['DGP_EXECUTOR'] = sc.executor
    py = sys.executable
    f = lambda n: os.path.join(d, n)  # noqa: E731
    procs = []

    def start(name, args, log):
        pr = subprocess.Popen([py, PROCS] + args, env=est_env if name == 'estimator' else env,
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                              cwd=d)
        procs.append((name, pr))
        return pr

    watch = CpuWatch()
    if sc.hog:
        watch.track('hog', start('hog', ['hog'], subprocess.DEVNULL).pid)
    model_path = f('arm.npz')
    params = {'inverse_dynamics': 'urdf', 'urdf_file': urdf, 'joints': json.dumps(names),
              'model_path': model_path, 'diagnostics_period_s': '0.5'}
    if a.passivity:
        params['passivity'] = a.passivity
    if a.queue_depth:
        params['queue_depth'] = str(a.queue_depth)
    params.update(sc.params)
    ros = ['--ros-args', '-r', 'generalized_state:=/joint_states']
    for k, v in params.items():
        ros += ['-p', f'{k}:={v}']
    est_log = open(f('estimator.log'), 'w')
    est = start('estimator', ['estimator', '--cpu-out', f('est_cpu.json')] + ros, est_log)
    watch.track('estimator', est.pid)
    lis = start('listener', ['listener', '--out', f('listener.npz'), '--ready', f('lis.ready')],
                open(f('listener.log'), 'w'))
    watch.track('listener', lis.pid)
    prober = None
    if sc.probe_period or sc.refit_period:
        prober = start('prober', ['prober', '--out', f('prober.npz'), '--ready',
                                  f('prober.ready'), '--probe-period', str(sc.probe_period),
                                  '--refit-period', str(sc.refit_period)],
                       open(f('prober.log'), 'w'))
        watch.track('prober', prober.pid)
    seconds = sum(float(p.split(':')[1]) for p in sc.phases.split(','))
    kills: list = []
    stop = threading.Event()
    result = {'scenario': sc.name, 'label': sc.label}
    try:
        deadline = time.monotonic() + 120
        while not (os.path.exists(f('lis.ready')) and
                   (prober is None or os.path.exists(f('prober.ready')))):
            if time.monotonic() > deadline or lis.poll() is not None or est.poll() is not None:
                raise RuntimeError(f'{sc.name}: listener/estimator did not come up '
                                   f'(see {d})')
            time.sleep(0.1)
        player = start('player', ['player', '--phases', sc.phases, '--out', f('player.json'),
                                  '--ready', f('player.ready'), '--wait', '90'],
                       open(f('player.log'), 'w'))
        watch.track('player', player.pid)
        while not os.path.exists(f('player.ready')) and player.poll() is None:
            time.sleep(0.05)
        watch.start()                       # the window: the stream (the player's life)
        killer = None
        if sc.kills:
            killer = threading.Thread(target=_killer, args=(est.pid, sc, time.time() + 1.0,
                                                            seconds, env, kills, stop))
            killer.start()
        player.wait(timeout=seconds * 4 + 180)
        result.update(watch.report())
        if killer is not None:
            stop.set()
            killer.join(30)
        time.sleep(1.5)                     # the last answers and a diagnostics message
    finally:
        stop.set()
        # listener and prober first: their last probes must not go to an estimator that is
        # exiting
        for pr in (lis, prober):
            if pr is not None and pr.poll() is None:
                pr.send_signal(signal.SIGTERM)
                try:
                    pr.wait(30)
                except subprocess.TimeoutExpired:
                    pr.kill()
        est.send_signal(signal.SIGINT)
        try:
            result['est_rc'] = est.wait(60)
        except subprocess.TimeoutExpired:
            est.kill()
            result['est_rc'] = est.wait()
        for name, pr in procs:
            if pr.poll() is None:
                pr.send_signal(signal.SIGTERM if name != 'hog' else signal.SIGKILL)
        for name, pr in procs:
            try:
                pr.wait(30)
            except subprocess.TimeoutExpired:
                pr.kill()
        est_log.close()
    result['player'] = json.load(open(f('player.json')))
    L = np.load(f('listener.npz'), allow_pickle=False)
    result['lis'] = {k: L[k] for k in ('meas', 'ans', 'effort')}
    result['diags'] = json.loads(str(L['diags']))
    result['probes'], result['first_probes'] = {}, {}
    if prober is not None:
        P = np.load(f('prober.npz'), allow_pickle=False)
        result['probes'] = json.loads(str(P['probes']))
        result['first_probes'] = json.loads(str(P['first']))
    result['est_cpu'] = json.load(open(f('est_cpu.json'))) if os.path.exists(
        f('est_cpu.json')) else {}
    log = open(f('estimator.log')).read()
    result['tracebacks'] = log.count('Traceback')
    result['log_tail'] = log[-800:]
    result['kills'] = kills
    result['model_path'] = model_path if os.path.exists(model_path) else None
    result['seconds'] = seconds
    return result


# ----------------------------------------------------------------------------- numbers
def _pct(x, q):
    return float(np.percentile(x, q)) if len(x) else None


def summarize(r: dict, rng: np.ndarray) -> dict:
    """Return the row numbers of one run (ms, %, cores)."""
    meas, ans, eff = r['lis']['meas'], r['lis']['ans'], r['lis']['effort']
    pub = r['player']['published']
    m = dict(zip(meas[:, 0].astype(np.int64), meas[:, 1]))
    a_t = dict(zip(ans[:, 0].astype(np.int64), ans[:, 1]))
    paired = sorted(set(m) & set(a_t))
    lat = np.array([a_t[s] - m[s] for s in paired]) * 1e3
    age = (ans[:, 1] - ans[:, 0] * 1e-9) * 1e3
    s = {'published': pub, 'received': len(m), 'answers': len(a_t), 'paired': len(paired),
         'answered': len(a_t) / pub if pub else 0.0,
         'lat_p50': _pct(lat, 50), 'lat_p99': _pct(lat, 99),
         'lat_max': float(lat.max()) if len(lat) else None,
         'age_p50': _pct(age, 50), 'age_p99': _pct(age, 99),
         'bg': r['bg_cores'], 'load': r['load'], 'tracebacks': r['tracebacks'],
         'est_rc': r['est_rc']}
    if len(eff):
        s['answer_ratio'] = float(np.max(np.abs(eff[:, :rng.size]) / rng))
    # the backlog: the answers' age in the middle and the last third of the stream
    if len(age) > 30:
        order = np.argsort(ans[:, 0])
        thirds = np.array_split(age[order], 3)
        s['age_mid_p50'] = float(np.median(thirds[1]))
        s['age_last_p50'] = float(np.median(thirds[2]))
    # the longest silence of the answers while the stream ran (and of the measurements)
    if len(ans) > 2:
        t_a = np.sort(ans[:, 1])
        t_m = np.sort(meas[:, 1]) if len(meas) else t_a
        inside = (t_a >= t_m[0] + 0.5) & (t_a <= t_m[-1])
        g = np.diff(t_a[inside]) * 1e3 if inside.sum() > 2 else np.zeros(1)
        s['ans_gap_max'] = float(g.max())
        s['meas_gap_max'] = float(np.diff(t_m).max() * 1e3) if len(t_m) > 2 else None
        # around each kill: from the last answer before it until 0.5 s after the learner was
        # back (the whole run's longest silence may be elsewhere, e.g. the first model's swap)
        kg = []
        for k in r.get('kills', []):
            t0 = k.get('t_kill')
            if t0 is None:
                continue
            t1 = t0 + (k.get('t_back') or 2.0) + 0.5
            i0 = max(0, int(np.searchsorted(t_a, t0)) - 1)
            w = t_a[i0:int(np.searchsorted(t_a, t1))]
            if len(w) > 1:
                kg.append(float(np.diff(w).max() * 1e3))
        if kg:
            s['kill_gap_max'] = max(kg)
    d = r['diags'][-1] if r['diags'] else {}
    s['diag'] = d
    wall = r['wall_s']
    s['node_cores'] = r.get('cpu_estimator_s', 0.0) / wall
    s['learner_cores'] = r.get('cpu_estimator_kids_s', 0.0) / wall     # fork server, learner
    ec = r['est_cpu']
    if ec and ec.get('calls'):
        # from its first message callback to its last (the wrapper in live_procs.py)
        n = ec.get('received') or int(d.get('messages_received', 0) or 0) or 1
        s['us_ours'] = ec['callbacks_s'] / n * 1e6
        s['us_exec'] = (ec['main_thread_s'] - ec['callbacks_s']) / n * 1e6
        s['us_proc'] = ec['process_s'] / n * 1e6
    # the diagnostics' inter-arrival (their period is 0.5 s unless the scenario sets it)
    t_d = np.array([x['t'] for x in r['diags']])
    if len(t_d) > 2:
        s['diag_gap_max'] = float(np.diff(t_d).max())          # as the listener got them
    t_n = np.array(ec.get('diag_times', []) if ec else [])
    if len(t_n) > 2:
        s['diag_gap_node'] = float(np.diff(t_n).max())         # as the node sent them
    for kind, vals in r.get('first_probes', {}).items():
        s[f'first_{kind}'] = float(vals[0][1]) * 1e3 if vals else None
    for kind, vals in r['probes'].items():
        rt = np.array([v[1] for v in vals]) * 1e3
        if len(rt):
            s[f'probe_{kind}'] = (len(rt), _pct(rt[np.isfinite(rt)], 50) if np.isfinite(
                rt).any() else None, _pct(rt[np.isfinite(rt)], 99) if np.isfinite(rt).any()
                else None, float(rt.max()), int((~np.isfinite(rt)).sum()))
    if r['kills']:
        k = r['kills']
        s['kills'] = len(k)
        s['kills_mid_refit'] = sum(1 for x in k if x.get('refit_running') == 'True')
        s['t_fork'] = [x.get('t_fork') for x in k]
        s['t_back'] = [x.get('t_back') for x in k]
        s['learner_restarts'] = d.get('learner_restarts')
    return s


# ----------------------------------------------------------------------------- scenarios
def scenarios(a) -> List[Scenario]:
    q = a.quick
    T = a.duration
    chosen = [x for x in ('khz', 'hz500', 'hog', 'services', 'kill', 'learn_all', 'cpu_split')
              if getattr(a, x)]
    if not chosen:
        chosen = ['khz', 'services', 'kill'] if q else \
            ['khz', 'hz500', 'hog', 'services', 'kill', 'learn_all', 'cpu_split']
    out = []
    if 'khz' in chosen:
        out.append(Scenario('khz', f'1 kHz, {T:g} s', f'1000:{T:g}', heldout=True))
    if 'hz500' in chosen:
        out.append(Scenario('hz500', f'500 Hz, {T:g} s', f'500:{T:g}'))
    if 'hog' in chosen:
        out.append(Scenario('hog', f'1 kHz, {T:g} s, one core kept busy', f'1000:{T:g}',
                            hog=True, probe_period=0.2))
    if 'services' in chosen:
        f = 2.0 if q else 5.0
        out.append(Scenario('services', f'1 kHz {f:g} s, 10 kHz {f:g} s, 1 kHz {f:g} s; '
                            'services probed', f'1000:{f:g},10000:{f:g},1000:{f:g}',
                            probe_period=0.2, refit_period=2.0))
    if 'kill' in chosen:
        n = 2 if q else 10
        out.append(Scenario('kill', f'1 kHz, learner SIGKILLed mid-refit {n}x',
                            f'1000:{max(T, 3.0 * n):g}', kills=n,
                            params={'diagnostics_period_s': '0.1'}))
    if 'learn_all' in chosen:
        out.append(Scenario('learn_all', f'1 kHz, {T:g} s, every message learned, buffer 500',
                            f'1000:{T:g}', params={'buffer_size': '500', 'selection': 'all',
                                                   'min_sample_interval_s': '0.0'}))
    if 'cpu_split' in chosen:
        for ex in ('single', 'events', 'waitset'):
            out.append(Scenario(f'cpu_{ex}', f'1 kHz, {T:g} s, executor {ex}', f'1000:{T:g}',
                                executor=ex))
        if a.before_rev:
            out.append(Scenario('cpu_before', f'1 kHz, {T:g} s, code of {a.before_rev} '
                                '(before)', f'1000:{T:g}', tree='BEFORE'))
    return out


def _before_tree(rev: str, work: str) -> str:
    d = os.path.join(work, 'before')
    os.makedirs(d)
    arch = subprocess.run(['git', 'archive', rev, 'dgp_ros', 'sim_bridge'], cwd=C.REPO,
                          capture_output=True, check=True).stdout
    subprocess.run(['tar', '-x', '-C', d], input=arch, check=True)
    return d


def heldout(r: dict, d: dict, k: int, urdf: str, names: List[str]) -> dict:
    """Score the saved model on the held-out rest of the trajectory, and a sigmoid model."""
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig
    import robot_arms
    model = load_model(r['model_path'])
    te = np.arange(k, len(d['t']), 10)
    Qt, truth = d['qd_true'][te], d['friction'][te]
    nmse = np.mean((model.predict(Qt) - truth) ** 2, axis=0) / np.var(truth, axis=0)
    Qr, R = robot_arms.residual_stream({'sim': d, 'k': k, 'names': names}, urdf,
                                       EstimatorConfig())
    sig = np.empty_like(truth)
    for j in range(len(names)):
        cv = robot_arms.fit_cv(Qr[:, j], R[:, j])
        sig[:, j] = robot_arms.fit_sigmoid(Qr[:, j], R[:, j], cv)['f'](Qt[:, j])
    nmse_sig = np.mean((sig - truth) ** 2, axis=0) / np.var(truth, axis=0)
    X = np.random.default_rng(0).uniform(-3, 3, (100_000, len(names)))
    neg = int(np.sum(np.einsum('ij,ij->i', X, model.predict(X)) < 0))
    return {'nmse': nmse.tolist(), 'nmse_sigmoid': nmse_sig.tolist(), 'negative_power': neg,
            'friction_rms': np.sqrt(np.mean(truth ** 2, axis=0)).tolist()}


# ----------------------------------------------------------------------------- the section
def _ms(x):
    return C.fmt(x) if x is not None else '-'


def _gate(ok: Optional[bool]) -> str:
    return '-' if ok is None else ('met' if ok else '**missed**')


def section(a, runs: List[dict], held: Optional[dict], wall: float, names) -> str:
    lines = [C.header_lines('A 7-joint arm at 1 kHz, live (player -> estimator node -> '
                            'listener)', 'bench/arm_live.py', a.quick, wall), '',
             f'A simulated Panda (7 joints and a finger joint, like its driver) published by a '
             f'player process at absolute deadlines into the `estimator` node (`model=full`, '
             f'`prior=auto`, `passivity={a.passivity or "default"}`, `inverse_dynamics=urdf`, '
             f'other parameters default unless the scenario says; its own executor is the '
             f'wait-set loop unless named) and a listener process, all on this 2-core machine, '
             f'DDS isolated per run. **bg** is the CPU the machine spent outside these '
             f'processes during the run (other jobs), in cores of the 2; load is the 1-min '
             f'load average at the end. Latency: the listener receives the measurement -> it '
             f"receives the answer; age: the answer received minus the measurement's stamp "
             f'(its deadline on the wall clock). Answered: answers received / messages '
             f'published. |answer| / range: the largest |estimate| over the per-joint range of '
             f'the residual the estimator learns from. CPU us/msg (per message received): ours '
             f"= in the message callbacks; executor = the rest of the node's main thread; "
             f'process = every thread of the node process (not the learner).', '']
    hdr = ['scenario', 'answered', 'latency p50 / p99 / max ms', 'age p50 / p99 ms',
           '|answer| / range', 'node / learner cores', 'CPU us/msg ours / executor / process',
           'lost (listener saw / node received)', 'bg cores', 'load']
    rows = []
    for r in runs:
        s = r['sum']
        d = s['diag']
        rows.append([r['label'], f'{100 * s["answered"]:.2f} %',
                     f'{_ms(s["lat_p50"])} / {_ms(s["lat_p99"])} / {_ms(s["lat_max"])}',
                     f'{_ms(s["age_p50"])} / {_ms(s["age_p99"])}',
                     C.fmt(s.get('answer_ratio')),
                     f'{s.get("node_cores", 0):.2f} / {s.get("learner_cores", 0):.2f}',
                     f'{C.fmt(s.get("us_ours"))} / {C.fmt(s.get("us_exec"))} / '
                     f'{C.fmt(s.get("us_proc"))}',
                     f'{s["published"] - s["received"]} / '
                     f'{d.get("messages_received", "-")} of {s["published"]}',
                     f'{s["bg"]:.2f}', f'{s["load"]:.2f}'])
    lines += [C.md_table(hdr, rows), '']
    by = {}
    for r in runs:
        by.setdefault(r['scenario'], []).append(r)
    # the main scenario in the form the CI smoke test reads
    if 'khz' in by:
        r = by['khz'][0]
        s, d = r['sum'], r['sum']['diag']
        rows = [['answered (of published)', f'{100 * s["answered"]:.2f} %'],
                ['received by the listener', f'{s["received"]} of {s["published"]}'],
                ['end-to-end latency median / p99', f'{_ms(s["lat_p50"])} / '
                                                    f'{_ms(s["lat_p99"])} ms'],
                ['estimator: messages received', d.get('messages_received', '-')],
                ['estimator: messages missing (from stamp gaps)',
                 d.get('messages_missing', '-')],
                ['estimator: stamp -> answer median / p99 (s)',
                 f'{d.get("stamp_to_answer_median_s", "-")} / '
                 f'{d.get("stamp_to_answer_p99_s", "-")}'],
                ['estimator: samples learned / refits ok / rejected',
                 f'{d.get("samples_added", "-")} / {d.get("refits_ok", "-")} / '
                 f'{d.get("refits_rejected", "-")}'],
                ['estimator: certified / guarantee', f'{d.get("certified", "-")} / '
                                                     f'{d.get("guarantee", "-")}'],
                ['estimator: status at the end', d.get('message', '-')],
                ['estimator exit status after SIGINT (model saved)', s['est_rc']],
                ['negative power in 10^5 random velocities',
                 held['negative_power'] if held else '-']]
        lines += ['### 1 kHz, the main run', '', C.md_table(['quantity', 'value'], rows), '']
        if held:
            lines.append(C.md_table(
                ['joint', 'held-out NMSE (live model)', 'sigmoid model', 'ratio'],
                [[j, C.fmt(x), C.fmt(y), C.fmt(x / y)] for j, x, y in
                 zip(names, held['nmse'], held['nmse_sigmoid'])]))
    if 'services' in by or 'hog' in by:
        rows = []
        for key in ('services', 'hog'):
            for r in by.get(key, []):
                s = r['sum']
                for kind in ('get_parameters', 'refit'):
                    p = s.get(f'probe_{kind}')
                    if p:
                        rows.append([r['label'], kind, p[0], f'{_ms(p[1])} / {_ms(p[2])} / '
                                     f'{_ms(p[3])}', p[4], _ms(s.get(f'first_{kind}'))])
                rows.append([r['label'], '/diagnostics (period 0.5 s)', '-',
                             f'largest interval {C.fmt(s.get("diag_gap_node"))} s sent, '
                             f'{C.fmt(s.get("diag_gap_max"))} s received', '-', '-'])
        lines += ['### Services and /diagnostics under the stream', '',
                  'Round trips from a prober process that does nothing else (`get_parameters` is '
                  "served by the node's executor alone; `~/refit` is answered by the learner, or "
                  "after 20 ms by the node saying the request is queued). A client's first "
                  'call also waits for DDS to match its reply reader with the service: it is '
                  'shown apart and not counted.', '',
                  C.md_table(['scenario', 'service', 'calls', 'round trip p50 / p99 / max ms',
                              'unanswered', 'first call ms'], rows), '']
    if 'kill' in by:
        rows = []
        for r in by['kill']:
            s = r['sum']
            fork = [x for x in s.get('t_fork', []) if x is not None]
            back = [x for x in s.get('t_back', []) if x is not None]
            rows.append([r['label'], f'{s.get("kills", 0)} ({s.get("kills_mid_refit", 0)})',
                         f'{_ms(s.get("kill_gap_max"))} / {_ms(s.get("ans_gap_max"))} '
                         f'(measurements {_ms(s.get("meas_gap_max"))})',
                         f'{C.fmt(np.median(fork) * 1e3) if fork else "-"} / '
                         f'{C.fmt(max(fork) * 1e3) if fork else "-"}',
                         f'{C.fmt(np.median(back)) if back else "-"} / '
                         f'{C.fmt(max(back)) if back else "-"} ({len(back)} of '
                         f'{s.get("kills", 0)})', s.get('learner_restarts', '-'),
                         s['tracebacks'], s['est_rc']])
        lines += ['### The learner killed mid-refit', '',
                  'SIGKILL to the learner process 0.2 s after a `~/refit` reply (mid-refit: '
                  'the refit is running at the kill per the last /diagnostics, period 0.1 s). '
                  'Back: until /diagnostics (period 0.1 s) shows the restart with the learner '
                  'alive.', '',
                  'Longest answer gap: around the kills (from the last answer before one '
                  'until 0.5 s after the learner was back) / over the whole run after its '
                  'first 0.5 s.', '',
                  C.md_table(['scenario', 'kills (mid-refit)',
                              'longest answer gap ms: kills / run',
                              'new learner forked median / max ms', 'back median / max s',
                              'restarts counted', 'tracebacks in its log', 'exit status'],
                             rows), '']
    if 'learn_all' in by:
        rows = []
        for r in by['learn_all']:
            s = r['sum']
            d = s['diag']
            learned = int(d.get('samples_added', 0) or 0)
            rows.append([r['label'], d.get('messages_received', '-'), learned,
                         f'{learned / r["seconds"]:.0f}', d.get('samples_pending', '-'),
                         f'{d.get("samples_skipped", "-")} / {d.get("samples_outliers", "-")}',
                         d.get('samples_dropped', '-'), f'{100 * s["answered"]:.2f} %',
                         f'{s.get("node_cores", 0):.2f}', f'{s.get("learner_cores", 0):.2f}',
                         C.fmt(s.get('us_ours'))])
        lines += ['### Every message learned (buffer 500)', '',
                  "Learned per second of stream: the learner process's `samples_added` at the "
                  "end over the stream's length (what went in end to end); the ring between "
                  'the processes drops (and counts) what the learner cannot take.', '',
                  C.md_table(['scenario', 'messages received', 'samples learned',
                              'learned / s', 'still in the ring at the end',
                              'skipped / outliers', 'dropped at the ring', 'answered',
                              'node cores', 'learner cores', 'message path us/msg'], rows), '']
    cpu_rows = [r for r in runs if r['scenario'].startswith('cpu_') or r['scenario'] == 'khz']
    if any(r['scenario'].startswith('cpu_') for r in runs):
        rows = []
        for r in cpu_rows:
            s = r['sum']
            rows.append([r['label'], C.fmt(s.get('us_exec')), C.fmt(s.get('us_ours')),
                         C.fmt(s.get('us_proc')), f'{100 * s["answered"]:.2f} %',
                         f'{s["bg"]:.2f}'])
        lines += ['### CPU per message on the message path', '',
                  "Thread CPU of the node's main thread per message received: in the message "
                  'callbacks (ours: validate, hand over to the learner, answer, publish) and '
                  'the rest (the executor: waiting, taking, dispatching); process: every '
                  'thread of the node process (DDS, the snapshot receiver).', '',
                  C.md_table(['run', 'executor us/msg', 'ours us/msg', 'process us/msg',
                              'answered', 'bg cores'], rows), '']
    lines += ['### Targets (issue 23)', '',
              C.md_table(['target', 'status', 'measured'], targets(by, held)), '']
    return '\n'.join(lines)


def targets(by: dict, held: Optional[dict]) -> list:
    out = []

    def first(key):
        return by[key][0]['sum'] if key in by else None
    s = first('khz')
    if s:
        out.append(['1 kHz: >= 99 % answered', _gate(s['answered'] >= 0.99),
                    f'{100 * s["answered"]:.2f} % (bg {s["bg"]:.2f})'])
        out.append(['1 kHz: end-to-end p99 <= 5 ms', _gate((s['lat_p99'] or 1e9) <= 5),
                    f'{_ms(s["lat_p99"])} ms'])
        out.append(['1 kHz: median <= 2 ms', _gate((s['lat_p50'] or 1e9) <= 2),
                    f'{_ms(s["lat_p50"])} ms'])
        out.append(['1 kHz: no answer over 2x the data range',
                    _gate(s.get('answer_ratio', 1e9) <= 2), C.fmt(s.get('answer_ratio'))])
    s = first('hz500')
    if s:
        out.append(['500 Hz: >= 99.9 % answered', _gate(s['answered'] >= 0.999),
                    f'{100 * s["answered"]:.2f} % (bg {s["bg"]:.2f})'])
    s = first('hog')
    if s:
        grows = s.get('age_last_p50') is not None and \
            s['age_last_p50'] > 2 * s['age_mid_p50'] + 20
        p = s.get('probe_get_parameters')
        out.append(['one core busy: >= 95 % answered at 1 kHz', _gate(s['answered'] >= 0.95),
                    f'{100 * s["answered"]:.2f} % (bg {s["bg"]:.2f})'])
        out.append(['one core busy: no backlog that grows', _gate(not grows),
                    f'answer age median {_ms(s.get("age_mid_p50"))} ms (middle third) -> '
                    f'{_ms(s.get("age_last_p50"))} ms (last third)'])
        out.append(['one core busy: services within 100 ms',
                    _gate(p is not None and p[3] <= 100 and not p[4]),
                    f'get_parameters max {_ms(p[3]) if p else "-"} ms'])
    s = first('services')
    if s:
        for kind in ('get_parameters', 'refit'):
            p = s.get(f'probe_{kind}')
            out.append([f'flood: {kind} answered within 100 ms',
                        _gate(p is not None and p[3] <= 100 and not p[4]),
                        f'max {_ms(p[3]) if p else "-"} ms, unanswered {p[4] if p else "-"}'])
        out.append(['flood: /diagnostics within 100 ms of its period',
                    _gate(s.get('diag_gap_node', 9) <= 0.6),
                    f'largest interval {C.fmt(s.get("diag_gap_node"))} s sent by the node, '
                    f'{C.fmt(s.get("diag_gap_max"))} s received (period 0.5 s)'])
    s = first('kill')
    if s:
        back = [x for x in s.get('t_back', []) if x is not None]
        out.append(['learner SIGKILL x10: answers never stop > 50 ms',
                    _gate(s.get('kill_gap_max', 1e9) <= 50),
                    f'{_ms(s.get("kill_gap_max"))} ms around the kills '
                    f'({_ms(s.get("ans_gap_max"))} ms over the whole run)'])
        out.append(['learner SIGKILL x10: back within 2 s',
                    _gate(len(back) == s.get('kills') and max(back) <= 2.0),
                    f'max {C.fmt(max(back)) if back else "-"} s, {len(back)} of '
                    f'{s.get("kills")}'])
        out.append(['learner SIGKILL x10: no traceback', _gate(s['tracebacks'] == 0),
                    str(s['tracebacks'])])
    s = by.get('learn_all')
    if s:
        r = s[0]
        d = r['sum']['diag']
        learned = int(d.get('samples_added', 0) or 0) / r['seconds']
        queued = int(d.get('samples_pending', 0) or 0)
        # a 1 kHz stream is the ceiling: kept up = (almost) all of it learned, nothing queued
        # (the first residual trails its message by the filter's half window, 0.05 s)
        out.append(['every message learned at buffer 500: >= 1000 msg/s end to end',
                    _gate(learned >= 990 and queued < 100),
                    f'{learned:.0f} msg/s learned of a 1 kHz stream, {queued} still queued for '
                    'the learner at the end (the learner carries the cost; the message path '
                    'only pushes a row into the ring)'])
    if held:
        import robot_arms
        trio = zip(held['nmse'], held['nmse_sigmoid'], held['friction_rms'])
        ok = all(x <= 0.5 * y for x, y, f in trio if f > robot_arms.NOISE_SD)
        out.append(['held-out NMSE <= 0.5 x sigmoid on every joint whose friction exceeds '
                    'the noise', _gate(ok), ', '.join(C.fmt(x / y) for x, y in
                                                      zip(held['nmse'], held['nmse_sigmoid']))])
    return out


def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv, _extra)
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')     # the killer's node too
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    if a.quick:
        a.duration = min(a.duration, 4.0)
    names = list(ARM_JOINTS['panda'])
    urdf = example_robot_urdf('panda')
    t0 = time.perf_counter()
    runs, failed = [], []
    held = None
    with tempfile.TemporaryDirectory() as tmp:
        work = a.keep or tmp
        os.makedirs(work, exist_ok=True)
        scs = scenarios(a)
        if any(sc.tree == 'BEFORE' for sc in scs):
            before = _before_tree(a.before_rev, work)
            for sc in scs:
                if sc.tree == 'BEFORE':
                    sc.tree = before
        # the residual's range per joint (what an answer is compared with): the played stream
        T = max(float(p.split(':')[1]) for sc in scs for p in sc.phases.split(','))
        d = simulate_arm('panda', max(T, a.duration) / 0.6, seed=7)
        k = int(round(a.duration * 1000))
        import robot_arms
        from dgp_ros.online import EstimatorConfig
        _, R = robot_arms.residual_stream({'sim': d, 'k': min(k, len(d['t'])), 'names': names},
                                          urdf, EstimatorConfig())
        rng = np.abs(R).max(axis=0)
        for sc in scs:
            for i in range(a.repeat):
                C.log(f'arm_live: {sc.label} (run {i + 1} of {a.repeat})')
                try:
                    r = run_one(sc, a, work, urdf, names)
                except Exception as exc:        # noqa: BLE001 - the section says so
                    C.log(f'arm_live: {sc.name} failed: {exc}')
                    failed.append(f'{sc.label}: {exc}')
                    continue
                r['sum'] = summarize(r, rng)
                s = r['sum']
                C.log(f'arm_live: {sc.name}: answered {100 * s["answered"]:.2f} %, latency '
                      f'p50 {_ms(s["lat_p50"])} p99 {_ms(s["lat_p99"])} ms, ours/exec '
                      f'{C.fmt(s.get("us_ours"))}/{C.fmt(s.get("us_exec"))} us/msg, bg '
                      f'{s["bg"]:.2f}')
                if sc.heldout and held is None and r['model_path']:
                    held = heldout(r, d, k, urdf, names)
                r.pop('lis', None)
                runs.append(r)
    wall = time.perf_counter() - t0
    text = section(a, runs, held, wall, names)
    if failed:
        text += '\nRuns that failed: ' + '; '.join(failed) + '\n'
    C.write_section(a.out, SECTION, text)
    with open(os.path.join(C.plot_dir(a.out), 'arm_live_runs.json'), 'w') as f:
        json.dump([{k: v for k, v in r.items() if k not in ('diags',)} for r in runs], f,
                  default=lambda o: o.tolist() if hasattr(o, 'tolist') else str(o))
    return 0


if __name__ == '__main__':
    sys.exit(main())

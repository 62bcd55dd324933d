#!/usr/bin/env python3
"""
A 7-joint arm at 1 kHz, live: a player, the estimator node and a listener over real DDS.

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
from typing import Dict, List

import numpy as np

from arm_live_report import fmt_ms, section, summarize  # noqa: E402
import common as C  # noqa: E402
from cpu_watch import CpuWatch, learner_pids  # noqa: E402

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, simulate_arm  # noqa: E402

SECTION = 'arm_live'
HERE = os.path.dirname(os.path.abspath(__file__))
PROCS = os.path.join(HERE, 'live_procs.py')


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
    node: str = 'estimator'                      # or 'relay' (the floor, bench/arm_floor.py)
    stream: str = ''                             # the real Panda's folder: its residual plays
    env: Dict[str, str] = field(default_factory=dict)     # more environment of the estimator


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


# ----------------------------------------------------------------------------- one run
def _killer(est_pid: int, sc: Scenario, t_start: float, seconds: float, ros_env: dict,
            out: list, stop: threading.Event) -> None:
    """SIGKILL the learner mid-refit ``sc.kills`` times; notes kill, fork and back times."""
    from std_srvs.srv import Trigger
    from dgp_ros.nodes.executor import WaitSetExecutor
    from live_common import close, on_diagnostics, ros_node
    ctx, node = ros_node('arm_live_killer', domain_id=int(ros_env['ROS_DOMAIN_ID']))
    cli = node.create_client(Trigger, '/dgp_estimator/refit')
    last = {}

    def on_diag(st, values):
        last.clear()
        last.update(values, t=time.time())
    on_diagnostics(node, on_diag, 10)
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
        pids = learner_pids(est_pid)
        t_kill = time.time()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        rec.update(t_kill=t_kill, killed=pids)
        while time.time() - t_kill < 10 and not stop.is_set():
            new = [p for p in learner_pids(est_pid) if p not in pids]
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
    close(ctx, node, ex)


def run_one(sc: Scenario, a, work: str, urdf: str, names: List[str]) -> dict:
    """Run one scenario; returns its raw results."""
    d = os.path.join(work, sc.name + f'_{random.randint(0, 1 << 30)}')
    os.makedirs(d)
    env = C.dds_env(**C.CHILD_ENV)
    env.pop('DGP_EXECUTOR', None)
    # the estimator runs the scenario's code and executor; the other processes this tree's
    est_env = dict(env, PYTHONPATH=sc.tree or C.REPO)
    if sc.executor:
        est_env['DGP_EXECUTOR'] = sc.executor
    est_env.update(sc.env)
    py = sys.executable
    f = lambda n: os.path.join(d, n)  # noqa: E731
    procs = []

    def start(name, args, log):
        pr = C.start([py, PROCS] + args, log, est_env if name in ('estimator', 'relay') else env,
                     d)
        procs.append((name, pr))
        return pr

    watch = CpuWatch()
    if sc.hog:
        watch.track('hog', start('hog', ['hog'], subprocess.DEVNULL).pid)
    model_path = f('arm.npz')
    params = {'inverse_dynamics': 'urdf', 'urdf_file': urdf, 'joints': json.dumps(names),
              'model_path': model_path, 'diagnostics_period_s': '0.5'}
    if sc.stream:                       # a residual: the estimator's defaults, no dynamics
        params = {'joints': json.dumps(names), 'model_path': model_path,
                  'diagnostics_period_s': '0.5'}
    if a.passivity:
        params['passivity'] = a.passivity
    if a.queue_depth:
        params['queue_depth'] = str(a.queue_depth)
    params.update(sc.params)
    ros = ['--ros-args', '-r', 'generalized_state:=/joint_states']
    for k, v in params.items():
        ros += ['-p', f'{k}:={v}']
    est_log = open(f('estimator.log'), 'w')
    if sc.node == 'relay':
        est = start('relay', ['relay', '--cpu-out', f('est_cpu.json')], est_log)
    else:
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
        stream = ['--stream', sc.stream, '--seconds', str(seconds)] if sc.stream else []
        player = start('player', ['player', '--phases', sc.phases, '--out', f('player.json'),
                                  '--ready', f('player.ready'), '--wait', '90'] + stream,
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
            C.stop(pr, signal.SIGTERM, 30)
        result['est_rc'] = C.stop(est, signal.SIGINT, 60)
        for name, pr in procs:
            C.stop(pr, signal.SIGTERM if name != 'hog' else signal.SIGKILL, 30)
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
    from dgp_ros.dynamics.baselines import fit_cv, fit_sigmoid
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig
    from robot_arms_runs import residual_stream
    model = load_model(r['model_path'])
    te = np.arange(k, len(d['t']), 10)
    Qt, truth = d['qd_true'][te], d['friction'][te]
    nmse = np.mean((model.predict(Qt) - truth) ** 2, axis=0) / np.var(truth, axis=0)
    Qr, R = residual_stream({'sim': d, 'k': k, 'names': names}, urdf, EstimatorConfig())
    sig = np.empty_like(truth)
    for j in range(len(names)):
        cv = fit_cv(Qr[:, j], R[:, j])
        sig[:, j] = fit_sigmoid(Qr[:, j], R[:, j], cv)['f'](Qt[:, j])
    nmse_sig = np.mean((sig - truth) ** 2, axis=0) / np.var(truth, axis=0)
    X = np.random.default_rng(0).uniform(-3, 3, (100_000, len(names)))
    neg = int(np.sum(np.einsum('ij,ij->i', X, model.predict(X)) < 0))
    return {'nmse': nmse.tolist(), 'nmse_sigmoid': nmse_sig.tolist(), 'negative_power': neg,
            'friction_rms': np.sqrt(np.mean(truth ** 2, axis=0)).tolist()}


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv, _extra)
    C.localhost_only()                                              # the killer's node too
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
        from dgp_ros.online import EstimatorConfig
        from robot_arms_runs import residual_stream
        _, R = residual_stream({'sim': d, 'k': min(k, len(d['t'])), 'names': names}, urdf,
                               EstimatorConfig())
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
                      f'p50 {fmt_ms(s["lat_p50"])} p99 {fmt_ms(s["lat_p99"])} ms, ours/exec '
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

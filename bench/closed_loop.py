#!/usr/bin/env python3
"""
Closed-loop friction compensation on the simulated arm, measured.

Per robot (Panda, UR5), in process and lock-step (``dgp_ros.apps.loop_run``: the estimator with
the node's defaults except ``refit_mode='sync'``), the same reference path and seed:

1. the four compensations none / sigmoid / dgp / dgp_damping_only over ``--duration`` s, learning
   the first ``--learn`` s, the rest held out: tracking RMS per joint and mean, dgp / none and
   dgp / sigmoid, the worst joint's dgp / none, injected energy, non-passive answers;
2. (``--stability``) one ``dgp`` run of 60 s: tracking RMS of the first and the last third, and the
   count of published answers with ``qd . tau_hat < 0``;
3. the estimator killed at the middle of a ``dgp`` run (it answers nothing from then on, as after
   a SIGKILL): tracking RMS from the kill + the controller's timeout to the end, against the none
   run's over the same window.

Writes ``<out>/closed_loop.json`` and prints markdown rows (the sweep at a2de3ce:
docs/CHANGELOG.md).
Usage: bench/closed_loop.py [--robots panda,ur5] [--duration 24] [--learn 16] [--stability]
"""
from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
import json
import multiprocessing
import os
import time

import numpy as np

from dgp_ros.apps.loop_demo import summarize, sweep
from dgp_ros.apps.loop_run import run_loop, score, TIMEOUT_S
from dgp_ros.dynamics import ARM_JOINTS


def _killed(args):
    robot, duration, learn, kill = args
    r = run_loop(robot, 'dgp', duration, learn, kill_at_s=kill)
    return {'t': r['t'], 'error': r['error'], 'stale': r['stale']}


def _stable(args):
    robot, duration = args
    r = run_loop(robot, 'dgp', duration, duration / 3.0)
    third = duration / 3.0
    return {'first_third': score(r, 0.0, third)[0].tolist(),
            'last_third': score(r, 2 * third, duration)[0].tolist(),
            'answers': r['answers'], 'nonpassive_answers': r['nonpassive_answers'],
            'wall_s': r['wall_s']}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--robots', default='panda,ur5')
    ap.add_argument('--duration', type=float, default=24.0)
    ap.add_argument('--learn', type=float, default=16.0)
    ap.add_argument('--stability', type=float, default=60.0, help='0: skip')
    ap.add_argument('--out', default='out/bench_closed_loop')
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    res = {}
    ctx = multiprocessing.get_context('spawn')
    for robot in a.robots.split(','):
        t0 = time.monotonic()
        kill = 0.5 * a.duration
        with ProcessPoolExecutor(2, mp_context=ctx) as ex:
            side = [ex.submit(_killed, (robot, a.duration, a.learn, kill))]
            if a.stability > 0:
                side.append(ex.submit(_stable, (robot, a.stability)))
            runs = sweep(robot, a.duration, a.learn, 0, 2)
            killed = side[0].result()
            stable = side[1].result() if a.stability > 0 else None
        s = summarize(runs, a.learn, ARM_JOINTS[robot])
        after = kill + TIMEOUT_S
        k_rms = score(killed, after)[0]
        n_rms = score(runs['none'], after)[0]
        s['kill'] = {'at_s': kill, 'scored_from_s': after, 'rms_killed': k_rms.tolist(),
                     'rms_none': n_rms.tolist(), 'ratio_mean': float(k_rms.mean() / n_rms.mean()),
                     'worst_joint_ratio': float(np.max(k_rms / n_rms)),
                     'stale_steps': killed['stale']}
        s['stability'] = stable
        s['wall_s'] = time.monotonic() - t0
        res[robot] = s
        keys = ('tracking_rms_mean', 'ratio_dgp_none', 'ratio_dgp_sigmoid',
                'worst_joint_ratio_dgp_none', 'kill', 'stability', 'wall_s')
        print(json.dumps({robot: {k: s[k] for k in keys}}, indent=1), flush=True)
    with open(os.path.join(a.out, 'closed_loop.json'), 'w') as f:
        json.dump(res, f, indent=2)
    for robot, s in res.items():
        print(f'\n{robot}: held-out tracking RMS [mrad] (from {a.learn:g} s of {a.duration:g} s)')
        print('| compensation | ' + ' | '.join(s['joints']) + ' | mean |')
        print('|---' * (len(s['joints']) + 2) + '|')
        for c in ('none', 'sigmoid', 'dgp', 'dgp_damping_only'):
            v = 1e3 * np.array(s['tracking_rms'][c])
            print(f'| {c} | ' + ' | '.join(f'{x:.1f}' for x in v) + f' | {v.mean():.2f} |')


if __name__ == '__main__':
    main()

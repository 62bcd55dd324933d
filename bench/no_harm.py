#!/usr/bin/env python3
"""
Do no harm: the closed-loop learning transient and a restart without the model.

Per robot (Panda, UR5), exactly the runs of ``dgp-demo --robot R --closed-loop`` with its
defaults (``dgp_ros.apps.loop_demo``: 12 s, the sigmoid fitted on the first 8 s, the estimator
with the node's defaults except ``refit_mode=sync``, the controller scaling ``k`` by the
published confidence; in process, lock-step, deterministic), plus ``dgp_restart``: the estimator
killed at mid-run and restarted without its model. Scored against the ``none`` run of the same
path and noise: the mean-over-joints tracking RMS of every 1 s window from t = 0 (at most 1.05x
none's), each joint's largest |error| over the first 2 s (at most 1.05x), every window after the
restart (at most 1.05x), and held out (8-12 s) dgp / none and dgp / sigmoid (at most 0.5x and
0.8x). The confidence the controller applied, per 1 s window, beside them.

Writes the section ``no_harm`` of docs/BENCHMARKS.md and ``<out>/bench/no_harm_<robot>.json``.
Usage: bench/no_harm.py [--robots panda,ur5] [--quick]
"""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

import common as C  # noqa: E402

NAME = 'no_harm'
DURATION_S, LEARN_S = 12.0, 8.0          # the demo's defaults
LIMIT = 1.05


def _extra(p) -> None:
    p.add_argument('--robots', default='panda,ur5')


def run(robot: str, duration: float, learn: float) -> dict:
    """Run the demo's sweep with a restart at mid-run; return its ``loop_demo.summarize``."""
    from dgp_ros.apps.loop_demo import summarize, sweep
    from dgp_ros.dynamics import ARM_JOINTS
    t0 = time.perf_counter()
    runs = sweep(robot, duration, learn, 0, 2, restart_at=0.5 * duration)
    s = summarize(runs, learn, ARM_JOINTS[robot])
    s['wall_s'] = time.perf_counter() - t0
    return s


def _f(v, d=2) -> str:
    return ' / '.join(f'{x:.{d}f}' for x in v)


def report(a, res: dict, wall: float) -> str:
    lines = [C.header_lines('Do no harm: the closed-loop transient, a restart',
                            'bench/no_harm.py', a.quick, wall),
             'Each run is `dgp-demo --robot R --closed-loop` with its defaults '
             f'({DURATION_S:g} s, learn {LEARN_S:g} s; `--quick`: shorter), the controller '
             'scaling `k` by the '
             'published confidence; `dgp_restart`: the estimator killed at mid-run and started '
             'again without its model. Ratios are over the `none` run of the same path and '
             f'noise; the limits are {LIMIT}x per 1 s window (mean over joints), {LIMIT}x for '
             "each joint's largest |error| over the first 2 s, 0.5x none and 0.8x sigmoid "
             'held out.', '']
    lines += ['| robot | compensation | worst 1 s window / none | each window | worst joint max '
              'first 2 s / none | after the restart, worst window | no harm |',
              '|---|---|---|---|---|---|---|']
    for robot, s in res.items():
        for c, d in s['transient'].items():
            lines.append(f'| {robot} | {c} | {d["worst_window_ratio"]:.3f} | '
                         f'{_f(d["window_ratios"])} | {d["worst_max_first_2s_ratio"]:.3f} | '
                         f'{d.get("worst_after_restart_ratio", float("nan")):.3f} | '
                         f'{"yes" if d["no_harm"] else "**no**"} |')
    lines += ['', '| robot | held out: dgp / none | dgp / sigmoid | mean RMS none / sigmoid / '
              'dgp [mrad] | non-passive answers (dgp) | wall |', '|---|---|---|---|---|---|']
    for robot, s in res.items():
        m = s['tracking_rms_mean']
        lines.append(f'| {robot} | {s["ratio_dgp_none"]:.3f} | {s["ratio_dgp_sigmoid"]:.3f} | '
                     f'{1e3 * m["none"]:.1f} / {1e3 * m["sigmoid"]:.1f} / {1e3 * m["dgp"]:.1f} | '
                     f'{s["nonpassive_answers"]["dgp"]} | {s["wall_s"]:.0f} s |')
    lines += ['', 'Confidence applied by the controller, mean over joints per 1 s window:', '',
              '| robot | run | windows |', '|---|---|---|']
    for robot, s in res.items():
        for c, w in s['confidence_windows'].items():
            if c.startswith('dgp'):
                lines.append(f'| {robot} | {c} | {_f(np.mean(w, axis=1))} |')
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    a = C.parse_args(__doc__.strip().splitlines()[0], argv, _extra)
    t0 = time.perf_counter()
    dur, learn = (6.0, 4.0) if a.quick else (DURATION_S, LEARN_S)
    res = {}
    for robot in a.robots.split(','):
        res[robot] = run(robot, dur, learn)
        C.log(f'{NAME}: {robot} {res[robot]["wall_s"]:.0f} s')
        with open(os.path.join(C.plot_dir(a.out), f'no_harm_{robot}.json'), 'w') as f:
            keys = ('transient', 'tracking_rms_windows', 'tracking_max_first_2s',
                    'confidence_windows', 'ratio_dgp_none', 'ratio_dgp_sigmoid')
            json.dump({k: res[robot][k] for k in keys}, f, indent=1)
    C.write_section(a.out, NAME, report(a, res, time.perf_counter() - t0))
    return 0


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""
A busy computer: the demos beside processes that take the CPU, against the same demos quiet.

A robot's or an aircraft's computer is never idle. This script starts the load itself
(``--load`` busy processes, one shell-like spin loop each, at the default priority) and runs,
with the node's defaults over real DDS (``dgp-demo``, the user's command):

* the A320 approach at real time, ``--runs`` times beside the load and ``--runs`` times quiet;
* the same at ``--fast`` times real time (``sim_bridge``'s ``real_time_factor``: a fast stream
  is a busy computer too), beside the load;
* the robot demo (``--robot panda``: the simulated Panda at 1 kHz, its saved model held out
  against the true friction) beside the load and quiet, once each.

For each run: the NMSE per output one step ahead over the flight and its second half, the held
out NMSE of the model saved after 30 s (the robot demo: held out per joint, beside the
least-squares fits), the refits, and every distinct /diagnostics message the demo printed
(the status under load must say so, with the reason). ``--quick``: one A320 run each way at
half the flight. Writes section ``busy`` of docs/BENCHMARKS.md (``--out``).

Usage: bench/busy.py [--quick] [--runs K] [--load P] [--fast F] [--fast-runs K] [--out DIR]
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

import common as C  # noqa: E402

NAME = 'busy'
OUTPUTS = ('alpha', 'beta', 'airspeed')


class Load:
    """``n`` busy processes (a spin loop each) while the ``with`` block runs."""

    def __init__(self, n: int):
        self.n, self.procs = int(n), []

    def __enter__(self):
        code = 'while True:\n    pass\n'
        self.procs = [subprocess.Popen([sys.executable, '-c', code]) for _ in range(self.n)]
        time.sleep(0.5)
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()


def demo(args: list, out: str) -> dict:
    """Run ``dgp-demo`` with ``args`` into ``out``; its summary.json and the status lines."""
    cmd = [sys.executable, '-m', 'dgp_ros.apps.demo', '--out', out] + args
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=C.REPO,
                       env=dict(os.environ, OPENBLAS_NUM_THREADS='1'))
    wall = time.perf_counter() - t0
    path = os.path.join(out, 'summary.json')
    res = json.load(open(path)) if os.path.exists(path) else {}
    # every distinct status the progress lines carried (after the counters)
    said = []
    for line in r.stdout.splitlines():
        m = re.search(r'\| refits \S+ \| (.*)$', line)
        if m:
            for part in m.group(1).split('; '):
                key = re.sub(r'[0-9.]+', '#', part)[:70]
                if key not in {re.sub(r'[0-9.]+', '#', s)[:70] for s in said}:
                    said.append(part)
    return {'rc': r.returncode, 'wall_s': wall, 'summary': res, 'said': said,
            'tail': r.stdout.splitlines()[-25:]}


def _per_output(s: dict, key: str) -> str:
    """Format ``s[key]`` per output (alpha / beta / airspeed), '-' where absent."""
    d = s.get(key) or {}
    return ' / '.join(C.fmt(d[o]) for o in OUTPUTS) if d else '-'


def a320_row(label: str, r: dict) -> list:
    s = r['summary']
    if not s:
        return [label, f'failed (rc {r["rc"]})'] + ['-'] * 6
    d = s.get('diagnostics') or {}
    level = d.get('level')
    last = ['OK', 'WARN', 'ERROR', 'STALE'][min(int(level), 3)] if level is not None else '-'
    return [label, _per_output(s, 'nmse'), _per_output(s, 'nmse_from_1s'),
            _per_output(s, 'worst_window'), _per_output(s.get('held_out') or {}, 'nmse'),
            f'{d.get("refits_ok", "-")}', last, f'{r["wall_s"]:.0f} s']


def _ratios(results, quiet: list) -> list:
    """Each run's worst output over the quiet median: over the flight, from 1 s, held out."""
    keys = ('nmse', 'nmse_from_1s', 'held_out')

    def get(s, k):
        d = (s.get('held_out') or {}).get('nmse') if k == 'held_out' else s.get(k)
        return np.array([d[o] for o in OUTPUTS]) if d else None
    med = {k: np.median([get(s, k) for s in quiet if get(s, k) is not None], axis=0)
           for k in keys if any(get(s, k) is not None for s in quiet)}
    rows = []
    for kind, label, r in results:
        if kind != 'a320' or not r['summary']:
            continue
        rows.append([label] + [f'{np.max(get(r["summary"], k) / np.maximum(med[k], 1e-300)):.2f}x'
                               if k in med and get(r['summary'], k) is not None else '-'
                               for k in keys])
    return [' / '.join(C.fmt(x) for x in med[k]) if k in med else '-' for k in keys], rows


def _find(d, key):
    """Return the first value under ``key`` anywhere in nested dicts ``d`` (None if absent)."""
    if isinstance(d, dict):
        if key in d:
            return d[key]
        for v in d.values():
            x = _find(v, key)
            if x is not None:
                return x
    return None


def robot_row(label: str, r: dict) -> list:
    """Return the robot demo's saved model held out per joint, beside the least-squares fits."""
    s = r['summary']
    nm, sg, cv = (_find(s, k) for k in ('nmse', 'nmse_sigmoid', 'nmse_coulomb_viscous'))
    if not nm or not sg or not cv:
        return [label, f'no held-out score (rc {r["rc"]})', '-', '-', f'{r["wall_s"]:.0f} s']
    joints = list(nm)
    model = np.array([nm[j] for j in joints])
    ls = np.minimum([sg[j] for j in joints], [cv[j] for j in joints])
    return [label, ' / '.join(C.fmt(x) for x in model), ' / '.join(C.fmt(x) for x in ls),
            f'{np.max(model / ls):.2f}', f'{r["wall_s"]:.0f} s']


def main(argv=None) -> int:
    def extra(p):
        p.add_argument('--runs', type=int, default=3, help='A320 runs each way')
        p.add_argument('--load', type=int, default=2, help='busy processes')
        p.add_argument('--fast', type=float, default=4.0, help='real-time factor of the fast '
                       'runs (0: none)')
        p.add_argument('--fast-runs', type=int, default=None,
                       help='runs at --fast times real time (default: --runs)')
        p.add_argument('--no-robot', action='store_true', help='skip the robot demo')
    a = C.parse_args(__doc__.strip().split('\n')[0], argv, extra)
    runs = 1 if a.quick else a.runs
    flight = ['--max-sim-time', '35', '--held-out-after', '20'] if a.quick else []
    t0 = time.perf_counter()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        def run(kind, label, args, loaded):
            C.log(f'{NAME}: {label}')
            with Load(a.load if loaded else 0):
                results.append((kind, label, demo(args, os.path.join(tmp, str(len(results))))))
        for k in range(runs):
            for loaded in (True, False):
                run('a320', f'A320 {"beside the load" if loaded else "quiet"} {k + 1}', flight,
                    loaded)
        if a.fast and not a.quick:
            for k in range(runs if a.fast_runs is None else a.fast_runs):
                run('a320', f'A320 at {a.fast:g}x real time beside the load {k + 1}',
                    ['--real-time-factor', str(a.fast)], True)
        if not a.no_robot and not a.quick:
            for loaded in (True, False):
                run('robot', f'robot demo (Panda) {"beside the load" if loaded else "quiet"}',
                    ['--robot', 'panda'], loaded)
    wall = time.perf_counter() - t0
    quiet = [r['summary'] for kind, label, r in results
             if kind == 'a320' and 'quiet' in label and r['summary']]
    lines = [C.header_lines('A busy computer: the demos beside busy processes', f'bench/{NAME}.py',
                            a.quick, wall), '',
             f"The user's commands (`dgp-demo`, the node's defaults over real DDS), quiet and "
             f'beside {a.load} busy processes (spin loops at the default priority, started by '
             'this script) on this machine. A320: NMSE per output (drag / side force / lift) one '
             'step ahead over the flight, from 1 s on (the first answer knows nothing) and its '
             "worst 1 s window (over the flight's variance); held out: the model saved after 30 "
             's, on the rest of the flight; the last status word of the demo.', '',
             C.md_table(['run', 'flight', 'from 1 s', 'worst 1 s', 'held out', 'refits ok',
                         'last status', 'wall'],
                        [a320_row(label, r) for kind, label, r in results if kind == 'a320']),
             '']
    if quiet:
        med, rows = _ratios(results, quiet)
        lines += [f'Quiet medians: over the flight {med[0]}; from 1 s {med[1]}; held out '
                  f'{med[2]}. Each run, its worst output over the quiet median:', '',
                  C.md_table(['run', 'over the flight', 'from 1 s', 'held out'], rows), '']
    robots = [(label, r) for kind, label, r in results if kind == 'robot']
    if robots:
        lines += ['Robot demo (the simulated Panda at 1 kHz, its saved model held out against the '
                  'true friction per joint, beside the better of the Coulomb-viscous and sigmoid '
                  'least-squares fits on the same samples):', '',
                  C.md_table(['run', 'model per joint', 'least squares per joint',
                              'worst joint over least squares', 'wall'],
                             [robot_row(label, r) for label, r in robots]), '']
    lines += ['What the status said during each run (each distinct message once):', '']
    for kind, label, r in results:
        lines.append(f'- {label}: ' + ('; '.join(f'`{x}`' for x in r['said']) or '-'))
    C.write_section(a.out, NAME, '\n'.join(lines) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())

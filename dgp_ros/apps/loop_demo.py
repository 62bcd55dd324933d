"""
Closed-loop demo: ``dgp-demo --robot panda --closed-loop`` (or ``ur5``): does it track better.

The simulated arm (``dynamics.closed_loop``: the URDF with a payload it lacks, realistic friction
outside the estimator's prior family, torque-sensor bias and noise) tracks the same reference path
from the same seed under the example controller (PD + the URDF's feed-forward) with each
compensation: ``none``, ``sigmoid`` (a Makkar sigmoid per joint fitted by least squares on the
learning part), ``dgp`` (the live estimator's damping force and rigid-body correction) and
``dgp_damping_only``. The estimator learns while the loop runs (it sees the effect of its own
compensation); the first ``--learn`` seconds are the learning part, the rest is scored.

Two modes, both lock-step through simulated time (docs/CHANGELOG.md, "Closed loop"):

1. the four-way sweep in worker processes, each run in one process (``apps.loop_run``: the
   estimator with the node's defaults except ``refit_mode='sync'``): reproducible;
2. the ``dgp`` run over real DDS for the first ``--dds-duration`` seconds (``apps.loop_dds``: the
   ``dgp-arm-loop``, ``estimator`` and ``dgp-controller`` processes on an isolated domain), to
   show the nodes do what the sweep does (reported next to the sweep's dgp over the same window).

Writes ``summary.json`` (``tracking_rms`` / ``tracking_max`` per compensation per joint [rad] over
the held-out part, their means and ratios; ``tracking_rms_windows`` per compensation, a list over
consecutive 1 s windows from t = 0 of per-joint RMS [rad], and ``tracking_max_first_2s`` per
joint, with the no-harm checks of the learning transient in ``transient``; the energy each
compensation injected [J], answers and non-passive answers, stale steps, wall time) and
``tracking_error.png`` (the tracking error and, beside it, the confidence the controller applied)
to ``--out``. The run ``dgp_restart`` kills the estimator at ``--restart-at`` and restarts it
without its model.
"""
from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
import json
import multiprocessing
import os
import sys
import time

import numpy as np

from dgp_ros.apps.loop_run import COMPENSATIONS, RESTART_GAP_S, run_loop, score, windows

#: longest first: two workers finish together; ``dgp_restart`` is ``dgp`` with the estimator
#: killed at ``--restart-at`` and restarted without its model
ORDER = ('dgp', 'dgp_restart', 'dgp_damping_only', 'sigmoid', 'none')
#: a compensation's 1 s window or first-2 s peak counts as doing no harm up to this x none's
NO_HARM = 1.05


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog='dgp-demo',
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--robot', required=True, choices=('panda', 'ur5'),
                    help='simulated arm (example-robot-data URDF)')
    ap.add_argument('--closed-loop', action='store_true', help='this demo (always on here)')
    ap.add_argument('--out', default=None, help='output folder (default out/loop_<robot>)')
    ap.add_argument('--duration', type=float, default=12.0, help='simulated run [s]')
    ap.add_argument('--learn', type=float, default=8.0,
                    help='learning part [s]; the rest is scored')
    ap.add_argument('--seed', type=int, default=0, help='reference path and sensor noise')
    ap.add_argument('--dds-duration', type=float, default=2.0,
                    help='simulated seconds of the dgp run over DDS (0: skip)')
    ap.add_argument('--workers', type=int, default=2, help='processes of the sweep')
    ap.add_argument('--restart-at', type=float, default=None,
                    help='dgp_restart: the estimator killed and restarted without its model at '
                         'this time [s] (default: the middle of the run; negative: no such run)')
    a = ap.parse_args(argv)
    if a.out is None:
        a.out = os.path.join('out', f'loop_{a.robot}')
    if not 0.0 < a.learn < a.duration:
        ap.error('--learn must be in (0, --duration)')
    if a.restart_at is None:
        a.restart_at = 0.5 * a.duration
    return a


def _one(args) -> dict:
    robot, comp, duration, learn, seed, restart = args
    if comp == 'dgp_restart':
        r = run_loop(robot, 'dgp', duration, learn, seed=seed, restart_at_s=restart)
        r['compensation'], r['restart_at_s'] = comp, restart
    else:
        r = run_loop(robot, comp, duration, learn, seed=seed)
    return {k: r[k] for k in ('compensation', 't', 'error', 'comp', 'confidence', 'injected_j',
                              'answers', 'nonpassive_answers', 'stale', 'clipped', 'wall_s',
                              'restart_at_s') if k in r}


def sweep(robot: str, duration: float, learn: float, seed: int, workers: int,
          restart_at: float = -1.0) -> dict:
    """Run every compensation (:data:`ORDER`) in ``workers`` processes; {name: run}."""
    jobs = [(robot, c, duration, learn, seed, restart_at) for c in ORDER
            if c != 'dgp_restart' or 0.0 < restart_at < duration]
    if workers <= 1:
        return {j[1]: _one(j) for j in jobs}
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context('spawn')) as ex:
        return {j[1]: r for j, r in zip(jobs, ex.map(_one, jobs))}


def summarize(runs: dict, learn: float, names) -> dict:
    """Return the held-out numbers of ``runs`` ({compensation: run}) as summary.json has."""
    rms = {c: score(r, learn)[0] for c, r in runs.items()}
    mx = {c: score(r, learn)[1] for c, r in runs.items()}
    mean = {c: float(np.mean(v)) for c, v in rms.items()}
    out = {'joints': list(names), 'held_out_from_s': learn,
           'tracking_rms': {c: v.tolist() for c, v in rms.items()},
           'tracking_max': {c: v.tolist() for c, v in mx.items()},
           'tracking_rms_mean': mean,
           # while learning (the estimator's first models), and its first 2 s alone
           'tracking_rms_learning': {c: score(r, 0.0, learn)[0].tolist() for c, r in runs.items()},
           'tracking_rms_first_2s': {c: score(r, 0.0, 2.0)[0].tolist() for c, r in runs.items()},
           'injected_energy_j': {c: float(r['injected_j']) for c, r in runs.items()},
           'answers': {c: int(r['answers']) for c, r in runs.items()},
           'nonpassive_answers': {c: int(r['nonpassive_answers']) for c, r in runs.items()},
           'stale_steps': {c: int(r['stale']) for c, r in runs.items()},
           'clipped_commands': {c: int(r['clipped']) for c, r in runs.items()},
           'run_wall_s': {c: float(r['wall_s']) for c, r in runs.items()}}
    if 'none' in mean and 'dgp' in mean:
        out['ratio_dgp_none'] = mean['dgp'] / mean['none']
        out['worst_joint_ratio_dgp_none'] = float(np.max(rms['dgp'] / rms['none']))
    if 'sigmoid' in mean and 'dgp' in mean:
        out['ratio_dgp_sigmoid'] = mean['dgp'] / mean['sigmoid']
    out['tracking_rms_windows'] = {c: windows(r).tolist() for c, r in runs.items()}
    out['tracking_max_first_2s'] = {c: score(r, 0.0, 2.0)[1].tolist() for c, r in runs.items()}
    out['confidence_windows'] = {c: _mean_windows(r['t'], r['confidence']).tolist()
                                 for c, r in runs.items() if 'confidence' in r}
    if 'none' in runs:
        out['transient'] = transient(runs)
    return out


def _mean_windows(t, x, width_s: float = 1.0) -> np.ndarray:
    """Mean of x (k, N) per joint over consecutive windows of t (k,) from 0: (w, N)."""
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0        # as loop_run.windows counts them
    k = int(np.floor((t[-1] + dt) / width_s + 1e-9))
    return np.array([x[(t >= i * width_s) & (t < (i + 1) * width_s)].mean(axis=0)
                     for i in range(k)])


def transient(runs: dict) -> dict:
    """
    Check the learning transient against the ``none`` run (no harm).

    Per compensation that uses the estimator: the mean-over-joints RMS of every 1 s window from
    t = 0 over none's (``window_ratios``, each at most ``NO_HARM``); the largest |error| of
    every joint over the first 2 s over none's (``max_first_2s_ratios``); for ``dgp_restart``,
    the windows that start after the restart (``after_restart_ratios``).
    """
    none = runs['none']
    wn = windows(none).mean(axis=1)
    mn = score(none, 0.0, 2.0)[1]
    out = {}
    for c, r in runs.items():
        if not c.startswith('dgp'):
            continue
        wr = windows(r).mean(axis=1) / np.maximum(wn, 1e-12)
        d = {'window_ratios': wr.tolist(), 'worst_window_ratio': float(wr.max()),
             'max_first_2s_ratios': (score(r, 0.0, 2.0)[1] / np.maximum(mn, 1e-12)).tolist()}
        d['worst_max_first_2s_ratio'] = float(max(d['max_first_2s_ratios']))
        if r.get('restart_at_s') is not None:
            first = int(np.floor(r['restart_at_s']))
            d['restart_at_s'] = r['restart_at_s']
            d['after_restart_ratios'] = wr[first:].tolist()
            d['worst_after_restart_ratio'] = float(wr[first:].max())
        d['no_harm'] = bool(d['worst_window_ratio'] <= NO_HARM and
                            d['worst_max_first_2s_ratio'] <= NO_HARM and
                            d.get('worst_after_restart_ratio', 0.0) <= NO_HARM)
        out[c] = d
    return out


def plot(runs: dict, names, learn: float, path: str) -> str:
    """Tracking error per joint (left) and the confidence the controller applied (right)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n = len(names)
    fig, axes = plt.subplots(n, 2, figsize=(14, 1.6 * n), sharex=True,
                             gridspec_kw={'width_ratios': [3, 1]})
    for j in range(n):
        ax, axc = axes[j]
        for c in COMPENSATIONS + ('dgp_restart',):
            if c in runs:
                r = runs[c]
                ax.plot(r['t'][::10], r['error'][::10, j], lw=0.7, label=c)
                if c.startswith('dgp') and 'confidence' in r:
                    axc.plot(r['t'][::10], r['confidence'][::10, j], lw=0.8, label=c)
        for a_ in (ax, axc):
            a_.axvline(learn, color='k', lw=0.8, ls='--')
        axc.set_ylim(-0.05, 1.05)
        ax.set_ylabel(f'{names[j]}\n[rad]', fontsize=7)
    axes[0, 0].legend(ncol=5, fontsize=7, loc='upper right')
    axes[0, 1].legend(fontsize=6, loc='lower right')
    axes[0, 0].set_title('tracking error q_ref - q per joint (dashed: end of the learning part)')
    axes[0, 1].set_title('confidence applied (k x c)', fontsize=9)
    for a_ in axes[-1]:
        a_.set_xlabel('simulated time [s]')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    a = parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    t0 = time.monotonic()
    from dgp_ros.dynamics import ARM_JOINTS
    names = ARM_JOINTS[a.robot]
    print(f'[loop] {a.robot}: {", ".join(ORDER)} on the same path (seed {a.seed}), '
          f'{a.duration:g} s each, learning {a.learn:g} s, scored after; {a.workers} workers',
          flush=True)
    runs = sweep(a.robot, a.duration, a.learn, a.seed, a.workers, a.restart_at)
    summary = summarize(runs, a.learn, names)
    for c in ORDER:
        if c not in runs:
            continue
        print(f'[loop] {c:17s} held-out tracking RMS [mrad] '
              f'{np.round(1e3 * np.array(summary["tracking_rms"][c]), 1).tolist()} mean '
              f'{1e3 * summary["tracking_rms_mean"][c]:.2f}; injected '
              f'{summary["injected_energy_j"][c]:.1f} J; run {runs[c]["wall_s"]:.0f} s',
              flush=True)
    print(f'[loop] dgp / none {summary["ratio_dgp_none"]:.3f} (worst joint '
          f'{summary["worst_joint_ratio_dgp_none"]:.3f}), dgp / sigmoid '
          f'{summary["ratio_dgp_sigmoid"]:.3f}', flush=True)
    for c, d in summary['transient'].items():
        extra = (f'; after the restart at {d["restart_at_s"]:g} s (+{RESTART_GAP_S:g} s without '
                 f'answers) worst window {d["worst_after_restart_ratio"]:.3f}'
                 if 'restart_at_s' in d else '')
        print(f'[loop] transient {c}: 1 s windows / none {np.round(d["window_ratios"], 2)} '
              f'(worst {d["worst_window_ratio"]:.3f}), first 2 s peak / none per joint '
              f'{np.round(d["max_first_2s_ratios"], 2)}{extra}: '
              f'{"no harm" if d["no_harm"] else "HARM"} (limit {NO_HARM:g})', flush=True)
    if a.dds_duration > 0:
        summary['dds'] = _dds(a, runs['dgp'])
    files = [plot(runs, names, a.learn, os.path.join(a.out, 'tracking_error.png'))]
    summary['wall_time_s'] = time.monotonic() - t0
    summary['args'] = vars(a)
    path = os.path.join(a.out, 'summary.json')
    with open(path, 'w') as f:
        json.dump(summary, f, indent=2)
    print(f'[loop] wrote {", ".join(files + [path])} in {summary["wall_time_s"]:.0f} s',
          flush=True)
    return 0


def _dds(a, sweep_dgp: dict) -> dict:
    """Run dgp over DDS for ``--dds-duration`` s, against the sweep's dgp over that window."""
    from dgp_ros.apps.children import isolated_env
    from dgp_ros.apps.loop_dds import run_dds
    env = isolated_env()
    print(f'[loop] dgp over DDS (dgp-arm-loop, estimator, dgp-controller; ROS_DOMAIN_ID='
          f'{env["ROS_DOMAIN_ID"]}) for {a.dds_duration:g} s of simulated time ...', flush=True)
    r = run_dds(a.robot, 'dgp', a.dds_duration, os.path.join(a.out, 'dds'), env, seed=a.seed)
    half = 0.5 * a.dds_duration
    rms_dds = np.sqrt(np.mean(r['error'][r['t'] >= half] ** 2, axis=0))
    rms_in = score(sweep_dgp, half, a.dds_duration)[0]
    c = r['controller']
    print(f'[loop] over DDS: {len(r["t"])} steps in {r["wall_s"]:.0f} s; tracking RMS from '
          f'{half:g} s [mrad] {np.round(1e3 * rms_dds, 1).tolist()} (in process '
          f'{np.round(1e3 * rms_in, 1).tolist()}); controller: {c["answers"]} answers, '
          f'{c["nonpassive_answers"]} non-passive, {c["stale"]} stale, {c["waited_out"]} '
          f'waits timed out; exit {r["exit"]}', flush=True)
    return {'steps': int(len(r['t'])), 'wall_s': r['wall_s'], 'window_s': [half, a.dds_duration],
            'tracking_rms_dds': rms_dds.tolist(), 'tracking_rms_in_process': rms_in.tolist(),
            'controller': c, 'exit': r['exit']}


if __name__ == '__main__':
    sys.exit(main())

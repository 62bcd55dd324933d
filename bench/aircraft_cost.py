#!/usr/bin/env python3
"""
What the aircraft's part learned from every sample costs: the message path, the learner, a replay.

The default approach (``sim_bridge``'s ``simulate_approach(SimConfig())``, 60 Hz) streamed through
the node's defaults in line, and measured in the same run:

* ``stream part``: the message path's share per accepted message (``online.stream_part``: its
  answer, the weighing and its recursive least squares; a twin of the estimator's, fed the
  same messages), one message at a time as the node at 60 Hz takes them, against the gate's
  answer from the snapshot alone (``answer.answer``) and a bare Cholesky of the window's
  200 x 200 kernel matrix (the unit of a refit);
* ``follow``: the learner's refit of the couplings on the long history and the served model's
  ``remean`` (``Structure.follow``, ``Posterior.remean``), per call;
* ``dgp-replay``: the flight written as a bag and replayed by ``dgp-replay`` with the defaults
  (the user's command), its wall time over the flight's.

Usage: bench/aircraft_cost.py [--quick] [--out DIR]
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from scipy.linalg import cholesky

import common as C  # noqa: E402

NAME = 'aircraft_cost'


def _flight(quick: bool):
    from sim_bridge import SimConfig, simulate_approach
    fl = simulate_approach(SimConfig(max_time_s=25.0) if quick else SimConfig())
    return fl['t'], fl['q'], fl['tau'], list(fl['joint_names'])


def _timed_stream(t, Q, T, names) -> dict:
    """
    Stream in line (``process``, as the node); time per message (s) what the node adds.

    A second stream part, fed exactly what the estimator's gets, is timed apart (its answer,
    the weighing and its learning), and the gate's answer from the same snapshot.
    """
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    from dgp_ros.online.path.gate import answer
    from dgp_ros.online.path.stream_part import StreamPart
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    L = est.learner
    part = StreamPart(Q.shape[1])
    part_s, gate_s, follow_s = [], [], []
    follow = L.structure.follow

    def timed(now):                     # the learner's refit of the couplings and the remean
        t0 = time.perf_counter()
        if not follow(now):
            return False
        L.served.remean(L.structure.frozen_prior())
        follow_s.append(time.perf_counter() - t0)
        return False                    # remeaned here already
    L.structure.follow = timed
    for i in range(len(t)):
        q = Q[i:i + 1]
        snap = L.snapshot(False)
        t0 = time.perf_counter()
        pred = answer(snap, q, False, False, 'certified', est.health, L.note_error, None)
        t1 = time.perf_counter()
        out, mine = part.weigh_answers(pred, q)
        part.learn(t[i:i + 1], q, T[i:i + 1], *mine, out[0])
        t2 = time.perf_counter()
        if i > 60:
            gate_s.append(t1 - t0)
            part_s.append(t2 - t1)
        est.process(float(t[i]), names, Q[i], T[i])
    d = est.diagnostics()
    est.close()
    return {'part': np.array(part_s), 'gate': np.array(gate_s), 'follow': np.array(follow_s),
            'structure': d.get('structure')}


def _chol_s() -> float:
    rng = np.random.default_rng(0)
    X = rng.standard_normal((200, 3))
    K = np.exp(-0.5 * ((X[:, None, :] - X[None, :, :]) ** 2).sum(-1)) + 1e-6 * np.eye(200)
    return C.timeit(lambda: cholesky(K, lower=True), repeat=20)


def _replay(t, Q, T, names, runs: int = 3) -> tuple:
    """Write the flight as a bag, ``dgp-replay`` it with the defaults: (median wall s, codes)."""
    from dgp_ros.bags import write_joint_state_bag
    with tempfile.TemporaryDirectory() as tmp:
        bag = os.path.join(tmp, 'a320')
        write_joint_state_bag(bag, [(float(t[i]), names, np.zeros(0), Q[i], T[i])
                                    for i in range(len(t))], topic='/generalized_state')
        walls, codes = [], []
        for k in range(runs):
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, '-m', 'dgp_ros.apps.replay', bag, '--out',
                                os.path.join(tmp, f'out{k}')], capture_output=True, text=True,
                               env=dict(os.environ, OPENBLAS_NUM_THREADS='1'))
            walls.append(time.perf_counter() - t0)
            codes.append(r.returncode)
        return walls, codes


def main(argv=None) -> int:
    a = C.parse_args(__doc__.strip().split('\n')[0], argv)
    t0 = time.perf_counter()
    t, Q, T, names = _flight(a.quick)
    r = _timed_stream(t, Q, T, names)
    chol = _chol_s()
    walls, codes = _replay(t, Q, T, names, 1 if a.quick else 3)
    wall, rc = float(np.median(walls)), max(codes)
    flight = float(t[-1] - t[0])
    us = lambda x: f'{1e6 * x:.1f} us'  # noqa: E731
    rows = [['stream part (answer, weighing, learning), per message',
             us(np.median(r['part'])), us(np.percentile(r['part'], 99)),
             f'{np.median(r["part"]) / chol:.3f}'],
            ["the gate's answer from the snapshot, per message", us(np.median(r['gate'])),
             us(np.percentile(r['gate'], 99)), f'{np.median(r["gate"]) / chol:.3f}'],
            ["the learner's refit of the couplings and the model's remean, per call",
             us(np.median(r['follow'])) if len(r['follow']) else '-',
             us(np.percentile(r['follow'], 99)) if len(r['follow']) else '-',
             f'{np.median(r["follow"]) / chol:.3f}' if len(r['follow']) else '-'],
            ['bare Cholesky of a 200 x 200 kernel matrix', us(chol), '-', '1']]
    body = '\n'.join([
        C.header_lines("The aircraft's part learned from every sample: what it costs",
                       f'bench/{NAME}.py', a.quick, time.perf_counter() - t0), '',
        f"The default approach ({len(t)} messages, {flight:.1f} s) through the node's defaults "
        f'in line; structure at the end: `{r["structure"]}`.', '',
        C.md_table(['what', 'median', 'p99', 'over a bare Cholesky (median)'], rows), '',
        f'`dgp-replay` of the flight as a bag (the defaults, `--save-model` not asked), '
        f'{len(walls)} runs: ' + ', '.join(f'{w:.1f} s' for w in walls) +
        f' wall for {flight:.1f} s of flight, median **{wall / flight:.2f}x real time** '
        f'(exit codes {codes}; the interpreter start, the bag read, the final proof and the '
        'plots included).', ''])
    C.write_section(a.out, NAME, body)
    return 0 if rc == 0 else 1


if __name__ == '__main__':
    sys.exit(main())

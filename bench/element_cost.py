#!/usr/bin/env python3
"""
What the elements of D from every sample cost the learner: per sample, per re-selection, memory.

The long history (``dynamics.history.LongHistory``) of a 7-joint arm, fed a stream of learned
samples (100 Hz of stamp time, the node's ``min_sample_interval_s``), with and without the
per-joint elements (``history_elements``), for the three corrections a user meets: none (an
aircraft, a plugin without positions), the model-free potential (a Python plugin) and the URDF
regressor (the Panda's example-robot-data URDF: 70 columns). Reported in the same run:

* ``push``: learner time per sample (``push``, its share of the flushes in 64-row batches);
* ``select``: one re-selection (structure CV, fit, and with elements their CV, halves and fit);
* ``memory``: the bytes of every statistic the history holds (older, recent memories, blocks,
  current block, halves), after 60 s and after 600 s of stream: it must not grow with the run;
* the ratio of each to a bare Cholesky factorization of the window GP's kernel matrix (n = 200,
  ``scipy.linalg.cholesky``), timed in the same run: the cost unit of a refit.

Usage: bench/element_cost.py [--quick] [--out DIR]
"""
from __future__ import annotations

import sys
import time

import numpy as np
from scipy.linalg import cholesky

import common as C  # noqa: E402

NAME = 'element_cost'
HZ = 100.0
N = 7


def _basis(kind: str):
    if kind == 'none':
        return None
    from dgp_ros.dynamics import example_robot_urdf
    from dgp_ros.dynamics.conservative import PotentialBasis, RegressorBasis
    from dgp_ros.dynamics.inverse import UrdfInverseDynamics
    if kind == 'potential':
        return PotentialBasis(N)
    names = [f'panda_joint{j}' for j in range(1, 8)]
    with open(example_robot_urdf('panda'), encoding='utf-8') as f:
        urdf = f.read()
    return RegressorBasis(UrdfInverseDynamics(urdf=urdf, joints=names), 'bench', urdf)


def _stream(seconds: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / HZ)
    w = rng.uniform(0.2, 0.9, N)
    Q = np.sin(np.outer(t, w) + rng.uniform(0, 6, N))
    V = np.cos(np.outer(t, w)) * 1.2
    A = -np.sin(np.outer(t, w)) * w
    R = 0.5 * np.tanh(V / 0.02) + 0.3 * V + 0.05 * rng.standard_normal(V.shape)
    return t, Q, V, A, R


def _bytes(h) -> int:
    st = [h._older, h._cur, *h._recent, *h._blocks, *h.element.halves]
    return int(sum(s.Gt.nbytes + s.bt.nbytes + (0 if s.Gd is s.Gt else s.Gd.nbytes + s.bd.nbytes)
                   for s in st))


def measure(kind: str, elements: bool, seconds: float) -> dict:
    """Feed one history ``seconds`` of stream; time its pushes and a re-selection."""
    from dgp_ros.dynamics.history import LongHistory
    basis = _basis(kind)
    t, Q, V, A, R = _stream(seconds)
    h = LongHistory(N, basis, 'friction', offsets=basis is not None, elements=elements)
    mem, t_push = {}, 0.0
    for i in range(len(t)):
        t0 = time.perf_counter()
        h.push(t[i], Q[i], V[i], A[i], R[i])
        t_push += time.perf_counter() - t0
        if abs(t[i] - 60.0) < 0.5 / HZ:
            mem[60] = _bytes(h)
    mem[int(seconds)] = _bytes(h)
    sel = C.timeit(h.select, repeat=3)
    fit = h.select()
    return {'kind': kind, 'elements': elements, 'push_us': 1e6 * t_push / len(t),
            'select_ms': 1e3 * sel, 'memory': mem, 'on': fit.element.label() if fit.element
            else '', 'samples': len(t)}


def answer_cost() -> dict:
    """
    Time one message's answer (the message path's lean pass, ``online.plan.AnswerPlan``).

    A Diag-D-GP of 7 joints at the node's buffer (200 samples), its prior the frozen friction
    alone, and the same with elements from every sample on all 7 joints, each with symmetric and
    with asymmetric friction (a level per direction on every joint), and with a coupled
    transmission on the last two joints beside the elements: us per answer (the least of 15
    rounds of 200, the priors interleaved).
    """
    from dgp_ros.gp import DiagDGP
    from dgp_ros.gp.joint_element import JointElementMean, M_BASIS, VelocityBasis
    from dgp_ros.gp.means import BasisFrictionMean
    from dgp_ros.gp.transmission import TransmissionMean
    from dgp_ros.dynamics.parametric import EPS_S, F, FRICTION_EPS, STRIBECK_VS
    from dgp_ros.online.learner.plan import AnswerPlan
    rng = np.random.default_rng(1)
    Qd = rng.normal(0.0, 0.8, (200, N))
    Tau = 0.4 * np.tanh(Qd / 0.02) + 0.3 * Qd + 0.02 * rng.normal(size=Qd.shape)
    base = BasisFrictionMean(np.abs(rng.normal(0.0, 0.2, (N, F))), FRICTION_EPS, EPS_S,
                             STRIBECK_VS)
    W = rng.normal(0.0, 0.1, (N, M_BASIS)) / np.arange(1, M_BASIS + 1)
    asym = BasisFrictionMean(base.coef, FRICTION_EPS, EPS_S, STRIBECK_VS,
                             coef_neg=np.abs(rng.normal(0.0, 0.2, (N, F))))
    plans = {}
    for label, prior in (('parametric prior', base),
                         ('with elements on 7 joints',
                          JointElementMean(base, VelocityBasis(np.full(N, 2.0)), W)),
                         ('asymmetric parametric prior (7 joints)', asym),
                         ('asymmetric, with elements on 7 joints',
                          JointElementMean(asym, VelocityBasis(np.full(N, 2.0)), W)),
                         ('with elements on 7 joints and a wrist motor (joints 6 + 7)',
                          TransmissionMean(JointElementMean(base, VelocityBasis(np.full(N, 2.0)),
                                                            W), [(5, 6, 1)], [[0.3, 0.1]]))):
        plans[label] = AnswerPlan(DiagDGP(prior=prior, n_restarts=0).fit(Qd, Tau))
    # the labels interleaved, round after round, the least time of each: the same moments of a
    # shared machine for every prior (a burst of the others' jobs hits one round, not one label)
    q = Qd[:1] * 1.1
    best = {k: np.inf for k in plans}
    for _ in range(15):
        for label, plan in plans.items():
            t0 = time.perf_counter()
            for _ in range(200):
                plan.answers(q, False)
            best[label] = min(best[label], (time.perf_counter() - t0) / 200)
    return {k: 1e6 * v for k, v in best.items()}


def main(argv=None) -> int:
    a = C.parse_args(__doc__.strip().split('\n')[0], argv)
    seconds = 70.0 if a.quick else 600.0
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, N))
    K = np.exp(-0.5 * ((X[:, None] - X[None]) ** 2).sum(-1)) + 1e-3 * np.eye(200)
    chol = C.timeit(lambda: cholesky(K, lower=True), repeat=20)
    rows = []
    for kind in ('none', 'potential', 'regressor'):
        for el in (False, True):
            r = measure(kind, el, seconds)
            C.log(f'{NAME}: {kind}, elements {el}: push {r["push_us"]:.1f} us, select '
                  f'{r["select_ms"]:.1f} ms, memory {r["memory"]}')
            rows.append(r)
    ans = answer_cost()
    C.log(f'{NAME}: answers {ans}')
    table = []
    for r in rows:
        base = next(b for b in rows if b['kind'] == r['kind'] and not b['elements'])
        m = r['memory']
        table.append([r['kind'], 'on' if r['elements'] else 'off', f'{r["push_us"]:.1f}',
                      f'{r["push_us"] / base["push_us"]:.2f}',
                      f'{r["push_us"] * 1e-6 / chol:.3f}', f'{r["select_ms"]:.1f}',
                      f'{r["select_ms"] * 1e-3 / chol:.0f}',
                      ' / '.join(f'{m[k] / 2 ** 20:.2f}' for k in sorted(m)),
                      r['on'] or '-'])
    body = (C.header_lines('What the elements of D from every sample cost the learner',
                           f'bench/{NAME}.py', a.quick, time.perf_counter() - t0)
            + f"\n7 joints, {seconds:.0f} s of learned samples at {HZ:.0f} Hz (the node's "
            '`min_sample_interval_s`) into the long history, with and without the elements '
            '(`history_elements`), for each correction basis. Per sample: `push` (its share of '
            'the 64-row flushes included); per re-selection: `select` (structure CV and fit, '
            'and with elements their CV, halves and fit); memory of every statistic held '
            f'after 60 s / after {seconds:.0f} s (MiB): constant. The unit: one bare Cholesky '
            f'of the window GP (n = 200) in the same run, {1e6 * chol:.0f} us.\n\n'
            + C.md_table(['correction', 'elements', 'push us/sample', 'over no elements',
                          'push in Choleskys', 'select ms', 'select in Choleskys',
                          'memory MiB (60 s / end)', 'elements on (synthetic stream)'],
                         table) + "\n\nOne message answered (the message path's lean pass, "
            '`online.plan.AnswerPlan`, a Diag-D-GP of 7 joints at buffer 200): '
            + '; '.join(f'{k} {v:.1f} us' for k, v in ans.items()) + '.\n')
    C.write_section(a.out, NAME, body)
    return 0


if __name__ == '__main__':
    sys.exit(main())

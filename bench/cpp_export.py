#!/usr/bin/env python3
"""
The frozen model as generated C++: equality with Python and the node, time per call.

For each model: learn it with the node's defaults in line (``refit_mode='sync'``), save it, export
it (``dgp_ros.export``: proven at export as the frozen node proves a file), compile the header
with ``g++ -std=c++17 -Wall -Wextra -Werror -O2`` and compare on ``K`` random velocities inside
the training box and ``K`` 10-30x outside it (random poses in [-pi, pi]):

* against ``load_model(M)`` after that proof: ``predict``, ``damping_matrix``,
  ``predict_residual`` (largest error per answer over the answer's largest entry);
* against the frozen node's published answers (``OnlineEstimator(learning=False,
  model_path=M)``: ``tau_hat`` and ``D``), and negative power of every C++ damping answer.

Models: the A320 (sim_bridge's approach, the ledger's flight, the whole of it), the real Panda
(``../shared/data/panda_real``, t < 7.5 s, its identified model as ``python:panda_rb:tau_rb``:
a model of the buffer's 200 samples with the URDF regressor correction of
example-robot-data's panda; the node's defaults keep none of its 49 elements of D, so it is
also exported with ``elements=all``, the paper's Full-D, all 49), the real UR10
(``../shared/data/ur10_real``, t < 10 s, ``python:ur10_rb:tau_rb``: an element of D from every
sample on its wrist 3) and the robot demo's simulated Panda after 8 task cycles (80 s: elements
from every sample on several joints, ``gp.joint_element``) and with a wrist motor driving its
last two joints (24 s, ``coupled_wrist=0.6``: a coupled transmission, ``gp.transmission``,
served by the defaults); a real log that is absent
is replaced by the simulated Panda of the robot demo (said in the table). Time per
``friction()`` call: the example program (``examples/cpp/friction_along_log.cpp``) on 2000
samples of the model's own velocities, at ``-O2`` and ``-O2 -march=native`` with g++ (and
clang++ where installed), beside one Python ``predict_residual`` call on one sample (median of
300) in the same run.

Usage: bench/cpp_export.py [--quick] [--out DIR]
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

import common as C  # noqa: E402
from robot_family import ARMS  # noqa: E402,I100,I201

NAME = 'cpp_export'
TITLE = 'The frozen model as generated C++'
EXAMPLE = os.path.join(C.REPO, 'examples', 'cpp', 'friction_along_log.cpp')
SHARED = [os.path.join(C.REPO, '..', 'shared', 'data'), '/work/shared/data']


def _shared(name):
    for base in SHARED:
        d = os.path.join(base, name)
        if os.path.isdir(d):
            return os.path.abspath(d)
    return None


def _stream(est, t, names, qd, tau, q=None, bag=False):
    for i in range(len(t)):
        s = float(t[i])
        if bag:
            sec, ns = divmod(int(round((1.7e9 + t[i]) * 1e9)), 1_000_000_000)
            s = sec + 1e-9 * ns
        est.process(s, names, qd[i], tau[i], None if q is None else q[i])


def _sim_panda(seconds: float, coupled: float = 0.0):
    """
    Learn ``seconds`` of the robot demo's Panda in line; (the estimator, the run).

    ``coupled`` : the Coulomb level [N m] of a motor driving its last two joints (0: none).
    """
    from dgp_ros.dynamics import example_robot_urdf
    from dgp_ros.dynamics.arm_stream import demo_arm
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    s = demo_arm('panda', seconds, seed=0, coupled_wrist=coupled)
    names = list(s['names'])
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync', inverse_dynamics='urdf',
                                          joints=names, urdf_file=example_robot_urdf('panda')))
    est.set_outputs(stddev=False, damping=False)
    _stream(est, s['t'], names, s['qd'], s['effort'], s['q'])
    return est, s


def learn(case: str, path: str, quick: bool) -> str:
    """Learn ``case`` with the node's defaults and save it to ``path``; returns a label."""
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    if case == 'a320':
        from sim_bridge import SimConfig, simulate_approach
        f = simulate_approach(SimConfig())
        k = int(np.searchsorted(f['t'], f['t'][0] + (10.0 if quick else 1e9)))
        est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
        _stream(est, f['t'][:k], list(f['joint_names']), f['q'][:k], f['tau'][:k])
        label = f'A320, {f["t"][k - 1] - f["t"][0]:.0f} s of the approach'
    elif case == 'simpanda':
        # 8 task cycles of the robot demo's Panda: the elements of D from every sample on
        est, s = _sim_panda(80.0)
        on = (est.diagnostics().get('joint_elements') or {}).get('on', [])
        label = f'simulated Panda, 8 task cycles (elements from every sample on joints {on})'
    elif case == 'motor':
        # a wrist whose motor drives the last two joints (bench/coupled_wrist.py): the
        # defaults serve the transmission
        est, s = _sim_panda(24.0, coupled=0.6)
        label = (f'simulated Panda with a wrist motor, 24 s '
                 f'({est.diagnostics().get("structure")})')
    else:
        extra = {'elements': 'all'} if case.endswith('_full') else {}
        case = case.split('_')[0]
        d = _shared(f'{case}_real')
        if d is None or quick:
            est, s = _sim_panda(2.0 if quick else 8.0)
            label = f'simulated Panda ({"no " + case + " log; " if d is None else ""}' \
                    f'{s["t"][-1]:.0f} s)'
        else:
            if d not in sys.path:
                sys.path.insert(0, d)
            z = np.load(os.path.join(d, f'{case}_log_train.npz'), allow_pickle=False)
            _, _, names, split = ARMS[f'{case}_real']
            tr = z['t'] < split
            est = OnlineEstimator(EstimatorConfig(
                refit_mode='sync', inverse_dynamics=f'python:{case}_rb:tau_rb', **extra))
            est.set_source('bag')
            est.set_outputs(stddev=False, damping=False)
            _stream(est, z['t'][tr], names, z['qd'][tr], z['tau_meas'][tr], z['q'][tr], True)
            label = f'real {case.upper() if case == "ur10" else "Panda"} log, t < {split} s' + \
                (', elements=all (Full-D)' if extra else '')
    est.save(path)
    est.close()
    return label


def rel(a, b) -> float:
    """Return the largest error per answer relative to that answer's largest entry."""
    a, b = np.asarray(a).reshape(len(a), -1), np.asarray(b).reshape(len(b), -1)
    return float((np.abs(a - b).max(axis=1) / np.maximum(np.abs(b).max(axis=1), 1e-300)).max())


def velocities(X, k, far, rng):
    """Return k velocities uniform in the box of X (n, N), or (``far``) 10-30x beyond it."""
    c, r = 0.5 * (X.max(0) + X.min(0)), 0.5 * (X.max(0) - X.min(0))
    if not far:
        return rng.uniform(c - r, c + r, (k, X.shape[1]))
    u = rng.normal(size=(k, X.shape[1]))
    u /= np.abs(u).max(axis=1, keepdims=True)
    return c + r * u * rng.uniform(10.0, 30.0, (k, 1))


def node_answers(spec, path, Qd):
    """Return the frozen node's published (tau_hat, D) at each velocity and its guarantee."""
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync', learning=False, model_path=path,
                                          model=spec.kind, passivity=spec.passivity,
                                          joints=spec.names))
    res = [est.process(float(i), spec.names, Qd[i], np.zeros(spec.N)) for i in range(len(Qd))]
    guarantee = est.diagnostics().get('guarantee')
    est.close()
    return np.array([e.tau_hat for e in res]), np.array([e.D for e in res]), guarantee


def timing(hdr, model, d, cxx, flags, rng):
    """Return us per friction() call of the example program (``hdr`` as friction_model.hpp)."""
    from dgp_ros.export.toolchain import compile_program
    X = model.X_train_
    Qd = X[rng.integers(0, len(X), 2000)] + 0.02 * rng.normal(size=(2000, X.shape[1])) * \
        X.std(axis=0)
    Q = rng.uniform(-1.0, 1.0, Qd.shape)
    log = os.path.join(d, 'log.csv')
    np.savetxt(log, np.hstack([Q, Qd]), delimiter=',', header='q, qd')
    exe = compile_program(open(EXAMPLE, encoding='utf-8').read(), os.path.join(d, 'ex'), cxx,
                          flags, defines=(f'DGP_MODEL_HEADER="{hdr}"',))
    out = subprocess.run([exe, log], capture_output=True, text=True, check=True).stdout
    return float(re.search(r'friction\(\): ([0-9.]+) us', out).group(1))


def python_call_us(model, rng) -> float:
    X = model.X_train_
    t = []
    for _ in range(300):
        qd = X[rng.integers(0, len(X))][None, :]
        q = rng.uniform(-1.0, 1.0, qd.shape)
        t0 = time.perf_counter()
        model.predict_residual(q=q, qd=qd)
        t.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(t))


def _power(Qd, tau):
    """
    ``qd . tau`` per answer (k,), summed joint after joint as the header sums it.

    A projected answer (a coupled prior's) lies on ``qd . tau = 0``: the sign of its computed
    power is the order of the sum (numpy's einsum gave -1e-17 relative on the A320 where the
    header's order gives 0; ``test/export/test_export_cpp.py`` sums so too).
    """
    p = Qd[:, 0] * tau[:, 0]
    for i in range(1, Qd.shape[1]):
        p = p + Qd[:, i] * tau[:, i]
    return p


def run_case(case, quick, d):
    from dgp_ros.export import header_spec, write_header
    from dgp_ros.export.toolchain import driver, evaluate, find_compiler
    path = os.path.join(d, f'{case}.npz')
    t0 = time.perf_counter()
    label = learn(case, path, quick)
    C.log(case, label, f'learned in {time.perf_counter() - t0:.0f} s')
    t0 = time.perf_counter()
    spec, model = header_spec(path)
    hdr = os.path.join(d, f'{case}.hpp')
    text = write_header(spec, hdr)
    r = {'label': label, 'N': spec.N, 'n': spec.n, 'E': len(spec.elements),
         'guarantee': f'{spec.guarantee} ({spec.method})', 'bytes': len(text.encode()),
         'export_s': time.perf_counter() - t0,
         'correction': 'none' if spec.correction is None else
         (spec.correction['basis'] or 'offsets')}
    gxx = find_compiler(('g++',))
    exe = driver(hdr, d, gxx)
    K = 500 if quick else 10_000
    rng = np.random.default_rng(0)
    for far in (False, True):
        Qd = velocities(model.X_train_, K, far, rng)
        Q = rng.uniform(-np.pi, np.pi, Qd.shape)
        out = evaluate(exe, Q, Qd, d)
        tau, D, g = node_answers(spec, path, Qd)
        side = 'out' if far else 'in'
        r[f'{side}_model'] = max(rel(out['model_damping'], model.predict(Qd)),
                                 rel(out['model_damping_matrix'], model.damping_matrix(Qd)),
                                 rel(out['model_residual'], model.predict_residual(q=Q, qd=Qd)))
        r[f'{side}_node'] = max(rel(out['damping'], tau), rel(out['damping_matrix'], D))
        # Python against itself: the model's predict against the node's answers where the gate
        # did not act (the conditioning of the GP sum: its terms cancel)
        same = np.all(out['damping'] == out['damping'], axis=1) & \
            np.all(np.abs(out['damping'] - out['model_damping']) == 0, axis=1)
        r[f'{side}_py'] = rel(model.predict(Qd[same]), tau[same]) if same.any() else 0.0
        r[f'{side}_negative'] = int((_power(Qd, out['damping']) < 0).sum() +
                                    (_power(Qd, out['model_damping']) < 0).sum())
        moved = np.abs(out['damping'] - out['model_damping']) > 0
        r[f'{side}_bounded'] = int(moved.any(axis=1).sum())
        r['node_guarantee'] = g
    r['K'] = K
    r['py_us'] = python_call_us(model, rng)
    r['us'] = {}
    for cxx in filter(None, (gxx, find_compiler(('clang++',)))):
        for flags in (('-O2',), ('-O2', '-march=native')):
            key = f'{os.path.basename(cxx)} {" ".join(flags)}'
            r['us'][key] = timing(hdr, model, d, cxx, flags, rng)
    C.log(case, {k: v for k, v in r.items() if k != 'label'})
    return r


def report(a, res, seconds) -> str:
    lines = [C.header_lines(TITLE, 'bench/cpp_export.py', a.quick, seconds), '',
             'Equality (largest error per answer over its largest entry, over K velocities each; '
             '"model": `predict`, `damping_matrix`, `predict_residual` of the model proven at '
             'export; "node": the frozen node\'s `tau_hat` and `D`; negative: answers with '
             '`qd . tau < 0`, C++ damping and model damping together):', '',
             '| model | N, n, elements | guarantee (proven at export) | correction | K | '
             'inside: model / node | outside 10-30x: model / node | Python predict vs node '
             '(in / out, gate silent) | gate acted outside | negative | header |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for r in res:
        lines.append(
            f'| {r["label"]} | {r["N"]}, {r["n"]}, {r["E"]} | {r["guarantee"]} (node: '
            f'{r["node_guarantee"]}) | {r["correction"]} | {r["K"]} | '
            f'{r["in_model"]:.1e} / {r["in_node"]:.1e} | {r["out_model"]:.1e} / '
            f'{r["out_node"]:.1e} | {r["in_py"]:.1e} / {r["out_py"]:.1e} | '
            f'{r["out_bounded"]} | {r["in_negative"] + r["out_negative"]}'
            f' | {r["bytes"] / 1024:.0f} KiB |')
    lines += ['', 'Time per `friction()` call (the example program, best of its passes over '
              '2000 samples) beside one Python `predict_residual` call (median of 300, same '
              'run):', '', '| model | build | C++ us/call | Python us/call | ratio |',
              '|---|---|---|---|---|']
    for r in res:
        for key, us in r['us'].items():
            lines.append(f'| {r["label"]} ({r["E"]} elements) | {key} | {us:.1f} | '
                         f'{r["py_us"]:.0f} | {r["py_us"] / us:.0f}x |')
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv)
    t0 = time.perf_counter()
    from dgp_ros.export.toolchain import find_compiler
    if find_compiler(('g++',)) is None:
        C.log('no g++: nothing to measure')
        return 0
    res = []
    with tempfile.TemporaryDirectory() as d:
        cases = ('a320', 'panda') if a.quick else (
            'a320', 'panda', 'panda_full', 'ur10', 'simpanda', 'motor')
        for case in cases:
            res.append(run_case(case, a.quick, d))
    C.write_section(a.out, NAME, report(a, res, time.perf_counter() - t0))
    return 0


if __name__ == '__main__':
    sys.exit(main())

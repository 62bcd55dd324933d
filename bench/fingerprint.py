#!/usr/bin/env python3
"""
Fingerprints of what the estimator answers: a refactoring must not change one bit.

Every case runs the estimator in line (``refit_mode='sync'``: deterministic) with the node's
defaults and hashes (sha256) what a user gets from it:

* ``a320``: the default approach, every answer one step ahead (the ledger's ``a320_case``);
* ``family<k>``: flights of the ledger's A320 family (``--family``, default 2 3 6);
* ``panda_real``, ``panda_real_30hz``, ``ur10_real`` (and ``panda_real_500hz``,
  ``panda_real_125hz``): the robot family's cases (shared logs; skipped without them): the
  live answers, the saved model file's arrays and its held-out ``predict_residual``;
* ``panda_sim``, ``ur5_sim``: the ledger's simulated arms, their saved models' answers held out;
* ``loop``: the ledger's closed-loop learning transient (the Panda under the example controller
  with the estimator's compensation, 3 s): the tracking errors and the compensation;
* ``header``: the C++ header ``dgp-export`` writes for the UR10's saved model (the simulated
  Panda's without the shared logs).

``--repo DIR`` fingerprints another checkout (its ``dgp_ros``, ``sim_bridge`` and ``bench``
are imported instead of this one's), so two commits are compared on one machine:

    bench/fingerprint.py --repo ../old --json old.json; bench/fingerprint.py --json new.json
    bench/fingerprint.py --compare old.json new.json

Nothing is timed: the hashes are the same on every run of one commit on one machine.

Usage: bench/fingerprint.py [--repo DIR] [--json FILE] [--cases a320 ...] [--compare A B]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
CASES = ('a320', 'family', 'panda_real', 'panda_real_30hz', 'ur10_real', 'panda_sim', 'header',
         'loop', 'panda_real_500hz', 'panda_real_125hz', 'ur5_sim')


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a, dtype=float))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _timeless(x):
    """Return a JSON record without its wall times (``seconds``) and checksums."""
    if isinstance(x, dict):
        return {k: _timeless(v) for k, v in x.items() if k not in ('seconds', 'sha256')}
    if isinstance(x, list):
        return [_timeless(v) for v in x]
    return x


def _file_digest(path: str) -> str:
    """
    Hash a model file by its arrays and its header.

    The zip headers of an npz carry times, and the header records how long the proof took
    (``seconds``) and a checksum of itself: those are left out.
    """
    z = np.load(path, allow_pickle=False)
    h = hashlib.sha256()
    for k in sorted(z.files):
        a = z[k]
        if k == 'header':
            a = np.array(json.dumps(_timeless(json.loads(str(a))), sort_keys=True))
        h.update(k.encode() + str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def a320(wind: dict) -> dict:
    """Fly one approach one step ahead; the answers' hash and the NMSE (the ledger's case)."""
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    from sim_bridge import SimConfig, simulate_approach
    f = simulate_approach(SimConfig(**wind))
    t, Q, T, names = f['t'], f['q'], f['tau'], list(f['joint_names'])
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    P = np.zeros_like(T)
    for i in range(len(t)):
        P[i] = est.predict(Q[i])[0]
        est.process(float(t[i]), names, Q[i], T[i])
    d = est.diagnostics()
    est.close()
    nmse = ((P - T) ** 2).mean(axis=0) / T.var(axis=0)
    return {'answers': _digest(P), 'nmse': [repr(float(x)) for x in nmse],
            'structure': d.get('structure', ''), 'elements': d.get('elements', ''),
            'refits_ok': d.get('refits_ok')}


def arm(label: str, saved: dict) -> dict:
    """Stream a robot family case (``robot_family.arm_case``) and hash it; None if absent."""
    import robot_family as RF
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    log = RF.family_log(label)
    if log is None:
        return None
    t, q, qd, ref = log['t'], log['q'], log['qd'], log['ref']
    tr, te = t < log['split'], t >= log['split']
    est = OnlineEstimator(EstimatorConfig(inverse_dynamics=log['plugin'], refit_mode='sync'))
    est.set_source('bag')
    answers = []
    names = log['names']
    for i in np.flatnonzero(tr):
        e = est.process(RF._stamp(t[i]), names, qd[i], tau_i(log, i), q[i])
        if e is not None:
            answers.append(e.tau_hat)
    d = est.diagnostics()
    path = os.path.join(saved['dir'], f'{log["name"]}_{log["hz"]}.npz')
    est.save(path)
    est.close()
    model = load_model(path)
    held = model.predict_residual(q=q[te], qd=qd[te])
    nm = ((held - ref[te]) ** 2).mean(axis=0) / ref[te].var(axis=0)
    saved.setdefault('paths', {})[label] = path
    return {'answers': _digest(np.array(answers)), 'model_file': _file_digest(path),
            'held_out': _digest(held), 'held_nmse': [repr(float(x)) for x in nm],
            'mean': repr(float(nm.mean())), 'structure': d.get('structure', ''),
            'elements': d.get('elements', ''), 'level': d.get('level'),
            'message': d.get('message')}


def tau_i(log: dict, i: int) -> np.ndarray:
    return log['tau'][i]


def panda_sim(saved: dict, robot: str = 'panda') -> dict:
    """Learn the ledger's simulated arm (60 % of 20 s) and hash its saved model held out."""
    from dgp_ros.dynamics import example_robot_urdf
    from dgp_ros.dynamics.arm_stream import demo_arm
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    d = demo_arm(robot, 20.0, seed=0)
    names = list(d['names'])
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync', inverse_dynamics='urdf',
                                          urdf_file=example_robot_urdf(robot), joints=names))
    est.set_outputs(stddev=False, damping=False)
    t = d['t']
    k = int(np.searchsorted(t, 12.0))
    answers = []
    for i in range(k):
        e = est.process(float(t[i]), names, d['qd'][i], d['effort'][i], d['q'][i])
        if e is not None:
            answers.append(e.tau_hat)
    path = os.path.join(saved['dir'], f'{robot}_sim.npz')
    est.save(path)
    est.close()
    saved.setdefault('paths', {})[f'{robot}_sim'] = path
    model = load_model(path)
    held = model.predict(d['qd_true'][k::10])
    return {'answers': _digest(np.array(answers)), 'model_file': _file_digest(path),
            'held_out': _digest(held)}


def header(saved: dict) -> dict:
    """Hash the C++ header of the UR10's saved model (else the simulated Panda's)."""
    from dgp_ros.export import export_cpp
    paths = saved.get('paths', {})
    src = paths.get('real UR10, 125 Hz') or paths.get('panda_sim')
    if src is None:
        return None
    out = os.path.join(saved['dir'], 'friction.hpp')
    export_cpp(src, out)
    with open(out, 'rb') as fh:
        text = fh.read()
    # the line naming the model file carries its checksum, which covers the wall time its
    # proof took (recorded in the file): the rest is the model
    body = b''.join(x for x in text.splitlines(True) if not x.startswith(b'// Model:'))
    return {'source': os.path.basename(src), 'header': hashlib.sha256(body).hexdigest()[:16],
            'bytes': len(body)}


def loop() -> dict:
    """Fly the ledger's closed-loop transient (``apps.loop_run.run_loop``, in line)."""
    from dgp_ros.apps.loop_run import run_loop
    r = run_loop('panda', 'dgp', 3.0, 3.0)
    return {'error': _digest(r['error']), 'comp': _digest(r['comp']),
            'confidence': _digest(r['confidence']), 'answers': r['answers']}


def run(cases, family) -> dict:
    import ledger as L
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        saved = {'dir': tmp}
        for case in cases:
            t0 = time.perf_counter()
            if case == 'a320':
                out['a320'] = a320({})
            elif case == 'family':
                for k in family:
                    out[f'family{k}'] = a320(L.A320_FAMILY[k][1])
            elif case == 'panda_real':
                out[case] = arm('real Panda, ~1 kHz', saved)
            elif case == 'panda_real_30hz':
                out[case] = arm('real Panda at 30 Hz', saved)
            elif case == 'ur10_real':
                out[case] = arm('real UR10, 125 Hz', saved)
            elif case == 'panda_sim':
                out[case] = panda_sim(saved)
            elif case == 'header':
                out[case] = header(saved)
            elif case == 'loop':
                out[case] = loop()
            elif case == 'panda_real_500hz':
                out[case] = arm('real Panda at 500 Hz', saved)
            elif case == 'panda_real_125hz':
                out[case] = arm('real Panda at 125 Hz', saved)
            elif case == 'ur5_sim':
                out[case] = panda_sim(saved, 'ur5')
            print(f'[fingerprint] {case}: {time.perf_counter() - t0:.0f} s', file=sys.stderr,
                  flush=True)
    return out


def compare(a: str, b: str, section: bool = False) -> int:
    """Print case by case whether two fingerprint files agree; 1 if any case differs."""
    with open(a) as fa, open(b) as fb:
        A, B = json.load(fa), json.load(fb)
    ca, cb = A.pop('_commit', '?'), B.pop('_commit', '?')
    bad, rows = 0, []
    for case in sorted(set(A) | set(B)):
        same = A.get(case) == B.get(case)
        bad += not same
        print(f'{case:18s} {"identical" if same else "DIFFERENT"}')
        keys = ('answers', 'model_file', 'held_out', 'header', 'error')
        got = B.get(case) or {}
        rows.append(f'| {case} | {"identical" if same else "**different**"} | ' +
                    ', '.join(f'{k} {got[k]}' for k in keys if k in got) + ' |')
        if not same:
            for k in sorted(set(A.get(case) or {}) | set(B.get(case) or {})):
                x, y = (A.get(case) or {}).get(k), (B.get(case) or {}).get(k)
                if x != y:
                    print(f'    {k}: {x} -> {y}')
    if section:
        sys.path.insert(0, HERE)
        import common as C
        body = '\n'.join([
            C.header_lines(f'Fingerprints: {ca} against {cb}',
                           'bench/fingerprint.py --compare A B --section', False).rstrip(), '',
            'Every case in line with the defaults (module docstring of bench/fingerprint.py); '
            'sha256 (first 16 hex digits) of every answer one step ahead, of the saved model '
            "file (its arrays and header, without the proof's wall time), of its held-out "
            'answers and of the exported header.', '',
            '| case | result | hashes (second file) |', '|---|---|---|'] + rows)
        print('wrote', C.write_section(os.path.join(os.path.dirname(HERE), 'docs'),
                                       'fingerprint', body))
    return 1 if bad else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--repo', default=os.path.dirname(HERE), help='checkout to fingerprint')
    p.add_argument('--json', help='write the fingerprints here')
    p.add_argument('--cases', nargs='*', default=list(CASES), choices=CASES)
    p.add_argument('--family', nargs='*', type=int, default=[2, 3, 6])
    p.add_argument('--compare', nargs=2, metavar=('A', 'B'), help='compare two JSON files')
    p.add_argument('--section', action='store_true',
                   help="with --compare: write the table into docs/BENCHMARKS.md ('fingerprint')")
    a = p.parse_args(argv)
    if a.compare:
        return compare(*a.compare, section=a.section)
    repo = os.path.abspath(a.repo)
    sys.path[:0] = [repo, os.path.join(repo, 'bench')]
    for m in [m for m in sys.modules if m.split('.')[0] in ('dgp_ros', 'sim_bridge')]:
        del sys.modules[m]
    import dgp_ros
    print(f'[fingerprint] {os.path.dirname(dgp_ros.__file__)}', file=sys.stderr)
    out = run(a.cases, a.family)
    import subprocess
    out['_commit'] = subprocess.run(['git', '-C', repo, 'rev-parse', '--short', 'HEAD'],
                                    capture_output=True, text=True).stdout.strip() or '?'
    text = json.dumps(out, indent=1, sort_keys=True)
    if a.json:
        with open(a.json, 'w') as fh:
            fh.write(text + '\n')
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())

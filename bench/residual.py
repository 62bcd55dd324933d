#!/usr/bin/env python3
"""
Real-arm accuracy with the defaults: what the structure selection picks, held out.

1. Real Franka Panda (``panda_log_train.npz`` of the shared ``panda_real`` folder, see
   ``certification.py`` for where it is looked up; skipped with the reason when absent): a bag of
   its raw joint states for t < 7.5 s goes through ``dgp-replay`` with the defaults and the
   identified model as ``inverse_dynamics`` (``python:panda_rb:tau_rb``), ``--save-model``; the
   saved model's ``predict_residual(q, qd)`` is scored on every sample of 7.5-12.6 s against the
   reference residual (raw and low-passed) and against a Makkar sigmoid refit by least squares on
   the same training samples. Then every fixed structure of the long history (friction family x
   offsets x correction), fitted on the same front end's samples, scored the same way, beside
   its cross-validation score: what the selection saw and what each choice would have given.
   Negative dissipated power of ``predict`` on 10^5 random velocities inside and 10x outside the
   data.
2. A320 (``sim_bridge.simulate_approach``): the approach as a JointState bag through
   ``replay`` with the defaults and with hand-picked settings; NMSE per output of the
   one-step-ahead answers.

Usage: bench/residual.py [--quick] [--out DIR] [--data DIR]
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

import common as C  # noqa: E402
from certification import _extra, panda_dir  # noqa: E402,I100,I201

NAME = 'residual'
TITLE = 'Real-arm residual with the defaults: selection, correction, held out'
SPLIT_S = 7.5
A320_SETTINGS = (('defaults (prior=auto)', {}),
                 ('prior=viscous bias=false', {'prior': 'viscous', 'bias': False}),
                 ('prior=friction+stribeck bias=true',
                  {'prior': 'friction+stribeck', 'bias': True}),
                 ('prior=friction bias=false', {'prior': 'friction', 'bias': False}))


def panda_part(a, path):
    """Replay the training bag, score the saved model and every fixed structure."""
    from dgp_ros.dynamics import AccelFilter, FrictionResidual
    from dgp_ros.dynamics.baselines import fit_cv, fit_sigmoid, predict_sigmoid
    from dgp_ros.dynamics.conservative import correction_basis
    from dgp_ros.dynamics.history import LongHistory
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig
    z = np.load(os.path.join(path, 'panda_log_train.npz'), allow_pickle=False)
    t, q, qd, tau = z['t'], z['q'], z['qd'], z['tau_meas']
    tr, te = t < SPLIT_S, t >= SPLIT_S
    ref, lp = z['tau_friction_offline'][te], z['tau_friction_offline_lp'][te]
    out = {'split_s': SPLIT_S, 'bag_s': float(t[tr][-1] - t[0])}
    env = dict(os.environ, PYTHONPATH=path + os.pathsep + os.environ.get('PYTHONPATH', ''))
    with tempfile.TemporaryDirectory() as d:
        bag = os.path.join(d, 'bag')
        subprocess.run([sys.executable, os.path.join(path, 'make_bag.py'), bag, '--end-s',
                        str(SPLIT_S)], check=True, env=env, capture_output=True)
        model_path = os.path.join(d, 'm.npz')
        exe = os.path.join(os.path.dirname(sys.executable), 'dgp-replay')
        t0 = time.perf_counter()
        r = subprocess.run([exe, bag, '-o', os.path.join(d, 'out'), '--no-plots', '--set',
                            'inverse_dynamics=python:panda_rb:tau_rb', '--save-model',
                            model_path], env=env, capture_output=True, text=True)
        out['replay_s'] = time.perf_counter() - t0
        out['replay_rc'] = r.returncode
        out['replay_stderr'] = [ln for ln in r.stderr.splitlines() if 'replay [' not in ln]
        out['warnings'] = [ln for ln in r.stderr.splitlines()
                           if 'Warning' in ln or 'Traceback' in ln]
        m = load_model(model_path)
    P = m.predict_residual(q=q[te], qd=qd[te])
    out['raw'], out['lp'] = C.nmse(P, ref), C.nmse(P, lp)
    corr = getattr(m, 'correction_', None)
    out['basis'] = '' if corr is None or corr.basis is None else corr.basis.source
    sig = np.column_stack([predict_sigmoid(fit_sigmoid(qd[tr, j], z['tau_friction_offline'][tr, j],
                                                       fit_cv(qd[tr, j],
                                                              z['tau_friction_offline'][tr, j])),
                                           qd[te, j]) for j in range(7)])
    out['sig_raw'], out['sig_lp'] = C.nmse(sig, ref), C.nmse(sig, lp)
    # negative power of predict: 10^5 random velocities inside and 10x outside the data box
    rng = np.random.default_rng(0)
    k = 20000 if a.quick else 100000
    lo, hi = qd.min(0), qd.max(0)
    neg = {}
    for label, f in (('inside', 1.0), ('10x outside', 10.0)):
        V = C.random_points(rng, lo, hi, k, f)
        neg[label] = int(C.negative_power_count(m, V)[1])
    out['negative'] = neg
    # every fixed structure on the same front end's samples (what the selection chose from)
    cfg = EstimatorConfig()
    sys.path.insert(0, path)
    import panda_rb
    front = FrictionResidual(panda_rb.tau_rb, AccelFilter(cfg.accel_half_window_s))
    names = [f'panda_joint{j}' for j in range(1, 8)]
    hist = LongHistory(7, correction_basis(panda_rb.tau_rb, names))
    last = None
    for i in np.flatnonzero(tr):
        want = last is None or t[i] >= last + cfg.min_sample_interval_s
        last = t[i] if want else last
        for s in front.push(t[i], q[i], qd[i], tau[i], want=want):
            hist.push(s.stamp_s, s.q, s.qd, s.qdd, s.residual)
    sel = hist.select()
    rows = []
    for cand in hist.candidates():
        f = hist.fit(*cand)
        p = f.friction_mean().force(qd[te]) + f.correction()(q[te])
        rows.append((cand, sel.scores.get(cand, float('nan')), C.nmse(p, ref), C.nmse(p, lp)))
    # offsets may be chosen joint by joint ((N,) bools): a candidate carries one bool for all
    offs = np.atleast_1d(np.asarray(sel.offsets, bool))
    out['candidates'], out['selected'] = rows, (sel.family, bool(offs.any()), sel.conservative)
    some = offs.size > 1 and offs.any()
    out['offset_joints'] = [int(j) for j in np.flatnonzero(offs)] if some else None
    return out


def a320_part(a):
    """Replay an A320 approach bag with the defaults and hand-picked settings."""
    from dgp_ros.bags import write_joint_state_bag
    from dgp_ros.online import EstimatorConfig
    from dgp_ros.apps.replay import replay, summarize
    from sim_bridge import SimConfig, simulate_approach
    data = simulate_approach(SimConfig(), max_time_s=60.0 if a.quick else None)
    names = list(data['joint_names'])
    rows = []
    with tempfile.TemporaryDirectory() as d:
        bag = os.path.join(d, 'a320')
        write_joint_state_bag(bag, [(float(t), names, np.zeros(3), v, e) for t, v, e in
                                    zip(data['t'], data['q'], data['tau'])])
        for label, kw in A320_SETTINGS:
            cfg = EstimatorConfig(refit_mode='sync', **kw)
            t0 = time.perf_counter()
            est_list, est, info = replay(bag, config=cfg)
            s = summarize(bag, est_list, est, info, names)
            rows.append((label, [s['nmse'][n] for n in names], time.perf_counter() - t0,
                         est.diagnostics().get('structure', '')))
    return {'names': names, 'rows': rows, 'seconds': float(data['t'][-1])}


def report(a, P, A, wall, path) -> str:
    lines = [C.header_lines(TITLE, 'bench/residual.py', a.quick, wall), '']
    if P is None:
        lines += ['Real Panda data not found: that part was skipped.', '']
    else:
        r = P
        lines += [f'### Real Franka Panda, learn on t < {SPLIT_S} s, predict 7.5-12.6 s', '',
                  f'Source: the development log `panda_log_train.npz` ({path}). '
                  f'`dgp-replay` of the {r["bag_s"]:.1f} s bag with the defaults and '
                  '`inverse_dynamics=python:panda_rb:tau_rb`, `--save-model`: '
                  f'{r["replay_s"]:.1f} s wall ({r["replay_s"] / r["bag_s"]:.2f}x real time), '
                  f'exit code {r["replay_rc"]}, Python warnings or tracebacks printed: '
                  f'{len(r["warnings"])}. Conservative basis: {r["basis"] or "none"}.', '',
                  'What dgp-replay printed: ' +
                  ' / '.join(f'`{ln}`' for ln in r['replay_stderr'][-2:]), '']
        hdr = ['', 'mean'] + [f'j{j + 1}' for j in range(7)]
        rows = [['saved model, predict_residual, raw'] + [C.fmt(r['raw'].mean())] +
                [C.fmt(v) for v in r['raw']],
                ['sigmoid refit (Makkar), raw'] + [C.fmt(r['sig_raw'].mean())] +
                [C.fmt(v) for v in r['sig_raw']],
                ['ratio raw'] + [C.fmt(r['raw'].mean() / r['sig_raw'].mean())] +
                [C.fmt(v) for v in r['raw'] / r['sig_raw']],
                ['saved model, low-passed reference'] + [C.fmt(r['lp'].mean())] +
                [C.fmt(v) for v in r['lp']],
                ['sigmoid, low-passed reference'] + [C.fmt(r['sig_lp'].mean())] +
                [C.fmt(v) for v in r['sig_lp']],
                ['ratio low-passed'] + [C.fmt(r['lp'].mean() / r['sig_lp'].mean())] +
                [C.fmt(v) for v in r['lp'] / r['sig_lp']]]
        lines += [C.md_table(hdr, rows), '',
                  'Negative dissipated power of `predict` (beyond 1e-12 |qd||tau|): ' +
                  ', '.join(f'{k} {v}' for k, v in r['negative'].items()) +
                  f' of {20000 if a.quick else 100000} random velocities each.', '',
                  'Every fixed structure of the long history (the parametric part only, no '
                  'GP), with the cross-validation score the selection used (lower is better); '
                  f'**selected: {r["selected"]}**' +
                  ('' if r.get('offset_joints') is None else
                   f' (offsets on joints {r["offset_joints"]})') + ':', '']
        crow = []
        for cand, score, raw, lpv in sorted(r['candidates'], key=lambda x: x[2].mean()):
            mark = ' **(selected)**' if cand == r['selected'] else ''
            crow.append([f'{cand[0]}, {"offsets" if cand[1] else "no offsets"}, '
                         f'{"correction" if cand[2] else "no correction"}{mark}',
                         C.fmt(score), C.fmt(raw.mean()), C.fmt(raw.max()), C.fmt(lpv.mean())])
        lines += [C.md_table(['structure', 'CV score', 'held-out raw mean', 'worst joint',
                              'low-passed mean'], crow), '']
    lines += [f'### A320 approach ({A["seconds"]:.0f} s), replay one-step-ahead NMSE', '']
    best = np.min([row[1] for row in A['rows']], axis=0)
    rows = [[label] + [C.fmt(v) for v in nm] +
            [C.fmt(max(np.array(nm) / best)), C.fmt_time(sec), st or '-']
            for label, nm, sec, st in A['rows']]
    heads = ['setting'] + A['names'] + ['worst ratio to best', 'wall', 'structure']
    lines += [C.md_table(heads, rows), '']
    return '\n'.join(lines)


def main(argv=None) -> int:
    return C.panda_a320_main(NAME, argv, _extra, panda_dir, panda_part, a320_part, report)


if __name__ == '__main__':
    sys.exit(main())

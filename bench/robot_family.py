#!/usr/bin/env python3
"""
The robot family with the node's defaults: real arms at their own rates and resampled.

One robot is not the robots. Each case streams a real arm's raw joint states (stamped as the
log's bag, ``make_bag.py``: 1.7e9 s + t) through the estimator in line (``refit_mode='sync'``:
the node's learner, deterministic) with the log's identified rigid-body model as
``inverse_dynamics`` (``python:<robot>_rb:tau_rb``), learns on the first part of the shared log
(``t < split``), saves the model as ``--save-model`` would and scores:

* ``held``: the saved model's ``predict_residual`` on every sample of the rest of the shared log
  against the log's reference residual (offline zero-phase acceleration), NMSE per joint;
* ``cv`` / ``sigmoid``: a Coulomb + viscous + offset least-squares refit (``baselines.fit_cv``)
  and a Makkar sigmoid refit (``baselines.fit_sigmoid``) of the residual samples the estimator
  learned, offsets included, scored the same way;
* ``live``: the answers the node published one step ahead (the damping force, blended by the
  grounds, plus the model's correction and offsets, at the message each learned residual sample
  belongs to, before it was learned) against those samples, NMSE per joint, beside answering
  zero (``zero``);
* ``prior`` / ``parametric``: the saved model's prior (its parametric part with the elements of
  D from every sample, ``gp.joint_element``) and its parametric part alone, held out the same
  way; and, learned on the first third of the log only (``no_harm``), the same per joint;
* ``negative_power``: published answers with ``qd . tau_hat < 0`` beyond rounding, and of the
  saved model at 40000 random velocities inside the learned box and 10x beyond it;
* ``status``: the /diagnostics level and message at the end; ``wall_s``: the learning time.

``resample(log, hz)`` decimates a log to another stream rate (the first logged sample at or
after each tick: a robot publishes measurements, not interpolations). The simulated arms
(friction outside the prior's family) are the ledger's (``ledger.panda_sim_case``).

The shared logs are found in ``../shared/data`` (or ``DGP_SHARED_DATA``); a case whose log is
absent is skipped with the reason (a user's clone has none). ``LIMITS`` are the tests'
(``test/test_robot_family.py``, default suite).

``curve``: the whole UR10 log (``ur10_log_rest.npz`` beside the shared part) learned on its first
20 / 40 / 60 % and held out on its last 40 %.

Usage: bench/robot_family.py [--quick] [--out DIR]
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from typing import Optional

import numpy as np

import common as C  # noqa: E402

from dgp_ros.dynamics import ARM_JOINTS  # noqa: E402

NAME = 'robot_family'
TITLE = "The robot family with the node's defaults: real arms held out"
#: the shared real logs: file, plugin module, joint names, the learning split (s)
ARMS = {
    'panda_real': ('panda_log_train.npz', 'panda_rb', list(ARM_JOINTS['panda']), 7.5),
    'ur10_real': ('ur10_log_train.npz', 'ur10_rb', list(ARM_JOINTS['ur5']), 10.0),  # UR names
}
#: the family: (label, arm, stream rate in Hz or None for the log's own)
CASES = (
    ('real Panda, ~1 kHz', 'panda_real', None),
    ('real Panda at 500 Hz', 'panda_real', 500.0),
    ('real Panda at 125 Hz', 'panda_real', 125.0),
    ('real Panda at 30 Hz', 'panda_real', 30.0),
    ('real UR10, 125 Hz', 'ur10_real', None),
)
#: the tests' limits per case (the worst joint's bound is against the Coulomb-viscous refit's
#: same joint): the held-out mean at or below both refits' means at every rate, and every
#: joint of the UR10
_REFITS = {'vs_sigmoid': 1.0, 'vs_cv': 1.0}
LIMITS = {
    'real Panda, ~1 kHz': dict(_REFITS, mean=0.545),
    'real Panda at 500 Hz': dict(_REFITS),
    'real Panda at 125 Hz': dict(_REFITS),
    'real Panda at 30 Hz': dict(_REFITS),
    'real UR10, 125 Hz': dict(_REFITS, vs_cv_joint=1.5),
}
STAMP0 = 1.7e9
#: random velocities for the saved model's passivity (inside the learned box, and 10x beyond)
N_RANDOM = 20000


def arm_dir(name: str):
    """Return the shared folder of arm ``name`` or None (``DGP_SHARED_DATA``, else ../shared)."""
    base = os.environ.get('DGP_SHARED_DATA') or os.path.join(C.REPO, '..', 'shared', 'data')
    path = os.path.join(base, name)
    return os.path.abspath(path) if os.path.isfile(os.path.join(path, ARMS[name][0])) else None


def load_log(name: str, path: str) -> dict:
    """Return the log of arm ``name`` in ``path``: t, q, qd, tau, ref (n, N), names, plugin."""
    fname, module, names, split = ARMS[name]
    z = np.load(os.path.join(path, fname), allow_pickle=False)
    if path not in sys.path:
        sys.path.insert(0, path)            # the identified model: python:<module>:tau_rb
    return {'name': name, 't': z['t'], 'q': z['q'], 'qd': z['qd'], 'tau': z['tau_meas'],
            'ref': z['tau_friction_offline'], 'names': list(names),
            'plugin': f'python:{module}:tau_rb', 'split': split, 'hz': None}


#: the whole UR10 log: its shared rest, and the learning curve's fractions (the last 40 %
#: held out at each)
UR10_REST = 'ur10_log_rest.npz'
CURVE = (0.2, 0.4, 0.6)


def whole_log(name: str = 'ur10_real') -> Optional[dict]:
    """Return arm ``name``'s whole log (its train part and its rest), or None if absent."""
    path = arm_dir(name)
    if path is None or not os.path.isfile(os.path.join(path, UR10_REST)):
        return None
    log = load_log(name, path)
    z = np.load(os.path.join(path, UR10_REST), allow_pickle=False)
    for k, key in (('t', 't'), ('q', 'q'), ('qd', 'qd'), ('tau', 'tau_meas'),
                   ('ref', 'tau_friction_offline')):
        log[k] = np.concatenate([log[k], z[key]])
    return log


def curve(log: dict, keep: bool = False) -> list:
    """Learn ``log``'s first 20 / 40 / 60 % (``CURVE``), score each on its last 40 %."""
    t = log['t']
    span = float(t[-1] - t[0])
    return [(f, arm_case(log, split_s=float(t[0] + f * span),
                         test_s=float(t[0] + 0.6 * span), keep=keep)) for f in CURVE]


def _curve_section(rows: list) -> list:
    lines = ['', '### The whole UR10 log: the learning curve', '',
             'The whole 27.5 s log (`ur10_log_train.npz` and `ur10_log_rest.npz`), learned on its '
             'first 20 / 40 / 60 % with the defaults and held out on its last 40 % (the '
             'acceptance split at 60 %). Columns as above; `best refit` is the better of the '
             'Coulomb-viscous and sigmoid refits of the same learned samples, per mean.', '']
    table = []
    for f, r in rows:
        if r is None or not r['trained']:
            table.append([f'{f:.0%}', 'never trained'] + ['-'] * 6)
            continue
        best = min(float(np.mean(r['cv'])), float(np.mean(r['sigmoid'])))
        table.append([f'{f:.0%}', C.fmt(r['mean']), C.fmt(np.mean(r['parametric'])),
                      C.fmt(np.mean(r['cv'])), C.fmt(np.mean(r['sigmoid'])),
                      f'{r["mean"] / best:.3f}', ' / '.join(C.fmt(v) for v in r['held']),
                      f'{r["structure"]}; {r["elements"]}'])
    return lines + [C.md_table(['learned', 'held out', 'its parametric part', 'cv refit',
                                'sigmoid refit', 'over the best refit', 'per joint',
                                'structure; elements'], table), '']


def resample(log: dict, hz: float) -> dict:
    """Decimate ``log`` to ``hz``: the first sample at or after each tick of 1/hz."""
    t = log['t']
    keep, nxt = [], t[0]
    for i, ti in enumerate(t):
        if ti >= nxt - 1e-9:
            keep.append(i)
            nxt = max(nxt + 1.0 / hz, ti + 0.5 / hz)
    out = dict(log, hz=float(hz))
    for k in ('t', 'q', 'qd', 'tau', 'ref'):
        out[k] = log[k][np.array(keep)]
    return out


def family_log(label: str):
    """Return the log of the family case ``label`` (resampled as it says), or None if absent."""
    _, arm, hz = next(c for c in CASES if c[0] == label)
    path = arm_dir(arm)
    if path is None:
        return None
    log = load_log(arm, path)
    return resample(log, hz) if hz else log


def _nmse(p, r):
    return ((p - r) ** 2).mean(axis=0) / np.maximum(r.var(axis=0), 1e-300)


def _stamp(t: float) -> float:
    sec, ns = divmod(int(round((STAMP0 + t) * 1e9)), 1_000_000_000)
    return sec + 1e-9 * ns


def _stream(est, log: dict, train: np.ndarray):
    """Stream the learning part; return (live pairs, learned samples, negative answers)."""
    t, q, qd, tau, names = (log[k] for k in ('t', 'q', 'qd', 'tau', 'names'))
    answers, live, learned, neg = {}, [], [], 0
    for i in np.flatnonzero(train):
        s = _stamp(t[i])
        e = est.process(s, names, qd[i], tau[i], q[i])
        if e is None:
            continue
        neg += int(e.power < -1e-12 * (np.abs(e.qd) @ np.abs(e.tau_hat)))
        corr = getattr(est.model, 'correction_', None)
        answers[s] = e.tau_hat + (0.0 if corr is None else corr(q[i][None])[0])
        for r in e.residuals:
            a = answers.pop(r.stamp_s, None)
            if a is not None and np.all(np.isfinite(r.residual)):
                live.append((a, r.residual))
                learned.append((r.qd, r.residual))
        for old in [k for k in answers if k < s - 1.0]:
            del answers[old]
    return live, learned, neg


def _baselines(out: dict, learned: list, qd_te: np.ndarray, ref_te: np.ndarray) -> None:
    from dgp_ros.dynamics.baselines import fit_cv, fit_sigmoid, predict_cv, predict_sigmoid
    V, R = (np.array(x) for x in zip(*learned))
    N = V.shape[1]
    cv = [fit_cv(V[:, j], R[:, j]) for j in range(N)]
    out['cv'] = _nmse(np.column_stack([predict_cv(cv[j], qd_te[:, j]) + cv[j]['b']
                                       for j in range(N)]), ref_te)
    sg = [fit_sigmoid(V[:, j], R[:, j], cv[j]) for j in range(N)]
    out['sigmoid'] = _nmse(np.column_stack([predict_sigmoid(sg[j], qd_te[:, j]) + sg[j]['b']
                                            for j in range(N)]), ref_te)


def arm_case(log: dict, split_s=None, baselines: bool = True, test_s=None, keep: bool = False,
             **params) -> dict:
    """
    Learn ``log`` on t < split and score it (module docstring) on t >= split or ``test_s``.

    ``params``: estimator parameters besides the defaults.

    Returns a dict with ``held``, ``cv``, ``sigmoid``, ``live``, ``zero`` (N,) NMSE, ``mean``,
    ``parametric`` (the saved model's parametric part alone, held out), ``prior`` (with the
    elements of D from every sample, ``gp.joint_element``: its prior mean), ``elements``,
    ``structure``, ``status``, ``negative_power``, ``saved_negative_power``, ``wall_s``,
    ``stream_s``, ``trained``; with ``keep`` also ``model`` (the saved model, loaded).
    """
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    split = log['split'] if split_s is None else split_s
    t, q, qd, ref = log['t'], log['q'], log['qd'], log['ref']
    tr, te = t < split, t >= (split if test_s is None else test_s)
    est = OnlineEstimator(EstimatorConfig(**dict({'inverse_dynamics': log['plugin']}, **params,
                                                 refit_mode='sync')))
    est.set_source('bag')
    t0 = time.perf_counter()
    live, learned, neg = _stream(est, log, tr)
    d = est.diagnostics()
    with tempfile.TemporaryDirectory() as tmp:
        model = load_model(est.save(os.path.join(tmp, 'm.npz'))) if est.trained else None
    wall = time.perf_counter() - t0
    est.close()
    out = {'name': log['name'], 'hz': log['hz'], 'split': split, 'wall_s': wall,
           'stream_s': float(t[tr][-1] - t[tr][0]), 'trained': model is not None,
           'status': (d['level'], d['message']), 'negative_power': neg,
           'structure': d.get('structure', ''), 'elements': d.get('elements', ''),
           'refits': (d.get('refits_ok'), d.get('refits_failed'))}
    if live:
        A, R = (np.array(x) for x in zip(*live))
        out['live'], out['zero'] = _nmse(A, R), _nmse(np.zeros_like(R), R)
    if model is not None:
        out['held'] = _nmse(model.predict_residual(q=q[te], qd=qd[te]), ref[te])
        out['mean'] = float(out['held'].mean())
        corr = getattr(model, 'correction_', None)
        c = 0.0 if corr is None else corr(q[te])
        mean = model.mean_
        # the parametric part alone, and with the elements of D from every sample (its prior)
        out['parametric'] = _nmse(getattr(mean, 'base', mean).force(qd[te]) + c, ref[te])
        out['prior'] = _nmse(mean.force(qd[te]) + c, ref[te])
        rng = np.random.default_rng(0)
        lo, hi = qd[tr].min(axis=0), qd[tr].max(axis=0)
        Qs = np.vstack([rng.uniform(lo, hi, (N_RANDOM, lo.size)),
                        rng.uniform(lo - 10 * (hi - lo), hi + 10 * (hi - lo),
                                    (N_RANDOM, lo.size))])
        out['saved_negative_power'] = C.negative_power_count(model, Qs)[1]    # beyond rounding
        if keep:
            out['model'] = model
    if baselines and learned:
        _baselines(out, learned, qd[te], ref[te])
    return out


def check(label: str, r: dict) -> list:
    """Return what case ``label``'s result ``r`` misses of its limits (``LIMITS``), as text."""
    lim, bad = LIMITS[label], []
    if not r['trained']:
        return [f'{label}: never trained ({r["status"][1]})']
    if 'mean' in lim and not r['mean'] <= lim['mean']:
        bad.append(f'{label}: held-out mean {r["mean"]:.4g} > {lim["mean"]}')
    for key, base in (('vs_sigmoid', 'sigmoid'), ('vs_cv', 'cv')):
        if key in lim and not r['mean'] <= lim[key] * float(np.mean(r[base])):
            bad.append(f'{label}: held-out mean {r["mean"]:.4g} > {lim[key]} x the {base} '
                       f"refit's {np.mean(r[base]):.4g}")
    if 'vs_cv_joint' in lim:
        ratio = r['held'] / r['cv']
        bad += [f'{label}: joint {j} {ratio[j]:.3g} x the cv refit'
                for j in np.flatnonzero(~(ratio <= lim['vs_cv_joint']))]
    bad += [f'{label}: live joint {j} {r["live"][j]:.3g} >= zero {r["zero"][j]:.3g}'
            for j in np.flatnonzero(~(r['live'] < r['zero']))]
    if r['negative_power'] or r['saved_negative_power']:
        bad.append(f'{label}: negative power {r["negative_power"]} published, '
                   f'{r["saved_negative_power"]} saved')
    if 'does not behave as joint torque' in r['status'][1]:     # torques, never a false alarm
        bad.append(f'{label}: {r["status"][1]}')
    return bad


# ------------------------------------------------------------------------------ the report
def _row(label: str, r: dict) -> list:
    f = C.fmt
    if r is None:
        return [label, 'log not found: skipped'] + ['-'] * 7
    if not r['trained']:
        return [label, f'never trained: {r["status"][1]}'] + ['-'] * 7
    zero = ' / '.join(f'{a:.2g}<{b:.2g}' for a, b in zip(r['live'], r['zero']))
    return [label, f(r['mean']), f(np.mean(r['parametric'])), f(np.mean(r['cv'])),
            f(np.mean(r['sigmoid'])), f'{r["mean"] / np.mean(r["cv"]):.3f} / '
            f'{r["mean"] / np.mean(r["sigmoid"]):.3f}',
            f'{np.max(r["held"] / r["cv"]):.2f}', zero,
            f'{r["wall_s"]:.1f} s / {r["stream_s"]:.1f} s']


def report(a, results: list, wall: float) -> str:
    lines = [C.header_lines(TITLE, 'bench/robot_family.py', a.quick, wall), '',
             "The node's defaults in line (`refit_mode=sync`). Each case learns the first part "
             'of a shared real log (Panda t < 7.5 s, UR10 t < 10 s; the Panda log also decimated '
             "to 500, 125 and 30 Hz) and its saved model's `predict_residual` is held out on the "
             'rest of the shared part against the reference residual (NMSE, mean of the joints). '
             'Refits: Coulomb + viscous + offset (cv) and Makkar sigmoid, offsets included, '
             'fitted on the residual samples the estimator learned. Live: the published answers '
             'one step ahead against the learned samples, per joint, beside answering zero. '
             'Limits of '
             '`test/test_robot_family.py`: ' + '; '.join(
                 f'{k}: ' + ', '.join(f'{n} {v}' for n, v in lim.items())
                 for k, lim in LIMITS.items()) + '.', '',
             C.md_table(['case', 'held out', 'its parametric part', 'cv refit', 'sigmoid refit',
                         'over cv / sigmoid', 'worst joint over cv',
                         'live one step < zero, per joint', 'learning / stream'],
                        [_row(label, r) for label, r in results]), '']
    for label, r in results:
        if r is None or not r['trained']:
            continue
        lines += [f'**{label}**: structure `{r["structure"]}`, elements `{r["elements"]}`, '
                  f'refits ok / failed {r["refits"][0]} / {r["refits"][1]}, status '
                  f'`{r["status"][1]}`; negative power published / saved: '
                  f'{r["negative_power"]} / {r["saved_negative_power"]}; limits: '
                  f'{"; ".join(check(label, r)) or "met"}.', '',
                  C.md_table(['', 'mean'] + [f'j{j + 1}' for j in range(len(r['held']))],
                             [[k, C.fmt(np.mean(r[k]))] + [C.fmt(v) for v in r[k]]
                              for k in ('held', 'prior', 'parametric', 'cv', 'sigmoid', 'live',
                                        'zero')]),
                  '']
    return '\n'.join(lines)


#: no harm outside the data: learn on the first third of the shared log only, score the rest
NO_HARM = ('real Panda, ~1 kHz', 'real UR10, 125 Hz')


def no_harm(label: str) -> Optional[dict]:
    """
    Learn ``label``'s log on its first third only and score the rest (``arm_case``).

    The rest holds poses and speeds the start never visited: per joint the model, its prior
    (the parametric part with the elements of D from every sample) and the parametric part
    alone. None without the log.
    """
    log = family_log(label)
    if log is None:
        return None
    r = arm_case(log, split_s=float(log['t'][0] + (log['t'][-1] - log['t'][0]) / 3.0),
                 baselines=False)
    return r


def _no_harm_section(rows: list) -> list:
    lines = ['', '### No harm outside the data', '',
             'Each case learned on the first third of the shared log only and held out on the '
             'rest (poses and speeds the start never visited). Per joint, held-out NMSE of the '
             'saved model, of its prior (the parametric part with the elements of D from every '
             'sample) and of the parametric part alone; the worst joint of the prior over the '
             'parametric part (the elements must not make a joint worse where they have no '
             'grounds).', '']
    table = []
    for label, r in rows:
        if r is None or not r['trained']:
            table.append([label, 'log not found: skipped' if r is None else 'never trained',
                          '-', '-', '-', '-'])
            continue
        table.append([label, r['structure'] or '-',
                      ' / '.join(C.fmt(v) for v in r['held']),
                      ' / '.join(C.fmt(v) for v in r['prior']),
                      ' / '.join(C.fmt(v) for v in r['parametric']),
                      f'{np.max(r["prior"] / r["parametric"]):.3f}'])
    return lines + [C.md_table(['case (first third)', 'structure', 'model per joint',
                                'prior per joint', 'parametric per joint',
                                'worst joint: prior / parametric'], table), '']


#: the README's figure: the whole UR10 log learned on its first 60 %, its last 40 % drawn
FIGURE = 'ur10_heldout_friction.png'


def figure(out: str, log: dict, r: Optional[dict] = None) -> str:
    """
    Draw ``FIGURE`` in ``out``'s plot folder; return its path.

    Per joint the held-out reference residual (never learned) against velocity, the saved
    model's curve and band, its parametric part and a Coulomb-viscous refit of the learned
    samples (``apps.friction_plot``). ``r``: the learning curve's 60 % case, learned with
    ``keep`` (else it is learned here).
    """
    from dgp_ros.apps.friction_plot import friction_curves
    t = log['t']
    split = float(t[0] + 0.6 * float(t[-1] - t[0]))
    if r is None:
        r = arm_case(log, split_s=split, baselines=False, keep=True)
    te, tr = t >= split, t < split
    path = os.path.join(C.plot_dir(out), FIGURE)
    friction_curves(path, r['model'], log['qd'][te], log['ref'][te], q=log['q'][te],
                    refit_on=(log['qd'][tr], log['ref'][tr], log['q'][tr]),
                    names=log['names'], points='held-out residual (last 40 %, never learned)',
                    title="real UR10, the node's defaults, learned on the first 60 % of the "
                          f'log, held out on the rest: NMSE {r["mean"]:.4f}')
    return path


def _extra(p) -> None:
    p.add_argument('--figure', action='store_true',
                   help=f'only draw the README figure (docs/bench/{FIGURE}, about a minute)')


def main(argv=None) -> int:
    a = C.parse_args(__doc__.strip().splitlines()[0], argv, _extra)
    t0 = time.perf_counter()
    if a.figure:
        whole = whole_log()
        if whole is None:
            C.log(f'{NAME}: no whole UR10 log under ../shared: no figure')
            return 1
        C.log(f'{NAME}: wrote {figure(a.out, whole)}')
        return 0
    results = []
    for label, _, _ in (CASES[::2] if a.quick else CASES):
        log = family_log(label)
        r = None if log is None else arm_case(log)
        C.log(f'{NAME}: {label} ' + ('skipped (no log)' if r is None else
                                     f'{r["wall_s"]:.1f} s, held out {r.get("mean", "-")}'))
        results.append((label, r))
    harm = [] if a.quick else [(label, no_harm(label)) for label in NO_HARM]
    whole = None if a.quick else whole_log()
    rows = [] if whole is None else curve(whole, keep=True)
    if rows:
        figure(a.out, whole, dict(rows)[0.6])
    body = report(a, results, time.perf_counter() - t0)
    if harm:
        body += '\n'.join(_no_harm_section(harm))
    if rows:
        body += '\n'.join(_curve_section(rows))
    C.write_section(a.out, NAME, body)
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""
The data sets and the rows of bench/robot_arms.py: simulate an arm, replay it, score the models.

``make_data`` simulates a Panda or UR5 and writes its raw ``/joint_states`` bags (the learning
60 % and the whole run); ``replay_row`` learns one configuration online through the replay (the
node's code path) and scores the saved model on the held-out 40 %; ``run_dataset`` does every
row of one data set, with the parametric baselines and the negative-power checks. The protocol
is in bench/robot_arms.py's docstring.
"""
from __future__ import annotations

import json
import os
import shutil
import time

import numpy as np

import common as C
from dgp_ros.dynamics.baselines import fit_cv, fit_sigmoid
from dgp_ros.dynamics.baselines import residual_stream as _residual_stream
from dgp_ros.online.config import PARAMS

NAME = 'robot_arms'
LEARN_FRACTION = 0.6
NOISE_SD = 0.3                       # simulate_arm's torque noise [N m]
#: the estimator's shipped defaults (model, prior, bias): the '(defaults)' rows
SHIPPED = (PARAMS['model'].default, PARAMS['prior'].default, PARAMS['bias'].default)
# extra joints / message order of a real driver (the estimator selects and orders by 'joints')
EXTRA = {'panda': ('panda_finger_joint1', 'panda_finger_joint2'), 'ur5': ()}


def _driver_order(robot, names):
    if robot == 'ur5':         # ur_robot_driver publishes shoulder_pan_joint last
        return list(names[1:]) + [names[0]]
    return list(names) + list(EXTRA[robot])


# ----------------------------------------------------------------------------- data
def make_data(robot, duration, seed, work):
    """Simulate, write the learning bag (first 60 %) and the whole bag; return a dict."""
    from dgp_ros.bags import write_joint_state_bag
    from dgp_ros.dynamics import ARM_JOINTS, friction_truth, simulate_arm
    d = simulate_arm(robot, duration, seed=seed)
    names = list(ARM_JOINTS[robot])
    order = _driver_order(robot, names)
    idx = [names.index(n) if n in names else -1 for n in order]

    def msgs(sl):
        for t, q, v, e in zip(d['t'][sl], d['q'][sl], d['qd'][sl], d['effort'][sl]):
            pos = np.array([q[i] if i >= 0 else 0.02 for i in idx])
            vel = np.array([v[i] if i >= 0 else 0.0 for i in idx])
            eff = np.array([e[i] if i >= 0 else 0.1 for i in idx])
            yield (t, order, pos, vel, eff)

    k = int(round(LEARN_FRACTION * len(d['t'])))
    base = os.path.join(work, f'{robot}_{seed}')
    learn_bag = write_joint_state_bag(base + '_learn', msgs(slice(0, k)), topic='/joint_states')
    full_bag = write_joint_state_bag(base + '_all', msgs(slice(None)), topic='/joint_states')
    Qh = d['qd_true'][k:]
    return {'robot': robot, 'seed': seed, 'sim': d, 'names': names, 'k': k,
            'learn_bag': str(learn_bag), 'full_bag': str(full_bag), 'Qh': Qh,
            'Fh': friction_truth(robot, Qh),
            'duration': duration}


def residual_stream(D, urdf, config):
    """Return the estimator front end's residual samples on the learning part: (Qd, R)."""
    d, k = D['sim'], D['k']
    return _residual_stream(d['t'][:k], d['q'][:k], d['qd'][:k], d['effort'][:k], urdf,
                            D['names'], config.accel_half_window_s, config.min_sample_interval_s)


# ----------------------------------------------------------------------------- D-GP rows
def replay_row(D, urdf, work, kind, prior, bias, passivity='projected', defaults=False,
               bag=None, save=True, extra=None, note=''):
    """
    Learn through dgp_ros.apps.replay.run; return the row's numbers (and the loaded model).

    ``extra``: further estimator parameters (non-default rows); ``note``: shown with the row.
    """
    from dgp_ros.gp import load_model
    from dgp_ros.apps.replay import ReplayError, build_config, run
    over = {'joints': D['names'], 'inverse_dynamics': 'urdf', 'urdf_file': urdf}
    if not defaults:
        over.update(model=kind, prior=prior, bias=bias, passivity=passivity, **(extra or {}))
    cfg = build_config(None, **over)
    tag = (f'{D["robot"]}_{D["seed"]}_{kind}_{prior}_{int(bias)}_{passivity}_'
           f'{cfg.buffer_size}').replace('+', 'p')
    path = os.path.join(work, tag + '.npz') if save else None
    out = os.path.join(work, tag + '_out')
    error = ''
    try:
        s = run(bag or D['learn_bag'], out, config=cfg, plots=False, save_model=path)
    except ReplayError as exc:      # e.g. never trained: the summary was written, report it
        error = str(exc)
        summary = os.path.join(out, 'summary.json')
        if not os.path.exists(summary):
            raise
        with open(summary) as f:
            s = json.load(f)
    shutil.rmtree(out, ignore_errors=True)
    r = {'kind': kind, 'prior': prior, 'bias': bias, 'passivity': passivity, 'summary': s,
         'config': cfg,
         'timings': s['timings'], 'refits': s['refits'], 'status': s['status'], 'note': note,
         'defaults': defaults, 'error': error, 'nmse': np.full(len(D['names']), np.nan),
         'neg': None}
    if save and not error:
        m = load_model(path)
        r['model'] = m
        r['pred'] = m.predict(D['Qh'])
        r['nmse'] = C.nmse(r['pred'], D['Fh'])
        if kind != 'ard':
            r['prior_nmse'] = C.nmse(m.mean_.force(D['Qh']), D['Fh'])
        r['bias_hat'] = m.bias_
    return r


def neg_power(model, lo, hi, k, seed):
    rng = np.random.default_rng(seed)
    s_in, t_in, m_in = C.negative_power_count(model, C.random_points(rng, lo, hi, k))
    s_far, t_far, m_far = C.negative_power_count(model, C.far_points(rng, lo, hi, k))
    return {'s_in': s_in, 's_far': s_far, 't_in': t_in, 't_far': t_far,
            'min_rel': min(m_in, m_far)}


def coverage(X, Q):
    """Fraction of the rows of Q inside the bounding box of X (every joint), and per joint."""
    lo, hi = X.min(axis=0), X.max(axis=0)
    inside = (Q >= lo) & (Q <= hi)
    return {'all': float(np.mean(np.all(inside, axis=1))), 'per': np.mean(inside, axis=0)}


def gmean(x):
    x = np.asarray(x, float)
    return float(np.exp(np.mean(np.log(np.maximum(x, 1e-300)))))


# ----------------------------------------------------------------------------- one data set
def run_dataset(a, robot, seed, duration, work, urdf, configs, k_pass, extras, big_buffer=0,
                quick=False):
    """
    Every row on one simulated bag.

    ``extras``: also the 'none' rows, the best row with a ``big_buffer`` buffer (if > 0), the
    whole-bag timing replay and the no-inverse-dynamics WARN replay (quick: no whole-bag replay,
    and only the ARD-GP 'none' row).
    """
    from dgp_ros.apps.replay import build_config
    C.log(f'{NAME}: {robot} seed {seed}: simulate {duration:g} s and write the bags')
    D = make_data(robot, duration, seed, work)
    d = D['sim']
    N = len(D['names'])
    cfg0 = build_config(None, joints=D['names'], inverse_dynamics='urdf', urdf_file=urdf)
    t0 = time.perf_counter()
    Qs, Rs = residual_stream(D, urdf, cfg0)
    cv, sg = [], []
    for j in range(N):
        c = fit_cv(Qs[:, j], Rs[:, j])
        cv.append(c)
        sg.append(fit_sigmoid(Qs[:, j], Rs[:, j], c))
    base_s = time.perf_counter() - t0
    pred_cv = np.column_stack([cv[j]['f'](D['Qh'][:, j]) for j in range(N)])
    pred_sg = np.column_stack([sg[j]['f'](D['Qh'][:, j]) for j in range(N)])
    D.update(stream_n=Qs.shape[0], base_seconds=base_s, cv=cv, sg=sg,
             pred_cv=pred_cv, pred_sg=pred_sg,
             nmse_cv=C.nmse(pred_cv, D['Fh']), nmse_sg=C.nmse(pred_sg, D['Fh']),
             friction_rms=np.sqrt(np.mean(D['Fh'] ** 2, axis=0)))
    D['above_noise'] = D['friction_rms'] > NOISE_SD
    Ql = d['qd'][:D['k']]
    lo, hi = Ql.min(axis=0), Ql.max(axis=0)
    D['box'] = (lo, hi)
    rows = []
    for (kind, prior, bias) in configs:
        defaults = (kind, prior, bias) == SHIPPED
        C.log(f'{NAME}: {robot} seed {seed}: replay {kind} {prior} bias={bias}'
              + (' (defaults)' if defaults else ''))
        r = replay_row(D, urdf, work, kind, prior, bias, defaults=defaults)
        if defaults:     # the defaults as shipped are exactly this row
            assert (r['config'].model, r['config'].prior, r['config'].bias,
                    r['config'].passivity) == SHIPPED + (PARAMS['passivity'].default,)
        if not r['error']:
            r['neg'] = neg_power(r['model'], lo, hi, k_pass, 100 + seed)
        rows.append(r)
    D['rows'] = rows
    # sigmoid refit on the buffer the shipped defaults ended with (the estimator's own samples)
    # (the buffer does not depend on the model: selection and outlier filter look at the data)
    trained = [r for r in rows if not r['error']]
    dflt = next((r for r in trained if r['defaults']), trained[0] if trained else None)
    if dflt is not None:
        Xb, Yb = dflt['model'].X_train_, dflt['model'].Y_train_
        D['buffers_equal'] = all(np.array_equal(r['model'].X_train_, Xb) for r in trained)
        D['coverage'] = coverage(Xb, D['Qh'])
        cvb = [fit_cv(Xb[:, j], Yb[:, j]) for j in range(N)]
        sgb = [fit_sigmoid(Xb[:, j], Yb[:, j], cvb[j]) for j in range(N)]
        D['nmse_sg_buf'] = C.nmse(np.column_stack([sgb[j]['f'](D['Qh'][:, j])
                                                   for j in range(N)]), D['Fh'])
        D['nmse_cv_buf'] = C.nmse(np.column_stack([cvb[j]['f'](D['Qh'][:, j])
                                                   for j in range(N)]), D['Fh'])
        D['buffer_n'] = Xb.shape[0]
    else:
        D['nmse_sg_buf'] = D['nmse_cv_buf'] = np.full(N, np.nan)
        D['buffer_n'], D['coverage'] = 0, None
    dg = [r for r in trained if r['kind'] != 'ard']
    crit = D['above_noise'] if D['above_noise'].any() else np.ones(N, bool)
    D['best'] = min(dg, key=lambda r: gmean(r['nmse'][crit])) if dg else None
    D['extra_rows'] = []
    if extras:
        b = D['best']
        todo = ([(b['kind'], b['prior'], b['bias'], 'none', None, 'passivity none')]
                if b and not quick else []) + ([] if quick else
                                               [SHIPPED + ('none', None, 'passivity none')]) + \
            [('ard', 'viscous', False, 'none', None, 'passivity none')]
        todo = [t for i, t in enumerate(todo) if t[:3] not in [u[:3] for u in todo[:i]]]
        if big_buffer and b:
            todo.append((b['kind'], b['prior'], b['bias'], 'projected',
                         {'buffer_size': big_buffer}, f'buffer_size={big_buffer}'))
        for kind, prior, bias, mode, ex, note in todo:
            C.log(f'{NAME}: {robot} seed {seed}: replay {kind} {prior} bias={bias} {note}')
            r = replay_row(D, urdf, work, kind, prior, bias, passivity=mode, extra=ex,
                           note=note)
            if not r['error']:
                r['neg'] = neg_power(r['model'], lo, hi, k_pass, 100 + seed)
            if ex and not r['error']:
                r['buffer_n'] = r['model'].n_samples_
                r['coverage'] = coverage(r['model'].X_train_, D['Qh'])
            D['extra_rows'].append(r)
        if quick:     # the learning bag's replay of the defaults stands in
            D['whole'] = next((r for r in rows if r['defaults']), None)
        else:
            C.log(f'{NAME}: {robot} seed {seed}: replay the whole {duration:g} s bag (defaults)')
            D['whole'] = replay_row(D, urdf, work, *SHIPPED, defaults=True,
                                    bag=D['full_bag'], save=False)
        C.log(f'{NAME}: {robot} seed {seed}: replay the learning bag without inverse dynamics')
        from dgp_ros.apps.replay import run
        out = os.path.join(work, f'{robot}_{seed}_raw_out')
        s = run(D['learn_bag'], out, config=build_config(None, joints=D['names']), plots=False)
        D['raw'] = {'level': s['status']['level'], 'message': s['status']['message'],
                    'learned_neg': s['learned_negative_power_fraction']}
    for r in rows + D['extra_rows']:
        r.pop('model', None)            # keep memory small; predictions are kept
    return D

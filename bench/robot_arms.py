#!/usr/bin/env python3
"""
Real robot arms: raw /joint_states in, passive friction out.

Data: ``dgp_ros.dynamics.simulate_arm`` (Panda, 7 joints; UR5, 6 joints): 20 s at 1 kHz with
jittered stamps, raw joint torques = rigid body (pinocchio RNEA on the example-robot-data URDF)
+ friction (Coulomb + Stribeck + viscous, known) + a constant sensor bias per joint + 0.3 Nm
noise, common standstills every 5 s. They are written as a raw ``sensor_msgs/JointState`` bag
with positions, velocities and efforts, as a real driver publishes them: the Panda's with its two
finger joints appended, the UR5's in the ``ur_robot_driver`` order (shoulder_pan last), so the
``joints`` parameter selects and orders.

Protocol: the first 60 % of the bag (a bag of its own) is learned ONLINE by
``dgp_ros.apps.replay.run`` (the estimator node's code path, ``refit_mode='sync'``) with
``inverse_dynamics=urdf``; the final model is saved (``save_model=``, as ``dgp-replay
--save-model``), loaded with ``dgp_ros.gp.load_model`` and evaluated at the TRUE velocities of
the last 40 % against the TRUE friction (``friction_truth``, no bias): held-out NMSE per joint.
Estimator parameters are the shipped defaults except model / prior / bias (and passivity in the
'none' rows).

Baselines, per joint, by least squares (scipy ``least_squares``) on the residual stream the
estimator learns from (the estimator's own front end: ``FrictionResidual`` with the URDF RNEA and
the same ``AccelFilter``, one sample per ``min_sample_interval_s`` = 10 ms, the first 60 %):
Coulomb-viscous ``Fc tanh(v / eps) + Fv v + b`` (eps from a grid) and the sigmoid model of
Makkar et al. ``a1 (tanh(b1 v) - tanh(b2 v)) + a2 tanh(b3 v) + a3 v + b`` (multi-start); the
bias ``b`` is fitted and left out of the prediction, as the D-GP's.
(The fits are dgp_ros/dynamics/baselines.py, shared with the robot demo.)

Usage: bench/robot_arms.py [--quick] [--out DIR]
"""
from __future__ import annotations

import shutil
import sys
import tempfile
import time

import numpy as np  # noqa: E402

import common as C  # noqa: E402
from robot_arms_runs import gmean, LEARN_FRACTION, NAME, run_dataset, SHIPPED  # noqa: E402

TITLE = 'Real robot arms: raw /joint_states in, passive friction out'
PRIORS = ('viscous', 'friction', 'friction+stribeck')
KIND_ORDER = ('full', 'diag')


# ----------------------------------------------------------------------------- report
def row_label(kind, prior, bias):
    if kind == 'ard':
        return ('ARD-GP', 'constant', '-')
    return (C.LABEL[kind], prior, 'on' if bias else 'off')


def plot_dataset(a, D):
    plt = C.plt()
    N = len(D['names'])
    ncol = 4
    nrow = int(np.ceil(N / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.0 * ncol, 3.1 * nrow), squeeze=False)
    b = D['best']
    lab = '' if b is None else ' '.join(row_label(b['kind'], b['prior'], b['bias'])[:2]) + \
        (' + bias' if b['bias'] else '')
    sub = slice(None, None, 8)
    for j in range(N):
        ax = axes[j // ncol, j % ncol]
        v = D['Qh'][:, j]
        o = np.argsort(v)
        if b is not None:
            ax.plot(v[sub], b['pred'][sub, j], '.', ms=2, color='C2', alpha=0.5,
                    label=f'{lab} (D-GP, at held-out qd)')
        ax.plot(v[o], D['pred_sg'][o, j], '-', color='C1', lw=1.2, label='sigmoid (Makkar) LS')
        ax.plot(v[o], D['Fh'][o, j], '-', color='k', lw=0.9, label='truth')
        ax.set_title(f'{D["names"][j]}  NMSE D-GP '
                     f'{C.fmt(b["nmse"][j], 2) if b is not None else "-"} / '
                     f'sigm. {C.fmt(D["nmse_sg"][j], 2)}', fontsize=8)
        ax.set_xlabel('qd [rad/s]', fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if j % ncol == 0:
            ax.set_ylabel('friction [N m]', fontsize=8)
    for j in range(N, nrow * ncol):
        axes[j // ncol, j % ncol].axis('off')
    h, lbl = axes[0, 0].get_legend_handles_labels()
    if N < nrow * ncol:
        axes[-1, -1].legend(h, lbl, loc='center', fontsize=8, markerscale=4)
    else:
        axes[0, 0].legend(fontsize=6, markerscale=3)
    fig.suptitle(f'{D["robot"]} (seed {D["seed"]}): held-out 40 % friction vs velocity, learned '
                 f'online on the first 60 % of a raw /joint_states bag', fontsize=10)
    fig.tight_layout()
    return C.savefig(fig, a.out, f'robot_arms_{D["robot"]}.png')


def nmse_table(D):
    names = D['names']
    short = [n.replace('panda_', '').replace('_joint', '') for n in names]
    hdr = ['model', 'prior', 'bias'] + short + ['geo. mean*', 'prior alone*']
    crit = D['above_noise'] if D['above_noise'].any() else np.ones(len(names), bool)
    rows = []
    rows.append(['truth: friction RMS [N m]', '', ''] + [C.fmt(x) for x in D['friction_rms']]
                + ['', ''])
    rows.append(['friction RMS > noise sd (0.3 N m)?', '', ''] +
                ['yes' if x else 'no' for x in D['above_noise']] + ['', ''])
    for r in D['rows'] + D['extra_rows']:
        lab = list(row_label(r['kind'], r['prior'], r['bias']))
        if r['defaults']:
            lab[0] += ' **(defaults)**'
        if r is D['best']:
            lab[0] += ' **(best)**'
        if r['note']:
            lab[0] += f', {r["note"]}' + (f' (n={r["buffer_n"]})' if 'buffer_n' in r else '')
        if r['error']:
            rows.append(lab + ['**not trained** (below)'] + ['-'] * (len(names) + 1))
            continue
        cells = [C.fmt(x) for x in r['nmse']]
        rows.append(lab + cells + [C.fmt(gmean(r['nmse'][crit])),
                                   C.fmt(gmean(r['prior_nmse'][crit])) if 'prior_nmse' in r
                                   else '-'])
    rows.append([f'Coulomb-viscous LS (n={D["stream_n"]})', '', 'fitted'] +
                [C.fmt(x) for x in D['nmse_cv']] + [C.fmt(gmean(D['nmse_cv'][crit])), ''])
    rows.append([f'sigmoid (Makkar) LS (n={D["stream_n"]})', '', 'fitted'] +
                [C.fmt(x) for x in D['nmse_sg']] + [C.fmt(gmean(D['nmse_sg'][crit])), ''])
    rows.append(['0.5 x sigmoid (the target)', '', ''] + [C.fmt(0.5 * x) for x in D['nmse_sg']]
                + [C.fmt(0.5 * gmean(D['nmse_sg'][crit])), ''])
    rows.append([f'Coulomb-viscous LS on the estimator\'s final buffer (n={D["buffer_n"]})', '',
                 'fitted'] + [C.fmt(x) for x in D['nmse_cv_buf']] +
                [C.fmt(gmean(D['nmse_cv_buf'][crit])), ''])
    rows.append([f'sigmoid (Makkar) LS on the estimator\'s final buffer (n={D["buffer_n"]})', '',
                 'fitted'] + [C.fmt(x) for x in D['nmse_sg_buf']] +
                [C.fmt(gmean(D['nmse_sg_buf'][crit])), ''])
    return C.md_table(hdr, rows)


def timing_table(D):
    hdr = ['model', 'prior', 'bias', 'passivity', 'replay wall / data s', 'msg p99',
           'refits (ok)', 'refit total', 'refit max', 'neg inside', 'neg far', 'neg>tol (in/far)',
           'worst cos']
    rows = []
    for r in D['rows'] + D['extra_rows']:
        t, n = r['timings'], r['neg']
        lab = list(row_label(r['kind'], r['prior'], r['bias']))
        if r['defaults']:
            lab[0] += ' (defaults)'
        if r['note'].startswith('buffer'):
            lab[0] += f', {r["note"]}'
        neg = (['-'] * 4 if n is None else
               [n['s_in'], n['s_far'], f'{n["t_in"]}/{n["t_far"]}', C.fmt(n['min_rel'])])
        rows.append(lab + [r['passivity'], C.fmt(t['wall_per_data_second']),
                           C.fmt_time(t['process_per_msg_p99_s']),
                           f'{r["refits"]["ok"]}/{r["refits"]["started"]}',
                           C.fmt_time(t['refit_total_s']), C.fmt_time(t['refit_max_s'])] + neg)
    return C.md_table(hdr, rows)


def status_notes(D) -> str:
    """Return the estimator's final status of each row that did not end 'ok' (or never trained)."""
    out = []
    for r in D['rows'] + D['extra_rows']:
        st = r['status']
        if r['error'] or st.get('level', 0) > 0:
            lab = ' '.join(row_label(r['kind'], r['prior'], r['bias'])) + \
                (f' ({r["note"]})' if r['note'] else '')
            what = r['error'] or st.get('message', '')
            out.append(f'- {lab}: ' + ('**never trained**: ' if r['error'] else
                                       f'ended at level {st.get("level")}: ') + _cell(what, 300))
    if not out:
        return ''
    return 'Estimator status at the end of the replay, where it was not ok:\n\n' + \
        '\n'.join(out) + '\n'


def _cell(text, n):
    """``text`` as one markdown table cell, at most ``n`` characters."""
    t = ' '.join(str(text).split()).replace('|', '/')
    return t if len(t) <= n else t[:n - 3] + '...'


def _warning(message):
    """Return the part of a status message giving the negative-power reason (else all of it)."""
    i = message.find('data are not damping')
    return message if i < 0 else message[i:]


def target_check(D, r, ref='nmse_sg'):
    """(met, worst ratio DGP / sigmoid over the joints above the noise, joints that fail)."""
    crit = D['above_noise']
    ratio = r['nmse'] / D[ref]
    ratio = np.where(np.isfinite(ratio), ratio, np.inf)      # not trained: fails
    fails = [D['names'][j] for j in range(len(crit)) if crit[j] and not ratio[j] <= 0.5]
    worst = float(np.max(ratio[crit])) if crit.any() else float('nan')
    return not fails, worst, fails


def main(argv=None) -> int:
    a = C.parse_args(__doc__.splitlines()[0], argv)
    t_start = time.perf_counter()
    from dgp_ros.dynamics import example_robot_urdf
    if a.quick:
        robots, seeds, duration, k_pass, big = ['panda'], [0], 20.0, 10_000, 0
        configs = [SHIPPED, ('full', 'viscous', False), ('ard', 'viscous', False)]
    else:
        robots, seeds, duration, k_pass, big = ['panda', 'ur5'], [0, 1, 2], 20.0, 100_000, 1000
        configs = [(k, p, b) for k in KIND_ORDER for p in PRIORS for b in (False, True)] + \
            [('ard', 'viscous', False)]
    work = tempfile.mkdtemp(prefix='dgp_robot_arms_')
    results = {}
    try:
        for robot in robots:
            urdf = example_robot_urdf(robot)
            for seed in seeds:
                results[(robot, seed)] = run_dataset(
                    a, robot, seed, duration, work, urdf, configs, k_pass,
                    extras=(seed == seeds[0]), big_buffer=big, quick=a.quick)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    # ---------------------------------------------------------------- plots (first seed)
    plots = {robot: plot_dataset(a, results[(robot, seeds[0])]) for robot in robots}
    wall = time.perf_counter() - t_start

    # ---------------------------------------------------------------- section
    L = [C.header_lines(TITLE, 'bench/robot_arms.py', a.quick, wall)]
    L.append(
        f'Data: `simulate_arm(robot, {duration:g} s, seed)` (dgp_ros/dynamics/arm_sim.py): 1 kHz '
        'jittered stamps, raw joint torque = rigid body (pinocchio RNEA) + friction (Coulomb + '
        'Stribeck + viscous, 0.3-1.3 N m) + constant sensor bias + 0.3 N m noise, common '
        'standstills every 5 s; written as a raw `/joint_states` bag (Panda: with its two finger '
        "joints; UR5: in the driver's order). The first 60 % is a bag of its own, learned "
        "online by `dgp_ros.apps.replay.run` (the node's code path) with `inverse_dynamics=urdf`, "
        '`joints` selected, `save_model=`; every other estimator parameter is the shipped default '
        '(buffer 200, one learned sample per 10 ms, refit every 10 s, passivity projected). The '
        'saved model (`load_model`) predicts the TRUE friction at the TRUE velocities of the last '
        '40 % (held out): NMSE per joint. Baselines: least squares per joint on the residual '
        'stream the estimator learns from (its front end: URDF RNEA + the same acceleration '
        'filter, one sample per 10 ms of the 60 %), with a bias term that is left out of the '
        "prediction (as the D-GP's). The sigmoid model is Makkar et al.'s "
        '`a1 (tanh(b1 v) - tanh(b2 v)) + a2 tanh(b3 v) + a3 v + b` (8 starts); Coulomb-viscous '
        '`Fc tanh(v / eps) + Fv v + b` (eps from a grid). The D-GP keeps only its 200-sample '
        "buffer; the baselines see the whole stream, and once more only the estimator's final "
        'buffer (its learned samples, the same for every model: selection does not depend on '
        'the model). ' + (f'The best configuration is also run with `buffer_size={big}` (not '
                          'the default) and with passivity `none`. ' if big else '') +
        'ARD-GP has its constant prior (one row): '
        'it cannot separate the bias, which it learns as friction. '
        f'Seeds {seeds}; detailed tables for seed {seeds[0]}.\n')
    L.append('`*` geometric mean over the joints whose friction RMS on the held-out part '
             'exceeds the torque noise sd (0.3 N m), which is what "friction exceeds the noise" '
             'means in the targets; "prior alone" is the same for the model\'s fitted prior mean '
             'without the GP correction (`mean_.force`). **(best)**: lowest geometric mean among '
             'the D-GP rows with default parameters.\n')

    targets = []
    for robot in robots:
        D = results[(robot, seeds[0])]
        L.append(f'### {robot}: held-out NMSE per joint (seed {seeds[0]})\n')
        bias_txt = ', '.join(f'{C.fmt(x, 2)}' for x in D['sim']['bias'])
        bh = D['best']['bias_hat'] if D['best'] is not None else []
        L.append(f"True bias [N m]: {bias_txt}; the best model's learned bias: "
                 f'{", ".join(C.fmt(x, 2) for x in bh) or "-"}. Raw `qd . effort < 0` on '
                 f'{100 * D["sim"]["raw_negative_power_fraction"]:.0f} % of the samples, '
                 f'residual `qd . (effort - tau_rb) < 0` on '
                 f'{100 * D["sim"]["nonpassive_fraction"]:.1f} %. Residual stream: '
                 f'{D["stream_n"]} samples; baselines fitted in '
                 f'{C.fmt_time(D["base_seconds"])} (all joints, both models).\n')
        cov = D['coverage'] or {'all': float('nan'), 'per': []}
        big_rows = [r for r in D['extra_rows'] if 'coverage' in r]
        L.append(f'Coverage: the estimator\'s final buffer (n={D["buffer_n"]}, the newest novel '
                 'samples: a window) spans a velocity box that holds '
                 f'{100 * cov["all"]:.0f} % of the held-out samples in every joint (per joint '
                 f'{", ".join(f"{100 * x:.0f}" for x in cov["per"])} %)' +
                 ''.join(f'; with {r["note"]} (n={r["buffer_n"]}) '
                         f'{100 * r["coverage"]["all"]:.0f} %' for r in big_rows) +
                 '. Outside its box a model extrapolates: the parametric priors do it well, the '
                 'GP correction does not.\n')
        L.append(nmse_table(D))
        notes = status_notes(D)
        if notes:
            L.append(notes)
        L.append(f'![{robot} friction vs velocity]({C.rel(plots[robot], a.out)})\n')
        L.append(f'### {robot}: replay time and negative power (seed {seeds[0]})\n')
        L.append(f'Replay of the {LEARN_FRACTION * duration:g} s learning bag: wall time per '
                 'second of data and refits from `summary["timings"]`. Negative power: '
                 f'`qd . tau_hat < 0` of the saved model at {k_pass} random velocities in the '
                 f'box of the learning data and {k_pass} in the box 100x as large, outside 2x '
                 '(`neg` exact, `neg>tol` below `-1e-12 |qd| |tau_hat|`, worst cos = smallest '
                 '`qd . tau_hat / (|qd| |tau_hat|)`). The `none` rows show that without '
                 'enforcement the count can be nonzero.\n')
        L.append(timing_table(D))
    if len(seeds) > 1:
        L.append(f'### Across seeds: geometric-mean NMSE* per seed {seeds}\n')
        hdr = ['model', 'prior', 'bias'] + [f'{r}' for r in robots] + ['rank (mean over all)']
        keys = [(r['kind'], r['prior'], r['bias']) for r in results[(robots[0], seeds[0])]['rows']]
        score = {}
        cells = {}

        def per_seed(robot, pick):
            """Geometric-mean NMSE* of pick(run) per seed of ``robot`` (above the noise)."""
            out = []
            for seed in seeds:
                D = results[(robot, seed)]
                out.append(gmean(pick(D)[D['above_noise'] if D['above_noise'].any()
                                         else slice(None)]))
            return out
        for key in keys:
            cells[key] = []
            vals = []
            for robot in robots:
                g = per_seed(robot, lambda D: next(x for x in D['rows'] if (
                    x['kind'], x['prior'], x['bias']) == key)['nmse'])
                cells[key].append(' / '.join(C.fmt(x, 2) for x in g))
                vals += g
            v = np.asarray(vals, float)
            score[key] = float(np.mean(np.log(v))) if np.all(np.isfinite(v)) else np.inf
        ranked = sorted(keys, key=lambda k: score[k])
        rows = []
        for key in keys:
            lab = list(row_label(*key))
            if key == SHIPPED:
                lab[0] += ' (defaults)'
            rows.append(lab + cells[key] + [ranked.index(key) + 1 if np.isfinite(score[key])
                                            else '- (not trained in every run)'])
        for nm, fld in (('sigmoid (Makkar) LS, stream', 'nmse_sg'),
                        ('Coulomb-viscous LS, stream', 'nmse_cv'),
                        ('sigmoid (Makkar) LS, final buffer', 'nmse_sg_buf'),
                        ('Coulomb-viscous LS, final buffer', 'nmse_cv_buf')):
            rows.append([nm, '', 'fitted'] + [' / '.join(C.fmt(
                x, 2) for x in per_seed(robot, lambda D: D[fld])) for robot in robots] + [''])
        L.append(C.md_table(hdr, rows))
        results['_ranked'] = ranked

    # ---------------------------------------------------------------- targets
    for robot in robots:
        D = results[(robot, seeds[0])]
        for which, r in (('best', D['best']),
                         ('defaults', next((x for x in D['rows'] if x['defaults']), None))):
            if r is None:
                continue
            lab = ' '.join(row_label(r['kind'], r['prior'], r['bias'])[:2]) + \
                (' + bias' if r['bias'] else '')
            for ref, ref_txt in (('nmse_sg', f'the residual stream (n={D["stream_n"]})'),
                                 ('nmse_sg_buf', "the estimator's final buffer "
                                                 f'(n={D["buffer_n"]})')):
                met_all, worst_all, fail_all, n_joints = True, 0.0, {}, 0
                for seed in seeds:
                    Ds = results[(robot, seed)]
                    rs = next(x for x in Ds['rows']
                              if (x['kind'], x['prior'], x['bias']) == (r['kind'], r['prior'],
                                                                        r['bias']))
                    met, worst, fails = target_check(Ds, rs, ref)
                    met_all &= met
                    worst_all = max(worst_all, worst)
                    if fails:
                        fail_all[seed] = [f.replace('panda_', '') for f in fails]
                    n_joints += int(Ds['above_noise'].sum())
                targets.append([f'{robot}, {which} ({lab}): held-out NMSE <= 0.5 x sigmoid '
                                f'refit on {ref_txt}, on every joint whose friction exceeds the '
                                f'noise ({n_joints} joint-runs over seeds {seeds})',
                                'met' if met_all else '**missed**',
                                f'worst D-GP / sigmoid NMSE ratio {C.fmt(worst_all)}' +
                                ('; fails on ' + '; '.join(
                                    f'seed {sd}: {", ".join(f)}' for sd, f in fail_all.items())
                                 if fail_all else '')])
    allneg = [(D['robot'], r) for key, D in results.items() if key != '_ranked'
              for r in D['rows'] + D['extra_rows']
              if r['passivity'] != 'none' and r['neg'] is not None]
    tot = sum(r['neg']['s_in'] + r['neg']['s_far'] for _, r in allneg)
    targets.append([f'0 negative power in {k_pass} random velocities (every saved model, '
                    f'passivity projected: {len(allneg)} models x {k_pass} inside + {k_pass} far '
                    'outside)',
                    'met' if tot == 0 else '**missed**', f'{tot} negative'])
    for robot in robots:
        D = results[(robot, seeds[0])]
        w = D['whole']['timings'] if D.get('whole') else None
        secs = duration if not a.quick else LEARN_FRACTION * duration
        if w is not None:
            targets.append([f'a {secs:g} s, {len(D["names"])}-joint, 1 kHz bag ({robot}) '
                            'replays in at most 10x real time (wall <= 10 x data duration, '
                            'shipped defaults)' + (' (quick: the learning bag)' if a.quick
                                                   else ''),
                            'met' if w['wall_per_data_second'] <= 10 else '**missed**',
                            f'{C.fmt(w["wall_time_s"])} s wall for {secs:g} s of data '
                            f'({C.fmt(w["wall_per_data_second"])}x real time)'])
        raw = D['raw']
        why = _warning(raw['message'])
        ok = raw['level'] >= 1 and 'data are not damping' in why and 'inverse_dynamics' in why
        targets.append([f'{robot}: raw effort (gravity in it), no inverse dynamics -> WARN with '
                        'its reason', 'met' if ok else '**missed**',
                        f'level {raw["level"]}, learned qd.tau < 0 on '
                        f'{100 * raw["learned_neg"]:.0f} %: "{_cell(why, 200)}"'])
    L.append('### Targets\n')
    L.append('The live-node target (the same through the node fed by `dgp-play`) and the README '
             'target are checked by the tests, not here.\n')
    L.append(C.md_table(['target', 'status', 'measured'], targets))
    C.write_section(a.out, NAME, '\n'.join(L))
    C.log(f'{NAME}: wrote section and {", ".join(plots.values())} in {wall:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())

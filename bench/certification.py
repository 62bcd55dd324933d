#!/usr/bin/env python3
"""
Certified by default: accuracy on real data, certification time, violations.

1. Real Franka Panda friction residual (``panda_log_train.npz`` of the shared ``panda_real``
   folder; ``--data`` or env ``DGP_PANDA_REAL``, default ``<repo>/../shared/data/panda_real``, then
   ``/work/shared/data/panda_real``; skipped with the reason when absent). Learn on t < 7.5 s
   (n evenly spaced samples of ``tau_friction_offline`` with ``Qd = qd``), predict every sample of
   7.5-12.6 s. Per prior setting, model and n: ``projected`` with hyper-parameter optimization,
   ``certified`` at those hyper-parameters (``fit(optimize=False)``: what certification costs),
   ``certified`` with its own optimization. Held-out NMSE per joint and the ratios.
2. A320 flight envelope (``sim_bridge.FrozenAero``): 500 random samples of the envelope, 3000
   fresh points of it; ``certified`` (the envelope declared, and the data box only) against the
   unconstrained model at the same hyper-parameters.
3. Violations: random velocities per model (10^6 in full mode) inside the data box and in the box
   10x its size: answers with ``q^T tau < 0`` beyond rounding, and the proven property itself on
   the proven domain (least eigenvalue of the symmetric part of ``D`` for 'psd', ``q^T D q`` on
   the outer box for 'passive-on-domain').

Usage: bench/certification.py [--quick] [--out DIR] [--data DIR]
"""
from __future__ import annotations

import os
import sys

import numpy as np

import common as C  # noqa: E402
from common import timed  # noqa: E402

NAME = 'certification'
TITLE = 'Certified by default: accuracy on real data, proof time, violations'
SPLIT_S = 7.5
PRIORS = (('friction+stribeck', True), ('viscous', False))
DATA_FILE = 'panda_log_train.npz'


def _extra(p):
    p.add_argument('--data', default=None,
                   help='folder of panda_log_train.npz (default: env DGP_PANDA_REAL, else '
                        '<repo>/../shared/data/panda_real, else /work/shared/data/panda_real)')


def panda_dir(arg=None):
    """Return the real-Panda folder or None: --data, else DGP_PANDA_REAL, else the defaults."""
    given = arg or os.environ.get('DGP_PANDA_REAL')
    cands = [given] if given else [os.path.join(C.REPO, '..', 'shared', 'data', 'panda_real'),
                                   '/work/shared/data/panda_real']
    for c in cands:
        if c and os.path.isfile(os.path.join(c, DATA_FILE)):
            return os.path.abspath(c)
    return None


def _chunks(X, k=50_000):
    for i in range(0, len(X), k):
        yield X[i:i + k]


def violations(model, lo, hi, k, seed):
    """
    Count violations at k random velocities inside [lo, hi] and k in the box 10x its size.

    Returns {'answers': (in, out), 'property': (in, out), 'worst': float}: answers with
    ``q^T tau < -1e-12 |q| |tau|`` (``predict``), and points of the proven domain where the
    proven property fails (beyond 1e-12 relative): 'psd' the least eigenvalue of the symmetric
    part of D, 'passive-on-domain' ``q^T D q`` of the unblended posterior on the outer box.
    """
    rng = np.random.default_rng(seed)
    cert = model.certificate()
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    ans, prop, worst = [], [], np.inf
    for f in (1.0, 10.0):
        na = npr = 0
        X = rng.uniform(c - f * h, c + f * h, (k, lo.size))
        for Xc in _chunks(X):
            # one pass: the answers and the published damping matrices of the same queries
            tau, _, D = model.predict_with_damping(Xc, return_var=False,
                                                   return_damping=cert.guarantee == 'psd')
            p = np.einsum('ij,ij->i', Xc, tau)
            na += int(np.sum(p < -1e-12 * np.linalg.norm(Xc, axis=1)
                             * np.linalg.norm(tau, axis=1)))
            if cert.guarantee == 'psd':
                lam = np.linalg.eigvalsh(0.5 * (D + np.swapaxes(D, 1, 2)))[:, 0]
                rel = lam / np.maximum(np.abs(D).max(axis=(1, 2)), 1e-300)
            elif cert.guarantee == 'passive-on-domain':
                olo, ohi = (np.asarray(v) for v in cert.details['outer_box'])
                Z = olo + (ohi - olo) * rng.uniform(size=Xc.shape)   # the proven box itself
                D = model.posterior_.damping(Z)
                P = np.einsum('ki,kij,kj->k', Z, D, Z)
                rel = P / np.maximum(np.einsum('ki,kij,kj->k', np.abs(Z), np.abs(D),
                                               np.abs(Z)), 1e-300)
            else:
                rel = np.zeros(1)
            npr += int(np.sum(rel < -1e-12))
            worst = min(worst, float(rel.min()))
        ans.append(na)
        prop.append(npr)
    return {'answers': tuple(ans), 'property': tuple(prop), 'worst': worst}


# ============================================================================ 1. real Panda
def panda_part(a, path):
    from dgp_ros.gp import make_model
    d = np.load(os.path.join(path, DATA_FILE), allow_pickle=False)
    t, qd, tau = d['t'], d['qd'], d['tau_friction_offline']
    tr = t < SPLIT_S
    Qa, Ta, Qh, Th = qd[tr], tau[tr], qd[~tr], tau[~tr]
    ns = (100,) if a.quick else (200, 500)
    priors = PRIORS[:1] if a.quick else PRIORS
    k_pass = 10_000 if a.quick else 100_000
    rows = []
    for prior, bias in priors:
        for n in ns:
            idx = np.unique(np.linspace(0, len(Qa) - 1, n).round().astype(int))
            Q, T = Qa[idx], Ta[idx]
            for kind in ('full', 'diag'):
                kw = {'prior': prior, 'bias': bias}
                if a.quick:
                    kw.update(n_restarts=0, max_opt_samples=100)
                C.log(f'panda {prior} bias={bias} n={n} {kind}: projected (optimized)')
                proj, t_proj = timed(lambda: make_model(kind, passivity='projected',
                                                        **kw).fit(Q, T))
                hp = proj.hyperparams_
                cert, t_cert = timed(lambda: make_model(kind, passivity='certified',
                                                        hyperparams=hp, **kw)
                                     .fit(Q, T, optimize=False))
                C.log(f'panda {prior} bias={bias} n={n} {kind}: certified (optimized)')
                own, t_own = timed(lambda: make_model(kind, passivity='certified',
                                                      **kw).fit(Q, T))
                r = {'prior': prior, 'bias': bias, 'n': n, 'kind': kind,
                     'nmse_p': C.nmse(proj.predict(Qh), Th),
                     'nmse_c': C.nmse(cert.predict(Qh), Th),
                     'nmse_o': C.nmse(own.predict(Qh), Th),
                     't_proj': t_proj, 't_cert': t_cert, 't_own': t_own,
                     'cert': cert.certificate(), 'own_cert': own.certificate()}
                # 10^6 per box at the smaller n (10^6 answers of a 7-joint model at n = 500
                # take about 7 min per box on this machine: 10^5 there)
                k = 1_000_000 if not a.quick and n == ns[0] else k_pass
                C.log(f'panda {prior} n={n} {kind}: {k} random velocities x 2 boxes')
                r['viol'] = violations(cert, Q.min(axis=0), Q.max(axis=0), k, 1)
                r['k'] = k
                rows.append(r)
    return {'rows': rows, 'n_held': len(Qh), 'n_learn_pool': len(Qa), 'names':
            [f'j{i + 1}' for i in range(qd.shape[1])]}


# ============================================================================ 2. A320
def a320_part(a):
    from dgp_ros.gp import make_model
    from paper_experiments import VOLUME_HI, VOLUME_LO
    from sim_bridge import FrozenAero, SimConfig
    aero = FrozenAero(SimConfig())
    rng = np.random.default_rng(4242)
    k_test = 500 if a.quick else 3000
    Qt = C.random_points(rng, VOLUME_LO, VOLUME_HI, k_test)
    Tt = aero.tau(Qt)
    ns = (100,) if a.quick else (200, 500)
    seeds = (0,) if a.quick else (0, 1, 2)
    k_pass = 10_000 if a.quick else 1_000_000
    rows = []
    for n in ns:
        for seed in seeds:
            r0 = np.random.default_rng(100 * seed + n)
            Q = C.random_points(r0, VOLUME_LO, VOLUME_HI, n)
            T = aero.tau(Q)
            for kind in ('full', 'diag'):
                kw = {'n_restarts': 0, 'max_opt_samples': 100} if a.quick else {}
                base, t_base = timed(lambda: make_model(kind, passivity='none', random_state=seed,
                                                        **kw).fit(Q, T))
                hp = base.hyperparams_
                nb = C.nmse(base.predict(Qt), Tt)
                for declared in (True, False):
                    od = (VOLUME_LO, VOLUME_HI) if declared else None
                    m, t = timed(lambda: make_model(kind, passivity='certified', hyperparams=hp,
                                                    operating_domain=od, **kw)
                                 .fit(Q, T, optimize=False))
                    r = {'n': n, 'seed': seed, 'kind': kind, 'declared': declared,
                         'ratio': C.nmse(m.predict(Qt), Tt) / nb, 't': t, 't_base': t_base,
                         'cert': m.certificate(), 'nmse_base': nb}
                    if n == ns[-1] and seed == 0 and declared:
                        C.log(f'A320 n={n} {kind} declared={declared}: {k_pass} velocities x 2')
                        r['viol'] = violations(m, Q.min(axis=0), Q.max(axis=0), k_pass, 2)
                        r['k'] = k_pass
                    rows.append(r)
    return {'rows': rows, 'k_test': k_test}


# ============================================================================ report
def _cert_cell(c):
    s = f'{c.method}' + ('' if c.certified else ' (not certified)')
    rep = c.details.get('repaired_points')
    return s + (f', {rep} cuts' if rep else '')


def report(a, P, A, wall, data_path):
    L = [C.header_lines(TITLE, f'bench/{NAME}.py', a.quick, wall), '']
    tgt = []
    # ---- Panda
    L.append('### Real Franka Panda: held-out NMSE, certified / projected\n')
    if P is None:
        L.append(f'Skipped: `{DATA_FILE}` not found (`--data`, `DGP_PANDA_REAL`, '
                 '`<repo>/../shared/data/panda_real`, `/work/shared/data/panda_real`).\n')
    else:
        L.append(f'Data: `{data_path}`. Learn on t < {SPLIT_S} s ({P["n_learn_pool"]} samples, '
                 f'n of them evenly spaced), predict all {P["n_held"]} samples of t >= '
                 f'{SPLIT_S} s; target `tau_friction_offline`, `Qd = qd`. "certified" is fitted '
                 "at the projected fit's hyper-parameters (`hyperparams=`, "
                 '`fit(optimize=False)`); "own opt." is certified with its own '
                 'hyper-parameter optimization. Ratio = certified NMSE / projected NMSE.\n')
        rows = []
        for r in P['rows']:
            ratio = r['nmse_c'] / r['nmse_p']
            own = r['nmse_o'] / r['nmse_p']
            rows.append([f'{r["prior"]}, bias {r["bias"]}', r['n'], C.LABEL[r['kind']],
                         C.fmt(float(np.mean(r['nmse_p']))), C.fmt(float(np.mean(r['nmse_c']))),
                         C.fmt(float(np.mean(r['nmse_c']) / np.mean(r['nmse_p']))),
                         ' / '.join(C.fmt(x) for x in ratio), C.fmt(float(ratio.max())),
                         C.fmt(float(np.mean(r['nmse_o']) / np.mean(r['nmse_p']))),
                         C.fmt(float(own.max())), _cert_cell(r['cert'])])
        L.append(C.md_table(['prior', 'n', 'model', 'NMSE projected (mean)',
                             'NMSE certified (mean)', 'ratio of means',
                             'ratio per joint ' + ' / '.join(P['names']), 'worst joint',
                             'own opt.: ratio of means', 'own opt.: worst joint',
                             'certificate'], rows))
        L.append('Per-joint NMSE (projected | certified):\n')
        rows = [[f'{r["prior"]}, bias {r["bias"]}', r['n'], C.LABEL[r['kind']],
                 ' / '.join(C.fmt(x) for x in r['nmse_p']),
                 ' / '.join(C.fmt(x) for x in r['nmse_c'])] for r in P['rows']]
        L.append(C.md_table(['prior', 'n', 'model', 'projected', 'certified'], rows))
        L.append('### Real Panda: certification time (same run as the fits)\n')
        rows = [[f'{r["prior"]}, bias {r["bias"]}', r['n'], C.LABEL[r['kind']],
                 C.fmt_time(r['t_proj']), C.fmt_time(r['t_cert']),
                 C.fmt_time(float(r['cert'].details.get('seconds', np.nan))),
                 C.fmt_time(r['t_own']), C.fmt(r['t_own'] / r['t_proj'])] for r in P['rows']]
        L.append(C.md_table(['prior', 'n', 'model', 'projected fit (optimized)',
                             'certified fit at fixed hyper-parameters', 'of which the proof',
                             'certified fit (optimized)', 'certified / projected (optimized)'],
                            rows))
        for kind in ('full', 'diag'):
            rs = [r for r in P['rows'] if r['kind'] == kind]
            means = [np.mean(r['nmse_c']) / np.mean(r['nmse_p']) for r in rs]
            worst = [float((r['nmse_c'] / r['nmse_p']).max()) for r in rs]
            tgt.append([f'Panda, {C.LABEL[kind]}: certified <= 1.1x projected (mean NMSE), '
                        'every setting', 'met' if max(means) <= 1.1 else '**missed**',
                        f'worst {max(means):.3f}x'])
            tgt.append([f'Panda, {C.LABEL[kind]}: certified <= 1.3x projected on every joint',
                        'met' if max(worst) <= 1.3 else '**missed**',
                        f'worst {max(worst):.3f}x'])
        big = [r for r in P['rows'] if r['kind'] == 'full' and r['n'] == max(
            x['n'] for x in P['rows'])]
        if big:
            tc = max(r['t_cert'] for r in big)
            tot = max(r['t_own'] / r['t_proj'] for r in big)
            tgt.append([f'N = 7, n = {big[0]["n"]}, Full: certification <= 10 s',
                        'met' if tc <= 10 else '**missed**', f'{tc:.2f} s'])
            tgt.append([f'N = 7, n = {big[0]["n"]}, Full: certified fit <= 2x the projected '
                        'fit (both optimized)', 'met' if tot <= 2 else '**missed**',
                        f'{tot:.2f}x'])
    # ---- A320
    L.append('### A320 envelope: 500 random samples, fresh points of the envelope\n')
    L.append(f'{A["k_test"]} fresh uniform points of the flown envelope; ratio = certified NMSE / '
             'unconstrained NMSE at the same hyper-parameters, per output (drag / -side / '
             'lift), worst over seeds. "declared": `operating_domain` = the envelope.\n')
    rows = []
    groups = {}
    for r in A['rows']:
        groups.setdefault((r['n'], r['kind'], r['declared']), []).append(r)
    for (n, kind, declared), rs in groups.items():
        ratio = np.max([r['ratio'] for r in rs], axis=0)
        rows.append([n, C.LABEL[kind], 'declared' if declared else 'data box', len(rs),
                     ' / '.join(C.fmt(x) for x in ratio),
                     C.fmt_time(max(r['t'] for r in rs)),
                     C.fmt_time(float(np.median([r['t_base'] for r in rs]))),
                     '; '.join(sorted({_cert_cell(r['cert']) for r in rs}))])
    L.append(C.md_table(['n', 'model', 'domain', 'seeds', 'ratio (worst seed)',
                         'certification (worst seed)', 'unconstrained fit (median)',
                         'certificate'], rows))
    for n in sorted({r['n'] for r in A['rows']}):
        dec = [r for r in A['rows'] if r['n'] == n and r['declared']]
        worst = float(np.max([r['ratio'] for r in dec]))
        tgt.append([f'A320, n = {n}, envelope declared: certified <= 1.2x unconstrained on '
                    'every output', 'met' if worst <= 1.2 else '**missed**',
                    f'worst {worst:.3f}x'])
        full = [r for r in A['rows'] if r['n'] == n and r['kind'] == 'full']
        tmax = max(r['t'] for r in full)
        tgt.append([f'N = 3, n = {n}, Full: certification <= 1 s',
                    'met' if tmax <= 1 else '**missed**', f'{tmax:.2f} s (worst of '
                    f'{len(full)})'])
    # ---- violations
    L.append('### Violations\n')
    rows = []
    allv = []
    for src, rs in (('Panda', [] if P is None else P['rows']), ('A320', A['rows'])):
        for r in rs:
            if 'viol' not in r:
                continue
            v = r['viol']
            allv.append(v)
            what = (f'{r["prior"]}, n = {r["n"]}' if src == 'Panda' else
                    f'n = {r["n"]}, {"declared" if r["declared"] else "data box"}')
            rows.append([src, what, C.LABEL[r['kind']], r['cert'].guarantee, f'{r["k"]:.0e}',
                         f'{v["answers"][0]} / {v["answers"][1]}',
                         f'{v["property"][0]} / {v["property"][1]}', C.fmt(v['worst'])])
    L.append('Per model: random velocities inside the data box and in the box 10x its size. '
             '"answers": `predict` with `q^T tau < -1e-12 |q| |tau|`; "property": points where '
             'the proven property fails beyond 1e-12 relative (psd: least eigenvalue of the '
             'symmetric part of `D`; passive-on-domain: `q^T D q` of the posterior at as many '
             'uniform points of the proven outer box); "worst": the smallest relative value '
             'seen (>= 0 up to rounding).\n')
    L.append(C.md_table(['data', 'setting', 'model', 'guarantee', 'points per box',
                         'answers (in / out)', 'property (in / out)', 'worst'], rows))
    bad = sum(sum(v['answers']) + sum(v['property']) for v in allv)
    tgt.append(['0 violations of the proven property and 0 non-passive answers',
                'met' if bad == 0 else '**missed**', f'{bad} in {len(allv)} models'])
    L += ['### Targets', '', C.md_table(['target', 'status', 'measured'], tgt)]
    return '\n'.join(L)


def main(argv=None) -> int:
    return C.panda_a320_main(NAME, argv, _extra, panda_dir, panda_part, a320_part, report)


if __name__ == '__main__':
    sys.exit(main())

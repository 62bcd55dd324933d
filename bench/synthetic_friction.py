#!/usr/bin/env python3
"""
Synthetic 2-DOF joint friction: accuracy vs n and passivity of ARD-GP / Diag-D-GP / Full-D-GP.

Ground truth (passive by construction, ``qd^T tau(qd) >= 0`` for every ``qd``): per joint a
smoothed Coulomb + Stribeck + viscous friction

    f_i(v) = (Fc_i + (Fs_i - Fc_i) exp(-(v / vs_i)^2)) tanh(v / eps) + b_i v      (v f_i(v) >= 0)

plus a velocity-dependent symmetric cross-damping ``c(qd) [[1, rho], [rho, 1]] qd`` with
``c(qd) > 0`` and ``|rho| < 1`` (positive semidefinite, dissipative coupling) and a gyroscopic,
power-neutral coupling ``g cos(qd_2) [qd_2, -qd_1]``. Measurements add Gaussian noise.

Protocol: n training samples uniform in [-2, 2]^2 rad/s, NMSE per output on 4000 noise-free test
points of the same box; each model is fitted once with hyper-parameter optimization and then in
every passivity mode at those hyper-parameters (bench.common.fit_all_modes). Passivity: the
fraction of ``qd^T tau_hat(qd) < 0`` at random points inside the data box and far outside it
(a box 100x the data range, minus 2x the data box).

Usage: bench/synthetic_friction.py [--quick] [--out DIR]
"""
from __future__ import annotations

import sys
import time

import numpy as np  # noqa: E402

import common as C  # noqa: E402

NAME = 'synthetic_friction'
BOX = 2.0            # rad/s
NOISE = 0.05         # Nm
FC = np.array([1.0, 0.6])
FS = np.array([1.6, 1.0])
VS = np.array([0.15, 0.25])
B = np.array([0.8, 0.5])
EPS = 0.02
RHO, C0, G = 0.8, 0.3, 0.4


def truth(Q: np.ndarray) -> np.ndarray:
    """Noise-free friction torque (k, 2) at joint velocities Q (k, 2)."""
    Q = np.atleast_2d(Q)
    f = (FC + (FS - FC) * np.exp(-(Q / VS) ** 2)) * np.tanh(Q / EPS) + B * Q
    c = C0 * (1.0 + 0.5 * np.sin(2.0 * Q[:, 0]))[:, None]
    S = np.array([[1.0, RHO], [RHO, 1.0]])
    coup = c * (Q @ S.T)
    gyro = G * np.cos(Q[:, 1])[:, None] * np.column_stack([Q[:, 1], -Q[:, 0]])
    return f + coup + gyro


def sample(rng, n):
    Q = rng.uniform(-BOX, BOX, (n, 2))
    return Q, truth(Q) + NOISE * rng.standard_normal((n, 2))


def main(argv=None) -> int:
    a = C.parse_args(__doc__.splitlines()[0], argv)
    t_start = time.perf_counter()
    if a.quick:
        ns, seeds, k_pass = [20, 40], [0], 5_000
    else:
        ns, seeds, k_pass = [20, 50, 100, 200, 500], [0, 1, 2], 200_000
    rng_test = np.random.default_rng(12345)
    Qtest = rng_test.uniform(-BOX, BOX, (4000, 2))
    Ttest = truth(Qtest)
    lo, hi = np.full(2, -BOX), np.full(2, BOX)
    # truth is passive: check it on the same kind of points
    Pin = C.random_points(rng_test, lo, hi, k_pass)
    Pfar = C.far_points(rng_test, lo, hi, k_pass)
    truth_neg = int((C.power(Pin, truth(Pin)) < 0).sum() + (C.power(Pfar, truth(Pfar)) < 0).sum())

    combos = [(k, m) for k in C.KINDS for m in C.modes_for(k)]
    res = {c: {n: [] for n in ns} for c in combos}      # NMSE (N,) per seed
    cert = {c: {n: [] for n in ns} for c in combos}     # certificate seconds
    viol = {c: [0, 0, 0, 0] for c in combos}            # in strict, far strict, in tol, far tol
    certified_flags = {c: [] for c in combos}
    scales = {c: {n: [] for n in ns} for c in combos}
    fit_s = {c: {n: [] for n in ns} for c in combos}
    n_pass = 0
    for seed in seeds:
        for n in ns:
            if not a.quick and n > 100 and seed != seeds[0]:
                continue            # time budget: seed 0 only above n = 100
            rng = np.random.default_rng(1000 * seed + n)
            Q, T = sample(rng, n)
            for kind in C.KINDS:
                C.log(f'{NAME}: seed {seed} n {n} {kind}')
                fits = C.fit_all_modes(kind, Q, T, random_state=seed,
                                       **({'n_restarts': 0, 'max_boxes': 2000} if a.quick
                                          else {}))
                for mode, (m, sec) in fits.items():
                    c = (kind, mode)
                    res[c][n].append(C.nmse(m.predict(Qtest), Ttest))
                    cs = C.cert_summary(m)
                    cert[c][n].append(cs['seconds'])
                    certified_flags[c].append(cs['certified'])
                    scales[c][n].append(cs['scale'])
                    fit_s[c][n].append(sec)
                    # passivity at the largest n of every seed (the hardest case for the bounds)
                    if n == ns[-1] or a.quick:
                        prng = np.random.default_rng(7 + seed)
                        s1, t1, _ = C.negative_power_count(
                            m, C.random_points(prng, lo, hi, k_pass))
                        s2, t2, _ = C.negative_power_count(m, C.far_points(prng, lo, hi, k_pass))
                        v = viol[c]
                        v[0] += s1
                        v[1] += s2
                        v[2] += t1
                        v[3] += t2
            if (n == ns[-1] or a.quick) and (a.quick or n <= 100 or seed == seeds[0]):
                n_pass += 1

    wall = time.perf_counter() - t_start
    # ---------------------------------------------------------------- plots
    plt = C.plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for j, ax in enumerate(axes):
        for c in combos:
            med = [np.median([r[j] for r in res[c][n]]) for n in ns]
            ax.loglog(ns, med, C.MODE_STYLE[c[1]], color=C.KIND_COLOR[c[0]], marker='o', ms=3,
                      label=f'{C.LABEL[c[0]]} {c[1]}')
        ax.set_xlabel('training samples n')
        ax.set_title(f'joint {j + 1} friction torque')
        ax.grid(True, which='both', alpha=0.3)
    axes[0].set_ylabel('NMSE (median over seeds)')
    axes[1].legend(fontsize=7, ncol=2)
    fig.suptitle('Synthetic 2-DOF friction (Coulomb + Stribeck + viscous + coupling)')
    p1 = C.savefig(fig, a.out, 'synthetic_nmse_vs_n.png')

    # ---------------------------------------------------------------- section
    lines = [C.header_lines('Synthetic 2-DOF friction (Coulomb + Stribeck + viscous + coupling)',
                            'bench/synthetic_friction.py',
                            a.quick, wall)]
    lines.append(
        f'Truth: smoothed Coulomb + Stribeck + viscous per joint, a symmetric positive '
        f'cross-damping and a power-neutral gyroscopic coupling (passive: {truth_neg} '
        f'negative-power points of '
        f'{2 * k_pass}). Training: n uniform samples in [-{BOX:g}, {BOX:g}]^2 rad/s, '
        f'noise sd {NOISE} Nm; test: NMSE per joint on 4000 noise-free points of the same box; '
        f'seeds {seeds}' + ('' if a.quick else ' for n <= 100, seed 0 only above (time '
                            'budget); certified mode with the library default verification '
                            'budget') + '. Median over seeds shown. Each model is optimized once '
        '(passivity none) and every '
        'mode is fitted at those hyper-parameters.\n')
    lines.append('### NMSE per joint (median over seeds), joint 1 / joint 2\n')
    med = {(c, n): np.median(np.array(res[c][n]), axis=0) for c in combos for n in ns}
    lines.append(C.combo_table([f'n={n}' for n in ns], combos, lambda c: [
        f'{C.fmt(med[c, n][0])} / {C.fmt(med[c, n][1])}' for n in ns]))
    lines.append(f'![NMSE vs n]({C.rel(p1, a.out)})\n')
    nb = n_pass
    lines.append(f'### Passivity at n = {ns[-1]} ({nb} fitted model(s) per row, {k_pass} random '
                 f'points inside the data box and {k_pass} far outside it, per model)\n')
    lines.append('`neg` counts `qd^T tau_hat < 0` exactly as computed; `neg>tol` only those below '
                 '`-1e-12 |qd| |tau_hat|` (beyond round-off). Certificate time is `certificate()'
                 '.details["seconds"]` (median), the correction scale the factor the certificate '
                 'applied to the GP correction (1 = untouched).\n')
    tot = nb * k_pass

    def row(c):
        v = viol[c]
        ct = [x for n in ns for x in cert[c][n] if np.isfinite(x)]
        return list(v[:4]) + [f'{C.fmt(v[0] / tot)} / {C.fmt(v[1] / tot)}',
                              f'{sum(certified_flags[c])}/{len(certified_flags[c])}',
                              C.fmt(np.median(scales[c][ns[-1]])),
                              C.fmt_time(np.median(ct)) if ct else '-']
    lines.append(C.combo_table(['neg inside', 'neg far', 'neg>tol inside', 'neg>tol far',
                                'fraction neg (in / far)', 'certificate holds', 'corr. scale',
                                'cert. time'], combos, row))
    C.write_section(a.out, NAME, '\n'.join(lines))
    C.log(f'{NAME}: wrote section and {p1} in {wall:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())

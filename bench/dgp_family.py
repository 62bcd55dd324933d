#!/usr/bin/env python3
r"""
The paper's own problem: synthetic dissipative systems streamed through the node's defaults.

Every system is a true damping force ``tau = D(qd) qd`` (Dai, Evangelisti, Hirche, L4DC 2024)
whose symmetric part of ``D`` is positive definite at every velocity (diagonally dominant by
construction, so the system is truly passive: ``qd . tau > 0`` for ``qd != 0``), coupled
(off-diagonal entries, a symmetric part and a skew, gyroscopic-like part) and nonlinear in ``qd``:

* diagonal ``D_ii = b_i + a_i exp(-(v_i / vs_i)^2) + k_i |v_i| / s_i + g_i (v_j / s_j)^2``
  (Stribeck-like hump at rest, |v|-dependent viscous, dependence on another velocity j);
* symmetric couplings ``M_ij = m_ij (1 + 0.5 tanh(v_l / s_l))`` (l another velocity);
* skew couplings ``W_ij = -W_ji = w_ij sin(v_k / s_k)`` (no power, still a force);
* ``b_i = base_i + 1.875 sum_j |m_ij|`` so ``D_ii`` exceeds 1.25 x the largest row sum of
  ``|M_ij|`` (Gershgorin: ``sym(D)`` positive definite).

Velocities reverse: each a sum of three sines around zero with random (incommensurate)
frequencies in [0.05, 0.5] Hz and its own RMS ``s_i``. 90 s at 100 Hz; the measured force has
Gaussian noise of std 1 % of each output's RMS. Each stream goes through
``OnlineEstimator(EstimatorConfig(refit_mode='sync'))`` (the node's defaults in line, no
inverse dynamics): every message is answered by ``est.predict`` before ``est.process`` learns
it (one step ahead; ``process`` also answers before learning: both are kept and compared).

Scores per output:

* ``step_noisy`` / ``step_true``: one-step-ahead NMSE over the last 20 s against the noisy
  measurement and against the noise-free force (each over its own variance on those 20 s);
* ``box``: the final model (``est.predict``, the gated answer a user gets; ``est.model.predict``
  beside it) at 5000 fresh velocities uniform in the visited box (per-axis min/max of the
  stream) against the noise-free force, NMSE over the truth's variance on those points;
* ``path``: the final model on the next 30 s of the same motion (not streamed), against truth;
* ``elements`` / ``structure`` (and their scores) from ``est.diagnostics()`` at the end, and
  their time course (polled every second of stream time) beside the 1 s windows' one-step NMSE
  against truth (over the stream's truth variance).

Deterministic (fixed seeds, ``sync``). Usage:

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 PYTHONPATH=<checkout> \\
        python bench/dgp_family.py [--quick] [--systems 2ax,3ax] [--seed-offset K] \\
        [--out DIR] [--section]

writes ``DIR/dgp_family_<tag>.md`` and ``.json`` (``--section``: the report also into
docs/BENCHMARKS.md) (tag: the short commit of the imported
dgp_ros). ``--quick``: 2 systems (2 and 3 axes), 40 s streams, last 10 s scored.
"""
from __future__ import annotations

import os
import sys
import time
import traceback

from family_io import course_point, course_text, fmt, nmse, parse, parser, per_out, windows, write
import numpy as np

RATE_HZ = 100.0
DURATION_S = 90.0
LAST_S = 20.0
NOISE = 0.01
BOX_POINTS = 5000
PATH_S = 30.0

#: (name, axes, seed)
SYSTEMS = (
    ('2ax', 2, 11),
    ('3ax', 3, 12),
    ('4ax', 4, 13),
    ('5ax', 5, 14),
    ('7ax', 7, 15),
)
QUICK = ('2ax', '3ax')

#: estimator parameters besides the defaults (--set; none by default)
PARAMS = {}


# ------------------------------------------------------------------------------ systems
class System:
    """One synthetic dissipative system (module docstring), all parameters from ``seed``."""

    def __init__(self, name: str, N: int, seed: int):
        self.name, self.N, self.seed = name, N, seed
        rng = np.random.default_rng(seed)
        self.s = rng.uniform(0.4, 2.5, N)                       # velocity RMS per axis
        # velocity: 3 sines per axis
        self.freq = rng.uniform(0.05, 0.5, (N, 3))
        self.phase = rng.uniform(0, 2 * np.pi, (N, 3))
        amp = rng.uniform(0.3, 1.0, (N, 3))
        self.amp = amp / np.sqrt((amp ** 2).sum(axis=1, keepdims=True) / 2)   # unit RMS
        # diagonal
        self.base = rng.uniform(0.5, 1.5, N)
        self.a = rng.uniform(0.5, 2.0, N)                        # Stribeck-like hump
        self.vs = self.s * rng.uniform(0.1, 0.4, N)
        self.k = rng.uniform(0.2, 1.0, N)                        # |v|-dependent viscous
        self.g = rng.uniform(0.1, 0.5, N)                        # other velocity's effect
        self.gj = np.array([(i + 1 + rng.integers(0, N - 1)) % N for i in range(N)])
        # symmetric couplings (all pairs for N <= 4, about half of them beyond)
        p = 1.0 if N <= 4 else 0.5
        m = np.zeros((N, N))
        lidx = np.zeros((N, N), int)
        for i in range(N):
            for j in range(i + 1, N):
                if rng.random() < p or j == i + 1:
                    m[i, j] = m[j, i] = rng.choice([-1, 1]) * rng.uniform(0.3, 1.0)
                lidx[i, j] = lidx[j, i] = rng.integers(0, N)
        self.m, self.lidx = m, lidx
        # skew couplings
        w = np.zeros((N, N))
        kidx = np.zeros((N, N), int)
        for i in range(N):
            for j in range(i + 1, N):
                if rng.random() < 0.5:
                    w[i, j] = rng.uniform(-0.5, 0.5)
                    w[j, i] = -w[i, j]
                kidx[i, j] = kidx[j, i] = rng.integers(0, N)
        self.w, self.kidx = w, kidx
        self.b = self.base + 1.875 * np.abs(m).sum(axis=1)

    # velocities
    def velocity(self, t: np.ndarray) -> np.ndarray:
        """Velocities (k, N) at times t (k,)."""
        t = np.asarray(t, float)[:, None, None]
        return self.s * (self.amp * np.sin(2 * np.pi * self.freq * t + self.phase)).sum(axis=2)

    def damping(self, V: np.ndarray) -> np.ndarray:
        """D(qd) (k, N, N)."""
        V = np.atleast_2d(V)
        k, N = V.shape
        U = V / self.s
        D = np.zeros((k, N, N))
        idx = np.arange(N)
        D[:, idx, idx] = (self.b + self.a * np.exp(-(V / self.vs) ** 2) + self.k * np.abs(U)
                          + self.g * U[:, self.gj] ** 2)
        for i in range(N):
            for j in range(N):
                if i != j:
                    if self.m[i, j]:
                        D[:, i, j] += self.m[i, j] * (1 + 0.5 * np.tanh(U[:, self.lidx[i, j]]))
                    if self.w[i, j]:
                        D[:, i, j] += self.w[i, j] * np.sin(U[:, self.kidx[i, j]])
        return D

    def force(self, V: np.ndarray) -> np.ndarray:
        """Return the force tau = D(qd) qd (k, N)."""
        V = np.atleast_2d(V)
        return np.einsum('kij,kj->ki', self.damping(V), V)

    def min_sym_eig(self, V: np.ndarray) -> float:
        """Smallest eigenvalue of sym(D) over the velocities V (the passivity check)."""
        D = self.damping(V)
        return float(np.linalg.eigvalsh(0.5 * (D + D.transpose(0, 2, 1))).min())

    def coupling_share(self, V: np.ndarray) -> np.ndarray:
        """Per output: RMS of the off-diagonal part of the force over the RMS of the force."""
        D = self.damping(V)
        idx = np.arange(self.N)
        off = D.copy()
        off[:, idx, idx] = 0.0
        Toff = np.einsum('kij,kj->ki', off, V)
        T = np.einsum('kij,kj->ki', D, V)
        return np.sqrt((Toff ** 2).mean(axis=0) / (T ** 2).mean(axis=0))

    def stream(self, duration_s: float):
        """(t, qd, tau_true, tau_noisy) at RATE_HZ; noise std NOISE x each output's RMS."""
        t = np.arange(int(round(duration_s * RATE_HZ))) / RATE_HZ
        V = self.velocity(t)
        T = self.force(V)
        rng = np.random.default_rng(1000 + self.seed)
        Tn = T + rng.standard_normal(T.shape) * NOISE * np.sqrt((T ** 2).mean(axis=0))
        return t, V, T, Tn


# ------------------------------------------------------------------------------ scoring


def run_system(sysm: System, duration_s: float, last_s: float) -> dict:
    """Stream one system through the defaults; the scores (module docstring)."""
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    t, V, T, Tn = sysm.stream(duration_s)
    names = [f'{sysm.name}_j{i}' for i in range(sysm.N)]
    est = OnlineEstimator(EstimatorConfig(**dict(PARAMS, refit_mode='sync')))
    P = np.zeros_like(T)
    P2 = np.full_like(T, np.nan)
    course = []
    per_s = int(round(RATE_HZ))
    t0 = time.perf_counter()
    for i in range(len(t)):
        P[i] = est.predict(V[i])[0]                 # before it is learned (one step ahead)
        e = est.process(float(t[i]), names, V[i], Tn[i])
        if e is not None:
            P2[i] = e.tau_hat
        if (i + 1) % per_s == 0:
            course_point(est, t[i], course)
    wall = time.perf_counter() - t0
    d = est.diagnostics()
    last = t >= t[-1] - last_s + 1e-9
    # the final model: fresh velocities in the visited box, and the motion's continuation
    rng = np.random.default_rng(2000 + sysm.seed)
    lo, hi = V.min(axis=0), V.max(axis=0)
    Vb = rng.uniform(lo, hi, (BOX_POINTS, sysm.N))
    Tb = sysm.force(Vb)
    Pb = est.predict(Vb)
    try:
        Pb_model = est.model.predict(Vb)
    except Exception as exc:                         # noqa: BLE001
        Pb_model = None
        d['model_predict_error'] = repr(exc)
    tc = t[-1] + (1 + np.arange(int(PATH_S * RATE_HZ))) / RATE_HZ
    Vc = sysm.velocity(tc)
    Tc = sysm.force(Vc)
    Pc = est.predict(Vc)
    var_all = T.var(axis=0)
    starts, W = windows(P, T, t, var_all)
    wmax = W[1:].max(axis=0)
    wat = starts[1:][W[1:].argmax(axis=0)]
    est.close()
    scale = np.abs(P).max(axis=0) + 1e-300
    return {
        'name': sysm.name, 'N': sysm.N, 'seed': sysm.seed, 'samples': int(len(t)),
        'duration_s': duration_s, 'last_s': last_s,
        'coupling_share': sysm.coupling_share(V), 'min_sym_eig': sysm.min_sym_eig(V[::10]),
        'measured_negative_power': int((np.einsum('ki,ki->k', V, Tn) < 0).sum()),
        'step_noisy': nmse(P[last], Tn[last]), 'step_true': nmse(P[last], T[last]),
        'step_noise_floor': nmse(T[last], Tn[last]),
        'step_whole_true': nmse(P, T),
        'process_vs_predict_maxdiff': float(np.nanmax(np.abs(P2 - P) / scale)),
        'box': nmse(Pb, Tb),
        'box_model': None if Pb_model is None else nmse(Pb_model, Tb),
        'box_negative_power': int((np.einsum('ki,ki->k', Vb, Pb) < -1e-12).sum()),
        'path': nmse(Pc, Tc),
        'window_max': wmax, 'window_at_s': wat,
        'windows': W, 'window_starts': starts,
        'elements': d.get('elements'), 'elements_scores': d.get('elements_scores'),
        'structure': d.get('structure'), 'structure_scores': d.get('structure_scores'),
        'refits_ok': d.get('refits_ok'), 'refits_failed': d.get('refits_failed'),
        'proofs_failed': d.get('proofs_failed'), 'certified': d.get('certified'),
        'level': d.get('level'), 'message': d.get('message'),
        'course': course, 'wall_s': wall,
    }


# ------------------------------------------------------------------------------ report


def report(results: list, tag: str, where: str, quick: bool, wall: float,
           offset: int = 0) -> str:
    new = f', seeds +{offset} (systems of the same kind never developed on)' if offset else ''
    lines = [f'# D-GP synthetic family: {tag}{" (quick)" if quick else ""}{new}', '',
             f'dgp_ros from `{where}`; defaults in line (`refit_mode=sync`)'
             f'{"; besides them " + str(PARAMS) if PARAMS else ""}; '
             f"{RATE_HZ:.0f} Hz, noise {100 * NOISE:.0f} % of each output's RMS. "
             f'Wall time {wall:.0f} s.', '',
             '| system | coupling share | one-step last s vs noisy | vs truth | noise floor '
             '(truth vs noisy) | box held-out (est.predict) | next 30 s of the motion | '
             'worst 1 s window (at s) | elements | structure | refits ok/failed | wall s |',
             '|' + '---|' * 12]
    for r in results:
        if 'error' in r:
            lines.append(f'| {r["name"]} | ERROR: {r["error"]} |' + ' |' * 10)
            continue
        lines.append(
            f'| {r["name"]} | {per_out(r["coupling_share"])} | {per_out(r["step_noisy"])} | '
            f'{per_out(r["step_true"])} | {per_out(r["step_noise_floor"])} | {per_out(r["box"])} '
            f'| {per_out(r["path"])} | {fmt(max(r["window_max"]))} '
            f'({r["window_at_s"][int(np.argmax(r["window_max"]))]:.0f}) | '
            f'{r["elements"]} | {r["structure"]} | {r["refits_ok"]}/{r["refits_failed"]} | '
            f'{r["wall_s"]:.0f} |')
    lines += ['', 'Elements over time (each change, polled every second of stream time):', '']
    lines += [f'- {r["name"]}: {course_text(r["course"])}' for r in results if 'course' in r]
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    ap = parser(__doc__, 'dgp_family')
    ap.add_argument('--systems', default='', help='comma-separated names (default: all)')
    ap.add_argument('--seed-offset', type=int, default=0,
                    help="added to every system's seed: systems of the same kind never "
                         'developed on (e.g. 100)')
    a, tag, where = parse(ap, argv, PARAMS)
    chosen = a.systems.split(',') if a.systems else (QUICK if a.quick else
                                                     [s[0] for s in SYSTEMS])
    duration, last = (40.0, 10.0) if a.quick else (DURATION_S, LAST_S)
    os.makedirs(a.out, exist_ok=True)
    results = []
    t0 = time.perf_counter()
    for name, N, seed in SYSTEMS:
        if name not in chosen:
            continue
        print(f'[dgp_family {tag}] {name} ...', flush=True)
        try:
            r = run_system(System(name, N, seed + a.seed_offset), duration, last)
            print(f'  one-step vs truth {per_out(r["step_true"])}  box {per_out(r["box"])}  '
                  f'elements {r["elements"]}  structure {r["structure"]}  '
                  f'{r["wall_s"]:.0f} s', flush=True)
        except Exception as exc:                     # noqa: BLE001
            traceback.print_exc()
            r = {'name': name, 'N': N, 'seed': seed, 'error': repr(exc),
                 'traceback': traceback.format_exc()}
        results.append(r)
    wall = time.perf_counter() - t0
    base = os.path.join(a.out, f'dgp_family_{tag}{"_quick" if a.quick else ""}'
                               f'{"_" + a.systems.replace(",", "-") if a.systems else ""}'
                               f'{"_seed+%d" % a.seed_offset if a.seed_offset else ""}')
    write(base, {'tag': tag, 'dgp_ros': where, 'quick': a.quick, 'wall_s': wall,
                 'results': results}, report(results, tag, where, a.quick, wall, a.seed_offset),
          (('dgp_family' + ('_new_seeds' if a.seed_offset else '')) if a.section
           else None), a.quick, wall, __file__)
    return 0


if __name__ == '__main__':
    sys.exit(main())

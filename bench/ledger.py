#!/usr/bin/env python3
"""
The accuracy ledger: both worlds with the node's defaults, one row per commit.

Every case runs the estimator with the node's defaults in line (``refit_mode='sync'``: the same
learner as the node, deterministic), and scores what a user gets, never the error on samples
just learned:

* ``a320``: sim_bridge's A320 approach (``simulate_approach(SimConfig())``, the flight the
  ``sim_bridge`` node publishes), each message answered before it is learned (one step ahead);
  NMSE per output (alpha / beta / airspeed: drag / -side / lift) over the first
  ``A320_EARLY_S`` s and over the whole flight.
* ``a320_family``: one flight is not the aircraft. ``A320_FAMILY``: sim_bridge's approach in
  wind along the runway from 5 to 20 m/s (the default 5), phases varied, each scored as ``a320``
  and per 1 s window after the first second (NMSE of the window against the flight's variance:
  a controller uses every answer, and an average hides the seconds the aircraft first enters
  new territory). ``A320_TEST_FAMILY`` is the part the default suite flies.
* ``loop_transient``: the closed-loop arm (``apps.loop_run``, Panda, the estimator with the
  node's defaults in line) with the estimator's compensation against none over the first
  ``LOOP_S`` s, where the first models are fitted: the mean tracking RMS of every 1 s window and
  every joint's largest |error| over the first 2 s, over none's (do no harm: at most
  ``NO_HARM``).
* ``panda_real``: the shared real Franka Panda log, the first case of the robot family
  (``robot_family``: learn t < 7.5 s of its raw joint states with its identified rigid-body
  model, the saved model's ``predict_residual`` held out on 7.5-12.6 s; the mean NMSE of the 7
  joints, beside a Makkar sigmoid refit of the samples learned; its test is the family's).
* ``panda_sim``: the robot demo's simulated Panda (``demo_arm``: friction outside the prior's
  family, a payload its URDF lacks, sensor noise and bias, jittered 1 kHz stamps), the URDF as
  ``inverse_dynamics``: learn on the first 60 % of a ``SIM_S`` s run; the saved model's
  ``predict`` against the true friction on the rest (geometric mean and worst joint).

``LIMITS`` are the thresholds of the ledger's tests (``test/test_accuracy_ledger.py``, in the
default suite): about 1.4 x the best value this project has reached on each figure, so that a
1.5x loss of any of them fails CI, on the worse of the machine kinds measured where the figure
depends on the machine (the A320's side force in the first 20 s: its structure choice is a near
tie that rounding decides, 6.6e-7 on an Intel Xeon, 3.9e-6 on an AMD EPYC for the same code).
The section in docs/BENCHMARKS.md keeps one row per commit (re-running at a commit replaces
its row). Full mode adds the A320 with hand-picked settings
(prior, passivity, bias) beside the defaults.

Usage: bench/ledger.py [--quick] [--out DIR] [--data DIR]
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
import time

import numpy as np

import common as C  # noqa: E402
from certification import _extra  # noqa: E402,I100,I201

NAME = 'ledger'
TITLE = "Accuracy ledger: the A320 and the arm with the node's defaults"
A320_EARLY_S = 20.0
SPLIT_S = 7.5
SIM_S = 20.0
SIM_LEARN = 0.6
#: thresholds of the ledger's tests: ~1.4 x the best reached (module docstring); the A320 rows
#: are per output (alpha, beta, airspeed)
LIMITS = {
    'a320_early': (0.0068, 5.5e-6, 0.0084),
    'a320_whole': (0.0025, 3.3e-5, 0.0025),
    # every flight of the family (issue 36's bars): whole, first 20 s, worst 1 s window
    'family_whole': 5e-3,
    'family_early': 0.02,
    'family_window': 0.1,
    # closed-loop learning transient, over no compensation
    'loop_window': 1.05,
    'loop_peak': 1.05,
    # the robot family's (robot_family.LIMITS): today's 0.545 may not be lost
    'panda_real_mean': 0.545,
    'panda_real_vs_sigmoid': 1.0,
    'panda_sim_geo': 0.048,
    'panda_sim_worst': 0.065,
    # the simulated UR5 (~1.4 x 0.025 / 0.042, its first measurement)
    'ur5_sim_geo': 0.035,
    'ur5_sim_worst': 0.06,
}
#: the A320 hand-picked settings of the full run (label, estimator parameters)
A320_SETTINGS = (
    ('defaults (certified, prior auto)', {}),
    ('passivity projected', {'passivity': 'projected'}),
    ('prior viscous, bias false', {'prior': 'viscous', 'bias': False}),
    ('prior viscous, bias false, projected', {'prior': 'viscous', 'bias': False,
                                              'passivity': 'projected'}),
    ('prior friction, bias false', {'prior': 'friction', 'bias': False}),
    ('prior friction+stribeck, bias false', {'prior': 'friction+stribeck', 'bias': False}),
    ('prior viscous, bias true', {'prior': 'viscous', 'bias': True}),
    ('prior friction+stribeck, bias true', {'prior': 'friction+stribeck', 'bias': True}),
)


#: the flight family: (label, ``SimConfig`` arguments); wind along the runway 5 to 20 m/s
A320_FAMILY = (
    ('default (5 m/s)', {}),
    ('runway 15 m/s', {'wind_amplitude': (15.0, 25.0, 10.0)}),
    ('runway 20 m/s', {'wind_amplitude': (20.0, 25.0, 10.0)}),
    ('runway 15 m/s, phases 4.5/1/5', {'wind_amplitude': (15.0, 20.0, 10.0),
                                       'wind_phase': (4.5, 1.0, 5.0)}),
    ('runway 12.7 m/s, phases 6/2/2.7', {'wind_amplitude': (12.7, 24.5, 5.7),
                                         'wind_phase': (5.96, 1.96, 2.66)}),
    ('runway 19.4 m/s, phases 1.7/1/6.1', {'wind_amplitude': (19.4, 22.2, 7.7),
                                           'wind_phase': (1.74, 1.01, 6.09)}),
    ('runway 12.7 m/s, phases 4.9/3.9/5.8', {'wind_amplitude': (12.7, 16.2, 8.1),
                                             'wind_phase': (4.88, 3.85, 5.76)}),
)
#: the flights of the family the default suite flies (3 and 6 failed on 0623bec, 2 on dd2123c:
#: 0.35 where 1b13a8e had 1.4e-3, its airspeed's couplings dropped when it slowed to 60 m/s)
A320_TEST_FAMILY = (2, 3, 6)
#: closed-loop transient: simulated seconds, robot
LOOP_S = 3.0
LOOP_ROBOT = 'panda'


def _windows(P, T, t, width_s: float = 1.0) -> np.ndarray:
    """NMSE per output of every 1 s window after the first second, over the flight's variance."""
    var = T.var(axis=0)
    out = []
    for w in range(1, int((t[-1] - t[0]) // width_s) + 1):
        s = (t >= t[0] + w * width_s) & (t < t[0] + (w + 1) * width_s)
        if s.sum() >= 10:
            out.append(((P[s] - T[s]) ** 2).mean(axis=0) / var)
    return np.array(out)


# ------------------------------------------------------------------------------ the cases
def a320_flight(**wind) -> dict:
    """Return sim_bridge's approach (``simulate_approach(SimConfig(**wind))``)."""
    from sim_bridge import SimConfig, simulate_approach
    return simulate_approach(SimConfig(**wind))


def a320_case(flight: dict, **params) -> dict:
    """
    Stream the flight through the estimator; the one-step-ahead NMSE per output.

    ``params``: estimator parameters besides the defaults. Returns ``early``, ``whole`` (3,) each,
    ``wall_s``, ``flight_s``, ``structure`` and the learner's counters.
    """
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    t, Q, T = flight['t'], flight['q'], flight['tau']
    names = list(flight['joint_names'])
    est = OnlineEstimator(EstimatorConfig(**dict(params, refit_mode='sync')))
    P = np.zeros_like(T)
    t0 = time.perf_counter()
    for i in range(len(t)):
        P[i] = est.predict(Q[i])[0]        # before it is learned, whatever the mode answers
        est.process(float(t[i]), names, Q[i], T[i])
    wall = time.perf_counter() - t0
    d = est.diagnostics()
    est.close()
    early = t <= t[0] + A320_EARLY_S
    W = _windows(P, T, t)
    return {'early': C.nmse(P[early], T[early]), 'whole': C.nmse(P, T), 'wall_s': wall,
            'window_max': W.max(axis=0), 'window_at_s': W.argmax(axis=0) + 1.0,
            'flight_s': float(t[-1] - t[0]), 'structure': d.get('structure', ''),
            'refits_ok': d.get('refits_ok'), 'refits_failed': d.get('refits_failed'),
            'absorbs_rejected': d.get('absorbs_rejected'),
            'proofs_failed': d.get('proofs_failed'), 'novelty_refits': d.get('novelty_refits')}


def family_case(index: int) -> dict:
    """Fly ``A320_FAMILY[index]`` and score it (``a320_case``), with its label."""
    label, wind = A320_FAMILY[index]
    return dict(a320_case(a320_flight(**wind)), label=label)


def family_check(r: dict) -> list:
    """Return the figures of one family flight beyond the family limits, as text ([])."""
    lab = r.get('label', '')
    return [f'{lab}: {x}' for name, key in (('family_whole', 'whole'),
                                            ('family_early', 'early'),
                                            ('family_window', 'window_max'))
            for x in check(name, r[key], [LIMITS[name]] * len(r[key]))]


def loop_transient_case(duration_s: float = LOOP_S, robot: str = LOOP_ROBOT) -> dict:
    """
    Fly the closed-loop learning transient (module docstring): dgp against none.

    Returns ``window_ratios`` (per 1 s window, mean RMS over none's), ``peak_ratios`` (per joint,
    largest |error| over the first 2 s over none's), the confidence per window and wall time.
    """
    from dgp_ros.apps.loop_run import run_loop, score, windows
    t0 = time.perf_counter()
    none = run_loop(robot, 'none', duration_s, duration_s)
    dgp = run_loop(robot, 'dgp', duration_s, duration_s)
    wn, wd = windows(none).mean(axis=1), windows(dgp).mean(axis=1)
    peak = min(2.0, duration_s)
    return {'window_ratios': wd / wn,
            'peak_ratios': score(dgp, 0.0, peak)[1] / score(none, 0.0, peak)[1],
            'nonpassive_answers': dgp['nonpassive_answers'],
            'confidence_mean': float(dgp['confidence'].mean()),
            'wall_s': time.perf_counter() - t0}


def panda_real_case(path: str = None) -> dict:
    """
    Score the real Panda split (``robot_family``'s case: module docstring); None without the log.

    Returns ``nmse`` (7,), ``mean``, ``sigmoid`` (7,), ``ratio`` (mean over the sigmoid refit's
    mean), ``wall_s``.
    """
    import robot_family
    log = robot_family.family_log(robot_family.CASES[0][0])
    if log is None:
        return None
    r = robot_family.arm_case(log)
    return {'nmse': r['held'], 'mean': r['mean'], 'sigmoid': r['sigmoid'],
            'ratio': float(r['mean'] / np.mean(r['sigmoid'])), 'wall_s': r['wall_s']}


def panda_sim_case(duration_s: float = SIM_S, seed: int = 0, robot: str = 'panda') -> dict:
    """
    Score the simulated Panda (module docstring): held-out NMSE against the true friction.

    Returns ``nmse`` (N,), ``geo`` (geometric mean), ``worst``, ``wall_s``. The answers are
    computed without the variance and the damping matrix (as the node computes them while
    nobody subscribes to those). ``robot``: 'panda', or the demo's other arm ('ur5').
    """
    from dgp_ros.dynamics import example_robot_urdf
    from dgp_ros.dynamics.arm_stream import demo_arm
    from dgp_ros.gp import load_model
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    d = demo_arm(robot, duration_s, seed=seed)
    names = list(d['names'])
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync', inverse_dynamics='urdf',
                                          urdf_file=example_robot_urdf(robot), joints=names))
    est.set_outputs(stddev=False, damping=False)
    t = d['t']
    k = int(np.searchsorted(t, SIM_LEARN * duration_s))
    t0 = time.perf_counter()
    for i in range(k):
        est.process(float(t[i]), names, d['qd'][i], d['effort'][i], d['q'][i])
    with tempfile.TemporaryDirectory() as dd:
        model = load_model(est.save(os.path.join(dd, 'm.npz')))
    wall = time.perf_counter() - t0
    est.close()
    held = np.arange(k, t.size, 10)
    nm = C.nmse(model.predict(d['qd_true'][held]), d['friction'][held])
    return {'nmse': nm, 'geo': float(np.exp(np.log(nm).mean())), 'worst': float(nm.max()),
            'wall_s': wall}


def check(name: str, value, limit=None) -> list:
    """Return the figures of ``value`` beyond ``LIMITS[name]`` (or ``limit``), as text ([])."""
    lim = np.atleast_1d(LIMITS[name] if limit is None else limit)
    val = np.atleast_1d(value)
    return [f'{name}[{i}] = {v:.4g} > {m:.4g}' for i, (v, m) in enumerate(zip(val, lim))
            if not v <= m]


# ------------------------------------------------------------------------------ the report
def _worst(F, key) -> float:
    return float(max(np.max(r[key]) for r in F))


def _row(rev: str, A, P, S, F=None, L=None) -> list:
    f3 = ' / '.join
    return [rev, time.strftime('%Y-%m-%d'),
            f3(C.fmt(x) for x in A['early']), f3(C.fmt(x) for x in A['whole']),
            '-' if P is None else f'{C.fmt(P["mean"])} ({C.fmt(P["ratio"])}x sigmoid)',
            f'{C.fmt(S["geo"])} / {C.fmt(S["worst"])}',
            '-' if not F else ' / '.join(C.fmt(_worst(F, k))
                                         for k in ('whole', 'early', 'window_max')),
            '-' if L is None else f'{C.fmt(float(np.max(L["window_ratios"])))} / '
                                  f'{C.fmt(float(np.max(L["peak_ratios"])))}']


_HEAD = ['commit', 'date', 'A320 first 20 s: alpha / beta / airspeed',
         'A320 whole flight', 'real Panda held out, mean of 7 joints',
         'simulated Panda held out, geo-mean / worst joint',
         'A320 family, worst output and flight: whole / first 20 s / 1 s window',
         'closed-loop transient / none: worst 1 s window / worst joint peak (first 2 s)']


def _history(out: str) -> list:
    """Rows of the history table of the section written before (commit first)."""
    old = C.read_section(out, NAME) or ''
    rows, on = [], False
    for ln in old.splitlines():
        if ln.startswith('### History'):
            on = True
        elif on and ln.startswith('### '):
            break
        elif on and ln.startswith('| ') and not ln.startswith('| commit') and \
                not re.match(r'^\|[\s|:-]+\|$', ln):
            rows.append([c.strip() for c in ln.strip().strip('|').split('|')])
    return rows


def report(a, A, P, S, table, wall, history, F=None, L=None) -> str:
    rev = C.machine_info()['git']
    rows = [r + ['-'] * (len(_HEAD) - len(r)) for r in history if r and r[0] != rev] + \
        [_row(rev, A, P, S, F, L)]
    lim = LIMITS
    lines = [C.header_lines(TITLE, 'bench/ledger.py', a.quick, wall), '',
             "The node's defaults (certified, prior auto) in line (`refit_mode=sync`, the node's "
             "learner, deterministic). A320: sim_bridge's approach, "
             f'{A["flight_s"]:.1f} s at 60 Hz, each message answered before it is learned (one '
             'step ahead), NMSE per output. Real Panda: learn t < 7.5 s of the shared log, the '
             "saved model's `predict_residual` held out on 7.5-12.6 s against the reference "
             "residual. Simulated Panda: the robot demo's arm (friction outside the prior's "
             f'family, payload), learn on {100 * SIM_LEARN:.0f} % of {SIM_S:.0f} s at 1 kHz, the '
             "saved model held out against the true friction. The ledger's tests "
             '(`test/test_accuracy_ledger.py`, default suite) fail beyond: A320 first 20 s '
             f'{" / ".join(C.fmt(x) for x in lim["a320_early"])}, whole flight '
             f'{" / ".join(C.fmt(x) for x in lim["a320_whole"])}; real Panda mean '
             f'{lim["panda_real_mean"]} and {lim["panda_real_vs_sigmoid"]}x the sigmoid; '
             f'simulated Panda {lim["panda_sim_geo"]} / {lim["panda_sim_worst"]}.', '',
             '### History', '', C.md_table(_HEAD, rows), '',
             '### This run', '',
             f'A320: structure chosen `{A["structure"]}`, refits ok {A["refits_ok"]} / failed '
             f'{A["refits_failed"]}, rebases refused {A["absorbs_rejected"]}, unproven models '
             f'{A["proofs_failed"]}; {A["wall_s"]:.1f} s for the {A["flight_s"]:.0f} s flight.',
             '']
    if P is None:
        lines += ['Real Panda: data not found, skipped.', '']
    else:
        lines += [C.md_table(['', 'mean'] + [f'j{j + 1}' for j in range(7)],
                             [['real Panda, defaults', C.fmt(P['mean'])] +
                              [C.fmt(v) for v in P['nmse']],
                              ['sigmoid refit', C.fmt(P['sigmoid'].mean())] +
                              [C.fmt(v) for v in P['sigmoid']]]), '']
    lines += [C.md_table(['', 'geo-mean'] + [f'j{j + 1}' for j in range(7)],
                         [['simulated Panda, defaults', C.fmt(S['geo'])] +
                          [C.fmt(v) for v in S['nmse']]]), '']
    if F:
        lines += ['### A320: the flight family', '',
                  'One step ahead with the defaults, alpha / beta / airspeed (drag / -side / '
                  'lift); worst 1 s window after the first second, as NMSE against the '
                  "flight's variance, and where it falls. Bars (issue 36, the family's tests): "
                  f'whole <= {LIMITS["family_whole"]:g}, first 20 s <= '
                  f'{LIMITS["family_early"]:g}, every window <= {LIMITS["family_window"]:g}.', '',
                  C.md_table(['flight', 'whole flight', f'first {A320_EARLY_S:g} s',
                              'worst 1 s window', 'at s', 'novelty refits', 'wall'],
                             [[r['label'], ' / '.join(C.fmt(x) for x in r['whole']),
                               ' / '.join(C.fmt(x) for x in r['early']),
                               ' / '.join(C.fmt(x) for x in r['window_max']),
                               ' / '.join(f'{x:.0f}' for x in r['window_at_s']),
                               str(r.get('novelty_refits', '-')), C.fmt_time(r['wall_s'])]
                              for r in F]), '']
    if L is not None:
        lines += ['### Closed loop: the learning transient', '',
                  f'{LOOP_ROBOT} in closed loop (`apps.loop_run`, the estimator in line with the '
                  f"node's defaults, the compensation times the answers' confidence) over the "
                  f'first {LOOP_S:g} s, against no compensation: mean tracking RMS per 1 s window '
                  f'{" / ".join(f"{x:.3f}" for x in L["window_ratios"])}; largest |error| per '
                  'joint over the first 2 s '
                  f'{" / ".join(f"{x:.3f}" for x in L["peak_ratios"])} (limit '
                  f'{LIMITS["loop_window"]:g}); mean confidence {L["confidence_mean"]:.3f}; '
                  f'{L["nonpassive_answers"]} non-passive answers; {L["wall_s"]:.0f} s.', '']
    if table:
        best_e = np.min([r['early'] for _, r in table], axis=0)
        best_w = np.min([r['whole'] for _, r in table], axis=0)
        rows = [[label, ' / '.join(C.fmt(x) for x in r['early']),
                 ' / '.join(C.fmt(x) for x in r['whole']),
                 ' / '.join(C.fmt(x) for x in r['whole'] / best_w), C.fmt_time(r['wall_s']),
                 r['structure'] or '-'] for label, r in table]
        lines += ['### A320: the defaults beside hand-picked settings', '',
                  'One step ahead, alpha / beta / airspeed; ratio: whole flight over the best '
                  f'setting per output (best first 20 s: {" / ".join(C.fmt(x) for x in best_e)}). '
                  'A bias is learned apart from the damping force and not published in it: '
                  'the rows with bias true miss it in every answer.', '',
                  C.md_table(['setting', 'first 20 s', 'whole flight', 'ratio to best', 'wall',
                              'structure chosen'], rows), '']
    return '\n'.join(lines)


def main(argv=None) -> int:
    a = C.parse_args(__doc__.strip().splitlines()[0], argv, _extra)
    t0 = time.perf_counter()
    flight = a320_flight()
    A = a320_case(flight)
    C.log(f'{NAME}: A320 {A["wall_s"]:.1f} s')
    P = panda_real_case()
    C.log(f'{NAME}: real Panda {"skipped (no data)" if P is None else "%.1f s" % P["wall_s"]}')
    S = panda_sim_case(8.0 if a.quick else SIM_S)
    C.log(f'{NAME}: simulated Panda {S["wall_s"]:.1f} s')
    F = [dict(A, label=A320_FAMILY[0][0])]
    for i in (A320_TEST_FAMILY if a.quick else range(1, len(A320_FAMILY))):
        F.append(family_case(i))
        C.log(f'{NAME}: A320 {F[-1]["label"]} {F[-1]["wall_s"]:.1f} s')
    L = loop_transient_case()
    C.log(f'{NAME}: closed-loop transient {L["wall_s"]:.1f} s')
    table = []
    if not a.quick:
        for label, params in A320_SETTINGS:
            table.append((label, A if not params else a320_case(flight, **params)))
            C.log(f'{NAME}: A320 {label}')
    history = _history(a.out)
    C.write_section(a.out, NAME, report(a, A, P, S, table, time.perf_counter() - t0,
                                        history, F, L))
    return 0


if __name__ == '__main__':
    sys.exit(main())

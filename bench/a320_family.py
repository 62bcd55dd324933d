#!/usr/bin/env python3
r"""
Random A320 approaches streamed through the node's defaults, scored as the ledger's a320_case.

``FLIGHTS`` flights (fixed seeds): each draws wind on all three axes of the runway frame,
amplitudes north (along the runway) / east / down uniform in [0, 25] m/s each, frequencies
uniform in [0.05, 0.4] Hz per axis, phases uniform in [0, 2 pi), approach speed uniform in
[170, 200] kt, from ``numpy.random.default_rng([SEED_BASE, flight])``. A draw the aircraft cannot
fly is drawn again from the same generator (the next draw), and the report says so:

* ``trim``: ``TrimError`` (the approach does not trim);
* ``stall``: |alpha| reaches ``STALL_DEG`` (the full-flap stall is ~16 deg; sim_bridge's sweep
  calls a flight flyable below 15 deg);
* ``envelope``: load factor outside ``LOAD_FACTOR`` g, or non-finite states;
* ``no touch-down`` within the simulator's ``max_time_s``.

The simulation is sim_bridge's ``ApproachSimulator`` stepped as ``simulate_approach`` does
(stopped early at a stall or envelope exit). Flights are cached in ``CACHE`` (one ``.npz``
per draw, rejected draws too), so re-runs on other commits reuse the same flights.

Scoring (``bench/ledger.py``'s ``a320_case``): ``OnlineEstimator(EstimatorConfig(refit_mode=
'sync'))``, each message answered by ``est.predict`` before ``est.process`` learns it (one step
ahead); NMSE per output (alpha / beta / airspeed: drag / -side / lift) over the whole flight and
over the first 20 s, both from 1 s on (the very first answer has learned nothing: zero); every 1 s
window after the first second, its NMSE over the flight's
variance, the worst kept with where it is. The ledger's bars: whole <= 5e-3, first 20 s <= 0.02,
no 1 s window above 0.1, per output. ``est.diagnostics()`` is polled every second of flight time
for ``elements`` / ``structure`` (changes kept, with ``elements_scores``), so a window that blows
up can be read against what the model held then.

Usage:

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 PYTHONPATH=<checkout> \\
        python bench/a320_family.py [--quick] [--flights 0,3,7] [--simulate-only]
                                    [--out DIR] [--cache DIR] [--tag NAME] [--section]

writes ``DIR/a320_family_<tag>.md`` and ``.json`` (tag: the short commit of the imported
dgp_ros). ``--quick``: the first 2 flights. ``--simulate-only``: fill the cache, no learning.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
import traceback

from family_io import course_point, course_text, fmt, nmse, parse, parser, per_out, windows, write
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
#: simulated flights (about 1.4 s each to make again): out/ of the checkout
CACHE = os.path.join(REPO, 'out', 'a320_family_cache')
SEED_BASE = DEVELOPED_SEED = 20241
#: the seed of the flights first flown to check the developed ones (their section
#: ``a320_family_new_seeds``); any other seed gets a section of its own
NEW_SEED = 777
FLIGHTS = 24
MAX_DRAWS = 30
STALL_DEG = 15.0
LOAD_FACTOR = (-0.5, 2.5)
#: --keep-stalls (a probe, not the family): nothing but a failed trim is drawn again, so a draw
#: that stalls is flown to touch-down (its own cache files)
KEEP_STALLS = False
EARLY_S = 20.0
BARS = {'whole': 5e-3, 'early': 0.02, 'window_max': 0.1}
OUTPUTS = ('drag', 'side', 'lift')

#: estimator parameters besides the defaults (--set; none by default)
PARAMS = {}


# ------------------------------------------------------------------------------ flights
def draw(rng) -> dict:
    """One random approach: ``SimConfig`` arguments."""
    amp = rng.uniform(0.0, 25.0, 3)
    freq = rng.uniform(0.05, 0.4, 3)
    phase = rng.uniform(0.0, 2 * np.pi, 3)
    speed = rng.uniform(170.0, 200.0)
    return {'wind_amplitude': [round(float(x), 3) for x in amp],
            'wind_frequency': [round(float(x), 4) for x in freq],
            'wind_phase': [round(float(x), 3) for x in phase],
            'approach_speed_kts': round(float(speed), 2)}


def fly(cfg_kw: dict) -> dict:
    """
    Simulate one approach; ``status`` 'ok' or the reason it was rejected (module docstring).

    The samples are those of ``sim_bridge.simulate_approach`` (same stepping), stopped early
    at a stall or an envelope exit.
    """
    from sim_bridge import SimConfig
    from sim_bridge.simulator import ApproachSimulator, TrimError
    cfg = SimConfig(**cfg_kw)
    sim = ApproachSimulator(cfg)
    try:
        states = [sim.reset()]
    except TrimError as exc:
        return {'status': 'trim', 'detail': str(exc)[:300]}
    status, detail = 'ok', ''
    for s in sim.run():
        states.append(s)
        a = math.degrees(s.alpha)
        if not (np.isfinite(s.q).all() and np.isfinite(s.tau).all()):
            status, detail = 'envelope', f'non-finite state at t={s.t:.1f} s'
            break
        if KEEP_STALLS:
            continue
        if abs(a) >= STALL_DEG:
            status, detail = 'stall', f'alpha {a:.1f} deg at t={s.t:.1f} s'
            break
        if not LOAD_FACTOR[0] < s.load_factor < LOAD_FACTOR[1]:
            status, detail = 'envelope', f'load factor {s.load_factor:.2f} g at t={s.t:.1f} s'
            break
    if status == 'ok' and not sim.touched_down:
        status, detail = 'no touch-down', f'{sim.t:.0f} s'
    arr = lambda name: np.array([getattr(s, name) for s in states], float)  # noqa: E731
    out = {'status': status, 'detail': detail, 't': arr('t'),
           'q': np.array([s.q for s in states]), 'tau': np.array([s.tau for s in states]),
           'alpha': arr('alpha'), 'load_factor': arr('load_factor'), 'airspeed': arr('airspeed'),
           'joint_names': list(sim.cfg.joint_names),
           'trim_speed_kts': float(sim.trim_speed_kts),
           'trim_airspeed_mps': float(sim.trim_airspeed_mps)}
    if status != 'ok':          # keep the rejected draw's reason only
        out = {k: out[k] for k in ('status', 'detail', 'trim_speed_kts')}
    return out


def _cache_path(cache: str, flight: int, k: int) -> str:
    kind = 'a320stalls' if KEEP_STALLS else 'a320'
    return os.path.join(cache, f'{kind}_{SEED_BASE}_{flight:02d}_{k:02d}.npz')


def flight(index: int, cache: str, log=print) -> dict:
    """Return the ``index``-th flight: its samples and its rejected draws."""
    rng = np.random.default_rng([SEED_BASE, index])
    rejected = []
    for k in range(MAX_DRAWS):
        kw = draw(rng)
        path = _cache_path(cache, index, k)
        if os.path.exists(path):
            z = np.load(path, allow_pickle=False)
            rec = {key: z[key] for key in z.files}
            rec = {key: (str(v) if v.dtype.kind == 'U' and v.ndim == 0 else v)
                   for key, v in rec.items()}
            if json.loads(str(rec['config'])) != kw:
                raise RuntimeError(f'{path}: cached for another draw')
            rec['sim_s'] = float(rec.get('sim_s', float('nan')))
        else:
            t0 = time.perf_counter()
            rec = fly(kw)
            rec['sim_s'] = time.perf_counter() - t0
            os.makedirs(cache, exist_ok=True)
            save = {key: (np.array(v) if not isinstance(v, str) else np.array(v))
                    for key, v in rec.items()}
            save['config'] = np.array(json.dumps(kw))
            tmp = path + '.tmp.npz'
            np.savez(tmp, **save)
            os.replace(tmp, path)
            log(f'  flight {index} draw {k}: {rec["status"]} {rec.get("detail", "")} '
                f'({rec["sim_s"]:.0f} s simulated)')
        status = str(rec['status'])
        if status == 'ok':
            rec['config'] = kw
            rec['draw'] = k
            rec['rejected'] = rejected
            rec['joint_names'] = [str(x) for x in np.atleast_1d(rec['joint_names'])]
            return rec
        rejected.append({'draw': k, 'status': status, 'detail': str(rec.get('detail', '')),
                         'config': kw})
    raise RuntimeError(f'flight {index}: no flyable draw in {MAX_DRAWS}')


# ------------------------------------------------------------------------------ scoring


def score(fl: dict) -> dict:
    """Stream the flight through the defaults (ledger.a320_case) and score it."""
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    t, Q, T = fl['t'], fl['q'], fl['tau']
    names = list(fl['joint_names'])
    est = OnlineEstimator(EstimatorConfig(**dict(PARAMS, refit_mode='sync')))
    P = np.zeros_like(T)
    course = []
    per_s = max(1, int(round(1.0 / np.median(np.diff(t)))))
    t0 = time.perf_counter()
    for i in range(len(t)):
        P[i] = est.predict(Q[i])[0]        # before it is learned (one step ahead)
        est.process(float(t[i]), names, Q[i], T[i])
        if (i + 1) % per_s == 0:
            course_point(est, t[i], course)
    wall = time.perf_counter() - t0
    d = est.diagnostics()
    est.close()
    # scored from 1 s on (the first answer has nothing learned: zero), as the windows are
    on = t >= t[0] + 1.0
    early = on & (t <= t[0] + EARLY_S)
    starts, W = windows(P, T, t, first=1)
    bad = [(float(s), [float(x) for x in w]) for s, w in zip(starts, W) if w.max() > BARS[
        'window_max']]
    return {'early': nmse(P[early], T[early]), 'whole': nmse(P[on], T[on]),
            'window_max': W.max(axis=0), 'window_at_s': starts[W.argmax(axis=0)],
            'windows': W, 'window_starts': starts, 'bad_windows': bad,
            'flight_s': float(t[-1] - t[0]), 'wall_s': wall,
            'elements': d.get('elements'), 'elements_scores': d.get('elements_scores'),
            'structure': d.get('structure'), 'structure_scores': d.get('structure_scores'),
            'refits_ok': d.get('refits_ok'), 'refits_failed': d.get('refits_failed'),
            'absorbs_rejected': d.get('absorbs_rejected'),
            'proofs_failed': d.get('proofs_failed'), 'novelty_refits': d.get('novelty_refits'),
            'course': course}


def passes(r: dict) -> bool:
    return all(np.max(r[k]) <= b for k, b in BARS.items())


# ------------------------------------------------------------------------------ report


def _elements_at(course: list, t: float):
    cur = None
    for c in course:
        if c['t'] <= t + 1.0:
            cur = c
    return None if cur is None else cur['elements']


def report(results: list, tag: str, where: str, quick: bool, wall: float) -> str:
    ok = [r for r in results if 'error' not in r]
    npass = sum(passes(r) for r in ok)
    seed = '' if SEED_BASE == DEVELOPED_SEED else \
        f', seed {SEED_BASE} (flights never developed on)'
    lines = [f'# A320 random family: {tag}{" (quick)" if quick else ""}{seed}'
             f'{" (probe: stalled draws flown to touch-down)" if KEEP_STALLS else ""}', '',
             f'dgp_ros from `{where}`; defaults in line (`refit_mode=sync`)'
             f'{"; besides them " + str(PARAMS) if PARAMS else ""}, one step ahead, '
             f'NMSE per output drag / side / lift. Bars: whole <= {BARS["whole"]}, first '
             f'{EARLY_S:.0f} s <= {BARS["early"]}, every 1 s window <= {BARS["window_max"]}. '
             f'Wall time {wall:.0f} s (learning and scoring; simulation cached).', '',
             f'**{npass} of {len(ok)} flights pass all bars**'
             + (f'; {len(results) - len(ok)} raised' if len(ok) < len(results) else '') + '.',
             '', '| flight | wind N/E/D m/s | freq Hz | kt | redraws | s | whole | first 20 s | '
             'worst 1 s window (at s) | pass | elements (end) | structure | elements at the '
             'worst window | refits ok/failed |', '|' + '---|' * 14]
    for r in results:
        c = r.get('config', {})
        head = (f'| {r["flight"]} | {"/".join(f"{x:.1f}" for x in c.get("wind_amplitude", []))} '
                f'| {"/".join(f"{x:.2f}" for x in c.get("wind_frequency", []))} | '
                f'{c.get("approach_speed_kts", 0):.0f} | {len(r.get("rejected", []))} ')
        if 'error' in r:
            lines.append(head + f'| ERROR: {r["error"]} |' + ' |' * 8)
            continue
        j = int(np.argmax(r['window_max']))
        lines.append(
            head + f'| {r["flight_s"]:.0f} | {per_out(r["whole"])} | {per_out(r["early"])} | '
            f'{per_out(r["window_max"])} ({r["window_at_s"][j]:.0f}) | '
            f'{"yes" if passes(r) else "**no**"} | {r["elements"]} | {r["structure"]} | '
            f'{_elements_at(r["course"], r["window_at_s"][j])} | '
            f'{r["refits_ok"]}/{r["refits_failed"]} |')
    if ok:
        lines += ['', '| worst over the family | drag | side | lift |', '|---|---|---|---|']
        for k, lab in (('whole', 'whole'), ('early', 'first 20 s'),
                       ('window_max', 'worst 1 s window')):
            M = np.array([r[k] for r in ok])
            lines.append(f'| {lab} | ' + ' | '.join(
                f'{fmt(M[:, i].max())} (flight {ok[int(M[:, i].argmax())]["flight"]})'
                for i in range(3)) + ' |')
    rej = [(r['flight'], x) for r in results for x in r.get('rejected', [])]
    if rej:
        lines += ['', f'Draws rejected and drawn again ({len(rej)}):', '']
        for f, x in rej:
            c = x['config']
            lines.append(f'- flight {f} draw {x["draw"]}: {x["status"]} ({x["detail"]}); wind '
                         f'{"/".join(f"{v:.1f}" for v in c["wind_amplitude"])} m/s at '
                         f'{"/".join(f"{v:.2f}" for v in c["wind_frequency"])} Hz, '
                         f'{c["approach_speed_kts"]:.0f} kt')
    lines += ['', 'Elements over time (each change, polled every second of flight time), for '
              'the flights that fail a bar:', '']
    lines += [f'- flight {r["flight"]}: {course_text(r["course"])}' for r in ok if not passes(r)]
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    global KEEP_STALLS, SEED_BASE
    ap = parser(__doc__, 'a320_family', 'the first 2 flights')
    ap.add_argument('--flights', default='', help='comma-separated indices (default: all)')
    ap.add_argument('--simulate-only', action='store_true', help='fill the cache only')
    ap.add_argument('--keep-stalls', action='store_true',
                    help='probe: fly stalled draws to touch-down instead of drawing again')
    ap.add_argument('--cache', default=CACHE)
    ap.add_argument('--seed-base', type=int, default=SEED_BASE,
                    help=f"the flights' seed (default {SEED_BASE}; another: flights never "
                         'developed on, their own section)')
    a, tag, where = parse(ap, argv, PARAMS)
    KEEP_STALLS = a.keep_stalls
    new = a.seed_base != SEED_BASE
    SEED_BASE = a.seed_base
    idx = ([int(x) for x in a.flights.split(',')] if a.flights else
           list(range(2 if a.quick else FLIGHTS)))
    results = []
    t0 = time.perf_counter()
    for i in idx:
        print(f'[a320_family {tag}] flight {i} ...', flush=True)
        try:
            fl = flight(i, a.cache)
        except Exception as exc:                     # noqa: BLE001
            traceback.print_exc()
            results.append({'flight': i, 'error': f'simulation: {exc!r}'})
            continue
        base = {'flight': i, 'config': fl['config'], 'draw': fl['draw'],
                'rejected': fl['rejected'], 'samples': int(len(fl['t'])),
                'alpha_deg': [float(np.degrees(fl['alpha']).min()),
                              float(np.degrees(fl['alpha']).max())],
                'load_factor': [float(fl['load_factor'].min()),
                                float(fl['load_factor'].max())],
                'airspeed_mps': [float(fl['airspeed'].min()), float(fl['airspeed'].max())],
                'trim_speed_kts': float(fl['trim_speed_kts'])}
        if a.simulate_only:
            results.append(base)
            continue
        try:
            r = dict(base, **score(fl))
            print(f'  whole {per_out(r["whole"])}  early {per_out(r["early"])}  window '
                  f'{per_out(r["window_max"])}  elements {r["elements"]}  '
                  f'{"pass" if passes(r) else "FAIL"}  {r["wall_s"]:.0f} s', flush=True)
        except Exception as exc:                     # noqa: BLE001
            traceback.print_exc()
            r = dict(base, error=repr(exc), traceback=traceback.format_exc())
        results.append(r)
    wall = time.perf_counter() - t0
    if a.simulate_only:
        for r in results:
            print(r.get('flight'), r.get('config'), len(r.get('rejected', [])), 'redraws',
                  r.get('error', ''))
        return 0
    os.makedirs(a.out, exist_ok=True)
    out = os.path.join(a.out, f'a320_family_{tag}{"_quick" if a.quick else ""}'
                       f'{"_stalls" if KEEP_STALLS else ""}{"_" + a.flights if a.flights else ""}'
                       f'{"_seed%d" % SEED_BASE if new else ""}')
    write(out, {'tag': tag, 'dgp_ros': where, 'quick': a.quick, 'wall_s': wall, 'bars': BARS,
                'results': results}, report(results, tag, where, a.quick, wall),
          ('a320_family' + ('' if not new else '_new_seeds' if SEED_BASE == NEW_SEED
                            else f'_seed_{SEED_BASE}')) if a.section else None, a.quick,
          wall, __file__)
    return 0


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""
Answers at the floor: the estimator beside a bare rclpy relay, in the same harness.

Each repeat plays the same stream twice or more, one process set each (``arm_live.run_one``):
into a bare rclpy relay (``live_procs.py relay``: subscribe JointState, publish JointState), then
into the ``estimator`` node with its defaults, learning on (the learner at nice 10, its default;
``--sched idle,nice``: under ``SCHED_IDLE`` too; ``--before-rev``: the code of that revision too).
Relay and estimator runs are interleaved, so each ratio compares runs seconds apart on the same
machine. The stream (``--stream``): ``real``, the real Panda's friction residual
(``../shared/data/panda_real``, read there only: its first 7.5 s looped at the logger's own
jittered timing, 7 joints, about 930 messages/s; the rest of the log is held out), or ``sim``,
the simulated Panda's raw /joint_states at 1 kHz through ``inverse_dynamics=urdf``.

Per run: answered (answers received / published); latency (the listener receives a measurement
-> receives its answer) median, p99 and max, and its p99 over the first and the last third of
the stream; in the estimator runs the samples learned per second of stream (the learner's
``samples_added`` at the end over the stream's length), what was still queued at the end, the
held-out NMSE of the model saved at the end (real stream: mean over the joints on the held-out
log after 7.5 s against ``tau_friction_offline``), the latency max around the first model swap
(the measurements received +-0.1 s around the first answer from the first model: the
swap that stalled the answers for 42-77 ms before), and the service round trips of a
prober calling ``get_parameters`` every 0.2 s and ``~/refit`` every 2 s (in the relay runs
``get_parameters`` of the relay node). Background CPU and load average as in arm_live.

Issue 33's protocol: ``--durations 20,60 --repeat 5 --repeat-long 3 --before-rev REV`` (the
code of REV runs once per duration: the swap silence before). Issue 38 adds the CPU of the
node's own process per message against the relay's (the learner's beside it), the path's stages
from one profiled run per tree (``--profile-seconds``, bench/path_profile.py) and, with
``--replay``, the held-out NMSE of a dgp-replay of the same stream (in line, every sample learned
before the next answer) beside the live models'.
"""
from __future__ import annotations

import json
import os
import random
import sys
import tempfile
import time
from types import SimpleNamespace
from typing import List, Optional

import numpy as np

from arm_live import run_one, Scenario  # noqa: E402, I100
from arm_live_report import fmt_ms, summarize  # noqa: E402, I201
import common as C  # noqa: E402
from live_procs import REAL_SPLIT_S  # noqa: E402, I100, I201

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf  # noqa: E402

SECTION = 'arm_floor'
REAL_DIR = os.path.normpath(os.path.join(C.REPO, '..', 'shared', 'data', 'panda_real'))
#: the issue's targets: median and p99 against the relay's of the same repeat
MEDIAN_X, P99_X = 2.0, 3.0
#: issue 38: the node's own CPU per message against the relay's of the same repeat
CPU_X = 0.5
#: "no growth" of p99 from the first to the last third: the median over runs at most this
GROWTH_X = 1.2


def _extra(p):
    p.add_argument('--stream', choices=['real', 'sim'], default='real')
    p.add_argument('--durations', default='20',
                   help='stream lengths (s), comma-separated, e.g. 20,60')
    p.add_argument('--repeat', type=int, default=5, help='repeats of each duration')
    p.add_argument('--repeat-long', type=int, default=0,
                   help='repeats of durations over 30 s (0: --repeat)')
    p.add_argument('--sched', default='nice',
                   help="the learner's scheduling in the estimator runs: nice (the node's "
                        'default), idle or both (idle,nice)')
    p.add_argument('--nice-runs', type=int, default=2,
                   help='with both: repeats (of each duration) that also run the learner at '
                        'nice 10')
    p.add_argument('--before-rev', default='',
                   help='git revision whose estimator also runs (once per duration)')
    p.add_argument('--data', default=REAL_DIR, help="the real Panda's folder")
    p.add_argument('--relay-executor', choices=['single', 'waitset'], default='single',
                   help="the relay's executor: rclpy's SingleThreadedExecutor (bare rclpy) "
                        "or the node's wait-set loop")
    p.add_argument('--keep', default='', help="keep every process's files here")
    p.add_argument('--profile-seconds', type=float, default=20.0,
                   help="seconds of the profiled run of each tree's estimator (the path's "
                        'stages, bench/path_profile.py); 0: none')
    p.add_argument('--replay', action='store_true',
                   help='also replay each duration of the real stream in line (dgp-replay: '
                        'refit_mode=sync) for the held-out NMSE beside the live models')


# ----------------------------------------------------------------------------- one run
def _extras(r: dict) -> dict:
    """Return what summarize() does not give (issue 33): thirds, first swap, learning."""
    meas, ans = r['lis']['meas'], r['lis']['ans']
    m = dict(zip(meas[:, 0].astype(np.int64), meas[:, 1]))
    a_t = dict(zip(ans[:, 0].astype(np.int64), ans[:, 1]))
    paired = sorted(set(m) & set(a_t), key=lambda k: m[k])
    t_in = np.array([m[k] for k in paired])
    lat = np.array([a_t[k] - m[k] for k in paired]) * 1e3
    out = {}
    if len(lat) > 30:
        thirds = np.array_split(lat, 3)
        out['p99_first'] = float(np.percentile(thirds[0], 99))
        out['p99_last'] = float(np.percentile(thirds[2], 99))
    swaps = (r.get('est_cpu') or {}).get('swaps') or []
    models = [x for x in swaps if len(x) > 2 and x[2]]      # the first model's swap
    if models and len(lat):
        ts = models[0][0]
        w = (t_in >= ts - 0.1) & (t_in <= ts + 0.1)
        out['swap_first_max'] = float(lat[w].max()) if w.any() else None
        out['swaps_seen'] = len(swaps)
    pub = r['player']['published'] or 1
    # CPU of the node's own process (not the learner's) and of the learner, per message published
    out['us_node'] = r.get('cpu_estimator_s', 0.0) / pub * 1e6
    out['us_learner'] = r.get('cpu_estimator_kids_s', 0.0) / pub * 1e6
    ec = r.get('est_cpu') or {}
    if ec.get('calls'):
        out['per_wakeup'] = pub / ec['calls']
    d = r['sum']['diag']
    if d:
        added = d.get('samples_added')
        out['learned_per_s'] = float(added) / r['seconds'] if added not in (None, '') else None
        out['pending_end'] = d.get('samples_pending', '-')
        out['dropped'] = d.get('samples_dropped', '-')
        out['sched'] = d.get('learner_sched', 'nice 10 (before)')
        out['refits_ok'] = d.get('refits_ok', '-')
        out['trained'] = d.get('trained') == 'True'
        out['prepare_max'] = d.get('snapshot_prepare_max_ms')
    return out


def heldout(model_path: Optional[str], data: str, names: List[str], model=None
            ) -> Optional[float]:
    """Return the mean NMSE over the joints of the saved model on the held-out real log."""
    if not model_path and model is None:
        return None
    from dgp_ros.gp import load_model
    z = np.load(os.path.join(data, 'panda_log_train.npz'), allow_pickle=False)
    t = z['t'] - z['t'][0]
    te = t >= REAL_SPLIT_S
    model = load_model(model_path) if model is None else model
    if hasattr(model, 'predict_residual'):
        P = model.predict_residual(q=z['q'][te], qd=z['qd'][te])
    else:
        P = model.predict(z['qd'][te])
    ref = z['tau_friction_offline'][te]
    return float(np.mean(((P - ref) ** 2).mean(0) / ref.var(0)))


def replay_heldout(data: str, seconds: float, names: List[str]) -> dict:
    """
    Replay the stream an estimator run gets through ``dgp-replay``'s estimator (the reference).

    The real stream of ``seconds`` (``live_procs.real_stream``) into ``OnlineEstimator`` with the
    defaults in line (``dgp_ros.replay.build_config``: ``refit_mode=sync``), stamps on an
    epoch-like clock; the held-out NMSE of its model at the end, and its learned samples.
    """
    from dgp_ros.online import OnlineEstimator
    from dgp_ros.replay import build_config
    from live_procs import real_stream
    est = OnlineEstimator(build_config())
    est.set_outputs(stddev=False, damping=False, residuals=False)
    t0 = time.perf_counter()
    try:
        for t, q, qd, r in real_stream(data, seconds):
            est.process(1.7e9 + t, names, qd, r, q)
        d = est.diagnostics()
        return {'heldout': heldout(None, data, names, est.model) if est.trained else None,
                'samples_added': d.get('samples_added'), 'refits_ok': d.get('refits_ok'),
                'wall_s': time.perf_counter() - t0}
    finally:
        est.close()


def _run(sc: Scenario, a, work, urdf, names, rng, data) -> Optional[dict]:
    C.log(f'arm_floor: {sc.label}')
    try:
        r = run_one(sc, a, work, urdf, names)
    except Exception as exc:        # noqa: BLE001 - the section says so
        C.log(f'arm_floor: {sc.label} failed: {exc}')
        return {'label': sc.label, 'failed': str(exc)}
    r['sum'] = s = summarize(r, rng)
    s.update(_extras(r))
    if sc.node == 'estimator' and sc.stream:
        try:
            s['heldout'] = heldout(r['model_path'], data, names)
        except Exception as exc:    # noqa: BLE001
            s['heldout_error'] = str(exc)
    r.pop('lis', None)
    C.log(f'arm_floor: {sc.label}: answered {100 * s["answered"]:.2f} %, latency p50 '
          f'{fmt_ms(s["lat_p50"])} p99 {fmt_ms(s["lat_p99"])} max {fmt_ms(s["lat_max"])} ms, '
          f'thirds p99 {fmt_ms(s.get("p99_first"))} / {fmt_ms(s.get("p99_last"))}, CPU '
          f'{s["us_node"]:.0f} us/msg (learner {s["us_learner"]:.0f}), learned/s '
          f'{C.fmt(s.get("learned_per_s"))}, held out {C.fmt(s.get("heldout"))}, bg '
          f'{s["bg"]:.2f}, load {s["load"]:.2f}')
    return r


# ----------------------------------------------------------------------------- the section
def _ratio(x, y):
    return None if x is None or y is None or not y else x / y


def _probe(s, kind):
    p = s.get(f'probe_{kind}')
    return '-' if not p else f'{fmt_ms(p[1])} / {fmt_ms(p[3])} ({p[0]}, {p[4]} unanswered)'


def section(a, groups: list, wall: float, stream_text: str, profiles=(), replays=None) -> str:
    lines = [C.header_lines('Answers at the floor: the estimator beside a bare rclpy relay',
                            'bench/arm_floor.py', a.quick, wall), '',
             __doc__.split('\n\n', 1)[1].strip(), '', f'Stream: {stream_text}.', '']
    hdr = ['repeat', 'run', 'answered', 'latency p50 / p99 / max ms',
           'p50 / p99 vs relay', 'p99 first / last third ms',
           'CPU us/msg: node (learner)', 'CPU vs relay',
           'learned/s (queued at end), refits ok',
           'held-out NMSE', 'first model swap: max latency ms', 'get_parameters p50 / max ms',
           '~/refit p50 / max ms', 'bg cores', 'load']
    rows, checks = [], []
    for g in groups:
        relay = g['runs'][0] if g['runs'] and g['runs'][0].get('node') == 'relay' else None
        rs = relay['sum'] if relay and 'sum' in relay else None
        for r in g['runs']:
            if 'sum' not in r:
                rows.append([g['name'], r['label'], 'failed: ' + r.get('failed', '')] +
                            ['-'] * (len(hdr) - 3))
                continue
            s = r['sum']
            rm = rp = rc = None
            if rs is not None and r is not relay:
                rm, rp = _ratio(s['lat_p50'], rs['lat_p50']), _ratio(s['lat_p99'], rs['lat_p99'])
                rc = _ratio(s.get('us_node'), rs.get('us_node'))
                checks.append({'dur': g['dur'], 'run': r['kind'], 'rm': rm, 'rp': rp, 'rc': rc,
                               'us': s.get('us_node'), 'us_l': s.get('us_learner'),
                               'refits': s.get('refits_ok'),
                               'answered': s['answered'], 'first': s.get('p99_first'),
                               'last': s.get('p99_last'), 'learned': s.get('learned_per_s'),
                               'held': s.get('heldout'), 'swap': s.get('swap_first_max'),
                               'trained': s.get('trained'),
                               'gp': s.get('probe_get_parameters'),
                               'refit': s.get('probe_refit'), 'bg': s['bg'],
                               'load': s['load']})
            learned = '-' if s.get('learned_per_s') is None else \
                f'{s["learned_per_s"]:.0f} ({s.get("pending_end", "-")}), {s["refits_ok"]}'
            held = C.fmt(s.get('heldout')) if s.get('heldout') is not None else \
                ('no model saved (none trained)' if r.get('node') == 'estimator' else '-')
            rows.append([g['name'], r['label'], f'{100 * s["answered"]:.2f} %',
                         f'{fmt_ms(s["lat_p50"])} / {fmt_ms(s["lat_p99"])} / '
                         f'{fmt_ms(s["lat_max"])}',
                         '-' if rm is None else f'{rm:.2f}x / {rp:.2f}x',
                         f'{fmt_ms(s.get("p99_first"))} / {fmt_ms(s.get("p99_last"))}',
                         f'{s.get("us_node", 0):.0f}' + (
                             f' ({s["us_learner"]:.0f})' if r.get('node') == 'estimator'
                             else ''),
                         '-' if rc is None else f'{rc:.2f}x',
                         learned, held, fmt_ms(s.get('swap_first_max')),
                         _probe(s, 'get_parameters'), _probe(s, 'refit'),
                         f'{s["bg"]:.2f}', f'{s["load"]:.2f}'])
    lines += [C.md_table(hdr, rows), '']
    thdr = ['duration, run', 'runs', 'answered min', 'CPU / relay max (<= 0.5)',
            'p50 / relay max (<= 2)',
            'p99 / relay median, max (<= 3)', 'p99 last / first third median, max',
            'learned/s median', 'trained at the end', 'held-out NMSE median',
            'first model swap max latency ms median, max', 'get_parameters max ms',
            '~/refit max ms',
            'bg cores median']
    lines += ['### Against the targets', '',
              f'Met: every run answered everything; the largest CPU ratio at most {CPU_X:g}, '
              f'the largest median ratio at most '
              f'{MEDIAN_X:g} and the largest p99 ratio at most {P99_X:g} (each against the relay '
              f'of the same repeat); p99 of the last third over the first: median over the runs '
              f'at most {GROWTH_X:g}.', '', C.md_table(thdr, _target_rows(checks)), '']
    lines += _references(checks, replays)
    lines += _profile_lines(profiles)
    return '\n'.join(lines)


def _references(checks: list, replays) -> list:
    """Return the rows of the held-out NMSE: the live models beside a dgp-replay."""
    if not replays:
        return []
    rows = []
    for dur in sorted({c['dur'] for c in checks}):
        ref = (replays or {}).get(dur) or {}
        for run in sorted({c['run'] for c in checks if c['dur'] == dur}):
            held = [c['held'] for c in checks if (c['dur'], c['run']) == (dur, run) and
                    c['held'] is not None]
            med = float(np.median(held)) if held else None
            rep = ref.get('heldout')
            rows.append([f'{dur:g} s, {run}', len(held), C.fmt(med),
                         C.fmt(rep), '-' if med is None or not rep else f'{med / rep:.2f}x',
                         f"{ref.get('samples_added', '-')}, {ref.get('refits_ok', '-')}"])
    return ['### Held-out NMSE: the live models beside a dgp-replay of the same stream', '',
            'dgp-replay: the same stream through `OnlineEstimator` in line (`refit_mode=sync`, '
            'the defaults, `dgp_ros.replay.build_config`): every sample reaches the model before '
            'the next answer. Target: the live models within 1.2x of it.', '',
            C.md_table(['duration, run', 'models', 'live median', 'dgp-replay',
                        'live / replay', 'replay: samples learned, refits ok'], rows), '']


def _profile_lines(profiles) -> list:
    """Return the lines of the profile: stages per message, one column per profiled tree."""
    profiles = [(label, r) for label, r in profiles
                if ((r.get('est_cpu') or {}).get('profile') or {}).get('stages')]
    if not profiles:
        return []
    cols = [(label, r['est_cpu']['profile'], r) for label, r in profiles]
    names = [n for n, _, _ in cols[0][1]['stages']]
    rows = []
    for i, name in enumerate(names):
        rows.append([name] + [f'{pr["stages"][i][1]:.1f}' for _, pr, _ in cols])
    rows.append(['**main thread, total**'] + [
        f'**{sum(x[1] for x in pr["stages"]):.1f}**' for _, pr, _ in cols])
    rows.append(['snapshot receiver thread'] + [f'{pr["receiver_us"]:.1f}' for _, pr, _ in cols])
    rows.append(['middleware threads (DDS)'] + [f'{pr["dds_us"]:.1f}' for _, pr, _ in cols])
    rows.append(['messages per wake-up'] + [C.fmt(r['sum'].get('per_wakeup'))
                                            for _, _, r in cols])
    rows.append(['(profiled run: node CPU us/msg, bg cores)'] + [
        f'{r["sum"].get("us_node", 0):.0f}, {r["sum"]["bg"]:.2f}' for _, _, r in cols])
    return ['### The path of one message, by stage (us of thread CPU per message)', '',
            'One profiled run per tree (`DGP_PATH_PROFILE=1`, bench/path_profile.py): each call '
            "of a stage's functions charged to it exclusively, the profiler's own cost per call "
            '(about 2.5 us: two thread-clock reads) taken out; the executor is what the main '
            'thread spends outside every stage (waiting, taking messages off the subscription, '
            'dispatching, the timer and services). Its own CPU makes these runs slower than the '
            'others: compare the columns with each other, the CPU of the unprofiled runs above '
            'with the relay.', '',
            C.md_table(['stage'] + [label for label, _, _ in cols], rows), '']


def _target_rows(checks: list) -> list:
    rows = []
    keys = sorted({(c['dur'], c['run']) for c in checks})
    med = lambda v: C.fmt(float(np.median(v))) if v else '-'      # noqa: E731
    mx = lambda v: C.fmt(float(np.max(v))) if v else '-'          # noqa: E731
    for dur, run in keys:
        cs = [c for c in checks if (c['dur'], c['run']) == (dur, run)]
        rm = [c['rm'] for c in cs if c['rm'] is not None]
        rp = [c['rp'] for c in cs if c['rp'] is not None]
        gr = [c['last'] / c['first'] for c in cs if c['first'] and c['last']]
        sw = [c['swap'] for c in cs if c['swap'] is not None]
        gp = [c['gp'][3] for c in cs if c['gp']]
        rf = [c['refit'][3] for c in cs if c['refit']]
        gate = lambda ok: '' if ok is None else (' met' if ok else ' **missed**')  # noqa: E731
        rc = [c['rc'] for c in cs if c.get('rc') is not None]
        rows.append([f'{dur:g} s, {run}', len(cs),
                     f'{100 * min(c["answered"] for c in cs):.2f} %' +
                     gate(min(c['answered'] for c in cs) >= 1.0),
                     mx(rc) + gate(max(rc) <= CPU_X if rc else None),
                     mx(rm) + gate(max(rm) <= MEDIAN_X if rm else None),
                     f'{med(rp)}, {mx(rp)}' + gate(max(rp) <= P99_X if rp else None),
                     f'{med(gr)}, {mx(gr)}' + gate(float(np.median(gr)) <= GROWTH_X if gr
                                                   else None),
                     med([c['learned'] for c in cs if c['learned'] is not None]),
                     f'{sum(1 for c in cs if c["trained"])} of {len(cs)}',
                     med([c['held'] for c in cs if c['held'] is not None]),
                     f'{med(sw)}, {mx(sw)}', mx(gp), mx(rf),
                     med([c['bg'] for c in cs])])
    return rows


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv, _extra)
    C.localhost_only()
    durations = [float(x) for x in a.durations.split(',') if x]
    if a.quick:
        durations, a.repeat = [4.0], 1
        a.profile_seconds = min(a.profile_seconds, 4.0)
    scheds = [x for x in a.sched.split(',') if x]
    names = list(ARM_JOINTS['panda'])
    urdf = example_robot_urdf('panda')
    # run_one's options: the node's defaults
    ra = SimpleNamespace(passivity='', queue_depth=None)
    stream = ''
    if a.stream == 'real':
        if not os.path.exists(os.path.join(a.data, 'panda_log_train.npz')):
            C.log(f'arm_floor: {a.data} has no panda_log_train.npz: the real stream is skipped '
                  '(run with --stream sim)')
            return 0
        stream = a.data
        z = np.load(os.path.join(a.data, 'panda_log_train.npz'), allow_pickle=False)
        rng = np.abs(z['tau_friction_offline']).max(axis=0)
        stream_text = (f"the real Panda's friction residual ({a.data}, first "
                       f'{REAL_SPLIT_S:g} s looped at its own timing, 7 joints, no inverse '
                       'dynamics: the defaults)')
    else:
        rng = np.ones(len(names))
        stream_text = 'the simulated Panda at 1 kHz, `inverse_dynamics=urdf`'
    t0 = time.perf_counter()
    groups = []
    with tempfile.TemporaryDirectory() as tmp:
        work = a.keep or tmp
        os.makedirs(work, exist_ok=True)
        before = ''
        if a.before_rev:
            from arm_live import _before_tree
            before = _before_tree(a.before_rev, work)
        profiles = []
        if a.profile_seconds > 0:
            # the path's stages, one profiled run per tree (their CPU is not compared)
            for label, tree in [('after (this tree)', '')] + \
                    ([(f'before ({a.before_rev})', before)] if before else []):
                x = Scenario('profile', f'{a.profile_seconds:g} s, profiled, {label}',
                             f'1000:{a.profile_seconds:g}', stream=stream, tree=tree,
                             env={'DGP_PATH_PROFILE': '1'})
                x.kind = 'profile'
                r = _run(x, ra, work, urdf, names, rng, a.data)
                profiles.append((label, r))
        replays = {}
        if a.replay and stream:
            for dur in durations:
                C.log(f'arm_floor: dgp-replay of the {dur:g} s stream')
                replays[dur] = replay_heldout(a.data, dur, names)
                C.log(f'arm_floor: dgp-replay {dur:g} s: {replays[dur]}')
        for dur in durations:
            n = a.repeat_long if dur > 30 and a.repeat_long else a.repeat
            for i in range(n):
                phases = f'1000:{dur:g}'

                def sc(kind, label, **kw):
                    x = Scenario(f'{kind}_{int(dur)}', f'{dur:g} s, {label}', phases,
                                 stream=stream, probe_period=0.2, **kw)
                    x.kind = kind
                    return x
                plan = [sc('relay', f'bare rclpy relay ({a.relay_executor})', node='relay',
                           executor=a.relay_executor)]
                for sched in scheds:
                    if sched == 'nice' and len(scheds) > 1 and i >= a.nice_runs:
                        continue
                    plan.append(sc(sched, 'estimator, learner ' +
                                   ('SCHED_IDLE' if sched == 'idle' else 'nice 10'),
                                   refit_period=2.0, env={'DGP_LEARNER_SCHED': sched}))
                if before and i == 0:
                    plan.append(sc('before', f'estimator, code of {a.before_rev}',
                                   refit_period=2.0, tree=before))
                g = {'name': f'{dur:g} s #{i + 1}', 'dur': dur, 'runs': []}
                for x in plan:
                    r = _run(x, ra, work, urdf, names, rng, a.data)
                    r['node'], r['kind'] = x.node, x.kind
                    g['runs'].append(r)
                groups.append(g)
                _write(a, groups, time.perf_counter() - t0, stream_text, profiles, replays)
    return 0


def _write(a, groups, wall, stream_text, profiles=(), replays=None) -> None:
    """Write the section (after every repeat: a run cut short keeps what it measured)."""
    C.write_section(a.out, SECTION, section(a, groups, wall, stream_text, profiles, replays))
    with open(os.path.join(C.plot_dir(a.out), 'arm_floor_runs.json'), 'w') as f:
        json.dump([{**g, 'runs': [{k: v for k, v in r.items() if k not in ('diags',)}
                                  for r in g['runs']]} for g in groups], f,
                  default=lambda o: o.tolist() if hasattr(o, 'tolist') else str(o))


if __name__ == '__main__':
    random.seed()
    sys.exit(main())

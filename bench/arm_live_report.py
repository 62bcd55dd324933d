"""
The numbers and the section of bench/arm_live.py.

``summarize`` turns one run's raw results (arrival times, answers, probes, CPU) into its row;
``section`` returns the text of the ``arm_live`` section of BENCHMARKS.md from the rows, with
the targets of the issue it answers (``targets``).
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

import common as C


def _pct(x, q):
    return float(np.percentile(x, q)) if len(x) else None


def summarize(r: dict, rng: np.ndarray) -> dict:
    """Return the row numbers of one run (ms, %, cores)."""
    meas, ans, eff = r['lis']['meas'], r['lis']['ans'], r['lis']['effort']
    pub = r['player']['published']
    m = dict(zip(meas[:, 0].astype(np.int64), meas[:, 1]))
    a_t = dict(zip(ans[:, 0].astype(np.int64), ans[:, 1]))
    paired = sorted(set(m) & set(a_t))
    lat = np.array([a_t[s] - m[s] for s in paired]) * 1e3
    age = (ans[:, 1] - ans[:, 0] * 1e-9) * 1e3
    s = {'published': pub, 'received': len(m), 'answers': len(a_t), 'paired': len(paired),
         'answered': len(a_t) / pub if pub else 0.0,
         'lat_p50': _pct(lat, 50), 'lat_p99': _pct(lat, 99),
         'lat_max': float(lat.max()) if len(lat) else None,
         'age_p50': _pct(age, 50), 'age_p99': _pct(age, 99),
         'bg': r['bg_cores'], 'load': r['load'], 'tracebacks': r['tracebacks'],
         'est_rc': r['est_rc']}
    if len(eff):
        s['answer_ratio'] = float(np.max(np.abs(eff[:, :rng.size]) / rng))
    # the backlog: the answers' age in the middle and the last third of the stream
    if len(age) > 30:
        order = np.argsort(ans[:, 0])
        thirds = np.array_split(age[order], 3)
        s['age_mid_p50'] = float(np.median(thirds[1]))
        s['age_last_p50'] = float(np.median(thirds[2]))
    # the longest silence of the answers while the stream ran (and of the measurements)
    if len(ans) > 2:
        t_a = np.sort(ans[:, 1])
        t_m = np.sort(meas[:, 1]) if len(meas) else t_a
        inside = (t_a >= t_m[0] + 0.5) & (t_a <= t_m[-1])
        g = np.diff(t_a[inside]) * 1e3 if inside.sum() > 2 else np.zeros(1)
        s['ans_gap_max'] = float(g.max())
        s['meas_gap_max'] = float(np.diff(t_m).max() * 1e3) if len(t_m) > 2 else None
        # around each kill: from the last answer before it until 0.5 s after the learner was
        # back (the whole run's longest silence may be elsewhere, e.g. the first model's swap)
        kg = []
        for k in r.get('kills', []):
            t0 = k.get('t_kill')
            if t0 is None:
                continue
            t1 = t0 + (k.get('t_back') or 2.0) + 0.5
            i0 = max(0, int(np.searchsorted(t_a, t0)) - 1)
            w = t_a[i0:int(np.searchsorted(t_a, t1))]
            if len(w) > 1:
                kg.append(float(np.diff(w).max() * 1e3))
        if kg:
            s['kill_gap_max'] = max(kg)
    d = r['diags'][-1] if r['diags'] else {}
    s['diag'] = d
    wall = r['wall_s']
    s['node_cores'] = r.get('cpu_estimator_s', 0.0) / wall
    s['learner_cores'] = r.get('cpu_estimator_kids_s', 0.0) / wall     # fork server, learner
    ec = r['est_cpu']
    if ec and ec.get('calls'):
        # from its first message callback to its last (the wrapper in live_procs.py)
        n = ec.get('received') or int(d.get('messages_received', 0) or 0) or 1
        s['us_ours'] = ec['callbacks_s'] / n * 1e6
        s['us_exec'] = (ec['main_thread_s'] - ec['callbacks_s']) / n * 1e6
        s['us_proc'] = ec['process_s'] / n * 1e6
    # the diagnostics' inter-arrival (their period is 0.5 s unless the scenario sets it)
    t_d = np.array([x['t'] for x in r['diags']])
    if len(t_d) > 2:
        s['diag_gap_max'] = float(np.diff(t_d).max())          # as the listener got them
    t_n = np.array(ec.get('diag_times', []) if ec else [])
    if len(t_n) > 2:
        s['diag_gap_node'] = float(np.diff(t_n).max())         # as the node sent them
    for kind, vals in r.get('first_probes', {}).items():
        s[f'first_{kind}'] = float(vals[0][1]) * 1e3 if vals else None
    for kind, vals in r['probes'].items():
        rt = np.array([v[1] for v in vals]) * 1e3
        if len(rt):
            s[f'probe_{kind}'] = (len(rt), _pct(rt[np.isfinite(rt)], 50) if np.isfinite(
                rt).any() else None, _pct(rt[np.isfinite(rt)], 99) if np.isfinite(rt).any()
                else None, float(rt.max()), int((~np.isfinite(rt)).sum()))
    if r['kills']:
        k = r['kills']
        s['kills'] = len(k)
        s['kills_mid_refit'] = sum(1 for x in k if x.get('refit_running') == 'True')
        s['t_fork'] = [x.get('t_fork') for x in k]
        s['t_back'] = [x.get('t_back') for x in k]
        s['learner_restarts'] = d.get('learner_restarts')
    return s


# ----------------------------------------------------------------------------- the section
def fmt_ms(x):
    return C.fmt(x) if x is not None else '-'


def _gate(ok: Optional[bool]) -> str:
    return '-' if ok is None else ('met' if ok else '**missed**')


def section(a, runs: List[dict], held: Optional[dict], wall: float, names) -> str:
    lines = [C.header_lines('A 7-joint arm at 1 kHz, live (player -> estimator node -> '
                            'listener)', 'bench/arm_live.py', a.quick, wall), '',
             f'A simulated Panda (7 joints and a finger joint, like its driver) published by a '
             f'player process at absolute deadlines into the `estimator` node (`model=full`, '
             f'`prior=auto`, `passivity={a.passivity or "default"}`, `inverse_dynamics=urdf`, '
             f'other parameters default unless the scenario says; its own executor is the '
             f'wait-set loop unless named) and a listener process, all on this 2-core machine, '
             f'DDS isolated per run. **bg** is the CPU the machine spent outside these '
             f'processes during the run (other jobs), in cores of the 2; load is the 1-min '
             f'load average at the end. Latency: the listener receives the measurement -> it '
             f"receives the answer; age: the answer received minus the measurement's stamp "
             f'(its deadline on the wall clock). Answered: answers received / messages '
             f'published. |answer| / range: the largest |estimate| over the per-joint range of '
             f'the residual the estimator learns from. CPU us/msg (per message received): ours '
             f"= in the message callbacks; executor = the rest of the node's main thread; "
             f'process = every thread of the node process (not the learner).', '']
    hdr = ['scenario', 'answered', 'latency p50 / p99 / max ms', 'age p50 / p99 ms',
           '|answer| / range', 'node / learner cores', 'CPU us/msg ours / executor / process',
           'lost (listener saw / node received)', 'bg cores', 'load']
    rows = []
    for r in runs:
        s = r['sum']
        d = s['diag']
        rows.append([r['label'], f'{100 * s["answered"]:.2f} %',
                     f'{fmt_ms(s["lat_p50"])} / {fmt_ms(s["lat_p99"])} / {fmt_ms(s["lat_max"])}',
                     f'{fmt_ms(s["age_p50"])} / {fmt_ms(s["age_p99"])}',
                     C.fmt(s.get('answer_ratio')),
                     f'{s.get("node_cores", 0):.2f} / {s.get("learner_cores", 0):.2f}',
                     f'{C.fmt(s.get("us_ours"))} / {C.fmt(s.get("us_exec"))} / '
                     f'{C.fmt(s.get("us_proc"))}',
                     f'{s["published"] - s["received"]} / '
                     f'{d.get("messages_received", "-")} of {s["published"]}',
                     f'{s["bg"]:.2f}', f'{s["load"]:.2f}'])
    lines += [C.md_table(hdr, rows), '']
    by = {}
    for r in runs:
        by.setdefault(r['scenario'], []).append(r)
    # the main scenario in the form the CI smoke test reads
    if 'khz' in by:
        r = by['khz'][0]
        s, d = r['sum'], r['sum']['diag']
        rows = [['answered (of published)', f'{100 * s["answered"]:.2f} %'],
                ['received by the listener', f'{s["received"]} of {s["published"]}'],
                ['end-to-end latency median / p99', f'{fmt_ms(s["lat_p50"])} / '
                                                    f'{fmt_ms(s["lat_p99"])} ms'],
                ['estimator: messages received', d.get('messages_received', '-')],
                ['estimator: messages missing (from stamp gaps)',
                 d.get('messages_missing', '-')],
                ['estimator: stamp -> answer median / p99 (s)',
                 f'{d.get("stamp_to_answer_median_s", "-")} / '
                 f'{d.get("stamp_to_answer_p99_s", "-")}'],
                ['estimator: samples learned / refits ok / rejected',
                 f'{d.get("samples_added", "-")} / {d.get("refits_ok", "-")} / '
                 f'{d.get("refits_rejected", "-")}'],
                ['estimator: certified / guarantee', f'{d.get("certified", "-")} / '
                                                     f'{d.get("guarantee", "-")}'],
                ['estimator: status at the end', d.get('message', '-')],
                ['estimator exit status after SIGINT (model saved)', s['est_rc']],
                ['negative power in 10^5 random velocities',
                 held['negative_power'] if held else '-']]
        lines += ['### 1 kHz, the main run', '', C.md_table(['quantity', 'value'], rows), '']
        if held:
            lines.append(C.md_table(
                ['joint', 'held-out NMSE (live model)', 'sigmoid model', 'ratio'],
                [[j, C.fmt(x), C.fmt(y), C.fmt(x / y)] for j, x, y in
                 zip(names, held['nmse'], held['nmse_sigmoid'])]))
    if 'services' in by or 'hog' in by:
        rows = []
        for key in ('services', 'hog'):
            for r in by.get(key, []):
                s = r['sum']
                for kind in ('get_parameters', 'refit'):
                    p = s.get(f'probe_{kind}')
                    if p:
                        rows.append([r['label'], kind, p[0], f'{fmt_ms(p[1])} / {fmt_ms(p[2])} / '
                                     f'{fmt_ms(p[3])}', p[4], fmt_ms(s.get(f'first_{kind}'))])
                rows.append([r['label'], '/diagnostics (period 0.5 s)', '-',
                             f'largest interval {C.fmt(s.get("diag_gap_node"))} s sent, '
                             f'{C.fmt(s.get("diag_gap_max"))} s received', '-', '-'])
        lines += ['### Services and /diagnostics under the stream', '',
                  'Round trips from a prober process that does nothing else (`get_parameters` is '
                  "served by the node's executor alone; `~/refit` is answered by the learner, or "
                  "after 20 ms by the node saying the request is queued). A client's first "
                  'call also waits for DDS to match its reply reader with the service: it is '
                  'shown apart and not counted.', '',
                  C.md_table(['scenario', 'service', 'calls', 'round trip p50 / p99 / max ms',
                              'unanswered', 'first call ms'], rows), '']
    if 'kill' in by:
        rows = []
        for r in by['kill']:
            s = r['sum']
            fork = [x for x in s.get('t_fork', []) if x is not None]
            back = [x for x in s.get('t_back', []) if x is not None]
            rows.append([r['label'], f'{s.get("kills", 0)} ({s.get("kills_mid_refit", 0)})',
                         f'{fmt_ms(s.get("kill_gap_max"))} / {fmt_ms(s.get("ans_gap_max"))} '
                         f'(measurements {fmt_ms(s.get("meas_gap_max"))})',
                         f'{C.fmt(np.median(fork) * 1e3) if fork else "-"} / '
                         f'{C.fmt(max(fork) * 1e3) if fork else "-"}',
                         f'{C.fmt(np.median(back)) if back else "-"} / '
                         f'{C.fmt(max(back)) if back else "-"} ({len(back)} of '
                         f'{s.get("kills", 0)})', s.get('learner_restarts', '-'),
                         s['tracebacks'], s['est_rc']])
        lines += ['### The learner killed mid-refit', '',
                  'SIGKILL to the learner process 0.2 s after a `~/refit` reply (mid-refit: '
                  'the refit is running at the kill per the last /diagnostics, period 0.1 s). '
                  'Back: until /diagnostics (period 0.1 s) shows the restart with the learner '
                  'alive.', '',
                  'Longest answer gap: around the kills (from the last answer before one '
                  'until 0.5 s after the learner was back) / over the whole run after its '
                  'first 0.5 s.', '',
                  C.md_table(['scenario', 'kills (mid-refit)',
                              'longest answer gap ms: kills / run',
                              'new learner forked median / max ms', 'back median / max s',
                              'restarts counted', 'tracebacks in its log', 'exit status'],
                             rows), '']
    if 'learn_all' in by:
        rows = []
        for r in by['learn_all']:
            s = r['sum']
            d = s['diag']
            learned = int(d.get('samples_added', 0) or 0)
            rows.append([r['label'], d.get('messages_received', '-'), learned,
                         f'{learned / r["seconds"]:.0f}', d.get('samples_pending', '-'),
                         f'{d.get("samples_skipped", "-")} / {d.get("samples_outliers", "-")}',
                         d.get('samples_dropped', '-'), f'{100 * s["answered"]:.2f} %',
                         f'{s.get("node_cores", 0):.2f}', f'{s.get("learner_cores", 0):.2f}',
                         C.fmt(s.get('us_ours'))])
        lines += ['### Every message learned (buffer 500)', '',
                  "Learned per second of stream: the learner process's `samples_added` at the "
                  "end over the stream's length (what went in end to end); the ring between "
                  'the processes drops (and counts) what the learner cannot take.', '',
                  C.md_table(['scenario', 'messages received', 'samples learned',
                              'learned / s', 'still in the ring at the end',
                              'skipped / outliers', 'dropped at the ring', 'answered',
                              'node cores', 'learner cores', 'message path us/msg'], rows), '']
    cpu_rows = [r for r in runs if r['scenario'].startswith('cpu_') or r['scenario'] == 'khz']
    if any(r['scenario'].startswith('cpu_') for r in runs):
        rows = []
        for r in cpu_rows:
            s = r['sum']
            rows.append([r['label'], C.fmt(s.get('us_exec')), C.fmt(s.get('us_ours')),
                         C.fmt(s.get('us_proc')), f'{100 * s["answered"]:.2f} %',
                         f'{s["bg"]:.2f}'])
        lines += ['### CPU per message on the message path', '',
                  "Thread CPU of the node's main thread per message received: in the message "
                  'callbacks (ours: validate, hand over to the learner, answer, publish) and '
                  'the rest (the executor: waiting, taking, dispatching); process: every '
                  'thread of the node process (DDS, the snapshot receiver).', '',
                  C.md_table(['run', 'executor us/msg', 'ours us/msg', 'process us/msg',
                              'answered', 'bg cores'], rows), '']
    lines += ['### Targets', '',
              C.md_table(['target', 'status', 'measured'], targets(by, held)), '']
    return '\n'.join(lines)


def targets(by: dict, held: Optional[dict]) -> list:
    out = []

    def first(key):
        return by[key][0]['sum'] if key in by else None
    s = first('khz')
    if s:
        out.append(['1 kHz: >= 99 % answered', _gate(s['answered'] >= 0.99),
                    f'{100 * s["answered"]:.2f} % (bg {s["bg"]:.2f})'])
        out.append(['1 kHz: end-to-end p99 <= 5 ms', _gate((s['lat_p99'] or 1e9) <= 5),
                    f'{fmt_ms(s["lat_p99"])} ms'])
        out.append(['1 kHz: median <= 2 ms', _gate((s['lat_p50'] or 1e9) <= 2),
                    f'{fmt_ms(s["lat_p50"])} ms'])
        out.append(['1 kHz: no answer over 2x the data range',
                    _gate(s.get('answer_ratio', 1e9) <= 2), C.fmt(s.get('answer_ratio'))])
    s = first('hz500')
    if s:
        out.append(['500 Hz: >= 99.9 % answered', _gate(s['answered'] >= 0.999),
                    f'{100 * s["answered"]:.2f} % (bg {s["bg"]:.2f})'])
    s = first('hog')
    if s:
        grows = s.get('age_last_p50') is not None and \
            s['age_last_p50'] > 2 * s['age_mid_p50'] + 20
        p = s.get('probe_get_parameters')
        out.append(['one core busy: >= 95 % answered at 1 kHz', _gate(s['answered'] >= 0.95),
                    f'{100 * s["answered"]:.2f} % (bg {s["bg"]:.2f})'])
        out.append(['one core busy: no backlog that grows', _gate(not grows),
                    f'answer age median {fmt_ms(s.get("age_mid_p50"))} ms (middle third) -> '
                    f'{fmt_ms(s.get("age_last_p50"))} ms (last third)'])
        out.append(['one core busy: services within 100 ms',
                    _gate(p is not None and p[3] <= 100 and not p[4]),
                    f'get_parameters max {fmt_ms(p[3]) if p else "-"} ms'])
    s = first('services')
    if s:
        for kind in ('get_parameters', 'refit'):
            p = s.get(f'probe_{kind}')
            out.append([f'flood: {kind} answered within 100 ms',
                        _gate(p is not None and p[3] <= 100 and not p[4]),
                        f'max {fmt_ms(p[3]) if p else "-"} ms, unanswered {p[4] if p else "-"}'])
        out.append(['flood: /diagnostics within 100 ms of its period',
                    _gate(s.get('diag_gap_node', 9) <= 0.6),
                    f'largest interval {C.fmt(s.get("diag_gap_node"))} s sent by the node, '
                    f'{C.fmt(s.get("diag_gap_max"))} s received (period 0.5 s)'])
    s = first('kill')
    if s:
        back = [x for x in s.get('t_back', []) if x is not None]
        out.append(['learner SIGKILL x10: answers never stop > 50 ms',
                    _gate(s.get('kill_gap_max', 1e9) <= 50),
                    f'{fmt_ms(s.get("kill_gap_max"))} ms around the kills '
                    f'({fmt_ms(s.get("ans_gap_max"))} ms over the whole run)'])
        out.append(['learner SIGKILL x10: back within 2 s',
                    _gate(len(back) == s.get('kills') and max(back) <= 2.0),
                    f'max {C.fmt(max(back)) if back else "-"} s, {len(back)} of '
                    f'{s.get("kills")}'])
        out.append(['learner SIGKILL x10: no traceback', _gate(s['tracebacks'] == 0),
                    str(s['tracebacks'])])
    s = by.get('learn_all')
    if s:
        r = s[0]
        d = r['sum']['diag']
        learned = int(d.get('samples_added', 0) or 0) / r['seconds']
        queued = int(d.get('samples_pending', 0) or 0)
        # a 1 kHz stream is the ceiling: kept up = (almost) all of it learned, nothing queued
        # (the first residual trails its message by the filter's half window, 0.05 s)
        out.append(['every message learned at buffer 500: >= 1000 msg/s end to end',
                    _gate(learned >= 990 and queued < 100),
                    f'{learned:.0f} msg/s learned of a 1 kHz stream, {queued} still queued for '
                    'the learner at the end (the learner carries the cost; the message path '
                    'only pushes a row into the ring)'])
    if held:
        from robot_arms_runs import NOISE_SD
        trio = zip(held['nmse'], held['nmse_sigmoid'], held['friction_rms'])
        ok = all(x <= 0.5 * y for x, y, f in trio if f > NOISE_SD)
        out.append(['held-out NMSE <= 0.5 x sigmoid on every joint whose friction exceeds '
                    'the noise', _gate(ok), ', '.join(C.fmt(x / y) for x, y in
                                                      zip(held['nmse'], held['nmse_sigmoid']))])
    return out

"""
The ``hostile_input`` section of RELIABILITY.md (``bench/hostile.py``).

The summary table by attack class (``summarize``) and the section with every class's tables
(``build_report``).
"""
from __future__ import annotations

import os
from typing import List

from common import fmt, header_lines, md_table

#: the command that writes the section (its header names it)
SCRIPT = 'python bench/hostile.py'


def yes_no(b) -> str:
    return 'yes' if b else 'no'


def tbl(headers, rows) -> str:
    """``common.md_table`` with the cells' own pipes escaped (|v|, |tau_hat|)."""
    esc = lambda c: str(c).replace('|', '\\|')  # noqa: E731
    return md_table([esc(h) for h in headers], [[esc(c) for c in r] for r in rows])


def build_report(R: dict, quick: bool, seconds: float) -> str:
    L = [header_lines('Hostile input', SCRIPT, quick, seconds)]
    L.append('The adversarial trial of the node and its tools, repeated by one command '
             '(`python -m bench hostile`). '
             'Everything a peer can send (messages), set (parameters) or hand over (model files, '
             'bags) is thrown at the estimator; each row counts the inputs and the result. '
             '"Documented exceptions" are `ValueError` from configuration and model files, '
             '`BagError` / exit 2 from the bag tools; `process()` must never raise. '
             'Non-passive means `qd . tau_hat` below `-8 eps sum|qd_i||tau_hat_i|` (rounding) '
             'or a negative published power. All inputs and decoys (a text file, a text '
             "file named `*.npz`, a user's numpy `.npz`, a directory, a FIFO, symlinks out of "
             'the directory and to `/dev/zero`) live in a private temporary directory that is '
             'fingerprinted (inode, size, mtime, SHA-256) before and after, together with '
             '`/dev/full`, `/dev/zero` and `/dev/null`.\n')
    S = R['summary']
    L.append('### Summary\n')
    L.append(tbl(
        ['Attack class', 'Inputs', 'Crashes', 'Non-finite outputs', 'Non-passive outputs',
         'Learning frozen?', 'Files touched other than the model',
         'Exceptions other than the documented ones', 'Result'],
        [[r['cls'], r['inputs'], r['crashes'], r['nonfinite'], r['nonpassive'], r['frozen'],
          r['touched'], r['exceptions'], r['result']] for r in S]))
    if R.get('touched'):
        L.append('Files touched: ' + ', '.join(f'`{p}`' for p in R['touched']) + '\n')

    # 1. messages
    L.append('### 1. Messages\n')
    L.append('In-process: `OnlineEstimator.process` (sync refits, buffer 200, min_samples 20, '
             'refit every 10 s of stamp time, `model_path` set), one long-lived estimator per '
             'configuration taking every class in turn; good messages are interleaved so that '
             'it keeps learning. "Truthful" counts messages whose counters disagree with what '
             'happened (an unanswered message must raise exactly one rejection counter, an '
             'answered one none, and `messages_received` must count it).\n')
    for run in R['messages']:
        L.append(f'**{run["label"]}** (configuration `model={run["config"]["model"]}, '
                 f'passivity={run["config"]["passivity"]}`)\n')
        rows = []
        for T in run['tallies'].values():
            rows.append([T.name, T.sent, T.answered, T.reasons(), T.nonfinite, T.nonpassive,
                         T.strict_negative, sum(T.exceptions.values()), T.untruthful,
                         ', '.join(f'{a} {b}' for a, b in T.unexpected.items()) or '-',
                         T.refits, f'{T.seconds:.2f}', '; '.join(T.notes) or '-'])
        L.append(tbl(['Class', 'Messages', 'Answered', 'Rejected (reason count)',
                      'Non-finite', 'Non-passive', 'Power < 0 within rounding',
                      'Exceptions', 'Untruthful', 'Other than expected', 'Refits',
                      'Seconds', 'Notes'], rows))
        lr = run['learning']
        L.append(f'After all classes: samples_added {lr["added_before_outlier"]} before the '
                 f'outlier, {lr["added_after_outlier"]} after it, {lr["added_end"]} at the end; '
                 f'NMSE on the last good data {fmt(lr["nmse_recovery"])} (a control estimator fed '
                 f'only the {lr["good_messages"]} good messages, same order and stamps: '
                 f'{fmt(lr["nmse_control"])}, samples_added {lr["added_control"]}); '
                 f'max |tau_hat| after '
                 f'the outlier {fmt(lr["max_abs_tau_after_outlier"])}; learning frozen: '
                 f'{yes_no(lr["frozen"])}; still poisoned at the end (NMSE above max(10 x '
                 f'control, 0.05)): {yes_no(lr["poisoned"])}. Counters: received '
                 f'{lr["counted"]["received"]}, '
                 f'accepted {lr["counted"]["accepted"]}, rejected {lr["counted"]["rejected"]} '
                 f'(agree with what was sent: {yes_no(lr["counters_agree"])}); '
                 f'nonfinite_outputs {lr["nonfinite_outputs"]}, passivity_fallbacks '
                 f'{lr["passivity_fallbacks"]}; trained {lr["trained"]}, certified '
                 f'{lr["certified"]} ({lr["method"]}); learning clock '
                 f'`{lr["learning_clock"]}`. Final status (level {lr["level"]}): '
                 f'"{lr["message"]}".\n')
    o = R['outlier']
    L.append(f'**Finding 1 exactly** (fresh estimator, full/projected): trained on '
             f'{o["added_before"]} samples (NMSE {fmt(o["nmse_before"])}), one message with '
             f'|v| = 9999, then {o["stamp_seconds_after"]:.0f} s of good data: samples_added '
             f'{o["added_before"]} -> {o["added_after"]}, NMSE {fmt(o["nmse_after"])} (the '
             f'same data without the outlier: {fmt(o["nmse_control"])}), max '
             f'|tau_hat| {fmt(o["max_abs_tau_after"])} (max |truth| {fmt(o["max_abs_truth"])}), '
             f'samples_outliers '
             f'{o["outliers"]}, status level {o["level"]} "{o["message"]}". Learning frozen: '
             f'{yes_no(o["frozen"])}; poisoned: {yes_no(o["poisoned"])}.\n')
    st = R['stamps']
    L.append(f'**Finding 6 exactly** (fresh estimator, every stamp 0, one message every 2 ms of '
             f'wall time): after {st["n"]} messages '
             f'trained {st["zero"]["trained"]}, samples_added {st["zero"]["added"]}, learning '
             f'clock `{st["zero"]["clock"]}`, status level {st["zero"]["level"]} '
             f'"{st["zero"]["message"]}". Then {st["n"]} messages with advancing stamps: '
             f'samples_added {st["after"]["added"]}, learning clock `{st["after"]["clock"]}`, '
             f'status level {st["after"]["level"]} "{st["after"]["message"]}".\n')
    for b in R['burst']:
        L.append(f'**A burst of five in-range huge efforts** ({b["label"]}, trained on '
                 f'{b["added_before"]} samples; effort 5e7 < max_abs_effort 1e8, three in a row '
                 f'count as a real change of motion: {b["learned"]} of the 5 entered the buffer, '
                 f'the others being near-duplicates), then good data; the control is a second '
                 f'estimator fed the same good data without the burst:\n')
        L.append(tbl(['Good data after (s)', 'NMSE', 'NMSE of the control', 'max |tau_hat|',
                      'max |truth|', 'samples_added', 'Status'],
                     [[f'{r["seconds"]:.0f}', fmt(r['nmse']), fmt(r['nmse_control']),
                       fmt(r['max_tau']),
                       fmt(r['max_truth']), r['added'],
                       f'{r["level"]}: {r["message"][:90]}'] for r in b['rows']]))
    lv = R.get('live') or {}
    if lv.get('skipped'):
        L.append(f'Live over DDS: skipped ({lv["skipped"]}).\n')
    elif lv:
        L.append(f'Live over DDS (the `estimator` node process, domain {R["domain"]}, '
                 'localhost discovery; best-effort input, so a flood may drop messages before '
                 'the node sees them: "received" is the node\'s own count). Every '
                 '`~/damping_force`, `~/damping_force_stddev`, `~/damping_matrix` and '
                 '`~/dissipated_power` message received was checked.\n')
        L.append(tbl(['Class', 'Sent', 'Received by the node', 'Answers received',
                      'Rejected (node counters)', 'Bad outputs', 'Node alive', 'msg/s'],
                     [[r['name'], r['sent'], r['received'], r['answers'], r['rejected'],
                       r['bad'], yes_no(r['alive']),
                       f'{r["rate"]:.0f}' if r['name'].startswith(('flood', 'repeats'))
                       else '-']
                      for r in lv['classes']]))
        lr = lv.get('learning', {})
        L.append(f'Outputs received: {", ".join(f"{k} {v}" for k, v in lv["got"].items())}; '
                 f'bad: {lv["bad"] or "none"}. After the outlier: samples_added '
                 f'{lr.get("added_before")} -> {lr.get("added_after")}. Node exit status '
                 f'on SIGINT: {lv["rc"]} (traceback in its log: {yes_no(lv["traceback"])}); '
                 f'peak RSS {lv["node_max_rss_mib"]:.0f} MiB; its model file saved: '
                 f'{yes_no(lv["model_saved"])}.\n')

    # 2. parameters
    P = R['params']
    L.append('### 2. Parameter sets\n')
    c = P['counts']
    L.append(f'In-process: {P["cases"]} hostile sets (every parameter: inf, -inf, nan, 1e308, '
             f'1e200, below / above its range, huge integers, wrong types, too long; and '
             f'combinations: min_samples > buffer_size, dimensions against the joints, hostile '
             f'`model_path`s, bad `inverse_dynamics`), each through `EstimatorConfig.validate()`, '
             f'`check_reconfigure()` and `reconfigure()` of a trained estimator: '
             f'{c["attempts"]} attempts, refused with a reason naming the parameter '
             f'{c["refused with a reason"]}, accepted by `validate()` alone where it cannot know '
             f'N (expected) {c["accepted by validate() alone (cannot know N; expected)"]}, '
             f'**accepted {c["accepted"]}**, refused with a reason that does not name it '
             f'{c["refused, reason does not name the parameter"]}, other exceptions '
             f'{c["other exception"]}, estimator changed {c["changed something"]} (then rebuilt '
             f'for the next case). Afterwards it still learns: {yes_no(P["still_learning"])} '
             f'(answers {P["tally"].answered}/{P["tally"].sent}, non-finite '
             f'{P["tally"].nonfinite}, non-passive {P["tally"].nonpassive}, exceptions '
             f'{sum(P["tally"].exceptions.values())}).\n')
    if P['problems']:
        L.append('Not refused: ' + '; '.join(f'`{x}`' for x in P['problems'][:20]) + '\n')
    L.append('Per-joint parameters that do not fit the joints, set before the first message '
             '(`joints` not configured, so N is unknown until a message arrives), then 200 '
             'good 3-joint messages:\n')
    L.append(tbl(['Configuration', 'Messages', 'Answered', 'Exceptions from process()',
                  'Non-finite', 'Non-passive', 'Trained', 'Refits failed', 'Status'],
                 [[e['label'], e['tally'].sent, e['tally'].answered,
                   (f'{sum(e["tally"].exceptions.values())} ({e["exception"]})'
                    if e['exception'] else '0'), e['tally'].nonfinite,
                   e['tally'].nonpassive, yes_no(e['trained']), e['refits_failed'],
                   e['message'][:120]] for e in P['early']]))
    if lv and lv.get('params'):
        L.append("Live, through the node's parameter services (`AsyncParameterClient`); after "
                 'each set the watched parameters are read back and `~/save_model` is called '
                 "(it must write the node's own model file only):\n")
        L.append(tbl(['Set', 'Refused', 'Reason (start)', 'Nothing changed', 'Node alive',
                      '~/save_model after it'],
                     [[f'`{r["set"]}`', yes_no(r['refused']),
                       r['reason'][:90], yes_no(r['unchanged']),
                       yes_no(r['alive']), r['save'][:60].replace(
                                os.path.dirname(R['sandbox']), '...')]
                      for r in lv['params']]))
        fr = lv.get('fresh')
        if fr and 'set' in fr:
            L.append(f'Live, a fresh node (no message yet), `{fr["set"]}` then {fr["sent"]} good '
                     f'3-joint messages: set refused {yes_no(fr["refused"])}'
                     + (f' ("{fr["reason"][:100]}")' if fr['refused'] else '') +
                     f'; answers received {fr["answers"]}; node alive '
                     f'{yes_no(fr["alive"])}; exit status {fr["rc"]}; last log line: '
                     f'`{fr["last_line"][:160]}`.\n')
        pi = lv.get('plugin_import')
        if pi:
            L.append(f'Observation: `inverse_dynamics=python:this:no_such_function` set by a '
                     f'peer: refused {yes_no(pi["refused"])} ("{pi["reason"][:100]}"), but the '
                     f'node imported the module `this` while checking it: '
                     f'{yes_no(pi["imported"])}.\n')

    # 3. files
    F = R['files']
    L.append('### 3. Model files\n')
    L.append('Each file through `load_model` in a forked child (seconds and peak RSS above the '
             "child's start), and a copy given as `model_path` to an `OnlineEstimator` "
             '(`certified` for the files that should load, else `projected`; then 30 good '
             'messages, 5 in quick mode: it must train (full mode), answer finite and passive, '
             'and never overwrite a file that is not a dgp_ros model).\n')
    rows = []
    for r in F['rows']:
        mp = r['mp']
        rows.append([r['name'], f'{r["outcome"]}: {r["message"][:80]}'
                     if r['outcome'] != 'ok' else 'loaded' + (
                         f' (certified {r["info"]["certified"]}, stale {r["info"]["stale"]}, '
                         f'method {r["info"]["method"]})' if r['info'] else ''),
                     f'{r["seconds"]:.3f}', f'{r["rss_mib"]:.1f}',
                     f'{mp[0]}: {str(mp[1])[:60]}' if mp[0] != '-' else '-',
                     'ok' if r['ok'] and r['mp_ok'] else '**FAILED**'])
    L.append(tbl(['File', 'load_model', 'Seconds', 'Peak RSS delta (MiB)',
                  'As model_path', 'Result'], rows))
    L.append(f'Max seconds {max(r["seconds"] for r in F["rows"]):.3f}, max peak RSS delta '
             f'{max(r["rss_mib"] for r in F["rows"]):.1f} MiB.\n')
    if lv and lv.get('starts'):
        L.append('Live: the node started with `model_path:=FILE` (a copy of the hostile file): '
                 'exit status 2 with a one-line reason, or it runs with the file not used. '
                 'Peak RSS of the whole node process (the control has no model_path).\n')
        L.append(tbl(['model_path at start', 'Exit status', 'Seconds to exit / first '
                      'diagnostics', 'Peak RSS (MiB)', 'Trained / certified (method)',
                      'load_error / last log line', 'Traceback'],
                     [[r['start'], r['rc'], f'{r["seconds"]:.1f}', f'{r["hwm_mib"]:.0f}',
                       f'{r["trained"]} / {r["certified"]} ({r["method"]})'
                       if r['trained'] != '' else '-',
                       (r['load_error'] or r['first_line'])[:110],
                       yes_no(r['traceback'])] for r in lv['starts']]))

    # 4. bags
    B = R['bags']
    L.append('### 4. Bags\n')
    L.append('Each bag has one topic of a refused type (alone, and next to a good '
             '`sensor_msgs/JointState` topic), played by `dgp-play` and by '
             '`dgp_ros.bags.ros.Player` in a subprocess that then checks `sys.modules`.\n')
    L.append(tbl(['Bag', 'Entry', 'Exit / result', 'Modules imported', 'Message', 'Result'],
                 [[r['bag'], r['entry'], r['rc'], ', '.join(r['imported']) or 'none',
                   r['message'][:100],
                   'ok' if r['ok'] else '**FAILED**'] for r in B['rows']]))
    if R.get('findings'):
        L.append('### Findings\n')
        L.append('\n'.join(f'- {f}' for f in R['findings']) + '\n')
    return '\n'.join(L)


def summarize(R: dict) -> List[dict]:
    S = []
    touched_other = R['touched']
    tf = f'{len(touched_other)}' if touched_other else 'none'
    # 1. messages
    tal = [T for run in R['messages'] for T in run['tallies'].values()]
    tal.append(R['outlier']['tally'])
    tal.append(R['stamps']['tally'])
    tal += [b['tally'] for b in R['burst']]
    lv = R.get('live') or {}
    lclasses = lv.get('classes', [])
    live_msgs = sum(r['sent'] for r in lclasses)
    live_crash = int(bool(lclasses) and (lv.get('rc') not in (0, None) or
                                         not lv.get('alive_at_end', True) or
                                         lv.get('traceback', False)))
    nonfin = sum(T.nonfinite for T in tal) + sum(v for k, v in lv.get('bad', {}).items()
                                                 if 'non-finite' in k)
    nonpas = sum(T.nonpassive for T in tal) + sum(v for k, v in lv.get('bad', {}).items()
                                                  if 'non-finite' not in k)
    frozen = any(run['learning']['frozen'] for run in R['messages']) or R['outlier']['frozen'] \
        or lv.get('learning', {}).get('frozen', False)
    exc = sum(sum(T.exceptions.values()) for T in tal)
    untruthful = sum(T.untruthful for T in tal) + sum(
        0 if run['learning']['counters_agree'] else 1 for run in R['messages'])
    poisoned = [f'barrage {run["label"]}' for run in R['messages']
                if run['learning']['poisoned']] + \
        (['outlier scenario'] if R['outlier']['poisoned'] else []) + \
        [f'5-message burst {b["label"]} (|tau_hat| {fmt(b["rows"][0]["max_tau"])}, status '
         f'level {b["rows"][0]["level"]})' for b in R['burst']
         if b['rows'] and b['rows'][0]['max_tau'] > 100 * b['rows'][0]['max_truth']]
    st = R['stamps']
    if not st['zero']['trained']:
        poisoned.append('zero stamps: never trained')
    ok = not (nonfin or nonpas or frozen or exc or untruthful or live_crash or touched_other
              or poisoned)
    why = []
    if untruthful:
        why.append(f'untruthful counters {untruthful}')
    if poisoned:
        why.append('poisoned: ' + '; '.join(poisoned) + ' (see the findings)')
    S.append({'cls': '1. Messages', 'inputs': f'{sum(T.sent for T in tal)} in-process, '
              f'{live_msgs} live', 'crashes': exc + live_crash, 'nonfinite': nonfin,
              'nonpassive': nonpas, 'frozen': yes_no(frozen), 'touched': tf, 'exceptions': exc,
              'result': ('held' if ok else '**FAILED**') +
              (f' ({"; ".join(why)})' if why else '')})
    # 2. parameters
    P = R['params']
    c = P['counts']
    lp = lv.get('params', [])
    early_exc = sum(sum(e['tally'].exceptions.values()) for e in P['early'])
    fresh = lv.get('fresh', {})
    p_ok = (c['accepted'] == 0 and c['other exception'] == 0 and c['changed something'] == 0
            and c['refused, reason does not name the parameter'] == 0 and P['still_learning']
            and all(r['ok'] for r in lp) and not early_exc and
            not fresh.get('crashed', False))
    live_after = lv.get('after_params', {})
    frozen_p = not P['still_learning'] or (bool(live_after) and
                                           live_after['added_after'] <= live_after['added_before'])
    S.append({'cls': '2. Parameter sets', 'inputs': f'{c["attempts"]} in-process ({P["cases"]} '
              f'sets x 3 paths) + {len(P["early"])} before the first message, '
              f'{len(lp) + (1 if fresh else 0)} live',
              'crashes': int(bool(lp) and live_crash) + int(fresh.get('crashed', False)),
              'nonfinite': P['tally'].nonfinite, 'nonpassive': P['tally'].nonpassive,
              'frozen': yes_no(frozen_p), 'touched': tf,
              'exceptions': c['other exception'] + early_exc,
              'result': (f'held: {c["refused with a reason"]} + '
                         f'{sum(r["refused"] for r in lp)} refused with a reason, nothing '
                         f'changed' if p_ok and not frozen_p else
                         f'**FAILED**: accepted {c["accepted"]}, process() raised {early_exc} '
                         f'times' + (', live node died' if fresh.get('crashed') else ''))})
    # 3. files
    F = R['files']['rows']
    starts = lv.get('starts', [])
    f_ok = all(r['ok'] and r['mp_ok'] for r in F) and not any(
        r['traceback'] or r['rc'] not in (0, 2) for r in starts)
    f_exc = sum(1 for r in F if r['outcome'] not in ('ok', 'ValueError'))
    f_mp_exc = sum(1 for r in F if r['mp'][0] not in ('-', 'refused', 'load_error', 'loaded'))
    S.append({'cls': '3. Model files', 'inputs': f'{len(F)} files x 2 (load_model, model_path), '
              f'{len(starts)} live starts', 'crashes': sum(1 for r in F if r['outcome'] in
                                                           ('died', 'timeout')) +
              sum(1 for r in starts if r['traceback']),
              'nonfinite': 0, 'nonpassive': sum(1 for r in F if r['info'] and
                                                r['info'].get('min_power', 0) < 0),
              'frozen': 'no' if all(r['mp_ok'] for r in F) else 'see table', 'touched': tf,
              'exceptions': f_exc + f_mp_exc,
              'result': (f'held: max {max(r["seconds"] for r in F):.2f} s, max peak RSS '
                         f'delta {max(r["rss_mib"] for r in F):.0f} MiB' if f_ok
                         else '**FAILED**')})
    # 4. bags
    B = R['bags']['rows']
    b_ok = all(r['ok'] for r in B)
    S.append({'cls': '4. Bags', 'inputs': f'{len(B)} plays ({len(B) // 2} bags x 2 entries)',
              'crashes': sum(1 for r in B if r['rc'] == 3), 'nonfinite': '-', 'nonpassive': '-',
              'frozen': '-', 'touched': tf, 'exceptions': sum(1 for r in B if r['rc'] == 3),
              'result': ('held: refused, nothing imported' if b_ok else '**FAILED**')})
    return S

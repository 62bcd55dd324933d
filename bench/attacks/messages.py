"""
Class 1, messages through ``OnlineEstimator.process`` in-process (``bench/hostile.py``).

The barrage by class on one long-lived estimator per configuration (bad lengths, non-finite
values, names, joints, stamps, a flood, repeats, huge efforts, an in-range outlier), with good
data between the classes, and three scenarios on fresh estimators: the outlier, constant stamps
and a burst of in-range huge efforts.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import time
from typing import Dict

import numpy as np

import common
from common import fmt

from .base import feed, Good, NAMES, Sandbox, Tally, truth


def _variants_bad_lengths():
    q, t = [0.1, 0.2, 0.3], [1.0, 1.0, 1.0]
    L, E, F = ('length_mismatch',), ('empty',), ('non_finite',)
    return [
        ('velocity 2, effort 3', NAMES, q[:2], t, L),
        ('velocity 3, effort 4', NAMES, q, t + [1.0], L),
        ('3 names, 2 values', NAMES, q[:2], t[:2], L),
        ('scalar velocity and effort', NAMES, 0.1, 1.0, L),
        ('2-D 3x3 arrays', NAMES, np.ones((3, 3)), np.ones((3, 3)), L),
        ('10^6 values', NAMES, np.ones(10 ** 6), np.ones(10 ** 6), L),
        ('empty velocity', NAMES, [], t, E),
        ('empty effort', NAMES, q, [], E),
        ('velocity None', NAMES, None, t, E),
        ('ragged nested list', NAMES, [[0.1, 0.2], [0.3]], t, F),
        ('velocity a string', NAMES, 'abc', t, F),
        ('velocity of objects', NAMES, [object(), 1.0, 2.0], t, F),
    ]


def _variants_nonfinite():
    q, t = np.array([0.1, 0.2, 0.3]), np.array([1.0, 1.0, 1.0])
    F, R = ('non_finite',), ('out_of_range',)
    out = []
    for bad, reason in ((np.nan, F), (np.inf, F), (-np.inf, F), (1e308, R), (-1e308, R),
                        (np.finfo(float).max, R)):
        for field in ('velocity', 'effort'):
            v, e = q.copy(), t.copy()
            (v if field == 'velocity' else e)[1] = bad
            out.append((f'{field} {bad:g}', NAMES, v, e, reason))
    out += [
        ('velocity 1e300', NAMES, [1e300, 0.1, 0.1], t, R),
        ('velocity 10001 (just above the limit)', NAMES, [10001.0, 0.1, 0.1], t, R),
        ('denormal velocity 5e-324', NAMES, [5e-324, 5e-324, -5e-324], t, 'answer'),
        ('denormal effort 5e-324', NAMES, q, [5e-324, -5e-324, 5e-324], 'answer'),
        ('velocity 1e-300', NAMES, [1e-300, -1e-300, 1e-300], t, 'answer'),
        ('zero velocity (-0.0)', NAMES, [-0.0, 0.0, -0.0], t, 'answer'),
    ]
    return out


def _variants_names():
    q, t = [0.1, 0.2, 0.3], [1.0, 1.0, 1.0]
    D, B = ('duplicate_name',), ('bad_names',)
    dup = [('names a,a,c', ['a', 'a', 'c'], q, t, D), ('names a,b,b', ['a', 'b', 'b'], q, t, D),
           ('names a,a,a', ['a', 'a', 'a'], q, t, D), ('names "", "", ""', ['', '', ''], q, t, D)]
    bad = [('names 1,2,3', [1, 2, 3], q, t, B),
           ('names None x3 (also duplicates)', [None] * 3, q, t, B + D),
           ('names bytes', [b'a', b'b', b'c'], q, t, B),
           ('names None, 1, 2.5', [None, 1, 2.5], q, t, B),
           ('names lists (unhashable)', [['a'], ['b'], ['c']], q, t, B),
           ('names 1.5,b,c', [1.5, 'b', 'c'], q, t, B), ('names = 42', 42, q, t, B),
           ('names = object()', object(), q, t, B)]
    return dup, bad


def _variants_joints():
    q, t = [0.1, 0.2, 0.3], [1.0, 1.0, 1.0]
    seven = list('abcdefg')
    M, DM = ('missing_joint',), ('dimension_mismatch',)
    nchange = [
        ('7 named, includes a,b,c (selected by name)', seven, q + [9.0] * 4, t + [9.0] * 4,
         'answer'),
        ('7 named, other names', list('tuvwxyz'), q + [0.1] * 4, t + [1.0] * 4, M),
        ('7 unnamed', [], q + [0.1] * 4, t + [1.0] * 4, DM),
        ('2 named a,b', ['a', 'b'], q[:2], t[:2], M),
        ('1 unnamed', [], q[:1], t[:1], DM),
        ('3 unnamed (positional)', [], q, t, 'answer'),
    ]
    many = [
        ('30 named', [f'j{i}' for i in range(30)], np.full(30, 0.1), np.ones(30), M),
        ('30 unnamed', [], np.full(30, 0.1), np.ones(30), DM),
        ('1000 named', [f'j{i}' for i in range(1000)], np.full(1000, 0.1), np.ones(1000), M),
    ]
    return nchange, many


def _variants_stamps(t):
    """(label, stamp) of hostile stamps near the good stream's time t; expected reason."""
    S = ('bad_stamp',)
    return [
        ('back by 1 s', t - 1.0, 'answer'), ('back by 1000 s', max(t - 1000.0, 0.0), 'answer'),
        ('zero', 0.0, 'answer'), ('far future 1e12 s', 1e12, 'answer'),
        ('far future 2^31-1 s', float(2 ** 31 - 1), 'answer'), ('far future 1e300 s', 1e300,
                                                                'answer'),
        ('negative -1 s', -1.0, S), ('negative -1e9 s', -1e9, S), ('NaN', float('nan'), S),
        ('+inf', float('inf'), S), ('-inf', float('-inf'), S), ('a string', 'abc', S),
        ('None', None, S), ('a list', [1.0], S), ('complex', 1j, S),
    ]


def run_messages(cfg_kw: dict, sizes: dict, sandbox: Sandbox, seed: int = 0) -> dict:
    """
    Run the message barrage on one estimator (one configuration).

    Returns tallies and the learning checks.
    """
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    base = {'buffer_size': 200, 'min_samples': 20, 'refit_period_s': 10.0, 'refit_mode': 'sync'}
    base.update(cfg_kw)
    label = f'{base.get("model", "full")}/{base.get("passivity", "projected")}'
    model_path = os.path.join(sandbox.models, f'inproc_{label.replace("/", "_")}.npz')
    cfg = EstimatorConfig(model_path=model_path, **base)
    k = sizes['k']
    good = Good(seed=seed)
    tallies: Dict[str, Tally] = collections.OrderedDict()

    def tally(name):
        return tallies.setdefault(name, Tally(name))

    goodlog: list = []          # every good message, replayed into a control estimator

    def good_msgs(est, T, n, expect='answer', keep=None, tag=''):
        for _ in range(n):
            t, q, tau = good.next()
            goodlog.append((t, q, tau, tag))
            e = feed(est, T, t, NAMES, q, tau, expect)
            if keep is not None and e is not None:
                keep.append(e)

    # -- first message with 30 joints, on a fresh estimator
    est = OnlineEstimator(cfg)
    T = tally('first message with 30 joints, then 3')
    t0 = time.perf_counter()
    names30 = [f'j{i}' for i in range(30)]
    for _ in range(k):
        feed(est, T, good.t, names30, np.full(30, 0.1), np.ones(30), ('too_many_joints',))
    lat = []
    for _ in range(max(50, k)):
        t, q, tau = good.next()
        a = time.perf_counter()
        feed(est, T, t, NAMES, q, tau, 'answer')
        lat.append(time.perf_counter() - a)
    T.seconds = time.perf_counter() - t0
    T.notes.append(f'then 3 joints: p99 process() {fmt(1e3 * np.percentile(lat, 99))} ms')

    # -- warm-up (good data; not an attack)
    T = tally('good data (warm-up, not an attack)')
    t0 = time.perf_counter()
    good_msgs(est, T, sizes['warm'])
    T.seconds = time.perf_counter() - t0
    d = est.diagnostics()
    T.notes.append(f'trained {d["trained"]}, samples_added {d["samples_added"]}, '
                   f'refits ok {d["refits_ok"]}')

    def run_variants(name, variants, interleave=True):
        T = tally(name)
        t0 = time.perf_counter()
        for i in range(k):
            for _lab, names, v, e, expect in variants:
                if isinstance(v, np.ndarray) and v.size > 10 ** 5 and i > k // 50:
                    continue        # the 10^6 one: fewer
                feed(est, T, good.t, names, v, e, expect)
            if interleave:
                good_msgs(est, T, 1)
        T.seconds = time.perf_counter() - t0
        return T

    run_variants('bad lengths', _variants_bad_lengths())
    run_variants('NaN / Inf / 1e308 / denormals', _variants_nonfinite())
    dup, bad = _variants_names()
    run_variants('duplicate names', dup)
    run_variants('non-string names', bad)
    nchange, many = _variants_joints()
    run_variants('N changing 3 -> 7 (and 2, 1)', nchange)
    run_variants('30 and 1000 joints (trained)', many)

    # -- stamps
    T = tally('stamps back / zero / constant / far future / negative / NaN')
    t0 = time.perf_counter()
    for _ in range(k):
        for _lab, stamp, expect in _variants_stamps(good.t):
            _t, q, tau = good.next()
            feed(est, T, stamp, NAMES, q, tau, expect)
        good_msgs(est, T, 1)
    for _ in range(k):                      # constant stamps (a driver that never sets them)
        _t, q, tau = good.next()
        feed(est, T, 1234.5, NAMES, q, tau, 'answer')
    for _ in range(k):                      # zero stamps
        _t, q, tau = good.next()
        feed(est, T, 0.0, NAMES, q, tau, 'answer')
    T.seconds = time.perf_counter() - t0
    d = est.diagnostics()
    T.notes.append(f'time_jumps_back {d["time_jumps_back"]}, learning clock '
                   f'{d["learning_clock"]}')
    good_msgs(est, tally('good data between classes'), 200)

    # -- flood: as fast as possible, stamps 0.2 ms apart (5 kHz in stamp time)
    T = tally('flood (as fast as possible)')
    dt0 = good.dt
    good.dt = 2e-4
    t0 = time.perf_counter()
    good_msgs(est, T, sizes['flood'])
    T.seconds = time.perf_counter() - t0
    good.dt = dt0
    T.notes.append(f'{T.sent / T.seconds:.0f} msg/s')

    # -- repeats: one message, identical stamp and content
    T = tally('repeats (identical message)')
    t, q, tau = good.next()
    t0 = time.perf_counter()
    for _ in range(sizes['repeats']):
        feed(est, T, t, NAMES, q, tau, 'answer')
    T.seconds = time.perf_counter() - t0
    T.notes.append(f'{T.sent / T.seconds:.0f} msg/s')
    good_msgs(est, tally('good data between classes'), 200)

    # -- huge efforts (in range and out of range), isolated and in runs
    T = tally('huge efforts')
    t0 = time.perf_counter()
    for i in range(k):
        for e in ([9.9e7, 1.0, 1.0], [-9.9e7, -9.9e7, -9.9e7], [1e9, 1.0, 1.0]):
            _t, q, _tau = good.next()
            feed(est, T, _t, NAMES, q, e, ('out_of_range',) if abs(e[0]) > 1e8 else 'answer')
        good_msgs(est, T, 2)
    for _ in range(5):                      # a run: the motion "really changed"; learned
        _t, q, _tau = good.next()
        feed(est, T, _t, NAMES, q, [5e7, 5e7, 5e7], 'answer')
    T.seconds = time.perf_counter() - t0
    d = est.diagnostics()
    T.notes.append(f'samples_outliers {d["samples_outliers"]}')

    # -- one in-range outlier, then good data
    T = tally('in-range outlier |v| = 9999, then good data')
    added0 = est.diagnostics()['samples_added']
    feed(est, T, good.t, NAMES, [9999.0, 0.1, 0.1], [1.0, 1.0, 1.0], 'answer')
    keep: list = []
    t0 = time.perf_counter()
    good_msgs(est, T, sizes['after_outlier'], keep=keep)
    T.seconds = time.perf_counter() - t0
    d = est.diagnostics()

    # -- recovery: good data after everything
    R = tally('good data after all attacks')
    added1 = d['samples_added']
    rec: list = []
    t0 = time.perf_counter()
    good_msgs(est, R, sizes['recovery'], keep=rec, tag='rec')
    R.seconds = time.perf_counter() - t0
    d = est.diagnostics()
    tail = rec[len(rec) // 2:]
    nm = float(np.max(common.nmse(np.array([x.tau_hat for x in tail]),
                                  np.array([truth(x.qd) for x in tail]))))
    # control: a fresh estimator fed only the good messages, in the same order and stamps
    ctrl = OnlineEstimator(dataclasses.replace(cfg, model_path=''))
    crec = []
    for t, q, tau, tag in goodlog:
        e = ctrl.process(t, NAMES, q, tau)
        if tag == 'rec':
            crec.append(e)
    ctail = crec[len(crec) // 2:]
    nm_ctrl = float(np.max(common.nmse(np.array([x.tau_hat for x in ctail]),
                                       np.array([truth(x.qd) for x in ctail]))))
    added_ctrl = ctrl.diagnostics()['samples_added']
    ctrl.close()
    learning = {'added_before_outlier': added0, 'added_after_outlier': added1,
                'added_end': d['samples_added'], 'nmse_recovery': nm,
                'max_abs_tau_after_outlier': float(max(np.abs(x.tau_hat).max()
                                                       for x in keep + rec)),
                'level': d['level'], 'message': d['message'],
                'learning_clock': d['learning_clock'],
                'trained': d['trained'], 'certified': d['certified'], 'method': d['method'],
                'nonfinite_outputs': d['nonfinite_outputs'],
                'passivity_fallbacks': d['passivity_fallbacks'], 'nmse_control': nm_ctrl,
                'added_control': added_ctrl, 'good_messages': len(goodlog)}
    learning['frozen'] = not (added1 > added0 and d['samples_added'] > added1) or \
        'stalled' in d['message']
    learning['poisoned'] = not nm <= max(10.0 * nm_ctrl, 0.05)
    R.notes.append(f'samples_added {added1} -> {d["samples_added"]}, NMSE {fmt(nm)} '
                   f'(control without the attacks {fmt(nm_ctrl)})')
    # totals as the estimator counted them vs. what was sent
    sent = sum(x.sent for x in tallies.values())
    answered = sum(x.answered for x in tallies.values())
    counted = {'received': d['messages_received'], 'accepted': d['messages_accepted'],
               'rejected': d['rejected_total']}
    learning['counters_agree'] = (counted['received'] == sent and counted['accepted'] ==
                                  answered and counted['rejected'] == sent - answered)
    learning['counted'] = counted
    est.close()
    return {'label': label, 'config': cfg.to_dict(), 'tallies': tallies, 'learning': learning}


def run_outlier_scenario(cfg_kw: dict, sizes: dict, seed: int = 1) -> dict:
    """
    Run the issue's finding 1 exactly.

    A trained estimator, one in-range outlier (|v| = 9999), then 60 s of good data: learning goes
    on and the error stays small.
    """
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    base = {'buffer_size': 200, 'min_samples': 20, 'refit_period_s': 10.0, 'refit_mode': 'sync'}
    base.update(cfg_kw)
    est = OnlineEstimator(EstimatorConfig(**base))
    good = Good(seed=seed)
    T = Tally('outlier scenario')
    before = []
    for _ in range(sizes['warm']):
        t, q, tau = good.next()
        e = feed(est, T, t, NAMES, q, tau, 'answer')
        if e is not None:
            before.append(e)
    d0 = est.diagnostics()
    feed(est, T, good.t, NAMES, [9999.0, 0.1, 0.1], [1.0, 1.0, 1.0], 'answer')
    after = []
    for _ in range(sizes['after_outlier']):
        t, q, tau = good.next()
        e = feed(est, T, t, NAMES, q, tau, 'answer')
        if e is not None:
            after.append(e)
    d1 = est.diagnostics()
    est.close()
    # control: the same good messages without the outlier
    ctrl = OnlineEstimator(EstimatorConfig(**base))
    g2 = Good(seed=seed)
    cafter = []
    for i in range(sizes['warm'] + sizes['after_outlier']):
        t, q, tau = g2.next()
        e = ctrl.process(t, NAMES, q, tau)
        if i >= sizes['warm']:
            cafter.append(e)
    ctrl.close()

    def nm(es):
        es = es[-min(len(es), 1000):]
        return float(np.max(common.nmse(np.array([x.tau_hat for x in es]),
                                        np.array([truth(x.qd) for x in es]))))

    out = {'stamp_seconds_after': sizes['after_outlier'] * good.dt,
           'added_before': d0['samples_added'], 'added_after': d1['samples_added'],
           'nmse_before': nm(before), 'nmse_after': nm(after), 'nmse_control': nm(cafter),
           'max_abs_tau_after': float(max(np.abs(x.tau_hat).max() for x in after)),
           'max_abs_truth': float(max(np.abs(truth(x.qd)).max() for x in after)),
           'outliers': d1['samples_outliers'], 'level': d1['level'], 'message': d1['message'],
           'tally': T}
    out['frozen'] = not out['added_after'] > out['added_before'] + 10 or \
        'stalled' in d1['message']
    out['poisoned'] = not out['nmse_after'] <= max(10 * out['nmse_control'], 0.05)
    return out


def run_stamp_scenario(cfg_kw: dict, n: int) -> dict:
    """
    Run the issue's finding 6.

    Every stamp 0 from the start (a driver that never sets them), then the same number of messages
    with advancing stamps.
    """
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    base = {'buffer_size': 200, 'min_samples': 20, 'refit_period_s': 10.0, 'refit_mode': 'sync'}
    base.update(cfg_kw)
    est = OnlineEstimator(EstimatorConfig(**base))
    good = Good(seed=2)
    T = Tally('zero stamps')
    t0 = time.perf_counter()
    for _ in range(n):
        _t, q, tau = good.next()
        feed(est, T, 0.0, NAMES, q, tau, 'answer')
        time.sleep(2e-3)        # a driver at a few hundred Hz: the arrival clock advances
    d0 = est.diagnostics()
    for _ in range(n):
        t, q, tau = good.next()
        feed(est, T, t, NAMES, q, tau, 'answer')
    d1 = est.diagnostics()
    est.close()
    return {'n': n, 'seconds': time.perf_counter() - t0, 'tally': T,
            'zero': {'trained': d0['trained'], 'added': d0['samples_added'],
                     'clock': d0['learning_clock'], 'level': d0['level'],
                     'message': d0['message']},
            'after': {'trained': d1['trained'], 'added': d1['samples_added'],
                      'clock': d1['learning_clock'], 'level': d1['level'],
                      'message': d1['message']}}


def run_burst_scenario(cfg_kw: dict, warm: int, chunks: int, chunk: int) -> dict:
    """
    Run the burst scenario.

    Five consecutive in-range huge efforts (5e7 < max_abs_effort) on a trained estimator,
    then good data in chunks: how far the answers go, how long until they recover, and what the
    status says meanwhile.
    """
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    base = {'buffer_size': 200, 'min_samples': 20, 'refit_period_s': 10.0, 'refit_mode': 'sync'}
    base.update(cfg_kw)
    est = OnlineEstimator(EstimatorConfig(**base))
    ctrl = OnlineEstimator(EstimatorConfig(**base))     # the same good data, no burst
    good = Good(seed=6)
    T = Tally('burst')
    for _ in range(warm):
        t, q, tau = good.next()
        feed(est, T, t, NAMES, q, tau, 'answer')
        ctrl.process(t, NAMES, q, tau)
    d0 = est.diagnostics()
    for _ in range(5):
        t, q, _tau = good.next()
        feed(est, T, t, NAMES, q, [5e7, 5e7, 5e7], 'answer')
    learned = est.diagnostics()['samples_added'] - d0['samples_added']
    rows = []

    def nmse_of(es):
        return float(np.max(common.nmse(np.array([x.tau_hat for x in es]),
                                        np.array([truth(x.qd) for x in es]))))

    for c in range(chunks):
        es, cs = [], []
        for _ in range(chunk):
            t, q, tau = good.next()
            e = feed(est, T, t, NAMES, q, tau, 'answer')
            if e is not None:
                es.append(e)
            cs.append(ctrl.process(t, NAMES, q, tau))
        d = est.diagnostics()
        nm = nmse_of(es)
        rows.append({'seconds': (c + 1) * chunk * good.dt, 'nmse': nm, 'nmse_control': nmse_of(cs),
                     'max_tau': float(max(np.abs(x.tau_hat).max() for x in es)),
                     'max_truth': float(max(np.abs(truth(x.qd)).max() for x in es)),
                     'added': d['samples_added'], 'level': d['level'], 'message': d['message']})
    est.close()
    ctrl.close()
    rec = next((r['seconds'] for r in rows
                if r['nmse'] <= max(10 * r['nmse_control'], 0.05)), None)
    return {'label': f'{base.get("model", "full")}/{base.get("passivity", "projected")}',
            'added_before': d0['samples_added'], 'rows': rows, 'recovered_after_s': rec,
            'tally': T, 'learned': learned}

"""
What is thrown at the ``estimator`` node process live over DDS (``bench/hostile.py``).

Messages, parameter sets through the node's parameter services and model files as
``model_path`` at start, each checked on the node's answers, diagnostics and exit status.
"""
from __future__ import annotations

import os
import shutil
import time

import numpy as np

from common import log

from .base import Good, NAMES, Sandbox, short
from .node import Child, counter, estimator_exe, Live, rejections, wait_future


def run_live(sb: Sandbox, sizes: dict, quick: bool) -> dict:
    """
    Run the live trial over DDS.

    Messages (class 1, a smaller share), parameter sets (class 2) and model files given as
    ``model_path`` at start (class 3) against the ``estimator`` node process.
    """
    from rclpy.parameter import Parameter, parameter_value_to_python
    from rclpy.parameter_client import AsyncParameterClient
    from std_srvs.srv import Trigger
    exe = estimator_exe()
    if not exe:
        return {'skipped': 'console script `estimator` not found'}
    model_path = os.path.join(sb.models, 'live_model.npz')
    live = Live()
    out: dict = {'classes': [], 'params': [], 'starts': []}
    child = Child([exe, '--ros-args', '-p', f'model_path:={model_path}',
                   '-p', 'diagnostics_period_s:=0.2', '-p', 'buffer_size:=100',
                   '-p', 'min_samples:=20', '-p', 'refit_period_s:=5.0',
                   '-p', 'queue_depth:=1000'], os.path.join(sb.logs, 'estimator.log'))
    try:
        if not live.spin_until(lambda: live.pub.get_subscription_count() >= 1 and live.diag,
                               30, child):
            out['skipped'] = (f'estimator not discovered (alive {child.alive()}): '
                              f'{child.text()[-400:]}')
            return out
        k = sizes['k_live']
        good = Good(t0=1.0, seed=7)

        def goods(n, dt=None):
            ms = []
            for _ in range(n):
                if dt:
                    good.t += dt - good.dt
                t, q, tau = good.next()
                ms.append(live.msg(t, NAMES, q, tau))
            return ms

        prev = [live.fresh_diag(5.0, child)]

        def run_class(name, msgs, rate=1000.0, expect_answers=None):
            bad0 = sum(live.bad.values())
            got0 = live.got['force']
            dt = live.send(msgs, rate, child)
            live.settle(child)
            d = live.fresh_diag(5.0, child)
            for _ in range(10):             # until the node's count stops moving
                d2 = live.fresh_diag(2.0, child)
                if counter(d2, 'messages_received') == counter(d, 'messages_received'):
                    break
                d = d2
            d0 = prev[0]
            rej = rejections(d) - rejections(d0)
            row = {'name': name, 'sent': len(msgs),
                   'received': counter(d, 'messages_received') -
                   counter(d0, 'messages_received'),
                   'accepted': counter(d, 'messages_accepted') -
                   counter(d0, 'messages_accepted'),
                   'answers': live.got['force'] - got0,
                   'rejected': ', '.join(f'{a} {b}' for a, b in sorted(rej.items())) or '-',
                   'bad': sum(live.bad.values()) - bad0, 'alive': child.alive(), 'seconds': dt,
                   'level': d.get('_level'), 'message': d.get('_message', '')}
            row['rate'] = len(msgs) / dt if dt > 0 else float('nan')
            prev[0] = d
            out['classes'].append(row)
            log(f'  live {name}: sent {row["sent"]}, received {row["received"]}, answers '
                f'{row["answers"]}, rejected {row["rejected"]}, bad {row["bad"]}')
            return row

        # 1. messages
        run_class('first messages with 30 joints',
                  [live.msg(good.t, [f'j{i}' for i in range(30)], np.full(30, 0.1),
                            np.ones(30)) for _ in range(k)])
        run_class('good data (warm-up)', goods(sizes['warm_live']))
        q3, t3 = [0.1, 0.2, 0.3], [1.0, 1.0, 1.0]
        ms = []
        for _ in range(k):
            ms += [live.msg(good.t, NAMES, q3[:2], t3), live.msg(good.t, NAMES, q3, t3 + [1.0]),
                   live.msg(good.t, NAMES, [], t3), live.msg(good.t, NAMES, q3, []),
                   live.msg(good.t, NAMES[:2], q3, t3)] + goods(1)
        run_class('bad lengths', ms)
        ms = []
        for _ in range(k):
            for bad in (np.nan, np.inf, -np.inf, 1e308, -1e308):
                ms += [live.msg(good.t, NAMES, [0.1, bad, 0.3], t3),
                       live.msg(good.t, NAMES, q3, [1.0, bad, 1.0])]
            ms += [live.msg(good.t, NAMES, [5e-324, -5e-324, 5e-324], t3),
                   live.msg(good.t, NAMES, q3, [5e-324, 5e-324, -5e-324])] + goods(1)
        run_class('NaN / Inf / 1e308 / denormals', ms)
        ms = []
        for _ in range(k):
            ms += [live.msg(good.t, ['a', 'a', 'c'], q3, t3),
                   live.msg(good.t, ['', '', ''], q3, t3)] + goods(1)
        run_class('duplicate names', ms)
        ms = []
        for _ in range(k):
            ms += [live.msg(good.t, list('abcdefg'), q3 + [9.0] * 4, t3 + [9.0] * 4),
                   live.msg(good.t, list('tuvwxyz'), [0.1] * 7, [1.0] * 7),
                   live.msg(good.t, [], [0.1] * 7, [1.0] * 7),
                   live.msg(good.t, [f'j{i}' for i in range(30)], [0.1] * 30, [1.0] * 30),
                   live.msg(good.t, [], [0.1] * 30, [1.0] * 30)] + goods(1)
        run_class('N changing 3 -> 7, 30 joints', ms)
        ms = []
        for _ in range(k):
            t = good.t
            for st in ((max(int(t) - 1000, 0), 0), (0, 0), (2 ** 31 - 1, 999_999_999),
                       (-1, 0), (-2 ** 31, 0), (int(t), 2 ** 32 - 1)):
                _t, q, tau = good.next()
                ms.append(live.msg(st, NAMES, q, tau))
            ms += goods(1)
        for _ in range(k):
            _t, q, tau = good.next()
            ms.append(live.msg((1234, 500_000_000), NAMES, q, tau))
        for _ in range(k):
            _t, q, tau = good.next()
            ms.append(live.msg((0, 0), NAMES, q, tau))
        ms += goods(50)
        run_class('stamps back / zero / constant / far future / negative', ms)
        run_class('flood (as fast as possible)', goods(sizes['flood_live'], dt=2e-4), rate=0)
        t, q, tau = good.next()
        rep = live.msg(t, NAMES, q, tau)
        run_class('repeats (identical message)', [rep] * sizes['repeats_live'], rate=0)
        ms = []
        for _ in range(k):
            for e in ([9.9e7, 1.0, 1.0], [-9.9e7, -9.9e7, -9.9e7], [1e9, 1.0, 1.0]):
                _t, q, _tau = good.next()
                ms.append(live.msg(_t, NAMES, q, e))
            ms += goods(2)
        run_class('huge efforts', ms)
        d0 = live.fresh_diag(5.0, child)
        added0 = counter(d0, 'samples_added')
        ms = [live.msg(good.t, NAMES, [9999.0, 0.1, 0.1], t3)] + goods(sizes['after_live'])
        row = run_class('in-range outlier |v| = 9999, then good data', ms)
        d1 = prev[0]
        out['learning'] = {'added_before': added0, 'added_after': counter(d1, 'samples_added'),
                           'message': d1.get('_message', ''), 'level': d1.get('_level')}
        out['learning']['frozen'] = not out['learning']['added_after'] > added0 or \
            'stalled' in out['learning']['message']
        row['notes'] = f'samples_added {added0} -> {out["learning"]["added_after"]}'

        # 2. parameter sets through the parameter services
        client = AsyncParameterClient(live.node, 'dgp_estimator')
        if not client.wait_for_services(timeout_sec=20):
            out['params_skipped'] = 'parameter services not found'
        else:
            def call(fut, timeout=20.0):
                return wait_future(live, fut, child, timeout)

            def get(names):
                r = call(client.get_parameters(names))
                return None if r is None else [parameter_value_to_python(v) for v in r.values]

            D, I, S = Parameter.Type.DOUBLE, Parameter.Type.INTEGER, Parameter.Type.STRING
            DA = Parameter.Type.DOUBLE_ARRAY
            dec = sb.decoy
            sets = [
                ('diagnostics_period_s', D, float('inf')), ('diagnostics_period_s', D, 1e308),
                ('diagnostics_period_s', D, float('nan')), ('diagnostics_period_s', D, 0.0),
                ('diagnostics_period_s', D, -1.0), ('buffer_size', I, 10 ** 9),
                ('buffer_size', I, 2 ** 63 - 1), ('buffer_size', I, -5),
                ('buffer_size', S, 'abc'), ('selection_min_distance', D, 1e200),
                ('max_abs_velocity', D, float('inf')), ('max_abs_effort', D, 1e308),
                ('refit_period_s', D, 1e308), ('min_sample_interval_s', D, -1.0),
                ('queue_depth', I, 10 ** 9), ('operating_domain', DA, [-1.0, 1.0]),
                ('selection_scale', DA, [1.0]), ('selection_scale', DA, [float('nan')] * 3),
                ('model', S, 'evil'), ('passivity', S, 'off'),
                ('model_path', S, dec('notes.txt')), ('model_path', S, dec('notes.npz')),
                ('model_path', S, dec('user_arrays.npz')), ('model_path', S, dec('dir.npz')),
                ('model_path', S, dec('fifo.npz')), ('model_path', S, dec('link.npz')),
                ('model_path', S, '/dev/full'), ('model_path', S, '/dev/zero'),
                ('model_path', S, '/nonexistent_dir/m.npz'),
                ('buffer_sise', I, 500),
            ]
            watched = sorted({s[0] for s in sets if s[0] != 'buffer_sise'})
            before = get(watched)
            srv = live.node.create_client(Trigger, '/dgp_estimator/save_model')
            srv.wait_for_service(timeout_sec=10)
            for name, typ, val in sets:
                r = call(client.set_parameters([Parameter(name, typ, val)]))
                res = r.results[0] if r is not None and r.results else None
                now = get(watched)
                saved = call(srv.call_async(Trigger.Request()))
                row = {'set': f'{name}={short(val)}',
                       'refused': res is not None and not res.successful,
                       'reason': (res.reason if res is not None else 'no answer'),
                       'unchanged': now == before, 'alive': child.alive(),
                       'save': (saved.message if saved is not None else 'no answer')}
                row['ok'] = row['refused'] and bool(row['reason']) and row['unchanged'] and \
                    row['alive']
                out['params'].append(row)
                log(f'  live set {row["set"]}: refused {row["refused"]} '
                    f'({row["reason"][:80]!r}), unchanged {row["unchanged"]}')
            # a peer-chosen module name for the inverse-dynamics plugin (observation)
            r = call(client.set_parameters([Parameter('inverse_dynamics', S,
                                                      'python:this:no_such_function')]))
            res = r.results[0] if r is not None and r.results else None
            live.spin(0.5, child)
            out['plugin_import'] = {
                'refused': res is not None and not res.successful,
                'reason': res.reason if res is not None else 'no answer',
                'imported': 'Beautiful is better than ugly' in child.text()}
            # still answering and learning after the parameter attacks
            d0 = live.fresh_diag(5.0, child)
            run_class('good data after the parameter sets', goods(sizes['after_live']))
            d1 = prev[0]
            out['after_params'] = {'added_before': counter(d0, 'samples_added'),
                                   'added_after': counter(d1, 'samples_added')}
        out['final_diag'] = dict((prev[0] or {}).items())
    finally:
        out['bad'] = dict(live.bad)
        out['got'] = dict(live.got)
        out['alive_at_end'] = child.alive()
        out['rc'] = child.stop()
        out['log_tail'] = child.text()[-600:]
        out['traceback'] = 'Traceback' in child.text()
        out['node_max_rss_mib'] = child.maxrss_mib
        out['model_saved'] = os.path.exists(model_path)
        if out.get('skipped'):
            live.close()

    # 2b. a fresh node: a per-joint parameter that does not fit the joints, set before the
    # first message (N is unknown then), then good 3-joint messages
    fresh: dict = {}
    c = Child([exe, '--ros-args', '-p', 'diagnostics_period_s:=0.2', '-p', 'min_samples:=10'],
              os.path.join(sb.logs, 'fresh.log'))
    live.diag.clear()
    try:
        if live.spin_until(lambda: live.pub.get_subscription_count() >= 1 and live.diag, 30, c):
            cl = AsyncParameterClient(live.node, 'dgp_estimator')
            cl.wait_for_services(timeout_sec=20)
            r = wait_future(live, cl.set_parameters([Parameter(
                'selection_scale', Parameter.Type.DOUBLE_ARRAY, [1.0, 1.0])]), c)
            res = r.results[0] if r is not None and r.results else None
            got0 = live.got['force']
            g = Good(t0=1.0, seed=8)
            ms = []
            for _ in range(200):
                t, q, tau = g.next()
                ms.append(live.msg(t, NAMES, q, tau))
            live.send(ms, 500.0, c)
            live.spin(1.0, c)
            alive = c.alive()
            fresh = {'set': 'selection_scale=[1.0, 1.0] before the first message',
                     'refused': res is not None and not res.successful,
                     'reason': res.reason if res is not None else 'no answer',
                     'sent': len(ms), 'answers': live.got['force'] - got0, 'alive': alive}
            fresh['crashed'] = not alive
    finally:
        fresh['rc'] = c.stop()
        lines = [x for x in c.text().splitlines() if x.strip()]
        fresh['last_line'] = lines[-1][:200] if lines else ''
        log(f'  live fresh node: {fresh}')
    out['fresh'] = fresh

    # 3. model files given as model_path at start
    starts = [('control: no model_path', None)]
    files = sb.files
    starts += [('/dev/zero', '/dev/zero')]
    if not quick:
        starts += [('a text file named .npz', sb.decoy('notes.npz')),
                   ('a directory', sb.decoy('dir.npz')),
                   ('zip bomb (X)', os.path.join(files, 'bomb_X.npz')),
                   ('header N = 1200', os.path.join(files, 'N1200.npz')),
                   ('header N = 10^5', os.path.join(files, 'N100000.npz')),
                   ('forged certificate', os.path.join(files, 'forged.npz')),
                   ('symlink to /dev/zero', sb.decoy('zero.npz'))]
    for i, (lab, path) in enumerate(starts):
        # a name of its own: a late diagnostics message of the previous node must not count
        node_name = f'dgp_estimator_start{i}'
        cmd = [exe, '--ros-args', '-r', f'__node:={node_name}', '-p', 'diagnostics_period_s:=0.2']
        use = path
        if path and path.startswith(files):        # a copy: a save may replace our own file
            use = os.path.join(sb.scratch, 'start_' + os.path.basename(path))
            shutil.copyfile(path, use)
        if 'forged' in lab:
            cmd += ['-p', 'model:=diag', '-p', 'passivity:=certified']
        if use:
            cmd += ['-p', f'model_path:={use}']
        live.diag.clear()
        c = Child(cmd, os.path.join(sb.logs, f'start_{len(out["starts"])}.log'))
        t0 = time.monotonic()
        mine = lambda: [x for x in live.diag if x.get('_node') == '/' + node_name]  # noqa: E731
        live.spin_until(lambda: bool(mine()) or not c.alive(), 30)
        first = time.monotonic() - t0
        d = mine()[-1] if mine() else {}
        hwm = c.hwm()
        rc = c.stop() if c.alive() else c.rc
        hwm = c.maxrss_mib if c.maxrss_mib == c.maxrss_mib else hwm
        text = c.text()
        lines = [x for x in text.splitlines() if x.strip()]
        row = {'start': lab, 'rc': rc, 'seconds': first, 'hwm_mib': hwm,
               'load_error': d.get('load_error', ''), 'certified': d.get('certified', ''),
               'method': d.get('method', ''), 'trained': d.get('trained', ''),
               'first_line': (lines[-1] if lines else '')[:160],
               'traceback': 'Traceback' in text}
        out['starts'].append(row)
        log(f'  live start {lab}: rc {rc}, {first:.1f} s, max RSS {row["hwm_mib"]:.0f} MiB, '
            f'load_error {row["load_error"][:80]!r}')
    live.close()
    return out

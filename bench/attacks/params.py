"""
Class 2, parameter sets in-process (``bench/hostile.py``).

Hostile values for every parameter and semantic cases (per-joint lengths, ``model_path``s into
the sandbox's decoys, ...) through ``EstimatorConfig.validate()``, ``check_reconfigure`` and
``reconfigure``: each refused with a reason, nothing changed.
"""
from __future__ import annotations

import collections
import dataclasses
import os
from typing import List

import numpy as np

from .base import feed, Good, NAMES, Sandbox, short, Tally


def hostile_values(spec) -> list:
    """Values that ``spec`` must refuse."""
    inf, nan = float('inf'), float('nan')
    t = spec.type
    if t in ('int', 'float'):
        vals = [inf, -inf, nan, 1e308, -1e308, 1e200, 'abc', None, [1], True]
        if spec.low is not None:
            vals += [spec.low - 1.0 if t == 'float' else int(spec.low) - 1,
                     spec.high * 10 + 1 if t == 'float' else int(spec.high) * 10 + 1]
        if t == 'int':
            vals += [10 ** 9 if spec.high < 10 ** 9 else 10 ** 12, 10 ** 30, 2 ** 63, 1.5,
                     np.float64(2.0)]
        return vals
    if t == 'bool':
        return ['true', 1, None, 2.0, 'false']
    if t == 'str':
        vals = [123, None, b'bytes', ['x'], 1.5]
        if spec.choices:
            vals += ['bogus', spec.choices[0].upper() + '_', '']
        if spec.max_len:
            vals.append('x' * (spec.max_len + 1))
        return vals
    if t == 'str[]':
        return ['abc', None, 42, [1, 2], [''], [None], ['a', 'a'],
                [f'j{i}' for i in range(spec.max_len + 1)]]
    if t == 'float[]':
        return ['x', None, 1.0, [nan], [inf, 1.0], [1e308, 2e308], ['a'], [None],
                [0.5] * (spec.max_len + 2), [-1e13, 1e13]]
    return []


def semantic_cases(sandbox: Sandbox) -> list:
    """(label, overrides) that pass each field's own check but not the configuration's."""
    d = sandbox.decoy
    return [
        ('min_samples > buffer_size', {'buffer_size': 10, 'min_samples': 11}),
        ('joints 17 > max_joints 16', {'joints': [f'j{i}' for i in range(17)]}),
        ('joints 3, selection_scale 2', {'joints': NAMES, 'selection_scale': [1.0, 1.0]}),
        ('joints 3, operating_domain 4', {'joints': NAMES, 'operating_domain': [-1, -1, 1, 1]}),
        ('operating_domain odd length', {'operating_domain': [-1.0, 1.0, 2.0]}),
        ('operating_domain lo >= hi', {'operating_domain': [1.0, 1.0, 1.0, 0.0, 0.0, 0.0]}),
        ('passivity paper for ard', {'model': 'ard', 'passivity': 'paper'}),
        ('inverse_dynamics bogus', {'inverse_dynamics': 'bogus'}),
        ('inverse_dynamics python: (malformed)', {'inverse_dynamics': 'python:'}),
        # urdf with neither robot_description nor urdf_file is valid: the node then takes the
        # URDF from /robot_description (test/ros/test_robot_description.py)
        ('inverse_dynamics urdf, missing urdf_file',
         {'inverse_dynamics': 'urdf', 'urdf_file': '/nonexistent/robot.urdf'}),
        ('model_path a text file (.txt)', {'model_path': d('notes.txt')}),
        ('model_path a text file named .npz', {'model_path': d('notes.npz')}),
        ("model_path a user's numpy .npz", {'model_path': d('user_arrays.npz')}),
        ('model_path a directory', {'model_path': d('dir.npz')}),
        ('model_path a FIFO', {'model_path': d('fifo.npz')}),
        ('model_path a symlink out of the dir', {'model_path': d('link.npz')}),
        ('model_path a symlink to /dev/zero', {'model_path': d('zero.npz')}),
        ('model_path /dev/full', {'model_path': '/dev/full'}),
        ('model_path /dev/zero', {'model_path': '/dev/zero'}),
        ('model_path in a missing directory', {'model_path': '/nonexistent_dir/m.npz'}),
        ('model_path with a NUL byte', {'model_path': d('a\x00b.npz')}),
        ('model_path no suffix', {'model_path': os.path.join(sandbox.models, 'model')}),
    ]


def run_params_inprocess(sandbox: Sandbox, quick: bool) -> dict:
    """
    Run the parameter attacks in process.

    Every hostile value of every parameter through validate(), check_reconfigure() and
    reconfigure() of a trained estimator (N = 3 seen, joints not configured); then per-joint
    parameters whose length does not fit the joints, set before the first message.
    """
    from dgp_ros.online import PARAMS, EstimatorConfig, OnlineEstimator
    cases = []      # (label, overrides, parameter named in the reason, validate may accept)
    for spec in PARAMS.values():
        for v in hostile_values(spec):
            cases.append((f'{spec.name}={short(v)}', {spec.name: v}, spec.name, False))
    for lab, ov in semantic_cases(sandbox):
        cases.append((lab, ov, next(iter(ov)) if len(ov) == 1 else None, False))
    cases.append(('unknown name buffer_sise (from_dict)', {'buffer_sise': 500}, 'buffer_sise',
                  False))
    # dimensions against the joints the trained estimator has seen (N = 3): validate() alone
    # cannot know N, check_reconfigure() and reconfigure() must refuse
    for lab, ov in (('operating_domain 1 entry per bound', {'operating_domain': [-1.0, 1.0]}),
                    ('operating_domain for N = 7', {'operating_domain': [-1.0] * 7 + [1.0] * 7}),
                    ('selection_scale 1 entry', {'selection_scale': [1.0]}),
                    ('selection_scale 7 entries', {'selection_scale': [1.0] * 7})):
        cases.append((lab + ' (N = 3 seen)', ov, next(iter(ov)), True))

    base = {'model': 'full', 'passivity': 'projected', 'buffer_size': 100, 'min_samples': 20,
            'refit_mode': 'sync', 'model_path': os.path.join(sandbox.models, 'params_model.npz')}
    good = Good(seed=3)

    def trained():
        e = OnlineEstimator(EstimatorConfig(**base))
        for _ in range(300 if quick else 600):
            t, q, tau = good.next()
            e.process(t, NAMES, q, tau)
        return e

    est = trained()
    res = collections.Counter()
    bad: List[str] = []
    rebuilt = 0
    for lab, ov, name, validate_may_accept in cases:
        snap = (est.config.to_dict(), id(est.model), est.samples()[0].tobytes())
        changed = False
        for how in ('validate', 'check_reconfigure', 'reconfigure'):
            try:
                if how == 'validate':
                    if 'buffer_sise' in ov:
                        EstimatorConfig.from_dict(dict(base, **ov)).validate()
                    else:
                        EstimatorConfig(**dict(base, **ov)).validate()
                elif 'buffer_sise' in ov:
                    continue
                else:
                    getattr(est, how)(dataclasses.replace(est.config, **ov))
                kind, msg = 'accepted', ''
            except ValueError as exc:
                kind, msg = 'ValueError', str(exc)
            except Exception as exc:  # noqa: BLE001 - counted: undocumented exception
                kind, msg = type(exc).__name__, str(exc)
            res['attempts'] += 1
            if kind == 'accepted' and how == 'validate' and validate_may_accept:
                res['accepted by validate() alone (cannot know N; expected)'] += 1
            elif kind == 'ValueError' and msg and (name is None or name in msg or
                                                   (name == 'buffer_sise' and 'unknown' in msg)):
                res['refused with a reason'] += 1
            elif kind == 'ValueError':
                res['refused, reason does not name the parameter'] += 1
                bad.append(f'{lab}: {how}: reason {msg[:120]!r}')
            elif kind == 'accepted':
                res['accepted'] += 1
                bad.append(f'{lab}: {how}() accepted it')
            else:
                res['other exception'] += 1
                bad.append(f'{lab}: {how}: {kind}: {msg[:120]}')
            if how != 'validate' and not changed and \
                    snap != (est.config.to_dict(), id(est.model), est.samples()[0].tobytes()):
                changed = True
                res['changed something'] += 1
                bad.append(f'{lab}: {how}() changed the estimator')
        if changed:                 # isolate the next case
            est.close()
            est = trained()
            rebuilt += 1
    res['sets'] = len(cases)
    # still learning and answering after all that
    added0 = est.diagnostics()['samples_added']
    T = Tally('after parameter attacks')
    for _ in range(300):
        t, q, tau = good.next()
        feed(est, T, t, NAMES, q, tau, 'answer')
    d = est.diagnostics()
    est.close()
    # per-joint parameters that do not fit the joints, set before the first message (N is not
    # known yet, so nothing can refuse them): the messages that follow
    early = []
    for lab, ov in (('selection_scale 2 entries, then 3-joint messages',
                     {'selection_scale': [1.0, 1.0]}),
                    ('operating_domain 1 entry per bound (certified), then 3-joint messages',
                     {'passivity': 'certified', 'operating_domain': [-1.0, 1.0]})):
        e = OnlineEstimator(EstimatorConfig(**dict(base, model_path='', **ov)))
        Te = Tally(lab)
        g = Good(seed=4)
        for _ in range(200):
            t, q, tau = g.next()
            feed(e, Te, t, NAMES, q, tau, 'answer')
        de = e.diagnostics()
        e.close()
        first = next(iter(Te.exceptions), '')
        early.append({'label': lab, 'tally': Te, 'trained': de['trained'],
                      'refits_failed': de['refits_failed'], 'message': de['message'][:200],
                      'exception': first})
    return {'counts': res, 'problems': bad, 'cases': len(cases), 'rebuilt': rebuilt,
            'still_learning': d['samples_added'] > added0, 'tally': T, 'early': early}

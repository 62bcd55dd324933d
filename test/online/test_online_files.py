"""
Reliability: model files (issue 8, item 6) and no pickle anywhere in the package.

An incompatible version, a tampered, truncated or foreign file gives a clear ValueError from
``load_model``; through OnlineEstimator (model_path) such a file is not used, the reason is in
diagnostics()['load_error'] and nothing raises. Saves are atomic (a concurrent reader never sees
a half-written file).
"""
import json
import os
import pathlib
import re
import threading

import numpy as np
import pytest

from dgp_ros.gp import FORMAT_VERSION, load_model, make_model
from dgp_ros.gp.persistence import is_model_file
from dgp_ros.online import EstimatorConfig, OnlineEstimator

REPO = pathlib.Path(__file__).resolve().parents[2]


def _data(n=40, seed=0):
    rng = np.random.default_rng(seed)
    Q = rng.normal(size=(n, 3)) * [0.1, 0.05, 8.0] + [0.05, 0.0, 70.0]
    return Q, Q * [2.0, 1.0, 0.3]


@pytest.fixture(scope='module')
def saved(tmp_path_factory):
    Q, T = _data()
    m = make_model('full', passivity='paper').fit(Q, T)
    p = tmp_path_factory.mktemp('m') / 'model.npz'
    m.save(p)
    return m, p


def _arrays(p):
    with np.load(p, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _write(path, arrays):
    with open(path, 'wb') as f:
        np.savez(f, **arrays)
    return path


def _with_header(arrays, **changes):
    a = dict(arrays)
    h = json.loads(str(a['header']))
    for k, v in changes.items():
        if v is _DEL:
            h.pop(k, None)
        else:
            h[k] = v
    a['header'] = np.array(json.dumps(h))
    return a


_DEL = object()


def _cases(saved_path, tmp):
    a = _arrays(saved_path)
    raw = saved_path.read_bytes()
    out = {}
    out['version_99'] = (_write(tmp / 'v99.npz', _with_header(a, format_version=99)),
                         'format version 99')
    out['version_0'] = (_write(tmp / 'v0.npz', _with_header(a, format_version=0)),
                        'format version 0')
    out['version_missing'] = (_write(tmp / 'vnone.npz', _with_header(a, format_version=_DEL)),
                              'format version None')
    out['foreign_format'] = (_write(tmp / 'foreign.npz', _with_header(a, format='other')),
                             'not a dgp_ros model file')
    b = dict(a)
    b['alpha'] = b['alpha'].copy()
    b['alpha'][0, 0] += 1e-12
    out['array_bitflip'] = (_write(tmp / 'flip.npz', b), 'checksum mismatch')
    b = dict(a)
    b.pop('L0')
    out['array_removed'] = (_write(tmp / 'rm.npz', b), 'checksum mismatch')
    b = dict(a)
    b['extra'] = np.zeros(3)
    out['array_added'] = (_write(tmp / 'add.npz', b), 'checksum mismatch')
    b = dict(a)
    b.pop('header')
    out['no_header'] = (_write(tmp / 'nohdr.npz', b), 'no header')
    b = dict(a)
    b['header'] = np.array('{not json')
    out['corrupt_header'] = (_write(tmp / 'badjson.npz', b), 'corrupt header')
    for frac in (0.0, 0.1, 0.5, 0.99):
        p = tmp / f'trunc{frac}.npz'
        p.write_bytes(raw[:int(len(raw) * frac)])
        out[f'truncated_{frac}'] = (p, r'unreadable or truncated|not a dgp_ros')
    p = tmp / 'garbage.npz'
    p.write_bytes(os.urandom(4096))
    out['garbage'] = (p, r'unreadable or truncated|not a dgp_ros')
    p = tmp / 'text.npz'
    p.write_text('hello')
    out['text'] = (p, r'unreadable or truncated|not a dgp_ros')
    p = tmp / 'pickled.npy'
    np.save(p, np.array([{'a': 1}], dtype=object), allow_pickle=True)
    out['object_array'] = (p, r'not a dgp_ros|unreadable|pickle')
    out['missing'] = (tmp / 'nope.npz', 'no such model file')
    return out


CASE_NAMES = ['version_99', 'version_0', 'version_missing', 'foreign_format', 'array_bitflip',
              'array_removed', 'array_added', 'no_header', 'corrupt_header', 'truncated_0.0',
              'truncated_0.1', 'truncated_0.5', 'truncated_0.99', 'garbage', 'text',
              'object_array', 'missing']


@pytest.mark.parametrize('case', CASE_NAMES)
def test_bad_model_file_gives_clear_error(saved, tmp_path, case):
    path, pattern = _cases(saved[1], tmp_path)[case]
    with pytest.raises(ValueError, match=pattern) as ei:
        load_model(path)
    assert str(path) in str(ei.value)
    # through the estimator: a file that is not a model of ours is refused as model_path (a save
    # would overwrite it); a damaged model file is not used, the reason is reported, nothing
    # raises and the estimates are the prior's
    cfg = EstimatorConfig(model='full', passivity='paper', model_path=str(path),
                          refit_mode='sync')
    if path.exists() and not is_model_file(path):
        with pytest.raises(ValueError, match='not a dgp_ros model file|must end in .npz'):
            cfg.validate()
    elif path.exists():
        est = OnlineEstimator(EstimatorConfig(model='full', passivity='paper',
                                              model_path=str(path), refit_mode='sync'))
        assert not est.trained
        assert est.load_error and re.search(pattern, est.load_error)
        d = est.diagnostics()
        assert d['load_error'] and 'model file not used' in d['message'] and d['level'] >= 1
        e = est.process(1.0, ['a', 'b', 'c'], [0.1, 0.0, 70.0], [0.2, 0.0, 21.0])
        assert e is not None and e.source == 'prior' and e.power >= 0


def test_good_file_round_trip_and_format_version(saved):
    m, p = saved
    assert json.loads(str(_arrays(p)['header']))['format_version'] == FORMAT_VERSION
    Q = _data(30, seed=5)[0]
    np.testing.assert_array_equal(load_model(p).predict(Q), m.predict(Q))


@pytest.mark.parametrize('field', ['scale', 'certificate', 'params'])
def test_tampered_header_is_detected(saved, tmp_path, field):
    a = _arrays(saved[1])
    h = json.loads(str(a['header']))
    if field == 'scale':
        h['scale'] = 50.0
    elif field == 'certificate':
        h['certificate'] = dict(h['certificate'], margin=123.0)
    else:
        h['params'] = dict(h['params'], passivity='none')
    a['header'] = np.array(json.dumps(h))
    p = _write(tmp_path / 'hdr.npz', a)
    with pytest.raises(ValueError, match='checksum|tamper|modified'):
        load_model(p)


def test_wrong_kind_or_passivity_file_not_used(saved, tmp_path):
    m, p = saved
    for cfg in ({'model': 'diag', 'passivity': 'paper'},
                {'model': 'full', 'passivity': 'certified'}):
        est = OnlineEstimator(EstimatorConfig(model_path=str(p), refit_mode='sync', **cfg))
        assert not est.trained and est.load_error


def test_save_is_atomic_under_concurrent_reads(tmp_path):
    """A reader polling the file while it is rewritten 30 times never sees a partial file."""
    Q, T = _data(60)
    models = [make_model('diag', passivity='projected').fit(Q[:k], T[:k]) for k in (20, 40)]
    p = tmp_path / 'm.npz'
    models[0].save(p)
    stop = threading.Event()
    errors, loads = [], [0]

    def reader():
        while not stop.is_set():
            try:
                load_model(p)
                loads[0] += 1
            except ValueError as exc:
                errors.append(str(exc))

    th = threading.Thread(target=reader)
    th.start()
    try:
        for i in range(30):
            models[i % 2].save(p)
    finally:
        stop.set()
        th.join(10)
    assert not errors, errors[:3]
    assert loads[0] > 0
    assert not [f for f in os.listdir(tmp_path) if f.startswith('.tmp-')]


_PICKLE = re.compile(r'\b(import|from)\s+(c?pickle|dill|joblib|shelve|marshal)\b|'
                     r'\b(c?pickle|dill|joblib|marshal)\.(loads?|dumps?|Unpickler)\b|'
                     r'allow_pickle\s*=\s*True|\bnp\.load\(|numpy\.load\(')


def test_no_pickle_in_package_sources():
    hits = []
    files = [f for d in ('dgp_ros', 'sim_bridge') for f in (REPO / d).rglob('*.py')]
    files += [REPO / 'setup.py'] + list((REPO / 'bench').glob('*.py'))
    assert len(files) > 10
    for f in files:
        if not f.exists():
            continue
        for n, line in enumerate(f.read_text().splitlines(), 1):
            code = line.split('#', 1)[0]
            if 'allow_pickle=False' in code.replace(' ', '') and 'np.load(' in code:
                continue                         # an explicit, safe np.load
            if _PICKLE.search(code):
                hits.append(f'{f.relative_to(REPO)}:{n}: {line.strip()}')
    assert not hits, '\n'.join(hits)


def test_model_path_never_points_at_anything_but_a_model_file_of_ours(tmp_path):
    """The hardening issue's finding 4: refused at validation, so nothing is ever overwritten."""
    text = tmp_path / 'notes.npz'
    text.write_text('my notes')
    link = tmp_path / 'link.npz'
    good = tmp_path / 'good.npz'
    link.symlink_to(good)
    cases = {str(text): 'not a dgp_ros model file', str(tmp_path): 'must end in .npz',
             str(tmp_path / 'dir.npz'): 'not a regular file', '/dev/full': 'must end in .npz',
             str(link): 'symbolic link', str(tmp_path / 'nodir' / 'm.npz'): 'does not exist',
             str(tmp_path / 'm.txt'): 'must end in .npz'}
    (tmp_path / 'dir.npz').mkdir()
    for path, why in cases.items():
        with pytest.raises(ValueError, match=why):
            EstimatorConfig(model_path=path).validate()
    assert text.read_text() == 'my notes'
    # a save re-checks the path: replaced by a foreign file meanwhile, it is refused
    est = OnlineEstimator(EstimatorConfig(model='diag', min_samples=5, refit_mode='sync',
                                          selection='all', model_path=str(good)))
    for k in range(10):
        q = np.array([0.1 * k, 0.05 * k, 1.0 + 0.01 * k])
        est.process(0.1 * k, ['a', 'b', 'c'], q, 2 * q)
    assert est.trained and good.exists()
    good.unlink()
    good.write_text('replaced')
    with pytest.raises(ValueError, match='not a dgp_ros model file'):
        est.save()
    assert good.read_text() == 'replaced'

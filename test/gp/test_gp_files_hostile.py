"""
Model files from anywhere (the hardening issue's finding 5, and 8 for energy-injecting data).

The loader caps what it reads before it inflates or allocates, checks every shape, never trusts a
certificate, and raises only ValueError with a reason.
"""
import io
import json
import resource
import time
import zipfile

import numpy as np
import pytest

from dgp_ros.gp import DiagDGP, FullDGP, load_model, PASSIVITY_MODES
from dgp_ros.gp.persistence import _digest


def _data(n=40, seed=0, sign=1.0):
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-1, 1, (n, 3))
    return Q, (sign * (Q * [2.0, 1.0, 0.5] + 0.3 * np.tanh(Q / 0.1))
               + 0.01 * rng.normal(size=Q.shape))


def _arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _rewrite(path, arrays, **header_changes):
    """Change the header and recompute the digest (a forger can; it only stops accidents)."""
    a = dict(arrays)
    h = json.loads(str(a.pop('header')))
    h.update(header_changes)
    h['sha256'] = _digest(a, h)
    a['header'] = np.array(json.dumps(h))
    np.savez(path, **a)
    return path


@pytest.fixture(scope='module')
def saved(tmp_path_factory):
    m = FullDGP(passivity='certified', n_restarts=0).fit(*_data())
    p = tmp_path_factory.mktemp('m') / 'model.npz'
    m.save(p)
    return m, p


def test_header_with_a_huge_N_is_refused_before_any_work(saved, tmp_path):
    for N in (1200, 10 ** 5):
        p = _rewrite(tmp_path / f'n{N}.npz', _arrays(saved[1]), N=N)
        t0 = time.perf_counter()
        with pytest.raises(ValueError, match='outside 1..64'):
            load_model(p)
        assert time.perf_counter() - t0 < 1.0


def test_zip_bomb_is_refused_before_it_inflates(saved, tmp_path):
    a = _arrays(saved[1])
    p = tmp_path / 'bomb.npz'
    with zipfile.ZipFile(p, 'w', zipfile.ZIP_DEFLATED) as zf:
        for k, v in a.items():
            if k == 'X':
                continue
            buf = io.BytesIO()
            np.save(buf, v)
            zf.writestr(k + '.npy', buf.getvalue())
        with zf.open('X.npy', 'w', force_zip64=True) as f:       # 400 MB of zeros, ~400 kB
            hdr = io.BytesIO()
            np.lib.format.write_array_header_1_0(hdr, {'descr': '<f8', 'fortran_order': False,
                                                       'shape': (50_000_000,)})
            f.write(hdr.getvalue())
            chunk = bytes(1 << 22)
            for _ in range(100):
                f.write(chunk)
    assert p.stat().st_size < 5_000_000
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ValueError, match='inflates to'):
        load_model(p)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 50_000     # kB


def test_shapes_are_checked_against_N_and_n(saved, tmp_path):
    a = _arrays(saved[1])
    a['alpha'] = a['alpha'][:-1]
    with pytest.raises(ValueError, match='array alpha'):
        load_model(_rewrite(tmp_path / 'short.npz', a))


def test_a_forged_certificate_is_never_trusted(tmp_path):
    # a certified model of energy-injecting data: no proof exists (every answer is projected),
    # then a header that claims a certificate and a policy state that blends as if proven
    Q, T = _data(sign=-1.0)
    m = DiagDGP(passivity='certified', n_restarts=0).fit(Q, T)
    c0 = m.certificate()
    assert not c0.certified and c0.guarantee == 'pointwise'
    p = tmp_path / 'm.npz'
    m.save(p)
    a = _arrays(p)
    h = json.loads(str(a['header']))
    cert = dict(h['certificate'], certified=True, method='forged', margin=1.0,
                guarantee='psd')
    r = load_model(_rewrite(tmp_path / 'forged.npz', a, certificate=cert,
                            policy={'scale': 1.0, 'blend': True}))
    c = r.certificate()
    assert not c.certified and c.stale and c.method != 'forged' and c.guarantee == 'pointwise'
    X = np.random.default_rng(1).uniform(-3, 3, (20000, 3))
    assert np.einsum('ij,ij->i', X, r.predict(X)).min() >= 0     # passive pointwise meanwhile
    c = r.recertify()                  # re-derived from the model: the same verdict as the fit
    assert (c.certified, c.method, c.guarantee) == (c0.certified, c0.method, c0.guarantee)
    assert np.einsum('ij,ij->i', X, r.predict(X)).min() >= 0
    np.testing.assert_allclose(r.predict(X), m.predict(X), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('header', [
    '[' * 100_000 + ']' * 100_000,                       # RecursionError in json
    json.dumps({'format': 'dgp_ros.gp', 'format_version': 2}),             # KeyError
    json.dumps({'format': 'dgp_ros.gp', 'format_version': 2, 'kind': 'full', 'N': 'x'}),
    json.dumps({'format': 'dgp_ros.gp', 'format_version': 2, 'kind': ['full'], 'N': 3}),
])
def test_malformed_headers_raise_value_error_only(saved, tmp_path, header):
    a = _arrays(saved[1])
    a['header'] = np.array(header)
    p = tmp_path / 'h.npz'
    np.savez(p, **a)
    with pytest.raises(ValueError):
        load_model(p)


def test_devices_and_directories_are_refused(tmp_path):
    for p in ('/dev/zero', '/dev/null', str(tmp_path)):
        t0 = time.perf_counter()
        with pytest.raises(ValueError, match='not a regular file'):
            load_model(p)
        assert time.perf_counter() - t0 < 1.0


@pytest.mark.parametrize('cls', [FullDGP, DiagDGP])
@pytest.mark.parametrize('mode', PASSIVITY_MODES)
def test_energy_injecting_data_fit_without_lapack_errors(cls, mode):
    Q, T = _data(60, sign=-5.0)
    m = cls(passivity=mode, n_restarts=0).fit(Q, T)
    X = np.random.default_rng(2).uniform(-3, 3, (5000, 3))
    P = np.einsum('ij,ij->i', X, m.predict(X))
    assert np.all(np.isfinite(P))
    if mode != 'none':
        c = m.certificate()
        assert P.min() >= 0
        # no passive model fits energy-injecting data: a structural mode either proves one
        # (paper: by shrinking the correction) or says so and projects every answer
        assert c.certified or (mode == 'certified' and c.guarantee == 'pointwise')

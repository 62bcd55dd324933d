"""
Class 3, model files for ``load_model`` and as ``model_path`` (``bench/hostile.py``).

Crafted files (truncated, garbage, zip bombs, forged sizes and certificates, wrong shapes, ...)
built from a real model in the sandbox; each is loaded in a forked child (``in_child``) whose
time and peak RSS are measured.
"""
from __future__ import annotations

import io
import json
import os
import select
import shutil
import signal
import stat
import time
import zipfile

import numpy as np

from common import log

from .base import feed, fingerprint, Good, NAMES, proc_status, Sandbox, Tally, truth


def _arrays(path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _rewrite(path, arrays, header_changes=None, header_text=None, digest=True):
    """Write ``arrays`` with a changed header and (by default) the digest recomputed."""
    from dgp_ros.gp.persistence import _digest
    a = dict(arrays)
    if header_text is not None:
        a['header'] = np.array(header_text)
    else:
        h = json.loads(str(a.pop('header')))
        h.update(header_changes or {})
        if digest:
            h['sha256'] = _digest(a, h)
        a['header'] = np.array(json.dumps(h))
    np.savez(path, **a)
    return str(path)


def _rearray(path, arrays, **changes):
    """Arrays changed, digest recomputed (a forger can: it only stops accidents)."""
    from dgp_ros.gp.persistence import _digest
    a = dict(arrays)
    a.update(changes)
    h = json.loads(str(a.pop('header')))
    h['sha256'] = _digest(a, h)
    a['header'] = np.array(json.dumps(h))
    np.savez(path, **a)
    return str(path)


def _bomb(path, arrays, member: str, inflated: int):
    """
    Write a model file whose ``member`` inflates to ``inflated`` bytes.

    Zeros, streamed: the file stays small.
    """
    with zipfile.ZipFile(path, 'w', zipfile.ZIP_DEFLATED) as zf:
        for k, v in arrays.items():
            if k == member:
                continue
            buf = io.BytesIO()
            np.save(buf, v)
            zf.writestr(k + '.npy', buf.getvalue())
        with zf.open(member + '.npy', 'w', force_zip64=True) as f:
            hdr = io.BytesIO()
            np.lib.format.write_array_header_1_0(
                hdr, {'descr': '<f8', 'fortran_order': False, 'shape': (inflated // 8,)})
            f.write(hdr.getvalue())
            chunk = bytes(1 << 22)
            left = inflated
            while left > 0:
                f.write(chunk[:min(left, len(chunk))])
                left -= len(chunk)
    return str(path)


def build_files(sb: Sandbox, quick: bool) -> list:
    """
    Build the hostile model files.

    (name, path, expect, model kind) of hostile model files; expect: 'ValueError',
    'loads' (the control) or 'untrusted' (loads, the certificate is not taken from the file).
    """
    from dgp_ros.gp import DiagDGP, FullDGP
    rng = np.random.default_rng(0)
    Q = rng.uniform(-1, 1, (40, 3))
    T = truth(Q) + 0.01 * rng.normal(size=Q.shape)
    good = os.path.join(sb.files, 'good.npz')
    FullDGP(passivity='certified', n_restarts=0).fit(Q, T).save(good)
    a = _arrays(good)
    raw = open(good, 'rb').read()
    f = lambda n: os.path.join(sb.files, n)  # noqa: E731
    V = 'ValueError'
    cases = [('control: a good model file', good, 'loads', 'full')]
    for frac in (0.0, 0.1, 0.5, 0.9, 0.99):
        p = f(f'truncated_{frac}.npz')
        open(p, 'wb').write(raw[:int(len(raw) * frac)])
        cases.append((f'truncated at {int(frac * 100)} %', p, V, 'full'))
    for n, data in (('garbage 4 kB', os.urandom(4096)), ('garbage 1 MB', os.urandom(1 << 20)),
                    ('garbage after a zip signature', b'PK\x03\x04' + os.urandom(8192)),
                    ('text', b'hello, I am not a model\n' * 100)):
        p = f(n.replace(' ', '_') + '.npz')
        open(p, 'wb').write(data)
        cases.append((n, p, V, 'full'))
    mb = 100 if quick else 400
    cases.append((f'zip bomb: X inflates to {mb} MB', _bomb(f('bomb_X.npz'), a, 'X', mb << 20),
                  V, 'full'))
    cases.append((f'zip bomb: header inflates to {mb // 2} MB',
                  _bomb(f('bomb_header.npz'), a, 'header', (mb // 2) << 20), V, 'full'))
    cases.append((f'zip bomb: unknown member inflates to {mb // 2} MB',
                  _bomb(f('bomb_member.npz'), dict(a, pol_zz=np.zeros(1)), 'pol_zz',
                        (mb // 2) << 20), V, 'full'))
    n_members = 2000 if quick else 20000
    p = f('many_members.npz')
    with zipfile.ZipFile(p, 'w', zipfile.ZIP_STORED) as zf:
        for k, v in a.items():
            buf = io.BytesIO()
            np.save(buf, v)
            zf.writestr(k + '.npy', buf.getvalue())
        small = io.BytesIO()
        np.save(small, np.zeros(1))
        for i in range(n_members):
            zf.writestr(f'pol_m{i}.npy', small.getvalue())
    cases.append((f'{n_members} extra members', p, V, 'full'))
    for N in (1200, 10 ** 5):
        cases.append((f'header N = {N} (digest recomputed)',
                      _rewrite(f(f'N{N}.npz'), a, {'N': N}), V, 'full'))
    cases.append(('header n = 10^9 (digest recomputed)',
                  _rewrite(f('n1e9.npz'), a, {'n': 10 ** 9}), V, 'full'))
    cases.append(('header kind "evil" (digest recomputed)',
                  _rewrite(f('kind.npz'), a, {'kind': 'evil'}), V, 'full'))
    cases.append(('header params not a dict',
                  _rewrite(f('params.npz'), a, {'params': 'x'}), V, 'full'))
    cases.append(('header params with an unknown argument',
                  _rewrite(f('params2.npz'), a, {'params': {'__class__': 1}}), V, 'full'))
    cases.append(('header mean bogus',
                  _rewrite(f('mean.npz'), a, {'mean': {'name': 'evil'}}), V, 'full'))
    cases.append(('deep JSON header (10^5 nested lists)',
                  _rewrite(f('deep.npz'), a, header_text='[' * 100_000 + ']' * 100_000), V,
                  'full'))
    deep = json.loads(str(a['header']))
    deep['params'] = 'DEEP'
    text = json.dumps(deep).replace('"DEEP"', '[' * 50_000 + ']' * 50_000)
    cases.append(('deep JSON inside params',
                  _rewrite(f('deep2.npz'), a, header_text=text), V, 'full'))
    cases.append(('header not JSON', _rewrite(f('badjson.npz'), a, header_text='{not json'), V,
                  'full'))
    cases.append(('alpha one row short', _rearray(f('short.npz'), a, alpha=a['alpha'][:-1]), V,
                  'full'))
    n = a['X'].shape[0]
    cases.append(('L0 of shape (n+1, n+1)', _rearray(f('L0.npz'), a, L0=np.eye(n + 1)), V,
                  'full'))
    cases.append(('X float32', _rearray(f('f32.npz'), a, X=a['X'].astype(np.float32)), V,
                  'full'))
    cases.append(('X 3-D', _rearray(f('x3d.npz'), a, X=a['X'][:, :, None]), V, 'full'))
    xn = a['X'].copy()
    xn[0, 0] = np.nan
    cases.append(('X with NaN', _rearray(f('xnan.npz'), a, X=xn), V, 'full'))
    cases.append(('hyper-parameters 1e300', _rearray(f('hp.npz'), a, hp_log_ls=np.full_like(
        a['hp_log_ls'], 1e300)), V, 'full'))
    p = f('pickle.npz')
    b = dict(a)
    b['jit'] = np.array([{'x': 1}], dtype=object)
    with open(p, 'wb') as fh:
        np.savez(fh, **b)         # np.savez pickles object arrays
    cases.append(('an object (pickle) member', p, V, 'full'))
    # forged certificate: a certified model of energy-injecting data (its correction switched
    # off), with a header that switches it on and claims a certificate
    m = DiagDGP(passivity='certified', n_restarts=0).fit(Q, -T)
    p0 = f('forged_src.npz')
    m.save(p0)
    a2 = _arrays(p0)
    h = json.loads(str(a2['header']))
    cert = dict(h['certificate'], certified=True, method='forged', margin=1.0,
                correction_scale=1.0)
    cases.append(('forged certificate (digest recomputed)',
                  _rewrite(f('forged.npz'), a2, {'certificate': cert, 'policy': {'scale': 1.0}}),
                  'untrusted', 'diag'))
    sparse = f('sparse_5GB.npz')
    with open(sparse, 'wb') as fh:
        fh.truncate(5 << 30)
    cases.append(('5 GB sparse file', sparse, V, 'full'))
    cases += [('/dev/zero', '/dev/zero', V, 'full'), ('/dev/urandom', '/dev/urandom', V, 'full'),
              ('/dev/null', '/dev/null', V, 'full'), ('a directory', sb.decoy('dir.npz'), V,
                                                      'full'),
              ('a FIFO', sb.decoy('fifo.npz'), V, 'full'),
              ('symlink to /dev/zero', sb.decoy('zero.npz'), V, 'full'),
              ('missing file', f('missing.npz'), V, 'full')]
    return cases


# ----------------------------------------------------------------------------- forked loads
def in_child(fn, timeout: float):
    """
    Run ``fn()`` in a forked child; return (outcome, message, seconds, rss_delta_mib, info).

    outcome: 'ok' (returned), an exception class name, or 'timeout' / 'died'.
    """
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:                      # child
        try:
            os.close(r)
            try:
                with open('/proc/self/clear_refs', 'w') as f:
                    f.write('5')      # reset VmHWM to the current RSS
            except OSError:
                pass
            rss0 = proc_status('VmRSS')
            t0 = time.perf_counter()
            info = None
            try:
                info = fn()
                outcome, msg = 'ok', ''
            except BaseException as exc:  # noqa: BLE001 - the outcome is what we measure
                outcome, msg = type(exc).__name__, str(exc)
            dt = time.perf_counter() - t0
            hwm = proc_status('VmHWM')
            data = json.dumps([outcome, msg[:400], dt, hwm - rss0, info], default=str).encode()
            os.write(w, data)
        finally:
            os._exit(0)
    os.close(w)
    buf = b''
    end = time.monotonic() + timeout
    while True:
        left = end - time.monotonic()
        if left <= 0:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(r)
            return 'timeout', f'more than {timeout} s', timeout, float('nan'), None
        rl, _, _ = select.select([r], [], [], left)
        if rl:
            chunk = os.read(r, 1 << 16)
            if not chunk:
                break
            buf += chunk
    os.close(r)
    _, status = os.waitpid(pid, 0)
    if not buf:
        return 'died', f'status {status}', float('nan'), float('nan'), None
    outcome, msg, dt, drss, info = json.loads(buf)
    return outcome, msg, dt, drss, info


def _load_probe(path):
    def fn():
        from dgp_ros.gp import load_model
        m = load_model(path)
        c = m.certificate()
        X = np.random.default_rng(0).uniform(-3, 3, (2000, m.X_train_.shape[1]))
        P = np.einsum('ij,ij->i', X, m.predict(X))
        return {'certified': bool(c.certified), 'stale': bool(getattr(c, 'stale', False)),
                'method': str(c.method), 'min_power': float(P.min()),
                'finite': bool(np.all(np.isfinite(P)))}
    return fn


def _model_path_probe(path, kind, passivity, n_msgs=30):
    def fn():
        from dgp_ros.online import EstimatorConfig, OnlineEstimator
        try:
            est = OnlineEstimator(EstimatorConfig(model=kind, passivity=passivity,
                                                  model_path=path, refit_mode='sync',
                                                  buffer_size=100, min_samples=10))
        except ValueError as exc:
            return {'result': 'refused', 'reason': str(exc)[:300]}
        d = est.diagnostics()
        T = Tally('model_path')
        good = Good(seed=5)
        for _ in range(n_msgs):
            t, q, tau = good.next()
            feed(est, T, t, NAMES, q, tau, 'answer')
        d2 = est.diagnostics()
        est.close()
        return {'result': 'load_error' if d['load_error'] else 'loaded',
                'reason': d['load_error'][:300], 'certified': d['certified'],
                'method': d['method'],
                'stale': d['certificate_stale'], 'nonfinite': T.nonfinite,
                'nonpassive': T.nonpassive, 'trained_after': d2['trained'],
                'samples_added': d2['samples_added']}
    return fn


def run_files(sb: Sandbox, quick: bool) -> dict:
    from dgp_ros.gp.persistence import is_model_file
    t0 = time.perf_counter()
    cases = build_files(sb, quick)
    n_probe = 5 if quick else 30          # quick: answers only (min_samples 10: no fit)
    log(f'files: {len(cases)} built in {time.perf_counter() - t0:.1f} s')
    rows = []
    for name, path, expect, kind in cases:
        oc, msg, dt, drss, info = in_child(_load_probe(path), 120.0)
        if expect == 'ValueError':
            ok = oc == 'ValueError' and bool(msg)
        elif expect == 'loads':
            ok = oc == 'ok'
        else:
            ok = oc == 'ok' and info is not None and not (
                info['certified'] and info['method'] == 'forged') and info['min_power'] >= 0
        # as model_path (a copy in the scratch directory, so a save may overwrite it)
        mp_row = ('-', '', float('nan'), float('nan'))
        mp_ok = True
        # the file's own passivity where it should load (else the mode mismatch is the reason)
        pas = 'certified' if expect != 'ValueError' else 'projected'
        src_is_ours = False
        if os.path.isfile(path) and not os.path.islink(path):
            dst = path                  # huge (sparse) files in place: they must be refused
            if os.path.getsize(path) < (64 << 20):
                dst = os.path.join(sb.scratch, os.path.basename(path))
                shutil.copyfile(path, dst)
            src_is_ours = is_model_file(dst)
            fp0 = fingerprint(dst)
            moc, mmsg, mdt, mdrss, minfo = in_child(
                _model_path_probe(dst, kind, pas, n_probe), 120.0)
            fp1 = fingerprint(dst)
            if moc != 'ok' or minfo is None:
                mp_ok = False
                mp_row = (moc, mmsg, mdt, mdrss)
            else:
                res = minfo['result']
                mp_ok = (minfo.get('nonfinite', 0) == 0 and minfo.get('nonpassive', 0) == 0 and
                         (res == 'refused' or quick or minfo.get('trained_after', False)))
                if expect == 'ValueError':
                    mp_ok = mp_ok and res in ('refused', 'load_error')
                if expect == 'untrusted':
                    mp_ok = mp_ok and not (minfo['certified'] and minfo['method'] == 'forged')
                # a file that is not one of ours must never be overwritten
                if fp0 != fp1 and not src_is_ours:
                    mp_ok = False
                    minfo['overwritten'] = True
                mp_row = (res, minfo.get('reason', '') or
                          f'certified {minfo.get("certified")}, method {minfo.get("method")}',
                          mdt, mdrss)
        elif path.startswith('/dev/') or os.path.islink(path) or os.path.isdir(path) or \
                stat.S_ISFIFO(os.lstat(path).st_mode if os.path.lexists(path) else 0):
            moc, mmsg, mdt, mdrss, minfo = in_child(
                _model_path_probe(path, kind, pas, n_probe), 60.0)
            mp_ok = moc == 'ok' and minfo and minfo['result'] == 'refused'
            mp_row = (minfo['result'] if minfo else moc, (minfo or {}).get('reason', mmsg),
                      mdt, mdrss)
        rows.append({'name': name, 'expect': expect, 'outcome': oc, 'message': msg, 'seconds': dt,
                     'rss_mib': drss, 'info': info, 'ok': bool(ok), 'mp': mp_row,
                     'mp_ok': bool(mp_ok)})
        log(f'  file {name}: {oc} ({dt:.3f} s, {drss:.1f} MiB) | model_path: {mp_row[0]}'
            + ('' if ok and mp_ok else '  <-- FAILED'))
    os.unlink(os.path.join(sb.files, 'sparse_5GB.npz'))
    return {'rows': rows}

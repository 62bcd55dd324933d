"""
Model files: an ``.npz`` of plain arrays plus a JSON header; no pickle, bounded reads.

Writing is atomic (temp file in the same directory, fsync, ``os.replace``): a reader sees the old
file or the new one. The header carries the format version, the model kind and sizes, the
constructor arguments, the prior mean, the passivity policy's state and a SHA-256 over header and
arrays (it detects accidental damage; it is not a signature).

Reading trusts nothing in the file:

* only a regular file, at most ``MAX_FILE_BYTES``; the header member is read first (at most
  ``MAX_HEADER_BYTES``) and ``N <= MAX_JOINTS``, ``n <= MAX_SAMPLES`` are checked before any array
  is inflated; every member's inflated size is checked against what ``N`` and ``n`` allow (a zip
  bomb is refused before it expands);
* every array's shape and dtype is checked against ``N`` and ``n``; hyper-parameters and the prior
  mean are validated (finite, in range, passive prior);
* the certificate is never taken from the file: a structural certificate is marked *stale*
  (``certified`` False until ``recertify()`` re-proves it); the cheap ones are recomputed;
* every failure is a ``ValueError`` with a reason.

A model may carry a *correction* besides its damping force (the online learner's conservative
correction of a rigid-body model, ``correction_``). Its record is saved by kind and rebuilt by
the code that owns the kind; this package imports none of it. Owners are found two ways: a
module registers its kinds when imported (``register_correction``: ``dgp_ros.dynamics``
registers 'conservative'), and an installed package declares them as entry points of the group
``dgp_ros.corrections`` (``ENTRY_POINTS``; dgp_ros's ``setup.py`` declares 'conservative'),
found with ``importlib.metadata`` by the record's kind when a saved correction is first
evaluated. So ``load_model(path).predict_residual(q=..., qd=...)`` works after importing
``dgp_ros.gp`` alone, and the owner's import (pinocchio for a URDF basis) is paid only then. A
model whose correction has no owner loads all the same (its damping force needs none): the
record is kept as a :class:`SavedCorrection`, saved back unchanged, and evaluating it raises
ValueError naming what to install or import. A kind is only ever looked up among installed
entry points, never imported by a name a file gives.
"""
from __future__ import annotations

from dataclasses import dataclass
import hashlib
import importlib.metadata
import io
import json
import os
import stat
import tempfile
from typing import Optional
import zipfile

import numpy as np

from .kernels import KINDS, Structure
from .means import mean_from_dict
from .posterior import Hyper, Posterior

__all__ = ['save_model', 'read_model', 'ModelFile', 'is_model_file', 'FORMAT_VERSION',
           'MAX_JOINTS', 'MAX_SAMPLES', 'register_correction', 'rebuild_correction',
           'SavedCorrection', 'ENTRY_POINTS']

FORMAT_VERSION = 2
MAX_JOINTS = 64
MAX_SAMPLES = 20_000
MAX_FILE_BYTES = 4 << 30
MAX_HEADER_BYTES = 1 << 20
MAX_LEAVES = 1_000_000
_NPY_OVERHEAD = 4096


def _digest(arrays: dict, header: dict) -> str:
    """SHA-256 over every array (name, dtype, shape, bytes) and the header (minus the digest)."""
    h = hashlib.sha256()
    h.update(json.dumps({k: v for k, v in header.items() if k != 'sha256'},
                        sort_keys=True).encode())
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode())
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_model(model, path) -> None:
    """Write a fitted model to ``path`` atomically (see the module docstring)."""
    post = model.posterior_.ensure_factors()       # a predict-only snapshot: refactorized
    arrays = {'X': post.X, 'R': post.R, 'alpha': post.alpha, 'jit': post.jitter}
    if post.delta is not None:
        arrays['delta'] = post.delta
    for m, f in enumerate(post.factors):
        arrays[f'L{m}'] = f.L
        arrays[f'z{m}'] = f.z
    for k in post.hyper.FIELDS:
        arrays['hp_' + k] = np.asarray(getattr(post.hyper, k), float)
    meta, parr = model.policy_.state()
    arrays.update({'pol_' + k: v for k, v in parr.items()})
    params = model.get_params()
    if not isinstance(params.get('prior'), str):      # a frozen prior: it is the mean record
        params['prior'] = 'frozen'
    params = _jsonable(params)
    params['hyperparams'] = None
    header = {'format': 'dgp_ros.gp', 'format_version': FORMAT_VERSION,
              'kind': post.structure.kind, 'N': post.N, 'n': post.n, 'params': params,
              'window': post.window, 'mean': post.mean.to_dict(), 'policy': meta,
              'certificate': model.policy_.cert.to_dict()}
    correction = getattr(model, 'correction_', None)
    if correction is not None:      # what the residual holds besides damping (online learner)
        header['correction'] = _jsonable(correction.to_dict())
    grounds = getattr(model, 'grounds_', None)
    if grounds is not None:         # the online learner's earned gains (a record, kept as is)
        header['grounds'] = _jsonable(grounds)
    header['sha256'] = _digest(arrays, header)
    arrays['header'] = np.array(json.dumps(header))
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix='.tmp-', suffix='.npz', dir=d)
    try:
        with os.fdopen(fd, 'wb') as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _jsonable(x):
    """Convert constructor arguments to JSON: arrays and tuples become lists."""
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _read_member(zf: zipfile.ZipFile, name: str, limit: int) -> np.ndarray:
    info = zf.getinfo(name)
    if info.file_size > limit:
        raise ValueError(f'member {name} inflates to {info.file_size} bytes, more than the '
                         f'{limit} its header allows')
    with zf.open(info) as f:
        raw = f.read(limit + 1)
    if len(raw) > limit:
        raise ValueError(f'member {name} is larger than declared')
    return np.load(io.BytesIO(raw), allow_pickle=False)


def _expected_shapes(kind: str, N: int, n: int, E: int) -> dict:
    shapes = {'X': (n, N), 'R': (n, N), 'alpha': (n, N), 'jit': (N,), 'hp_log_sf2': (E,),
              'hp_log_ls': (E, N), 'hp_log_sn2': (N,), 'hp_sx': (N,), 'hp_sy': (N,)}
    for m in range(N):
        shapes[f'L{m}'] = (n, n)
        shapes[f'z{m}'] = (n,)
    return shapes


def is_model_file(path) -> bool:
    """
    Tell whether ``path`` is a dgp_ros model file.

    True when ``path`` is a regular file whose header says it is a dgp_ros model (any format
    version); reads the header member only. Never raises.
    """
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_FILE_BYTES:
            return False
        with zipfile.ZipFile(path) as zf:
            header = json.loads(str(_read_member(zf, 'header.npy', MAX_HEADER_BYTES)))
        return isinstance(header, dict) and header.get('format') == 'dgp_ros.gp'
    except Exception:
        return False


@dataclass
class ModelFile:
    """
    The validated content of a model file (``read_model``), not yet a model.

    kind : 'full' | 'diag' | 'ard'; params : constructor arguments (``hyperparams`` None);
    posterior : the restored ``Posterior``; policy : the policy's saved state (json dict);
    policy_arrays : its arrays; certificate : the saved record (never trusted: the policy
    re-derives it); correction, grounds : records the online learner saved with the model.
    """

    kind: str
    params: dict
    posterior: Posterior
    policy: dict
    policy_arrays: dict
    certificate: dict
    correction: Optional[dict] = None
    grounds: Optional[dict] = None      # the online learner's gains (``online.learner.grounds``)


def read_model(path) -> ModelFile:
    """
    Read and validate a file written by ``save_model`` (the module docstring says what is checked).

    This layer sits below the estimators: it returns the pieces and ``models.load_model`` builds
    the estimator from them. Raises ValueError with a reason for anything that is not a usable
    dgp_ros model file.
    """
    try:
        return _load(os.fspath(path))
    except ValueError:
        raise
    except (MemoryError, RecursionError, OverflowError) as exc:
        raise ValueError(f'{path}: model file too large or too deeply nested '
                         f'({type(exc).__name__})') from None
    except Exception as exc:  # zipfile, zlib, OSError, KeyError, TypeError from a crafted file
        raise ValueError(f'{path}: unreadable or malformed model file '
                         f'({type(exc).__name__}: {exc})') from None


def _load(path: str) -> ModelFile:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ValueError(f'{path}: no such model file') from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f'{path}: not a regular file')
    if st.st_size > MAX_FILE_BYTES:
        raise ValueError(f'{path}: {st.st_size} bytes, larger than a model file may be')
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise ValueError(f'{path}: unreadable or truncated model file ({exc})') from None
    with zf:
        names = {n[:-4]: n for n in zf.namelist() if n.endswith('.npy')}
        if 'header' not in names:
            raise ValueError(f'{path}: not a dgp_ros model file (no header)')
        try:
            header = json.loads(str(_read_member(zf, names['header'], MAX_HEADER_BYTES)))
        except json.JSONDecodeError as exc:
            raise ValueError(f'{path}: corrupt header ({exc})') from None
        if not isinstance(header, dict) or header.get('format') != 'dgp_ros.gp':
            raise ValueError(f'{path}: not a dgp_ros model file')
        version = header.get('format_version')
        if version not in (1, FORMAT_VERSION):
            raise ValueError(f'{path}: model format version {version} is not supported by this '
                             f'dgp_ros (reads 1 and {FORMAT_VERSION}); refit and save again')
        kind, N = header.get('kind'), header.get('N')
        if kind not in KINDS:
            raise ValueError(f"unknown model kind {kind!r}: expected one of {', '.join(KINDS)}")
        if not isinstance(N, int) or not 1 <= N <= MAX_JOINTS:
            raise ValueError(f'{path}: N = {N!r} outside 1..{MAX_JOINTS}')
        structure = Structure.of(kind, N)
        n = header.get('n')
        if version == 1:       # sizes were not in the header: read X (bounded) to learn n
            X = _read_member(zf, names['X'], 8 * MAX_SAMPLES * N + _NPY_OVERHEAD)
            n = int(X.shape[0]) if X.ndim == 2 else None
        if not isinstance(n, int) or not 1 <= n <= MAX_SAMPLES:
            raise ValueError(f'{path}: n = {n!r} samples outside 1..{MAX_SAMPLES}')
        shapes = _expected_shapes(kind, N, n, structure.E)
        limit_other = 8 * MAX_LEAVES * N + _NPY_OVERHEAD      # the proof partition
        arrays = {}
        for key, member in names.items():
            if key == 'header':
                continue
            shape = shapes.get(key, (n, N) if key == 'delta' else None)
            lim = (8 * int(np.prod(shape)) + _NPY_OVERHEAD) if shape else limit_other
            arrays[key] = _read_member(zf, member, lim)
    if _digest(arrays, header) != header.get('sha256'):
        raise ValueError(f'{path}: checksum mismatch: the model file was modified or damaged')
    if version == 1:
        header, arrays = _upgrade_v1(header, arrays, kind, N)
    for key, shape in shapes.items():
        a = arrays.get(key)
        if a is None or a.shape != shape or a.dtype != np.float64:
            raise ValueError(f'{path}: array {key} missing or not float64 of shape {shape} '
                             f'(N = {N}, n = {n})')
        if not np.all(np.isfinite(a)) and key != 'hp_log_sf2':
            raise ValueError(f'{path}: array {key} has non-finite values')
    params = dict(header['params'])
    params['hyperparams'] = None
    hyper = Hyper.from_dict({k: arrays['hp_' + k] for k in Hyper.FIELDS}, structure)
    mean = mean_from_dict(header['mean'], N)
    window = header.get('window', params.get('window'))
    delta = arrays.get('delta')
    if delta is not None and (delta.shape != (n, N) or not np.all(np.isfinite(delta))):
        raise ValueError(f'{path}: array delta is not a finite ({n}, {N}) array')
    post = Posterior.restore(structure, hyper, mean, arrays['X'], arrays['R'], arrays['alpha'],
                             arrays['jit'], [arrays[f'L{m}'] for m in range(N)],
                             [arrays[f'z{m}'] for m in range(N)], window, delta)
    pol_arrays = {k[4:]: v for k, v in arrays.items() if k.startswith('pol_')}
    if params.get('prior') == 'frozen':
        params['prior'] = mean
    grounds = header.get('grounds')
    return ModelFile(kind, params, post, header.get('policy', {}), pol_arrays,
                     header.get('certificate', {}), header.get('correction'),
                     grounds if isinstance(grounds, dict) else None)


def _upgrade_v1(header: dict, arrays: dict, kind: str, N: int):
    """Format 1 (constant prior ``hp_mean``, policy state in the header) -> format 2."""
    header = dict(header)
    hp_mean = arrays.pop('hp_mean', None)
    if hp_mean is None or hp_mean.shape != (N,):
        raise ValueError('format 1 model without a valid prior mean')
    if kind == 'ard':
        header['mean'] = {'name': 'constant', 'value': hp_mean.tolist(), 'bias': [0.0] * N}
    else:
        header['mean'] = {'name': 'viscous', 'm_d': hp_mean.tolist(), 'bias': [0.0] * N}
    header['policy'] = {'scale': header.get('scale', 1.0)}
    for k in ('dom_ilo', 'dom_ihi', 'dom_olo', 'dom_ohi', 'leaves_lo', 'leaves_hi'):
        if k in arrays:
            arrays['pol_' + k] = arrays.pop(k)
    return header, arrays


# ------------------------------------------------------------------------ saved corrections
#: rebuilders of the corrections a model file may carry, by kind (``register_correction``)
_CORRECTIONS: dict = {}
#: the module that registers each kind the package writes (named in an error, never imported)
_OWNERS = {'conservative': 'dgp_ros.dynamics'}
#: the entry-point group in which installed packages declare correction kinds: the name is the
#: kind, the object its rebuilder ``from_dict(record)``
ENTRY_POINTS = 'dgp_ros.corrections'


def register_correction(kind: str, from_dict) -> None:
    """
    Let model files carry corrections of ``kind``, rebuilt by ``from_dict(record)``.

    A correction is what a model's ``correction_`` holds besides the damping force:
    ``correction(Q)`` at poses Q (k, N), or None when it does not use them, gives (k, N) N m,
    and ``correction.to_dict()`` its JSON record, with its ``kind``. The module that owns a kind
    registers it when imported (module docstring).
    """
    _CORRECTIONS[str(kind)] = from_dict


def _kind(record: dict) -> str:
    # a record without a kind was written before kinds were recorded: the conservative one
    return str(record.get('kind', 'conservative'))


def _rebuilder(kind: str):
    """Return the rebuilder of ``kind``: registered, else an installed entry point; or None."""
    from_dict = _CORRECTIONS.get(kind)
    if from_dict is not None:
        return from_dict
    try:
        found = [ep for ep in importlib.metadata.entry_points(group=ENTRY_POINTS)
                 if ep.name == kind]
    except Exception:       # noqa: BLE001 - broken metadata: as if nothing were declared
        found = []
    for ep in found[:1]:
        from_dict = ep.load()           # imports the owner, which may register it itself
        _CORRECTIONS.setdefault(kind, from_dict)
        return _CORRECTIONS[kind]
    return None


def rebuild_correction(record: dict):
    """Rebuild a saved correction by its kind; a :class:`SavedCorrection` if none is registered."""
    from_dict = _CORRECTIONS.get(_kind(record))
    return SavedCorrection(record) if from_dict is None else from_dict(record)


class SavedCorrection:
    """
    A saved correction whose owner is not imported: kept as its record, rebuilt when called.

    ``save`` writes the record back unchanged; calling it (``predict_residual``) rebuilds it
    through the registry once its owner has been imported, and raises ValueError naming that
    module before.
    """

    def __init__(self, record: dict):
        self.record = record
        self._built = None

    def __call__(self, Q=None) -> np.ndarray:
        """Return the correction at poses Q (k, N), (k, N) N m (see ``register_correction``)."""
        if self._built is None:
            kind = _kind(self.record)
            from_dict = _rebuilder(kind)
            if from_dict is None:
                owner = _OWNERS.get(kind, 'the module that defines it')
                raise ValueError(f'this model carries a {kind!r} correction of the rigid-body '
                                 f'model and no installed package declares it (entry point '
                                 f'group {ENTRY_POINTS}); install dgp_ros or import {owner} '
                                 '(which rebuilds it) to evaluate it')
            self._built = from_dict(self.record)
        return self._built(Q)

    def to_dict(self) -> dict:
        return self.record

"""
The export of a frozen model: read the file as the frozen node does, prove it, write C++.

"Frozen" is a property of what serves, not of a file: a model file never changes, and the node
started with ``learning:=false model_path:=M`` serves exactly ``load_model(M)`` after proving
its certificate (never taken from the file). So any model file can be exported, also one saved
while its learner was still learning (Ctrl-C, ``~/save_model``): the header answers as a frozen
node serving that file would. What cannot be exported is a model that is still changing: an
``OnlineEstimator`` or ``Learner`` (stop learning, which saves ``model_path``, and export that
file), or a fitted model object whose owner may still ``update`` it (it is written to a file
and read back, so the header carries that moment's model, proven as the node would prove it).
"""
from __future__ import annotations

import hashlib
import os
import tempfile
from typing import List, Optional, Tuple

import numpy as np

from dgp_ros import __version__
from dgp_ros.gp import load_model

from .cpp import render
from .errors import ExportError
from .literals import comment
from .spec import model_spec, prove_as_node, Spec

__all__ = ['served_model', 'export_cpp', 'header_spec', 'write_header', 'check_correction']


def _digest(path: str) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def served_model(path) -> Tuple[object, str]:
    """
    Return (model, proof) as the frozen node serves the model file ``path``.

    ``load_model(path)``, then its certificate proven as the node proves a file it loads
    (``spec.prove_as_node``); ``proof`` is '' when the certificate holds, else why every answer
    is projected. Raises ExportError for a file that is not a model.
    """
    try:
        model = load_model(path)
    except ValueError as exc:
        raise ExportError(f'{path}: not a model file that can be exported ({exc})') from None
    return model, prove_as_node(model)


def _as_path(source, tmpdir: str) -> str:
    """Return a model file path for ``source`` (a path, or a fitted model saved to ``tmpdir``)."""
    if isinstance(source, (str, os.PathLike)):
        return os.fspath(source)
    if hasattr(source, 'set_learning') or hasattr(source, 'adopt'):
        raise ExportError(f'a {type(source).__name__} is still learning: stop learning '
                          '(learning:=false saves model_path; or save()) and export that '
                          'model file')
    if not hasattr(source, 'posterior_') or not hasattr(source, 'save'):
        raise ExportError(f'cannot export a {type(source).__name__}: give a model file or a '
                          'fitted FullDGP / DiagDGP')
    path = os.path.join(tmpdir, 'model.npz')
    source.save(path)
    return path


def check_correction(model, spec: Spec, poses: int = 64) -> float:
    """
    Compare the header's kinematic gravity with the model's own correction at random poses.

    Returns the largest difference relative to the largest torque; ExportError beyond 1e-9
    (a URDF whose kinematics the generated code would get wrong is refused, not exported).
    """
    c = spec.correction
    if c is None or c['basis'] != 'regressor':
        return 0.0
    from .kinematics import gravity_torque
    Q = np.random.default_rng(0).uniform(-np.pi, np.pi, (poses, spec.N))
    ref = np.einsum('knc,c->kn', model.correction_.basis.deploy(Q), c['theta'])
    got = gravity_torque(c['chain'], c['theta'], Q)
    err = float(np.abs(got - ref).max() / max(np.abs(ref).max(), 1e-300))
    if err > 1e-9:
        raise ExportError(f'the URDF kinematics read from the model do not reproduce its '
                          f'gravity regressor (relative error {err:.2g}): export with '
                          '--no-correction and add the correction in your controller')
    return err


def header_spec(source, names: Optional[List[str]] = None, correction: bool = True):
    """
    Return (spec, model, path info) of what the header of ``source`` carries.

    ``source``: a model file path or a fitted model (module docstring). The model returned is
    the Python model as the frozen node serves it (proven), for comparisons.
    """
    with tempfile.TemporaryDirectory() as tmp:
        path = _as_path(source, tmp)
        model, proof = served_model(path)
        digest = _digest(path)
    if not correction:
        model.correction_ = None
    spec = model_spec(model, names, proof)
    check_correction(model, spec)
    spec.info = {'source': os.fspath(source) if isinstance(source, (str, os.PathLike))
                 else f'a fitted {type(source).__name__}', 'sha256': digest}
    return spec, model


def _banner(spec: Spec) -> str:
    el = len(spec.elements)
    proof = ('the certificate holds' if not spec.proof else
             f'{spec.proof}: every answer is projected onto qd . tau >= 0')
    grounds = 'none (weight 1)' if spec.grounds is None else \
        ('per joint (psd kept)' if spec.per_joint else 'one scalar min(w)')
    lines = [
        f'// Generated by dgp-export (dgp_ros {__version__}): do not edit; export again.',
        f'// Model: {spec.info.get("source", "")} (sha256 {spec.info.get("sha256", "")[:16]}...)',
        f'// {spec.kind}-D-GP, N = {spec.N} joints, n = {spec.n} training samples, '
        f'{el} elements of D, passivity {spec.passivity!r}.',
        f'// Guarantee: {spec.guarantee} ({spec.method}), proven at export as the frozen node '
        f'proves a model file it loads ({proof}).',
        f'// Blend by the earned gains: {grounds}. Correction: '
        + ('none' if spec.correction is None else
           f'{spec.correction["basis"] or "offsets only"}') + '.',
        '// C++17, header-only: noexcept, no allocation, no exceptions, standard library only.']
    # a path, a label or a name from the model file is text for a comment, never code
    return '\n'.join('// ' + comment(line[3:]) for line in lines)


def export_cpp(source, out=None, namespace: str = 'dgp_model', names=None,
               correction: bool = True) -> str:
    """
    Write the header-only C++17 file of a frozen model; returns its text.

    source : a model file (what ``learning:=false model_path:=`` would serve) or a fitted
        FullDGP / DiagDGP; out : where to write it (None: only returned); namespace : the C++
        namespace of its functions; names : joint names (default: the correction's URDF joints,
        else ``joint_1..N``); correction : carry the correction and offsets (False: ``friction``
        is the damping force alone).
    Raises ExportError (a ValueError) naming why a model cannot be exported and what to do.
    """
    spec, _ = header_spec(source, names, correction)
    return write_header(spec, out, namespace)


def write_header(spec: Spec, out=None, namespace: str = 'dgp_model') -> str:
    """Render ``spec`` (``header_spec``) as the header text; write it to ``out`` if given."""
    text = render(spec, namespace, _banner(spec))
    if out is not None:
        out = os.fspath(out)
        d = os.path.dirname(os.path.abspath(out))
        fd, tmp = tempfile.mkstemp(prefix='.tmp-', suffix='.hpp', dir=d)
        try:
            with os.fdopen(fd, 'w', encoding='utf-8') as f:
                f.write(text)
            os.replace(tmp, out)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
    return text

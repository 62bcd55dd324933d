"""
The learner's model files: what a saved model carries, and a model taken in (no rclpy).

Steps of :class:`~dgp_ros.online.learner.Learner` on its parts (``parts.Parts``, passed in each
call). ``save`` writes the served model once it is caught up with what was learned (a rebase with a
fresh structure when samples or history wait), with the gains it earned (``Grounds.record``: a
frozen or loaded model answers with them). ``adopt`` serves a model from outside (a model file at
start, the last snapshot's model in a restarted learner process) and buffers its training samples;
its certificate is proven again, never trusted.
"""
from __future__ import annotations

import copy
import os
from typing import Optional

import numpy as np

from ..config import check_model_path
from ..jobs.worker import prove

__all__ = ['save', 'adopt', 'forward_weights', 'FORWARD_FRACTION']

#: the newest fraction of the buffer (by learning order) a saved model is checked on
FORWARD_FRACTION = 0.25


def forward_weights(model, Q: np.ndarray, T: np.ndarray) -> np.ndarray:
    """
    Return per output the weight a saved model's GP earns forward in time, in [0, 1] (N,).

    The model's kernel (its hyper-parameters, its prior) fitted on the buffered samples (Q, T)
    (n, N), oldest first, before the newest ``FORWARD_FRACTION``, predicts those; where its
    squared error exceeds the prior's alone, the weight is their ratio. One step ahead a GP
    along a slow drift (an aircraft's airspeed) reads the time off it and is exact; frozen, it
    answers a return to an airspeed with the forces of another time: the A320's model saved
    after 40 s answered the rest of its flight's drag at 0.074 of its variance, its prior alone
    at 0.0085, and this check gave its drag 0.15 (1.0 where the saved model did as well as its
    prior: the splits at 20 and 30 s gave 0.39 and 1.0).
    """
    N = Q.shape[1]
    k = int(Q.shape[0] * (1.0 - FORWARD_FRACTION))
    if k < 10 or Q.shape[0] - k < 5:
        return np.ones(N)
    try:
        from dgp_ros.gp import make_model
        kind = model.posterior_.structure.kind
        f = make_model(kind, prior=model.mean_, bias=False, passivity='projected',
                       hyperparams=model.hyperparams_).fit(Q[:k], T[:k], optimize=False)
        e_gp = ((f.predict(Q[k:]) - T[k:]) ** 2).mean(axis=0)
        e_prior = ((model.mean_.force(Q[k:]) - T[k:]) ** 2).mean(axis=0)
    except Exception:       # noqa: BLE001 - no check: the gains as earned
        return np.ones(N)
    return np.where(e_gp > e_prior, e_prior / np.maximum(e_gp, 1e-300), 1.0)


def save(parts, path: Optional[str] = None) -> str:
    """
    Save the served model atomically to ``path`` (default ``model_path``); returns it.

    ``parts``: the learner's parts as they are now (``Learner.parts``: its lock, settings,
    window, structure, grounds, served model, rebases, switch). The model is copied under the
    lock and written outside it, once learning has stopped (``Switch.wait_stopped``: a save
    asked for while it stops writes the proven model).
    """
    cfg = parts.settings()
    path = path or cfg.model_path
    if not path:
        raise ValueError('no path given and model_path is not set')
    check_model_path(path)
    parts.switch.wait_stopped(parts)
    served, structure, lock = parts.served, parts.structure, parts.lock
    with lock:
        if served.model is None:
            raise RuntimeError('no trained model to save yet')
        model = copy.deepcopy(served.model)
    if served.model is not None and parts.settings().learning and \
            (served.unheld(parts.window.seq) or structure.history_grew() or
             not structure.carried_by(model)):
        with lock:
            structure.reselect_soon()
        parts.rebases.run(parts)    # the saved prior and correction see the whole history
        with lock:
            model = copy.deepcopy(served.model)
    record = parts.grounds.record()
    if record is not None and not model.mean_.is_diagonal:
        with lock:
            Q, T = parts.window.arrays()
        w = forward_weights(model, Q, T)
        record['model_weight'] = [min(float(a), float(b))
                                  for a, b in zip(record['model_weight'], w)]
    if record is not None:      # restored with the model (``Learner._load``)
        model.grounds_ = record
    path = os.path.abspath(path)
    model.save(path)
    return path


def adopt(parts, model, source: str = '') -> int:
    """
    Serve ``model`` and buffer its training samples; returns the number of joints.

    ``parts``: the learner's parts as they are now (``Learner.parts``). Raises ValueError when
    it does not fit the configuration. Its certificate is proven again (never trusted from the
    file); one that does not hold serves with every answer projected, as a refit's would.
    """
    cfg = parts.settings()
    kind = model.posterior_.structure.kind
    if kind != cfg.model:
        raise ValueError(f'{source or "the"} model is a {kind!r} model, config model='
                         f'{cfg.model!r}')
    X, Y = model.X_train_, model.Y_train_
    if cfg.joints and X.shape[1] != len(cfg.joints):
        raise ValueError(f'{source or "the"} model has N={X.shape[1]}, joints has '
                         f'{len(cfg.joints)}')
    if cfg.passivity != 'none' and model.passivity != cfg.passivity:
        raise ValueError(f'{source or "the"} model passivity {model.passivity!r} != '
                         f'{cfg.passivity!r}')
    model.posterior_ = model.posterior_.ensure_factors()    # a snapshot is predict-only
    model.grounds_ = None       # the learner's gains blend its answers (restore_grounds)
    proof = prove(model, cfg.passivity)           # re-proves: never trusts the file
    with parts.lock:
        parts.health.proof_done(proof)
        seq = parts.window.adopt(X, Y)
        parts.rebases.restart()
        parts.served.based(model, seq, parts.window.target_gen)
        parts.refits.adopted(model, X)
    return X.shape[1]

"""
The refit worker: turns a job into a candidate model, off the message path.

A job is a snapshot (samples, hyper-parameters to start from, configuration) or, to re-prove a
stale certificate, a copy of the current model. ``run_job`` knows nothing about the estimator
that made the job: it builds the model with an injected factory, fits or re-proves it, and says
whether the candidate may replace the current model (finite and bounded on and around its data)
and, in a certifying passivity mode, whether it is proven. A candidate that is not proven still
serves: every answer of it is projected onto ``q^T tau >= 0`` (the mode's fallback) until a
re-proof succeeds; passive data never stop the learning. The estimator then appends the samples
that arrived meanwhile and swaps.
"""
from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Callable, Optional, Tuple

import numpy as np

from dgp_ros.gp.passivity import policy_class

__all__ = ['RefitJob', 'RefitResult', 'run_job', 'prove', 'sane', 'held_out']


@dataclass
class RefitJob:
    """
    What to do: ``kind`` 'fit' (Q, T, optimize, hyper) or 'recertify' (model).

    seq : samples the estimator had added when the snapshot was taken (for the catch-up);
    generation : the estimator's reset count (a reset discards the result); stamp : message
    stamp at the start (s); config : the ``EstimatorConfig`` the candidate is built for;
    warm : refine ``hyper`` without restarts; target_gen : the learner's target generation
    of ``T`` (a re-selection of ``prior='auto'`` changes the targets). For 'recertify', ``seq``
    is the last sample the served model held when it was copied.
    """

    kind: str
    config: object
    seq: int
    generation: int
    stamp: Optional[float]
    Q: Optional[np.ndarray] = None
    T: Optional[np.ndarray] = None
    optimize: bool = False
    hyper: Optional[dict] = None
    warm: bool = False
    model: object = None
    # 'fit' with optimize: (Qd, Tau) spread evenly over the run, what the hyper-parameters and
    # the elements are learned on (``Window.even_arrays``)
    hyper_rows: Optional[tuple] = None
    # 'recertify': the served model ``model`` is a copy of; 'fit': a snapshot of the served
    # model when the job started (the opponent of the held-out check)
    source: object = None
    kw: Optional[dict] = None   # 'fit': the model's constructor arguments (else the config's)
    correction: object = None   # 'fit': what the targets T exclude (saved with the model)
    target_gen: int = 0
    full: bool = False          # 'recertify': the full proof (learning stopped; ``switch``)


@dataclass
class RefitResult:
    """
    Outcome of a refit job.

    The candidate (None when building it failed), whether it may be swapped in, why not,
    the wall time spent (s), and why its certificate is not proven ('' when it is, or when the
    mode proves nothing); ``cpu_seconds``: the job thread's own computing time (its wall time
    over it says how short of CPU the learner was).
    """

    job: RefitJob
    model: object
    ok: bool
    reason: str
    seconds: float
    proof: str = ''
    cpu_seconds: float = float('nan')


def prove(model, passivity: str, full: bool = False) -> str:
    """
    Prove ``model``'s certificate under ``passivity`` where it is stale; '' when it holds.

    Otherwise the reason (the model then answers with every estimate projected). Non-certifying
    modes have nothing to prove. This and ``gp``'s own fit are the only places that prove.
    ``full``: the proof a fit makes, from scratch, unless the certificate holds
    (``recertify(full=True)``).
    """
    if not policy_class(passivity).certifies:
        return ''
    try:
        cert = model.certificate()
        if full:
            cert = model.recertify(full=True)
        elif cert.stale:
            cert = model.recertify()
    except Exception as exc:
        return f'certificate failed: {type(exc).__name__}: {exc}'
    if cert.certified:
        return ''
    return f'certificate does not hold (margin {cert.margin:.3g}, {cert.method})'


#: a candidate's estimates may exceed the largest force of its data by at most this factor
SANE_FACTOR = 10.0


def sane(model, Q: np.ndarray, T: np.ndarray, rng=None, probes: int = 2000) -> Tuple[bool, str]:
    """
    Check that a candidate's estimates are finite and bounded.

    (ok, reason): are a candidate's estimates finite and bounded by ``SANE_FACTOR`` x the
    largest force of its data, on its data and on velocities up to 1.5 x beyond its data box?
    A fit on a short, poorly excited stretch can extrapolate wildly; such a model must not
    replace one that works.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    lo, hi = Q.min(axis=0), Q.max(axis=0)
    c, w = 0.5 * (lo + hi), 0.75 * (hi - lo)
    probe = np.vstack([Q, rng.uniform(c - w, c + w, (probes, Q.shape[1]))])
    P = model.predict(probe)
    limit = SANE_FACTOR * np.maximum(np.abs(T).max(axis=0), 1e-12)
    if not np.all(np.isfinite(P)):
        return False, 'sanity check: non-finite estimates'
    worst = np.abs(P).max(axis=0) / limit
    if np.any(worst > 1.0):
        j = int(np.argmax(worst))
        return False, (f'sanity check: estimates up to {worst[j] * SANE_FACTOR:.0f} x the '
                       f'largest force of the data on output {j}')
    return True, ''


def held_out(model, base, Q: np.ndarray, T: np.ndarray, factor: float) -> Tuple[bool, str]:
    """
    Check a candidate one step ahead on samples neither it nor ``base`` has learned.

    (ok, reason): is the candidate's mean squared error on (Q, T) (k, N) each within ``factor``
    x that of ``base`` (the served model when the candidate's fit started) and of its own
    parametric part, plus 1 % of the samples' variance (a candidate that good is good enough,
    however good the incumbent happens to be on them)? A check that cannot be computed passes
    (a broken candidate is caught by ``sane``).
    """
    try:
        e_new = model.predict(Q) - T
        e_old = base.predict(Q) - T
        e_par = model.mean_.force(Q) - T if model.posterior_.structure.has_damping else e_old
    except Exception as exc:          # noqa: BLE001 - a broken candidate is caught later
        return True, f'held-out check skipped: {exc}'
    e_new = float(np.mean(np.square(e_new)))
    e_old = float(np.mean(np.square(e_old)))
    e_par = float(np.mean(np.square(e_par)))
    floor = float(np.mean(np.var(T, axis=0))) * 1e-2
    for e_ref, whose in ((e_old, "the current model's"), (e_par, "its parametric part's")):
        if e_new > factor * e_ref + floor:
            return False, (f'sanity check: error on the {len(T)} samples that arrived during '
                           f'the fit {e_new / max(e_ref, 1e-300):.1f} x {whose}')
    return True, ''


def run_job(job: RefitJob, factory: Callable) -> RefitResult:
    """Build (fit) or re-prove the candidate of ``job``; never raises."""
    t0, c0 = time.perf_counter(), time.thread_time()
    cfg = job.config
    try:
        if job.kind == 'recertify':
            model = job.model
        else:
            kw = dict(job.kw) if job.kw is not None else cfg.model_kwargs()
            if job.hyper is not None:
                kw['hyperparams'] = job.hyper
                kw['warm_start'] = job.warm
            model = factory(cfg.model, **kw)
            # a new model is served before its domain proof (every answer projected meanwhile,
            # as after each append): the proof runs in the re-proof job that follows. Proven
            # first, the A320's refits spent most of their time in the branch-and-bound
            # (quiet: 7 s of wall per refit beside the learner's own loop; two busy processes:
            # 24 s) and a learner short of CPU served its first, 20-sample model for 20 s
            extra = {} if job.hyper_rows is None else {'hyper_rows': job.hyper_rows}
            model.fit(job.Q, job.T, optimize=job.optimize, prove=False, **extra)
            model.correction_ = job.correction
            ok, why = sane(model, job.Q, job.T)
            if not ok:
                return RefitResult(job, model, False, why, time.perf_counter() - t0)
        proof = prove(model, cfg.passivity, job.full) if job.kind == 'recertify' or \
            job.full else ''
    except Exception as exc:
        return RefitResult(job, None, False, f'{type(exc).__name__}: {exc}',
                           time.perf_counter() - t0)
    return RefitResult(job, model, True, '', time.perf_counter() - t0, proof,
                       time.thread_time() - c0)

"""
The online estimator's message path: validate, learn, answer (no rclpy).

``process`` validates one measurement, maybe learns from it (``selection``) with the model's
O(n^2) ``update``, decides whether a refit job is due, and answers with the estimate at the
measured velocity. Refit jobs run in the worker (``worker.run_job``: a background thread in
'async' mode, in line in 'sync' mode); their result is integrated here: the samples that arrived
meanwhile are replayed into the candidate and it is swapped in under the lock, which is held
only for the swap. Every answer passes one output gate (``_gate``): non-finite or non-passive
estimates (beyond rounding) are replaced by the passive prior and counted.

Refits: the first as soon as ``min_samples`` are buffered; then every ``refit_period_s`` of
stamp time, on ``request_refit()``, and whenever the buffer has doubled since the
hyper-parameters were learned (20 -> 40 -> 80 ... while it fills; a first optimum learned on a
few samples of a near-stationary start can be far off). Refit number k re-learns the
hyper-parameters when ``k % optimize_every_n_refits == 0``, on the first fit and after a
doubling; otherwise it refits at the current ones. A stale certificate (``certified`` mode, after
updates) is re-proven by a 'recertify' job, at most every ``refit_period_s / 4`` of stamp time.
"""
from __future__ import annotations

from collections import deque
import copy
import dataclasses
from dataclasses import dataclass
import math
import os
import threading
import time
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from dgp_ros.dynamics import AccelFilter, FrictionResidual, make_inverse_dynamics
from dgp_ros.gp import load_model, make_model, passive_tolerance
from dgp_ros.gp.means import make_mean
from dgp_ros.gp.passivity import policy_class

from .config import check_model_path, EstimatorConfig
from .health import Health
from .selection import Buffer, Selector
from .worker import provable, RefitJob, RefitResult, run_job

__all__ = ['OnlineEstimator', 'Estimate']

# Structural fields: changing one at run time drops the model and refits.
_STRUCTURAL = ('model', 'passivity', 'prior', 'bias', 'buffer_size', 'joints',
               'operating_domain', 'inverse_dynamics', 'robot_description', 'urdf_file',
               'accel_half_window_s')
_FRONT_END = ('inverse_dynamics', 'robot_description', 'urdf_file', 'joints')
#: learned samples over which the negative-power warning is decided (and the least it needs)
_POWER_WINDOW, _POWER_MIN = 1000, 100


@dataclass
class Estimate:
    """
    The estimate answering one measurement (model units; N joints).

    qd, tau : (N,) the measured velocity and effort; tau_hat : (N,) the damping force estimate at
    qd; stddev : (N,) its posterior standard deviation; D : (N, N) damping matrix (None for the
    ARD baseline); power : ``qd^T tau_hat``; measured_power : ``qd^T tau``; source : 'model' |
    'prior' | 'fallback'; added : the sample was learned (with ``inverse_dynamics``: taken for
    learning; its residual is learned once the acceleration filter's window is complete);
    processing_time_s : wall time spent; residuals : the friction residual samples
    (``dynamics.ResidualSample``) completed by this message (delayed by the filter's half
    window), which is what the model learned.
    """

    stamp_s: float
    names: List[str]
    qd: np.ndarray
    tau: np.ndarray
    tau_hat: np.ndarray
    stddev: np.ndarray
    D: Optional[np.ndarray]
    power: float
    measured_power: float
    source: str
    added: bool
    processing_time_s: float
    residuals: list = dataclasses.field(default_factory=list)


class OnlineEstimator:
    """
    Online D-GP estimator (module docstring).

    Parameters
    ----------
    config : EstimatorConfig
    model_factory : callable ``(kind, **kwargs) -> model``
        Builds candidate models (default ``dgp_ros.gp.make_model``); injectable for tests.
    model_loader : callable ``(path) -> model``
        Reads ``model_path`` (default ``dgp_ros.gp.load_model``).

    """

    #: longest catch-up replayed sample by sample; a longer backlog gets a fresh snapshot refit
    MIN_SNAPSHOT_BACKLOG = 50
    #: a stamp this many refit periods ahead of the refit clock is a jump, not elapsed time
    CLOCK_JUMP_PERIODS = 10
    #: equal stamps in a row after which learning switches to arrival time (and advancing ones
    #: after which it switches back)
    STALLED_STAMPS = 20
    #: stamp time without a learned sample (while moving) after which learning is said to stall
    STALL_WARN_S = 30.0

    def __init__(self, config: Optional[EstimatorConfig] = None,
                 model_factory: Optional[Callable] = None,
                 model_loader: Optional[Callable] = None):
        self.config = dataclasses.replace(config or EstimatorConfig()).validate()
        self._factory = model_factory or make_model
        self._loader = model_loader or load_model
        self._lock = threading.RLock()
        self._thread: Optional[threading.Thread] = None
        self._generation = 0
        self._want_stddev = True
        self._want_damping = True
        self.load_error = ''
        self._inverse = make_inverse_dynamics(
            self.config.inverse_dynamics, robot_description=self.config.robot_description,
            urdf_file=self.config.urdf_file, joints=self.config.joints)
        self._init_state()
        path = self.config.model_path
        if path and os.path.exists(path):
            self._load(path)

    # ------------------------------------------------------------------ state
    def _init_state(self, keep_health: bool = False) -> None:
        self._generation += 1
        names = list(self.config.joints) or list(getattr(self._inverse, 'joint_names', []))
        self._names: Optional[List[str]] = names or None
        self._N: Optional[int] = len(names) or None
        self._front = FrictionResidual(
            self._inverse, AccelFilter(self.config.accel_half_window_s)
            if self._inverse is not None else None)
        self._learned_power: deque = deque(maxlen=_POWER_WINDOW)
        self._buf: Optional[Buffer] = None
        self._selector = Selector()
        self._seq = 0                     # samples ever added (orders the catch-up)
        # (seq, qd, tau) added while a refit runs; only the newest buffer_size can survive the
        # model's window, so older ones are dropped here instead of being replayed
        self._pending: deque = deque(maxlen=self.config.buffer_size)
        self._model = None
        self._hyper: Optional[dict] = None   # warm start of the next fit (hyperparams_)
        self._opt_n = 0                   # samples the current hyper-parameters were learned on
        self._prior = None                # fitted prior of the buffer (lazy)
        self._last_stamp: Optional[float] = None       # learning time of the last message
        self._raw_last_stamp: Optional[float] = None
        self._same_stamps = 0
        self._advancing = 0
        self._arrival_t0: Optional[float] = None        # set: learning uses arrival time
        self._last_added_t: Optional[float] = None
        self._recent_q: deque = deque(maxlen=100)       # recent candidates (stall check)
        self._clock: Optional[float] = None   # stamp of the last refit decision
        self._last_recert: Optional[float] = None
        self._refit_requested = False
        self._retry_at: Optional[int] = None  # _seq at which a rejected candidate is retried
        self._last_est: Optional[Estimate] = None
        if not keep_health:
            self.health = Health()

    def set_outputs(self, stddev: bool = True, damping: bool = True) -> None:
        """
        Which optional parts of an estimate to compute (the node: what has subscribers).

        Without ``stddev`` an Estimate's stddev is NaN; without ``damping`` its D is None. The
        force, its power and its passivity are always computed.
        """
        self._want_stddev, self._want_damping = bool(stddev), bool(damping)

    @property
    def trained(self) -> bool:
        return self._model is not None

    @property
    def model(self):
        """
        Get the current model, None before the first fit.

        Do not mutate it.
        """
        return self._model

    @property
    def names(self) -> Optional[List[str]]:
        return None if self._names is None else list(self._names)

    def samples(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return copies of the buffered samples, (Qd, Tau), (n, N) each, oldest first."""
        with self._lock:
            if self._buf is None:
                return np.zeros((0, self._N or 0)), np.zeros((0, self._N or 0))
            return self._buf.arrays()

    def refit_running(self) -> bool:
        t = self._thread
        return t is not None and t.is_alive()

    # ------------------------------------------------------------------ messages
    def process(self, stamp_s: float, names: Sequence[str], velocity, effort,
                position=None) -> Optional[Estimate]:
        """
        Validate one measurement, learn from it, return the estimate at its velocity.

        Never raises on bad input: returns None and counts the rejection reason.
        """
        t0 = time.perf_counter()
        h = self.health
        with self._lock:
            h.messages_received += 1
            try:
                stamp = float(stamp_s)
            except (TypeError, ValueError, OverflowError):
                stamp = float('nan')
            sel = self._validate(names, velocity, effort, position)
            if isinstance(sel, str):            # content problems are reported first
                h.reject(sel)
                return None
            if not math.isfinite(stamp) or stamp < 0.0:     # before the epoch / sim start
                h.reject('bad_stamp')
                return None
            names, qd, tau, q = sel
            h.gaps.note(stamp)
            if self._N is None:
                try:
                    self.config.check_dimension(qd.size)
                except ValueError:              # per-joint parameters for another joint count
                    h.reject('dimension_mismatch')
                    return None
                self._N = qd.size
            h.accept()
            if self._names is None and names:
                self._names = list(names)
            if self._buf is None:
                self._buf = Buffer(self.config.buffer_size, self._N)
            t = self._learning_time(stamp)
            if self._last_stamp is not None and t < self._last_stamp:
                # documented policy: keep model and buffer, restart the refit clock, count it
                h.time_jumps_back += 1
                if self._clock is not None:
                    self._clock = t
            self._last_stamp = t
            added, residuals = self._learn(t, qd, tau, q)
            job = self._next_job(t)
            est = self._estimate(stamp, list(names) if names else [], qd, tau, added)
            est.residuals = residuals
            est.processing_time_s = time.perf_counter() - t0
            h.latencies.append(est.processing_time_s)
            self._last_est = est
        if job is not None:
            self._start(job)
        return est

    def _learning_time(self, stamp: float) -> float:
        """
        Return the time learning decisions use (s).

        The message stamp, unless stamps stopped advancing (``STALLED_STAMPS`` equal stamps in a
        row: a driver that leaves header.stamp at 0 or constant); then the arrival time, with a
        WARN. Answers keep the message's own stamp either way.
        """
        advancing = self._raw_last_stamp is not None and stamp > self._raw_last_stamp
        self._raw_last_stamp = stamp
        if self._arrival_t0 is None:
            self._same_stamps = 0 if advancing else self._same_stamps + 1
            if self._same_stamps >= self.STALLED_STAMPS:
                self._arrival_t0 = time.monotonic() - (self._last_stamp or 0.0)
                self._advancing = 0
        else:
            self._advancing = self._advancing + 1 if advancing else 0
            if self._advancing >= self.STALLED_STAMPS:      # the stamps recovered
                self._arrival_t0 = None
                self._same_stamps = 0
        if self._arrival_t0 is None:
            return stamp
        return time.monotonic() - self._arrival_t0

    def _validate(self, names, velocity, effort, position):
        """
        Validate one message.

        One message's content: (names, qd, tau, q) in the configured joint order (``q`` None
        without inverse dynamics), or the rejection reason (a string).
        """
        if velocity is None or effort is None:
            return 'empty'
        try:
            v = np.asarray(velocity, dtype=float).ravel()
            e = np.asarray(effort, dtype=float).ravel()
            p = None
            if self._inverse is not None:
                p = np.asarray([] if position is None else position, dtype=float).ravel()
        except (TypeError, ValueError, OverflowError):
            return 'non_finite'
        try:
            names = list(names) if names is not None else []
            if len(set(names)) != len(names):
                return 'duplicate_name'
        except TypeError:                      # not iterable, or unhashable entries
            return 'bad_names'
        if not all(isinstance(n, str) for n in names):
            return 'bad_names'
        if v.size == 0 or e.size == 0:
            return 'empty'
        if p is not None and p.size == 0:
            return 'missing_position'
        if v.size != e.size or (names and len(names) != v.size) or \
                (p is not None and p.size != v.size):
            return 'length_mismatch'
        if self._names is not None and names:
            pos = {n: i for i, n in enumerate(names)}
            try:
                idx = [pos[n] for n in self._names]
            except KeyError:
                return 'missing_joint'
            v, e, names = v[idx], e[idx], list(self._names)
            p = None if p is None else p[idx]
        elif self._names is not None and not names and self.config.joints:
            return 'missing_joint'
        if self._N is None and v.size > self.config.max_joints:
            return 'too_many_joints'
        if self._N is not None and v.size != self._N:
            return 'dimension_mismatch'
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(e)) and
                (p is None or np.all(np.isfinite(p)))):
            return 'non_finite'
        if np.any(np.abs(v) > self.config.max_abs_velocity) or \
                np.any(np.abs(e) > self.config.max_abs_effort):
            return 'out_of_range'
        return names, v, e, p

    def _learn(self, stamp: float, qd: np.ndarray, tau: np.ndarray, q) -> Tuple[bool, list]:
        """
        Offer the sample for learning (rate limit).

        It goes through the friction residual front end when there is inverse dynamics. Returns
        (taken, completed residual samples).
        """
        h, sel = self.health, self._selector
        want = not sel.rate_limited(self.config, stamp)
        if want:
            sel.added(stamp)
        else:
            h.samples_rate_limited += 1
        if self._inverse is None:
            return (self._add(stamp, qd, tau) if want else False), []
        try:
            done = self._front.push(stamp, q, qd, tau, want=want)
        except Exception as exc:        # a plugin that fails: the message is still answered
            h.last_refit_error = f'inverse dynamics failed: {type(exc).__name__}: {exc}'
            h.inverse_dynamics_errors += 1
            return False, []
        for r in done:
            if np.all(np.isfinite(r.residual)):
                self._add(r.stamp_s, r.qd, r.residual)
        return want, done

    def _add(self, stamp: float, qd: np.ndarray, target: np.ndarray) -> bool:
        """Add one learning sample to the buffer and the model unless it is a near-duplicate."""
        h = self.health
        self._learned_power.append(float(qd @ target))
        self._recent_q.append(qd)
        if self._selector.outlier(self.config, self._buf, qd, target):
            h.samples_outliers += 1
            return False
        if not self._selector.novel(self.config, self._buf, qd):
            h.samples_skipped += 1
            return False
        self._last_added_t = stamp
        self._buf.append(qd, target)
        self._selector.additions += 1
        self._seq += 1
        h.samples_added += 1
        if self.refit_running():
            # the incumbent's answer before it learns the sample: the fair opponent of a
            # candidate that has not seen it either (see _held_out)
            before = None
            if self._model is not None:
                try:
                    before = self._model.predict(qd[None, :])[0]
                except Exception:       # noqa: BLE001 - then the sample only serves the replay
                    before = None
            self._pending.append((self._seq, qd.copy(), target.copy(), before))
        if self._model is not None:
            try:
                self._model.update(qd, target)
            except Exception as exc:  # a model that cannot take the sample: refit from buffer
                h.last_refit_error = f'update failed: {exc}'
                self._refit_requested = True
        return True

    # ------------------------------------------------------------------ estimates
    def _prior_estimate(self, qd: np.ndarray):
        """(tau, stddev, D) of the passive prior fitted to the buffer: diag(m_d(qd)) qd."""
        # refitted when the buffer changed by a tenth (a 7-joint friction prior costs ~15 ms:
        # refitted on every learned sample it held the message path while the first fit ran)
        if self._prior is None or self._seq >= self._prior[2] + max(1, self._prior[2] // 10):
            Q, T = self._buf.arrays() if self._buf is not None and self._buf.size else \
                (np.zeros((0, self._N)), np.zeros((0, self._N)))
            cfg = self.config
            prior = 'viscous' if cfg.model == 'ard' else cfg.prior
            try:
                mean = make_mean(prior, 'full', bool(cfg.bias)).fit(Q, T)
                resid = T - mean(Q) if Q.shape[0] else T
                std = np.sqrt(np.mean(resid ** 2, axis=0)) if Q.shape[0] else np.zeros(self._N)
            except Exception:           # degenerate buffer: no prior damping at all
                mean, std = make_mean('viscous', 'full').fit(Q[:0], T[:0]), np.zeros(self._N)
            self._prior = (mean, std, self._seq)
        mean, std, _ = self._prior
        q = qd[None, :]
        d = np.asarray(mean.diag(q), float)[0]
        tau = d * qd
        if not np.all(np.isfinite(tau)):
            d, tau = np.zeros_like(qd), np.zeros_like(qd)
        return tau, std.copy(), np.diag(d)

    def _estimate(self, stamp, names, qd, tau, added) -> Estimate:
        source = 'prior'
        if self._model is not None:
            try:
                tau_hat, var, D = self._model.predict_with_damping(
                    qd[None, :], self._want_stddev, self._want_damping)
                tau_hat = np.asarray(tau_hat, float)[0]
                std = (np.sqrt(np.maximum(np.asarray(var, float)[0], 0.0)) if var is not None
                       else np.full_like(tau_hat, np.nan))
                D = None if D is None else np.asarray(D, float)[0]
                source = 'model'
            except Exception as exc:
                self.health.last_refit_error = f'predict failed: {type(exc).__name__}: {exc}'
                self.health.nonfinite_outputs += 1
                source = 'fallback'
        if source != 'model':
            tau_hat, std, D = self._prior_estimate(qd)
        tau_hat, std, D, source, power = self._gate(qd, tau_hat, std, D, source)
        return Estimate(stamp_s=stamp, names=names, qd=qd, tau=tau, tau_hat=tau_hat, stddev=std,
                        D=D, power=power, measured_power=float(qd @ tau), source=source,
                        added=added, processing_time_s=0.0)

    def _gate(self, qd, tau_hat, std, D, source):
        """
        Check an answer (the one place this is done).

        Finite, and passive beyond rounding (unless passivity is 'none'); otherwise the passive
        prior, counted. Returns (tau_hat, std, D, source, power) with ``power >= 0`` unless
        passivity is 'none'.
        """
        h = self.health
        finite = (np.all(np.isfinite(tau_hat)) and
                  (not self._want_stddev or np.all(np.isfinite(std))) and
                  (D is None or np.all(np.isfinite(D))))
        if not finite:
            h.nonfinite_outputs += 1
        power = float(qd @ tau_hat) if finite else float('nan')
        guarded = self.config.passivity != 'none'
        negative = finite and guarded and \
            power < -float(passive_tolerance(qd[None], tau_hat[None])[0])
        if negative:
            h.passivity_fallbacks += 1
        if not finite or negative:
            tau_hat, std, D = self._prior_estimate(qd)
            source = 'fallback'
            power = float(qd @ tau_hat)
            if not np.all(np.isfinite(std)):
                std = np.zeros_like(std)
        if guarded and power < 0.0:       # rounding only (checked above): report it as 0
            power = 0.0
        return tau_hat, std, D, source, power

    def predict(self, Qs) -> np.ndarray:
        """Estimates (k, N) at velocities Qs with the rules of ``process`` (no learning)."""
        Qs = np.atleast_2d(np.asarray(Qs, dtype=float))
        with self._lock:
            if self._N is None:
                self._N = Qs.shape[1]
            return np.array([self._estimate(0.0, [], q, np.zeros_like(q), False).tau_hat
                             for q in Qs])

    # ------------------------------------------------------------------ refit jobs
    def _hypers_outgrown(self) -> bool:
        """Tell whether the buffer has at least doubled since the hyper-parameters were learned."""
        return 0 < self._opt_n and self._buf.size >= 2 * self._opt_n

    def _next_job(self, stamp: float) -> Optional[RefitJob]:
        """Make the one decision (under the lock) of what the worker does next, if anything."""
        cfg = self.config
        if self._buf is None or self._buf.size < cfg.min_samples or self.refit_running():
            return None
        if self._model is not None and self._clock is None:
            self._clock = stamp                          # loaded model: start the refit clock
        if self._clock is not None and cfg.refit_period_s > 0 and \
                stamp - self._clock > self.CLOCK_JUMP_PERIODS * cfg.refit_period_s:
            self._clock = stamp            # a jump forward (a bag loop, a bad stamp): no refit
            self.health.time_jumps_forward += 1
        due = (self._refit_requested
               or (self._model is None and self._clock is None)                # first fit
               or (cfg.refit_period_s > 0 and self._clock is not None and
                   stamp - self._clock >= cfg.refit_period_s)                 # periodic
               or (self._model is not None and self._hypers_outgrown() and
                   self.health.consecutive_refit_failures == 0)               # buffer doubled
               or (self._retry_at is not None and self._seq >= self._retry_at))  # rejected
        if due:
            self._refit_requested = False
            self._retry_at = None
            self._clock = stamp
            return self._fit_job()
        if self._model is not None and self._model.certificate().stale:
            # a stale model stays passive pointwise: re-prove at most every refit_period_s / 4
            gap = cfg.refit_period_s / 4.0 if cfg.refit_period_s > 0 else 0.25
            last = self._last_recert
            if last is None or stamp < last or stamp - last >= gap:
                self._last_recert = stamp
                return RefitJob('recertify', dataclasses.replace(cfg), self._seq,
                                self._generation, self._last_stamp,
                                model=copy.deepcopy(self._model))
        return None

    def _fit_job(self) -> RefitJob:
        h, cfg = self.health, self.config
        h.refits_started += 1
        k = h.refits_started
        optimize = (self._model is None or self._hyper is None or
                    (cfg.optimize_every_n_refits > 0 and k % cfg.optimize_every_n_refits == 0)
                    or self._hypers_outgrown())
        Q, T = self._buf.arrays()
        # re-learning on data like the last optimum's refines it (no restarts); after the buffer
        # doubled the data changed enough to search again from scratch
        warm = self._hyper is not None and not self._hypers_outgrown()
        return RefitJob('fit', dataclasses.replace(cfg), self._seq, self._generation,
                        self._last_stamp, Q=Q, T=T, optimize=optimize, hyper=self._hyper,
                        warm=warm)

    def request_refit(self) -> Tuple[bool, str]:
        """Refit now (async: start it in the background). Returns (ok, message)."""
        with self._lock:
            if self._buf is None or self._buf.size < self.config.min_samples:
                n = 0 if self._buf is None else self._buf.size
                return False, f'not enough samples ({n} < min_samples {self.config.min_samples})'
            if self.refit_running():
                return False, 'a refit is already running'
            if self._last_stamp is not None:
                self._clock = self._last_stamp
            job = self._fit_job()
        return self._start(job)

    def _start(self, job: RefitJob) -> Tuple[bool, str]:
        what = (f'{job.kind} started' if job.kind == 'recertify' else
                f'refit started on {job.Q.shape[0]} samples '
                f'({"optimizing" if job.optimize else "fixed"} hyper-parameters)')
        with self._lock:
            if self.refit_running():
                return False, 'a refit is already running'
            self._pending.clear()
            if job.config.refit_mode == 'async':
                self._thread = threading.Thread(target=self._run, args=(job,),
                                                name='dgp_refit', daemon=True)
                self._thread.start()
                return True, what
            self._thread = None
        return self._run(job)

    def _run(self, job: RefitJob) -> Tuple[bool, str]:
        return self._integrate(run_job(job, self._factory))

    def _integrate(self, res: RefitResult) -> Tuple[bool, str]:
        """
        Finish a refit job.

        Replay the samples that arrived during the job into the candidate, swap it in (if it
        may serve), and record the outcome. Long backlogs are absorbed by a fixed-hyper refit on
        a fresh snapshot; the lock is held only to read the backlog and for the swap.
        """
        job, model, ok, why = res.job, res.model, res.ok, res.reason
        cfg, h = job.config, self.health
        t0 = time.perf_counter() - res.seconds
        seq, rounds = job.seq, 0
        try:
            if ok and job.kind == 'fit':
                ok, why, seq = self._held_out(model, seq)
                if not ok:
                    h.refits_rejected += 1
            while ok:
                rounds += 1
                with self._lock:
                    if job.generation != self._generation:
                        return False, 'discarded: the estimator was reset'
                    newer = [(s, q, t) for (s, q, t, _) in self._pending if s > seq]
                    backlog = max(self.MIN_SNAPSHOT_BACKLOG, cfg.buffer_size // 4)
                    snapshot = None
                    if job.kind == 'fit' and rounds <= 5 and len(newer) > backlog:
                        snapshot = self._buf.arrays() + (self._seq,)
                    elif not newer or rounds > 5:
                        for s, q, t in newer:        # the last few, in the lock
                            model.update(q, t)
                        self._swap(job, model)
                        break
                if snapshot is not None:
                    model.fit(snapshot[0], snapshot[1], optimize=False)
                    seq = snapshot[2]
                else:
                    for s, q, t in newer:            # replay outside the lock
                        model.update(q, t)
                        seq = s
                ok, why = provable(model, cfg.passivity)
        except Exception as exc:
            ok, why = False, f'{type(exc).__name__}: {exc}'
        dt = time.perf_counter() - t0
        with self._lock:
            if job.generation != self._generation:
                return False, 'discarded: the estimator was reset'
            self._pending.clear()
            if job.kind == 'recertify':
                h.recertifications += int(ok)
                if not ok:
                    h.last_refit_error = f'recertification failed: {why}'
                return ok, (f'recertified in {dt:.3f} s' if ok else h.last_refit_error)
            if not ok and why.startswith('sanity check') and 'samples that arrived' not in why:
                h.refits_rejected += 1
            if ok:
                self._retry_at = None
            elif why.startswith('sanity check') and \
                    h.consecutive_refit_failures < self.MAX_RETRIES:
                # a rejected candidate is retried once fresh samples arrived (it learns from the
                # ones it failed on), not only at the next refit period; a short bag, or
                # refit_period_s = 0, would otherwise keep the first model for good
                self._retry_at = self._seq + max(10, cfg.buffer_size // 4)
            h.refit_done(ok, dt, job.stamp, job.optimize,
                         '' if ok else (why if model is None else f'not swapped in: {why}'),
                         time.time())
            error = h.last_refit_error
        if ok and cfg.model_path:
            try:
                self.save(cfg.model_path)
            except Exception as exc:
                with self._lock:
                    h.last_refit_error = f'refit ok but saving failed: {exc}'
        return (True, f'refit ok in {dt:.3f} s') if ok else (False, error)

    #: a candidate whose error on the samples that arrived during its fit exceeds the current
    #: model's by this factor (plus 1 % of their variance) is not swapped in
    HELD_OUT_FACTOR = 3.0
    #: rejected candidates retried on fresh data before waiting for the next refit period
    MAX_RETRIES = 3

    def _held_out(self, model, seq: int) -> Tuple[bool, str, int]:
        """
        Compare the candidate with the current model on the samples it has not seen.

        These are the samples that arrived while it was fitted (none in sync mode). The
        incumbent answered each of them before learning it; the candidate is given the same
        chance: it answers each sample, then learns it (the replay the swap needs anyway).
        Both errors are thus one step ahead. Returns (ok, reason, seq of the last sample the
        candidate learned).
        """
        with self._lock:
            newer = [(s, q, t, b) for (s, q, t, b) in self._pending if s > seq]
        if sum(b is not None for *_, b in newer) < 10:
            return True, '', seq
        e_new, e_old, T = [], [], []
        try:
            for s, q, t, b in newer:
                if b is not None:
                    e_new.append(model.predict(q[None, :])[0] - t)
                    e_old.append(b - t)
                    T.append(t)
                model.update(q, t)
                seq = s
        except Exception as exc:          # noqa: BLE001 - a broken candidate is caught later
            return True, f'held-out check skipped: {exc}', seq
        T = np.array(T)
        e_new = float(np.mean(np.square(e_new)))
        e_old = float(np.mean(np.square(e_old)))
        # a candidate within 1 % of the samples' variance is good enough, however good the
        # incumbent happens to be on them
        floor = float(np.mean(np.var(T, axis=0))) * 1e-2
        if e_new > self.HELD_OUT_FACTOR * e_old + floor:
            return False, (f'sanity check: error on the {len(T)} samples that arrived '
                           f'during the fit {e_new / max(e_old, 1e-300):.1f} x the current '
                           f"model's"), seq
        return True, '', seq

    def _swap(self, job: RefitJob, model) -> None:
        """Install the candidate (under the lock)."""
        self._model = model
        if job.kind == 'fit':
            self._hyper = model.hyperparams_
            if job.optimize:
                self._opt_n = job.Q.shape[0]

    def wait_for_refit(self, timeout: Optional[float] = None) -> bool:
        """Block until no refit is running; True if none is running at return."""
        t = self._thread
        if t is not None:
            t.join(timeout)
        return not self.refit_running()

    def close(self, timeout: float = 30.0) -> None:
        """Wait (bounded) for a running refit to finish; call before exit."""
        self.wait_for_refit(timeout)

    # ------------------------------------------------------------------ housekeeping
    def reset(self) -> None:
        """Forget the model, the buffer and all counters (a running refit is discarded)."""
        with self._lock:
            self._init_state()

    def check_reconfigure(self, config: EstimatorConfig) -> None:
        """
        Raise ValueError (with the reason) if ``reconfigure(config)`` would fail.

        Changes nothing.
        """
        config = dataclasses.replace(config).validate()
        if self._N is not None:
            config.check_dimension(self._N)
        if any(getattr(self.config, f) != getattr(config, f) for f in _FRONT_END):
            make_inverse_dynamics(config.inverse_dynamics,
                                  robot_description=config.robot_description,
                                  urdf_file=config.urdf_file, joints=config.joints)

    def reconfigure(self, config: EstimatorConfig) -> str:
        """Apply a new validated config; structural changes drop the model and refit."""
        config = dataclasses.replace(config).validate()
        if self._N is not None:
            config.check_dimension(self._N)
        old = self.config
        inverse = self._inverse
        if any(getattr(old, f) != getattr(config, f) for f in _FRONT_END):
            inverse = make_inverse_dynamics(        # ValueError before anything changes
                config.inverse_dynamics, robot_description=config.robot_description,
                urdf_file=config.urdf_file, joints=config.joints)
        with self._lock:
            self.config = config
            self._inverse = inverse
            changed = [f for f in _STRUCTURAL if getattr(old, f) != getattr(config, f)]
            if not changed:
                return 'applied'
            if any(f in changed for f in _FRONT_END):
                # other joints, or another rigid-body model: what was learned no longer applies
                self._init_state(keep_health=True)
                return f'{", ".join(changed)} changed: estimator reset'
            data = self._buf.arrays() if self._buf is not None and self._buf.size else None
            names, N = self._names, self._N
            self._init_state(keep_health=True)
            self._names, self._N = names, N
            if data is not None:
                self._buf = Buffer.of(config.buffer_size, *data)
                self._refit_requested = True
            return f'{", ".join(changed)} changed: model dropped, refit on the next sample'

    def save(self, path: Optional[str] = None) -> str:
        """
        Save the current model atomically to ``path`` (default ``model_path``); returns it.

        The model is copied under the lock and written outside it, so the message path never
        waits for the disk.
        """
        path = path or self.config.model_path
        if not path:
            raise ValueError('no path given and model_path is not set')
        check_model_path(path)
        with self._lock:
            if self._model is None:
                raise RuntimeError('no trained model to save yet')
            model = copy.deepcopy(self._model)
        path = os.path.abspath(path)
        model.save(path)
        return path

    def _load(self, path: str) -> None:
        cfg = self.config
        try:
            model = self._loader(path)
            kind = model.posterior_.structure.kind
            if kind != cfg.model:
                raise ValueError(f'file holds a {kind!r} model, config model={cfg.model!r}')
            X, Y = model.X_train_, model.Y_train_
            if cfg.joints and X.shape[1] != len(cfg.joints):
                raise ValueError(f'file model has N={X.shape[1]}, joints has {len(cfg.joints)}')
            if cfg.passivity != 'none' and model.passivity != cfg.passivity:
                raise ValueError(f'file model passivity {model.passivity!r} != '
                                 f'{cfg.passivity!r}')
            ok, why = provable(model, cfg.passivity)      # re-proves: never trusts the file
            if not ok:
                raise ValueError(why)
        except Exception as exc:
            self.load_error = f'could not use {path}: {exc}'
            return
        self._N = X.shape[1]
        self._buf = Buffer.of(cfg.buffer_size, X, Y)
        self._seq = self._buf.size
        self._model = model
        self._hyper = model.hyperparams_
        self._opt_n = X.shape[0]
        self._clock = None              # set by the first message

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self) -> dict:
        """
        Everything the node publishes on /diagnostics, as a dict.

        ``level`` is OK/WARN/ERROR (0/1/2, diagnostic_msgs values) and ``message`` joins the
        reasons (see ``health.Health.status``).
        """
        with self._lock:
            cert = self._model.certificate() if self._model is not None else None
            fill = 0 if self._buf is None else self._buf.size
            last = self._last_est
            certifies = policy_class(self.config.passivity).certifies
            d = {
                'model': self.config.model, 'passivity': self.config.passivity,
                'trained': self._model is not None,
                'certified': bool(cert.certified) if cert is not None else False,
                'certificate_stale': bool(cert.stale) if cert is not None else False,
                'margin': float(cert.margin) if cert is not None else float('nan'),
                'method': str(cert.method) if cert is not None else '',
                'domain': str(cert.domain) if cert is not None else '',
                'buffer_fill': fill, 'buffer_size': self.config.buffer_size,
                'refit_running': self.refit_running(),
                'measured_power': last.measured_power if last else float('nan'),
                'estimated_power': last.power if last else float('nan'),
                'last_source': last.source if last else '',
                'load_error': self.load_error, 'hyper_samples': self._opt_n,
                'pending_samples': len(self._pending),
                'negative_power_fraction': self.negative_power_fraction(),
                'residual_delay_s': self._front.delay_s,
                'accel_filter_restarts': self._front.restarts,
                'accel_filter_dropped': self._front.dropped,
                'learning_clock': 'arrival' if self._arrival_t0 is not None else 'stamp',
            }
            d.update(self.health.counters())
            state = {'trained': d['trained'], 'fill': fill, 'min_samples': self.config.min_samples,
                     'certifies': certifies, 'certified': d['certified'],
                     'stale': d['certificate_stale'], 'load_error': self.load_error,
                     'warnings': self._warnings()}
            d['level'], d['message'] = self.health.status(state)
            return d

    def _warnings(self) -> List[str]:
        """Conditions on the data the user should act on (WARN with the reason)."""
        out = []
        if self._arrival_t0 is not None:
            out.append('message stamps do not advance (header.stamp constant or 0): learning '
                       "uses the arrival time; fix the driver's stamps")
        if self._stalled():
            out.append(f'learning stalled: no sample learned for '
                       f'{self._last_stamp - self._last_added_t:.0f} s while the velocities '
                       f'moved (check selection_min_distance / selection_scale)')
        frac = self.negative_power_fraction()
        if frac is not None and frac > self.config.negative_power_warn_fraction:
            what = 'effort - inverse dynamics' if self._inverse is not None else 'effort'
            hint = ('check the URDF, the joint order and the torque sign convention'
                    if self._inverse is not None else
                    'raw joint torques hold gravity and inertia: set inverse_dynamics (urdf and '
                    'robot_description, or a python plugin) so the rigid-body torque is '
                    'subtracted')
            out.append(f'data are not damping: qd . ({what}) < 0 on {100 * frac:.0f}% of the '
                       f'recent samples (friction dissipates); {hint}')
        return out

    def _stalled(self) -> bool:
        """
        Tell whether learning is stalled.

        No sample learned for ``STALL_WARN_S`` of learning time although the recent
        candidates spread over many novelty distances (not a hovering state).
        """
        if self._last_added_t is None or self._last_stamp is None or self._buf is None or \
                self._last_stamp - self._last_added_t < self.STALL_WARN_S or \
                len(self._recent_q) < 10:
            return False
        Q = np.array(self._recent_q)
        spread = (Q.max(axis=0) - Q.min(axis=0)) / self._selector.scale(self.config, self._buf)
        return bool(spread.max() > 10.0 * max(self.config.selection_min_distance, 1e-3))

    def negative_power_fraction(self) -> Optional[float]:
        """
        Fraction of the recent learned samples with ``qd .

        target < 0`` (None before enough samples were seen to decide).
        """
        p = self._learned_power
        if len(p) < _POWER_MIN:
            return None
        return float(np.mean(np.asarray(p) < 0.0))

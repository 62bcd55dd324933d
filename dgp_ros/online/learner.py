"""
The learner: everything the online estimator learns, and nothing it answers (no rclpy).

A :class:`Learner` takes validated measurements in learning time (``learn``), turns them into
learning samples (the friction residual front end of ``dynamics`` when there is inverse
dynamics), decides which to keep (``selection``), updates the model, runs refit and re-proof
jobs (``worker``; their integration is ``jobs``) and publishes what a prediction needs as an
immutable :class:`~dgp_ros.online.snapshot.Snapshot`. The message path
(:class:`~dgp_ros.online.estimator.OnlineEstimator`) answers from the newest snapshot and never
waits for the learner; in the node the learner lives in a child process
(:mod:`dgp_ros.online.process`), in replay and tests in line (``refit_mode='sync'``).

Refits: the first as soon as ``min_samples`` are buffered; then every ``refit_period_s`` of
learning time, on ``request_refit()``, and whenever the buffer has doubled since the
hyper-parameters were learned (20 -> 40 -> 80 ... while it fills; a first optimum learned on a
few samples of a near-stationary start can be far off). Refit number k re-learns the
hyper-parameters when ``k % optimize_every_n_refits == 0``, on the first fit and after a
doubling; otherwise it refits at the current ones. A stale certificate (``certified`` mode, after
updates) is re-proven by a 'recertify' job, at most every ``refit_period_s / 4``.
"""
from __future__ import annotations

from collections import deque
import copy
import dataclasses
import os
import threading
from typing import Callable, List, Optional, Tuple

import numpy as np

from dgp_ros.dynamics import AccelFilter, FrictionResidual, make_inverse_dynamics
from dgp_ros.gp import load_model, make_model
from dgp_ros.gp.means import make_mean

from .absorb import Absorber
from .config import check_model_path, EstimatorConfig
from .grounds import SkillMixin
from .health import LearnerHealth, LearnerReport, POWER_WINDOW
from .jobs import JobRunner
from .selection import Buffer, Selector
from .snapshot import Snapshot
from .structure import StructureMixin
from .switch import LearningSwitch
from .worker import prove

__all__ = ['Learner', 'STRUCTURAL', 'FRONT_END']

#: structural fields: changing one at run time drops the model and refits
STRUCTURAL = ('model', 'passivity', 'elements', 'prior', 'bias', 'buffer_size', 'buffer_policy',
              'joints', 'operating_domain', 'inverse_dynamics', 'robot_description', 'urdf_file',
              'accel_half_window_s')
#: fields of the front end: changing one resets the learner
FRONT_END = ('inverse_dynamics', 'robot_description', 'urdf_file', 'joints')


class Learner(StructureMixin, SkillMixin, Absorber, LearningSwitch, JobRunner, LearnerReport):
    """
    Online learning of a D-GP from a stream of measurements (module docstring).

    Parameters
    ----------
    config : EstimatorConfig
    model_factory : callable ``(kind, **kwargs) -> model``
        Builds candidate models (default ``dgp_ros.gp.make_model``); injectable for tests.
    model_loader : callable ``(path) -> model``
        Reads ``model_path`` (default ``dgp_ros.gp.load_model``).

    """

    #: samples arriving during a refit on which its held-out check compares the models: the
    #: first this many, then evenly spread ones up to twice as many
    HELD_OUT_EVERY = 20

    def __init__(self, config: Optional[EstimatorConfig] = None,
                 model_factory: Optional[Callable] = None,
                 model_loader: Optional[Callable] = None):
        self.config = dataclasses.replace(config or EstimatorConfig()).validate()
        self._factory = model_factory or make_model
        self._loader = model_loader or load_model
        self._lock = threading.RLock()
        self._thread: Optional[threading.Thread] = None
        self._absorber: Optional[threading.Thread] = None
        self._absorb_wanted = threading.Event()
        self._generation = 0
        self.load_error = ''
        self._inverse = _inverse_dynamics(self.config)
        self._init_state()
        path = self.config.model_path
        if path and os.path.exists(path):
            self._load(path)

    # ------------------------------------------------------------------ state
    def _init_state(self, keep_health: bool = False) -> None:
        self._generation += 1
        names = list(self.config.joints) or list(getattr(self._inverse, 'joint_names', []))
        self._N: Optional[int] = len(names) or None
        self._front = FrictionResidual(
            self._inverse, AccelFilter(self.config.accel_half_window_s)
            if self._inverse is not None else None)
        self._learned_power: deque = deque(maxlen=POWER_WINDOW)
        self._buf: Optional[Buffer] = None
        self._history = None               # long history of prior='auto' (structure.py)
        self._param = None
        self._rmax = None                  # largest |residual| learned per joint (structure.py)
        self._selector = Selector()
        self._skill = None                # one-step skill of model and prior (grounds.py)
        self._gains_seq = getattr(self, '_gains_seq', 0) + 1   # gains_seq (grounds.py)
        self._seq = 0                     # samples ever added (orders the catch-up)
        self._reset_absorber(self.config.buffer_size)
        # (seq, qd, tau, answer before learning) added while a refit runs; only the newest
        # buffer_size can survive the model's window, so older ones are dropped here
        self._pending: deque = deque(maxlen=self.config.buffer_size)
        self._model = None
        self._hyper: Optional[dict] = None   # warm start of the next fit (hyperparams_)
        self._opt_n = 0                   # samples the current hyper-parameters were learned on
        self._hyper_box = None            # their velocity box (jobs.JobRunner._note_novelty)
        self._novel, self._novel_t = False, None
        self._prior = None                # fitted prior of the buffer (lazy): (mean, std, seq)
        self._last_t: Optional[float] = None
        self._last_added_t: Optional[float] = None
        self._recent_q: deque = deque(maxlen=100)       # recent candidates (stall check)
        self._clock: Optional[float] = None   # learning time of the last refit decision
        self._last_recert: Optional[float] = None
        self._refit_requested = False
        self._retry_at: Optional[int] = None  # _seq at which a rejected candidate is retried
        # bumped whenever what a snapshot holds changes; increasing across resets
        self._version = getattr(self, '_version', 0) + 1
        self._snap: Optional[Snapshot] = None
        self._snap_gains = -1             # the gains_seq self._snap carries
        self._reset_switch()
        if not keep_health:
            self.health = LearnerHealth()

    @property
    def trained(self) -> bool:
        return self._model is not None

    @property
    def model(self):
        """Get the current model, None before the first fit (do not mutate it)."""
        return self._model

    @property
    def N(self) -> Optional[int]:
        return self._N

    @property
    def version(self) -> int:
        """Return a number that changes whenever the next snapshot would differ."""
        return self._version

    def samples(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return copies of the buffered samples, (Qd, Tau), (n, N) each, oldest first."""
        with self._lock:
            if self._buf is None:
                return np.zeros((0, self._N or 0)), np.zeros((0, self._N or 0))
            return self._buf.arrays()

    def refit_running(self) -> bool:
        t = self._thread
        return t is not None and t.is_alive()

    # the rest of the interface the message path uses (``process.LearnerProcess`` has it too)
    def joint_names(self) -> List[str]:
        """Joint names the learner selects (``joints``, else the URDF's; [] = message order)."""
        return list(self.config.joints) or list(getattr(self._inverse, 'joint_names', []))

    @property
    def needs_position(self) -> bool:
        """Tell whether the learner uses joint positions (inverse dynamics)."""
        return bool(self.config.inverse_dynamics)

    def set_variance(self, on: bool) -> None:
        """In line the live model always has its factors: nothing to do."""

    def set_residuals(self, on: bool) -> None:
        """In line the residuals come with ``learn``: nothing to do."""

    def take_residuals(self) -> list:
        """Residual samples completed since the last call, beyond those ``learn`` returned."""
        return []

    def note_error(self, message: str) -> None:
        """Record an error of the message path (shown as the last error)."""
        with self._lock:
            self.health.last_refit_error = message

    # ------------------------------------------------------------------ learning
    def learn(self, t: float, qd: np.ndarray, tau: np.ndarray, q=None) -> Tuple[bool, list]:
        """
        Learn from one validated measurement at learning time ``t`` (s).

        qd, tau, q : (N,) velocity, effort, position (q None without inverse dynamics), in the
        configured joint order. Returns (taken for learning, completed residual samples); the
        residual samples (``dynamics.ResidualSample``) trail ``t`` by the filter's half window.
        Never raises on a failing plugin or model (counted, the sample is not learned).
        """
        with self._lock:
            if self._N is None:
                self._N = qd.size
            if self._buf is None:
                self._buf = Buffer(self.config.buffer_size, self._N, self.config.buffer_policy)
            if self._last_t is not None and t < self._last_t:
                # documented policy: keep model and buffer, restart the refit clock, count it
                self.health.time_jumps_back += 1
                if self._clock is not None:
                    self._clock = t
            self._last_t = t
            added, residuals = self._learn(t, qd, tau, q)
            if self.append_each:
                self.catch_up()
            job = self._next_job(t)
            absorb = job is None and self._absorb_due()
        if job is not None:
            self._start(job)
        elif absorb:
            self._absorb_soon()
        return added, residuals

    def poll(self, idle: bool = False) -> None:
        """
        Do what became due without a new sample: a job, or absorbing the last samples.

        ``idle``: the stream has paused (a learner process says so after ``PAUSE_S`` without a
        sample); a stale certificate is then re-proven at once: the proof holds until the stream
        resumes.
        """
        with self._lock:
            if self._last_t is None and not self._freeze_wanted:
                return
            job = self._next_job(self._last_t, idle)
            absorb = job is None and self._absorb_due()
        if job is not None:
            self._start(job)
        elif absorb:
            self._absorb_soon()

    def _learn(self, stamp: float, qd: np.ndarray, tau: np.ndarray, q) -> Tuple[bool, list]:
        """Offer the sample for learning (rate limit; the residual front end if any)."""
        h, sel = self.health, self._selector
        if self.config.awaits_urdf:             # no rigid-body model yet: nothing to learn
            h.samples_awaiting_model += 1
            return False, []
        want = not sel.rate_limited(self.config, stamp)
        if want:
            sel.added(stamp)
        else:
            h.samples_rate_limited += 1
        if self._inverse is None:
            return (self._add(stamp, qd, tau, q) if want else False), []
        try:
            done = self._front.push(stamp, q, qd, tau, want=want)
        except Exception as exc:        # a plugin that fails: the message is still answered
            h.last_refit_error = f'inverse dynamics failed: {type(exc).__name__}: {exc}'
            h.inverse_dynamics_errors += 1
            return False, []
        for r in done:
            if np.all(np.isfinite(r.residual)):
                self._add(r.stamp_s, r.qd, r.residual, r.q, r.qdd)
        return want, done

    def _add(self, stamp: float, qd: np.ndarray, residual: np.ndarray, q=None,
             qdd=None) -> bool:
        """
        Learn one sample: the long history always, the buffer unless it is a near-duplicate.

        residual (N,): what the damping and (``prior='auto'``) the correction explain; the
        buffer keeps it minus the current correction (``structure``).
        """
        h = self.health
        if not self.config.learning:            # serve only (``switch``)
            h.samples_not_learned += 1
            return False
        self._learned_power.append(float(qd @ residual))
        self._recent_q.append(qd)
        if self._selector.outlier(self.config, self._buf, qd, residual):
            h.samples_outliers += 1
            return False
        prior = self._skill_prior()             # the prior before this sample (one step ahead)
        yt = self._history_push(stamp, q, qd, qdd, residual)
        target = self._target(residual, yt)
        self._note_novelty(stamp, qd, self._note_skill(stamp, qd, target, prior, residual, q))
        if not self._selector.novel(self.config, self._buf, qd):
            h.samples_skipped += 1
            return False
        self._last_added_t = stamp
        self._buf.append(qd, target, (residual, yt) if self.auto else None)
        self._selector.additions += 1
        self._seq += 1
        self._rows.append((self._seq, self._target_gen, qd, target))
        if self._model is None:
            self._version += 1                  # the prior the answers come from may change
        h.samples_added += 1
        if self.refit_running():
            # the samples a running refit's candidate has not seen: its held-out check
            # (jobs.JobRunner._held_out)
            self._pending.append((self._seq, qd.copy(), target.copy()))
        return True

    # ------------------------------------------------------------------ snapshots
    def _fitted_prior(self):
        """(mean, std): the passive prior fitted to the buffer, refitted per tenth of it."""
        # a 7-joint friction prior costs ~15 ms: refitted on every learned sample it held the
        # answers while the first fit ran
        auto = self._auto_prior()
        if auto is not None:
            return auto
        if self._prior is None or self._seq >= self._prior[2] + max(1, self._prior[2] // 10):
            N = self._N
            Q, T = self._buf.arrays() if self._buf is not None and self._buf.size else \
                (np.zeros((0, N)), np.zeros((0, N)))
            cfg = self.config
            prior = 'viscous' if cfg.model == 'ard' or cfg.prior == 'auto' else cfg.prior
            try:
                mean = make_mean(prior, 'full', bool(cfg.bias)).fit(Q, T)
                resid = T - mean(Q) if Q.shape[0] else T
                std = np.sqrt(np.mean(resid ** 2, axis=0)) if Q.shape[0] else np.zeros(N)
            except Exception:           # degenerate buffer: no prior damping at all
                mean, std = make_mean('viscous', 'full').fit(Q[:0], T[:0]), np.zeros(N)
            self._prior = (mean, std, self._seq)
        return self._prior[0], self._prior[1]

    def snapshot(self, variance: bool = True, frozen: bool = False) -> Optional[Snapshot]:
        """
        Return what a prediction needs now (None before the first sample).

        variance : include what the posterior variance needs (the Cholesky factors).
        frozen : a self-contained copy for another process (``process``); else the snapshot
            refers to the live model (in-line use: the caller learns and answers in turn).
        """
        with self._lock:
            if self._N is None or self._buf is None:
                return None
            s = self._snap
            if s is not None and s.version == self._version and \
                    (s.frozen, s.variance) == (frozen, variance or not frozen):
                self._snap = self._with_gains(s)       # the gains earned since, if any
                return self._snap
            mean, std = self._fitted_prior()
            model = self._model
            if model is not None and model.posterior_.structure.has_damping:
                # a model answers with its own prior and bounds: the same after a reload
                mean, bound = model.mean_, np.abs(model.Y_train_).max(axis=0)
                Q = model.X_train_
            else:
                Q, T = self._buf.rows_unordered()
                bound = np.abs(T).max(axis=0) if self._buf.size else np.zeros(self._N)
            box = (Q.min(axis=0), Q.max(axis=0)) if len(Q) else None
            per_joint = model is not None and model.posterior_.structure.has_damping and \
                model.certificate().guarantee == 'psd'
            if model is not None and frozen:
                model = model.snapshot(variance=variance)
            self._snap = self._with_gains(Snapshot(
                version=self._version, model=model, prior=mean, prior_std=std,
                force_bound=bound, velocity_box=box,
                residual_bound=None if self._rmax is None else self._rmax.copy(),
                learned_through=self._last_t, frozen=frozen, variance=variance or not frozen,
                per_joint=per_joint))
            return self._snap

    # ------------------------------------------------------------------ housekeeping
    def reset(self) -> None:
        """Forget the model, the buffer and all counters (a running refit is discarded)."""
        with self._lock:
            self._init_state()

    def check_reconfigure(self, config: EstimatorConfig) -> None:
        """Raise ValueError (with the reason) if ``reconfigure(config)`` would fail."""
        config = dataclasses.replace(config).validate()
        if self._N is not None:
            config.check_dimension(self._N)
        if any(getattr(self.config, f) != getattr(config, f) for f in FRONT_END):
            _inverse_dynamics(config)

    def reconfigure(self, config: EstimatorConfig) -> str:
        """
        Apply a new validated config; structural changes drop the model and refit.

        A change of ``learning`` switches learning off (the model is proven and saved) or on
        (``switch``).
        """
        switched = bool(config.learning) != bool(self.config.learning)
        what = self._reconfigure(config)
        return self._switch_note(what, bool(config.learning)) if switched else what

    def _reconfigure(self, config: EstimatorConfig) -> str:
        config = dataclasses.replace(config).validate()
        if self._N is not None:
            config.check_dimension(self._N)
        old = self.config
        inverse = self._inverse
        if any(getattr(old, f) != getattr(config, f) for f in FRONT_END):
            inverse = _inverse_dynamics(config)     # ValueError before anything changes
        with self._lock:
            self.config = config
            self._inverse = inverse
            if bool(old.learning) != bool(config.learning):
                self._learning_switched(bool(config.learning))
            changed = [f for f in STRUCTURAL if getattr(old, f) != getattr(config, f)]
            self._version += 1
            if not changed:
                return 'applied'
            if any(f in changed for f in FRONT_END):
                # other joints, or another rigid-body model: what was learned no longer applies
                self._init_state(keep_health=True)
                return f'{", ".join(changed)} changed: estimator reset'
            data = self._buf.arrays() if self._buf is not None and self._buf.size else None
            N = self._N
            self._init_state(keep_health=True)
            self._N = N
            if data is not None:
                self._buf = Buffer.of(config.buffer_size, *data, policy=config.buffer_policy)
                self._refit_requested = True
            return f'{", ".join(changed)} changed: model dropped, refit on the next sample'

    def save(self, path: Optional[str] = None) -> str:
        """
        Save the current model atomically to ``path`` (default ``model_path``); returns it.

        The model is copied under the lock and written outside it, once learning has stopped.
        """
        path = path or self.config.model_path
        if not path:
            raise ValueError('no path given and model_path is not set')
        check_model_path(path)
        self.wait_stopped()
        with self._lock:
            if self._model is None:
                raise RuntimeError('no trained model to save yet')
            model = copy.deepcopy(self._model)
        if self._model is not None and self.config.learning and \
                (self.unheld or self._history_grew()):
            with self._lock:
                self._reselect_now = True
            self._absorb()          # the saved prior and correction see the whole history
            with self._lock:
                model = copy.deepcopy(self._model)
        record = self.grounds_record()
        if record is not None:      # restored with the model (``_load``)
            model.grounds_ = record
        path = os.path.abspath(path)
        model.save(path)
        return path

    def adopt(self, model, source: str = '') -> None:
        """
        Serve ``model`` and buffer its training samples (a model file, a restarted learner).

        Raises ValueError when it does not fit the configuration. Its certificate is proven
        again (never trusted from the file); one that does not hold serves with every answer
        projected, as a refit's would.
        """
        cfg = self.config
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
        with self._lock:
            self.health.proof_done(proof)
            self._N = X.shape[1]
            self._buf = Buffer.of(cfg.buffer_size, X, Y, policy=cfg.buffer_policy)
            self._seq = self._buf.size
            self._reset_absorber(cfg.buffer_size)
            self._based(model, self._seq, self._target_gen)
            self._hyper = model.hyperparams_
            self._opt_n = X.shape[0]
            self._hyper_box = (X.min(axis=0), X.max(axis=0))
            self._clock = None              # set by the first message

    def _load(self, path: str) -> None:
        try:
            model = self._loader(path)
            g = getattr(model, 'grounds_', None)
            self.adopt(model, 'file')
        except Exception as exc:
            self.load_error = f'could not use {path}: {exc}'
            return
        # a model file answers with the gains it was saved with (a file without them, at full
        # weight: the user gave it); one-step scores then move them as a learned model's
        self.restore_grounds(g, model.X_train_.shape[1])


def _inverse_dynamics(config: EstimatorConfig):
    """Build the rigid-body model of ``config`` (None: without one, or the URDF is awaited)."""
    if config.awaits_urdf:
        return None
    return make_inverse_dynamics(config.inverse_dynamics,
                                 robot_description=config.robot_description,
                                 urdf_file=config.urdf_file, joints=config.joints)

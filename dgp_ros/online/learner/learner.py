"""
The learner: everything the online estimator learns, and nothing it answers (no rclpy).

A :class:`Learner` takes validated measurements in learning time (``learn``), turns them into
learning samples, decides which to keep, updates the model, runs refit and re-proof jobs and
publishes what a prediction needs as an immutable
:class:`~dgp_ros.online.learner.snapshot.Snapshot`. The message path
(:class:`~dgp_ros.online.path.estimator.OnlineEstimator`) answers from the newest snapshot and
never waits for the learner; in the node the learner lives in a child process
(:mod:`dgp_ros.online.process.proxy`), in replay and tests in line (``refit_mode='sync'``).

It is composed of parts that own their state (``sampling``, ``window``, ``prior``, ``grounds``,
``served``, ``refits``, ``rebases``, ``switch``, ``snapshots``) and steps on them (``files``),
docs/ARCHITECTURE.md, "The learner's parts". Parts call each other through public methods; the
learner makes them anew on a reset and passes them to the steps (``parts.Parts``). Its one lock
guards them all and is never held while a model is fitted or proven.
"""
from __future__ import annotations

import dataclasses
import os
import threading
from typing import Callable, List, Optional, Tuple

import numpy as np

from dgp_ros.gp import load_model, make_model

from . import files
from .grounds import Grounds
from .health import LearnerHealth
from .parts import Parts
from .prior import Structure
from .report import learner_status
from .sampling import Front
from .served import Served
from .snapshot import Snapshot, Snapshots
from .window import Window
from ..config import EstimatorConfig
from ..jobs.rebase import Rebases
from ..jobs.refits import Refits
from ..jobs.switch import Switch

__all__ = ['Learner', 'STRUCTURAL', 'FRONT_END']

#: structural fields: changing one at run time drops the model and refits
STRUCTURAL = ('model', 'passivity', 'elements', 'prior', 'history_elements', 'bias',
              'buffer_size', 'buffer_policy', 'joints', 'operating_domain', 'inverse_dynamics',
              'robot_description', 'urdf_file', 'accel_half_window_s', 'effort_scale')
#: fields of the front end: changing one resets the learner (what it learned is of other data)
FRONT_END = ('inverse_dynamics', 'robot_description', 'urdf_file', 'joints', 'effort_scale')


class Learner:
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

    #: append each sample in ``learn`` (in line); the learner process appends per round instead
    append_each = True

    def __init__(self, config: Optional[EstimatorConfig] = None,
                 model_factory: Optional[Callable] = None,
                 model_loader: Optional[Callable] = None):
        self.config = dataclasses.replace(config or EstimatorConfig()).validate()
        self._factory = model_factory or make_model
        self._loader = model_loader or load_model
        self._lock = threading.RLock()
        self.load_error = ''
        self._inverse = Front.inverse_dynamics(self.config)
        self._names_hint: Optional[List[str]] = None
        self.health = LearnerHealth()
        self.refits = None
        self._init_state(keep_health=True)
        path = self.config.model_path
        if path and os.path.exists(path):
            self._load(path)

    # ------------------------------------------------------------------ the parts
    def _init_state(self, keep_health: bool = False) -> None:
        """Make the parts anew (a reset); what runs in the old ones is discarded."""
        cfg, old = self.config, self.refits
        if old is not None:
            old.discard()
        if not keep_health:
            self.health = LearnerHealth()
        h, lock = self.health, self._lock
        names = list(cfg.joints) or list(getattr(self._inverse, 'joint_names', []))
        self._N: Optional[int] = len(names) or None
        self.front = Front(cfg, self._inverse)
        self._last_t: Optional[float] = None
        self.window = Window(cfg.buffer_size, cfg.buffer_policy)
        self.structure = Structure(cfg, self._inverse)
        # the counts a snapshot is recognized by keep increasing across resets
        self.grounds = Grounds(1 if old is None else self.grounds.seq + 1)
        self.served = Served(1 if old is None else self.served.version + 1)
        self.refits = Refits(self._factory, cfg.buffer_size, 1 if old is None else old.generation)
        self.rebases = Rebases(self._factory)
        self.switch = Switch()                  # handed the parts in each call
        self.snapshots = Snapshots()
        self._parts = Parts(lock, self._settings, self.window, self.structure, self.grounds,
                            self.served, self.rebases, self.refits, self.switch, h,
                            lambda: self._last_t, files.save)

    def _settings(self) -> EstimatorConfig:
        return self.config

    def parts(self) -> Parts:
        """Return the learner's parts as they are now (what its steps are passed, not kept)."""
        return self._parts          # made anew with them (``_init_state``), only there

    # ------------------------------------------------------------------ state
    @property
    def trained(self) -> bool:
        return self.served.model is not None

    @property
    def model(self):
        """Get the current model, None before the first fit (do not mutate it)."""
        return self.served.model

    @property
    def N(self) -> Optional[int]:
        return self._N

    @property
    def version(self) -> int:
        """Return a number that changes whenever the next snapshot would differ."""
        return self.served.version

    @property
    def gains_seq(self) -> int:
        """Return a number that changes whenever the gains do (every scored sample)."""
        return self.grounds.seq

    @property
    def unheld(self) -> int:
        """Learned samples the model does not hold yet."""
        return self.served.unheld(self.window.seq)

    @property
    def last_t(self) -> Optional[float]:
        """Return the learning time of the newest sample (s), None before any."""
        return self._last_t

    @property
    def learning_state(self) -> str:
        """Return 'on', 'stopping' (the model being proven and saved) or 'off'."""
        return self.switch.state(self.config.learning)

    @property
    def inverse(self):
        """Return the rigid-body model (None without one)."""
        return self._inverse

    def samples(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return copies of the buffered samples, (Qd, Tau), (n, N) each, oldest first."""
        with self._lock:
            if self.window.buffer is None:
                return np.zeros((0, self._N or 0)), np.zeros((0, self._N or 0))
            return self.window.arrays()

    def refit_running(self) -> bool:
        return self.refits.running()

    # the rest of the interface the message path uses (``process.proxy.LearnerProcess`` has it too)
    def joint_names(self) -> List[str]:
        """Joint names the learner selects (``joints``, else the URDF's; [] = message order)."""
        return list(self.config.joints) or list(getattr(self._inverse, 'joint_names', []))

    def structure_names(self) -> List[str]:
        """Joint names for the structure and the report (``joint_names``, else the stream's)."""
        return self.joint_names() or list(self._names_hint or [])

    @property
    def needs_position(self) -> bool:
        """Tell whether the learner uses joint positions (inverse dynamics)."""
        return bool(self.config.inverse_dynamics)

    def set_joint_names(self, names) -> None:
        """Take the stream's joint names (they may name a known robot: its URDF kinematics)."""
        with self._lock:
            if not self._names_hint and names:
                self._names_hint = [str(n) for n in names]

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
    def learn(self, t: float, qd: np.ndarray, tau: np.ndarray, q=None,
              thin: int = 1) -> Tuple[bool, list]:
        """
        Learn from one validated measurement at learning time ``t`` (s).

        qd, tau, q : (N,) velocity, effort, position (q None without inverse dynamics), in the
        configured joint order. Returns (taken for learning, completed residual samples); the
        residual samples (``dynamics.ResidualSample``) trail ``t`` by the filter's half window.
        Never raises on a failing plugin or model (counted, the sample is not learned).
        ``thin`` k > 1: the front end takes the measurement (the acceleration filter needs every
        one) and of the samples it gives one in k is learned, the others counted as
        ``samples_thinned`` (a learner process behind its stream:
        ``child.LearnerLoop._samples``). The count runs over the samples the front end gives,
        not the measurements: a stream faster than ``min_sample_interval_s`` is not thinned
        twice over (one measurement in k that the interval lets through one in ten of).
        """
        with self._lock:
            if self._N is None:
                self._N = qd.size
            self.window.ensure(self._N)
            if self._last_t is not None and t < self._last_t:
                # documented policy: keep model and buffer, restart the refit clock, count it
                self.health.time_jumps_back += 1
                self.refits.jumped_back(t)
            self._last_t = t
            added, residuals = self._learn(t, qd, tau, q, thin)
            if self.append_each:
                self.catch_up()
            job = self._next_job(t)
            rebase = job is None and self.rebases.due(self._parts)
        if job is not None:
            self.refits.start(job, self.parts())
        elif rebase:
            self.rebases.soon(self.parts())
        return added, residuals

    def learn_many(self, t: np.ndarray, qd: np.ndarray, tau: np.ndarray, q=None):
        """``learn`` for k samples in order (t (k,), qd and tau (k, N)); (k flags, k lists)."""
        got = [self.learn(float(t[j]), qd[j], tau[j], None if q is None else q[j])
               for j in range(len(t))]
        return [g[0] for g in got], [g[1] for g in got]

    def poll(self, idle: bool = False) -> None:
        """
        Do what became due without a new sample: a job, or a rebase on the last samples.

        ``idle``: the stream has paused (a learner process says so after ``PAUSE_S`` without a
        sample); a stale certificate is then re-proven at once: the proof holds until the stream
        resumes.
        """
        with self._lock:
            if self._last_t is None and not self.switch.wanted:
                return
            job = self._next_job(self._last_t, idle)
            rebase = job is None and self.rebases.due(self._parts)
        if job is not None:
            self.refits.start(job, self.parts())
        elif rebase:
            self.rebases.soon(self.parts())

    def _next_job(self, stamp, idle: bool = False):
        """Return the job due now (under the lock): the freeze with learning off, else a refit."""
        if not self.config.learning:
            return self.switch.job(self._parts)     # serve only: nothing else (``switch``)
        return self.refits.next_job(stamp, self._last_t, self._parts, idle)

    def _learn(self, stamp: float, qd: np.ndarray, tau: np.ndarray, q,
               thin: int = 1) -> Tuple[bool, list]:
        """Offer the sample to learn (``sampling``); learn what it gives; (taken, residuals)."""
        want, done, take = self.front.offer(self.config, self.health, stamp, qd, tau, q)
        if thin > 1 and take:
            take, thinned = self.front.thin(take, thin, self.health)
            if self._inverse is None and self.config.learning:
                self.structure.push_thinned(thinned, self.window, self.config, self._N,
                                            self.structure_names(), self.health)
            if not take:
                return False, done
        if self._inverse is None:
            return (self._add(*take[0]) if take else False), []
        for sample in take:
            self._add(*sample)
        return want, done

    def _add(self, stamp: float, qd: np.ndarray, residual: np.ndarray, q=None,
             qdd=None) -> bool:
        """
        Learn one sample: the long history always, the window unless it is a near-duplicate.

        residual (N,): what the damping and (``prior='auto'``) the correction explain; the
        window keeps it minus the current correction (``prior``). Before it is learned the
        sample scores the served model and its parametric part (``grounds``): one step ahead.
        """
        h, win, st = self.health, self.window, self.structure
        if not self.config.learning:            # serve only (``switch``)
            h.samples_not_learned += 1
            return False
        win.offered(qd, residual)
        if win.outlier(self.config, qd, residual):
            h.samples_outliers += 1
            return False
        # the prior the answers came from before this sample (one step ahead)
        prior = st.answering(win, self._N, self.served.model, h)
        yt = st.push(stamp, q, qd, qdd, residual, self._N, self.structure_names(), h)
        target = st.target(residual, yt, h)
        surprise = self.grounds.note(stamp, qd, target, prior, residual, q, self.served.model)
        self.refits.note_novelty(stamp, qd, surprise, self._parts)
        if not win.novel(self.config, qd):
            h.samples_skipped += 1
            return False
        seq = win.add(stamp, qd, target, (residual, yt) if st.auto else None)
        if self.served.model is None:
            self.served.touch()                 # the prior the answers come from may change
        h.samples_added += 1
        # the samples a running refit's candidate has not seen: its held-out check
        self.refits.note_sample(seq, qd, target)
        return True

    def catch_up(self) -> int:
        """
        Append every learned sample the model does not hold yet (``Served.catch_up``).

        With learning off nothing: the model that serves is the one the freeze saved.

        Where the parametric part carries a persistent column's couplings, the model then takes
        it refitted on the history as it is now as its prior (``Structure.follow``): a prior
        refitted at each rebase only (50 samples) answered an approach's drag 3x worse.
        """
        with self._lock:
            if not self.config.learning:
                return 0                # frozen: the freeze brought the model up (``switch``)
            n = self.served.catch_up(self.window, self.health, self.config.buffer_size)
            if self.served.model is not None and self.structure.follow(self._last_t):
                self.served.remean(self.structure.frozen_prior())
            return n

    def catch_up_paused(self) -> None:
        """
        Append the samples the model does not hold yet, once the samples ran out.

        A learner process that fell behind appends nothing while samples queue up (its rebases
        take them in); when the stream pauses right after, nothing else would bring the last
        ones to the model before it resumes. Cheap when there is nothing to do.
        """
        if self.unheld and not self.served.blocked:
            self.catch_up()

    # ------------------------------------------------------------------ snapshots
    def snapshot(self, variance: bool = True, frozen: bool = False) -> Optional[Snapshot]:
        """Return what a prediction needs now, None before the first sample (``Snapshots``)."""
        with self._lock:
            return self.snapshots.take(self.parts(), self._N, self._last_t, variance, frozen)

    # ------------------------------------------------------------------ the gains
    def skill_gains(self):
        """Return (model weight, prior gain, confidence), (N,) each; Nones before any sample."""
        return self.grounds.gains()

    def restore_gains(self, model_weight, prior_gain, confidence, live=None) -> None:
        """Start from the gains a previous learner earned (``Grounds.restore``)."""
        with self._lock:
            if self.grounds.restore(model_weight, prior_gain, confidence, live):
                self.snapshots.forget()

    def restore_residual_bound(self, bound) -> None:
        """Take the largest |residual| per joint a previous learner saw (a restart), (N,)."""
        with self._lock:
            self.structure.restore_residual_bound(bound)
            self.snapshots.forget()     # the next snapshot carries it

    # ------------------------------------------------------------------ jobs
    def request_refit(self) -> Tuple[bool, str]:
        """Refit now (async: start it in the background). Returns (ok, message)."""
        with self._lock:
            job, why = self.refits.request(self._last_t, self._parts)
        if job is None:
            return False, why
        return self.refits.start(job, self.parts())

    def wait_for_refit(self, timeout: Optional[float] = None) -> bool:
        """Block until no refit is running; True if none is running at return."""
        return self.refits.wait(timeout)

    def close(self, timeout: float = 30.0) -> None:
        """Wait (bounded) for a running refit to finish; call before exit."""
        self.refits.wait(timeout)

    def status(self) -> dict:
        """Return the learner's part of the diagnostics (``report``)."""
        with self._lock:
            return learner_status(self)

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
            Front.inverse_dynamics(config)

    def reconfigure(self, config: EstimatorConfig) -> str:
        """
        Apply a new validated config; structural changes drop the model and refit.

        A change of ``learning`` switches learning off (the model is proven and saved) or on
        (``switch``).
        """
        on = bool(config.learning)
        switched = on != bool(self.config.learning)
        what = self._reconfigure(config)
        if not switched:
            return what
        if on:
            return f'{what}; learning on'
        self.switch.start(self.parts())
        with self._lock:
            frozen = self.served.model is not None
        note = ('learning off: the model is proven and saved (learning: stopping, then off)'
                if frozen else 'learning off: no model yet, the prior serves')
        return f'{what}; {note}'

    def _reconfigure(self, config: EstimatorConfig) -> str:
        config = dataclasses.replace(config).validate()
        if self._N is not None:
            config.check_dimension(self._N)
        old = self.config
        inverse = self._inverse
        if any(getattr(old, f) != getattr(config, f) for f in FRONT_END):
            inverse = Front.inverse_dynamics(config)     # ValueError before anything changes
        with self._lock:
            self.config = config
            self._inverse = inverse
            if bool(old.learning) != bool(config.learning):
                self._learning_switched(bool(config.learning))
            changed = [f for f in STRUCTURAL if getattr(old, f) != getattr(config, f)]
            self.served.touch()
            if not changed:
                return 'applied'
            if any(f in changed for f in FRONT_END):
                # other joints, or another rigid-body model: what was learned no longer applies
                self._init_state(keep_health=True)
                return f'{", ".join(changed)} changed: estimator reset'
            win = self.window
            data = win.arrays() if win.buffer is not None and win.size else None
            N = self._N
            self._init_state(keep_health=True)
            self._N = N
            if data is not None:
                self.window.refill(*data)
                self.refits.request_soon()
            return f'{", ".join(changed)} changed: model dropped, refit on the next sample'

    def _learning_switched(self, on: bool) -> None:
        """Under the lock, after ``config.learning`` changed to ``on``."""
        self.grounds.touch()                    # the snapshot's gains switch memory
        if on:
            self.switch.resume()
            self.refits.resumed()               # the refit clock starts at the next sample
            self.window.resumed(self._last_t)   # no 'stalled' warning for the pause
            return
        self.refits.discard()                   # a running refit or rebase is discarded
        self.switch.stop(self.served.model is not None)

    def save(self, path: Optional[str] = None, learn_waiting: bool = True) -> str:
        """Save the served model atomically to ``path`` (``files``; nothing waits in line)."""
        return files.save(self.parts(), path)

    def adopt(self, model, source: str = '') -> None:
        """Serve ``model`` and buffer its training samples (``files.adopt``)."""
        N = files.adopt(self.parts(), model, source)
        with self._lock:
            self._N = N

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
        self.restore_gains(*Grounds.record_gains(g, model.X_train_.shape[1]))

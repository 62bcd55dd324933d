"""
The online estimator's message path: validate, answer, hand over to the learner (no rclpy).

``process`` validates one measurement, hands it to the learner and answers with the estimate at
the measured velocity from the newest learner snapshot; ``process_batch`` does the same for every
message waiting at once, with one vectorized prediction, and ``process_arrays`` (``arrays``) for a
batch of like messages given as arrays (the node's raw path), without an object per message.
They differ only in how the messages are checked (one by one, or a batch at once: the same
rules); every accepted message is answered and learned by one step, ``_respond``, so the node,
``dgp-replay`` and the library answer alike by construction.
The learner (``learner.Learner``) is where everything is learned; where it runs is
``refit_mode``:

* ``'process'`` (the node's default): a child process (``process.proxy.LearnerProcess``) fed
  through a bounded shared-memory channel; snapshots come back and are swapped in by one reference
  assignment. The message path never waits for a fit, a proof or a rebuild; if the learner
  dies, the last snapshot keeps answering while a new learner starts from it.
* ``'async'``: the learner in this process, its refits in a background thread.
* ``'sync'``: everything in line, deterministic (``dgp-replay``, tests): each answer comes
  from the model that learned every message before it (one step ahead), as in the live node
  whose learner keeps up.

Every answer passes one output gate (``gate.answer``).
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from dgp_ros.gp.passivity import policy_class

from .arrays import Answers, last_estimate
from .clock import LearningClock
from .gate import answer, Estimate, guarantee
from .health import Health
from .intake import Intake
from .stream_part import StreamPart
from ..config import EstimatorConfig
from ..learner.learner import FRONT_END, Learner
from ..learner.plan import PlanCache
from ..learner.snapshot import Snapshot

__all__ = ['OnlineEstimator', 'Estimate']


class OnlineEstimator:
    """
    Online D-GP estimator (module docstring).

    Its parts: ``intake`` (the joints and the checks of every message: ``intake.Intake``),
    ``clock`` (the learning time: ``clock.LearningClock``), the learner (``learner.Learner`` or
    ``process.proxy.LearnerProcess``), ``health`` (the message path's counters) and the answer
    plans (``learner.plan.PlanCache``); one lock serializes the message path, diagnostics and
    control.

    Parameters
    ----------
    config : EstimatorConfig
    model_factory : callable ``(kind, **kwargs) -> model``
        Builds candidate models (default ``dgp_ros.gp.make_model``); in-process learners only.
    model_loader : callable ``(path) -> model``
        Reads ``model_path`` (default ``dgp_ros.gp.load_model``); in-process learners only.

    """

    def __init__(self, config: Optional[EstimatorConfig] = None,
                 model_factory: Optional[Callable] = None,
                 model_loader: Optional[Callable] = None):
        self.config = dataclasses.replace(config or EstimatorConfig()).validate()
        self._lock = threading.RLock()
        self._want_stddev = True
        self._want_damping = True
        self._want_residuals = True
        self._plans = PlanCache()             # the lean pass of the snapshot answered from
        if self.config.refit_mode == 'process':
            from ..process.proxy import LearnerProcess
            # a new snapshot's answer plan is built in the receiver thread, before the swap
            self._learner = LearnerProcess(
                self.config, prepare=lambda snap: self._plans.prepare(snap.model, snap.plan))
        else:
            self._learner = Learner(self.config, model_factory, model_loader)
        self._init_state()

    # ------------------------------------------------------------------ state
    def _init_state(self) -> None:
        self.intake = Intake(self._settings, list(self.config.joints) or
                             list(self._learner.joint_names()), self._learner.needs_position)
        self.clock = LearningClock()
        self._last_est = None               # the newest Estimate (or batch of Answers)
        self.health = Health()
        self.stream: Optional[StreamPart] = None    # made at the first accepted message

    def _stream_for(self, N: int) -> Optional[StreamPart]:
        """Return the stream part where it belongs (``StreamPart.belongs``), made for N."""
        if not StreamPart.belongs(self.config):
            self.stream = None
        elif self.stream is None or self.stream.N != N:
            self.stream = StreamPart(N)
        return self.stream

    def _settings(self) -> EstimatorConfig:
        return self.config

    def set_outputs(self, stddev: bool = True, damping: bool = True,
                    residuals: bool = True) -> None:
        """
        Which optional parts of an estimate to compute (the node: what has subscribers).

        Without ``stddev`` an Estimate's stddev is NaN; without ``damping`` its D is None;
        without ``residuals`` a learner process does not send its residual samples back. The
        force, its power and its passivity are always computed.
        """
        stddev, damping, residuals = bool(stddev), bool(damping), bool(residuals)
        if stddev != self._want_stddev:
            self._learner.set_variance(stddev)
        if residuals != self._want_residuals:
            self._learner.set_residuals(residuals)
        self._want_stddev, self._want_damping = stddev, damping
        self._want_residuals = residuals

    def set_source(self, source: str) -> None:
        """
        Say where the messages come from: 'live' (default) or 'bag'.

        It names the cause of stamp gaps on /diagnostics (a recorded log's own holes vs.
        messages lost on the way).
        """
        if source not in ('live', 'bag'):
            raise ValueError(f"source must be 'live' or 'bag', got {source!r}")
        self.health.source = source

    def note_lost(self, count: int) -> None:
        """Count messages the middleware reported lost (its message-lost event)."""
        self.health.messages_lost += int(count)

    @property
    def load_error(self) -> str:
        return self._learner.load_error

    @property
    def learner(self):
        """Return what learns: a ``Learner``, or a ``LearnerProcess`` in process mode."""
        return self._learner

    @property
    def trained(self) -> bool:
        return self.model is not None

    @property
    def model(self):
        """
        Get the model answers come from now, None before the first fit.

        Do not mutate it (with ``refit_mode='process'`` it is a predict-only snapshot).
        """
        s = self._learner.snapshot(self._want_stddev)
        return None if s is None else s.model

    def rigid_body_correction(self, q) -> Optional[np.ndarray]:
        """
        Return the current model's conservative correction of the rigid-body model at q (N,).

        ``dV/dq(q)`` [N m] (the payload's gravity the URDF lacks), without the offsets (see
        ``dynamics.conservative.Correction.conservative``), in the estimator's joint order; None
        when the model has none (no fit yet, no inverse dynamics, a fixed prior).
        """
        corr = getattr(self.model, 'correction_', None)
        if corr is None or not getattr(corr, 'needs_position', False):
            return None
        return corr.conservative(np.asarray(q, dtype=float))[0]

    @property
    def names(self) -> Optional[List[str]]:
        return self.intake.names

    def samples(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return copies of the buffered samples, (Qd, Tau), (n, N) each, oldest first."""
        return self._learner.samples()

    def refit_running(self) -> bool:
        return self._learner.refit_running()

    # ------------------------------------------------------------------ messages
    def process(self, stamp_s: float, names: Sequence[str], velocity, effort,
                position=None) -> Optional[Estimate]:
        """
        Validate one measurement, learn from it, return the estimate at its velocity.

        Never raises on bad input: returns None and counts the rejection reason.
        """
        return self.process_batch([(stamp_s, names, velocity, effort, position)])[0]

    def process_batch(self, messages: Sequence[tuple]) -> List[Optional[Estimate]]:
        """
        Process messages ``(stamp_s, names, velocity, effort, position)`` in order.

        Each is validated and answered as ``process`` does, from the model *before* it learned
        the message (as in the node, whose learner takes a message after its answer): the
        accepted ones together (one vectorized prediction), then they are handed to the
        learner; in line (``sync``) one by one, so that each answer comes from the model that
        learned every message before it. Returns one Estimate (or None) each: the rows of the
        answers ``_respond`` gives (the node's, ``process_arrays``).
        """
        t0 = time.perf_counter()
        out: List[Optional[Estimate]] = [None] * len(messages)
        with self._lock:
            accepted = []
            for i, m in enumerate(messages):
                s = self._accept(*m)
                if s is not None:
                    accepted.append((i,) + s)
            groups = ([[a] for a in accepted] if self.config.refit_mode == 'sync'
                      else [accepted] if accepted else [])
            for group in groups:
                q = None if group[0][5] is None else np.array([m[5] for m in group])
                a, taken, learned, late = self._respond(
                    tuple(self.intake.names or ()), np.array([m[0] for m in group]),
                    np.array([m[1] for m in group], float), np.array([m[3] for m in group]),
                    np.array([m[4] for m in group]), q, t0)
                for j, (i, stamp, names, qd, tau, _) in enumerate(group):
                    out[i] = Estimate(stamp, list(names) if names else [], qd, tau,
                                      a.tau_hat[j], a.stddev[j],
                                      None if a.D is None else a.D[j], float(a.power[j]),
                                      float(a.measured_power[j]), a.source[j], taken[j],
                                      a.processing_time_s, learned[j],
                                      None if a.confidence is None else a.confidence[j])
                if late:
                    out[group[-1][0]].residuals = list(learned[-1]) + late
                self._last_est = out[group[-1][0]]
        return out

    def _accept(self, stamp_s, names, velocity, effort, position):
        """Validate one message (counted); (stamp, names, qd, tau, q) or None if rejected."""
        h, intake = self.health, self.intake
        h.messages_received += 1
        try:
            stamp = float(stamp_s)
        except (TypeError, ValueError, OverflowError):
            stamp = float('nan')
        sel = intake.check(names, velocity, effort, position)
        if isinstance(sel, str):            # content problems are reported first
            h.reject(sel)
            return None
        if not math.isfinite(stamp) or stamp < 0.0:     # before the epoch / sim start
            h.reject('bad_stamp')
            return None
        names, qd, tau, q = sel
        h.gaps.note(stamp)
        why = intake.admit(qd, names)
        if why:
            h.reject(why)
            return None
        h.accept()
        if intake.name(names):
            self._learner.set_joint_names(intake.names)     # the correction basis needs them
        return stamp, names, qd, tau, q

    # ------------------------------------------------------------------ arrays
    def process_arrays(self, sec: np.ndarray, nsec: np.ndarray, names: tuple,
                       velocity: np.ndarray, effort: np.ndarray,
                       position: Optional[np.ndarray] = None) -> Optional[Answers]:
        """
        ``process_batch`` for k messages with the same names and array lengths, as arrays.

        sec, nsec : (k,) integer stamps (``header.stamp``); names : (n,) the messages' joint
        names; velocity, effort : (k, n); position : (k, n) or None (the messages have none).
        Returns the answers of the accepted messages (their ``rows``); None when the batch
        must take the per-message path (nothing was counted or learned then): ``sync`` (one
        answer per model), before the first accepted message (the joints are not known yet),
        messages without names or with arrays of other lengths. What is learned and answered
        is exactly what ``process_batch`` learns and answers for the same messages.
        """
        t0 = time.perf_counter()
        if self.config.refit_mode == 'sync' or \
                not self.intake.batch_ready(names, velocity, effort, position):
            return None
        with self._lock:
            N, joints = self.intake.N, tuple(self.intake.names)
            reasons, stamps, acc = self.intake.check_batch(sec, nsec, names, velocity, effort,
                                                           position)
            if reasons is None:                 # every message accepted (the usual case)
                rows = np.arange(len(stamps))
            else:
                ok = reasons == ''
                rows = np.flatnonzero(ok)
                stamps = stamps[ok]
            self.health.count_batch(reasons, stamps)
            qd, tau, q = acc if acc is not None else (np.zeros((0, N)),) * 2 + (None,)
            if not rows.size:
                e = np.zeros((0, N))
                return Answers(rows, joints, stamps[:0], e, e, None, e, e, None, np.zeros(0),
                               np.zeros(0), np.zeros(0, dtype=object),
                               time.perf_counter() - t0, [])
            return self._respond(joints, rows, stamps, qd, tau, q, t0)[0]

    # ------------------------------------------------------------------ answers
    def _respond(self, joints: tuple, rows: np.ndarray, stamps: np.ndarray, qd: np.ndarray,
                 tau: np.ndarray, q: Optional[np.ndarray], t0: float):
        """
        Answer k accepted messages and learn them: the one answer step of every entry point.

        joints : the answers' joint names; rows : (k,) the messages' places in their batch;
        stamps : (k,) [s]; qd, tau : (k, N) velocity [rad/s] and joint torque [N m] in the
        joint order; q : (k, N) position [rad] or None; t0 : the batch's start
        (``time.perf_counter``). The answers come from the snapshot taken *before* the messages
        are learned (one vectorized prediction, ``_estimate``), then the learner takes them
        (``learn_many``). Returns (``Answers``, the k ``learn`` flags, the k lists of residual
        samples each completed, the residual samples the learner completed beyond those:
        ``take_residuals``); ``Answers.residuals`` holds the k lists' and then the latter.
        """
        snap = self._learner.snapshot(self._want_stddev)
        pred, part = self._estimate(snap, qd)
        taken, learned = self._learner.learn_many(self.clock.times(stamps), qd, tau, q)
        if part is not None:
            self.stream.learn(stamps, qd, tau, *part, pred[0], self._lag(snap))
        tau_hat, std, D, source, conf = pred
        # one dot product per answer (what a controller computes for one message)
        power = np.array([a @ b for a, b in zip(qd, tau_hat)])
        if self.config.passivity != 'none':
            power[power < 0.0] = 0.0    # rounding only (the gate replaced the others)
        measured = np.array([a @ b for a, b in zip(qd, tau)])
        late = self._learner.take_residuals()
        residuals = [r for rs in learned for r in rs] + late
        dt = time.perf_counter() - t0
        a = Answers(rows, joints, stamps, qd, tau, q, tau_hat, std, D, power, measured, source,
                    dt, residuals, conf)
        self.health.latencies.extend([dt] * len(rows))
        self._last_est = a
        return a, taken, learned, late

    # ------------------------------------------------------------------ estimates
    def _estimate(self, snap: Optional[Snapshot], Q: np.ndarray):
        """
        Answer velocities Q (k, N) from ``snap`` (the gate) and the stream part.

        Returns ((tau_hat, std, D, source, confidence), part: ``StreamPart.weigh_answers``'s, or
        None without a stream part) and counts the answers' guarantee:
        the served model's, 'pointwise' where the stream part has a share (its projection).
        """
        pred = answer(snap, Q, self._want_stddev, self._want_damping, self.config.passivity,
                      self.health, self._learner.note_error, self._plans)
        stream = self._stream_for(Q.shape[1])
        out, part = (pred, None) if stream is None else stream.weigh_answers(pred, Q)
        g = guarantee(snap, self.config.passivity)
        if out[0] is not pred[0] and g != 'none':
            g = 'pointwise'
        self.health.answered(g, Q.shape[0])
        return out, part

    def _lag(self, snap: Optional[Snapshot]) -> float:
        """Return how far (s of learning time) ``snap`` lags behind the newest message."""
        if snap is None or snap.learned_through is None or self.clock.last is None:
            return 0.0
        return max(0.0, self.clock.last - float(snap.learned_through))

    def predict(self, Qs) -> np.ndarray:
        """Estimates (k, N) at velocities Qs with the rules of ``process`` (no learning)."""
        Qs = np.atleast_2d(np.asarray(Qs, dtype=float))
        with self._lock:
            snap = self._learner.snapshot(self._want_stddev)
            # the force only: the lean pass (no variance, no damping matrix)
            pred = answer(snap, Qs, False, False, self.config.passivity, self.health,
                          self._learner.note_error, self._plans)
            if self.stream is None:
                return pred[0]
            return self.stream.weigh(Qs, pred[0], None)[0]

    # ------------------------------------------------------------------ learner control
    def request_refit(self) -> Tuple[bool, str]:
        """Refit now (in the background unless ``refit_mode='sync'``). Returns (ok, message)."""
        return self._learner.request_refit()

    def request_refit_async(self, done: Callable[[Tuple[bool, str]], None]) -> None:
        """
        ``request_refit`` without waiting for a learner process: ``done((ok, message))``.

        A learner process replies through its receiver thread (so ``done`` may run in another
        thread); an in-process learner answers at once, in this thread.
        """
        f = getattr(self._learner, 'request_refit_async', None)
        if f is None:
            done(self._learner.request_refit())
        else:
            f(done)

    def wait_for_refit(self, timeout: Optional[float] = None) -> bool:
        """Block until no refit is running; True if none is running at return."""
        return self._learner.wait_for_refit(timeout)

    def close(self, timeout: float = 30.0) -> None:
        """Wait (bounded) for a running refit, stop a learner process; call before exit."""
        self._learner.close(timeout)

    def reset(self) -> None:
        """Forget the model, the buffer and all counters (a running refit is discarded)."""
        if self.config.refit_mode == 'process':
            # the learner process's reply is waited for outside the message path's lock
            self._learner.reset()
            with self._lock:
                self._init_state()
            return
        with self._lock:
            self._learner.reset()
            self._init_state()

    def check_reconfigure(self, config: EstimatorConfig) -> None:
        """Raise ValueError (with the reason) if ``reconfigure(config)`` would fail."""
        config = dataclasses.replace(config).validate()
        if self.intake.N is not None:
            config.check_dimension(self.intake.N)
        self._learner.check_reconfigure(config)

    def reconfigure(self, config: EstimatorConfig) -> str:
        """Apply a new validated config; structural changes drop the model and refit."""
        config = dataclasses.replace(config).validate()
        if self.intake.N is not None:
            config.check_dimension(self.intake.N)
        with self._lock:
            what = self._learner.reconfigure(config)
            old, self.config = self.config, config
            if any(getattr(old, f) != getattr(config, f) for f in FRONT_END):
                health = self.health
                self._init_state()
                self.health = health
        return what

    def save(self, path: Optional[str] = None, learn_waiting: bool = True) -> str:
        """
        Save the current model atomically to ``path`` (default ``model_path``); returns it.

        ``learn_waiting``: first learn the samples still on their way to a learner process
        (False at a shutdown: what it learned by then).
        """
        return self._learner.save(path, learn_waiting=learn_waiting)

    def set_learning(self, on: bool) -> str:
        """
        Switch learning on or off: ``reconfigure`` with ``learning`` changed (online.switch).

        Off: the model is proven and saved (to ``model_path`` when set) in the learner's job,
        then served as it is; ``diagnostics()['learning']`` is 'stopping' until then, 'off'
        afterwards. Returns what was done.
        """
        return self.reconfigure(dataclasses.replace(self.config, learning=bool(on)))

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self) -> dict:
        """
        Everything the node publishes on /diagnostics, as a dict.

        ``level`` is OK/WARN/ERROR (0/1/2, diagnostic_msgs values) and ``message`` joins the
        reasons (see ``health.Health.status``).
        """
        learner = self._learner.status()
        with self._lock:
            last = last_estimate(self._last_est)
            d = {'model': self.config.model, 'passivity': self.config.passivity,
                 'measured_power': last.measured_power if last else float('nan'),
                 'estimated_power': last.power if last else float('nan'),
                 'last_source': last.source if last else '',
                 'buffer_size': self.config.buffer_size,
                 'learning_clock': 'arrival' if self.clock.on_arrival else 'stamp'}
            d.update({k: v for k, v in learner.items()
                      if k not in ('warnings', 'version', 'refit_durations')})
            d.update(self.health.counters())
            if self._plans.mismatches:
                # the lean pass disagreed with the model (answers came from the model)
                d['answer_plan_mismatches'] = self._plans.mismatches
            warnings = list(learner.get('warnings', []))
            if self.stream is not None:
                d.update(self.stream.status())
                warnings += self.stream.verdict()
            if self.clock.on_arrival:
                warnings.insert(0, 'message stamps do not advance (header.stamp constant or 0): '
                                "learning uses the arrival time; fix the driver's stamps")
            state = {'trained': d.get('trained', False), 'fill': d.get('buffer_fill', 0),
                     'min_samples': self.config.min_samples,
                     'certifies': policy_class(self.config.passivity).certifies,
                     'certified': d.get('certified', False),
                     'stale': d.get('certificate_stale', False),
                     'learning': d.get('learning', 'on'),
                     'load_error': d.get('load_error', ''), 'warnings': warnings}
            d['level'], d['message'] = self.health.status(learner, state)
            return d

    def refit_durations(self) -> List[float]:
        """Wall seconds of the learner's recent refit jobs (at most 1000), oldest first."""
        return list(self._learner.status().get('refit_durations', []))

    def negative_power_fraction(self) -> Optional[float]:
        """Fraction of the recent learned samples with ``qd . target < 0`` (None: too few)."""
        return self._learner.status().get('negative_power_fraction')

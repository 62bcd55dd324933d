"""
The learner process's loop (no rclpy): samples in from the ring, snapshots and replies out.

Run by :func:`child_main`, the entry point of the child that
:class:`~dgp_ros.online.process.LearnerProcess` starts (this module does not import that one).
One thread takes every sample waiting in the ring, feeds them to the
:class:`~dgp_ros.online.learner.Learner` (whose refit and re-proof jobs run in a thread of their
own beside it), answers commands, and sends a snapshot whenever the learner's version changed (at
most every ``SNAPSHOT_PERIOD_S``), its status, and the residual samples it completed. It stops on
a 'stop' command or when the node's pipe closes.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import time
import traceback

import numpy as np

from .ring import SampleRing
from ..config import EstimatorConfig
from ..learner.grounds import GAINS
from ..learner.learner import Learner
from ..learner.plan import PlanCache
from ..memtrace import bound_heap, start_from_env as trace_memory, trim, TRIM_PERIOD_S

__all__ = ['LearnerLoop', 'child_main']


class LearnerLoop:
    """One learner process's work (module docstring); arguments as ``child_main``."""

    IDLE_WAIT_S = 0.002
    #: no sample for this long: the stream has paused (a stale certificate is re-proven)
    PAUSE_S = 0.3
    #: learning time per round (s): commands are read and snapshots sent between rounds
    ROUND_S = 0.01
    #: more than this many rounds' worth of samples waiting, and more than this much stamp
    #: time (s): the learner is behind and learns the newest ones thinned (``_samples``),
    #: taking at most this many rows at once
    BEHIND_ROUNDS, BEHIND_S, MAX_TAKE = 20, 5.0, 20000
    #: longest catch-up before a command that must see the samples sent before it (s)
    DRAIN_S = 0.05
    #: ... and before a save, which learns every row sent before it (``SampleRing.mark``):
    #: a learner short of CPU was 5 s of stamps behind its stream, and the model the demo
    #: saved "after 9.5 s" had learned its first 4 s (held out NMSE 1.3-1.6 against 6e-4);
    #: bounded well inside the node's reply timeout (``LearnerProcess.REPLY_TIMEOUT_S``)
    SAVE_DRAIN_S = 10.0
    #: snapshots back to the node: at most one per period (s), and at most this many bytes/s
    #: (a 60 Hz stream gets each sample's snapshot before the next message: at 20 ms every
    #: other answer came from a model two samples old)
    SNAPSHOT_PERIOD_S = 0.005
    SNAPSHOT_BYTES_PER_S = 100e6
    #: ... and at most this share of the learner's wall time goes to sending them: a learner
    #: short of CPU (two busy processes beside it: 5-10 % of a core) spent 3.7 ms of CPU per
    #: snapshot at 54 a second, more than it had, and fell behind the stream; with the
    #: period at least (1 - share) / share x a snapshot's wall time it keeps up, its
    #: snapshots fewer and each as fresh as it can be
    SNAPSHOT_SHARE = 0.25
    #: the status is sent at least this often (s)
    STATUS_PERIOD_S = 0.25
    #: gains that changed without a new model are sent at most this often (s)
    GAINS_PERIOD_S = 0.05

    def __init__(self, cfg: dict, cmd, out, lock, ring_info, init, variance: bool,
                 residuals: bool, sched: str = ''):
        self.cmd, self.out, self.lock = cmd, out, lock
        self.sched = sched              # what ``lower_priority`` got (the status says it)
        self.variance, self.residuals = variance, residuals
        self.ring = None
        self.sent_version = -1
        self.sent_gains = -1            # the learner's gains_seq the node has
        self.gains_at = 0.0             # when gains alone were last sent
        self.rejected_at = 0            # absorbs_rejected when the last 'wait' came
        self.waits = []                 # (id, wall deadline) of 'wait' commands
        self.sent_at = self.status_at = 0.0
        self.row_s = 1e-4               # learning seconds per sample (moving average)
        self.row_dt = 0.0               # stamp seconds between samples (moving average)
        self.sample_at = time.monotonic()   # when the last samples were taken from the ring
        self.period = self.SNAPSHOT_PERIOD_S
        self.plans = PlanCache()        # the answer plans sent with the snapshots
        try:
            config = dataclasses.replace(EstimatorConfig.from_dict(cfg), refit_mode='async')
            self.learner = Learner(config)
            self.learner.append_each = False      # appended per round below, as one block
            if init is not None and init.model is not None:   # newer than the last file
                self.learner.adopt(init.model, 'the last snapshot')
            if init is not None and init.residual_bound is not None:
                self.learner.restore_residual_bound(init.residual_bound)
            if init is not None:
                self.learner.restore_gains(getattr(init, 'model_weight', None),
                                           getattr(init, 'prior_gain', None),
                                           getattr(init, 'confidence', None))
        except Exception as exc:        # noqa: BLE001 - the node reports it and exits 2
            self.learner = None
            self.out.send(('error', f'{exc}'))
            return
        if ring_info is not None:
            self._attach(*ring_info)
        L = self.learner
        snap = L.snapshot(variance=variance, frozen=True)
        self.sent_version = L.version if snap is not None else -1
        self.sent_gains = L.gains_seq
        self.out.send(('ready', {'joint_names': L.joint_names(),
                                 'needs_position': L.needs_position,
                                 'load_error': L.load_error, 'snapshot': snap,
                                 'status': self._status()}))

    def _attach(self, name, width, capacity) -> None:
        self.ring = SampleRing(width, capacity, self.lock, name=name)

    # ------------------------------------------------------------------ loop
    #: ``DGP_LEARNER_PROFILE=PREFIX``: cProfile the loop, one file per this many seconds
    PROFILE_WINDOW_S = 20.0

    def _profile_window(self, prof):
        """Dump a profile window to ``PREFIX.K.prof`` when it is over; return the profile."""
        prefix = os.environ.get('DGP_LEARNER_PROFILE', '')
        if not prefix:
            return None
        import cProfile
        now = time.monotonic()
        if prof is None:
            self._prof_k, self._prof_t = 0, now
            prof = cProfile.Profile()
            prof.enable()
        elif now - self._prof_t >= self.PROFILE_WINDOW_S or now < 0:
            prof.disable()
            prof.dump_stats(f'{prefix}.{self._prof_k}.prof')
            self._prof_k, self._prof_t = self._prof_k + 1, now
            prof = cProfile.Profile()
            prof.enable()
        return prof

    def run(self) -> None:
        if self.learner is None:
            return
        prof = None
        trimmed = time.monotonic()
        try:
            while True:
                prof = self._profile_window(prof)
                if time.monotonic() - trimmed >= TRIM_PERIOD_S:
                    trim()                  # the freed heap back to the system (memtrace)
                    trimmed = time.monotonic()
                if not self._commands():
                    break
                busy = self._samples()
                if not busy:
                    self.learner.poll(idle=time.monotonic() - self.sample_at >= self.PAUSE_S)
                self._publish()
                if not busy:
                    self.cmd.poll(self.IDLE_WAIT_S)
        except (EOFError, OSError, BrokenPipeError):
            pass                          # the node is gone
        finally:
            if prof is not None:
                prof.disable()
                prof.dump_stats(f'{os.environ["DGP_LEARNER_PROFILE"]}.{self._prof_k}.prof')
            if self.ring is not None:
                self.ring.close()

    def _samples(self) -> bool:
        """
        Learn the samples waiting, for about ``ROUND_S``; True if there were any.

        A learner that cannot keep up (a stream faster than real time, a learner short of CPU)
        learns the newest samples thinned, not the old ones in full: where more than
        ``BEHIND_ROUNDS`` rounds' and ``BEHIND_S`` seconds of stamps wait, it takes them all (up
        to ``MAX_TAKE``) and learns one in k of the samples the front end gives, the newest
        measurement always (the others pass the front end only, counted as
        ``samples_thinned``), so that its model follows the stream at a lower rate instead of
        falling behind it. Beside two busy processes, the A320 at 4x real time was learning
        samples from 30 s before with two refits in its whole flight (one-step NMSE 3-4 over
        the flight). A burst of a second or two (a bag's first messages, a test's) is learned
        in full.
        """
        if self.ring is None:
            return False
        want = max(1, int(self.ROUND_S / self.row_s))
        waiting = self.ring.pending(0.0) or 0
        behind = waiting > self.BEHIND_ROUNDS * want and waiting * self.row_dt > self.BEHIND_S
        rows = self.ring.take(min(waiting, self.MAX_TAKE) if behind else want)
        if rows.shape[0] > 1:           # the stream's stamp step (a moving average)
            self.row_dt = 0.9 * self.row_dt + 0.1 * max(float(np.median(np.diff(rows[:, 0]))),
                                                        0.0)
        L = self.learner
        k = max(1, -(-rows.shape[0] // want)) if behind else 1
        # a full round means more are waiting: rebase less often and append nothing until the
        # queue is drained (the rebases take the samples in then)
        L.rebases.backlog(rows.shape[0] >= want and k == 1)
        if not rows.shape[0]:
            L.catch_up_paused()             # the last samples of a backlog reach the model
            return False
        self.sample_at = time.monotonic()
        t0 = time.perf_counter()
        N = (rows.shape[1] - 1) // 3
        done = []
        n = rows.shape[0]
        for i, r in enumerate(rows):
            q = r[1 + 2 * N:]
            _, res = self.learner.learn(float(r[0]), r[1:1 + N].copy(),
                                        r[1 + N:1 + 2 * N].copy(),
                                        None if np.isnan(q[0]) else q.copy(),
                                        thin=k if i < n - 1 else 1)
            done.extend(res)
        if L.rebases.appending:
            # the round's samples reach the model at once (one block); while samples queue up
            # the rebases take them in instead: one refit per batch costs less
            L.catch_up()
        # the learning cost per learned row (a moving average, the appends included) sizes
        # the next round
        learned = max(1, -(-n // k))
        self.row_s = 0.8 * self.row_s + 0.2 * (time.perf_counter() - t0) / learned
        if done and self.residuals:
            self.out.send(('residuals', done))
        return True

    def _drain(self, mark=None) -> None:
        """
        Learn what was sent before a command (bounded by ``DRAIN_S``).

        ``mark``: the ring's producer index when the command was sent (a save's): every row
        before it is learned, bounded by ``SAVE_DRAIN_S``.
        """
        full = mark is not None and self.ring is not None
        end = time.monotonic() + (self.SAVE_DRAIN_S if full else self.DRAIN_S)
        while time.monotonic() < end:
            if full and self.ring.taken >= mark:
                return
            if not self._samples():
                if not full:
                    return
                time.sleep(self.IDLE_WAIT_S)    # rows the node still holds (its backlog)

    def _publish(self) -> None:
        now = time.monotonic()
        L = self.learner
        if L.version != self.sent_version and now - self.sent_at >= self.period:
            snap = L.snapshot(variance=self.variance, frozen=True)
            if snap is not None:
                if snap.model is not None:
                    # the answer plan is built and checked here: the node's receiver only
                    # unpickles it (its thread holds the GIL the message path needs)
                    snap = dataclasses.replace(snap, plan=self.plans.build(snap.model))
                self.out.send(('snapshot', snap))
                self.sent_version, self.sent_at = snap.version, now
                self.sent_gains = L.gains_seq
                n, N = (0, 0) if snap.model is None else snap.model.posterior_.X.shape
                size = 8.0 * n * N * (4 + (n if self.variance else 0))
                cost = time.monotonic() - now            # wall time of this snapshot
                share = (1.0 - self.SNAPSHOT_SHARE) / self.SNAPSHOT_SHARE
                self.period = max(self.SNAPSHOT_PERIOD_S, size / self.SNAPSHOT_BYTES_PER_S,
                                  share * cost)
        elif L.gains_seq != self.sent_gains and L.version == self.sent_version and \
                (self.waits or now - self.gains_at >= self.GAINS_PERIOD_S):
            # the same model with newer gains: only they travel (the node swaps them in)
            snap = L.snapshot(variance=self.variance, frozen=True)
            if snap is not None:
                self.out.send(('gains', snap.version, {k: getattr(snap, k) for k in GAINS}))
            self.sent_gains, self.gains_at = L.gains_seq, now
        if self.waits and self._settled():
            self.out.send(('status', self._status()))        # arrives before the reply
            self.status_at = now
            for i, _ in self.waits:
                self.out.send(('reply', i, True, self.sent_version))
            self.waits = []
        elif self.waits:
            keep = []
            for i, deadline in self.waits:
                if time.time() > deadline:
                    self.out.send(('reply', i, False, 'timeout'))
                else:
                    keep.append((i, deadline))
            self.waits = keep
        if now - self.status_at >= self.STATUS_PERIOD_S:
            self.out.send(('status', self._status()))
            self.status_at = now

    def _settled(self) -> bool:
        """
        Tell whether the learner has caught up (a 'wait' is answered then).

        Every sample sent is learned and held by the model (appended, or taken in by a rebase),
        no job runs or is wanted (a rebase waits for its cost to allow it; one that failed
        since the 'wait' came is not waited for), and the node has the newest snapshot and
        gains.
        """
        L = self.learner
        # a caller waiting for the learner to settle has paused the stream; what became due
        # since this round's poll starts now
        L.poll(idle=True)
        if L.refit_running() or L.version != self.sent_version or \
                L.gains_seq != self.sent_gains:
            return False
        if L.config.learning and (L.unheld or L.rebases.wanted(L.parts())) and \
                L.health.absorbs_rejected == self.rejected_at:
            return False                 # (a running rebase is still wanted until it ends)
        return self.ring is None or self.ring.pending(timeout=0) == 0

    def _status(self) -> dict:
        d = self.learner.status()
        d['learner_sched'] = self.sched
        if d.get('learning') == 'off' and self.learner.version != self.sent_version:
            # 'off' means the node answers from the frozen model: not before it holds it
            d['learning'] = 'stopping'
        return d

    # ------------------------------------------------------------------ commands
    def _commands(self) -> bool:
        """Handle every command waiting; False on 'stop' (after a bounded wait for a job)."""
        while self.cmd.poll():
            msg = self.cmd.recv()
            kind = msg[0]
            if kind == 'stop':
                self.learner.close(msg[1] if len(msg) > 1 else 5.0)
                return False
            if kind == 'ring':
                self._attach(*msg[1:])
            elif kind == 'variance':
                self.variance = bool(msg[1])
                self.sent_version = -1           # the next snapshot carries what is wanted
            elif kind == 'residuals':
                self.residuals = bool(msg[1])
            elif kind == 'names':
                self.learner.set_joint_names(msg[1])
            elif kind == 'wait':
                self._drain()
                self.waits.append((msg[1], msg[2]))
                self.rejected_at = self.learner.health.absorbs_rejected
                self.sent_at = 0.0               # publish the newest at once
            else:
                if kind in ('refit', 'save', 'samples', 'reconfigure'):
                    # they act on what was sent before them
                    self._drain(msg[3] if kind == 'save' else None)   # (a save's mark)
                self._reply(kind, msg[1], msg[2:])
        return True

    def _reply(self, kind: str, i: int, args: tuple) -> None:
        L = self.learner
        try:
            if kind == 'refit':
                ok, what = L.request_refit()
            elif kind == 'save':
                ok, what = True, L.save(args[0])
            elif kind == 'reset':
                if args and args[0] is not None and self.ring is not None:
                    self.ring.skip_to(args[0])      # the samples sent before the reset
                L.reset()
                ok, what = True, 'reset'
            elif kind == 'check':
                L.check_reconfigure(self._config(args[0]))
                ok, what = True, ''
            elif kind == 'reconfigure':
                ok, what = True, (L.reconfigure(self._config(args[0])), L.joint_names(),
                                  L.needs_position)
            elif kind == 'samples':
                ok, what = True, L.samples()
            else:
                ok, what = False, f'unknown command {kind!r}'
        except (ValueError, RuntimeError, OSError) as exc:
            ok, what = False, f'{type(exc).__name__}: {exc}'
        except Exception as exc:            # noqa: BLE001 - report, never die on a command
            ok, what = False, f'{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}'
        # the state the command left arrives before its reply
        if L.version != self.sent_version or L.gains_seq != self.sent_gains:
            self.out.send(('snapshot', L.snapshot(variance=self.variance, frozen=True)))
            self.sent_version, self.sent_at = L.version, time.monotonic()
            self.sent_gains = L.gains_seq
        self.out.send(('status', self._status()))
        self.out.send(('reply', i, ok, what))

    @staticmethod
    def _config(d: dict) -> EstimatorConfig:
        return dataclasses.replace(EstimatorConfig.from_dict(d), refit_mode='async')


#: the learner's scheduling: 'idle' (SCHED_IDLE where allowed, else nice) or 'nice'
SCHED_CHOICES = ('idle', 'nice')


def lower_priority(sched: str, nice: int) -> str:
    """
    Put this process below the message path; return what it got ('idle' or 'nice N').

    'idle': ``SCHED_IDLE`` (it runs only when no other process of the machine wants the CPU: the
    node's wake-ups never wait for it, and with no idle CPU it learns less, never answers late),
    falling back to ``os.nice(nice)`` where the OS refuses it; 'nice': ``os.nice(nice)`` only.
    """
    if sched not in SCHED_CHOICES:
        raise ValueError(f'learner scheduling {sched!r}: one of ' + ', '.join(SCHED_CHOICES))
    if sched == 'idle' and hasattr(os, 'SCHED_IDLE'):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return 'idle'
        except (OSError, AttributeError):
            pass
    try:
        got = os.nice(nice)
    except OSError:
        return 'normal'
    return f'nice {got}'


def child_main(cfg: dict, cmd, out, lock, ring_info, init, nice: int, variance: bool,
               residuals: bool, sched: str = 'nice') -> None:
    """Run a Learner on the ring's samples: the child process (module docstring)."""
    # Ctrl-C and a SIGTERM to the process group are the node's to handle: it saves through
    # this process, then stops it. The child ends when the node's pipe closes (the node died).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    got = lower_priority(sched, nice)
    bound_heap()                 # large blocks in mappings of their own, not in arenas
    trace_memory('learner')      # a soak's tracemalloc (DGP_TRACEMALLOC), else none
    LearnerLoop(cfg, cmd, out, lock, ring_info, init, variance, residuals, got).run()


def raise_reply(what: str) -> None:
    """Raise a command's 'ValueError: ...' or 'RuntimeError: ...' reply as that type."""
    kind, _, text = what.partition(': ')
    raise (RuntimeError if kind == 'RuntimeError' else ValueError)(
        text if kind in ('ValueError', 'RuntimeError') else what)


def describe_exit(code) -> str:
    """Say how a learner process ended, from its exit code."""
    if code is None:
        return 'no exit status'
    if code < 0:
        try:
            return f'killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'killed by signal {-code}'
    return f'exit code {code}'

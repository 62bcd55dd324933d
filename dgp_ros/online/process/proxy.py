"""
The learner in a child process: what the node's message path talks to (no rclpy).

:class:`LearnerProcess` has the interface of :class:`~dgp_ros.online.learner.Learner` that the
message path uses, and runs a real ``Learner`` in a child process at a lower scheduling priority:

* samples go through a bounded shared-memory ring (``ring.SampleRing``): a push never waits for
  the learner; a full ring drops the sample and counts it (``samples_dropped``);
* the child sends back immutable snapshots (``Learner.snapshot(frozen=True)``: a predict-only
  model, pickled) at most every ``SNAPSHOT_PERIOD_S``, and less often when they are large (the
  Cholesky factors for the variance are ``8 N n^2`` bytes: at most ``SNAPSHOT_BYTES_PER_S``),
  its status every ``STATUS_PERIOD_S`` (all three of ``child.LearnerLoop``), and the friction
  residual samples it completed; a receiver thread here installs them by reference assignment;
* commands (refit, save, reset, reconfigure, ...) go through a pipe and are answered by id.

The child is forked from a ``forkserver`` (learner modules preloaded), never from the node
process, whose DDS threads a fork would copy inconsistently. It ignores SIGINT and SIGTERM (the
node decides: it saves through the child, then stops it) and exits when the node's pipe closes.
If it dies, the receiver thread counts it, says why (``status``) and starts a new one from the
last snapshot's model: the answers never stop (docs/ARCHITECTURE.md, "The learner process").
"""
from __future__ import annotations

from collections import deque
import dataclasses
import multiprocessing
from multiprocessing.reduction import ForkingPickler
import os
import signal
import threading
import time
from typing import Optional, Tuple

import numpy as np

from .child import child_main, describe_exit, raise_reply, SCHED_CHOICES
from .commands import Calls
from .ring import SampleRing
from ..config import EstimatorConfig
from ..learner.snapshot import SwapLog

__all__ = ['LearnerProcess']

_CTX = None


def _context():
    """Return the fork-server context; its server preloads the learner (started on first use)."""
    global _CTX
    if _CTX is None:
        ctx = multiprocessing.get_context('forkserver')
        ctx.set_forkserver_preload(['dgp_ros.online.learner.learner'])
        _CTX = ctx
    return _CTX


class LearnerProcess:
    """
    A :class:`~dgp_ros.online.learner.Learner` in a child process (module docstring).

    Parameters
    ----------
    config : EstimatorConfig
        The learner's configuration (its ``refit_mode`` is replaced by 'async' in the child:
        jobs there run in a thread beside the sample loop).
    nice : int
        Niceness increment of the child (``os.nice``) where it runs at nice.
    sched : str or None
        'idle' (``SCHED_IDLE`` where the OS allows it, else nice) or 'nice'; None: the
        environment's ``DGP_LEARNER_SCHED``, else 'nice'. ``status()['learner_sched']`` says
        what the child got.
    prepare : callable or None
        ``prepare(snapshot)``, called in the receiver thread before a new snapshot is installed:
        builds what answering from it needs (``PlanCache.prepare``) off the message path.

    Raises
    ------
    ValueError
        The child could not start the learner (with the child's reason).

    """

    RING_ROWS = 1 << 15                 # 33 s of a 1 kHz stream
    START_TIMEOUT_S = 120.0             # the first start also starts the fork server
    REPLY_TIMEOUT_S = 30.0

    def __init__(self, config: EstimatorConfig, nice: int = 10, sched: Optional[str] = None,
                 prepare=None):
        self.config = config
        self.nice = int(nice)
        sched = sched or os.environ.get('DGP_LEARNER_SCHED', '') or 'nice'
        if sched not in SCHED_CHOICES:
            raise ValueError(f'DGP_LEARNER_SCHED={sched!r}: one of ' + ', '.join(SCHED_CHOICES))
        self.sched = sched
        self.prepare = prepare
        self.swaps = SwapLog()
        self.calls = Calls(self.REPLY_TIMEOUT_S)
        self._snap = None
        self._status: dict = {}
        self._residuals: deque = deque(maxlen=10000)
        self._variance = True
        self._want_residuals = True
        self._N: Optional[int] = None
        self._ring: Optional[SampleRing] = None
        self._retired: Optional[SampleRing] = None
        self._closing = False
        self.samples_dropped = 0
        self.restarts = 0
        self.exit_reason = ''
        self._error = ''
        self._proc = None
        info = self._spawn(None, wait=True)
        self.joint_names_ = list(info.get('joint_names', []))
        self.needs_position = bool(info.get('needs_position', False))
        self.load_error = info.get('load_error', '')

    # ------------------------------------------------------------------ child life cycle
    def _spawn(self, init, wait: bool) -> dict:
        """
        Start a child (and its ring when N is known); returns its handshake info.

        init : the last snapshot (a restart: its model and what it learned about the data's
            range carry over) or None.
        """
        ctx = _context()
        lock = ctx.Lock()
        ring = None
        if self._N is not None:
            ring = SampleRing(1 + 3 * self._N, self.RING_ROWS, lock)
        cmd_r, cmd_w = ctx.Pipe(duplex=False)
        out_r, out_w = ctx.Pipe(duplex=False)
        _grow_pipe(out_w)
        cfg = dataclasses.asdict(self.config)
        ring_info = None if ring is None else (ring.name, ring.width, ring.capacity)
        proc = ctx.Process(target=child_main, name='dgp_learner', daemon=True,
                           args=(cfg, cmd_r, out_w, lock, ring_info, init, self.nice,
                                 self._variance, self._want_residuals, self.sched))
        proc.start()
        cmd_r.close()
        out_w.close()
        if getattr(self, '_names_hint', None):
            cmd_w.send(('names', self._names_hint))
        if not out_r.poll(self.START_TIMEOUT_S):
            proc.kill()
            raise ValueError('the learner process did not start within '
                             f'{self.START_TIMEOUT_S:.0f} s')
        try:
            kind, info = out_r.recv()
        except (EOFError, OSError):
            kind, info = 'error', f'the learner process exited at start (code {proc.exitcode})'
        if kind != 'ready':
            proc.join(5.0)
            raise ValueError(info)
        if info.get('snapshot') is not None:
            self._install(info['snapshot'], 0.0)
        self._status = info.get('status', {})
        old_ring = self._ring
        self._proc, self._cmd, self._out, self._lock_ring = proc, cmd_w, out_r, lock
        self._ring = ring
        # the message path may still be pushing into the old ring: it is closed one restart
        # later (unmapping it under a running push would crash the node)
        if self._retired is not None:
            self._retired.close()
        self._retired = old_ring
        self._rx = threading.Thread(target=self._receive, args=(proc, out_r),
                                    name='dgp_learner_rx', daemon=True)
        self._rx.start()
        return info

    def _receive(self, proc, conn) -> None:
        """Install what the child sends; restart it when it dies (unless closing)."""
        while True:
            try:
                buf = conn.recv_bytes()
                t0 = time.perf_counter()
                msg = ForkingPickler.loads(buf)      # what Connection.recv does, timed
                received = time.perf_counter() - t0
            except (EOFError, OSError):
                break
            except Exception as exc:     # noqa: BLE001 - an unreadable message: say so, go on
                self._error = f'learner message unreadable: {type(exc).__name__}: {exc}'
                continue
            kind = msg[0]
            if kind == 'snapshot':
                self._install(msg[1], received)
            elif kind == 'gains':           # the same model, with the gains earned since
                snap = self._snap
                if snap is not None and snap.version == msg[1]:
                    self._snap = dataclasses.replace(snap, **msg[2])
            elif kind == 'status':
                self._status = msg[1]
                ring = self._ring
                if ring is not None and ring.backlog:
                    ring.flush()           # rows kept while the learner held the lock
            elif kind == 'residuals':
                self._residuals.extend(msg[1])
            elif kind == 'reply':
                self.calls.deliver(msg[1], msg[2], msg[3])
        proc.join(1.0)
        if self._closing or proc is not self._proc:
            return
        code = proc.exitcode
        self.exit_reason = (f'learner process died ({describe_exit(code)}); restarted from '
                            'the last snapshot')
        self.calls.fail_all('the learner process died')
        while not self._closing:
            try:
                snap = self._snap
                self._spawn(snap, wait=True)
                self.restarts += 1
                return
            except Exception as exc:        # noqa: BLE001 - keep answering; retry in a while
                self.exit_reason = f'learner process could not be restarted: {exc}'
                time.sleep(1.0)

    def _install(self, snap, received: float) -> None:
        """Prepare a new snapshot here (the receiver thread), then swap it in by reference."""
        t0 = time.perf_counter()
        if self.prepare is not None and snap is not None:
            try:
                self.prepare(snap)
            except Exception as exc:     # noqa: BLE001 - the message path then builds it itself
                self._error = f'snapshot not prepared: {type(exc).__name__}: {exc}'
        self._snap = snap
        if snap is not None:
            self.swaps.note(snap.version, received, time.perf_counter() - t0)

    def _call(self, kind: str, *args, timeout: Optional[float] = None):
        """Send a command and wait for its reply (``Calls.call``)."""
        return self.calls.call(self._cmd.send, kind, *args, timeout=timeout)

    def _call_async(self, kind: str, done, *args, timeout: Optional[float] = None) -> None:
        """Send a command; ``done((ok, payload))`` gets its reply (``Calls.call_async``)."""
        self.calls.call_async(self._cmd.send, kind, done, *args, timeout=timeout)

    def _send(self, *msg) -> None:
        try:
            self._cmd.send(msg)
        except (OSError, ValueError):
            pass                          # a dead child: the restart sends the state again

    # ------------------------------------------------------------------ the Learner interface
    def joint_names(self) -> list:
        return list(self.joint_names_)

    def set_joint_names(self, names) -> None:
        """Tell the learner the joint names of the stream (kept for a restarted child)."""
        self._names_hint = list(names)
        self._send('names', self._names_hint)

    def set_variance(self, on: bool) -> None:
        self._variance = bool(on)
        self._send('variance', self._variance)

    def set_residuals(self, on: bool) -> None:
        self._want_residuals = bool(on)
        self._send('residuals', self._want_residuals)

    def learn(self, t: float, qd: np.ndarray, tau: np.ndarray, q=None) -> Tuple[bool, list]:
        """
        Hand one sample to the child (never waits); (queued, []).

        Learning off: only the samples the residual topic needs (inverse dynamics, subscribed).
        """
        if not self.config.learning and not (self.needs_position and self._want_residuals):
            return False, []
        if self._N is None:
            self._N = qd.size
            lock = self._lock_ring
            self._ring = SampleRing(1 + 3 * self._N, self.RING_ROWS, lock)
            self._send('ring', self._ring.name, self._ring.width, self._ring.capacity)
        ring = self._ring
        row = np.empty(1 + 3 * self._N)
        row[0] = t
        row[1:1 + self._N] = qd
        row[1 + self._N:1 + 2 * self._N] = tau
        row[1 + 2 * self._N:] = np.nan if q is None else q
        if ring is None or not ring.push(row):
            self.samples_dropped += 1
            return False, []
        return True, []

    def learn_many(self, t: np.ndarray, qd: np.ndarray, tau: np.ndarray,
                   q=None) -> Tuple[list, list]:
        """
        ``learn`` for k samples at once (t (k,) [s], qd and tau (k, N), q (k, N) or None).

        One push of the rows (``SampleRing.push_rows``: the same rows kept as k ``push``);
        unlike ``learn`` also with learning off (the child counts them as not learned).
        Returns (k flags: queued, a prefix; k empty lists, read-only: the child's residual
        samples come back through ``take_residuals``).
        """
        k = len(t)
        if k and self._N is None:                   # the first sample makes the ring
            n = int(self.learn(float(t[0]), qd[0], tau[0], None if q is None else q[0])[0])
            t, qd, tau, q = t[1:], qd[1:], tau[1:], None if q is None else q[1:]
            taken = [bool(n)]
        else:
            taken = []
        rows = np.concatenate((t[:, None], qd, tau, np.full_like(qd, np.nan) if q is None else q),
                              axis=1)
        ring = self._ring
        kept = ring.push_rows(rows) if ring is not None and len(t) else 0
        self.samples_dropped += len(t) - kept
        return taken + [True] * kept + [False] * (len(t) - kept), [[]] * k

    def snapshot(self, variance: bool = True):
        return self._snap

    def take_residuals(self) -> list:
        out = []
        while self._residuals:
            out.append(self._residuals.popleft())
        return out

    def note_error(self, message: str) -> None:
        self._error = message

    def samples(self):
        ok, payload = self._call('samples')
        if not ok:
            N = self._N or 0
            return np.zeros((0, N)), np.zeros((0, N))
        return payload

    def refit_running(self) -> bool:
        return bool(self._status.get('refit_running', False))

    def request_refit(self) -> Tuple[bool, str]:
        return self._call('refit')

    def request_refit_async(self, done) -> None:
        """``request_refit`` without waiting: ``done((ok, message))`` with the reply."""
        self._call_async('refit', done)

    def wait_for_refit(self, timeout: Optional[float] = None) -> bool:
        """
        Block until the child has caught up and its newest snapshot is installed.

        Caught up: every sample sent is learned and held by the model, no job runs, and the
        snapshot here carries the newest gains (``LearnerLoop._settled``). False on a timeout.
        """
        t = 3600.0 if timeout is None else float(timeout)
        ring = self._ring
        if ring is not None and ring.backlog:
            ring.flush(timeout=min(t, 1.0))      # the rows the learner has not seen yet
        ok, version = self._call('wait', time.time() + t, timeout=t + 5.0)
        if not ok:
            return False
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            s = self._snap
            if s is not None and s.version >= version:
                return True
            time.sleep(0.005)
        return False

    def reset(self) -> None:
        """Forget everything learned, the rows still in the ring included (``SampleRing.mark``)."""
        ring = self._ring
        self._call('reset', None if ring is None else ring.mark())

    def check_reconfigure(self, config: EstimatorConfig) -> None:
        ok, why = self._call('check', dataclasses.asdict(config))
        if not ok:
            raise_reply(why)

    def reconfigure(self, config: EstimatorConfig) -> str:
        ok, what = self._call('reconfigure', dataclasses.asdict(config))
        if not ok:
            raise_reply(what)
        self.config = config
        what, self.joint_names_, self.needs_position = what
        return what

    def save(self, path: Optional[str] = None, timeout: Optional[float] = None,
             learn_waiting: bool = True) -> str:
        """
        Save in the child; if it cannot (dead, no answer), save the last snapshot here.

        ``learn_waiting``: the saved model learns every row sent before the save (the child
        catches up for up to ``LearnerLoop.SAVE_DRAIN_S``); False: what it learned by now (a
        shutdown, whose time a launch file bounds).
        """
        path = path or self.config.model_path
        ring = self._ring if learn_waiting else None
        if ring is not None:
            ring.flush(timeout=1.0)             # the rows the learner has not seen yet
        ok, what = self._call('save', path, None if ring is None else ring.mark(),
                              timeout=timeout)
        if ok:
            return what
        if what.startswith(('ValueError: ', 'RuntimeError: ')):
            raise_reply(what)
        from ..config import check_model_path
        if not path:
            raise ValueError('no path given and model_path is not set')
        check_model_path(path)
        snap = self._snap
        if snap is None or snap.model is None:
            raise RuntimeError('no trained model to save yet')
        path = os.path.abspath(path)
        snap.model.save(path)
        return path

    def status(self) -> dict:
        self.calls.expire()
        d = dict(self._status)
        d['samples_dropped'] = self.samples_dropped
        d['learner_restarts'] = self.restarts
        d['learner_alive'] = self._proc is not None and self._proc.is_alive()
        d.update(self.swaps.summary())
        ring = self._ring
        if ring is not None:
            try:
                # sent, not yet taken by the learner (the backlog written first, or counted);
                # never waits on a learner holding the lock
                pending = ring.pending(timeout=0)
                if pending is not None:
                    d['samples_pending'] = pending
            except Exception:       # noqa: BLE001 - a ring being replaced: next time
                pass
        warnings = list(d.get('warnings', []))
        if self.exit_reason:
            warnings.append(self.exit_reason)
        if self._error:
            d['last_refit_error'] = d.get('last_refit_error') or self._error
        d['warnings'] = warnings
        return d

    def close(self, timeout: float = 30.0) -> None:
        """Let a running job finish (bounded), stop the child, release the ring."""
        self._closing = True
        proc = self._proc
        if proc is not None:
            # the child's end of the pipe closing is the sign it is gone (``proc.is_alive`` asks
            # the fork server, which a signal to the process group may have ended)
            self._send('stop', float(timeout))
            self._rx.join(timeout + 2.0)
            if self._rx.is_alive():
                try:
                    os.kill(proc.pid, signal.SIGKILL)
                except OSError:
                    pass
                self._rx.join(2.0)
            self._cmd.close()
        for ring in (self._ring, self._retired):
            if ring is not None:
                ring.close()
        self._ring = self._retired = None


#: the snapshot pipe's buffer (Linux ``F_SETPIPE_SZ``; 64 KiB by default, 1 MiB at most unless
#: the administrator allows more): a burst of snapshots waits there, not in the child's write
PIPE_BYTES = 1 << 20


def _grow_pipe(conn) -> None:
    try:
        import fcntl
        fcntl.fcntl(conn.fileno(), getattr(fcntl, 'F_SETPIPE_SZ', 1031), PIPE_BYTES)
    except (OSError, ImportError, ValueError):
        pass                                # the OS's default size

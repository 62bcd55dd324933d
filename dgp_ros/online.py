"""Online D-GP estimation: the one implementation shared by the ROS node and offline replay.

No rclpy here (house rule: everything a node does can be done offline). The estimator node
(``dgp_ros.estimator_node``) and the bag replay (``dgp-replay``) both drive this class; the API
below is stable.

API
---
::

    from dgp_ros.online import EstimatorConfig, OnlineEstimator, Estimate

    cfg = EstimatorConfig(model='full', passivity='certified', buffer_size=200,
                          refit_mode='sync')        # 'sync' for replay/tests, 'async' for the node
    cfg.validate()                                  # ValueError naming the bad field and why
    est = OnlineEstimator(cfg)                      # loads cfg.model_path if the file exists
    e = est.process(stamp_s, names, velocity, effort)   # one measurement -> Estimate or None
    est.request_refit()      # -> (ok: bool, message: str); async: starts a background refit
    est.wait_for_refit(timeout=None)                # block until no refit is running (tests/replay)
    est.reset()                                     # forget model, buffer, counters
    est.save(path=None)      # atomic (temp file in the same dir + os.replace); -> path
    est.diagnostics()        # dict, see ``OnlineEstimator.diagnostics``
    est.reconfigure(cfg2)    # validated; structural changes (model, passivity, buffer, joints) refit
    est.close()              # waits for a running refit (bounded) ; call at shutdown

``process`` never raises on bad input: a message that is not finite, has inconsistent lengths,
missing or duplicate names, the wrong number of joints or absurd magnitudes is rejected, counted
by reason (``diagnostics()['rejected']``) and ``None`` is returned. A good message is (subject to
the selection policy) added to the model with the O(n^2) ``update`` and the estimate at its velocity
is returned as an :class:`Estimate`: ``qd``, ``tau`` (measured), ``tau_hat``, ``stddev``, ``D``
(N x N, ``None`` for the ARD baseline), ``power = qd^T tau_hat`` and ``measured_power = qd^T tau``.

Default passivity: 'projected'
------------------------------
From docs/BENCHMARKS.md and docs/PASSIVITY.md: in *batch* fits the structural 'certified' mode now
matches the unconstrained Full-D-GP on the A320 (trajectory protocol and volume n = 50..500, ratio
1.0, 0 violations), and 'projected' matches it by construction. *Online* they differ (the demo,
A320 approach, full model, buffer 200, measured 2026-11-22): 'projected' NMSE 0.022 / 1e-7 / 1.7e-4
(drag / -side / lift) with 6 refits of 0.01-0.5 s; 'certified' 0.23 / 3e-4 / 0.048 offline in sync
mode, because every update that leaves the proven domain makes the certificate stale and each
re-proof is a refit with branch-and-bound (0.5-3 s at n = 200) that competes with the message path
for the CPU. Both never published a negative power. So the node defaults to 'projected' (exact
``qd^T tau_hat >= 0`` for every published estimate, microseconds, never less accurate where the
truth is passive); choose 'certified' when a controller needs the damping matrix itself certified.

Behaviour
---------
* Before a model exists (fewer than ``min_samples`` buffered, or the first fit still running) the
  estimate is the prior mean ``diag(m_d) qd`` with ``m_d = prior_mean_diag(buffer) >= 0``: passive
  by construction (``source == 'prior'``).
* Passivity (unless ``passivity == 'none'``): an estimate with ``qd^T tau_hat < 0`` is never
  returned. If the model ever produced one (it should not: paper/certified models are only swapped
  in when certified, projected models project), the prior-mean estimate is returned instead and
  ``passivity_fallbacks`` is counted (``source == 'fallback'``).
* Selection (``selection='novelty'``): a sample whose distance to the nearest buffered sample, in
  per-dimension standardized units, is below ``selection_min_distance`` is not added (a hovering
  state must not fill the buffer with near-duplicates); the estimate is still returned
  (``Estimate.added`` is False). The scale is ``selection_scale`` if given, else the per-dimension
  standard deviation of the buffered velocities (floored, see ``_selection_scale``).
* Learning rate limit: at most one sample per ``min_sample_interval_s`` of stamp time is added
  (default 10 ms, i.e. 100 Hz; ``samples_rate_limited`` counts the others). Every message still
  gets its estimate. With a full window an update costs O(n^2) per output (about 1 ms at
  n = 500, 2 ms at n = 1000, mostly the Givens rotations that drop the oldest sample), so
  learning from every message of a 1 kHz stream cannot keep up (measured: 212 msg/s at buffer
  500 with 0, 1020 msg/s with 0.01); consecutive 1 ms samples are near-duplicates anyway.
  Stamp time, not wall time, so a replay decides exactly as the live run did.
* Stale certificates ('certified' mode): ``update`` only tries the cheap bound; if it fails the
  GP marks its certificate stale (its estimates stay passive pointwise). The estimator then
  re-proves it off the message path on a copy of the model (like a refit: replay + swap).
* Refits: the first fit happens as soon as ``min_samples`` are buffered; then every
  ``refit_period_s`` of *message-stamp* time (sim-time friendly; 0 = only on request), on
  ``request_refit()``, and whenever the buffer has doubled since the hyper-parameters were
  learned (20 -> 40 -> 80 ... samples while it fills). Refit number k re-optimizes hyper-
  parameters when ``k % optimize_every_n_refits == 0``, for the first fit and after such a
  doubling; otherwise it refits at the current hyper-parameters. (Measured on the A320 approach
  from t = 0, 120 msg/s: without the doubling rule the first optimum, learned on 20 samples of
  near-trimmed flight, was kept until the 5th refit and the run's drag NMSE was 0.2; with it,
  2.8e-5 in sync and 1.7e-4 in async mode.) In 'async' mode the fit runs in a background
  thread on a snapshot of the buffer; ``process`` never waits for it. When the fit finishes, the
  samples that arrived meanwhile are replayed into the new model with ``update``; the new model is
  swapped in under a lock held only for the swap, and only if its certificate holds
  (paper/certified modes); a failed or uncertified refit keeps the old model and is counted
  (``refits_failed``, ``last_refit_error``). A backlog longer than max(50, buffer_size / 4)
  samples is absorbed by a fixed-hyper refit on a fresh snapshot instead of sample-by-sample
  replay. A successful refit is saved to ``model_path`` (if set), atomically.
* Sim time / bag loops: if a stamp goes backwards, the model and buffer are kept, the refit clock
  restarts at the new stamp and ``time_jumps_back`` is counted.
* Loading: at construction, if ``model_path`` names an existing file it is loaded with
  ``load_model``; its training set becomes the buffer. A file that cannot be loaded, holds another
  model kind, or (paper/certified) is not certified, is not used (``load_error`` in diagnostics).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ['EstimatorConfig', 'OnlineEstimator', 'Estimate', 'MODELS', 'PASSIVITY_MODES',
           'SELECTION_POLICIES', 'REFIT_MODES', 'REJECT_REASONS', 'OK', 'WARN', 'ERROR']

MODELS = ('full', 'diag', 'ard')
PASSIVITY_MODES = ('none', 'paper', 'certified', 'projected')
SELECTION_POLICIES = ('all', 'novelty')
REFIT_MODES = ('async', 'sync')
# Reasons a message can be rejected for (diagnostics()['rejected'] has one count per reason).
REJECT_REASONS = ('empty', 'length_mismatch', 'bad_names', 'duplicate_name', 'missing_joint',
                  'dimension_mismatch', 'non_finite', 'out_of_range', 'bad_stamp')
# Status levels (the values of diagnostic_msgs/DiagnosticStatus OK/WARN/ERROR).
OK, WARN, ERROR = 0, 1, 2

# Structural fields: changing one at run time drops the model and refits.
_STRUCTURAL = ('model', 'passivity', 'buffer_size', 'joints', 'operating_domain')


@dataclass
class EstimatorConfig:
    """Parameters of the online estimator (the node's ROS parameters have the same names).

    Defaults are the ones in ``config/estimator.yaml`` (a test keeps both in sync).
    """
    model: str = 'full'                  # full | diag | ard
    passivity: str = 'projected'         # none | paper | certified | projected (see below)
    buffer_size: int = 200               # samples kept (the model's window)
    min_samples: int = 20                # prior-mean estimate until this many are buffered
    refit_period_s: float = 10.0         # stamp time between refits; 0 = first fit + on request
    optimize_every_n_refits: int = 5     # hyper-parameter optimisation every n-th refit; 0 = first only
    selection: str = 'novelty'           # all | novelty
    selection_min_distance: float = 0.05  # novelty threshold, standardized units
    selection_scale: List[float] = field(default_factory=list)  # per-joint scale; [] = automatic
    min_sample_interval_s: float = 0.01  # learn at most one sample per this stamp time; 0 = all
    joints: List[str] = field(default_factory=list)  # select/order by name; [] = message order
    model_path: str = ''                 # load at start, save on refit / shutdown / request
    refit_mode: str = 'async'            # async (background thread) | sync (in-line, replay/tests)
    max_abs_velocity: float = 1.0e4      # |qd| above this is rejected (out_of_range)
    max_abs_effort: float = 1.0e8        # |tau| above this is rejected (out_of_range)
    # 'certified': declared operating box [lo_1..lo_N, hi_1..hi_N]; [] = the data box only
    operating_domain: List[float] = field(default_factory=list)

    def validate(self) -> 'EstimatorConfig':
        """Raise ValueError with a clear reason if a field is invalid; return self."""
        def fail(name, why):
            raise ValueError(f'{name}={getattr(self, name)!r}: {why}')

        if self.model not in MODELS:
            fail('model', f'must be one of {", ".join(MODELS)}')
        if self.passivity not in PASSIVITY_MODES:
            fail('passivity', f'must be one of {", ".join(PASSIVITY_MODES)}')
        if self.selection not in SELECTION_POLICIES:
            fail('selection', f'must be one of {", ".join(SELECTION_POLICIES)}')
        if self.refit_mode not in REFIT_MODES:
            fail('refit_mode', f'must be one of {", ".join(REFIT_MODES)}')
        for name in ('buffer_size', 'min_samples', 'optimize_every_n_refits'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                fail(name, 'must be an integer')
        if self.buffer_size < 2:
            fail('buffer_size', 'must be >= 2')
        if self.min_samples < 1:
            fail('min_samples', 'must be >= 1')
        if self.min_samples > self.buffer_size:
            fail('min_samples', f'must be <= buffer_size ({self.buffer_size}), '
                                'else the model is never trained')
        if self.optimize_every_n_refits < 0:
            fail('optimize_every_n_refits', 'must be >= 0 (0 = optimize on the first fit only)')
        for name in ('refit_period_s', 'selection_min_distance', 'min_sample_interval_s'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not math.isfinite(v) or v < 0:
                fail(name, 'must be a finite number >= 0')
        for name in ('max_abs_velocity', 'max_abs_effort'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not (v > 0):
                fail(name, 'must be a number > 0')
        if self.model == 'ard' and self.passivity in ('paper', 'certified'):
            fail('passivity', "the ARD baseline has no damping structure to certify: use "
                              "'none' or 'projected' with model=ard")
        if not isinstance(self.joints, (list, tuple)) or \
                not all(isinstance(j, str) and j for j in self.joints):
            fail('joints', 'must be a list of non-empty names')
        if len(set(self.joints)) != len(self.joints):
            fail('joints', 'names must be unique')
        if not isinstance(self.selection_scale, (list, tuple)):
            fail('selection_scale', 'must be a list of numbers')
        for s in self.selection_scale:
            if isinstance(s, bool) or not isinstance(s, (int, float, np.floating, np.integer)) \
                    or not (math.isfinite(s) and s > 0):
                fail('selection_scale', 'entries must be finite numbers > 0')
        if self.joints and self.selection_scale and \
                len(self.selection_scale) != len(self.joints):
            fail('selection_scale', f'needs one entry per joint ({len(self.joints)})')
        od = self.operating_domain
        if not isinstance(od, (list, tuple)) or any(
                isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer))
                or not math.isfinite(v) for v in od):
            fail('operating_domain', 'must be a list of finite numbers [lo_1..lo_N, hi_1..hi_N]')
        if od:
            if len(od) % 2:
                fail('operating_domain', 'needs an even length: N lower bounds, then N upper')
            k = len(od) // 2
            if any(hi <= lo for lo, hi in zip(od[:k], od[k:])):
                fail('operating_domain', 'every lower bound must be below its upper bound')
            if self.joints and k != len(self.joints):
                fail('operating_domain', f'needs 2 x {len(self.joints)} entries (one lower and '
                                         f'one upper bound per joint)')
        if not isinstance(self.model_path, str):
            fail('model_path', 'must be a string')
        if self.model_path:
            d = os.path.dirname(os.path.abspath(self.model_path))
            if not os.path.isdir(d):
                fail('model_path', f'directory {d} does not exist')
        return self

    @classmethod
    def from_dict(cls, d: dict) -> 'EstimatorConfig':
        """Build from a dict (e.g. ROS parameters); unknown keys raise ValueError."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f'unknown estimator parameter(s): {", ".join(sorted(unknown))}')
        kw = dict(d)
        for k in ('joints', 'selection_scale', 'operating_domain'):
            if k in kw:
                kw[k] = list(kw[k])
        return cls(**kw)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class Estimate:
    """The estimate answering one measurement."""
    stamp_s: float
    names: List[str]
    qd: np.ndarray                 # (N,) velocity the estimate is evaluated at
    tau: np.ndarray                # (N,) measured damping force
    tau_hat: np.ndarray            # (N,) estimated damping force
    stddev: np.ndarray             # (N,) posterior standard deviation
    D: Optional[np.ndarray]        # (N, N) damping matrix; None for the ARD baseline
    power: float                   # qd^T tau_hat (dissipated power of the estimate)
    measured_power: float          # qd^T tau
    source: str                    # 'model' | 'prior' | 'fallback'
    added: bool                    # the sample was added to the buffer/model
    processing_time_s: float       # wall time spent in process()


class _Buffer:
    """Fixed-capacity FIFO of (qd, tau) rows, numpy backed (ordered oldest -> newest on read)."""

    def __init__(self, capacity: int, N: int):
        self.capacity, self.N = capacity, N
        self._q = np.zeros((capacity, N))
        self._t = np.zeros((capacity, N))
        self._start = 0
        self.size = 0

    def append(self, q, t):
        i = (self._start + self.size) % self.capacity
        self._q[i], self._t[i] = q, t
        if self.size < self.capacity:
            self.size += 1
        else:
            self._start = (self._start + 1) % self.capacity

    def velocities_unordered(self) -> np.ndarray:
        if self.size < self.capacity:
            return self._q[:self.size]
        return self._q

    def arrays(self) -> Tuple[np.ndarray, np.ndarray]:
        idx = (self._start + np.arange(self.size)) % self.capacity
        return self._q[idx].copy(), self._t[idx].copy()


def _atomic_model_save(model, path: str) -> str:
    """Save ``model`` to ``path`` atomically (the GP's ``save`` writes a temp file in the same
    directory, fsyncs it and ``os.replace``s it: a reader sees the old or the new file)."""
    path = os.path.abspath(path)
    model.save(path)
    return path


class OnlineEstimator:
    """Online D-GP estimator (see the module docstring for the behaviour)."""

    #: recent-message window for the "many rejected samples" status
    REJECT_WINDOW = 200
    REJECT_WARN_FRACTION = 0.1
    #: consecutive failed refits that make the status ERROR (one failure is a WARN)
    REFIT_FAIL_ERROR = 3

    def __init__(self, config: Optional[EstimatorConfig] = None):
        from dgp_ros import gp as _gp  # noqa: F401  (fail early if the core is missing)
        self._gp = _gp
        self.config = (config or EstimatorConfig()).validate()
        self._lock = threading.RLock()
        self._refit_thread: Optional[threading.Thread] = None
        self.load_error = ''
        self._init_state()
        if self.config.model_path and os.path.exists(self.config.model_path):
            self._load(self.config.model_path)

    # ------------------------------------------------------------------ state
    def _init_state(self, keep_counters: bool = False):
        self._generation = getattr(self, '_generation', 0) + 1
        self._names: Optional[List[str]] = list(self.config.joints) or None
        self._N: Optional[int] = len(self.config.joints) or None
        self._buf: Optional[_Buffer] = None
        self._sample_seq = 0              # accepted samples ever added (for refit replay)
        # (seq, qd, tau) added while a refit runs; only the newest buffer_size can survive the
        # model's window, so older ones are dropped here instead of being replayed
        self._pending: deque = deque(maxlen=self.config.buffer_size)
        self._model = None
        self._m_d: Optional[np.ndarray] = None
        self._m_d_dirty = True
        self._last_stamp: Optional[float] = None
        self._last_added_stamp: Optional[float] = None
        self._last_refit_stamp: Optional[float] = None
        self._refit_requested = False
        self._opt_n = 0                   # samples the current hyper-parameters were learned on
        if keep_counters:
            return
        self.rejected: Dict[str, int] = {r: 0 for r in REJECT_REASONS}
        self._recent_ok: deque = deque(maxlen=self.REJECT_WINDOW)
        self.messages_received = 0
        self.messages_accepted = 0
        self.samples_added = 0
        self.samples_skipped = 0
        self.samples_rate_limited = 0
        self.passivity_fallbacks = 0
        self.time_jumps_back = 0
        self.refits_started = 0
        self.recertifications = 0
        self.refits_ok = 0
        self.refits_failed = 0
        self._consecutive_refit_failures = 0
        self.last_refit_error = ''
        self.last_refit_stamp: Optional[float] = None
        self.last_refit_wall_time: Optional[float] = None
        self.last_refit_duration_s: Optional[float] = None
        self.last_refit_optimized: Optional[bool] = None
        self.refit_durations: List[float] = []
        self._latencies: deque = deque(maxlen=1000)
        self._last_est: Optional[Estimate] = None

    # ------------------------------------------------------------- messages
    def _reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        self._recent_ok.append(False)

    def _select(self, names: Sequence[str], velocity, effort):
        """Validate one message; return (names, qd, tau) or a rejection reason string."""
        if velocity is None or effort is None:
            return 'empty'
        try:
            v = np.asarray(velocity, dtype=float).ravel()
            e = np.asarray(effort, dtype=float).ravel()
        except (TypeError, ValueError):
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
        if v.size != e.size or (names and len(names) != v.size):
            return 'length_mismatch'
        if self._names is not None and names:
            pos = {n: i for i, n in enumerate(names)}
            try:
                idx = [pos[n] for n in self._names]
            except KeyError:
                return 'missing_joint'
            v, e, names = v[idx], e[idx], list(self._names)
        elif self._names is not None and not names and self.config.joints:
            return 'missing_joint'
        if self._N is not None and v.size != self._N:
            return 'dimension_mismatch'
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(e))):
            return 'non_finite'
        if np.any(np.abs(v) > self.config.max_abs_velocity) or \
                np.any(np.abs(e) > self.config.max_abs_effort):
            return 'out_of_range'
        return names, v, e

    def process(self, stamp_s: float, names: Sequence[str], velocity, effort) -> Optional[Estimate]:
        """Validate one measurement, learn from it, and return the estimate at its velocity.

        Never raises on bad input: returns None and counts the rejection reason.
        """
        t0 = time.perf_counter()
        with self._lock:
            self.messages_received += 1
            try:
                stamp = float(stamp_s)
            except (TypeError, ValueError, OverflowError):
                stamp = float('nan')
            sel = self._select(names, velocity, effort)
            if isinstance(sel, str):            # content problems are reported first
                self._reject(sel)
                return None
            if not math.isfinite(stamp) or stamp < 0.0:     # before the epoch / sim start
                self._reject('bad_stamp')
                return None
            names, qd, tau = sel
            self._recent_ok.append(True)
            self.messages_accepted += 1
            if self._N is None:
                self._N = qd.size
            if self._names is None and names:
                self._names = list(names)
            if self._buf is None:
                self._buf = _Buffer(self.config.buffer_size, self._N)
            self._check_clock(stamp)

            added = self._maybe_add(stamp, qd, tau)
            start_thread = self._maybe_trigger_refit(stamp)
            if not start_thread and self._is_stale() and not self._refit_running() and \
                    self._recertify_due(stamp):
                # a refit at fixed hyper-parameters on the current buffer: it re-derives the
                # verified domain from the data the model now holds (a re-proof of the old
                # model would keep the domain of the data it was first fitted on)
                start_thread = 'fit'
            est = self._estimate(stamp, list(names) if names else [], qd, tau, added)
            est.processing_time_s = time.perf_counter() - t0
            self._latencies.append(est.processing_time_s)
            self._last_est = est
        if start_thread:
            self._start_refit('recertify' if start_thread == 'recertify' else 'fit')
        return est

    def _check_clock(self, stamp: float) -> None:
        if self._last_stamp is not None and stamp < self._last_stamp:
            # Documented policy: keep model and buffer, restart the refit clock, count it.
            self.time_jumps_back += 1
            if self._last_refit_stamp is not None:
                self._last_refit_stamp = stamp
        self._last_stamp = stamp

    def _selection_scale(self) -> np.ndarray:
        if self.config.selection_scale:
            return np.asarray(self.config.selection_scale, dtype=float)
        Q = self._buf.velocities_unordered()
        # std of the buffer, floored so that a degenerate (constant) dimension does not make
        # every tiny wiggle look novel
        s = Q.std(axis=0)
        floor = 1e-3 * (np.abs(Q).mean(axis=0) + 1e-3) if Q.shape[0] else np.ones(self._N)
        return np.maximum(s, floor)

    def _maybe_add(self, stamp: float, qd, tau) -> bool:
        dt = self.config.min_sample_interval_s
        last = self._last_added_stamp
        if dt > 0 and last is not None and last <= stamp < last + dt * (1.0 - 1e-9):
            # learning rate limit (stamp time, so replay decides exactly as live did)
            self.samples_rate_limited += 1
            return False
        if self.config.selection == 'novelty' and self._buf.size > 0 and \
                self.config.selection_min_distance > 0:
            scale = self._selection_scale()
            Q = self._buf.velocities_unordered()
            d2 = (((Q - qd) / scale) ** 2).sum(axis=1).min()
            if d2 < self.config.selection_min_distance ** 2:
                self.samples_skipped += 1
                return False
        self._buf.append(qd, tau)
        self._last_added_stamp = stamp
        self._sample_seq += 1
        self.samples_added += 1
        self._m_d_dirty = True
        if self._refit_running():
            self._pending.append((self._sample_seq, qd.copy(), tau.copy()))
        if self._model is not None:
            try:
                self._model.update(qd, tau)
            except Exception as exc:  # a model that cannot take the sample: refit from buffer
                self.last_refit_error = f'update failed: {exc}'
                self._refit_requested = True
        return True

    # ------------------------------------------------------------ estimates
    def _prior_md(self) -> np.ndarray:
        if self._m_d_dirty or self._m_d is None:
            Q, T = self._buf.arrays() if self._buf is not None and self._buf.size else \
                (np.zeros((0, self._N)), np.zeros((0, self._N)))
            self._m_d = np.maximum(np.asarray(self._gp.prior_mean_diag(Q, T), float), 0.0)
            if Q.shape[0]:
                r = T - Q * self._m_d
                self._prior_std = np.sqrt(np.mean(r ** 2, axis=0))
            else:
                self._prior_std = np.full(self._N, np.inf)
            self._m_d_dirty = False
        return self._m_d

    def _prior_estimate(self, qd):
        m_d = self._prior_md()
        return m_d * qd, self._prior_std.copy(), np.diag(m_d)

    def _estimate(self, stamp, names, qd, tau, added) -> Estimate:
        source = 'prior'
        if self._model is not None:
            try:
                tau_hat, var, D = self._model.predict_with_damping(qd[None, :])
                tau_hat = np.asarray(tau_hat, float)[0]
                std = np.sqrt(np.maximum(np.asarray(var, float)[0], 0.0))
                D = None if D is None else np.asarray(D, float)[0]
                source = 'model'
                if not (np.all(np.isfinite(tau_hat)) and np.all(np.isfinite(std))):
                    raise FloatingPointError('non-finite prediction')
            except Exception as exc:
                self.last_refit_error = f'predict failed: {exc}'
                source = 'fallback'
                self.passivity_fallbacks += 1
        if source != 'model':
            tau_hat, std, D = self._prior_estimate(qd)
        power = float(qd @ tau_hat)
        if self.config.passivity != 'none' and power < 0.0:
            # Belt and braces: never return a non-passive estimate. Prior mean is passive
            # exactly, also in floating point (a sum of non-negative terms m_d * qd^2).
            self.passivity_fallbacks += 1
            tau_hat, std, D = self._prior_estimate(qd)
            source = 'fallback'
            power = float(qd @ tau_hat)
        return Estimate(stamp_s=stamp, names=names, qd=qd, tau=tau, tau_hat=tau_hat, stddev=std,
                        D=D, power=power, measured_power=float(qd @ tau), source=source,
                        added=added, processing_time_s=0.0)

    def predict(self, Qs) -> np.ndarray:
        """Estimates (k, N) at velocities Qs with the same rules as ``process`` (no learning)."""
        Qs = np.atleast_2d(np.asarray(Qs, dtype=float))
        with self._lock:
            if self._N is None:
                self._N = Qs.shape[1]
            out = []
            for q in Qs:
                out.append(self._estimate(0.0, [], q, np.zeros_like(q), False).tau_hat)
        return np.array(out)

    # ---------------------------------------------------------------- refits
    def _refit_running(self) -> bool:
        t = self._refit_thread
        return t is not None and t.is_alive()

    def _maybe_trigger_refit(self, stamp: float) -> bool:
        """Decide (under the lock) whether a refit starts now; returns True to start one."""
        if self._buf is None or self._buf.size < self.config.min_samples:
            return False
        if self._refit_running():
            return False
        due = self._refit_requested
        if self._model is not None and self._last_refit_stamp is None:
            self._last_refit_stamp = stamp               # loaded model: start the refit clock
        if self._model is None and self._last_refit_stamp is None:
            due = True                                   # first fit
        elif self.config.refit_period_s > 0 and self._last_refit_stamp is not None and \
                stamp - self._last_refit_stamp >= self.config.refit_period_s:
            due = True                                   # periodic (also retries a failed fit)
        elif self._model is not None and 0 < self._opt_n and self._hypers_outgrown() and \
                self._consecutive_refit_failures == 0:
            due = True                                   # the buffer doubled: re-learn hypers
        if not due:
            return False
        self._refit_requested = False
        self._last_refit_stamp = stamp
        return True

    def _hypers_outgrown(self) -> bool:
        """The buffer has at least doubled since the hyper-parameters were learned: the first
        fit sees min_samples points of a possibly near-stationary start and its optimum can be
        far off, so they are re-learned (20 -> 40 -> 80 ... while the buffer fills)."""
        return self._buf.size >= 2 * self._opt_n

    def request_refit(self) -> Tuple[bool, str]:
        """Refit now (async: start it in the background). Returns (ok, message)."""
        with self._lock:
            if self._buf is None or self._buf.size < self.config.min_samples:
                n = 0 if self._buf is None else self._buf.size
                return False, f'not enough samples ({n} < min_samples {self.config.min_samples})'
            if self._refit_running():
                return False, 'a refit is already running'
            if self._last_stamp is not None:
                self._last_refit_stamp = self._last_stamp
        return self._start_refit()

    def _start_refit(self, kind: str = 'fit') -> Tuple[bool, str]:
        """Start a background job (run it in-line in 'sync' mode).

        kind 'fit': fit a new model on a snapshot of the buffer. kind 'recertify': re-prove the
        certificate of a copy of the current model after ``update`` left it stale (the GP then
        falls back pointwise to the prior mean; re-proving costs ms..s, so never in-line in
        'async' mode). Both replay the samples that arrived meanwhile and swap atomically.
        """
        with self._lock:
            if self._refit_running():
                return False, 'a refit is already running'
            if kind == 'recertify':
                if self._model is None:
                    return False, 'no model'
                job = dict(kind=kind, model=copy.deepcopy(self._model), seq=self._sample_seq,
                           generation=self._generation, config=dataclasses.replace(self.config),
                           stamp=self._last_stamp, optimize=False)
                what = 'recertification started'
            else:
                self.refits_started += 1
                k = self.refits_started
                optimize = (self._model is None or self._hyper is None or
                            (self.config.optimize_every_n_refits > 0 and
                             k % self.config.optimize_every_n_refits == 0) or
                            self._hypers_outgrown())
                Q, T = self._buf.arrays()
                job = dict(kind=kind, Q=Q, T=T, seq=self._sample_seq, optimize=optimize,
                           generation=self._generation, hyper=self._hyper,
                           config=dataclasses.replace(self.config), stamp=self._last_stamp)
                what = (f'refit started on {Q.shape[0]} samples '
                        f'({"optimizing" if optimize else "fixed"} hyper-parameters)')
            self._pending.clear()
            if self.config.refit_mode == 'sync':
                self._refit_thread = None
            else:
                self._refit_thread = threading.Thread(target=self._refit_job, args=(job,),
                                                      name='dgp_refit', daemon=True)
                self._refit_thread.start()
                return True, what
        return self._refit_job(job)

    @property
    def _hyper(self) -> Optional[dict]:
        return getattr(self, '_hyper_params', None)

    def _refit_job(self, job) -> Tuple[bool, str]:
        """Fit (or recertify) a model off the message path; replay newer samples; swap if
        certified. The lock is held only to read the pending samples and for the swap."""
        cfg = job['config']
        t0 = time.perf_counter()
        recert = job['kind'] == 'recertify'
        try:
            if recert:
                model = job['model']
            else:
                kw = dict(job['hyper'] or {})
                kw.update(passivity=cfg.passivity, window=cfg.buffer_size)
                if cfg.operating_domain and cfg.passivity == 'certified':
                    k = len(cfg.operating_domain) // 2
                    kw['operating_domain'] = (cfg.operating_domain[:k], cfg.operating_domain[k:])
                model = self._gp.make_model(cfg.model, **kw)
                model.fit(job['Q'], job['T'], optimize=job['optimize'])
            seq = job['seq']
            rounds = 0
            while True:
                # re-prove outside the lock (a no-op unless update() left the model stale)
                ok, why = self._certified(model, cfg)
                rounds += 1
                with self._lock:
                    if job['generation'] != self._generation:
                        return False, 'discarded: the estimator was reset'
                    newer = [(s, q, t) for (s, q, t) in self._pending if s > seq]
                    snapshot = None
                    if ok and not recert and rounds <= 5 and \
                            len(newer) > max(50, cfg.buffer_size // 4):
                        # a long backlog (slow fit, fast input): a fixed-hyper refit on the
                        # current buffer is cheaper than replaying it one update at a time
                        snapshot = self._buf.arrays() + (self._sample_seq,)
                    elif not newer or not ok or rounds > 5:
                        if ok and newer:            # catch up the last few in the lock
                            for s, q, t in newer:
                                model.update(q, t)
                        if ok:
                            self._model = model      # atomic swap
                            if not recert:
                                self._hyper_params = self._params_of(model)
                                if job['optimize']:
                                    self._opt_n = job['Q'].shape[0]
                        self._pending.clear()
                        break
                if snapshot is not None:
                    model.fit(snapshot[0], snapshot[1], optimize=False)
                    seq = snapshot[2]
                    continue
                for s, q, t in newer:                # replay outside the lock
                    model.update(q, t)
                    seq = s
            dt = time.perf_counter() - t0
            with self._lock:
                if recert:
                    self.recertifications += 1
                    if not ok:
                        self.last_refit_error = f'recertification failed: {why}'
                    return ok, (f'recertified in {dt:.3f} s' if ok else self.last_refit_error)
                self.last_refit_duration_s = dt
                self.refit_durations.append(dt)
                self.last_refit_wall_time = time.time()
                self.last_refit_stamp = job['stamp']
                self.last_refit_optimized = job['optimize']
                if ok:
                    self.refits_ok += 1
                    self._consecutive_refit_failures = 0
                    self.last_refit_error = ''
                else:
                    self.refits_failed += 1
                    self._consecutive_refit_failures += 1
                    self.last_refit_error = f'not swapped in: {why}'
            if ok and cfg.model_path:
                try:
                    self.save(cfg.model_path)
                except Exception as exc:
                    with self._lock:
                        self.last_refit_error = f'refit ok but saving failed: {exc}'
            return (True, f'refit ok in {dt:.3f} s') if ok else (False, self.last_refit_error)
        except Exception as exc:
            dt = time.perf_counter() - t0
            with self._lock:
                if recert:
                    self.last_refit_error = f'recertification failed: {type(exc).__name__}: {exc}'
                    return False, self.last_refit_error
                self.refits_failed += 1
                self._consecutive_refit_failures += 1
                self.last_refit_error = f'{type(exc).__name__}: {exc}'
                self.last_refit_duration_s = dt
                self.refit_durations.append(dt)
                self.last_refit_wall_time = time.time()
                self.last_refit_optimized = job['optimize']
            return False, self.last_refit_error

    @staticmethod
    def _params_of(model) -> Optional[dict]:
        try:
            p = dict(model.get_params())
        except Exception:
            return None
        p.pop('passivity', None)
        p.pop('window', None)
        return p

    @staticmethod
    def _certified(model, cfg) -> Tuple[bool, str]:
        if cfg.passivity not in ('paper', 'certified'):
            return True, ''
        try:
            cert = model.certificate()
        except Exception as exc:
            return False, f'certificate failed: {exc}'
        if cert.certified:
            return True, ''
        return False, f'certificate does not hold (margin {cert.margin:.3g}, {cert.method})'

    def _recertify_due(self, stamp: float) -> bool:
        """A stale model stays passive pointwise, so re-proving it on every sample would only
        burn CPU: re-prove (by a refit at fixed hyper-parameters) at most every
        ``refit_period_s / 4`` of stamp time (0.25 s if the period is 0)."""
        gap = self.config.refit_period_s / 4.0 if self.config.refit_period_s > 0 else 0.25
        last = getattr(self, '_last_recert_stamp', None)
        if last is not None and stamp >= last and stamp - last < gap:
            return False
        self._last_recert_stamp = stamp
        return True

    def _is_stale(self) -> bool:
        return self._model is not None and bool(getattr(self._model, 'certificate_stale', False))

    def wait_for_refit(self, timeout: Optional[float] = None) -> bool:
        """Block until no refit is running; True if none is running at return."""
        t = self._refit_thread
        if t is not None:
            t.join(timeout)
        return not self._refit_running()

    # -------------------------------------------------------- housekeeping
    def reset(self) -> None:
        """Forget the model, the buffer and all counters (a running refit is discarded)."""
        with self._lock:
            self._hyper_params = None
            self._init_state()

    def reconfigure(self, config: EstimatorConfig) -> str:
        """Apply a new validated config; structural changes drop the model and refit."""
        config = dataclasses.replace(config).validate()
        with self._lock:
            old = self.config
            self.config = config
            changed = [f for f in _STRUCTURAL if getattr(old, f) != getattr(config, f)]
            if not changed:
                return 'applied'
            if 'joints' in changed:
                self._hyper_params = None
                self._init_state(keep_counters=True)
                return 'joints changed: estimator reset'
            Q = T = None
            if self._buf is not None and self._buf.size:
                Q, T = self._buf.arrays()
            self._hyper_params = None
            names, N = self._names, self._N
            self._init_state(keep_counters=True)
            self._names, self._N = names, N
            if Q is not None:
                self._buf = _Buffer(config.buffer_size, N)
                for q, t in zip(Q[-config.buffer_size:], T[-config.buffer_size:]):
                    self._buf.append(q, t)
                self._refit_requested = True
            return f'{", ".join(changed)} changed: model dropped, refit on the next sample'

    def save(self, path: Optional[str] = None) -> str:
        """Save the current model atomically to ``path`` (default ``model_path``); returns it."""
        path = path or self.config.model_path
        if not path:
            raise ValueError('no path given and model_path is not set')
        with self._lock:
            if self._model is None:
                raise RuntimeError('no trained model to save yet')
            if self._is_stale():
                self._model.recertify()      # so that the file and the live model agree
            return _atomic_model_save(self._model, path)

    def _load(self, path: str) -> None:
        try:
            model = self._gp.load_model(path)
            kind = getattr(model, '_kind', type(model).__name__)
            if kind != self.config.model:
                raise ValueError(f'file holds a {kind!r} model, config model={self.config.model!r}')
            X = np.asarray(model.X_train_, float)
            Y = np.asarray(model.Y_train_, float)
            if self.config.joints and X.shape[1] != len(self.config.joints):
                raise ValueError(f'file model has N={X.shape[1]}, joints has {len(self.config.joints)}')
            if self.config.passivity != 'none' and \
                    getattr(model, 'passivity', self.config.passivity) != self.config.passivity:
                raise ValueError(f'file model passivity {getattr(model, "passivity", None)!r} '
                                 f'!= {self.config.passivity!r}')
            ok, why = self._certified(model, self.config)
            if not ok:
                raise ValueError(why)
        except Exception as exc:
            self.load_error = f'could not use {path}: {exc}'
            return
        self._N = X.shape[1]
        self._buf = _Buffer(self.config.buffer_size, self._N)
        for q, t in zip(X[-self.config.buffer_size:], Y[-self.config.buffer_size:]):
            self._buf.append(q, t)
        self._sample_seq = self._buf.size
        self._model = model
        self._hyper_params = self._params_of(model)
        self._opt_n = X.shape[0]
        self._last_refit_stamp = None   # set by the first message
        self._loaded = True

    def close(self, timeout: float = 30.0) -> None:
        """Wait (bounded) for a running refit to finish; call before exit."""
        self.wait_for_refit(timeout)

    # ----------------------------------------------------------- diagnostics
    @property
    def trained(self) -> bool:
        return self._model is not None

    @property
    def model(self):
        """The current model (None before the first fit). Do not mutate it."""
        return self._model

    @property
    def names(self) -> Optional[List[str]]:
        return None if self._names is None else list(self._names)

    def diagnostics(self) -> dict:
        """Everything the node publishes on /diagnostics, as a dict.

        ``level`` is OK/WARN/ERROR (0/1/2, diagnostic_msgs values) and ``message`` joins the
        reasons: 'not yet trained', 'not certified', 'many rejected samples', 'refit failing',
        'passivity fallbacks', 'model file not used'.
        """
        with self._lock:
            cert = None
            stale = self._is_stale()
            if self._model is not None and not stale:
                try:
                    cert = self._model.certificate()
                except Exception:
                    cert = None
            fill = 0 if self._buf is None else self._buf.size
            recent = list(self._recent_ok)
            rej_frac = (recent.count(False) / len(recent)) if recent else 0.0
            lat = np.array(self._latencies) if self._latencies else None
            last = self._last_est
            d = dict(
                model=self.config.model, passivity=self.config.passivity,
                trained=self._model is not None,
                certified=bool(cert.certified) if cert is not None else False,
                margin=float(cert.margin) if cert is not None else float('nan'),
                method=str(cert.method) if cert is not None else '',
                domain=str(getattr(cert, 'domain', None)) if cert is not None else '',
                buffer_fill=fill, buffer_size=self.config.buffer_size,
                messages_received=self.messages_received,
                messages_accepted=self.messages_accepted,
                samples_added=self.samples_added, samples_skipped=self.samples_skipped,
                samples_rate_limited=self.samples_rate_limited,
                rejected=dict(self.rejected), rejected_total=sum(self.rejected.values()),
                recent_rejected_fraction=rej_frac,
                refit_running=self._refit_running(),
                refits_ok=self.refits_ok, refits_failed=self.refits_failed,
                last_refit_error=self.last_refit_error,
                last_refit_stamp=self.last_refit_stamp,
                last_refit_wall_time=self.last_refit_wall_time,
                last_refit_duration_s=self.last_refit_duration_s,
                last_refit_optimized=self.last_refit_optimized,
                passivity_fallbacks=self.passivity_fallbacks,
                time_jumps_back=self.time_jumps_back,
                measured_power=last.measured_power if last else float('nan'),
                estimated_power=last.power if last else float('nan'),
                last_source=last.source if last else '',
                latency_median_s=float(np.median(lat)) if lat is not None else float('nan'),
                latency_p99_s=float(np.percentile(lat, 99)) if lat is not None else float('nan'),
                load_error=self.load_error,
                certificate_stale=stale, recertifications=self.recertifications,
            )
            reasons, level = [], OK
            if self._model is None:
                if fill < self.config.min_samples:
                    reasons.append(f'not yet trained ({fill}/{self.config.min_samples} samples)')
                elif self.refits_failed and self.config.passivity in ('paper', 'certified'):
                    reasons.append('not certified: no certified model yet, publishing prior mean')
                else:
                    reasons.append('not yet trained (first fit running)')
                level = max(level, WARN)
            elif stale:
                reasons.append('certificate being re-proven after updates '
                               '(estimates passive pointwise meanwhile)')
            elif self.config.passivity in ('paper', 'certified') and not d['certified']:
                reasons.append('not certified')
                level = max(level, WARN)
            if rej_frac > self.REJECT_WARN_FRACTION:
                reasons.append(f'many rejected samples ({100 * rej_frac:.0f}% of recent)')
                level = max(level, WARN)
            if self._consecutive_refit_failures:
                reasons.append(f'refit failing ({self._consecutive_refit_failures} in a row: '
                               f'{self.last_refit_error})')
                level = max(level, ERROR if self._consecutive_refit_failures >=
                            self.REFIT_FAIL_ERROR else WARN)
            if self.load_error:
                reasons.append('model file not used')
                level = max(level, WARN)
            d['level'] = level
            d['message'] = '; '.join(reasons) if reasons else 'ok'
            return d

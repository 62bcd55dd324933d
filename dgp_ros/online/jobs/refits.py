"""
Refit and re-proof jobs of the learner: when, start, integrate, swap (no rclpy).

A part of :class:`~dgp_ros.online.learner.Learner` that owns the jobs' state: the refit clock,
the hyper-parameters the served model was fitted at and the data they were learned on, the
novelty trigger, retries, the samples a running fit has not seen, the job thread and the
generation (a reset or switching learning off discards what runs).

It decides what runs next (``next_job``: a refit at ``min_samples``, then every
``refit_period_s`` of learning time, on request, when the buffer doubled, when data leave the
hyper-parameters' ground, a retry; else a re-proof of a stale certificate), starts it
(``worker.run_job``: in a background thread with ``refit_mode='async'``, in line with
``'sync'``), and integrates its result: the candidate is compared one step ahead with the
incumbent on the samples that arrived during its fit (``_held_out``), refitted at its new
hyper-parameters on the window as it is now, and swapped in under the lock, which is held only
to read the window and for the swap. A re-proven model is caught up with the samples appended to
the served one meanwhile. An unproven candidate serves with every answer projected
(``worker``); re-proofs after failed ones wait longer (``proof_gap``). The learning switch's
freeze job runs here too: ``run`` hands a freeze job, or the freeze wanted after a job, to
``parts.switch``. It keeps no other part: every step that reads or changes one is passed the
learner's parts (``parts.Parts``: the lock, the settings, the window, structure and served model
a job reads and feeds, the health record, the switch, and ``parts.save``, the step that saves a
swapped-in model to ``model_path``), and the job thread is handed them when it starts.
"""
from __future__ import annotations

from collections import deque
import copy
import dataclasses
import threading
import time
from typing import Callable, Optional, Tuple

import numpy as np

from dgp_ros.gp.select import choice_summary

from .worker import held_out, RefitJob, RefitResult, run_job

__all__ = ['Refits']


class Refits:
    """
    The learner's jobs (module docstring).

    It keeps no other part (module docstring): the steps are passed the learner's parts.
    factory : builds a model; buffer_size : the configuration's (the most samples a running fit
    keeps for its held-out check); generation : where to start counting.
    """

    #: a stamp this many refit periods ahead of the refit clock is a jump, not elapsed time
    CLOCK_JUMP_PERIODS = 10
    #: a re-proof waits this many times the last one's wall time after it (``_proof_spaced``)
    PROOF_SPACING = 3.0
    #: a candidate whose error on the samples that arrived during its fit exceeds the current
    #: model's by this factor (plus 1 % of their variance) is not swapped in
    HELD_OUT_FACTOR = 3.0
    #: rejected candidates retried on fresh data before waiting for the next refit period
    #: (without any model: always, each retry waiting twice as many samples, up to 64 x)
    MAX_RETRIES = 3
    #: samples arriving during a refit on which its held-out check compares the models: the
    #: first this many, then evenly spread ones up to twice as many
    HELD_OUT_EVERY = 20

    #: a learned sample beyond the velocities the hyper-parameters were learned on, by this
    #: fraction of their range on any joint, asks for an optimizing refit (``note_novelty``) ...
    NOVELTY_MARGIN = 0.1
    #: ... where the model's error on it is beyond this many times its recent RMS error ...
    NOVELTY_SURPRISE = 2.5
    #: ... at most once per this much learning time (s)
    NOVELTY_GAP_S = 1.0

    def __init__(self, factory: Callable, buffer_size: int, generation: int = 0):
        self._factory = factory
        self._generation = int(generation)
        self._thread: Optional[threading.Thread] = None
        self._hyper: Optional[dict] = None   # warm start of the next fit (hyperparams_)
        self._opt_n = 0                   # samples the current hyper-parameters were learned on
        self._hyper_box = None            # their velocity box (``note_novelty``)
        self._novel, self._novel_t = False, None
        self._clock: Optional[float] = None   # learning time of the last refit decision
        self._last_recert: Optional[float] = None
        self._proof_done: Optional[float] = None    # wall clock at the end of the last re-proof
        self._proof_wall = 0.0                      # and the wall time it took (s)
        self._recert_seq = -1             # the served model's ``held`` at the last re-proof
        self._requested = False
        self._retry_at: Optional[int] = None  # window seq at which a rejected fit is retried
        # (seq, qd, tau) added while a refit runs; only the newest buffer_size can survive the
        # model's window, so older ones are dropped here
        self._pending: deque = deque(maxlen=buffer_size)

    # ------------------------------------------------------------------ state
    @property
    def generation(self) -> int:
        """Return the count of discards: a job or rebase of another generation is dropped."""
        return self._generation

    def discard(self) -> None:
        """Drop what runs now when it ends (a reset, learning switched off)."""
        self._generation += 1

    @property
    def hyper(self) -> Optional[dict]:
        """Return the served model's hyper-parameters (the warm start of the next fit)."""
        return self._hyper

    @property
    def hyper_samples(self) -> int:
        """Return how many samples the hyper-parameters were learned on."""
        return self._opt_n

    def running(self) -> bool:
        """Tell whether a job runs in the job thread."""
        t = self._thread
        return t is not None and t.is_alive()

    @property
    def thread(self) -> Optional[threading.Thread]:
        """Return the job thread, None in line or before any job."""
        return self._thread

    def pending(self) -> int:
        """Return how many samples arrived during the running fit (0 when none runs)."""
        return len(self._pending) if self.running() else 0

    def adopted(self, model, X: np.ndarray) -> None:
        """Take an adopted model's hyper-parameters, learned on X (n, N)."""
        self._hyper = model.hyperparams_
        self._opt_n = X.shape[0]
        self._hyper_box = (X.min(axis=0), X.max(axis=0))
        self._clock = None              # set by the first message
        self._recert_seq = -1

    def resumed(self) -> None:
        """Learning was switched on again: the clocks start at the next sample."""
        self._clock = None
        self._last_recert = None

    def note_sample(self, seq: int, qd: np.ndarray, target: np.ndarray) -> None:
        """Keep a sample learned while a fit runs (its held-out check: ``_held_out``)."""
        if self.running():
            self._pending.append((seq, qd.copy(), target.copy()))

    def request_soon(self) -> None:
        """Refit at the next sample (the model was dropped, its data kept)."""
        self._requested = True

    def jumped_back(self, t: float) -> None:
        """Restart the refit clock at ``t``: a stamp went back."""
        if self._clock is not None:
            self._clock = t

    def proof_gap(self, base: float, health) -> float:
        """Stamp seconds between re-proofs: ``base``, doubled per failed proof in a row (<= 8x)."""
        return base * 2 ** min(health.proofs_failed_in_a_row, 3)

    # ------------------------------------------------------------------ decisions
    def note_novelty(self, stamp: float, qd: np.ndarray, surprise: float, parts) -> None:
        """
        Ask for an optimizing refit when the data leave what the hyper-parameters were fitted on.

        A refit by the clock answers a system that enters new territory (an aircraft at its
        first negative angle of attack and 20 % more airspeed) for up to ``refit_period_s`` x
        ``optimize_every_n_refits`` with hyper-parameters learned where it was before; the
        samples appended meanwhile are taken at those. So a learned sample beyond the box of the
        last optimization's velocities (grown by ``NOVELTY_MARGIN`` of its range) that the model
        answered badly (``surprise``: its one-step error over its recent RMS error, beyond
        ``NOVELTY_SURPRISE``, where the error is more than ``skill.SURPRISE_SIGNAL`` of the
        force's RMS) makes the next refit one that re-learns them, at most
        every ``NOVELTY_GAP_S`` of learning time (``novelty_refits`` on /diagnostics). A model
        that extrapolates well into new territory is left alone: an arm's first cycle leaves
        the box all the time.
        """
        box = self._hyper_box
        cfg = parts.settings()
        if box is None or parts.served.model is None or not surprise > self.NOVELTY_SURPRISE \
                or cfg.optimize_every_n_refits == 0 or cfg.refit_period_s == 0:   # by request
            return
        lo, hi = box
        grow = self.NOVELTY_MARGIN * np.maximum(hi - lo, 1e-12)
        if np.any(qd < lo - grow) or np.any(qd > hi + grow):
            last = self._novel_t
            if last is None or stamp < last or stamp - last >= self.NOVELTY_GAP_S:
                self._novel, self._novel_t = True, stamp
                parts.health.novelty_refits += 1

    def _outgrown(self, window) -> bool:
        """Tell whether the buffer has at least doubled since the hyper-parameters were learned."""
        return 0 < self._opt_n and window.size >= 2 * self._opt_n

    def next_job(self, stamp: float, last_t: Optional[float], parts,
                 idle: bool = False) -> Optional[RefitJob]:
        """
        Make the one decision (under the lock) of what the worker does next, if anything.

        ``stamp``: the learning time now; ``last_t``: the newest sample's (the job's stamp).
        ``idle``: the stream paused (``Learner.poll``): a stale model not tried since it last
        changed is re-proven without waiting for the re-proof period.
        """
        cfg, served, h = parts.settings(), parts.served, parts.health
        if parts.window.buffer is None or parts.window.size < cfg.min_samples or self.running():
            return None
        model = served.model
        if model is not None and self._clock is None:
            self._clock = stamp                          # loaded model: start the refit clock
        if self._clock is not None and cfg.refit_period_s > 0 and \
                stamp - self._clock > self.CLOCK_JUMP_PERIODS * cfg.refit_period_s:
            self._clock = stamp            # a jump forward (a bag loop, a bad stamp): no refit
            h.time_jumps_forward += 1
        due = (self._requested
               or (model is None and self._clock is None)                      # first fit
               or (cfg.refit_period_s > 0 and self._clock is not None and
                   stamp - self._clock >= cfg.refit_period_s)                 # periodic
               or (model is not None and self._outgrown(parts.window) and
                   h.consecutive_refit_failures == 0)                         # buffer doubled
               or (self._retry_at is not None and parts.window.seq >= self._retry_at)
               or (self._novel and model is not None))                        # new territory
        if due:
            self._requested = False
            self._retry_at = None
            self._clock = stamp
            return self._fit_job(last_t, parts)
        if cfg.refit_mode != 'sync' and model is not None and model.certificate().stale:
            # a stale model stays passive pointwise: re-prove at most every refit_period_s / 4
            # (longer after failed proofs), beside the answers; in line the proof comes with the
            # refits only (it would hold up the replay and be stale at the next sample)
            gap = self.proof_gap(cfg.refit_period_s / 4.0 if cfg.refit_period_s > 0 else 0.25, h)
            last = self._last_recert
            if (last is None or stamp < last or stamp - last >= gap or
                    (idle and served.held != self._recert_seq)) and self._proof_spaced():
                self._last_recert, self._recert_seq = stamp, served.held
                return self.recertify_job(last_t, parts)
        return None

    def _proof_spaced(self) -> bool:
        """
        Tell whether the last re-proof left the job thread free long enough (wall clock).

        Re-proofs share the one job thread with the refits: a learner short of CPU (two busy
        processes beside it) spent 10-15 s of wall on each domain proof of the A320, one after
        the other, and refitted every 14-18 s instead of every 10. So after a re-proof the next
        waits ``PROOF_SPACING`` x its wall time: the proofs take at most a quarter of the job
        thread, and a refit due meanwhile runs first.
        """
        return self._proof_done is None or \
            time.monotonic() >= self._proof_done + self.PROOF_SPACING * self._proof_wall

    def recertify_job(self, last_t: Optional[float], parts, config=None,
                      full: bool = False) -> RefitJob:
        """
        Return a job that re-proves a copy of the served model (under the lock).

        config : the job's configuration (default: a copy of the current one); full : the
        full proof (``switch``).
        """
        served = parts.served
        cfg = dataclasses.replace(parts.settings()) if config is None else config
        return RefitJob('recertify', cfg, served.held, self._generation, last_t,
                        model=copy.deepcopy(served.model), source=served.model,
                        target_gen=served.gen, full=full)

    def _fit_job(self, last_t: Optional[float], parts) -> RefitJob:
        h, cfg, win, st = parts.health, parts.settings(), parts.window, parts.structure
        h.refits_started += 1
        k = h.refits_started
        optimize = (parts.served.model is None or self._hyper is None or
                    (cfg.optimize_every_n_refits > 0 and k % cfg.optimize_every_n_refits == 0)
                    or self._outgrown(win) or self._novel)
        self._novel = False
        if st.auto:
            st.reselect(win, h)         # prior='auto': structure and correction on the history
        Q, T = win.arrays()
        if optimize and Q.shape[0]:
            self._hyper_box = (Q.min(axis=0), Q.max(axis=0))
        # re-learning on data like the last optimum's refines it (no restarts); after the buffer
        # doubled the data changed enough to search again from scratch
        warm = self._hyper is not None and not self._outgrown(win)
        # the served model as it is now: the candidate's opponent on the samples that arrive
        # during its fit (appended to the served one meanwhile; a snapshot keeps this state)
        model = parts.served.model
        base = None if model is None else model.snapshot(variance=False)
        return RefitJob('fit', dataclasses.replace(cfg), win.seq, self._generation, last_t,
                        Q=Q, T=T, optimize=optimize, hyper=st.with_prior(self._hyper),
                        hyper_rows=win.even_arrays() if optimize else None,
                        warm=warm, kw=st.model_kw(cfg), correction=st.correction(),
                        target_gen=win.target_gen, source=base)

    def request(self, last_t: Optional[float], parts) -> Tuple[Optional[RefitJob], str]:
        """Return the refit asked for now, or (None, why not) (under the lock)."""
        cfg = parts.settings()
        if not cfg.learning:
            return None, 'learning is off (parameter learning): the model is frozen'
        if parts.window.size < cfg.min_samples:
            return None, f'not enough samples ({parts.window.size} < min_samples ' \
                f'{cfg.min_samples})'
        if self.running():
            return None, 'a refit is already running'
        if last_t is not None:
            self._clock = last_t
        return self._fit_job(last_t, parts), ''

    # ------------------------------------------------------------------ running
    def start(self, job: RefitJob, parts) -> Tuple[bool, str]:
        """
        Run ``job``: in the job thread (``async``), else in line; (ok, message).

        parts : the learner's parts (``parts.Parts``), passed on to ``run`` (the job thread is
        handed them).
        """
        what = (f'{job.kind} started' if job.kind != 'fit' else
                f'refit started on {job.Q.shape[0]} samples '
                f'({"optimizing" if job.optimize else "fixed"} hyper-parameters)')
        with parts.lock:
            if self.running():
                return False, 'a refit is already running'
            self._pending.clear()
            if job.config.refit_mode == 'async':
                self._thread = threading.Thread(target=self.run, args=(job, parts),
                                                name='dgp_refit', daemon=True)
                self._thread.start()
                return True, what
            self._thread = None
        return self.run(job, parts)

    def run(self, job: RefitJob, parts) -> Tuple[bool, str]:
        """
        Run ``job`` here; a freeze wanted meanwhile (learning switched off) follows it.

        parts : the learner's parts (``parts.Parts``): a freeze is ``parts.switch``'s.
        """
        switch = parts.switch
        if job.kind == 'freeze':
            return switch.freeze(job, parts)
        out = self._integrate(run_job(job, self._factory), parts)
        follow = switch.due_after_job(parts)    # switched off while it ran (and discarded it)
        return switch.freeze(follow, parts) if follow is not None else out

    def prove_now(self, job: RefitJob, parts) -> Tuple[bool, str]:
        """Run a re-proof job here, with no freeze after it (the freeze's own proof)."""
        return self._integrate(run_job(job, self._factory), parts)

    def _integrate(self, res: RefitResult, parts) -> Tuple[bool, str]:
        """
        Finish a job: held-out check, catch-up, swap, record (module docstring).

        A fitted candidate that passes the held-out check is refitted at its new
        hyper-parameters on the window as it is now (the samples that arrived during its fit
        included) and swapped in; a re-proven model is swapped in if the served model is still
        the one it was copied from, with the samples appended to that one meanwhile.
        """
        job, model, ok, why, proof = res.job, res.model, res.ok, res.reason, res.proof
        cfg, h, win = job.config, parts.health, parts.window
        t0 = time.perf_counter() - res.seconds
        seq, gen = job.seq, job.target_gen
        try:
            if ok and job.kind == 'fit':
                ok, why, _ = self._held_out(model, job.source, job.seq, parts.lock)
                if not ok:
                    h.refits_rejected += 1
            if ok and job.kind == 'fit':
                with parts.lock:
                    newer = win.seq != job.seq or win.target_gen != job.target_gen
                    Q, T = win.arrays() if newer else (None, None)
                    correction = parts.structure.correction()
                    seq, gen = win.seq, win.target_gen
                if newer:
                    model.fit(Q, T, optimize=False, prove=False)
                    model.correction_ = correction
        except Exception as exc:
            ok, why = False, f'{type(exc).__name__}: {exc}'
        dt = time.perf_counter() - t0
        with parts.lock:
            if job.generation != self._generation:
                return False, 'discarded: the estimator was reset'
            self._pending.clear()
            if ok and (job.kind == 'recertify' or job.full):      # a fit is proven after it
                h.proof_done(proof, job.stamp)
            if job.kind == 'recertify':
                self._proof_done, self._proof_wall = time.monotonic(), dt
                return self._recertified(job, model, ok, why, proof, dt, parts)
            if ok:
                self._swap(job, model, seq, gen, parts)
            if not ok and why.startswith('sanity check') and 'samples that arrived' not in why:
                h.refits_rejected += 1
            if ok:
                self._retry_at = None
            elif parts.served.model is None or h.consecutive_refit_failures < self.MAX_RETRIES:
                # a rejected candidate is retried once fresh samples arrived (it learns from
                # the ones it failed on), not only at the next refit period; a short bag, or
                # refit_period_s = 0, would otherwise keep the first model (or, before any, the
                # prior) for good
                self._retry_at = win.seq + max(10, cfg.buffer_size // 4) * \
                    2 ** min(h.consecutive_refit_failures, 6)          # backing off
            h.refit_done(ok, dt, job.stamp, job.optimize,
                         '' if ok else (why if model is None else f'not swapped in: {why}'),
                         time.time(), res.seconds, res.cpu_seconds)
            error = h.last_refit_error
        if ok and cfg.model_path:
            try:
                parts.save(parts, cfg.model_path)
            except Exception as exc:
                with parts.lock:
                    h.last_refit_error = f'refit ok but saving failed: {exc}'
        return (True, f'refit ok in {dt:.3f} s') if ok else (False, error)

    def _recertified(self, job: RefitJob, model, ok: bool, why: str, proof: str,
                     dt: float, parts) -> Tuple[bool, str]:
        """
        Serve a re-proven copy of the model (under the lock); (ok, message).

        Only if the served model is still the one it was copied from (a rebase or a refit
        replaces it otherwise); the samples appended to that one since are appended to the copy
        (its certificate then goes stale again, its repairs stay).
        """
        h, served = parts.health, parts.served
        if not ok:
            h.last_refit_error = f'recertification failed: {why}'
            return False, h.last_refit_error
        if served.model is not job.source:
            return False, 'recertified, but a newer model serves'
        if served.held != job.seq:
            run = parts.window.run_of(job.seq, served.held, job.target_gen)
            if run is None:
                return False, 'recertified, but the model moved on'
            try:
                model.update(*run)
            except Exception as exc:    # noqa: BLE001 - the served model stays
                return False, f'recertified, but catching up failed: {exc}'
        served.replace(model)
        h.recertifications += int(not proof)
        if proof:
            h.last_refit_error = f'recertification failed: {proof}'
            return False, h.last_refit_error
        return True, f'recertified in {dt:.3f} s'

    def _held_out(self, model, base, seq: int, lock) -> Tuple[bool, str, int]:
        """
        Compare the candidate with ``base`` and its parametric part on the samples that arrived.

        ``base``: the served model when the fit started (a snapshot; the served one has
        appended them since). The samples that arrived while the candidate was fitted (none in
        line, where the elements' cross-validation alone holds a GP against the parametric
        part), the first ``HELD_OUT_EVERY``, then as many spread over the rest
        (``worker.held_out``). Returns (ok, reason, seq of the last of them).
        """
        with lock:
            newer = [(s, q, t) for (s, q, t) in self._pending if s > seq]
        if base is None or len(newer) < 10:
            return True, '', seq
        k = self.HELD_OUT_EVERY
        if len(newer) > 2 * k:          # the first k, then k spread over the rest
            rest = newer[k:]
            newer = newer[:k] + [rest[i] for i in np.linspace(0, len(rest) - 1, k).astype(int)]
        ok, why = held_out(model, base, np.array([q for _, q, _ in newer]),
                           np.array([t for _, _, t in newer]), self.HELD_OUT_FACTOR)
        return ok, why, newer[-1][0]

    def _swap(self, job: RefitJob, model, seq: int, gen: int, parts) -> None:
        """Install a fitted candidate that holds the samples up to ``seq`` (under the lock)."""
        parts.served.based(model, seq, gen)
        self._hyper = model.hyperparams_
        if job.optimize:
            self._opt_n = job.Q.shape[0]
            picked = getattr(model, 'fit_info_', {}).get('elements')
            if picked:
                parts.health.elements = choice_summary(picked['choices'])
                parts.health.elements_scores = {c: [round(v, 4) for v in e]
                                                for c, e in picked['heldout'].items()}

    def wait(self, timeout: Optional[float] = None) -> bool:
        """Block until no job is running; True if none is running at return."""
        t = self._thread
        if t is not None:
            t.join(timeout)
        return not self.running()

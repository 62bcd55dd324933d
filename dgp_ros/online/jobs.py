"""
Refit and re-proof jobs of the learner: start, integrate, swap (no rclpy).

``JobRunner`` is the job half of :class:`~dgp_ros.online.learner.Learner`: it starts a job
(``worker.run_job``: in a background thread with ``refit_mode='async'``, in line with
``'sync'``), and integrates its result: the candidate is compared one step ahead with the
incumbent on the samples that arrived during its fit (``_held_out``), refitted at its new
hyper-parameters on the buffer as it is now, and swapped in under the lock, which is held only to
read the buffer and for the swap. A re-proven model is caught up with the samples appended to the
served one meanwhile. An unproven candidate serves with every answer projected (``worker``);
re-proofs after failed ones wait longer (``Absorber._proof_gap``).
"""
from __future__ import annotations

import copy
import dataclasses
import threading
import time
from typing import Optional, Tuple

import numpy as np

from dgp_ros.gp.select import choice_summary

from .worker import prove, RefitJob, RefitResult, run_job

__all__ = ['JobRunner']


class JobRunner:
    """Mixin: the learner's jobs (see the module docstring); the learner provides the state."""

    #: a stamp this many refit periods ahead of the refit clock is a jump, not elapsed time
    CLOCK_JUMP_PERIODS = 10
    #: a candidate whose error on the samples that arrived during its fit exceeds the current
    #: model's by this factor (plus 1 % of their variance) is not swapped in
    HELD_OUT_FACTOR = 3.0
    #: rejected candidates retried on fresh data before waiting for the next refit period
    #: (without any model: always, each retry waiting twice as many samples, up to 64 x)
    MAX_RETRIES = 3

    #: a learned sample beyond the velocities the hyper-parameters were learned on, by this
    #: fraction of their range on any joint, asks for an optimizing refit (``_note_novelty``) ...
    NOVELTY_MARGIN = 0.1
    #: ... where the model's error on it is beyond this many times its recent RMS error ...
    NOVELTY_SURPRISE = 2.5
    #: ... at most once per this much learning time (s)
    NOVELTY_GAP_S = 1.0

    # ------------------------------------------------------------------ decisions
    def _note_novelty(self, stamp: float, qd: np.ndarray, surprise: float) -> None:
        """
        Ask for an optimizing refit when the data leave what the hyper-parameters were fitted on.

        A refit by the clock answers a system that enters new territory (an aircraft at its
        first negative angle of attack and 20 % more airspeed) for up to ``refit_period_s`` x
        ``optimize_every_n_refits`` with hyper-parameters learned where it was before; the
        samples appended meanwhile are taken at those. So a learned sample beyond the box of the
        last optimization's velocities (grown by ``NOVELTY_MARGIN`` of its range) that the model
        answered badly (``surprise``: its one-step error over its recent RMS error, beyond
        ``NOVELTY_SURPRISE``, where the error is more than ``grounds.SURPRISE_SIGNAL`` of the
        force's RMS) makes the next refit one that re-learns them, at most
        every ``NOVELTY_GAP_S`` of learning time (``novelty_refits`` on /diagnostics). A model
        that extrapolates well into new territory is left alone: an arm's first cycle leaves
        the box all the time.
        """
        box = self._hyper_box
        cfg = self.config
        if box is None or self._model is None or not surprise > self.NOVELTY_SURPRISE or \
                cfg.optimize_every_n_refits == 0 or cfg.refit_period_s == 0:    # by request
            return
        lo, hi = box
        grow = self.NOVELTY_MARGIN * np.maximum(hi - lo, 1e-12)
        if np.any(qd < lo - grow) or np.any(qd > hi + grow):
            last = self._novel_t
            if last is None or stamp < last or stamp - last >= self.NOVELTY_GAP_S:
                self._novel, self._novel_t = True, stamp
                self.health.novelty_refits += 1

    def _hypers_outgrown(self) -> bool:
        """Tell whether the buffer has at least doubled since the hyper-parameters were learned."""
        return 0 < self._opt_n and self._buf.size >= 2 * self._opt_n

    def _next_job(self, stamp: float, idle: bool = False) -> Optional[RefitJob]:
        """
        Make the one decision (under the lock) of what the worker does next, if anything.

        ``idle``: the stream paused (``Learner.poll``): a stale model not tried since it last
        changed is re-proven without waiting for the re-proof period.
        """
        cfg = self.config
        if not cfg.learning:
            return self._freeze_job()           # serve only: nothing else (``switch``)
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
               or (self._retry_at is not None and self._seq >= self._retry_at)   # rejected
               or (self._novel and self._model is not None))                  # new territory
        if due:
            self._refit_requested = False
            self._retry_at = None
            self._clock = stamp
            return self._fit_job()
        if cfg.refit_mode != 'sync' and self._model is not None and \
                self._model.certificate().stale:
            # a stale model stays passive pointwise: re-prove at most every refit_period_s / 4
            # (longer after failed proofs), beside the answers; in line the proof comes with the
            # refits only (it would hold up the replay and be stale at the next sample)
            gap = self._proof_gap(cfg.refit_period_s / 4.0 if cfg.refit_period_s > 0 else 0.25)
            last = self._last_recert
            if last is None or stamp < last or stamp - last >= gap or \
                    (idle and self._model_seq != self._recert_seq):
                self._last_recert, self._recert_seq = stamp, self._model_seq
                return RefitJob('recertify', dataclasses.replace(cfg), self._model_seq,
                                self._generation, self._last_t,
                                model=copy.deepcopy(self._model), source=self._model,
                                target_gen=self._model_gen)
        return None

    def _fit_job(self) -> RefitJob:
        h, cfg = self.health, self.config
        h.refits_started += 1
        k = h.refits_started
        optimize = (self._model is None or self._hyper is None or
                    (cfg.optimize_every_n_refits > 0 and k % cfg.optimize_every_n_refits == 0)
                    or self._hypers_outgrown() or self._novel)
        self._novel = False
        if self.auto:
            self._reselect()            # prior='auto': structure and correction on the history
        Q, T = self._buf.arrays()
        if optimize and Q.shape[0]:
            self._hyper_box = (Q.min(axis=0), Q.max(axis=0))
        # re-learning on data like the last optimum's refines it (no restarts); after the buffer
        # doubled the data changed enough to search again from scratch
        warm = self._hyper is not None and not self._hypers_outgrown()
        # the served model as it is now: the candidate's opponent on the samples that arrive
        # during its fit (appended to the served one meanwhile; a snapshot keeps this state)
        base = None if self._model is None else self._model.snapshot(variance=False)
        return RefitJob('fit', dataclasses.replace(cfg), self._seq, self._generation,
                        self._last_t, Q=Q, T=T, optimize=optimize,
                        hyper=self._with_prior(self._hyper),
                        warm=warm, kw=self._model_kw(cfg), correction=self._correction(),
                        target_gen=self._target_gen, source=base)

    def request_refit(self) -> Tuple[bool, str]:
        """Refit now (async: start it in the background). Returns (ok, message)."""
        with self._lock:
            if not self.config.learning:
                return False, 'learning is off (parameter learning): the model is frozen'
            if self._buf is None or self._buf.size < self.config.min_samples:
                n = 0 if self._buf is None else self._buf.size
                return False, f'not enough samples ({n} < min_samples {self.config.min_samples})'
            if self.refit_running():
                return False, 'a refit is already running'
            if self._last_t is not None:
                self._clock = self._last_t
            job = self._fit_job()
        return self._start(job)

    # ------------------------------------------------------------------ running
    def _start(self, job: RefitJob) -> Tuple[bool, str]:
        what = (f'{job.kind} started' if job.kind != 'fit' else
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
        Finish a job: held-out check, catch-up, swap, record (module docstring).

        A fitted candidate that passes the held-out check is refitted at its new
        hyper-parameters on the buffer as it is now (the samples that arrived during its fit
        included) and swapped in; a re-proven model is swapped in if the served model is still
        the one it was copied from, with the samples appended to that one meanwhile.
        """
        job, model, ok, why, proof = res.job, res.model, res.ok, res.reason, res.proof
        cfg, h = job.config, self.health
        t0 = time.perf_counter() - res.seconds
        seq, gen = job.seq, job.target_gen
        try:
            if ok and job.kind == 'fit':
                ok, why, _ = self._held_out(model, job.source, job.seq)
                if not ok:
                    h.refits_rejected += 1
            if ok and job.kind == 'fit':
                with self._lock:
                    newer = self._seq != job.seq or self._target_gen != job.target_gen
                    Q, T = self._buf.arrays() if newer else (None, None)
                    correction = self._correction()
                    seq, gen = self._seq, self._target_gen
                if newer:
                    model.fit(Q, T, optimize=False)
                    model.correction_ = correction
                    proof = prove(model, cfg.passivity)
        except Exception as exc:
            ok, why = False, f'{type(exc).__name__}: {exc}'
        dt = time.perf_counter() - t0
        with self._lock:
            if job.generation != self._generation:
                return False, 'discarded: the estimator was reset'
            self._pending.clear()
            if ok:
                h.proof_done(proof)
            if job.kind == 'recertify':
                return self._recertified(job, model, ok, why, proof, dt)
            if ok:
                self._swap(job, model, seq, gen)
            if not ok and why.startswith('sanity check') and 'samples that arrived' not in why:
                h.refits_rejected += 1
            if ok:
                self._retry_at = None
            elif self._model is None or h.consecutive_refit_failures < self.MAX_RETRIES:
                # a rejected candidate is retried once fresh samples arrived (it learns from
                # the ones it failed on), not only at the next refit period; a short bag, or
                # refit_period_s = 0, would otherwise keep the first model (or, before any, the
                # prior) for good
                self._retry_at = self._seq + max(10, cfg.buffer_size // 4) * \
                    2 ** min(h.consecutive_refit_failures, 6)          # backing off
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

    def _recertified(self, job: RefitJob, model, ok: bool, why: str, proof: str,
                     dt: float) -> Tuple[bool, str]:
        """
        Serve a re-proven copy of the model (under the lock); (ok, message).

        Only if the served model is still the one it was copied from (a rebase or a refit
        replaces it otherwise); the samples appended to that one since are appended to the copy
        (its certificate then goes stale again, its repairs stay).
        """
        h = self.health
        if not ok:
            h.last_refit_error = f'recertification failed: {why}'
            return False, h.last_refit_error
        if self._model is not job.source:
            return False, 'recertified, but a newer model serves'
        if self._model_seq != job.seq:
            rows = [r for r in self._rows if job.seq < r[0] <= self._model_seq]
            if len(rows) != self._model_seq - job.seq or \
                    any(r[1] != job.target_gen for r in rows):
                return False, 'recertified, but the model moved on'
            try:
                model.update(np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))
            except Exception as exc:    # noqa: BLE001 - the served model stays
                return False, f'recertified, but catching up failed: {exc}'
        self._model = model
        self._version += 1
        h.recertifications += int(not proof)
        if proof:
            h.last_refit_error = f'recertification failed: {proof}'
            return False, h.last_refit_error
        return True, f'recertified in {dt:.3f} s'

    def _held_out(self, model, base, seq: int) -> Tuple[bool, str, int]:
        """
        Compare the candidate with the served model and its own parametric part on new samples.

        These are the samples that arrived while the candidate was fitted (none in sync mode,
        where the elements' cross-validation alone holds a GP against the parametric part):
        the candidate, ``base`` (the served model when the fit started: a snapshot, the served
        one has appended them since) and the candidate's prior mean each predict them without
        having learned them.
        Returns (ok, reason, seq of the last of them).
        """
        with self._lock:
            newer = [(s, q, t) for (s, q, t) in self._pending if s > seq]
        if base is None or len(newer) < 10:
            return True, '', seq
        k = self.HELD_OUT_EVERY
        if len(newer) > 2 * k:          # the first k, then k spread over the rest
            rest = newer[k:]
            newer = newer[:k] + [rest[i] for i in np.linspace(0, len(rest) - 1, k).astype(int)]
        try:
            Qn = np.array([q for _, q, _ in newer])
            T = np.array([t for _, _, t in newer])
            e_new = model.predict(Qn) - T
            e_old = base.predict(Qn) - T
            e_par = model.mean_.force(Qn) - T if model.posterior_.structure.has_damping \
                else e_old
            seq = newer[-1][0]
        except Exception as exc:          # noqa: BLE001 - a broken candidate is caught later
            return True, f'held-out check skipped: {exc}', seq
        T = np.array(T)
        e_new = float(np.mean(np.square(e_new)))
        e_old = float(np.mean(np.square(e_old)))
        e_par = float(np.mean(np.square(e_par)))
        # a candidate within 1 % of the samples' variance is good enough, however good the
        # incumbent happens to be on them
        floor = float(np.mean(np.var(T, axis=0))) * 1e-2
        for e_ref, whose in ((e_old, "the current model's"), (e_par, "its parametric part's")):
            if e_new > self.HELD_OUT_FACTOR * e_ref + floor:
                return False, (f'sanity check: error on the {len(T)} samples that arrived '
                               f'during the fit {e_new / max(e_ref, 1e-300):.1f} x {whose}'), seq
        return True, '', seq

    def _swap(self, job: RefitJob, model, seq: int, gen: int) -> None:
        """Install a fitted candidate that holds the samples up to ``seq`` (under the lock)."""
        self._based(model, seq, gen)
        self._hyper = model.hyperparams_
        if job.optimize:
            self._opt_n = job.Q.shape[0]
            picked = getattr(model, 'fit_info_', {}).get('elements')
            if picked:
                self.health.elements = choice_summary(picked['choices'])
                self.health.elements_scores = {c: [round(v, 4) for v in e]
                                               for c, e in picked['heldout'].items()}

    def wait_for_refit(self, timeout: Optional[float] = None) -> bool:
        """Block until no refit is running; True if none is running at return."""
        t = self._thread
        if t is not None:
            t.join(timeout)
        return not self.refit_running()

    def close(self, timeout: float = 30.0) -> None:
        """Wait (bounded) for a running refit to finish; call before exit."""
        self.wait_for_refit(timeout)

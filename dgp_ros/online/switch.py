"""
The learning switch of the learner: stop learning, prove and save the model; resume (no rclpy).

``learning`` (a parameter of ``config``) off means serve only: the model that serves when it is
switched off (or the one loaded from ``model_path`` at start) is the one every later answer
comes from. Nothing is learned from the stream (``Learner._add`` counts the sample as
``samples_not_learned``), no refit, rebase or re-proof runs, ``~/refit`` is refused; the
friction residual front end still runs, so ``~/friction_residual`` goes on for monitoring.

Switching it off (``Learner.reconfigure``) freezes the model in a job of its own (``freeze``: in
line with ``refit_mode='sync'``, else in the refit thread, so neither the message path nor the
parameter call waits for it):

1. a refit or rebase still running is discarded (its candidate would change the model after the
   switch);
2. the model is brought up to what was learned, as ``save`` does: samples not appended yet are
   taken in, and with ``prior='auto'`` the structure sees the whole history;
3. it is proven once with the full proof (``recertify(full=True)``: what a fit proves, from
   scratch, unless its certificate holds), served, and saved to ``model_path`` when set.

Until step 3 is done ``status()['learning']`` is 'stopping' and the answers come from the model
as it was (with its guarantee then); afterwards 'off', with the proven guarantee, and every
answer comes from exactly the saved model, blended by the gains it carries (``grounds``: the
long memory's, what its ``predict`` applies too); the confidence published beside it is the one
it had earned when learning stopped. A save asked for while learning stops waits for the stop
(``wait_stopped``).
Switching it on again resumes learning where it stopped: the same buffer, model and history;
the refit clock starts again at the next sample.
"""
from __future__ import annotations

import copy
import dataclasses
from typing import Optional, Tuple

from .worker import RefitJob

__all__ = ['LearningSwitch']


class LearningSwitch:
    """Mixin of :class:`~dgp_ros.online.learner.Learner`: the switch (module docstring)."""

    def _reset_switch(self) -> None:
        """Forget the switch's work (a new learner state: nothing to freeze)."""
        self._freeze_wanted = False       # switched off: the model still to be proven and saved
        self._freezing = False            # its job runs

    @property
    def learning_state(self) -> str:
        """Return 'on', 'stopping' (the model being proven and saved) or 'off'."""
        if self.config.learning:
            return 'on'
        return 'stopping' if self._freeze_wanted or self._freezing else 'off'

    #: how long a save waits for learning to stop (s)
    STOP_WAIT_S = 60.0

    def wait_stopped(self, timeout: float = STOP_WAIT_S) -> bool:
        """
        Wait (bounded) while learning is stopping; True when it is not (any more).

        A save asked for meanwhile (``~/save_model``) writes the model that serves once it is
        proven, not the one before. The freeze job itself saves without waiting (in line, with
        ``refit_mode='sync'``, nothing else runs while it does).
        """
        import threading
        import time
        end = time.monotonic() + timeout
        while self.learning_state == 'stopping' and time.monotonic() < end:
            t = self._thread
            if t is None or t is threading.current_thread():
                break                   # in line, or the freeze's own save
            if t.is_alive():
                t.join(min(0.05, max(0.0, end - time.monotonic())))
            else:
                time.sleep(0.005)
        return self.learning_state != 'stopping'

    def _learning_switched(self, on: bool) -> None:
        """Under the lock, after ``config.learning`` changed to ``on``."""
        self._gains_seq += 1                    # the snapshot's gains switch memory (grounds)
        if on:
            self._freeze_wanted = False
            self._clock = None                  # the refit clock starts at the next sample
            self._last_recert = None
            self._last_added_t = self._last_t   # no 'stalled' warning for the pause
            return
        self._generation += 1                   # a running refit or rebase is discarded
        self._freeze_wanted = self._model is not None

    def _switch_note(self, what: str, on: bool) -> str:
        """Start the freeze job if one is wanted (outside the lock); ``what`` with a note."""
        if on:
            return f'{what}; learning on'
        job = self._freeze_job()
        if job is not None:
            self._start(job)
        with self._lock:
            frozen = self._model is not None
        note = ('learning off: the model is proven and saved (learning: stopping, then off)'
                if frozen else 'learning off: no model yet, the prior serves')
        return f'{what}; {note}'

    def _freeze_job(self) -> Optional[RefitJob]:
        """Return the freeze job when one is wanted and no job runs (else None)."""
        with self._lock:
            if not self._freeze_wanted or self._freezing or self.refit_running():
                return None
            return RefitJob('freeze', dataclasses.replace(self.config), self._seq,
                            self._generation, self._last_t)

    def _run(self, job: RefitJob) -> Tuple[bool, str]:
        if job.kind == 'freeze':
            return self._freeze(job)
        out = super()._run(job)
        with self._lock:
            # switched off while this job ran (and discarded it): freeze now, in this thread
            freeze = self._freeze_wanted and not self._freezing
            job = RefitJob('freeze', dataclasses.replace(self.config), self._seq,
                           self._generation, self._last_t) if freeze else None
        return self._freeze(job) if job is not None else out

    def _freeze(self, job: RefitJob) -> Tuple[bool, str]:
        """Do steps 2 and 3 of the module docstring (step 1 was the switch)."""
        with self._lock:
            if not self._freeze_wanted or job.generation != self._generation:
                return False, 'nothing to freeze'
            self._freeze_wanted, self._freezing = False, True
        try:
            with self._lock:
                if self._model is not None and self.unheld:
                    self.catch_up()
                behind = self._model is not None and (self.unheld or self._history_grew())
                if behind:
                    self._reselect_now = True
            if behind:
                self._absorb()          # a rebase: what save does before it writes
            with self._lock:
                model = self._model
                if model is None or job.generation != self._generation:
                    return False, 'no model to freeze'
                proof = RefitJob('recertify', job.config, self._model_seq, self._generation,
                                 self._last_t, model=copy.deepcopy(model), source=model,
                                 target_gen=self._model_gen, full=True)
            ok, what = super()._run(proof)
            path = job.config.model_path
            with self._lock:
                current = job.generation == self._generation and self._model is not None
            if current and path:
                try:
                    what = f'{what}; saved to {self.save(path)}'
                except Exception as exc:        # noqa: BLE001 - the model serves all the same
                    with self._lock:
                        self.health.last_refit_error = f'frozen, but saving failed: {exc}'
            return ok, what
        finally:
            with self._lock:
                self._freezing = False

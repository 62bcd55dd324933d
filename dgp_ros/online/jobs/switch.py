"""
The learning switch of the learner: stop learning, prove and save the model; resume (no rclpy).

A part of :class:`~dgp_ros.online.learner.Learner` that owns the freeze's state (wanted, running)
and runs it; the learner says when the switch moves (``stop``, ``resume``).

``learning`` (a parameter of ``config``) off means serve only: the model that serves when it is
switched off (or the one loaded from ``model_path`` at start) is the one every later answer
comes from. Nothing is learned from the stream (``Learner._add`` counts the sample as
``samples_not_learned``), no refit, rebase or re-proof runs, ``~/refit`` is refused; the
friction residual front end still runs, so ``~/friction_residual`` goes on for monitoring.

Switching it off (``Learner.reconfigure``) freezes the model in a job of its own (``freeze``: in
line with ``refit_mode='sync'``, else in the refit thread, so neither the message path nor the
parameter call waits for it; ``refits.Refits`` runs it):

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

import dataclasses
import threading
import time
from typing import Optional, Tuple

from .worker import RefitJob

__all__ = ['Switch']


class Switch:
    """
    The learning switch (module docstring).

    It keeps no other part: the steps that read or change them (``job``, ``due_after_job``,
    ``start``, ``freeze``, ``wait_stopped``) are passed the learner's parts (``parts.Parts``:
    the lock, the settings, the window, structure, served model, rebases and refits a freeze
    brings up to date and proves through, the health record, ``last_t`` (the newest sample's
    learning time: the job's stamp) and ``save`` (the step that writes the frozen model)).
    """

    #: how long a save waits for learning to stop (s)
    STOP_WAIT_S = 60.0

    def __init__(self):
        self._wanted = False          # switched off: the model still to be proven and saved
        self._freezing = False        # its job runs

    def state(self, learning: bool) -> str:
        """Return 'on', 'stopping' (the model being proven and saved) or 'off'."""
        if learning:
            return 'on'
        return 'stopping' if self._wanted or self._freezing else 'off'

    @property
    def wanted(self) -> bool:
        """Tell whether a freeze is wanted and not started yet."""
        return self._wanted

    def stop(self, has_model: bool) -> None:
        """Learning was switched off (under the lock): freeze the model if there is one."""
        self._wanted = has_model

    def resume(self) -> None:
        """Learning was switched on again (under the lock): nothing to freeze."""
        self._wanted = False

    def wait_stopped(self, parts, timeout: float = STOP_WAIT_S) -> bool:
        """
        Wait (bounded) while learning is stopping; True when it is not (any more).

        A save asked for meanwhile (``~/save_model``) writes the model that serves once it is
        proven, not the one before. The freeze job itself saves without waiting (in line, with
        ``refit_mode='sync'``, nothing else runs while it does).
        """
        end = time.monotonic() + timeout
        while self.state(parts.settings().learning) == 'stopping' and time.monotonic() < end:
            t = parts.refits.thread
            if t is None or t is threading.current_thread():
                break                   # in line, or the freeze's own save
            if t.is_alive():
                t.join(min(0.05, max(0.0, end - time.monotonic())))
            else:
                time.sleep(0.005)
        return self.state(parts.settings().learning) != 'stopping'

    def _job(self, parts) -> RefitJob:
        return RefitJob('freeze', dataclasses.replace(parts.settings()), parts.window.seq,
                        parts.refits.generation, parts.last_t())

    def job(self, parts) -> Optional[RefitJob]:
        """Return the freeze job when one is wanted and no job runs (else None)."""
        with parts.lock:
            if not self._wanted or self._freezing or parts.refits.running():
                return None
            return self._job(parts)

    def due_after_job(self, parts) -> Optional[RefitJob]:
        """Return the freeze job wanted after a job that ran meanwhile (in its thread), or None."""
        with parts.lock:
            return self._job(parts) if self._wanted and not self._freezing else None

    def start(self, parts) -> None:
        """Start the freeze job if one is wanted (outside the lock)."""
        job = self.job(parts)
        if job is not None:
            parts.refits.start(job, parts)

    def freeze(self, job: RefitJob, parts) -> Tuple[bool, str]:
        """
        Do steps 2 and 3 of the module docstring (step 1 was the switch).

        The model is brought up to what was learned (appends, else a rebase with a fresh
        structure), proven with the full proof, and saved to ``model_path``.
        """
        lock, served, win, refits = parts.lock, parts.served, parts.window, parts.refits
        with lock:
            if not self._wanted or job.generation != refits.generation:
                return False, 'nothing to freeze'
            self._wanted, self._freezing = False, True
        try:
            with lock:
                if served.model is not None and served.unheld(win.seq):
                    served.catch_up(win, parts.health, parts.settings().buffer_size)
                behind = served.model is not None and (served.unheld(win.seq) or
                                                       parts.structure.history_grew())
                if behind:
                    parts.structure.reselect_soon()
            if behind:
                parts.rebases.run(parts, freeze=True)  # what save does before it writes
            with lock:
                if served.model is None or job.generation != refits.generation:
                    return False, 'no model to freeze'
                proof = refits.recertify_job(parts.last_t(), parts, job.config, full=True)
            ok, what = refits.prove_now(proof, parts)
            path = job.config.model_path
            with lock:
                current = job.generation == refits.generation and served.model is not None
            if current and path:
                try:
                    what = f'{what}; saved to {parts.save(parts, path)}'
                except Exception as exc:        # noqa: BLE001 - the model serves all the same
                    with lock:
                        parts.health.last_refit_error = f'frozen, but saving failed: {exc}'
            return ok, what
        finally:
            with lock:
                self._freezing = False

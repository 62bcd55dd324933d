"""
How new samples reach the model: appended at once, rebased on the buffer now and then (no rclpy).

* **Appends.** A learned sample is appended to the live model as soon as it is buffered (in
  line: in ``learn``; the learner process: once per round of samples, as one block): an exact
  rank-k update of each output's Cholesky factor at the model's hyper-parameters, O(N n^2 k).
  The next answer already knows it: on a trajectory that keeps reaching new velocities (the A320
  entering angles of attack it has not flown yet) the answer one step ahead comes from its
  neighbour of 1/60 s ago, not from ten samples ago.
* **Rebases** (``absorb``). An exact refit on the buffer at the same hyper-parameters, once
  ``buffer_size // REBASE_FRACTION`` samples were appended: the buffer replaces samples anywhere
  (coverage), appends only add, so a rebase brings the model back to the buffer (and its size
  back to ``buffer_size``), and takes a re-selected prior (``prior='auto'``). A learner process
  that falls behind (samples queue up for it) stops appending and takes them in by rebases only:
  one refit per batch is cheaper than a long block of appends.

Neither waits for a proof: a certifying mode's model serves with what its cheap certificates
give (the global bound, the eigenvalue floor) or, while a domain proof is pending, with every
answer projected; the proof runs in a re-proof job (``jobs``). Only a non-finite model is refused
(the samples then wait for the next refit, and the learner's health says why).
"""
from __future__ import annotations

from collections import deque
import threading
import time

import numpy as np

__all__ = ['Absorber']


class Absorber:
    """
    Mixin of :class:`~dgp_ros.online.learner.Learner`: appends and rebases (module docstring).

    Uses the learner's ``_lock``, ``_buf``, ``_model``, ``_hyper``, ``_seq``, ``_generation``,
    ``_version``, ``_factory``, ``config`` and ``health``; owns ``_rows``, ``_model_seq``,
    ``_model_gen``, ``_target_gen``, ``_appended`` (set by ``_reset_absorber``).
    """

    #: a rebase once this fraction of ``buffer_size`` was appended since the last (re)fit
    REBASE_FRACTION = 4
    #: least wall time between two rebases in a learner process or thread (s)
    MIN_ABSORB_S = 0.02
    #: wait after a rebase, in units of its cost: 2 = at most a third of the time rebasing;
    #: a learner process raises it to BACKLOG_ABSORB_WAIT while samples queue up for it
    absorb_wait = 2.0
    BACKLOG_ABSORB_WAIT = 8.0
    #: append each sample in ``learn`` (in line); the learner process appends per round instead
    append_each = True
    #: appends keep up (a learner process clears it while samples queue up for it: rebases
    #: take them in then)
    appending = True

    def _reset_absorber(self, rows: int) -> None:
        """Forget what was appended (a new learner state; ``rows``: samples kept to append)."""
        self._rows: deque = deque(maxlen=max(1, rows))   # (seq, target generation, qd, target)
        self._model_seq = 0           # the model holds every learned sample up to this seq
        self._model_gen = 0           # the target generation of the samples it holds
        self._target_gen = 0          # bumped whenever the buffer's targets change (reselection)
        self._appended = 0            # samples appended since the model was (re)fitted
        self._append_blocked = False  # unheld samples the model cannot take by appending
        self._recert_seq = -1         # _model_seq when a re-proof was last started
        self._absorbed_at = 0.0       # perf_counter() at the end of the last rebase
        self._absorb_cost = 0.0       # wall seconds of the last rebase

    def _based(self, model, seq: int, gen: int) -> None:
        """Serve ``model``, fitted on the buffer of ``seq`` with targets of ``gen`` (locked)."""
        self._model = model
        self._model_seq, self._model_gen, self._appended = seq, gen, 0
        self._append_blocked = False
        self._version += 1

    @property
    def unheld(self) -> int:
        """Learned samples the model does not hold yet."""
        return self._seq - self._model_seq if self._model is not None else 0

    # ------------------------------------------------------------------ appends
    def catch_up_paused(self) -> None:
        """
        Append the samples the model does not hold yet, once the samples ran out.

        A learner process that fell behind appends nothing while samples queue up (its rebases
        take them in); when the stream pauses right after, nothing else would bring the last
        ones to the model before it resumes. Cheap when there is nothing to do.
        """
        if self.unheld and not self._append_blocked:
            self.catch_up()

    def catch_up(self) -> int:
        """
        Append every learned sample the model does not hold yet; returns how many.

        Nothing is appended when they are not all at hand in learning order with the model's
        targets (evicted, or retargeted by a re-selection): the next rebase takes them. A model
        that cannot take them (a singular update) is rebased instead.
        """
        with self._lock:
            if self._model is None or self._seq <= self._model_seq:
                return 0
            rows = [r for r in self._rows if r[0] > self._model_seq]
            if not rows or rows[0][0] != self._model_seq + 1 or \
                    any(r[1] != self._model_gen for r in rows):
                self._append_blocked = True
                return 0
            try:
                self._model.update(np.array([r[2] for r in rows]),
                                   np.array([r[3] for r in rows]))
            except Exception as exc:    # noqa: BLE001 - the rebase takes them
                self.health.last_absorb_error = f'append failed: {type(exc).__name__}: {exc}'
                self._appended = self.config.buffer_size     # rebase at once
                return 0
            self._model_seq = rows[-1][0]
            self._appended += len(rows)
            self._version += 1
            self.health.appends += len(rows)
            return len(rows)

    # ------------------------------------------------------------------ rebases
    def _absorb_due(self) -> bool:
        """
        Tell whether a rebase is due.

        When samples wait that appending does not take (a learner process that falls behind,
        samples of other targets), after ``buffer_size // REBASE_FRACTION`` appends, or when
        the structure is to be re-selected. In line
        (``sync``) at once (deterministic, in learning order); in a learner process or thread
        as soon as the last rebase's cost allows (at most a third of the time rebasing; a ninth
        while samples queue up for the learner: taking every sample in comes first).
        """
        if not self.absorb_wanted():
            return False
        if self.config.refit_mode == 'sync':
            return True
        return time.perf_counter() - self._absorbed_at >= max(self.MIN_ABSORB_S,
                                                              self.absorb_wait *
                                                              self._absorb_cost)

    def absorb_wanted(self) -> bool:
        """Tell whether a rebase is wanted, however soon its cost allows it (``_absorb_due``)."""
        if self._model is None or not self.config.learning:
            return False
        waiting = self.unheld and (not self.appending or self._append_blocked)
        return bool(waiting or self._reselect_due() or
                    self._appended >= max(1, self.config.buffer_size // self.REBASE_FRACTION))

    def _absorb_soon(self) -> None:
        """Rebase in line (``sync``), else in the absorber thread (never on the caller's path)."""
        if self.config.refit_mode == 'sync':
            self._absorb()
            return
        if self._absorber is None or not self._absorber.is_alive():
            self._absorber = threading.Thread(target=self._absorb_loop, name='dgp_absorb',
                                              daemon=True)
            self._absorber.start()
        self._absorb_wanted.set()

    def _absorb_loop(self) -> None:
        while True:
            self._absorb_wanted.wait()
            self._absorb_wanted.clear()
            self._absorb()

    def _absorb(self) -> None:
        """
        Refit the model on the buffer at its hyper-parameters (exact; O(N n^3)).

        The scales stay those of the last hyper-parameter fit; with ``prior='auto'`` the frozen
        prior is the newest fit of the long history (``structure``). A certifying mode's proof is
        left to the re-proof job (``fit(prove=False)``). The samples learned while it ran are
        appended to it after it is swapped in, by the thread that learns them.
        """
        t0 = time.perf_counter()
        with self._lock:
            seq, generation, hyper = self._seq, self._generation, self._hyper
            if self._reselect_due():
                self._reselect()        # retargets the buffer; the prior rides in the hyper
            gen = self._target_gen
            Q, T = self._buf.arrays()
            kw = dict(self._model_kw(), hyperparams=self._with_prior(hyper))
            correction = self._correction()
        why = ''
        try:
            model = self._factory(self.config.model, **kw).fit(Q, T, optimize=False,
                                                               prove=False)
            model.correction_ = correction
            if not np.all(np.isfinite(model.posterior_.weights)):
                why = 'non-finite weights'
        except Exception as exc:        # noqa: BLE001 - the incumbent keeps serving
            why = f'{type(exc).__name__}: {exc}'
        with self._lock:
            self._absorb_cost = time.perf_counter() - t0
            self._absorbed_at = time.perf_counter()
            if generation != self._generation or hyper is not self._hyper:
                return                  # reset, or a refit swapped in other hyper-parameters
            h = self.health
            if why:                     # the samples wait for the next refit
                h.absorbs_rejected += 1
                h.last_absorb_error = why
                return
            # the samples learned meanwhile are appended by the thread that learns them (in
            # a thread of the node process the message path answers from this very model)
            self._based(model, seq, gen)
            h.absorbs += 1
            h.last_absorb_error = ''

    def _proof_gap(self, base: float) -> float:
        """Stamp seconds between re-proofs: ``base``, doubled per failed proof in a row (<= 8x)."""
        return base * 2 ** min(self.health.proofs_failed_in_a_row, 3)

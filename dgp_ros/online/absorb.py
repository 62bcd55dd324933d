"""
Absorbing new samples: the learner's exact refit at fixed hyper-parameters (no rclpy).

New samples reach the model by one exact fit on the buffer per batch instead of a
one-sample update each: for 7 joints a windowed update cost about as much as a refit of 10
samples, and a refit also takes a buffer whose samples are replaced anywhere (coverage), not
only the oldest. The prior and the scales stay those of the last hyper-parameter fit. A model
that fails the bound check or (``certified``) the proof is not swapped in; the samples wait
for the next refit and the learner's health says why.
"""
from __future__ import annotations

import threading
import time

from .worker import provable, sane

__all__ = ['Absorber']


class Absorber:
    """
    Mixin of :class:`~dgp_ros.online.learner.Learner`: when and how new samples are absorbed.

    Uses the learner's ``_lock``, ``_buf``, ``_model``, ``_hyper``, ``_seq``, ``_fresh``,
    ``_generation``, ``_version``, ``_factory``, ``config`` and ``health``.
    """

    #: in line, new samples are absorbed every ``buffer_size // ABSORB_FRACTION`` of them
    ABSORB_FRACTION = 20
    #: least wall time between two absorbs in a learner process or thread (s)
    MIN_ABSORB_S = 0.02
    #: random probes of the bound check of an absorbed model (besides its training inputs)
    ABSORB_PROBES = 200
    #: wait after an absorb, in units of its cost: 2 = at most a third of the time absorbing;
    #: a learner process raises it to BACKLOG_ABSORB_WAIT while samples queue up for it
    absorb_wait = 2.0
    BACKLOG_ABSORB_WAIT = 8.0

    # ------------------------------------------------------------------ absorbing
    def _absorb_due(self) -> bool:
        """
        Tell whether the samples learned since the last refit are to be absorbed now.

        In line (``sync``): every ``absorb_every`` new samples (deterministic, in learning
        order). In a learner process or thread: as soon as the last refit's cost allows (at
        most a third of the time refitting; a ninth while samples queue up for the learner:
        taking every sample in comes first), so answers follow the data as closely as the
        machine affords.
        """
        if self._model is None or not self._fresh:
            return False
        if self.config.refit_mode == 'sync':
            return self._fresh >= max(1, self.config.buffer_size // self.ABSORB_FRACTION)
        return time.perf_counter() - self._absorbed_at >= max(self.MIN_ABSORB_S,
                                                              self.absorb_wait *
                                                              self._absorb_cost)

    def _absorb_soon(self) -> None:
        """Absorb in line (``sync``), else in the absorber thread (never on the caller's path)."""
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

        This is how new samples reach the model: one exact fit per batch instead of an update
        per sample (for 7 joints a windowed update cost about as much as a refit of 10 samples,
        and a refit also takes a buffer whose samples are replaced anywhere, not only the
        oldest). The scales stay those of the last hyper-parameter fit; with ``prior='auto'`` the
        frozen prior is the newest fit of the long history (``structure``).
        """
        t0 = time.perf_counter()
        with self._lock:
            seq, generation, hyper = self._seq, self._generation, self._hyper
            if self._reselect_due():
                self._reselect()        # retargets the buffer; the prior rides in the hyper
            Q, T = self._buf.arrays()
            kw = dict(self._model_kw(), hyperparams=self._with_prior(hyper))
            correction = self._correction()
        try:
            model = self._factory(self.config.model, **kw).fit(Q, T, optimize=False)
            model.correction_ = correction
            ok, why = sane(model, Q, T, probes=self.ABSORB_PROBES)
            if ok:
                ok, why = provable(model, self.config.passivity)
        except Exception as exc:        # noqa: BLE001 - the incumbent keeps serving
            ok, why = False, f'{type(exc).__name__}: {exc}'
        with self._lock:
            self._absorb_cost = time.perf_counter() - t0
            self._absorbed_at = time.perf_counter()
            if generation != self._generation or hyper is not self._hyper:
                return                  # reset, or a refit swapped in other hyper-parameters
            h = self.health
            self._fresh = max(0, self._seq - seq)
            if ok:
                self._model = model
                self._version += 1
                h.absorbs += 1
                h.last_absorb_error = ''
            else:                       # the samples wait for the next refit
                h.absorbs_rejected += 1
                h.last_absorb_error = why

"""
Rebases: the served model brought back to the window now and then (no rclpy).

A part of :class:`~dgp_ros.online.learner.Learner`. A rebase is an exact refit on the window at
the served model's hyper-parameters, once ``buffer_size // REBASE_FRACTION`` samples were
appended: the buffer replaces samples anywhere (coverage), appends only add, so a rebase brings
the model back to the buffer (and its size back to ``buffer_size``), and takes a re-selected
prior (``prior='auto'``). A learner process that falls behind (samples queue up for it) stops
appending (``Served.catch_up``) and takes them in by rebases only: one refit per batch is cheaper
than a long block of appends.

A rebase does not wait for a proof: a certifying mode's model serves with what its cheap
certificates give (the global bound, the eigenvalue floor) or, while a domain proof is pending,
with every answer projected; the proof runs in a re-proof job (``refits``). Only a non-finite
model is refused (the samples then wait for the next refit, and the learner's health says why).

In line (``refit_mode='sync'``) a rebase runs at once, in learning order; otherwise in a thread
of its own (``dgp_rebase``), as soon as the last rebase's cost allows it. It keeps no other part:
each call is passed the learner's parts (``parts.Parts``: the lock, the settings, the window,
structure and served model a rebase reads and feeds, the refits whose hyper-parameters and
generation it runs at, the health record), and the rebase thread is handed them when it starts
(the parts are made anew with the ``Rebases`` on a reset, so they are the same for its life).
"""
from __future__ import annotations

import threading
import time
from typing import Callable

import numpy as np

__all__ = ['Rebases']


class Rebases:
    """
    When and how the served model is rebased (module docstring).

    It keeps no other part (module docstring): ``wanted``, ``due``, ``soon`` and ``run`` are
    passed the learner's parts (the lock is taken to read the window and to swap, never while
    fitting). factory : builds a model (``dgp_ros.gp.make_model``).
    """

    #: a rebase once this fraction of ``buffer_size`` was appended since the last (re)fit
    REBASE_FRACTION = 4
    #: least wall time between two rebases in a learner process or thread (s)
    MIN_ABSORB_S = 0.02
    #: wait after a rebase, in units of its cost: 2 = at most a third of the time rebasing;
    #: a learner process raises it to BACKLOG_ABSORB_WAIT while samples queue up for it
    ABSORB_WAIT = 2.0
    BACKLOG_ABSORB_WAIT = 8.0

    def __init__(self, factory: Callable):
        self._factory = factory
        self._thread = None
        self._wanted = threading.Event()
        self._at = 0.0                # perf_counter() at the end of the last rebase
        self._cost = 0.0              # wall seconds of the last rebase
        #: appends keep up (a learner process clears it while samples queue up for it:
        #: rebases take them in then; ``backlog``)
        self.appending = True
        self._wait = self.ABSORB_WAIT

    def backlog(self, behind: bool) -> None:
        """Say whether samples queue up for the learner: no appends then, rarer rebases."""
        self.appending = not behind
        self._wait = self.BACKLOG_ABSORB_WAIT if behind else self.ABSORB_WAIT

    def restart(self) -> None:
        """Forget the last rebase's time and cost (a model adopted with its samples)."""
        self._at = 0.0
        self._cost = 0.0

    # ------------------------------------------------------------------ decisions
    def wanted(self, parts) -> bool:
        """Tell whether a rebase is wanted, however soon its cost allows it (``due``)."""
        cfg, served = parts.settings(), parts.served
        if served.model is None or not cfg.learning:
            return False
        waiting = served.unheld(parts.window.seq) and (not self.appending or served.blocked)
        return bool(waiting or parts.structure.reselect_due() or
                    served.appended >= max(1, cfg.buffer_size // self.REBASE_FRACTION))

    def due(self, parts) -> bool:
        """
        Tell whether a rebase is due.

        When samples wait that appending does not take (a learner process that falls behind,
        samples of other targets), after ``buffer_size // REBASE_FRACTION`` appends, or when
        the structure is to be re-selected. In line (``sync``) at once (deterministic, in
        learning order); in a learner process or thread as soon as the last rebase's cost
        allows (at most a third of the time rebasing; a ninth while samples queue up for the
        learner: taking every sample in comes first).
        """
        if not self.wanted(parts):
            return False
        if parts.settings().refit_mode == 'sync':
            return True
        return time.perf_counter() - self._at >= max(self.MIN_ABSORB_S, self._wait * self._cost)

    def soon(self, parts) -> None:
        """Rebase in line (``sync``), else in the rebase thread (never on the caller's path)."""
        if parts.settings().refit_mode == 'sync':
            self.run(parts)
            return
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._loop, args=(parts,), name='dgp_rebase',
                                            daemon=True)
            self._thread.start()
        self._wanted.set()

    def _loop(self, parts) -> None:
        """Rebase whenever one is wanted (``soon``), with the parts handed at its start."""
        while True:
            self._wanted.wait()
            self._wanted.clear()
            self.run(parts)

    # ------------------------------------------------------------------ the rebase
    def run(self, parts, freeze: bool = False) -> None:
        """
        Refit the model on the window at its hyper-parameters (exact; O(N n^3)).

        With learning off only the freeze (``freeze``) rebases: the saved model is the one that
        serves until learning is switched on again.

        The scales stay those of the last hyper-parameter fit; with ``prior='auto'`` the frozen
        prior is the newest fit of the long history (``prior``). A certifying mode's proof
        is left to the re-proof job (``fit(prove=False)``). The samples learned while it ran are
        appended to it after it is swapped in, by the thread that learns them.
        """
        t0 = time.perf_counter()
        win, st, refits, lock = parts.window, parts.structure, parts.refits, parts.lock
        with lock:
            cfg = parts.settings()
            if not (cfg.learning or freeze):
                return
            seq, generation, hyper = win.seq, refits.generation, refits.hyper
            if st.reselect_due():
                st.reselect(win, parts.health)  # retargets the window; the prior: in the hyper
            else:
                st.refresh()            # couplings of a persistent column: kept current
            gen = win.target_gen
            Q, T = win.arrays()
            kw = dict(st.model_kw(cfg), hyperparams=st.with_prior(hyper))
            correction = st.correction()
        why = ''
        try:
            model = self._factory(cfg.model, **kw).fit(Q, T, optimize=False, prove=False)
            model.correction_ = correction
            if not np.all(np.isfinite(model.posterior_.weights)):
                why = 'non-finite weights'
        except Exception as exc:        # noqa: BLE001 - the incumbent keeps serving
            why = f'{type(exc).__name__}: {exc}'
        with lock:
            self._cost = time.perf_counter() - t0
            self._at = time.perf_counter()
            if generation != refits.generation or hyper is not refits.hyper:
                return                  # reset, or a refit swapped in other hyper-parameters
            h = parts.health
            if why:                     # the samples wait for the next refit
                h.absorbs_rejected += 1
                h.last_absorb_error = why
                return
            # the samples learned meanwhile are appended by the thread that learns them (in
            # a thread of the node process the message path answers from this very model)
            parts.served.based(model, seq, gen)
            h.absorbs += 1
            h.last_absorb_error = ''

"""
The served model: the model every answer comes from, and which learned samples it holds.

A part of :class:`~dgp_ros.online.learner.Learner`, called under the learner's lock. It owns

* the model (None before the first fit) and ``version``, a number that changes whenever what a
  snapshot would hold changes (the model, its samples, or, through ``touch``, the prior or the
  configuration), increasing across resets;
* which samples of the window the model holds: all up to sequence number ``held`` (the window's
  ``seq`` counts every sample added), with targets of generation ``gen``;
* the appends (``catch_up``): a learned sample is appended to the live model as soon as it is
  buffered (in line: in ``learn``; the learner process: once per round of samples, as one
  block): an exact rank-k update of each output's Cholesky factor at the model's
  hyper-parameters, O(N n^2 k). The next answer already knows it: on a trajectory that keeps
  reaching new velocities (the A320 entering angles of attack it has not flown yet) the answer
  one step ahead comes from its neighbour of 1/60 s ago, not from ten samples ago. Samples that
  are not all at hand in learning order with the model's targets (evicted, or retargeted) are
  left to the next rebase (``jobs.rebase``), which ``blocked`` asks for.
"""
from __future__ import annotations

__all__ = ['Served']


class Served:
    """The model that serves (module docstring); ``version``: where to start counting."""

    def __init__(self, version: int = 0):
        self._model = None
        self._version = int(version)
        self._held = 0                # the model holds every learned sample up to this seq
        self._gen = 0                 # the target generation of the samples it holds
        self._appended = 0            # samples appended since the model was (re)fitted
        self._blocked = False         # unheld samples the model cannot take by appending

    @property
    def model(self):
        """Return the served model, None before the first fit (do not mutate it)."""
        return self._model

    @property
    def version(self) -> int:
        """Return a number that changes whenever the next snapshot would differ."""
        return self._version

    @property
    def held(self) -> int:
        """Return the sequence number of the newest sample the model holds."""
        return self._held

    @property
    def gen(self) -> int:
        """Return the target generation of the samples the model holds."""
        return self._gen

    @property
    def appended(self) -> int:
        """Return how many samples were appended since the model was (re)fitted."""
        return self._appended

    @property
    def blocked(self) -> bool:
        """Tell whether unheld samples wait that appending cannot take (a rebase must)."""
        return self._blocked

    def touch(self) -> None:
        """Count a change of what a snapshot holds besides the model (prior, configuration)."""
        self._version += 1

    def unheld(self, seq: int) -> int:
        """Return how many of the ``seq`` samples learned the model does not hold (0 without)."""
        return seq - self._held if self._model is not None else 0

    def based(self, model, seq: int, gen: int) -> None:
        """Serve ``model``, fitted on the window up to ``seq`` with targets of ``gen``."""
        self._model = model
        self._held, self._gen, self._appended = seq, gen, 0
        self._blocked = False
        self._version += 1

    def replace(self, model) -> None:
        """Serve ``model`` instead: the same samples (a re-proven copy caught up with them)."""
        self._model = model
        self._version += 1

    def remean(self, mean) -> None:
        """Serve the model with the prior ``mean`` instead (``model.remean``: no refit)."""
        if self._model is not None:
            self._model.remean(mean)
            self._version += 1

    def catch_up(self, window, health, rebase_after: int) -> int:
        """
        Append every learned sample of ``window`` the model does not hold yet; returns how many.

        Nothing is appended when they are not all at hand in learning order with the model's
        targets: the next rebase takes them (``blocked``). A model that cannot take them (a
        singular update) is rebased instead: ``appended`` jumps to ``rebase_after``. Nor once
        ``rebase_after`` samples were appended: the model then holds at most its window and
        as many again, however long its rebases take (they are due after a quarter).
        """
        if self._model is None or window.seq <= self._held:
            return 0
        k = window.seq - self._held
        run = window.run_of(self._held, window.seq, self._gen) \
            if self._appended + k <= rebase_after else None
        if run is None:
            self._blocked = True
            return 0
        try:
            self._model.update(*run)
        except Exception as exc:    # noqa: BLE001 - the rebase takes them
            health.last_absorb_error = f'append failed: {type(exc).__name__}: {exc}'
            self._appended = rebase_after      # rebase at once
            return 0
        self._held = window.seq
        self._appended += k
        self._version += 1
        health.appends += k
        return k

"""
The learner's parts as they are at a call: what the learner's steps are passed (no rclpy).

A step that reads or changes several parts (``files.save``, ``files.adopt``, ``Snapshots.take``,
the steps of ``Refits``, ``Rebases`` and ``Switch``) is handed them in each call instead of
keeping references to them, so a reset's new parts reach every step at once; ``Refits`` and
``Rebases`` keep no other part, nor does ``Switch`` (a freeze job goes from ``Refits.run`` to
``parts.switch``; a model a refit swapped in or a freeze proved is saved by ``parts.save``, the
step ``files.save``), and their threads are handed the parts when they start (made anew with
them on a reset).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

__all__ = ['Parts']


class Parts(NamedTuple):
    """``Learner.parts()``: its lock, settings (the configuration now), parts, last_t, save."""

    lock: Any
    settings: Callable
    window: Any
    structure: Any
    grounds: Any
    served: Any
    rebases: Any
    refits: Any
    switch: Any
    health: Any
    #: returns the newest sample's learning time (s), None before any
    last_t: Callable
    #: ``files.save(parts, path)``: the step that saves the served model (no part's method)
    save: Callable

"""
The learner's parts as they are at a call: what the learner's steps are passed (no rclpy).

A step that reads or changes several parts (``files.save``, ``files.adopt``, ``Snapshots.take``,
``Refits.start`` and ``run``, the steps of ``Switch``) is handed them in each call instead of
keeping references to them, so a reset's new parts reach every step at once; ``Refits`` and
``Switch`` keep none of each other (a freeze job goes from ``Refits.run`` to ``parts.switch``).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

__all__ = ['Parts']


class Parts(NamedTuple):
    """``Learner.parts()``: its lock, its settings (the configuration now) and its parts."""

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

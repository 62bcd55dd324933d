"""
The learner's parts as they are at a call: what the learner's steps are passed (no rclpy).

A step that reads or changes several parts (``files.save``, ``files.adopt``, ``Snapshots.take``)
is handed them in each call instead of keeping references to them, so no part holds another
and a reset's new parts reach every step at once.
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

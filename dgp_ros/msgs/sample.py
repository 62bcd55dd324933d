"""
The one ``sensor_msgs/JointState`` converter of the package (no rclpy).

The estimator node, ``dgp-replay``, the demo and the bag tools all turn a JointState into a
:class:`JointStateSample` with :func:`joint_state_sample`, so that a message gives the same numbers
whichever path it took: received over DDS (an rclpy ``sensor_msgs.msg.JointState``) or read from
a bag (a message deserialized by rosbags). Both are read by duck typing (attribute names only),
so this module imports neither rclpy nor rosbags.

The stamp is ``sec + 1e-9 * nanosec`` (Python ``int`` plus ``float``), exactly this expression:
a replayed bag reproduces the node's estimates bit for bit only if both compute the same float.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

import numpy as np

__all__ = ['JointStateSample', 'joint_state_sample', 'stamp_seconds']


@dataclass(frozen=True, eq=False)
class JointStateSample:
    """
    One JointState measurement as plain Python / numpy values.

    Attributes
    ----------
    stamp_s : float
        ``header.stamp`` in seconds (``sec + 1e-9 * nanosec``); NaN if the message has no
        readable stamp.
    names : list of str
        ``name``, in message order (may be empty: unnamed joints).
    position : numpy.ndarray, shape (k,)
        ``position`` as float64 (rad or m per joint); empty if absent.
    velocity : numpy.ndarray, shape (k,)
        ``velocity`` as float64 (rad/s or m/s per joint); empty if absent.
    effort : numpy.ndarray, shape (k,)
        ``effort`` as float64 (N m or N per joint); empty if absent.

    Notes
    -----
    The lengths are whatever the message holds: nothing here checks that they agree with each
    other or with ``names``. The consumer (:meth:`dgp_ros.online.OnlineEstimator.process`)
    validates the content and counts the rejection reason. Equality is identity (the fields
    hold arrays); compare the fields to compare two samples.

    """

    stamp_s: float
    names: list
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


def stamp_seconds(stamp: Any) -> float:
    """
    Convert a ``builtin_interfaces/Time`` (anything with ``sec`` and ``nanosec``) to seconds.

    Parameters
    ----------
    stamp : object
        ``header.stamp`` of an rclpy or a rosbags message.

    Returns
    -------
    float
        ``int(sec) + 1e-9 * int(nanosec)``; NaN if either field is missing or not an integer
        (the estimator rejects a NaN stamp as ``bad_stamp``).

    """
    try:
        return int(stamp.sec) + 1e-9 * int(stamp.nanosec)
    except Exception:       # duck typing: whatever the object raises, the answer is "no stamp"
        return math.nan


def _floats(msg: Any, field: str) -> np.ndarray:
    """``msg.<field>`` as a new 1-D float64 array; empty if missing or not numeric."""
    try:
        value = getattr(msg, field, None)
        if value is None:
            return np.empty(0)
        return np.array(value, dtype=np.float64).ravel()
    except Exception:
        return np.empty(0)


def _names(msg: Any) -> list:
    """``msg.name`` as a list (entries unchanged); empty if missing or not iterable."""
    try:
        value = getattr(msg, 'name', None)
        if value is None or isinstance(value, (str, bytes)):
            return []
        return list(value)
    except Exception:
        return []


def joint_state_sample(msg: Any) -> JointStateSample:
    """
    Convert a JointState message (rclpy or rosbags) to a :class:`JointStateSample`.

    Parameters
    ----------
    msg : object
        Anything shaped like ``sensor_msgs/JointState``: ``header.stamp.sec``,
        ``header.stamp.nanosec``, ``name``, ``position``, ``velocity``, ``effort``.

    Returns
    -------
    JointStateSample
        Copies of the fields (the sample does not alias the message's buffers).

    Notes
    -----
    Never raises on odd content: a missing or unreadable stamp gives NaN, a missing or
    non-numeric array field an empty array, a missing or non-iterable ``name`` an empty list.
    Name entries are kept as they are (not converted to ``str``), so that the estimator, which
    validates every field, can still reject bad names as such.

    """
    try:
        stamp = msg.header.stamp
    except Exception:
        stamp = None
    return JointStateSample(
        stamp_s=stamp_seconds(stamp),
        names=_names(msg),
        position=_floats(msg, 'position'),
        velocity=_floats(msg, 'velocity'),
        effort=_floats(msg, 'effort'),
    )

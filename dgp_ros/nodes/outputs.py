"""
The estimator node's outputs: answers published as serialized bytes, the rare ones as messages.

Every per-answer JointState output is a :class:`JointOutput`: a publisher and which arrays of the
answers (``online.path.arrays.Answers``) go into position, velocity and effort. The answers of a
batch are encoded at once (``cdr.JointStateWriter``: the measurement's header bytes echoed, the
names encoded once) and published as serialized messages; an output is encoded only while someone
subscribes (the force always). An output of this shape is one line of
``EstimatorNode._joint_outputs``.
"""
from __future__ import annotations

from array import array
from typing import Callable, Optional, Sequence

import numpy as np
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from dgp_ros.msgs.cdr import encode_float64, JointStateWriter

__all__ = ['damping_matrix_msg', 'joint_state', 'JointOutput', 'publish_raw', 'power_messages',
           'subscribers', 'Writers']


def damping_matrix_msg(D) -> Float64MultiArray:
    """N x N row-major Float64MultiArray with dims rows/cols (size and stride)."""
    n_rows, n_cols = D.shape
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label='rows', size=n_rows, stride=n_rows * n_cols),
                      MultiArrayDimension(label='cols', size=n_cols, stride=n_cols)]
    msg.layout.data_offset = 0
    msg.data = D.ravel().tolist()
    return msg


def _doubles(a) -> array:
    """Return a float64 sequence as the array('d') a message field takes unchecked."""
    out = array('d')
    out.frombytes(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return out


def joint_state(header, names, position=(), velocity=(), effort=()) -> JointState:
    m = JointState()
    m.header = header
    m.name = names
    m.position = _doubles(position)
    m.velocity = _doubles(velocity)
    m.effort = _doubles(effort)
    return m


def publish_raw(pub, blobs: Sequence[bytes]) -> None:
    """
    Publish serialized messages (``bytes``) in order.

    What ``Publisher.publish(bytes)`` does, holding the publisher's handle once per batch (it
    checks the message's type and enters the handle for every message).
    """
    handle = pub.handle
    with handle:
        send = handle.publish_raw
        for b in blobs:
            send(b)


def subscribers(pub) -> int:
    """``pub.get_subscription_count()``, without entering the handle (the node's own thread)."""
    return pub.handle.get_subscription_count()


def power_messages(power: np.ndarray) -> list:
    """``std_msgs/Float64`` messages' bytes, one per value."""
    return [encode_float64(p) for p in power.tolist()]


class Writers:
    """One ``JointStateWriter`` per joint-name list (the estimator's, the messages' own)."""

    KEEP = 8

    def __init__(self):
        self._by_names: dict = {}

    def get(self, names: tuple) -> JointStateWriter:
        w = self._by_names.get(names)
        if w is None:
            if len(self._by_names) >= self.KEEP:
                self._by_names.pop(next(iter(self._by_names)))
            w = self._by_names[names] = JointStateWriter(names)
        return w


class JointOutput:
    """
    A per-answer JointState output: ``fields(answers)`` -> (position, velocity, effort).

    Each is a (k, m) array or None (an empty field); ``fields`` returning None skips the
    output for that batch (not computed). ``always``: published without subscribers too (the
    force: its count is checked per batch all the same, it is the node's answer).
    """

    def __init__(self, pub, fields: Callable, always: bool = False):
        self.pub, self.fields, self.always = pub, fields, always
        self.wanted = always

    def update(self) -> None:
        """Note whether anybody subscribes (a publish without subscribers still costs)."""
        if not self.always:
            self.wanted = subscribers(self.pub) > 0

    def publish(self, writer: JointStateWriter, headers: Sequence[bytes], answers) -> None:
        if not self.wanted:
            return
        arrays: Optional[tuple] = self.fields(answers)
        if arrays is not None:
            publish_raw(self.pub, writer.write(headers, *arrays))

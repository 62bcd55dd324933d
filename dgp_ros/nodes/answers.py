"""
The estimator node's message path: serialized measurements in, serialized answers out.

The node subscribes raw (the DDS sample's bytes); :class:`MessagePath` reads a batch with the
codec (``cdr.JointStateReader``: one conversion per batch, no message object), answers each run
of like messages at once (``OnlineEstimator.process_arrays``) and publishes the answers as
serialized bytes (``outputs.JointOutput``). What the codec cannot read is deserialized by rclpy
and answered message by message (``/diagnostics``: ``messages_fallback``; bytes that are not a
JointState at all are rejected as ``undecodable``): never a crash, never a message unanswered
that the object path would have answered.
"""
from __future__ import annotations

from collections import deque
from typing import List

import numpy as np
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from dgp_ros.msgs.cdr import header_bytes, JointStateReader, parse_header
from dgp_ros.msgs.sample import joint_state_sample
from dgp_ros.nodes.outputs import (damping_matrix_msg, joint_state, JointOutput, power_messages,
                                   publish_raw, subscribers, Writers)
from dgp_ros.online.path.arrays import answers_of

__all__ = ['MessagePath', 'AGE_PLAUSIBLE_S']

#: stamp -> answer ages beyond this are stamps of another clock (a replayed bag): not latency
AGE_PLAUSIBLE_S = 60.0
#: what rclpy puts where a string's bytes are no UTF-8 (the replacement character)
_REPLACED = '\ufffd'


class MessagePath:
    """
    Answer batches of serialized JointState messages for an ``EstimatorNode`` (its publishers).

    ``answer(raws, now_ns)`` answers a batch; ``age`` holds the recent stamp -> answer ages (s);
    ``fallback`` counts the messages rclpy read for the codec.
    """

    def __init__(self, node):
        self.node, self.estimator = node, node.estimator
        self.age: deque = deque(maxlen=1000)
        self.fallback = 0
        self._reader = JointStateReader()
        self._writers = Writers()
        # the per-answer JointState outputs: (publisher, (position, velocity, effort) of the
        # answers); each encoded only while subscribed (the force always), the confidence
        # before the force (a controller acting on the force has both)
        self.joint_outputs = [
            JointOutput(node.pub_conf, lambda a: None if a.confidence is None else
                        (None, a.qd, a.confidence)),
            JointOutput(node.pub_force, lambda a: (None, a.qd, a.tau_hat), always=True),
            JointOutput(node.pub_std, lambda a: None if np.isnan(a.stddev).all() else
                        (None, a.qd, a.stddev)),
            JointOutput(node.pub_D_stamped, lambda a: None if a.D is None else
                        (None, a.qd, a.D.reshape(len(a), -1))),
        ]
        self._want_power = self._want_corr = self._want_D = False

    def update_outputs(self) -> None:
        """Compute and publish only what has subscribers (checked every batch: a few us)."""
        node = self.node
        for out in self.joint_outputs:
            out.update()
        self._want_D = subscribers(node.pub_D) > 0
        # the standard deviation and the damping matrix cost about 60 % of a 7-joint answer
        # (and the residuals are only sent back by the learner while someone listens)
        self.estimator.set_outputs(
            stddev=self.joint_outputs[2].wanted,
            damping=self._want_D or self.joint_outputs[3].wanted,
            residuals=subscribers(node.pub_residual) > 0)
        self._want_power = subscribers(node.pub_power) > 0
        self._want_corr = subscribers(node.pub_corr) > 0

    def answer(self, raws: List[bytes], now: int) -> None:
        """Answer the serialized messages ``raws`` in order (``now``: node clock, ns)."""
        self.update_outputs()
        runs, undecoded = self._reader.read(raws)
        for run in runs:
            if undecoded and undecoded[0] < run.start:
                undecoded = self._undecoded(raws, undecoded, run.start, now)
            answers = self.estimator.process_arrays(run.sec, run.nanosec, run.names,
                                                    run.velocity, run.effort, run.position)
            if answers is None:
                answers = self._one_by_one(run)
            self._publish(run.headers, answers, run, now)
        if undecoded:
            self._undecoded(raws, undecoded, len(raws), now)

    def _one_by_one(self, run):
        """Answer a run through ``process_batch`` (the first messages, ``sync``, no names)."""
        batch = []
        for j in range(run.stop - run.start):
            stamp = int(run.sec[j]) + 1e-9 * int(run.nanosec[j])     # stamp_seconds' float
            batch.append((stamp, list(run.names), run.velocity[j], run.effort[j],
                          None if run.position is None else run.position[j]))
        return answers_of(self.estimator.process_batch(batch), run.names)

    def _undecoded(self, raws, undecoded: list, stop: int, now: int) -> list:
        """Answer the messages the codec could not read (those before ``stop``) through rclpy."""
        from rclpy.serialization import deserialize_message
        while undecoded and undecoded[0] < stop:
            i = undecoded.pop(0)
            self.fallback += 1
            try:
                msg = deserialize_message(raws[i], JointState)
            except Exception:       # noqa: BLE001 - not a JointState at all: counted
                self.estimator.health.messages_received += 1
                self.estimator.health.reject('undecodable')
                continue
            if _REPLACED in msg.header.frame_id or any(_REPLACED in n for n in msg.name):
                # rclpy replaced bytes that are no UTF-8 text (the codec refused them): a peer's
                # bad string is dropped and counted, never echoed or decoded again downstream
                self.estimator.health.messages_received += 1
                self.estimator.health.reject('bad_text')
                continue
            s = joint_state_sample(msg)
            est = self.estimator.process_batch(
                [(s.stamp_s, s.names, s.velocity, s.effort, s.position)])
            hdr = header_bytes(msg.header.stamp.sec, msg.header.stamp.nanosec,
                               msg.header.frame_id)
            self._publish([hdr], answers_of(est, tuple(s.names)), None, now, msg)
        return undecoded

    def _publish(self, headers, a, run, now: int, msg=None) -> None:
        """Publish the answers ``a`` of a batch whose header bytes are ``headers``."""
        if not len(a):
            return
        node = self.node
        hdrs = [headers[i] for i in a.rows.tolist()]
        if self._want_corr:         # before the force: a controller acting on the force has both
            self._publish_corrections(hdrs, a, run, msg)
        writer = self._writers.get(a.names)
        for out in self.joint_outputs:
            out.publish(writer, hdrs, a)
        if a.D is not None and self._want_D:
            for D in a.D:
                node.pub_D.publish(damping_matrix_msg(D))
        if self._want_power:
            publish_raw(node.pub_power, power_messages(a.power))
        if a.residuals:
            self._publish_residuals(hdrs[-1], a.names, a.residuals)
        now_s = now * 1e-9
        # stamps on this clock only (not a bag's own time base)
        self.age.extend([x for x in (now_s - s for s in a.stamp_s.tolist())
                         if -AGE_PLAUSIBLE_S < x < AGE_PLAUSIBLE_S])

    def _publish_residuals(self, hdr: bytes, names, residuals) -> None:
        """``~/friction_residual``: each sample stamped with its own (earlier) time."""
        frame = parse_header(hdr)[2]
        for r in residuals:
            h = Header(frame_id=frame)
            h.stamp.sec = int(r.stamp_s // 1)
            h.stamp.nanosec = min(int(round((r.stamp_s % 1) * 1e9)), 999_999_999)
            self.node.pub_residual.publish(joint_state(h, list(names), r.q, r.qd, r.residual))

    def _publish_corrections(self, hdrs, a, run, msg) -> None:
        """``~/rigid_body_correction`` at each message's pose, if the model has a correction."""
        if run is not None:
            src, P = list(run.names), run.position
        else:
            src, P = list(msg.name), np.array([msg.position]) if len(msg.position) else None
        if P is None or not all(n in src for n in a.names):
            return
        idx = [src.index(n) for n in a.names]
        for hdr, j in zip(hdrs, a.rows.tolist()):
            q = P[j if run is not None else 0, idx]
            corr = self.estimator.rigid_body_correction(q)
            if corr is not None:
                sec, nsec, frame = parse_header(hdr)
                h = Header(frame_id=frame)
                h.stamp.sec, h.stamp.nanosec = sec, nsec
                self.node.pub_corr.publish(joint_state(h, list(a.names), q, (), corr))

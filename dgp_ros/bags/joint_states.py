"""
``sensor_msgs/JointState`` streams in bags, with rosbags only (no rclpy, no DDS).

:func:`iter_joint_states` is how ``dgp-replay`` reads a bag: every message of one JointState
topic, deserialized with the Jazzy typestore and converted by
:func:`dgp_ros.msgs.sample.joint_state_sample` (the estimator node's converter, so both compute the
same stamps and arrays). :func:`write_joint_state_bag` writes such a bag, for tests and
simulated data.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Iterable, Iterator, Optional, Sequence, Union

import numpy as np

from dgp_ros.bags.io import (_one_line, BagError, iter_bag, open_bag, storage_plugin, typestore)
from dgp_ros.msgs.sample import joint_state_sample, JointStateSample

JOINT_STATE = 'sensor_msgs/msg/JointState'


def joint_state_topic(reader, topic: Optional[str] = None) -> str:
    """
    Return the JointState topic of an open bag to read.

    Parameters
    ----------
    reader : rosbags.rosbag2.Reader
        Open bag.
    topic : str, optional
        Wanted topic (a leading ``/`` may be left out). Without it the choice is automatic if
        it is clear: the only JointState topic, else the only one named ``generalized_state``,
        else the only one named ``joint_states``.

    Raises
    ------
    BagError
        The topic is missing or not a JointState, or the automatic choice is ambiguous.

    """
    topics = reader.topics
    js = sorted(t for t, info in topics.items() if info.msgtype == JOINT_STATE)
    if topic:
        cands = [topic] if topic.startswith('/') else [topic, '/' + topic]
        for c in cands:
            if c in topics:
                if topics[c].msgtype != JOINT_STATE:
                    raise BagError(f'topic {c} is {topics[c].msgtype}, not {JOINT_STATE}')
                return c
        raise BagError(f'topic {topic} not in bag; JointState topics: {", ".join(js) or "none"}')
    if len(js) == 1:
        return js[0]
    if not js:
        raise BagError(f'no {JOINT_STATE} topic in bag (topics: '
                       f'{", ".join(sorted(topics)) or "none"})')
    for suffix in ('generalized_state', 'joint_states'):
        named = [t for t in js if t.rsplit('/', 1)[-1] == suffix]
        if len(named) == 1:
            return named[0]
    raise BagError(f'several JointState topics ({", ".join(js)}); choose one with --topic')


def iter_joint_states(bag, topic: Optional[str] = None, stamp: str = 'header',
                      reader=None) -> Iterator[Optional[JointStateSample]]:
    """
    Yield every JointState of one topic of a bag, in bag order, as samples.

    Parameters
    ----------
    bag : str or Path
        The bag (opened here unless ``reader`` is given).
    topic : str, optional
        See :func:`joint_state_topic` (``None``: automatic choice).
    stamp : {'header', 'bag'}
        ``stamp_s`` from ``header.stamp`` (as the estimator node) or from the receive time
        recorded in the bag.
    reader : rosbags.rosbag2.Reader, optional
        An open reader of ``bag`` to use (not closed here).

    Yields
    ------
    JointStateSample or None
        ``None`` for a message that does not deserialize (the caller counts it).

    """
    if stamp not in ('header', 'bag'):
        raise ValueError(f"stamp must be 'header' or 'bag', not {stamp!r}")
    ts = typestore()
    own = reader is None
    if own:
        reader = open_bag(bag)
    try:
        topic = joint_state_topic(reader, topic)
        for conn, t, raw in iter_bag(bag, topics=[topic], reader=reader):
            try:
                sample = joint_state_sample(ts.deserialize_cdr(raw, conn.msgtype))
            except Exception:
                yield None
                continue
            yield dataclasses.replace(sample, stamp_s=t * 1e-9) if stamp == 'bag' else sample
    finally:
        if own:
            reader.close()


def write_joint_state_bag(path, samples: Iterable, topic: Union[str, Sequence[str]] =
                          '/joint_states', storage: str = 'sqlite3') -> Path:
    """
    Write ``sensor_msgs/JointState`` messages to a new bag (rosbags CDR, Jazzy typestore).

    For tests and simulated data; no ROS needed.

    Parameters
    ----------
    path : str or Path
        Bag directory to create (must not exist).
    samples : iterable
        :class:`~dgp_ros.msgs.sample.JointStateSample` or tuples
        ``(stamp_s, names, position, velocity, effort)``: stamp in s (>= 0), arrays of
        shape (k,) (``position`` may be empty).
    topic : str or sequence of str
        Topic(s); with several, every message is written to each.
    storage : str
        ``'sqlite3'`` or ``'mcap'``.

    Returns
    -------
    Path
        ``path``. Header stamps are ``stamp_s`` rounded to whole nanoseconds, and the bag
        (receive) timestamp of each message equals its header stamp.

    """
    from rosbags.rosbag2 import Writer
    ts = typestore()
    T = ts.types
    topics = [topic] if isinstance(topic, str) else list(topic)
    w = Writer(Path(path), version=9, storage_plugin=storage_plugin(storage))
    try:
        w.open()
    except Exception as exc:
        raise BagError(f'{path}: cannot create bag: {_one_line(exc)}') from None
    try:
        conns = [w.add_connection(t, JOINT_STATE, typestore=ts) for t in topics]
        for s in samples:
            if not isinstance(s, JointStateSample):
                s = JointStateSample(*s)
            sec = math.floor(s.stamp_s)
            nsec = int(round((s.stamp_s - sec) * 1e9))
            sec, nsec = sec + nsec // 10**9, nsec % 10**9
            msg = T[JOINT_STATE](
                header=T['std_msgs/msg/Header'](
                    stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id=''),
                name=[str(n) for n in s.names],
                position=np.asarray(s.position, dtype=np.float64).ravel(),
                velocity=np.asarray(s.velocity, dtype=np.float64).ravel(),
                effort=np.asarray(s.effort, dtype=np.float64).ravel())
            raw = ts.serialize_cdr(msg, JOINT_STATE)
            for c in conns:
                w.write(c, sec * 10**9 + nsec, raw)
    finally:
        w.close()
    return Path(path)

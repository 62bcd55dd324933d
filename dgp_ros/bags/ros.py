"""
Record topics to a bag and publish a bag's messages, from inside an rclpy node.

:class:`Recorder` subscribes with ``raw=True`` and writes the received CDR bytes unchanged: the
bag holds exactly what travelled. A topic given by name only is subscribed once a publisher for
it is discovered (its type comes from the graph); the subscription QoS is adapted to the
publishers (reliable only if all of them are, transient-local only if all of them are) and the
publishers' offered QoS profiles are stored in the bag's metadata, as ``ros2 bag record`` does.
A topic given with its type is subscribed at once (reliable unless told otherwise; no offered
QoS to store), so that a recorder started first misses nothing. Message definitions and RIHS01
hashes come from :func:`dgp_ros.bags.io.message_definition`. The receive time (node clock, so
``use_sim_time`` is honoured) is the bag timestamp.

:class:`Player` publishes the stored bytes as they are (rclpy publishes ``bytes`` raw) with the
original inter-message timing scaled by ``rate``, optionally with ``/clock``, looping and
remapping topics.

A type is only turned into a Python class (``import <pkg>.msg``) after
:func:`dgp_ros.bags.io.check_message_type` accepted it: a bag (for the player) or a publisher on
the graph (for the recorder) never makes this process import a module it names.
"""
from __future__ import annotations

import importlib
from pathlib import Path
import threading
import time
from typing import Callable, Optional

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from dgp_ros.bags.io import (BagError, BagWriter, check_message_type, iter_bag,
                             message_definition, normalize_type, open_bag, playable_topics)

__all__ = ['Player', 'Recorder', 'adapted_qos', 'message_class', 'qos_to_rosbags']


def message_class(msgtype: str, allow_installed: bool = False):
    """
    Return the Python class of a message type, imported only once the type is accepted.

    Parameters
    ----------
    msgtype : str
        ``pkg/msg/Name`` or ``pkg/Name``.
    allow_installed : bool
        See :func:`dgp_ros.bags.io.check_message_type` (the recorder sets it; the player not).

    Raises
    ------
    BagError
        The type is refused (nothing was imported), or its package is not installed.

    """
    pkg, sub, name = check_message_type(msgtype, allow_installed).split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.{sub}'), name)
    except (ImportError, AttributeError):
        raise BagError(f'message type {pkg}/{sub}/{name} is not installed (no Python module '
                       f'{pkg}.{sub}.{name})') from None


def _duration_to_qostime(d):
    from rosbags.interfaces import QosTime
    ns = int(getattr(d, 'nanoseconds', 0))
    return QosTime(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def qos_to_rosbags(profile):
    """Convert rclpy ``QoSProfile`` to rosbags ``Qos`` (for a bag's ``offered_qos_profiles``)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability)

    def conv(enum_cls, value):
        name = getattr(value, 'name', str(value)).upper()
        return enum_cls.__members__.get(name, enum_cls.UNKNOWN)

    return Qos(
        history=conv(QosHistory, profile.history),
        depth=int(profile.depth),
        reliability=conv(QosReliability, profile.reliability),
        durability=conv(QosDurability, profile.durability),
        deadline=_duration_to_qostime(profile.deadline),
        lifespan=_duration_to_qostime(profile.lifespan),
        liveliness=conv(QosLiveliness, profile.liveliness),
        liveliness_lease_duration=_duration_to_qostime(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def adapted_qos(offered, depth: int = 1000, reliability: str = 'auto') -> QoSProfile:
    """
    Make a QoS compatible with all ``offered`` profiles (rclpy ``QoSProfile`` or rosbags ``Qos``).

    Reliable only if every offered profile is reliable, transient-local only if every one is
    (the rule ``ros2 bag`` uses); KEEP_LAST with ``depth``. ``reliability`` may force
    ``'reliable'`` or ``'best_effort'``.
    """
    def name(v):
        return getattr(v, 'name', str(v)).upper()

    rel = [name(p.reliability) for p in offered]
    dur = [name(p.durability) for p in offered]
    if reliability == 'reliable':
        r = ReliabilityPolicy.RELIABLE
    elif reliability == 'best_effort':
        r = ReliabilityPolicy.BEST_EFFORT
    else:
        r = (ReliabilityPolicy.RELIABLE if all(x == 'RELIABLE' for x in rel)
             else ReliabilityPolicy.BEST_EFFORT)
    d = (DurabilityPolicy.TRANSIENT_LOCAL if dur and all(x == 'TRANSIENT_LOCAL' for x in dur)
         else DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=r, durability=d)


class Recorder:
    """
    Record topics to a new rosbag2 bag from inside an rclpy node.

    Callbacks may run on any executor thread; the bag is written by one :class:`BagWriter`
    thread. Call :meth:`close` (always) to write the metadata.

    Parameters
    ----------
    node : rclpy.node.Node
        Hosts the subscriptions and the discovery timer; the caller spins it.
    path : str or Path
        Bag directory to create (must not exist).
    topics : mapping
        Topic name (relative names are resolved by the node) -> type ``pkg/msg/Name``, or
        ``None`` to take the type from the graph once a publisher shows up. A graph type is
        recorded only if :func:`~dgp_ros.bags.io.check_message_type` accepts it (with
        ``allow_installed``); otherwise the topic is skipped with a log line.
    storage : str
        ``'sqlite3'`` or ``'mcap'``.
    max_messages : int
        After this many messages in total, :attr:`done` becomes True and nothing more is
        written (``0``: no limit).
    depth, reliability : int, str
        Subscription queue depth; ``'auto'`` (adapt to the publishers), ``'reliable'`` or
        ``'best_effort'``.
    discovery_period : float
        Seconds between graph look-ups while some topic waits for a publisher.
    log : callable, optional
        ``log(str)``; the node's logger by default.

    Raises
    ------
    BagError
        The bag cannot be created, or an explicitly given type is refused or not installed.

    """

    def __init__(self, node, path, topics, storage: str = 'sqlite3', max_messages: int = 0,
                 depth: int = 1000, reliability: str = 'auto', discovery_period: float = 0.1,
                 log: Optional[Callable[[str], None]] = None):
        self.node = node
        self.path = Path(path)
        self.max_messages = int(max_messages or 0)
        self.depth = int(depth)
        self.reliability = reliability
        self.log = log or (lambda s: node.get_logger().info(s))
        self.count = 0
        self.counts: dict = {}
        self.done = False
        self._closed = False
        self._lock = threading.Lock()
        self._pending: dict = {}
        for name, typ in dict(topics).items():
            fq = node.resolve_topic_name(name)
            self._pending[fq] = check_message_type(typ, allow_installed=True) if typ else None
        self._subs: dict = {}
        self.writer = BagWriter(self.path, storage, {'recorded_by': 'dgp_ros.bags'})
        self._timer = None
        self._discover()
        if self._pending:
            self._timer = node.create_timer(discovery_period, self._discover)

    @property
    def subscribed(self) -> list:
        """Topics subscribed so far (fully qualified), sorted."""
        return sorted(self._subs)

    def _discover(self):
        if self._closed:
            return
        graph = None
        for topic, typ in list(self._pending.items()):
            pubs = self.node.get_publishers_info_by_topic(topic)
            if not pubs and typ is None:
                continue  # type unknown until a publisher shows up
            if typ is None:
                if graph is None:
                    graph = dict(self.node.get_topic_names_and_types())
                types = graph.get(topic) or sorted({p.topic_type for p in pubs})
                if len(types) != 1:
                    if types:
                        self.log(f'{topic}: several types {types}; give one with '
                                 f'--topic {topic}:TYPE')
                    continue
                try:
                    typ = check_message_type(types[0], allow_installed=True)
                except BagError as exc:
                    self.log(f'{topic}: not recorded: {exc}')
                    del self._pending[topic]
                    continue
            # explicit type and no publisher yet: subscribe now (reliable unless told otherwise,
            # volatile; no offered QoS to store), so that the first messages are not missed
            pubs_t = [p for p in pubs if _same_type(p.topic_type, typ)] or pubs
            self._subscribe(topic, typ, pubs_t)
            del self._pending[topic]
        if not self._pending and self._timer is not None:
            self._timer.cancel()

    def _subscribe(self, topic, typ, pubs):
        cls = message_class(typ, allow_installed=True)
        graph_hash = ''
        try:
            graph_hash = str(pubs[0].topic_type_hash) if pubs else ''
        except Exception:
            pass
        msgdef, rihs = message_definition(typ, graph_hash if graph_hash.startswith('RIHS') else '')
        offered = [qos_to_rosbags(p.qos_profile) for p in pubs]
        # rosbags needs some hash; an all-zero one marks "unknown" (rosbag2 writes an empty one)
        self.writer.add_connection(topic, typ, msgdef, rihs or 'RIHS01_' + '0' * 64, offered)
        self.counts[topic] = 0
        qos = adapted_qos([p.qos_profile for p in pubs], self.depth, self.reliability)
        self._subs[topic] = self.node.create_subscription(
            cls, topic, lambda data, _t=topic: self._on_message(_t, data), qos, raw=True)
        self.log(f'recording {topic} [{typ}] ({qos.reliability.name.lower()}, '
                 f'{qos.durability.name.lower()})')

    def _on_message(self, topic, data: bytes):
        with self._lock:
            if self._closed or self.done:
                return
            t = self.node.get_clock().now().nanoseconds
            self.writer.write(topic, t, data)
            self.count += 1
            self.counts[topic] += 1
            if self.max_messages and self.count >= self.max_messages:
                self.done = True

    def close(self):
        """
        Destroy the subscriptions and close the bag (writes metadata.yaml); idempotent.

        Call it while no other thread spins the node: rclpy cannot destroy a subscription an
        executor is waiting on (that executor's thread fails with ``InvalidHandle``).
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self.node.destroy_timer(self._timer)
        for sub in self._subs.values():
            self.node.destroy_subscription(sub)
        self._subs.clear()
        self.writer.close()


def _same_type(graph_type: str, typ: str) -> bool:
    try:
        return normalize_type(graph_type) == typ
    except ValueError:
        return False


class Player:
    """
    Publish a bag's messages from an rclpy node with their original timing.

    Publishing needs no executor: :meth:`run` blocks the calling thread until the bag is
    played (or :attr:`stop` is set).

    Parameters
    ----------
    node : rclpy.node.Node
        Hosts the publishers.
    path : str or Path
        The bag.
    rate : float
        Time scale: 1 = original timing, 2 = twice as fast, 0 = as fast as possible.
    clock_hz : float
        Publish ``/clock`` with the bag time at this wall rate (0: no ``/clock``); with
        ``rate=0`` a clock message precedes every message instead.
    loop : bool
        Play again and again until :attr:`stop` is set.
    topics : iterable of str, optional
        Only these bag topics (all by default); a missing one is a :class:`BagError`.
    remap : dict, optional
        {bag topic: published topic}.
    depth : int
        Publisher queue depth (reliability and durability adapt to the recorded offered QoS).
    start_delay : float
        Seconds to wait before playing.
    wait_for_subscribers : float
        Before starting, wait up to this many seconds until every publisher has at least
        ``min_subscribers`` subscribers (0: do not wait).
    stop : threading.Event, optional
        Ends playback early when set.
    log : callable, optional
        ``log(str)``; the node's logger by default.
    min_subscribers : int
        See ``wait_for_subscribers``.

    Raises
    ------
    BagError
        Unreadable bag, a missing topic, a topic with several types, or a message type that is
        refused or not installed (checked for every played topic before anything is imported).

    """

    def __init__(self, node, path, rate: float = 1.0, clock_hz: float = 0.0, loop: bool = False,
                 topics=None, remap=None, depth: int = 1000, start_delay: float = 0.0,
                 wait_for_subscribers: float = 0.0, stop: Optional[threading.Event] = None,
                 log: Optional[Callable[[str], None]] = None, min_subscribers: int = 1):
        if rate < 0:
            raise ValueError('rate must be >= 0')
        if int(min_subscribers) < 1:
            raise ValueError('min_subscribers must be >= 1')
        self.node = node
        self.path = Path(path)
        self.rate = float(rate)
        self.clock_hz = float(clock_hz)
        self.loop = bool(loop)
        self.topics = set(topics) if topics else None
        self.remap = dict(remap or {})
        self.depth = int(depth)
        self.start_delay = float(start_delay)
        self.wait_for_subscribers = float(wait_for_subscribers)
        self.min_subscribers = int(min_subscribers)
        self.stop = stop or threading.Event()
        self.log = log or (lambda s: node.get_logger().info(s))
        self.published = 0
        self.loops = 0
        self._reader = open_bag(self.path)
        self._pubs: dict = {}
        self._clock_pub = None
        try:
            self._make_publishers()
        except BaseException:
            self._reader.close()
            raise

    def _make_publishers(self):
        plan = playable_topics(self._reader, self.topics, name=self.path)
        for topic, (msgtype, cs) in plan.items():
            offered = [q for c in cs for q in getattr(c.ext, 'offered_qos_profiles', [])]
            self._pubs[topic] = self.node.create_publisher(
                message_class(msgtype), self.remap.get(topic, topic),
                adapted_qos(offered, self.depth))
        self._topics = list(plan)
        if self.clock_hz > 0:
            from rosgraph_msgs.msg import Clock
            self._clock_pub = self.node.create_publisher(Clock, '/clock', QoSProfile(depth=10))
            self._clock_cls = Clock

    def _publish_clock(self, t_ns):
        if self._clock_pub is None:
            return
        msg = self._clock_cls()
        msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 1_000_000_000)
        self._clock_pub.publish(msg)

    def _wait(self, until_wall, bag_t0, wall_t0):
        """Sleep until ``until_wall`` (monotonic), publishing /clock on the way."""
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= until_wall:
                return True
            step = until_wall - now
            if self._clock_pub is not None and self.clock_hz > 0:
                step = min(step, 1.0 / self.clock_hz)
                self._publish_clock(bag_t0 + (now - wall_t0) * self.rate * 1e9)
            self.stop.wait(min(step, 0.05))
        return False

    def _wait_subscribers(self):
        if self.wait_for_subscribers <= 0:
            return
        deadline = time.monotonic() + self.wait_for_subscribers
        while time.monotonic() < deadline and not self.stop.is_set():
            if all(p.get_subscription_count() >= self.min_subscribers
                   for p in self._pubs.values()):
                return
            self.stop.wait(0.02)
        lonely = [p.topic_name for p in self._pubs.values()
                  if p.get_subscription_count() < self.min_subscribers]
        if lonely:
            self.log(f'no subscriber yet on {", ".join(lonely)}; playing anyway')

    def run(self) -> int:
        """
        Play (blocking); returns the number of messages published.

        :attr:`published` counts the messages and :attr:`loops` the passes started.
        """
        self._wait_subscribers()
        if self.start_delay > 0:
            self.stop.wait(self.start_delay)
        while not self.stop.is_set():
            wall_t0 = time.monotonic()
            bag_t0 = None
            for conn, t, raw in iter_bag(self.path, reader=self._reader,
                                         topics=self._topics):
                if self.stop.is_set():
                    break
                if bag_t0 is None:
                    bag_t0 = t
                if self.rate > 0:
                    target = wall_t0 + (t - bag_t0) / 1e9 / self.rate
                    if not self._wait(target, bag_t0, wall_t0):
                        break
                if self._clock_pub is not None and (self.clock_hz <= 0 or self.rate == 0):
                    self._publish_clock(t)
                self._pubs[conn.topic].publish(bytes(raw))
                self.published += 1
            self.loops += 1
            if not self.loop or bag_t0 is None:
                break
        return self.published

    def wait_for_acks(self, timeout_s: float = 2.0):
        """Wait (bounded, per publisher) until reliable subscribers acknowledged everything."""
        for pub in self._pubs.values():
            try:
                pub.wait_for_all_acked(timeout=Duration(seconds=timeout_s))
            except Exception:
                pass

    def close(self):
        """Destroy the publishers and close the bag."""
        for pub in self._pubs.values():
            self.node.destroy_publisher(pub)
        self._pubs.clear()
        if self._clock_pub is not None:
            self.node.destroy_publisher(self._clock_pub)
            self._clock_pub = None
        try:
            self._reader.close()
        except Exception:
            pass

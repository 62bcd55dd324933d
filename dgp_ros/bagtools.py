"""rosbag2 record / play without the ``ros2`` CLI (``dgp-record``, ``dgp-play``).

Bags are standard rosbag2 (metadata version 9, storage ``sqlite3`` or ``mcap``) written and read
with the `rosbags` library, so a full ROS 2 Jazzy install (``ros2 bag info/play``) reads them.

Record (``dgp-record``)
    An rclpy node subscribes with ``raw=True`` and writes the received CDR bytes unchanged: the bag
    holds exactly what travelled. A topic given by name only is subscribed once a publisher for it
    is discovered (its type comes from the graph); the subscription QoS is adapted to the
    publishers (reliable only if all of them are, transient-local only if all of them are), and the
    publishers' offered QoS profiles are stored in the bag's metadata, as ``ros2 bag record``
    does. A topic given as ``--topic name:type`` with no publisher yet is subscribed at once
    (reliable unless ``--qos-reliability best_effort``; no offered QoS to store), so that a
    recorder started first misses nothing. Message definitions and RIHS01 type hashes come from
    the rosbags typestore for Jazzy, or from the ``.msg`` files of the installed interface
    packages for types it does not know. The
    receive time (node clock, so ``use_sim_time`` is honoured) is the bag timestamp. Recording
    stops cleanly (bag closed, metadata written) on SIGINT/SIGTERM, after ``--duration`` seconds or
    after ``--max-messages`` messages.

Play (``dgp-play``)
    Publishes the stored bytes as-is (rclpy publishes ``bytes`` raw) with the original
    inter-message timing (the bag's receive timestamps) scaled by ``--rate`` (``0`` = as fast as
    possible), optionally publishing ``/clock`` with the bag time, looping, and remapping topics
    (``--remap from:=to``; ``--ros-args -r`` works too).

Both commands print a one-line message and exit with code 2 for a missing, corrupt or truncated
bag (no traceback). The library functions (:func:`open_bag`, :func:`iter_bag`, :class:`Recorder`,
:class:`Player`) are what ``dgp-replay`` and the tests use.
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Optional

EXIT_OK = 0
EXIT_BAG_ERROR = 2
EXIT_USAGE = 2

STORAGES = ('sqlite3', 'mcap')


class BagError(Exception):
    """A bag cannot be opened, read or written; the message is one line, meant for the user."""


# --------------------------------------------------------------------------------------------
# Reading (pure rosbags, no rclpy): used by dgp-play and dgp-replay
# --------------------------------------------------------------------------------------------

def _one_line(exc: BaseException, limit: int = 200) -> str:
    text = ' '.join(str(exc).split())
    if not text or isinstance(exc, (MemoryError, OverflowError)):
        text = f'{type(exc).__name__} {text}'.strip() + ' while decoding (corrupt data?)'
    return text if len(text) <= limit else text[:limit - 3] + '...'


def open_bag(path):
    """Open a rosbag2 bag (directory, or a bare ``.db3``/``.mcap`` file) for reading.

    A directory without ``metadata.yaml`` (a recording that was killed before it could close)
    is opened through its single storage file. Returns an open ``rosbags.rosbag2.Reader``;
    raises :class:`BagError` with a one-line reason for anything that is not a readable bag.
    """
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise BagError(f'{p}: no such bag (path does not exist)')
    target = p
    if p.is_dir() and not (p / 'metadata.yaml').exists():
        files = sorted(list(p.glob('*.db3')) + list(p.glob('*.mcap')))
        if len(files) != 1:
            raise BagError(f'{p}: not a rosbag2 bag (no metadata.yaml'
                           + (' and no single .db3/.mcap file)' if not files else
                              f' and {len(files)} storage files)'))
        target = files[0]
    try:
        reader = Reader(target)
        reader.open()
    except BagError:
        raise
    except Exception as exc:  # rosbags raises ReaderError, sqlite3/OSError/struct errors, ...
        raise BagError(f'{p}: cannot open bag: {_one_line(exc)}') from None
    return reader


def iter_bag(path, topics=None, reader=None) -> Iterator[tuple]:
    """Yield ``(connection, timestamp_ns, rawdata)`` in timestamp order.

    ``topics``: iterable of topic names to keep (``None`` = all). Storage errors while reading
    (truncated/corrupt files) are raised as :class:`BagError` naming how far the read got.
    """
    own = reader is None
    if own:
        reader = open_bag(path)
    count = 0
    try:
        conns = [c for c in reader.connections if topics is None or c.topic in set(topics)]
        if topics is not None and not conns:
            return
        try:
            for conn, t, raw in reader.messages(connections=conns):
                count += 1
                yield conn, t, raw
        except GeneratorExit:
            raise
        except Exception as exc:
            raise BagError(f'{path}: bag is corrupt or truncated (failed after {count} messages): '
                           f'{_one_line(exc)}') from None
    finally:
        if own:
            try:
                reader.close()
            except Exception:
                pass


def bag_summary(path) -> dict:
    """Topics, types, counts and time span of a bag (for messages and tests)."""
    reader = open_bag(path)
    try:
        return {
            'topics': {t: {'type': info.msgtype, 'count': info.msgcount}
                       for t, info in reader.topics.items()},
            'message_count': reader.message_count,
            'start_ns': reader.start_time,
            'end_ns': reader.end_time,
        }
    finally:
        reader.close()


# --------------------------------------------------------------------------------------------
# Types, message definitions, QoS
# --------------------------------------------------------------------------------------------

def normalize_type(msgtype: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``."""
    parts = [x for x in msgtype.strip().split('/') if x]
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        raise ValueError(f'invalid message type {msgtype!r} (expected pkg/msg/Name)')
    return '/'.join(parts)


def get_message_class(msgtype: str):
    """Python class of an installed ROS message type (``pkg/msg/Name``)."""
    pkg, sub, name = normalize_type(msgtype).split('/')
    try:
        module = importlib.import_module(f'{pkg}.{sub}')
        return getattr(module, name)
    except (ImportError, AttributeError):
        raise BagError(f'message type {msgtype} is not installed (no Python module {pkg}.{sub}.'
                       f'{name})') from None


_TYPESTORE = None
_TS_LOCK = threading.Lock()


def typestore():
    """The rosbags typestore for ROS 2 Jazzy (shared, extended on demand with installed types)."""
    global _TYPESTORE
    with _TS_LOCK:
        if _TYPESTORE is None:
            from rosbags.typesys import Stores, get_typestore
            _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
        return _TYPESTORE


def _share_dirs():
    dirs = []
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix:
            dirs.append(Path(prefix) / 'share')
    dirs.append(Path(sys.prefix) / 'share')
    return dirs


def _register_from_share(ts, msgtype: str, seen=None) -> bool:
    """Register ``msgtype`` (and its dependencies) from installed ``.msg`` files."""
    from rosbags.typesys import get_types_from_msg

    seen = set() if seen is None else seen
    if msgtype in ts.fielddefs or msgtype in seen:
        return True
    seen.add(msgtype)
    pkg, sub, name = msgtype.split('/')
    for share in _share_dirs():
        f = share / pkg / sub / f'{name}.msg'
        if f.is_file():
            types = get_types_from_msg(f.read_text(), msgtype)
            # dependencies first
            for _, (_, fields) in types.items():
                for _, desc in fields:
                    for dep in _field_types(desc):
                        if '/' in dep and dep not in ts.fielddefs:
                            _register_from_share(ts, normalize_type(dep), seen)
            ts.register(types)
            return True
    return False


def _field_types(desc):
    """Names of complex types referenced by a rosbags field descriptor."""
    out = []
    try:
        kind, rest = desc
    except (TypeError, ValueError):
        return out
    kind_name = getattr(kind, 'name', str(kind))
    if kind_name == 'NAME':
        out.append(rest)
    elif kind_name in ('ARRAY', 'SEQUENCE'):
        out.extend(_field_types(rest[0]))
    return out


def message_definition(msgtype: str, graph_hash: str = '') -> tuple[str, str]:
    """``(msgdef, rihs01)`` for a message type, for rosbag2 metadata.

    From the Jazzy typestore; types it lacks are registered from the installed ``.msg`` files.
    If neither knows the type, the definition is empty (what ``ros2 bag`` writes for an unknown
    type) and the hash is the one the graph reported.
    """
    msgtype = normalize_type(msgtype)
    ts = typestore()
    with _TS_LOCK:
        try:
            if msgtype not in ts.fielddefs:
                _register_from_share(ts, msgtype)
            if msgtype in ts.fielddefs:
                msgdef, _ = ts.generate_msgdef(msgtype, ros_version=2)
                return msgdef, ts.hash_rihs01(msgtype)
        except Exception:
            pass
    return '', graph_hash or ''


def _duration_to_qostime(d):
    from rosbags.interfaces import QosTime
    ns = int(getattr(d, 'nanoseconds', 0))
    return QosTime(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def qos_to_rosbags(profile):
    """rclpy ``QoSProfile`` -> rosbags ``Qos`` (for ``offered_qos_profiles``)."""
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


def adapted_qos(offered, depth: int = 1000, reliability: str = 'auto'):
    """Subscription/publisher QoS compatible with all ``offered`` profiles (rclpy or rosbags).

    Reliable only if every offered profile is reliable, transient-local only if every one is
    (the rule ``ros2 bag`` uses). ``reliability`` may force ``reliable``/``best_effort``.
    """
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

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


def _storage_plugin(storage: str):
    from rosbags.rosbag2 import StoragePlugin
    try:
        return {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}[storage]
    except KeyError:
        raise BagError(f'unknown storage {storage!r} (use sqlite3 or mcap)') from None


# --------------------------------------------------------------------------------------------
# Recorder
# --------------------------------------------------------------------------------------------

class _WriterThread:
    """Owns the rosbags ``Writer`` in one thread.

    sqlite3 objects are bound to the thread that created them while subscription callbacks may
    run on any executor thread; this also keeps disk I/O out of the DDS callbacks. Operations
    are queued in order; errors are kept and raised (as :class:`BagError`) by :meth:`close`.
    """

    def __init__(self, path: Path, storage: str, custom: dict):
        import queue
        self.path = path
        self.error: Optional[str] = None
        self._q = queue.Queue()
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(storage, custom, ready),
                                        name='dgp_record_writer', daemon=True)
        self._thread.start()
        ready.wait()
        if self.error:
            self._thread.join()
            raise BagError(self.error)

    def _run(self, storage, custom, ready):
        from rosbags.rosbag2 import Writer
        try:
            w = Writer(self.path, version=9, storage_plugin=_storage_plugin(storage))
            w.open()
            for k, v in custom.items():
                w.set_custom_data(k, v)
        except Exception as exc:
            self.error = f'{self.path}: cannot create bag: {_one_line(exc)}'
            ready.set()
            return
        ready.set()
        conns = {}
        while True:
            op = self._q.get()
            try:
                if op[0] == 'add':
                    _, topic, typ, msgdef, rihs, offered = op
                    conns[topic] = w.add_connection(topic, typ, msgdef=msgdef, rihs01=rihs,
                                                    serialization_format='cdr',
                                                    offered_qos_profiles=offered)
                elif op[0] == 'write':
                    _, topic, t, data = op
                    w.write(conns[topic], t, data)
                elif op[0] == 'close':
                    w.close()
                    return
            except Exception as exc:
                if self.error is None:
                    self.error = f'{self.path}: writing failed: {_one_line(exc)}'
                if op[0] == 'close':
                    return

    def add_connection(self, topic, typ, msgdef, rihs, offered):
        self._q.put(('add', topic, typ, msgdef, rihs, offered))

    def write(self, topic, t_ns, data):
        self._q.put(('write', topic, t_ns, data))

    def close(self):
        """Flush everything queued, close the bag (metadata.yaml); raise BagError on failure."""
        if self._thread.is_alive():
            self._q.put(('close',))
            self._thread.join()
        if self.error:
            raise BagError(self.error)


class Recorder:
    """Record topics to a rosbag2 bag from inside an rclpy node.

    Callbacks may run on any executor thread; the bag is written by one writer thread.

    ``topics``: mapping fully-qualified-or-relative topic name -> type (``None`` = take it from
    the graph). Call :meth:`close` (always) to write the metadata. ``done`` becomes True once
    ``max_messages`` messages were written.
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
        self.counts: dict[str, int] = {}
        self.done = False
        self._closed = False
        self._lock = threading.Lock()
        self._pending: dict[str, Optional[str]] = {}
        for name, typ in dict(topics).items():
            fq = node.resolve_topic_name(name)
            self._pending[fq] = normalize_type(typ) if typ else None
        self._subs = {}
        self.writer = _WriterThread(self.path, storage, {'recorded_by': 'dgp_ros.bagtools'})
        self._timer = None
        self._discover()
        if self._pending:
            self._timer = node.create_timer(discovery_period, self._discover)

    @property
    def subscribed(self) -> list:
        """Topics subscribed so far (fully qualified)."""
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
                typ = normalize_type(types[0])
            # explicit type and no publisher yet: subscribe now (reliable unless told otherwise,
            # volatile; no offered QoS to store), so that the first messages are not missed
            pubs_t = [p for p in pubs if normalize_type(p.topic_type) == typ] or pubs
            self._subscribe(topic, typ, pubs_t)
            del self._pending[topic]
        if not self._pending and self._timer is not None:
            self._timer.cancel()

    def _subscribe(self, topic, typ, pubs):
        cls = get_message_class(typ)
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
        """Destroy the subscriptions and close the bag (writes metadata.yaml)."""
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


# --------------------------------------------------------------------------------------------
# Player
# --------------------------------------------------------------------------------------------

class Player:
    """Publish a bag's messages from an rclpy node with their original timing.

    ``rate``: time scale (2 = twice as fast; 0 = as fast as possible). ``clock_hz``: publish
    ``/clock`` with the bag time at this wall rate (``0`` = not at all; with ``rate=0`` a clock
    message precedes every message instead). ``remap``: {bag topic: published topic}.
    ``wait_for_subscribers``: before starting, wait up to this many seconds until every publisher
    has at least ``min_subscribers`` subscribers (``0`` = do not wait). ``stop``: a
    ``threading.Event`` that ends playback early. The player does not need an executor: publishing needs no spinning.
    """

    def __init__(self, node, path, rate: float = 1.0, clock_hz: float = 0.0, loop: bool = False,
                 topics=None, remap=None, depth: int = 1000, start_delay: float = 0.0,
                 wait_for_subscribers: float = 0.0, stop: Optional[threading.Event] = None,
                 log: Optional[Callable[[str], None]] = None, min_subscribers: int = 1):
        if rate < 0:
            raise ValueError('rate must be >= 0')
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
        if int(min_subscribers) < 1:
            raise ValueError('min_subscribers must be >= 1')
        self.min_subscribers = int(min_subscribers)
        self.stop = stop or threading.Event()
        self.log = log or (lambda s: node.get_logger().info(s))
        self.published = 0
        self.loops = 0
        self._reader = open_bag(self.path)
        self._pubs = {}
        self._clock_pub = None
        try:
            self._make_publishers()
        except BaseException:
            self._reader.close()
            raise

    def _make_publishers(self):
        conns = [c for c in self._reader.connections
                 if self.topics is None or c.topic in self.topics]
        if self.topics is not None:
            missing = self.topics - {c.topic for c in conns}
            if missing:
                raise BagError(f'{self.path}: topic(s) not in bag: {", ".join(sorted(missing))}')
        by_topic = {}
        for c in conns:
            by_topic.setdefault(c.topic, []).append(c)
        for topic, cs in by_topic.items():
            types = {c.msgtype for c in cs}
            if len(types) != 1:
                raise BagError(f'{self.path}: topic {topic} has several types {sorted(types)}')
            cls = get_message_class(cs[0].msgtype)
            offered = [q for c in cs for q in getattr(c.ext, 'offered_qos_profiles', [])]
            qos = adapted_qos(offered, self.depth)
            out = self.remap.get(topic, topic)
            self._pubs[topic] = self.node.create_publisher(cls, out, qos)
        self._conns = conns
        if self.clock_hz > 0:
            from rclpy.qos import QoSProfile
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
            time.sleep(0.02)
        lonely = [p.topic_name for p in self._pubs.values()
                  if p.get_subscription_count() < self.min_subscribers]
        if lonely:
            self.log(f'no subscriber yet on {", ".join(lonely)}; playing anyway')

    def run(self) -> int:
        """Play (blocking); returns the number of messages published."""
        self._wait_subscribers()
        if self.start_delay > 0:
            self.stop.wait(self.start_delay)
        while not self.stop.is_set():
            wall_t0 = time.monotonic()
            bag_t0 = None
            for conn, t, raw in iter_bag(self.path, reader=self._reader,
                                         topics=[c.topic for c in self._conns]):
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
        """Wait (bounded) until reliable subscribers acknowledged everything published."""
        from rclpy.duration import Duration
        for pub in self._pubs.values():
            try:
                pub.wait_for_all_acked(timeout=Duration(seconds=timeout_s))
            except Exception:
                pass

    def close(self):
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


# --------------------------------------------------------------------------------------------
# CLIs
# --------------------------------------------------------------------------------------------

def _split_ros_args(argv):
    """Split ``argv`` into (args for rclpy.init, args for argparse).

    Only what sits between ``--ros-args`` and ``--`` (or the end) goes to rclpy, so that our own
    ``--remap FROM:=TO`` is not taken for a deprecated ROS remapping rule.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    ros, mine, inside = [], [], False
    for tok in argv:
        if tok == '--ros-args':
            inside = True
            ros.append(tok)
        elif inside and tok == '--':
            inside = False
        elif inside:
            ros.append(tok)
        else:
            mine.append(tok)
    return ['dgp'] + ros, mine


class _Stop:
    """SIGINT/SIGTERM -> an Event (so the bag gets closed properly)."""

    def __init__(self):
        self.event = threading.Event()
        self.signum = None
        self._old = {}

    def __enter__(self):
        for s in (signal.SIGINT, signal.SIGTERM):
            self._old[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum, _frame):
        if self.event.is_set():  # second signal: give up politely
            raise KeyboardInterrupt
        self.signum = signum
        self.event.set()

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)
        return False


def _init_rclpy(full_argv):
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    ctx = rclpy.Context()
    rclpy.init(args=full_argv, context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    return ctx


def _err(prog, msg) -> int:
    print(f'{prog}: error: {msg}', file=sys.stderr)
    return EXIT_BAG_ERROR


def record_main(argv=None) -> int:
    prog = 'dgp-record'
    full, args_ = _split_ros_args(argv)
    ap = argparse.ArgumentParser(
        prog=prog, description='Record ROS 2 topics to a rosbag2 bag (CDR bytes as received).')
    ap.add_argument('topics', nargs='*', help='topics to record (type taken from the graph)')
    ap.add_argument('--topic', '-t', action='append', default=[], metavar='NAME[:TYPE]',
                    help='topic to record, optionally with its type (pkg/msg/Name); repeatable')
    ap.add_argument('--output', '-o', required=True,
                    help='bag directory to create (must not exist)')
    ap.add_argument('--storage', '-s', choices=STORAGES, default='sqlite3')
    ap.add_argument('--duration', '-d', type=float, default=0.0,
                    help='stop after this many seconds (wall time; 0 = until SIGINT/SIGTERM)')
    ap.add_argument('--max-messages', '-n', type=int, default=0,
                    help='stop after this many messages in total (0 = no limit)')
    ap.add_argument('--qos-depth', type=int, default=1000, help='subscription queue depth')
    ap.add_argument('--qos-reliability', choices=('auto', 'reliable', 'best_effort'),
                    default='auto', help='subscription reliability (auto: adapt to publishers)')
    ap.add_argument('--quiet', '-q', action='store_true')
    a = ap.parse_args(args_)
    topics = {}
    try:
        for t in a.topics:
            topics[t] = None
        for spec in a.topic:
            name, _, typ = spec.partition(':')
            topics[name] = normalize_type(typ) if typ else None
    except ValueError as exc:
        ap.error(str(exc))
    if not topics:
        ap.error('no topics given')
    if Path(a.output).exists():
        return _err(prog, f'{a.output} exists already, not overwriting')

    ctx = _init_rclpy(full)
    node = rec = None
    try:
        with _Stop() as stop:
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.node import Node
            node = Node('dgp_record', context=ctx)
            log = (lambda s: None) if a.quiet else (lambda s: print(f'{prog}: {s}',
                                                                    file=sys.stderr))
            rec = Recorder(node, a.output, topics, storage=a.storage, max_messages=a.max_messages,
                           depth=a.qos_depth, reliability=a.qos_reliability, log=log)
            ex = SingleThreadedExecutor(context=ctx)
            ex.add_node(node)
            t_end = time.monotonic() + a.duration if a.duration > 0 else None
            try:
                while not stop.event.is_set() and not rec.done and ctx.ok():
                    if t_end is not None and time.monotonic() >= t_end:
                        break
                    ex.spin_once(timeout_sec=0.05)
            finally:
                ex.shutdown()
            rec.close()
            if not a.quiet:
                per = ', '.join(f'{k}: {v}' for k, v in rec.counts.items()) or 'no topic seen'
                log(f'wrote {rec.count} messages to {a.output} ({per})')
        return EXIT_OK
    except BagError as exc:
        return _err(prog, exc)
    except KeyboardInterrupt:
        return 130
    finally:
        if rec is not None:
            try:
                rec.close()
            except Exception:
                pass
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


def _parse_remaps(specs):
    out = {}
    for spec in specs:
        src, sep, dst = spec.partition(':=')
        if not sep or not src or not dst:
            raise ValueError(f'invalid remap {spec!r} (expected from:=to)')
        out[src] = dst
    return out


def play_main(argv=None) -> int:
    prog = 'dgp-play'
    full, args_ = _split_ros_args(argv)
    ap = argparse.ArgumentParser(prog=prog, description='Publish the messages of a rosbag2 bag.')
    ap.add_argument('bag', help='bag directory (or .db3/.mcap file)')
    ap.add_argument('--rate', '-r', type=float, default=1.0,
                    help='time scale: 1 = original timing, 2 = twice as fast, 0 = as fast as '
                         'possible')
    ap.add_argument('--clock', nargs='?', type=float, const=100.0, default=0.0, metavar='HZ',
                    help='publish /clock with the bag time (default 100 Hz when given)')
    ap.add_argument('--loop', '-l', action='store_true', help='play again and again')
    ap.add_argument('--topics', nargs='+', default=None, help='only these topics')
    ap.add_argument('--remap', '-m', action='append', default=[], metavar='FROM:=TO',
                    help='publish bag topic FROM as TO; repeatable')
    ap.add_argument('--delay', type=float, default=0.0, help='seconds to wait before playing')
    ap.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                    help='wait up to S seconds for a subscriber on every topic before playing')
    ap.add_argument('--min-subscribers', type=int, default=1, metavar='K',
                    help='with --wait-for-subscribers: wait for K subscribers per topic')
    ap.add_argument('--qos-depth', type=int, default=1000)
    ap.add_argument('--quiet', '-q', action='store_true')
    a = ap.parse_args(args_)
    if a.rate < 0:
        ap.error('--rate must be >= 0')
    if a.min_subscribers < 1:
        ap.error('--min-subscribers must be >= 1')
    try:
        remap = _parse_remaps(a.remap)
    except ValueError as exc:
        ap.error(str(exc))
    # fail fast on a bad bag, before any ROS setup
    try:
        open_bag(a.bag).close()
    except BagError as exc:
        return _err(prog, exc)

    ctx = _init_rclpy(full)
    node = player = None
    try:
        with _Stop() as stop:
            from rclpy.node import Node
            node = Node('dgp_play', context=ctx)
            log = (lambda s: None) if a.quiet else (lambda s: print(f'{prog}: {s}',
                                                                    file=sys.stderr))
            player = Player(node, a.bag, rate=a.rate, clock_hz=a.clock, loop=a.loop,
                            topics=a.topics, remap=remap, depth=a.qos_depth, start_delay=a.delay,
                            wait_for_subscribers=a.wait_for_subscribers, stop=stop.event, log=log,
                            min_subscribers=a.min_subscribers)
            n = player.run()
            if not a.quiet:
                log(f'published {n} messages ({player.loops} pass(es))')
            # give reliable transports a moment to deliver the tail before tearing down
            player.wait_for_acks(2.0)
        return EXIT_OK
    except BagError as exc:
        return _err(prog, exc)
    except KeyboardInterrupt:
        return 130
    finally:
        if player is not None:
            player.close()
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


if __name__ == '__main__':  # pragma: no cover
    sys.exit(record_main())

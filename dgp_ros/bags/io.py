"""
rosbag2 reading and writing with the ``rosbags`` library only (no rclpy, no DDS).

Bags are standard rosbag2 (metadata version 9, storage ``sqlite3`` or ``mcap``), so a full
ROS 2 Jazzy install (``ros2 bag info/play``) reads what is written here and the other way round.
Everything that needs rclpy (recording from and publishing to DDS) is in
:mod:`dgp_ros.bags.ros`; JointState streams (read and write) are in
:mod:`dgp_ros.bags.joint_states`, on top of this module.

Errors a user can cause (a missing, corrupt or truncated bag, an unknown storage, a message type
that may not be resolved) are raised as :class:`BagError` with a one-line message.

Message types named in a bag are data, not code: :func:`check_message_type` decides, without
importing anything, whether a type may be turned into a Python class (``import <pkg>.msg``) at
all. Only the ROS 2 Jazzy types of the standard interface packages (:data:`ALLOWED_PACKAGES`)
pass, so a bag that names ``this/msg/Zen`` cannot make a tool import the module ``this``.
"""
from __future__ import annotations

import os
from pathlib import Path
import queue
import re
import sys
import threading
from typing import Iterable, Iterator, Optional

STORAGES = ('sqlite3', 'mcap')

# ROS 2 interface packages whose Jazzy message types may be resolved to Python classes: the
# core and common_interfaces packages (types outside the Jazzy typestore are refused anyway).
ALLOWED_PACKAGES = frozenset({
    'action_msgs', 'actionlib_msgs', 'builtin_interfaces', 'diagnostic_msgs', 'geometry_msgs',
    'lifecycle_msgs', 'nav_msgs', 'rcl_interfaces', 'rosgraph_msgs', 'sensor_msgs',
    'shape_msgs', 'statistics_msgs', 'std_msgs', 'stereo_msgs', 'tf2_msgs', 'trajectory_msgs',
    'unique_identifier_msgs', 'visualization_msgs',
})

_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_]*\Z')


class BagError(Exception):
    """A bag cannot be opened, read or written; the message is one line, meant for the user."""


def _one_line(exc: BaseException, limit: int = 200) -> str:
    """``exc`` as one line of at most ``limit`` characters (for :class:`BagError` messages)."""
    text = ' '.join(str(exc).split())
    if not text or isinstance(exc, (MemoryError, OverflowError)):
        text = f'{type(exc).__name__} {text}'.strip() + ' while decoding (corrupt data?)'
    return text if len(text) <= limit else text[:limit - 3] + '...'


# ------------------------------------------------------------------------------------ reading
def open_bag(path):
    """
    Open a rosbag2 bag for reading.

    Parameters
    ----------
    path : str or Path
        Bag directory, or a bare ``.db3`` / ``.mcap`` file. A directory without
        ``metadata.yaml`` (a recording killed before it could close) is opened through its
        single storage file.

    Returns
    -------
    rosbags.rosbag2.Reader
        Open; the caller closes it.

    Raises
    ------
    BagError
        With a one-line reason, for anything that is not a readable bag.

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
    except Exception as exc:  # rosbags raises ReaderError, sqlite3/OSError/struct errors, ...
        raise BagError(f'{p}: cannot open bag: {_one_line(exc)}') from None
    return reader


def iter_bag(path, topics: Optional[Iterable[str]] = None, reader=None) -> Iterator[tuple]:
    """
    Yield ``(connection, timestamp_ns, rawdata)`` in timestamp order.

    Parameters
    ----------
    path : str or Path
        The bag (opened here unless ``reader`` is given; also named in error messages).
    topics : iterable of str, optional
        Topic names to keep (``None``: all).
    reader : rosbags.rosbag2.Reader, optional
        An open reader to use (not closed here).

    Raises
    ------
    BagError
        A storage error while reading (truncated or corrupt file), naming how far it got.

    """
    own = reader is None
    if own:
        reader = open_bag(path)
    keep = None if topics is None else set(topics)
    count = 0
    try:
        conns = [c for c in reader.connections if keep is None or c.topic in keep]
        if keep is not None and not conns:
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
    """
    Topics, types, counts and time span of a bag.

    Returns
    -------
    dict
        ``topics`` ({topic: {'type', 'count'}}), ``message_count``, ``start_ns``, ``end_ns``
        (bag receive times, ns).

    """
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


# ------------------------------------------------------------------- types and definitions
def normalize_type(msgtype: str) -> str:
    """
    ``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``.

    Raises
    ------
    ValueError
        Not of that form, or a part is not a ROS name (letters, digits, ``_``; a letter
        first), which also keeps ``..`` out of the file paths built from a type.

    """
    parts = [x for x in str(msgtype).strip().split('/') if x]
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(_NAME.match(x) for x in parts):
        raise ValueError(f'invalid message type {msgtype!r} (expected pkg/msg/Name)')
    return '/'.join(parts)


_TYPESTORE = None
_JAZZY_TYPES: frozenset = frozenset()
_TS_LOCK = threading.Lock()


def typestore():
    """
    Return the rosbags typestore for ROS 2 Jazzy (one per process, shared).

    :func:`message_definition` extends it with types registered from installed ``.msg``
    files; :func:`check_message_type` only trusts the types it had before that.
    """
    global _TYPESTORE, _JAZZY_TYPES
    with _TS_LOCK:
        if _TYPESTORE is None:
            from rosbags.typesys import Stores, get_typestore
            _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
            _JAZZY_TYPES = frozenset(_TYPESTORE.fielddefs)
        return _TYPESTORE


def _jazzy_types() -> frozenset:
    """Type names of the Jazzy store as shipped by rosbags (none registered from files)."""
    typestore()
    return _JAZZY_TYPES


def _share_dirs() -> list:
    """``share`` folders of the ament prefixes, then of this Python environment."""
    dirs = [Path(p) / 'share' for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
            if p]
    dirs.append(Path(sys.prefix) / 'share')
    return dirs


def installed_definition(msgtype: str) -> Optional[Path]:
    """
    Return the installed ``share/<pkg>/msg/<Name>.msg`` file of a type, or None.

    Its presence marks ``<pkg>`` as an installed ROS interface package (found through
    ``AMENT_PREFIX_PATH`` or this environment's ``share`` folder).
    """
    pkg, sub, name = normalize_type(msgtype).split('/')
    for share in _share_dirs():
        f = share / pkg / sub / f'{name}.msg'
        if f.is_file():
            return f
    return None


def check_message_type(msgtype: str, allow_installed: bool = False) -> str:
    """
    Decide, without importing anything, whether a type may be resolved to a Python class.

    Parameters
    ----------
    msgtype : str
        ``pkg/msg/Name`` (or ``pkg/Name``), e.g. from a bag's connection or the ROS graph.
    allow_installed : bool
        Also accept a type outside the fixed store whose definition is installed
        (:func:`installed_definition`): the recorder's rule for user interface packages.
        Bag playback never sets it.

    Returns
    -------
    str
        The normalized type name. It is in the ROS 2 Jazzy typestore of rosbags and its
        package is in :data:`ALLOWED_PACKAGES` (or, with ``allow_installed``, installed).

    Raises
    ------
    BagError
        One line naming the type and the reason.

    """
    try:
        t = normalize_type(msgtype)
    except ValueError as exc:
        raise BagError(str(exc)) from None
    pkg = t.split('/')[0]
    if t in _jazzy_types() and pkg in ALLOWED_PACKAGES:
        return t
    if allow_installed and installed_definition(t) is not None:
        return t
    why = (f'package {pkg} is not an allowed interface package' if t in _jazzy_types()
           else 'not a ROS 2 Jazzy message type of the standard interface packages')
    raise BagError(f'message type {t} refused: {why}')


def _field_types(desc) -> list:
    """Names of the complex types referenced by a rosbags field descriptor."""
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


def _register_from_share(ts, msgtype: str, seen=None) -> bool:
    """Register ``msgtype`` (dependencies first) in ``ts`` from installed ``.msg`` files."""
    from rosbags.typesys import get_types_from_msg

    seen = set() if seen is None else seen
    if msgtype in ts.fielddefs or msgtype in seen:
        return True
    seen.add(msgtype)
    f = installed_definition(msgtype)
    if f is None:
        return False
    types = get_types_from_msg(f.read_text(), msgtype)
    for _, (_, fields) in types.items():
        for _, desc in fields:
            for dep in _field_types(desc):
                if '/' in dep and dep not in ts.fielddefs:
                    _register_from_share(ts, normalize_type(dep), seen)
    ts.register(types)
    return True


def message_definition(msgtype: str, graph_hash: str = '') -> tuple:
    """
    ``(msgdef, rihs01)`` of a message type, for rosbag2 metadata.

    From the Jazzy typestore; a type it lacks is registered from the installed ``.msg`` files.
    If neither knows the type, the definition is empty (what ``ros2 bag`` writes for an unknown
    type) and the hash is ``graph_hash`` (the one the ROS graph reported, may be empty).
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


def playable_topics(reader, topics: Optional[Iterable[str]] = None, name=None) -> dict:
    """
    Return the topics of an open bag to publish, each with its checked type and connections.

    Parameters
    ----------
    reader : rosbags.rosbag2.Reader
        Open bag.
    topics : iterable of str, optional
        Only these topics (all by default).
    name : str or Path, optional
        How error messages name the bag.

    Returns
    -------
    dict
        ``{topic: (msgtype, [connections])}`` in the bag's connection order; every ``msgtype``
        passed :func:`check_message_type` (so it may be imported).

    Raises
    ------
    BagError
        A wanted topic is missing, a topic has several types, or a type is refused.

    """
    name = name if name is not None else getattr(reader, 'path', 'bag')
    keep = None if topics is None else set(topics)
    conns = [c for c in reader.connections if keep is None or c.topic in keep]
    missing = sorted((keep or set()) - {c.topic for c in conns})
    if missing:
        raise BagError(f'{name}: topic(s) not in bag: {", ".join(missing)}')
    by_topic: dict = {}
    for c in conns:
        by_topic.setdefault(c.topic, []).append(c)
    out = {}
    for topic, cs in by_topic.items():
        found = sorted({c.msgtype for c in cs})
        if len(found) != 1:
            raise BagError(f'{name}: topic {topic} has several types {found}')
        try:
            out[topic] = (check_message_type(found[0]), cs)
        except BagError as exc:
            raise BagError(f'{name}: topic {topic}: {exc}') from None
    return out


# ------------------------------------------------------------------------------------ writing
def storage_plugin(storage: str):
    """``'sqlite3'`` / ``'mcap'`` -> ``rosbags.rosbag2.StoragePlugin``; BagError otherwise."""
    from rosbags.rosbag2 import StoragePlugin
    try:
        return {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}[storage]
    except KeyError:
        raise BagError(f'unknown storage {storage!r} (use sqlite3 or mcap)') from None


class BagWriter:
    """
    A rosbags ``Writer`` owned by one thread of its own, fed through a queue.

    sqlite3 objects are bound to the thread that created them, while a recorder's callbacks
    may run on any executor thread; the queue also keeps disk I/O out of those callbacks.
    Operations are applied in order; the first error is kept and raised by :meth:`close`.

    Parameters
    ----------
    path : str or Path
        Bag directory to create (must not exist).
    storage : str
        ``'sqlite3'`` or ``'mcap'``.
    custom : dict, optional
        Custom metadata (str -> str), e.g. ``{'recorded_by': ...}``.

    Raises
    ------
    BagError
        The bag cannot be created.

    """

    def __init__(self, path, storage: str = 'sqlite3', custom: Optional[dict] = None):
        self.path = Path(path)
        self.error: Optional[str] = None
        self._q: queue.Queue = queue.Queue()
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(storage, dict(custom or {}),
                                                                ready),
                                        name='dgp_bag_writer', daemon=True)
        self._thread.start()
        ready.wait()
        if self.error:
            self._thread.join()
            raise BagError(self.error)

    def _run(self, storage, custom, ready):
        from rosbags.rosbag2 import Writer
        try:
            w = Writer(self.path, version=9, storage_plugin=storage_plugin(storage))
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

    def add_connection(self, topic: str, msgtype: str, msgdef: str, rihs01: str,
                       offered=()) -> None:
        """Queue a connection (``offered``: rosbags ``Qos`` profiles for the metadata)."""
        self._q.put(('add', topic, msgtype, msgdef, rihs01, list(offered)))

    def write(self, topic: str, t_ns: int, data: bytes) -> None:
        """Queue one CDR message of ``topic`` with bag timestamp ``t_ns`` (ns)."""
        self._q.put(('write', topic, t_ns, data))

    def close(self) -> None:
        """Flush everything queued and close the bag (metadata.yaml); BagError on failure."""
        if self._thread.is_alive():
            self._q.put(('close',))
            self._thread.join()
        if self.error:
            raise BagError(self.error)

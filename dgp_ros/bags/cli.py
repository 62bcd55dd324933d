"""
``dgp-record`` and ``dgp-play``: rosbag2 record / play without the ``ros2`` CLI.

``dgp-record [TOPIC ...] [-t NAME[:TYPE] ...] -o BAG [-s sqlite3|mcap] [-d S] [-n N]``
    Records with :class:`dgp_ros.bags.ros.Recorder` until SIGINT/SIGTERM, ``--duration``
    seconds (wall time) or ``--max-messages`` messages. On a signal or at the end of the
    duration, the messages that have already arrived are taken (for at most one second), then
    the bag is closed properly (metadata written).

``dgp-play BAG [-r RATE] [--clock [HZ]] [-l] [--topics T ...] [-m FROM:=TO ...]``
    Publishes with :class:`dgp_ros.bags.ros.Player`. The bag and the types of the topics to
    play are checked before ROS starts (:func:`dgp_ros.bags.io.playable_topics`).

Both print a one-line message and exit with code 2 for a missing, corrupt or truncated bag, or
a refused message type (no traceback); 130 after a second SIGINT. ROS arguments go after
``--ros-args`` (``-r`` remaps, ``-p use_sim_time:=true``, ...).
"""
from __future__ import annotations

import argparse
from pathlib import Path
import signal
import sys
import threading
import time

from dgp_ros.bags.io import BagError, normalize_type, open_bag, playable_topics, STORAGES

EXIT_OK = 0
EXIT_BAG_ERROR = 2
EXIT_INTERRUPTED = 130
DRAIN_S = 1.0          # at most this long to take what has arrived when recording stops


def _split_ros_args(argv):
    """
    Split ``argv`` into (args for ``rclpy.init``, args for argparse).

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


def _parse(ap: argparse.ArgumentParser, argv):
    """``(args for rclpy.init, parsed namespace)``; exits with 2 on a usage error."""
    full, mine = _split_ros_args(argv)
    return full, ap.parse_args(mine)


class _Stop:
    """
    SIGINT/SIGTERM -> an Event, so that the bag gets closed properly.

    A second signal raises KeyboardInterrupt (the caller exits with 130).
    """

    def __init__(self):
        self.event = threading.Event()
        self.signum = None
        self._old = {}

    def __enter__(self):
        for s in (signal.SIGINT, signal.SIGTERM):
            self._old[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum, _frame):
        if self.event.is_set():
            raise KeyboardInterrupt
        self.signum = signum
        self.event.set()

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)
        return False


def _run_ros(prog: str, full_argv, node_name: str, body) -> int:
    """
    Run ``body(ctx, node, stop_event)`` with a fresh rclpy context and node.

    rclpy's own signal handlers are off (:class:`_Stop` turns SIGINT/SIGTERM into
    ``stop_event``). Returns the exit status: 0, 2 for a :class:`BagError` (one line on stderr),
    130 after a second signal. ``body`` releases what it creates; the node and the context are
    released here.
    """
    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    ctx = rclpy.Context()
    rclpy.init(args=full_argv, context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        with _Stop() as stop:
            node = Node(node_name, context=ctx)
            body(ctx, node, stop.event)
        return EXIT_OK
    except BagError as exc:
        return _err(prog, exc)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    finally:
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


def _err(prog, msg) -> int:
    print(f'{prog}: error: {msg}', file=sys.stderr)
    return EXIT_BAG_ERROR


def _logger(prog, quiet):
    return (lambda s: None) if quiet else (lambda s: print(f'{prog}: {s}', file=sys.stderr))


def _drain(ex, rec, limit_s: float = DRAIN_S) -> None:
    """
    Take the messages that have already arrived.

    Spin until two short spins in a row bring no message, or ``limit_s`` passed, or
    ``max_messages`` is reached.
    """
    t_end = time.monotonic() + limit_s
    idle = 0
    while idle < 2 and time.monotonic() < t_end and not rec.done:
        before = rec.count
        ex.spin_once(timeout_sec=0.01)
        idle = idle + 1 if rec.count == before else 0


def _record_parser(prog):
    ap = argparse.ArgumentParser(
        prog=prog, formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description='Record ROS 2 topics to a rosbag2 bag (CDR bytes as received).')
    ap.add_argument('topics', nargs='*', help='topics to record (type taken from the graph)')
    ap.add_argument('--topic', '-t', action='append', default=[], metavar='NAME[:TYPE]',
                    help='topic to record, optionally with its type (pkg/msg/Name); repeatable')
    ap.add_argument('--output', '-o', required=True,
                    help='bag directory to create (must not exist)')
    ap.add_argument('--storage', '-s', choices=STORAGES, default='sqlite3',
                    help='rosbag2 storage format of the bag written')
    ap.add_argument('--duration', '-d', type=float, default=0.0,
                    help='stop after this many seconds (wall time; 0 = until SIGINT/SIGTERM)')
    ap.add_argument('--max-messages', '-n', type=int, default=0,
                    help='stop after this many messages in total (0 = no limit)')
    ap.add_argument('--qos-depth', type=int, default=1000, help='subscription queue depth')
    ap.add_argument('--qos-reliability', choices=('auto', 'reliable', 'best_effort'),
                    default='auto', help='subscription reliability (auto: adapt to publishers)')
    ap.add_argument('--quiet', '-q', action='store_true', help='no progress lines on stderr')
    return ap


def record_main(argv=None) -> int:
    """``dgp-record``; returns the exit status (see the module docstring)."""
    prog = 'dgp-record'
    ap = _record_parser(prog)
    full, a = _parse(ap, argv)
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

    from rclpy.executors import SingleThreadedExecutor

    from dgp_ros.bags.ros import Recorder
    log = _logger(prog, a.quiet)

    def record(ctx, node, stop):
        rec = Recorder(node, a.output, topics, storage=a.storage, max_messages=a.max_messages,
                       depth=a.qos_depth, reliability=a.qos_reliability, log=log)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        t_end = time.monotonic() + a.duration if a.duration > 0 else None
        try:
            while not stop.is_set() and not rec.done and ctx.ok():
                if t_end is not None and time.monotonic() >= t_end:
                    break
                ex.spin_once(timeout_sec=0.05)
            if ctx.ok():
                _drain(ex, rec)
        finally:
            ex.shutdown()
            rec.close()                  # metadata.yaml; BagError if writing failed
        per = ', '.join(f'{k}: {v}' for k, v in rec.counts.items()) or 'no topic seen'
        log(f'wrote {rec.count} messages to {a.output} ({per})')

    return _run_ros(prog, full, 'dgp_record', record)


def _parse_remaps(specs) -> dict:
    """``['from:=to', ...]`` -> ``{from: to}``; ValueError for a malformed rule."""
    out = {}
    for spec in specs:
        src, sep, dst = spec.partition(':=')
        if not sep or not src or not dst:
            raise ValueError(f'invalid remap {spec!r} (expected from:=to)')
        out[src] = dst
    return out


def _play_parser(prog):
    ap = argparse.ArgumentParser(prog=prog, description='Publish the messages of a rosbag2 bag.',
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
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
    ap.add_argument('--qos-depth', type=int, default=1000, help='publisher queue depth')
    ap.add_argument('--quiet', '-q', action='store_true', help='no progress lines on stderr')
    return ap


def play_main(argv=None) -> int:
    """``dgp-play``; returns the exit status (see the module docstring)."""
    prog = 'dgp-play'
    ap = _play_parser(prog)
    full, a = _parse(ap, argv)
    if a.rate < 0:
        ap.error('--rate must be >= 0')
    if a.min_subscribers < 1:
        ap.error('--min-subscribers must be >= 1')
    try:
        remap = _parse_remaps(a.remap)
    except ValueError as exc:
        ap.error(str(exc))
    # fail fast on a bad bag or a refused type, before any ROS setup or message import
    try:
        reader = open_bag(a.bag)
        try:
            playable_topics(reader, a.topics, name=a.bag)
        finally:
            reader.close()
    except BagError as exc:
        return _err(prog, exc)

    from dgp_ros.bags.ros import Player
    log = _logger(prog, a.quiet)

    def play(ctx, node, stop):
        player = Player(node, a.bag, rate=a.rate, clock_hz=a.clock, loop=a.loop,
                        topics=a.topics, remap=remap, depth=a.qos_depth, start_delay=a.delay,
                        wait_for_subscribers=a.wait_for_subscribers, stop=stop, log=log,
                        min_subscribers=a.min_subscribers)
        try:
            n = player.run()
            log(f'published {n} messages ({player.loops} pass(es))')
            # give reliable transports a moment to deliver the tail before tearing down
            player.wait_for_acks(2.0)
        finally:
            player.close()

    return _run_ros(prog, full, 'dgp_play', play)

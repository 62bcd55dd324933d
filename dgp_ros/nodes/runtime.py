"""
What every node process of this package shares: --help, parameters, and a clean exit (rclpy).

* ``--help`` prints the parameters (default, range, description) and starts nothing.
* Parameters are declared from a table of ``online.config.ParamSpec`` with
  ``ParameterDescriptor`` ranges; overrides for names the node does not have (``-p
  buffer_sise:=500``, a params file) are refused at start by name, and so is a
  ``ros2 param set`` of an unknown name (with a "did you mean").
* SIGINT and SIGTERM only set a flag: rclpy's own handlers are off, so the context stays valid
  until the node has finished its last callback and saved what it must; the process exits 0
  without a traceback. Invalid parameters exit 2 with a one-line reason.
* The executor (``DGP_EXECUTOR``): ``waitset`` (default), ``executor.WaitSetExecutor``, a loop
  over one rcl wait set that serves services and timers first and hands a subscription every
  waiting message at once (``set_batch_handler``); ``single``, rclpy's SingleThreadedExecutor;
  ``events``, rclpy's EventsExecutor.
"""
from __future__ import annotations

import difflib
import gc
import os
import signal
import sys
import threading
from typing import Callable, Iterable, List

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from dgp_ros.nodes.executor import set_batch_handler, WaitSetExecutor
from dgp_ros.params import check_spec

__all__ = ['declare_parameters', 'unknown_overrides', 'reject_unknown', 'help_text', 'run',
           'WaitSetExecutor', 'set_batch_handler', 'EXECUTORS']

#: the executors ``DGP_EXECUTOR`` chooses from (the first is the default)
EXECUTORS = ('waitset', 'single', 'events')

EXIT_OK, EXIT_USAGE = 0, 2
_ARRAY = {'str[]': Parameter.Type.STRING_ARRAY, 'float[]': Parameter.Type.DOUBLE_ARRAY}


def declare_parameters(node, specs: Iterable) -> None:
    """Declare every ``ParamSpec`` with its default, description and range."""
    for spec in specs:
        desc = ParameterDescriptor(description=spec.description,
                                   read_only=bool(getattr(spec, 'read_only', False)))
        if spec.choices:
            desc.additional_constraints = 'one of: ' + ', '.join(spec.choices)
        if spec.low is not None and spec.type == 'float':
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
        elif spec.low is not None and spec.type == 'int':
            desc.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high),
                                               step=1)]
        if spec.type in _ARRAY and not spec.default:
            # an empty list has no ROS type: declare the type, then set the empty default
            p = node.declare_parameter(spec.name, _ARRAY[spec.type], desc)
            if p.type_ == Parameter.Type.NOT_SET:
                node.set_parameters([Parameter(spec.name, _ARRAY[spec.type], [])])
        else:
            node.declare_parameter(spec.name, spec.default, desc)


def checked_parameters(node, specs) -> dict:
    """
    Declare ``specs`` on ``node`` and return their values by name, each checked.

    ``specs``: ``params.ParamSpec``; unknown overrides are refused and a value outside its spec
    raises ValueError saying which and why.
    """
    specs = list(specs)
    declare_parameters(node, specs)
    check_unknown_overrides(node)
    values = {spec.name: node.get_parameter(spec.name).value for spec in specs}
    for spec in specs:
        check_spec(spec, values[spec.name])
    return values


def _hint(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), 1)
    return f"'{name}'" + (f" (did you mean '{close[0]}'?)" if close else '')


def unknown_overrides(node) -> List[str]:
    """
    List the overrides given to ``node`` (``-p``, params files) for parameters it did not declare.

    rclpy has no public list of the overrides: a throw-away node of the same name declares them
    all automatically, and the difference is what the node does not know.
    """
    probe = rclpy.create_node(node.get_name(), namespace=node.get_namespace(),
                              context=node.context, start_parameter_services=False,
                              enable_rosout=False,
                              automatically_declare_parameters_from_overrides=True)
    try:
        given = set(probe.list_parameters([], 0).names)
    finally:
        probe.destroy_node()
    known = set(node.list_parameters([], 0).names)
    return sorted(n for n in given - known if not n.startswith('qos_overrides.'))


def check_unknown_overrides(node) -> None:
    """Raise ValueError naming the overrides the node does not have."""
    unknown = unknown_overrides(node)
    if unknown:
        known = node.list_parameters([], 0).names
        raise ValueError('unknown parameter(s): ' + ', '.join(_hint(u, known) for u in unknown)
                         + ' (see --help)')


def reject_unknown(node, params) -> SetParametersResult:
    """
    Return a failed result naming the parameters ``node`` does not have, or None (all known).

    The node must be created with ``allow_undeclared_parameters=True`` so that this check (and
    not rclpy's, whose reason has no names) sees a set of an unknown name.
    """
    unknown = [p.name for p in params if not node.has_parameter(p.name)]
    if not unknown:
        return None
    known = node.list_parameters([], 0).names
    return SetParametersResult(successful=False, reason='unknown parameter(s): ' + ', '.join(
        _hint(u, known) for u in unknown))


def help_text(prog: str, description: str, specs: Iterable, remaps: str = '') -> str:
    """Return the ``--help`` text: usage and every parameter with its default and range."""
    import json
    import textwrap
    lines = [f'usage: {prog} [--help] [--ros-args -p NAME:=VALUE ... --params-file FILE '
             f'-r FROM:=TO ...]', '', description, '']
    if remaps:
        lines += [remaps, '']
    lines.append('parameters (name: type = default  range or choices):')
    for spec in specs:
        rng = spec.range_text()
        if rng and spec.choices:
            rng = f'one of {rng}'
        elif rng and spec.type.endswith('[]'):
            rng = f'each in {rng}'
        lines.append(f'  {spec.name}: {spec.type} = {json.dumps(spec.default)}'
                     + (f'  {rng}' if rng else '')
                     + ('  (start-up only)' if getattr(spec, 'read_only', False) else ''))
        lines += textwrap.wrap(spec.description, 95, initial_indent='      ',
                               subsequent_indent='      ')
    return '\n'.join(lines) + '\n'


def _wants_help(argv: List[str]) -> bool:
    mine = argv[1:argv.index('--ros-args')] if '--ros-args' in argv else argv[1:]
    return any(a in ('-h', '--help') for a in mine)


def _executor(context):
    """
    Make the node's executor: ``DGP_EXECUTOR`` = waitset (default) | single | events.

    ``waitset``: ``executor.WaitSetExecutor``. ``single``: rclpy's SingleThreadedExecutor, 350 to
    740 us of CPU per message of its own at 1 kHz (it rebuilds its wait set and wraps every
    callback in a task). ``events``: rclpy's EventsExecutor, cheaper per message than
    ``single`` but it queues one event per received message, unbounded and regardless of the
    subscription's KEEP_LAST depth, and serves timers and services behind that queue: a stream
    faster than the node (sim_bridge at real_time_factor 10, a loaded machine) makes it fall
    behind for good (no /diagnostics, ``~/refit`` unanswered after 20 s, memory growing); it
    also cannot pass the message info. Only ``spin_once`` is used: the EventsExecutor of the
    Jazzy wheels busy-loops in ``spin()``.
    """
    kind = os.environ.get('DGP_EXECUTOR', '') or EXECUTORS[0]
    if kind not in EXECUTORS:
        raise ValueError(f'DGP_EXECUTOR={kind!r}: one of ' + ', '.join(EXECUTORS))
    if kind == 'events':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor(context=context)
        except Exception:       # noqa: BLE001 - an rclpy without it, or one that fails to build it
            kind = 'single'
    if kind == 'waitset':
        return WaitSetExecutor(context=context)
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor(context=context)


def run(prog: str, make_node: Callable, help_message: str, args=None) -> int:
    """
    Run one node until SIGINT/SIGTERM (or ``node.done``); returns the exit status.

    ``make_node()`` builds the node (ValueError / ParameterException: invalid parameters, exit
    2); at the end ``node.shutdown()`` (if it has one) runs while the context is still valid.
    """
    argv = list(sys.argv if args is None else args)
    if _wants_help(argv):
        sys.stdout.write(help_message)
        return EXIT_OK
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, lambda *_: stop.set())
    context = rclpy.Context()
    rclpy.init(args=argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = executor = None
    code = EXIT_OK
    try:
        executor = _executor(context)
        node = make_node(context)
        # what start-up built lives as long as the process: out of the collector's full scans
        # (a gen-2 collection of it took 260 ms in the message path under a 10 kHz stream)
        gc.freeze()
        executor.add_node(node)
        while not stop.is_set() and context.ok() and not getattr(node, 'done', False):
            executor.spin_once(timeout_sec=0.1)
    except (ValueError, ParameterException) as exc:
        print(f'[{prog}] invalid parameters: {exc}', file=sys.stderr)
        code = EXIT_USAGE
    except KeyboardInterrupt:       # a signal before our handlers were installed
        pass
    finally:
        try:
            if node is not None:
                if hasattr(node, 'shutdown'):
                    node.shutdown()
                if executor is not None:
                    executor.remove_node(node)
                node.destroy_node()
            if executor is not None:
                executor.shutdown()
        finally:
            context.try_shutdown()
            if threading.current_thread() is threading.main_thread():
                # interpreter teardown restores the default handlers: a late signal must not
                # kill the process with a traceback or a signal status now
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return code

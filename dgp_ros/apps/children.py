"""
The child processes of a console tool: started isolated on DDS, logged, always stopped.

Both demos start ROS nodes as OS processes over real DDS and listen with a node of their own:

* ``isolated_env``: a random ``ROS_DOMAIN_ID`` and localhost-only discovery, for this process
  (before it creates a context) and its children;
* :class:`Children`: starts each child with its output in ``<out>/<name>.log`` (on Linux it also
  gets SIGTERM when this process dies) and stops it as a user would: SIGINT (a clean ROS
  shutdown: the estimator saves its model), then SIGTERM, then SIGKILL; ``close`` stops every
  child still running, the last started first;
* ``listener``: this process's own rclpy node and executor, shut down on exit.
"""
from __future__ import annotations

import contextlib
import os
import random
import signal
import subprocess
import sys
from typing import Dict, List, Optional

__all__ = ['isolated_env', 'console', 'spawn', 'stop', 'Children', 'listener']


def isolated_env() -> dict:
    """
    Isolate this process and its children on DDS; return the children's environment.

    A random ROS_DOMAIN_ID in 1..101 and localhost-only discovery, set in ``os.environ`` too
    (before this process creates a context); unbuffered child output.
    """
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 101))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    env['PYTHONUNBUFFERED'] = '1'
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                                           'RMW_IMPLEMENTATION')})
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    return env


def console(name: str, module: str) -> List[str]:
    """Return the console script ``name`` next to this interpreter, else ``python -m module``."""
    exe = os.path.join(os.path.dirname(sys.executable), name)
    return [exe] if os.access(exe, os.X_OK) else [sys.executable, '-m', module]


def _die_with_parent():                         # runs in the child before exec (Linux only)
    try:
        import ctypes
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except Exception:
        pass


def spawn(cmd: List[str], env: dict, log_path: str) -> subprocess.Popen:
    """Start ``cmd`` with stdout and stderr in ``log_path``; on Linux it dies with this process."""
    log = open(log_path, 'w')
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                            preexec_fn=_die_with_parent if sys.platform.startswith('linux')
                            else None)


def stop(proc: Optional[subprocess.Popen], name: str, grace: float = 30.0) -> Optional[int]:
    """
    Stop ``proc``: SIGINT, then SIGTERM, then SIGKILL; return its exit status (None: no process).

    ``grace`` [s] is the wait after SIGINT (the estimator saves its model then); 5 s after each
    of the others. A process that already exited is only asked for its status.
    """
    if proc is None:
        return None
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            print(f'[demo] {name} did not stop on {sig.name}', flush=True)
    return proc.poll()


class Children:
    """
    The child processes of one run (module docstring); a context manager that stops them all.

    Parameters
    ----------
    env : dict
        Their environment (``isolated_env``).
    out : str
        The folder of their logs, ``<out>/<name>.log``.

    """

    def __init__(self, env: dict, out: str):
        self.env, self.out = env, out
        self._procs: Dict[str, tuple] = {}          # name -> (Popen, grace [s]), start order

    def start(self, name: str, cmd: List[str], grace: float = 30.0) -> subprocess.Popen:
        """Start ``cmd`` as the child ``name``; ``grace`` [s]: its SIGINT wait in ``close``."""
        proc = spawn(cmd, self.env, os.path.join(self.out, name + '.log'))
        self._procs[name] = (proc, grace)
        return proc

    def stop(self, name: str, grace: Optional[float] = None) -> Optional[int]:
        """Stop the child ``name`` now (``stop``; its own grace unless given); its exit status."""
        proc, own = self._procs.get(name, (None, 0.0))
        return stop(proc, name, own if grace is None else grace)

    def close(self) -> Dict[str, Optional[int]]:
        """Stop every child still running, the last started first; ``{name: exit status}``."""
        return {name: stop(proc, name, grace)
                for name, (proc, grace) in reversed(list(self._procs.items()))}

    def __enter__(self) -> 'Children':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def listener(name: str):
    """
    Yield ``(node, executor)``: an rclpy node ``name`` of this process, spun by a single thread.

    In a context of its own (call ``isolated_env`` first); the executor, the node and the context
    are shut down on exit.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = ex = None
    try:
        node = rclpy.create_node(name, context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        yield node, ex
    finally:
        if ex is not None:
            ex.shutdown()
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()

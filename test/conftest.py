"""
Session-wide test isolation.

DDS: every test session gets its own ROS_DOMAIN_ID and localhost-only discovery, set before any
rclpy context exists, so parallel sessions on one machine (or CI next to a developer) never see
each other's nodes. The id is drawn at random and claimed with an exclusive lock file held for
the whole session, so two concurrent sessions never draw the same one. Child processes inherit
the environment. With pytest-xdist (``-n``, pytest.ini) every worker is a process of its own
that imports this file, so each worker claims a domain of its own the same way: the tests of
one worker never see another worker's nodes.

SIGINT: a session started as a background job of a non-interactive shell (``cmd &`` in a script,
as two concurrent suite runs are) inherits SIGINT *ignored*, and so does every child it starts;
Python then installs no KeyboardInterrupt handler, and a child a test interrupts (``dgp-replay``)
runs on as if nothing was sent. The tests send SIGINT as a terminal does, so the session restores
the default handler (its children then start with the default disposition too).

Expensive results several tests share (a trained model, a simulated flight) come from the
``session_once`` fixture: built once per session, whichever worker asks first, and read by the
others. pytest-xdist's own grouping (``xdist_group`` with ``--dist loadgroup``) does nothing
with pytest 9.2: it renames ``item._nodeid``, which pytest 9 no longer reads, so the tests of a
group ran on different workers and each built the result again (the ledger's A320 flight
twice, 27 s each).
"""
import fcntl
import os
import pickle
import random
import signal
import tempfile

import pytest

_DOMAIN_LOCK = []      # the open lock file: the claim lasts as long as this process


def _claim_domain_id() -> int:
    """Claim a ROS domain id in 1..101 that no other test session on this machine holds."""
    ids = list(range(1, 102))
    random.SystemRandom().shuffle(ids)
    for i in ids:
        f = open(os.path.join(tempfile.gettempdir(), f'dgp_ros_test_domain_{i}.lock'), 'a')
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        _DOMAIN_LOCK.append(f)
        return i
    return ids[0]      # all taken: share one (as a plain random draw would)


if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

os.environ['ROS_DOMAIN_ID'] = str(_claim_domain_id())
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
os.environ.setdefault('MPLBACKEND', 'Agg')
# one BLAS thread: see dgp_ros/__init__.py (oversubscribed OpenBLAS is 100x slower here)
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')


@pytest.fixture(scope='session')
def session_once(tmp_path_factory):
    """
    Return ``once(name, build)``: ``build(directory)`` run once per test session, its value shared.

    The first worker to ask builds under an exclusive lock (the others wait on it) and pickles the
    value; every later call, in any worker, unpickles it. ``directory`` (a str) is shared by all
    workers for the session: files the value names stay valid. A build that raises (or skips)
    stores nothing: the next caller tries again.
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get('PYTEST_XDIST_WORKER'):
        root = root.parent              # the session's directory, above popen-gwN

    def once(name, build):
        with open(root / f'{name}.lock', 'a') as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            data = root / f'{name}.pkl'
            if data.exists():
                return pickle.loads(data.read_bytes())
            directory = root / name
            directory.mkdir(exist_ok=True)
            value = build(str(directory))
            part = root / f'{name}.part'
            part.write_bytes(pickle.dumps(value))
            part.replace(data)
            return value
    return once

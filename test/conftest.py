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
"""
import fcntl
import os
import random
import signal
import tempfile

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

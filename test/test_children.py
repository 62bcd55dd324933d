"""
``dgp_ros.apps.children``: how the demos start, isolate and stop their child processes (no DDS).

A child that exits on SIGINT is stopped by it (its exit status is -SIGINT); one that ignores
SIGINT gets SIGTERM after its grace; ``close`` stops the last started first; ``isolated_env``
picks a domain id in 1..101 with localhost-only discovery for this process and its children.
"""
import os
import signal
import sys
import time

from dgp_ros.apps.children import Children, console, isolated_env

#: prints its start, then sleeps; ``{ignore}`` SIGINT
CHILD = ('import signal, sys, time\n'
         'if {ignore}: signal.signal(signal.SIGINT, signal.SIG_IGN)\n'
         'print("up", flush=True)\n'
         'time.sleep(60)\n')


def _wait_up(path, timeout=20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if os.path.exists(path) and 'up' in open(path).read():
            return
        time.sleep(0.02)
    raise AssertionError(f'{path}: the child did not start')


def test_children_stop_by_sigint_then_sigterm_the_last_started_first(tmp_path, capsys):
    kids = Children(dict(os.environ), str(tmp_path))
    polite = kids.start('polite', [sys.executable, '-c', CHILD.format(ignore=False)], grace=10.0)
    stubborn = kids.start('stubborn', [sys.executable, '-c', CHILD.format(ignore=True)],
                          grace=0.3)
    _wait_up(tmp_path / 'polite.log')
    _wait_up(tmp_path / 'stubborn.log')
    codes = kids.close()
    assert list(codes) == ['stubborn', 'polite']
    assert codes == {'stubborn': -signal.SIGTERM, 'polite': -signal.SIGINT}
    assert polite.poll() is not None and stubborn.poll() is not None
    assert 'stubborn did not stop on SIGINT' in capsys.readouterr().out
    assert kids.close() == codes                  # stopping again only reads the status
    assert kids.stop('never started') is None


def test_isolated_env_picks_a_private_domain(monkeypatch):
    # restored after the test: this session's own isolation (test/conftest.py) stays
    for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'RMW_IMPLEMENTATION'):
        if k in os.environ:
            monkeypatch.setenv(k, os.environ[k])
        else:
            monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv('ROS_LOCALHOST_ONLY', '1')
    env = isolated_env()
    assert 1 <= int(env['ROS_DOMAIN_ID']) <= 101
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST' and env['PYTHONUNBUFFERED'] == '1'
    assert 'ROS_LOCALHOST_ONLY' not in env and 'ROS_LOCALHOST_ONLY' not in os.environ
    assert os.environ['ROS_DOMAIN_ID'] == env['ROS_DOMAIN_ID']


def test_console_prefers_the_script_next_to_the_interpreter():
    assert console('no-such-script-here', 'dgp_ros.apps.demo') == \
        [sys.executable, '-m', 'dgp_ros.apps.demo']

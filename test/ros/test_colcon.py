"""
colcon build of the package in a throw-away workspace.

What ``ros2 run dgp_ros estimator`` uses.
"""
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
COLCON = os.path.join(os.path.dirname(sys.executable), 'colcon')
ITEMS = ['package.xml', 'setup.py', 'setup.cfg', 'resource', 'dgp_ros', 'sim_bridge', 'config',
         'launch']


@pytest.mark.ros
@pytest.mark.skipif(not os.path.exists(COLCON), reason='colcon not installed in this env')
def test_colcon_build_installs_runnable_estimator(tmp_path):
    src = tmp_path / 'ws' / 'src' / 'dgp_ros'
    src.mkdir(parents=True)
    for item in ITEMS:
        s = os.path.join(REPO, item)
        if os.path.isdir(s):
            shutil.copytree(s, src / item, ignore=shutil.ignore_patterns('__pycache__'))
        else:
            shutil.copy2(s, src / item)
    ws = tmp_path / 'ws'
    env = dict(os.environ)
    env['PATH'] = os.path.dirname(sys.executable) + os.pathsep + env.get('PATH', '')
    p = subprocess.run([COLCON, 'build', '--event-handlers', 'console_direct-'], cwd=ws, env=env,
                       capture_output=True, text=True, timeout=240)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    exe = ws / 'install' / 'dgp_ros' / 'lib' / 'dgp_ros' / 'estimator'
    assert exe.exists()
    assert (ws / 'install' / 'dgp_ros' / 'share' / 'ament_index' / 'resource_index' / 'packages'
            / 'dgp_ros').exists()
    assert (ws / 'install' / 'dgp_ros' / 'share' / 'dgp_ros' / 'config'
            / 'estimator.yaml').exists()
    # the executable starts from the install space (its own copy of dgp_ros first on the path)
    site = next((ws / 'install' / 'dgp_ros' / 'lib').glob('python3*/site-packages'))
    env['PYTHONPATH'] = str(site) + os.pathsep + env.get('PYTHONPATH', '')
    proc = subprocess.Popen([str(exe), '--ros-args', '-p', 'min_samples:=5'], env=env,
                            cwd=str(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    end = time.monotonic() + 60
    out = ''
    try:
        import selectors
        sel = selectors.DefaultSelector()
        sel.register(proc.stdout, selectors.EVENT_READ)
        while time.monotonic() < end and 'dgp_estimator: model=' not in out:
            if proc.poll() is not None:
                break
            if sel.select(timeout=0.5):
                out += proc.stdout.readline()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rest, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            rest, _ = proc.communicate()
    out += rest
    assert 'dgp_estimator: model=' in out, out
    assert proc.returncode == 0, out
    assert str(site) in subprocess.run(
        [sys.executable, '-c', 'import dgp_ros, os; print(os.path.dirname(dgp_ros.__file__))'],
        env=env, capture_output=True, text=True, cwd=str(tmp_path)).stdout

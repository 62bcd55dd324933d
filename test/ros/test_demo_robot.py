"""
The robot demo end to end over real DDS (``dgp-demo --robot panda --quick``), and its parts.

The quick run streams 6 s of a simulated Panda at 1 kHz into the estimator console script,
stops it with SIGINT and scores the saved model on the held-out 4 s.
"""
import json
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _gone(pid: int) -> bool:
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().split()[2] == 'Z'
    except OSError:
        return True


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(400)
def test_robot_demo_quick_writes_the_held_out_numbers(tmp_path):
    out = tmp_path / 'demo_panda'
    p = subprocess.run([sys.executable, '-m', 'dgp_ros.apps.demo', '--robot', 'panda', '--quick',
                        '--out', str(out), '--timeout', '300'], cwd=REPO, capture_output=True,
                       text=True, timeout=380)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-3000:]
    assert 'dgp_ros robot demo: panda' in p.stdout and 'held-out NMSE' in p.stdout
    s = json.loads((out / 'summary.json').read_text())
    joints = [f'panda_joint{i}' for i in range(1, 8)]
    for key in ('nmse', 'nmse_sigmoid', 'nmse_coulomb_viscous', 'friction_rms'):
        assert sorted(s[key]) == joints, key
        assert all(math.isfinite(v) and v >= 0 for v in s[key].values()), (key, s[key])
    assert abs(s['published'] - 6000) <= 1        # stamps before 6 s, jittered
    assert 0.2 < s['answered_fraction'] <= 1.0
    assert s['paired'] > 0 and 0 < s['latency_ms']['median'] <= s['latency_ms']['p99']
    # passive: no answer and no prediction below zero beyond rounding (-1e-12 |qd| |tau|; the
    # strict counts are in the summary too)
    assert s['answers_negative_power_beyond_roundoff'] == 0
    assert s['random_velocities'] == 100_000
    assert s['random_negative_power_beyond_roundoff'] == 0
    for f in ('friction_vs_time.png', 'friction_velocity.png', 'dissipated_power_histogram.png',
              'latency_histogram.png', 'friction_curves.png', 'friction.npz', 'answers.npz'):
        assert (out / f).stat().st_size > 0, f
    # both children have exited
    for name in ('estimator', 'arm_sim'):
        pid = int(re.search(rf'started {name} \(pid (\d+)\)', p.stdout).group(1))
        assert _gone(pid), name


def test_driver_stream_layout_and_timing():
    pytest.importorskip('pinocchio')
    from dgp_ros.dynamics.arm_stream import demo_arm, driver_order, DriverStream
    d = demo_arm('ur5', 2.0, seed=1)
    s = DriverStream(d, until_s=1.2)
    assert s.names == driver_order('ur5') and s.names[-1] == 'shoulder_pan_joint'
    assert len(s) == 1200 and s.stamps[-1] < 1.2
    j = list(d['names']).index('elbow_joint')
    np.testing.assert_array_equal(s.effort[:, s.names.index('elbow_joint')], d['effort'][:1200, j])
    assert len(s.due(0.0)) == 1                       # the first stamp is due at once
    assert s.due(0.5).stop == int(np.searchsorted(s.stamps, s.stamps[0] + 0.5, 'right'))
    assert len(s.due(0.5)) == 0 and not s.finished    # nothing twice
    assert s.due(10.0).stop == 1200 and s.finished
    p = DriverStream(demo_arm('panda', 2.0), until_s=None)
    assert p.names[-2:] == ['panda_finger_joint1', 'panda_finger_joint2'] and len(p) == 2000
    assert (p.velocity[:, -2:] == 0).all()
    assert len(p.due(0.0, real_time_factor=0)) == 2000


def test_robot_demo_arguments():
    from dgp_ros.apps.robot_demo import estimator_command, parse_args
    a = parse_args(['--robot', 'ur5', '--quick'])
    assert a.duration == 10.0 and a.out == os.path.join('out', 'demo_ur5')
    cmd = ' '.join(estimator_command('ur5', '/x.urdf', ['a', 'b'], '/m.npz'))
    assert 'inverse_dynamics:=urdf' in cmd and 'urdf_file:=/x.urdf' in cmd
    assert 'joints:=["a", "b"]' in cmd and 'model_path:=/m.npz' in cmd
    # the user's defaults: no prior, bias or passivity given
    assert not any(x in cmd for x in ('prior:=', 'bias:=', 'passivity:='))
    with pytest.raises(SystemExit):
        parse_args(['--robot', 'kuka'])


def test_readme_runs_the_robot_demo_with_one_command_and_keeps_two_setup_commands():
    from dgp_ros.apps.robot_demo import parse_args
    text = open(os.path.join(REPO, 'README.md')).read()
    two = text.split('## Two commands', 1)[1].split('```bash', 1)[1].split('```', 1)[0]
    assert [ln.split('#')[0].strip() for ln in two.strip().splitlines()] == [
        'bash scripts/run_demo.sh', 'bash scripts/run_tests.sh']
    robot = re.search(r'^bash scripts/run_demo\.sh (--robot \S+)', text, re.M)
    assert robot, 'no robot demo command in the README'
    assert parse_args(robot.group(1).split()).robot == 'panda'
    assert 'exec .venv/bin/python -m dgp_ros.apps.demo "$@"' in open(
        os.path.join(REPO, 'scripts', 'run_demo.sh')).read()       # arguments pass through

"""
One closed-loop run through real DDS: ``dgp-arm-loop``, ``estimator``, ``dgp-controller``.

Three OS processes (``apps.children``: a random ROS_DOMAIN_ID, localhost-only discovery, logs in
``out``), all with ``use_sim_time`` on the arm's ``/clock``, in lock-step (``nodes.arm_loop``,
``nodes.controller``); this process listens to ``/joint_states`` (stamps, positions) and scores
the tracking against the same reference path. ``kill_at_s``: the estimator is SIGKILLed once the
arm's time passes it. Used by ``dgp-demo --robot R --closed-loop`` (the dgp run over DDS) and by
the tests; the four-way sweep runs in one process (``apps.loop_run``), see docs/BENCHMARKS.md.
"""
from __future__ import annotations

import json
import os
import time
from typing import Optional

import numpy as np

from dgp_ros.apps.children import Children, console, listener
from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf
from dgp_ros.dynamics.closed_loop import reference_path

__all__ = ['run_dds']


def _commands(robot: str, compensation: str, duration_s: float, seed: int, out: str,
              timeout_s: float, refit_mode: str, wait_s: float) -> dict:
    sim = ['-p', 'use_sim_time:=true']
    est = console('estimator', 'dgp_ros.nodes.estimator') + [
        '--ros-args', '-r', 'generalized_state:=/joint_states', *sim,
        '-p', 'inverse_dynamics:=urdf', '-p', f'urdf_file:={example_robot_urdf(robot)}',
        '-p', f'joints:={json.dumps(list(ARM_JOINTS[robot]))}', '-p', f'refit_mode:={refit_mode}']
    arm = console('dgp-arm-loop', 'dgp_ros.nodes.arm_loop') + [
        '--ros-args', '-p', f'robot:={robot}', '-p', f'duration_s:={float(duration_s)}',
        '-p', f'seed:={int(seed)}', '-p', f'min_subscribers:={3 if compensation != "none" else 2}',
        '-p', f'step_timeout_s:={float(wait_s) + 5.0}']
    ctl = console('dgp-controller', 'dgp_ros.nodes.controller') + [
        '--ros-args', *sim, '-p', f'robot:={robot}', '-p', f'compensation:={compensation}',
        '-p', f'seed:={int(seed)}', '-p', f'timeout_s:={float(timeout_s)}',
        '-p', f'wait_for_answer_s:={float(wait_s)}',
        '-p', f'summary_path:={os.path.join(out, "controller.json")}']
    return {'estimator': est, 'arm_loop': arm, 'controller': ctl}


def run_dds(robot: str, compensation: str, duration_s: float, out: str, env: dict,
            seed: int = 0, timeout_s: float = 0.05, kill_at_s: Optional[float] = None,
            wall_limit_s: float = 300.0, refit_mode: str = 'process',
            wait_for_answer_s: float = 0.05) -> dict:
    """
    Run the three nodes until the arm's ``duration_s`` is done; return what was measured.

    Returns a dict: ``t`` (k,) the states' stamps [s], ``error`` (k, N) ``q_ref - q`` [rad],
    ``controller`` (its counts, ``nodes.controller``), ``exit`` (each child's exit status;
    the controller and the arm must exit 0), ``killed_at_s`` (the arm's time at the SIGKILL),
    ``wall_s``. ``env``: ``children.isolated_env()`` (called before this process's context).
    ``refit_mode``: the estimator's (``process``, its default: the learner beside the message
    path, asynchronous; ``sync``: in line, the run then equals ``loop_run``'s step for step when
    the controller waits for every answer, ``wait_for_answer_s`` longer than a refit).
    """
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState
    os.makedirs(out, exist_ok=True)
    names = ARM_JOINTS[robot]
    ref = reference_path(robot, seed=seed)
    rows = []
    t0 = time.monotonic()
    killed = None
    cmds = _commands(robot, compensation, duration_s, seed, out, timeout_s, refit_mode,
                     wait_for_answer_s)
    with listener('dgp_loop_listener') as (node, ex), Children(env, out) as kids:
        node.create_subscription(
            JointState, '/joint_states',
            lambda m: rows.append((m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
                                   [m.position[m.name.index(n)] for n in names])),
            QoSProfile(depth=1000))
        procs = {}
        if compensation != 'none':
            procs['estimator'] = kids.start('estimator', cmds['estimator'], grace=10.0)
        procs['controller'] = kids.start('controller', cmds['controller'], grace=10.0)
        procs['arm_loop'] = kids.start('arm_loop', cmds['arm_loop'], grace=5.0)
        while procs['arm_loop'].poll() is None:
            ex.spin_once(timeout_sec=0.05)
            if time.monotonic() - t0 > wall_limit_s:
                raise RuntimeError(f'closed loop over DDS: no end after {wall_limit_s:.0f} s')
            if kill_at_s is not None and killed is None and rows and rows[-1][0] >= kill_at_s:
                procs['estimator'].kill()
                killed = rows[-1][0]
            if procs['controller'].poll() is not None:
                raise RuntimeError('the controller exited; see controller.log')
        for _ in range(20):
            ex.spin_once(timeout_sec=0.01)
        codes = kids.close()
    if codes.get('arm_loop') != 0:
        raise RuntimeError(f'dgp-arm-loop exited with {codes.get("arm_loop")}; see arm_loop.log')
    with open(os.path.join(out, 'controller.json')) as f:
        counts = json.load(f)
    t = np.array([r[0] for r in rows])
    q = np.array([r[1] for r in rows]).reshape(-1, len(names))
    return {'t': t, 'error': ref(t)[0] - q if len(t) else q, 'controller': counts,
            'exit': codes, 'killed_at_s': killed, 'wall_s': time.monotonic() - t0}

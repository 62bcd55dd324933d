"""
Robot demo: ``dgp-demo --robot panda`` (or ``ur5``), a robot user's first hour, simulated.

Three OS processes over real DDS (a random ROS_DOMAIN_ID, localhost-only discovery):

1. ``arm_sim`` (``dgp_ros.nodes.arm_sim``): a Panda or UR5 with realistic friction (outside the
   estimator's prior family), a payload its URDF does not have, sensor bias and noise and
   jittered 1 kHz stamps publishes raw ``/joint_states`` like its driver (the Panda's finger
   joints too), at real time, for the first 60 % of the run;
2. the ``estimator`` console script with ``inverse_dynamics=urdf``, the example-robot-data URDF
   (without the payload), ``joints`` and ``model_path``; every other parameter is its default;
3. this process: a listener that receives the measurements and the answers (raw, stamps read from
   the bytes) and notes when each arrives.

When the stream ends the estimator gets SIGINT and saves its model; the saved model is evaluated
on the held-out last 40 % of the run (a part of the path the arm has not travelled) against the
true friction, next to the Makkar sigmoid and Coulomb-viscous models fitted by least squares on
the residual stream of the same 60 %. Summary, ``summary.json`` and plots go to ``--out``
(``dgp_ros.apps.robot_report``). Children are always stopped on exit (SIGINT, SIGTERM, SIGKILL).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import struct
import sys
import time

from dgp_ros.apps.children import Children, console, isolated_env, listener

LEARN_FRACTION = 0.6


def _stamp_ns(raw: bytes) -> int:
    """header.stamp of a CDR-encoded stamped message [ns] (after the 4-byte encapsulation)."""
    sec, nsec = struct.unpack_from('<iI', raw, 4)
    return sec * 1_000_000_000 + nsec


def _received_s(info) -> float:
    """When the middleware received a message [s, system clock] (now if it does not say)."""
    ns = info.get('received_timestamp', 0) if isinstance(info, dict) else 0
    return (ns if ns > 0 else time.time_ns()) * 1e-9


class Listener:
    """
    Measurements and answers, raw, with their arrival times.

    An arrival time is the middleware's reception stamp of the message [s] (rmw MessageInfo
    ``received_timestamp``, system clock): the latency it gives does not include this process's
    own delay in taking the messages.
    """

    def __init__(self, node, ns: str = '/dgp_estimator'):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.meas = {}               # stamp [ns] -> arrival [s]
        self.ans = {}                # stamp [ns] -> (arrival [s], raw CDR bytes)
        self.diag = None
        self.n_diag = 0
        self._node, self._ns, self._meas_sub, self._seen = node, ns, None, None
        self._be = QoSProfile(depth=10000, reliability=ReliabilityPolicy.BEST_EFFORT)
        self._JointState = JointState
        node.create_subscription(JointState, ns + '/damping_force', self._on_ans,
                                 QoSProfile(depth=10000), raw=True)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def poll(self) -> bool:
        """
        Subscribe to the measurements once this node has discovered the estimator's answers.

        The player streams once two subscriptions (the estimator's and this one) match; answers
        published before this node has discovered the estimator's publisher are lost (2.5 s
        of them once), so this one subscribes only after that. True once subscribed.
        """
        if self._meas_sub is not None:
            return True
        now = time.monotonic()
        if self._seen is None:
            if self._node.count_publishers(self._ns + '/damping_force') > 0:
                self._seen = now
        elif now - self._seen >= self.MATCH_S:
            self._meas_sub = self._node.create_subscription(
                self._JointState, '/joint_states', self._on_meas, self._be, raw=True)
        return self._meas_sub is not None

    #: discovered is not yet matched: the first 50 answers were lost once without this wait [s]
    MATCH_S = 0.5

    def _on_meas(self, raw, info):
        self.meas[_stamp_ns(raw)] = _received_s(info)

    def _on_ans(self, raw, info):
        self.ans[_stamp_ns(raw)] = (_received_s(info), raw)

    def _on_diag(self, msg):
        for st in msg.status:
            if 'dgp_estimator' in st.name:
                d = {kv.key: kv.value for kv in st.values}
                d['message'] = st.message
                lv = st.level
                d['level'] = int.from_bytes(lv, 'little') if isinstance(lv, bytes) else int(lv)
                self.diag = d
                self.n_diag += 1


class Progress:
    """One progress line: redrawn on a terminal, a new line every 10 % on a pipe."""

    def __init__(self, total_s: float, stream=None):
        self.total = total_s
        self.stream = stream or sys.stdout
        self.tty = hasattr(self.stream, 'isatty') and self.stream.isatty()
        self._decile = -1

    def update(self, t_s: float, text: str, final: bool = False) -> None:
        frac = min(max(t_s / self.total, 0.0), 1.0) if self.total > 0 else 1.0
        bar = '#' * int(round(30 * frac))
        line = f'[demo] [{bar:.<30}] {100 * frac:5.1f}% {t_s:5.1f}/{self.total:.1f} s | {text}'
        if self.tty:
            self.stream.write('\r' + line[:160].ljust(160) + ('\n' if final else ''))
        elif final or int(10 * frac) > self._decile:
            self._decile = int(10 * frac)
            self.stream.write(line + '\n')
        self.stream.flush()


def estimator_command(robot: str, urdf: str, joints, model_path: str) -> list:
    """Return the estimator as a robot user starts it: URDF, joints, model file, else defaults."""
    return console('estimator', 'dgp_ros.nodes.estimator') + [
        '--ros-args', '-r', 'generalized_state:=/joint_states',
        '-p', 'inverse_dynamics:=urdf', '-p', f'urdf_file:={urdf}',
        '-p', f'joints:={json.dumps(list(joints))}', '-p', f'model_path:={model_path}']


def sim_command(a, learn_s: float) -> list:
    return [sys.executable, '-m', 'dgp_ros.nodes.arm_sim', '--ros-args',
            '-p', f'robot:={a.robot}', '-p', f'duration_s:={float(a.duration)}',
            '-p', f'max_sim_time_s:={float(learn_s)}', '-p', f'seed:={int(a.seed)}',
            '-p', f'payload_kg:={float(a.payload_kg)}', '-p', f'friction:={a.friction}',
            '-p', f'cycle_s:={float(a.cycle)}',
            '-p', f'real_time_factor:={float(a.real_time_factor)}',
            '-p', 'min_subscribers:=2', '-p', 'wait_for_subscribers_s:=60.0']


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog='dgp-demo', description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument('--robot', required=True, choices=('panda', 'ur5'),
                    help='simulated arm (example-robot-data URDF)')
    ap.add_argument('--out', default=None, help='output folder (default out/demo_<robot>)')
    ap.add_argument('--duration', type=float, default=60.0,
                    help='the whole run [s]; the first 60 %% is streamed and learned')
    ap.add_argument('--quick', action='store_true', help='a 10 s run (the tests)')
    ap.add_argument('--seed', type=int, default=0, help='trajectory, jitter and noise')
    ap.add_argument('--cycle', type=float, default=10.0,
                    help='the task cycle the arm repeats [s] (0: one path over the whole run '
                    'that never repeats: the held-out part is new to the model)')
    ap.add_argument('--payload-kg', type=float, default=-1.0,
                    help='payload the URDF lacks [kg] (-1: Panda 0.5, UR5 1.0)')
    ap.add_argument('--friction', default='realistic', choices=('realistic', 'table'),
                    help="realistic: outside the prior family; table: the prior's own family")
    ap.add_argument('--real-time-factor', type=float, default=1.0,
                    help='stamp s per wall s of the stream (1 = a real robot)')
    ap.add_argument('--settle', type=float, default=30.0,
                    help='after the stream, wait at most this long [s] for the learner to take '
                    'in the samples the estimator received')
    ap.add_argument('--timeout', type=float, default=600.0, help='wall-clock limit [s]')
    a = ap.parse_args(argv)
    if a.quick:
        a.duration = 10.0
    if a.out is None:
        a.out = os.path.join('out', f'demo_{a.robot}')
    if not a.duration >= 2.0:
        ap.error('--duration must be >= 2 s')
    if a.cycle <= 0:
        a.cycle = a.duration
    if not a.cycle >= 1.0:
        ap.error('--cycle must be >= 1 s (or 0)')
    return a


def main(argv=None) -> int:
    a = parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    t_start = time.monotonic()
    env = isolated_env()
    print(f'[demo] {a.robot}: ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]} (localhost only); output in '
          f'{a.out}', flush=True)
    from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf

    learn_s = LEARN_FRACTION * a.duration
    model_path = os.path.abspath(os.path.join(a.out, 'friction.npz'))
    if os.path.exists(model_path):      # the estimator would load it: start from nothing
        os.remove(model_path)
    joints = ARM_JOINTS[a.robot]
    urdf = example_robot_urdf(a.robot)
    with listener('dgp_demo_listener') as (node, ex):
        return _run(a, env, node, ex, learn_s, model_path, joints, urdf, t_start)


def _run(a, env: dict, node, ex, learn_s: float, model_path: str, joints, urdf: str,
         t_start: float) -> int:
    """Start the estimator and the arm, listen, stop, score the saved model; the exit status."""
    from dgp_ros.apps import robot_report
    from dgp_ros.dynamics.arm_stream import demo_arm, DriverStream
    kids = Children(env, a.out)
    code = 0
    try:
        lis = Listener(node)
        est = kids.start('estimator', estimator_command(a.robot, urdf, joints, model_path),
                         grace=30.0)
        print(f'[demo] started estimator (pid {est.pid}): inverse_dynamics=urdf, '
              f'urdf_file={urdf}, joints={list(joints)}, model_path={model_path}, other '
              'parameters default', flush=True)
        sim = kids.start('arm_sim', sim_command(a, learn_s), grace=10.0)
        print(f'[demo] started arm_sim (pid {sim.pid}): {a.robot}, {a.friction} friction, '
              f'{a.duration:g} s run at 1 kHz; streams the first {learn_s:g} s at real-time '
              f'factor {a.real_time_factor:g} once both subscribers are up', flush=True)
        # the truth, computed while the children start (the same simulation as arm_sim's)
        truth = demo_arm(a.robot, a.duration, seed=a.seed, friction=a.friction,
                         payload_kg=None if a.payload_kg < 0 else a.payload_kg,
                         base_hz=1.0 / a.cycle)
        published = len(DriverStream(truth, learn_s))
        bar = Progress(learn_s)
        last = 0.0
        while sim.poll() is None:
            lis.poll()
            ex.spin_once(timeout_sec=0.05)
            now = time.monotonic()
            if now - t_start > a.timeout:
                raise RuntimeError(f'timeout after {a.timeout:.0f} s')
            if est.poll() is not None:
                raise RuntimeError(f'estimator exited ({est.returncode}); see estimator.log')
            if now - last >= 1.0:
                last = now
                bar.update(max(lis.meas) * 1e-9 if lis.meas else 0.0, _progress_text(lis))
        if sim.returncode != 0:
            raise RuntimeError(f'arm_sim exited with {sim.returncode}; see arm_sim.log')
        bar.update(max(lis.meas) * 1e-9 if lis.meas else 0.0, _progress_text(lis), final=True)
        _settle(ex, lis, a.settle, est)
        t_stop = time.monotonic()
        rc = kids.stop('estimator', grace=60.0)
        print(f'[demo] estimator stopped with SIGINT (exit {rc}) in '
              f'{time.monotonic() - t_stop:.1f} s; model {model_path}', flush=True)
        if rc != 0 or not os.path.exists(model_path):
            raise RuntimeError(f'the estimator did not save its model (exit {rc}); see '
                               'estimator.log')
        print('[demo] evaluating the saved model on the held-out 40 % and fitting the '
              'parametric baselines ...', flush=True)
        res = robot_report.evaluate(truth, learn_s, model_path, lis, published, urdf)
        res['wall_time_s'] = time.monotonic() - t_start
        res['diagnostics'] = lis.diag
        res['args'] = vars(a)
        files = robot_report.plot(res, truth, a.out)
        res['wall_time_s'] = time.monotonic() - t_start
        robot_report.print_summary(res)
        path = os.path.join(a.out, 'summary.json')
        with open(path, 'w') as f:
            json.dump(robot_report.jsonable(res), f, indent=2, default=str)
        robot_report.save_stream(res, os.path.join(a.out, 'answers.npz'))
        print('[demo] wrote ' + ', '.join(files + [path, os.path.join(a.out, 'answers.npz')]),
              flush=True)
    except KeyboardInterrupt:
        print('\n[demo] interrupted', flush=True)
        code = 130
    except RuntimeError as exc:
        print(f'\n[demo] error: {exc}', flush=True)
        code = 1
    finally:
        kids.close()                                # the arm first, then the estimator
    return code


def _settle(ex, lis: Listener, limit_s: float, est) -> None:
    """
    Let the last answers arrive and the learner take in what the estimator received.

    Waits at least 1.5 s, then until a /diagnostics (published after the stream ended) says
    that no sample is pending, no refit is running and the model is trained, at most
    ``limit_s``: on a loaded machine the learner (a child process at lower priority) trails the
    stream.
    """
    t0 = time.monotonic()
    n0 = lis.n_diag
    last = 0.0
    while True:
        ex.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        d = lis.diag or {}
        # samples_pending: sent to the learner process, not yet taken in
        ready = (lis.n_diag > n0 + 1 and d.get('samples_pending', '0') == '0' and
                 d.get('refit_running', 'False') != 'True' and d.get('trained', 'True') == 'True')
        if (now - t0 >= 1.5 and ready) or now - t0 >= limit_s or est.poll() is not None:
            break
        if now - t0 >= 3.0 and now - last >= 5.0:
            last = now
            print(f'[demo] waiting for the learner ({now - t0:.0f} s, at most {limit_s:.0f}): '
                  f'pending samples {d.get("samples_pending", "-")}, refit running '
                  f'{d.get("refit_running", "-")}, trained {d.get("trained", "-")}, buffer '
                  f'{d.get("buffer_fill", "-")}', flush=True)
    if not ready:
        print(f'[demo] the learner had not settled after {limit_s:.0f} s: stopping the estimator '
              'anyway', flush=True)


def _progress_text(lis: Listener) -> str:
    d = lis.diag or {}
    return (f'measurements {len(lis.meas)} | answers {len(lis.ans)} | buffer '
            f'{d.get("buffer_fill", "-")} (pending {d.get("samples_pending", "-")}) | refits '
            f'{d.get("refits_ok", "-")} | '
            f'{d.get("message", "waiting for the estimator")}')


if __name__ == '__main__':
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sys.exit(main())

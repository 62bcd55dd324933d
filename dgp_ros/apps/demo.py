"""
End-to-end demo: ``python -m dgp_ros.apps.demo`` (scripts/run_demo.sh, the README's main job).

Starts ``sim_bridge`` (JSBSim A320 approach in periodic wind) and the ``dgp_estimator`` with the
node's defaults as two OS processes talking over real DDS (random ROS_DOMAIN_ID, localhost-only
discovery), flies the whole approach at real time, records the measurements and the estimator's
answers with a node in this process, then prints a summary table and writes plots and
``summary.json`` and ``answers.npz`` (stamps, velocities, measured forces, answers) into
``--out`` (default ``out/demo``): the NMSE per output of the answers
against the measured force (each message is answered before the estimator learns it: one step
ahead, what a user of the node gets), over the run and its second half; the held-out NMSE of the
model the estimator saved (``~/save_model``) after ``--held-out-after`` s of flight, on the rest
of the flight; negative estimated dissipated power, refits, certification, latency.

``--synthetic`` replaces sim_bridge by an in-process publisher of a known passive damping law
(no JSBSim needed; used by the tests). ``--robot panda|ur5`` runs the robot demo instead: a
simulated arm publishing raw ``/joint_states`` into the estimator (``dgp_ros.apps.robot_demo``).
Children are always terminated on exit (SIGINT, then SIGTERM, then SIGKILL; on Linux they also
die with this process).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from typing import Dict, List

import numpy as np

from dgp_ros.apps.children import Children, isolated_env, listener
from dgp_ros.apps.demo_report import (analyse, certified_share, held_out, OUT_NAMES, plot,
                                      print_summary)
from dgp_ros.gp import KINDS, PASSIVITY_MODES
from dgp_ros.gp.passivity import describe_modes
from dgp_ros.msgs.sample import joint_state_sample


class _Recorder:
    """Subscribes to the measurements and every estimator output; keeps arrival wall times."""

    def __init__(self, node, ns: str = '/dgp_estimator'):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, Float64MultiArray
        self.node = node
        self.meas: Dict[float, tuple] = {}
        self.est: Dict[float, tuple] = {}
        self.std: Dict[float, list] = {}
        self.power: List[float] = []
        self.n_matrix = 0
        self.diag = None
        be = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
        node.create_subscription(JointState, 'generalized_state', self._on_meas, be)
        node.create_subscription(JointState, ns + '/damping_force', self._on_est, 1000)
        node.create_subscription(JointState, ns + '/damping_force_stddev', self._on_std, 1000)
        node.create_subscription(Float64, ns + '/dissipated_power',
                                 lambda m: self.power.append(m.data), 1000)
        node.create_subscription(Float64MultiArray, ns + '/damping_matrix', self._on_D, 1000)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)

    def _on_meas(self, m):
        s = joint_state_sample(m)
        self.meas[s.stamp_s] = (time.perf_counter(), s.names, s.velocity, s.effort)

    def _on_est(self, m):
        s = joint_state_sample(m)
        self.est[s.stamp_s] = (time.perf_counter(), s.velocity, s.effort)

    def _on_std(self, m):
        s = joint_state_sample(m)
        self.std[s.stamp_s] = s.effort.tolist()

    def _on_D(self, m):
        self.n_matrix += 1

    def _on_diag(self, m):
        for st in m.status:
            if 'dgp_estimator' in st.name:
                self.diag = dict(level=int.from_bytes(st.level, 'little') if isinstance(
                    st.level, bytes) else int(st.level), message=st.message,
                    **{kv.key: kv.value for kv in st.values})


def _synthetic_publisher(node, rate_hz: float, duration_s: float, rtf: float):
    """In-process stand-in for sim_bridge: a passive nonlinear D(qd) on an approach-like path."""
    from sensor_msgs.msg import JointState
    pub = node.create_publisher(JointState, 'generalized_state', 10)
    rng = np.random.default_rng(0)
    state = {'i': 0, 'done': False}

    def tick():
        i = state['i']
        t = i / rate_hz
        if t > duration_s:
            state['done'] = True
            return
        q = np.array([0.08 + 0.05 * np.sin(2 * np.pi * 0.3 * t),
                      0.1 * np.sin(2 * np.pi * 0.2 * t + 2.0),
                      92.0 + 5.0 * np.sin(2 * np.pi * 0.1 * t)])
        D = np.diag([6.0e5 * (1 + 2 * q[0]), 3.0e5 * (1 + q[1] ** 2), 8.0e3])
        D[2, 0] = 4.0e4
        D[0, 2] = 4.0e4
        tau = D @ q + rng.normal(0, 50.0, 3)
        m = JointState()
        m.header.stamp.sec = int(t)
        m.header.stamp.nanosec = int(round((t - int(t)) * 1e9)) % 1_000_000_000
        m.name = list(OUT_NAMES)
        m.velocity = q.tolist()
        m.effort = tau.tolist()
        pub.publish(m)
        state['i'] += 1

    period = 1.0 / (rate_hz * rtf) if rtf > 0 else 0.001
    node.create_timer(period, tick)
    return state


class _FirstPart:
    """
    Asks the estimator to save its model once the flight reaches ``--held-out-after``.

    A save that fails (no model trained yet: a slow or loaded machine) is asked again every
    ``RETRY_S`` of wall time; the split is where the save succeeded, and the summary says so.
    """

    RETRY_S = 0.5

    def __init__(self, node, args):
        from std_srvs.srv import Trigger
        self.args, self.req = args, Trigger.Request()
        self.client = node.create_client(Trigger, '/dgp_estimator/save_model')
        self.future, self.split_s = None, None
        self.retry_at, self.told = 0.0, False

    def poll(self, t_sim: float) -> None:
        """Call ``~/save_model`` at ``--held-out-after`` s; keep the file it wrote."""
        if self.future is None and self.split_s is None and \
                t_sim >= self.args.held_out_after and time.monotonic() >= self.retry_at and \
                self.client.service_is_ready():
            self.future = self.client.call_async(self.req)
        elif self.future is not None and self.split_s is None and self.future.done():
            r, self.future = self.future.result(), None
            if r is not None and r.success:
                import shutil
                shutil.copyfile(self.args.model_path, self.args.first_part)
                self.split_s = t_sim    # the saved model learned nothing stamped after this
                print(f'[demo] the model of the first {t_sim:.1f} s saved for the held-out '
                      'score', flush=True)
                return
            if not self.told:
                print(f'[demo] ~/save_model failed at {t_sim:.1f} s: '
                      f'{getattr(r, "message", "no answer")}; asking again every '
                      f'{self.RETRY_S:g} s', flush=True)
                self.told = True
            self.retry_at = time.monotonic() + self.RETRY_S


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if '--closed-loop' in argv:
        from dgp_ros.apps import loop_demo
        return loop_demo.main(argv)
    if any(x == '--robot' or x.startswith('--robot=') for x in argv):
        from dgp_ros.apps import robot_demo
        return robot_demo.main(argv)
    ap = argparse.ArgumentParser(prog='dgp-demo', description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                 epilog='The robot demo: dgp-demo --robot panda|ur5 [--quick] '
                                 '[--seed N] [--closed-loop] (its options: dgp-demo --robot '
                                 'panda --help; the closed loop: dgp-demo --robot panda '
                                 '--closed-loop --help).')
    ap.add_argument('--robot', choices=('panda', 'ur5'),
                    help='run the robot demo instead (a simulated arm publishing raw '
                    '/joint_states, see dgp_ros/apps/robot_demo.py)')
    ap.add_argument('--out', default='out/demo', help='output folder (plots, summary.json, logs)')
    ap.add_argument('--rate-hz', type=float, default=60.0, help='simulation output rate')
    ap.add_argument('--real-time-factor', type=float, default=1.0,
                    help='simulated s per wall s (0 = as fast as possible; faster than real time '
                    'the learner falls further behind the answers)')
    ap.add_argument('--max-sim-time', type=float, default=0.0,
                    help='stop the approach after this many simulated s (0 = to touch-down)')
    ap.add_argument('--model', choices=KINDS, help="default: the node's")
    ap.add_argument('--passivity', choices=PASSIVITY_MODES,
                    help=describe_modes() + "; default: the node's")
    ap.add_argument('--buffer-size', type=int, help="default: the node's")
    ap.add_argument('--refit-period', type=float,
                    help="simulated s between refits; default: the node's")
    ap.add_argument('--held-out-after', type=float, default=30.0,
                    help='s of flight after which the estimator saves its model '
                    '(~/save_model), scored on the rest of the flight')
    ap.add_argument('--synthetic', action='store_true',
                    help='in-process synthetic publisher instead of sim_bridge (no JSBSim)')
    ap.add_argument('--duration', type=float, default=30.0, help='--synthetic: simulated s')
    ap.add_argument('--timeout', type=float, default=900.0, help='wall-clock limit (s)')
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)

    env = isolated_env()
    print(f'[demo] ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]} (localhost only); output in {args.out}',
          flush=True)

    # the node's defaults, unless an option says otherwise: what a user gets
    args.model_path = os.path.abspath(os.path.join(args.out, 'model.npz'))
    args.first_part = os.path.join(args.out, 'model_first_part.npz')
    for f in (args.model_path, args.first_part):
        if os.path.exists(f):
            os.remove(f)                        # a file of an earlier run must not be loaded
    est_cmd = [sys.executable, '-m', 'dgp_ros.nodes.estimator', '--ros-args',
               '-p', 'diagnostics_period_s:=0.5', '-p', f'model_path:={args.model_path}']
    for name, value in (('model', args.model), ('passivity', args.passivity),
                        ('buffer_size', args.buffer_size),
                        ('refit_period_s', None if args.refit_period is None
                         else float(args.refit_period))):
        if value is not None:
            est_cmd += ['-p', f'{name}:={value}']
    sim_cmd = [sys.executable, '-m', 'sim_bridge.node', '--ros-args',
               '-p', f'rate_hz:={float(args.rate_hz)}',
               '-p', f'real_time_factor:={float(args.real_time_factor)}',
               '-p', 'loop:=false', '-p', f'max_sim_time_s:={float(args.max_sim_time)}',
               # the estimator and this recorder: every measurement of the flight is scored
               '-p', 'min_subscribers:=2']
    t_start = time.monotonic()
    with listener('dgp_demo_recorder') as (node, ex):
        return _run(args, env, node, ex, est_cmd, sim_cmd, t_start)


def _run(args, env: dict, node, ex, est_cmd: List[str], sim_cmd: List[str],
         t_start: float) -> int:
    """Start the estimator and the simulator, listen to the run, report; the exit status."""
    kids = Children(env, args.out)
    sim_proc = None
    code = 0
    try:
        rec = _Recorder(node)
        est_proc = kids.start('estimator', est_cmd, grace=30.0)
        given = ' '.join(a for a in est_cmd[est_cmd.index('--ros-args') + 1:] if a != '-p')
        print(f"[demo] started estimator (pid {est_proc.pid}) with the node's defaults but "
              f'{given}', flush=True)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and \
                node.count_publishers('/dgp_estimator/damping_force') < 1:
            ex.spin_once(timeout_sec=0.1)
            if est_proc.poll() is not None:
                raise RuntimeError(f'estimator exited with {est_proc.returncode}; see '
                                   f'{args.out}/estimator.log')
        if node.count_publishers('/dgp_estimator/damping_force') < 1:
            raise RuntimeError('estimator did not come up within 60 s')
        if args.synthetic:
            syn = _synthetic_publisher(node, args.rate_hz, args.duration, args.real_time_factor)
            finished = lambda: syn['done']  # noqa: E731
            print(f'[demo] synthetic publisher: {args.duration:.0f} s at {args.rate_hz:g} Hz',
                  flush=True)
        else:
            sim_proc = kids.start('sim_bridge', sim_cmd, grace=10.0)
            finished = lambda: sim_proc.poll() is not None  # noqa: E731
            print(f'[demo] started sim_bridge (pid {sim_proc.pid}): A320 approach at '
                  f'{args.rate_hz:g} Hz, real-time factor {args.real_time_factor:g}', flush=True)
        last_print = 0.0
        saver = _FirstPart(node, args)
        while not finished():
            ex.spin_once(timeout_sec=0.05)
            saver.poll(max(rec.meas) if rec.meas else 0.0)
            now = time.monotonic()
            if now - t_start > args.timeout:
                raise RuntimeError(f'timeout after {args.timeout:.0f} s')
            if est_proc.poll() is not None:
                raise RuntimeError(f'estimator died ({est_proc.returncode}); see estimator.log')
            if now - last_print >= 2.0:
                last_print = now
                ts = max(rec.meas) if rec.meas else 0.0
                d = rec.diag or {}
                print(f'[demo] t_sim {ts:6.1f} s | measurements {len(rec.meas):5d} | answers '
                      f'{len(rec.est):5d} | buffer {d.get("buffer_fill", "-")} | refits '
                      f'{d.get("refits_ok", "-")} | {d.get("message", "waiting for diagnostics")}',
                      flush=True)
        if sim_proc is not None and sim_proc.returncode not in (0, None):
            print(f'[demo] sim_bridge exited with {sim_proc.returncode}; see sim_bridge.log',
                  flush=True)
            code = 1
        # let the last answers and a final /diagnostics arrive
        end = time.monotonic() + 2.0
        n_diag_before = id(rec.diag)
        while time.monotonic() < end or (id(rec.diag) == n_diag_before and
                                         time.monotonic() < end + 3.0):
            ex.spin_once(timeout_sec=0.05)
        wall = time.monotonic() - t_start
        res = analyse(rec)
        if saver.split_s is not None:
            res['held_out'] = held_out(args.first_part, saver.split_s, res)
        print_summary(res, rec.diag, wall)
        if res.get('paired', 0) == 0:
            print('[demo] no estimates were received', flush=True)
            code = 1
        else:
            files = plot(res, args.out)
            summary = {k: v for k, v in res.items() if not isinstance(v, np.ndarray)}
            summary['diagnostics'] = rec.diag
            summary['certified_share'] = certified_share(rec.diag)
            summary['wall_time_s'] = wall
            summary['args'] = vars(args)
            with open(os.path.join(args.out, 'summary.json'), 'w') as f:
                json.dump(summary, f, indent=2, default=str)
            arrays = os.path.join(args.out, 'answers.npz')
            np.savez(arrays, **{k: res[k] for k in ('t', 'qd', 'tau', 'tau_hat')},
                     names=np.array(res['names']))
            print('[demo] wrote ' + ', '.join(
                files + [os.path.join(args.out, 'summary.json'), arrays]), flush=True)
    except KeyboardInterrupt:
        print('[demo] interrupted', flush=True)
        code = 130
    except RuntimeError as exc:
        print(f'[demo] error: {exc}', flush=True)
        code = 1
    finally:
        rc = kids.close().get('estimator')          # the simulator first
        if rc not in (0, None, -signal.SIGINT):
            print(f'[demo] estimator exit status {rc}', flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""
A 7-joint arm at 1 kHz, live: dgp-play -> estimator node -> a listener, over real DDS.

A simulated Panda (``dgp_ros.dynamics.simulate_arm``: raw torques with gravity and inertia, 1 kHz
jittered stamps, a finger joint in the messages like a real /joint_states) is written as a bag of
its first 60 %. ``dgp-play`` publishes it at real time into the ``estimator`` console script
(``inverse_dynamics=urdf``, ``model_path`` set), while a listener in this process receives both
the measurements and the answers (raw CDR, stamps read from the bytes) and pairs them by stamp.
Then the estimator gets SIGINT, saves its model, and the model predicts the last 40 % of the
trajectory (held out) against the true friction; the same for a sigmoid friction model fitted by
least squares on the same residual (``robot_arms.fit_sigmoid``, Makkar et al.).

Writes the section ``arm_live`` of ``DIR/BENCHMARKS.md``: answered fraction, end-to-end latency
(listener: measurement received -> answer received) median/p99, the estimator's own counters
(messages received, queue drops estimated from stamp gaps, stamp-to-answer latency), held-out NMSE
per joint against the sigmoid model's, and the targets.
"""
from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common as C  # noqa: E402

from dgp_ros.bags import write_joint_state_bag  # noqa: E402
from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, simulate_arm  # noqa: E402
from dgp_ros.online.config import PARAMS  # noqa: E402

SECTION = 'arm_live'
FINGER = 'panda_finger_joint1'


def _extra(p):
    p.add_argument('--duration', type=float, default=20.0, help='simulated seconds (60 %% played)')
    p.add_argument('--model', default=None, help='estimator model (default: its default)')
    p.add_argument('--prior', default=None, help='estimator prior (default: its default)')
    p.add_argument('--queue-depth', type=int, default=None)


def _stamp(raw: bytes) -> int:
    """header.stamp of a CDR-encoded stamped message, in ns (after the 4-byte encapsulation)."""
    sec, nsec = struct.unpack_from('<iI', raw, 4)
    return sec * 1_000_000_000 + nsec


class Listener:
    """Receives measurements and answers raw, notes the arrival times (perf_counter)."""

    def __init__(self, ctx):
        import rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.node = rclpy.create_node('arm_live_listener', context=ctx)
        self.meas, self.ans, self.diag = {}, {}, None
        be = QoSProfile(depth=10000, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.node.create_subscription(JointState, '/joint_states', self._m, be, raw=True)
        self.node.create_subscription(JointState, '/dgp_estimator/damping_force', self._a,
                                      QoSProfile(depth=10000), raw=True)
        from diagnostic_msgs.msg import DiagnosticArray
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._d, 10)

    def _m(self, raw):
        self.meas[_stamp(raw)] = time.perf_counter()

    def _a(self, raw):
        self.ans[_stamp(raw)] = time.perf_counter()

    def _d(self, msg):
        for st in msg.status:
            if 'dgp_estimator' in st.name:
                self.diag = {kv.key: kv.value for kv in st.values}
                self.diag['message'] = st.message


def run(a, work: str) -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    robot, names = 'panda', list(ARM_JOINTS['panda'])
    d = simulate_arm(robot, a.duration, seed=7)
    k = len(d['t'])
    cut = int(0.6 * k)
    bag = os.path.join(work, 'panda_60')
    write_joint_state_bag(bag, [(t, names + [FINGER], np.r_[q, 0.02], np.r_[v, 0.0], np.r_[e, 0.1])
                                for t, q, v, e in zip(d['t'][:cut], d['q'][:cut], d['qd'][:cut],
                                                      d['effort'][:cut])], topic='/joint_states')
    model_path = os.path.join(work, 'arm.npz')
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    bindir = os.path.dirname(sys.executable)
    params = ['-p', 'inverse_dynamics:=urdf', '-p', f'urdf_file:={example_robot_urdf(robot)}',
              '-p', f'joints:={json.dumps(names)}', '-p', f'model_path:={model_path}',
              '-p', 'diagnostics_period_s:=0.5']
    for name in ('model', 'prior'):
        if getattr(a, name):
            params += ['-p', f'{name}:={getattr(a, name)}']
    if a.queue_depth:
        params += ['-p', f'queue_depth:={a.queue_depth}']
    est_log = open(os.path.join(work, 'estimator.log'), 'w')
    est = subprocess.Popen([os.path.join(bindir, 'estimator'), '--ros-args', '-r',
                            'generalized_state:=/joint_states'] + params, env=env,
                           stdout=est_log, stderr=subprocess.STDOUT, start_new_session=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    lis = Listener(ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(lis.node)
    stop = threading.Event()

    def spin_until_stopped():
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.05)
    spin = threading.Thread(target=spin_until_stopped)
    spin.start()
    t_play = None
    try:
        deadline = time.monotonic() + 60
        while lis.node.count_publishers('/dgp_estimator/damping_force') < 1:
            if time.monotonic() > deadline or est.poll() is not None:
                raise RuntimeError('estimator did not come up (see estimator.log)')
            time.sleep(0.1)
        C.log(f'arm_live: playing {cut} messages at 1 kHz into the estimator')
        t_play = time.monotonic()
        play = subprocess.run([os.path.join(bindir, 'dgp-play'), bag, '--quiet',
                               '--wait-for-subscribers', '20', '--min-subscribers', '2'],
                              env=env, capture_output=True, text=True, timeout=a.duration * 5 + 60)
        t_play = time.monotonic() - t_play
        if play.returncode != 0:
            raise RuntimeError(f'dgp-play failed: {play.stderr[-500:]}')
        time.sleep(1.5)                     # the last answers and a diagnostics message
        diag = dict(lis.diag or {})
    finally:
        est.send_signal(signal.SIGINT)
        try:
            rc = est.wait(60)
        except subprocess.TimeoutExpired:
            est.kill()
            rc = est.wait()
        stop.set()
        spin.join()
        ex.shutdown()
        lis.node.destroy_node()
        ctx.try_shutdown()
    meas, ans = lis.meas, lis.ans
    paired = sorted(set(meas) & set(ans))
    lat = np.array([ans[s] - meas[s] for s in paired]) * 1e3
    from dgp_ros.gp import load_model
    import robot_arms
    model = load_model(model_path)
    te = np.arange(cut, k, 10)
    Qt, truth = d['qd_true'][te], d['friction'][te]
    nmse = np.mean((model.predict(Qt) - truth) ** 2, axis=0) / np.var(truth, axis=0)
    # the sigmoid model on the residual the estimator's front end produced (same samples)
    from dgp_ros.online import EstimatorConfig
    Qr, R = robot_arms.residual_stream({'sim': d, 'k': cut, 'names': names},
                                       example_robot_urdf(robot), EstimatorConfig())
    sig = np.empty_like(truth)
    for j in range(len(names)):
        cv = robot_arms.fit_cv(Qr[:, j], R[:, j])
        sig[:, j] = robot_arms.fit_sigmoid(Qr[:, j], R[:, j], cv)['f'](Qt[:, j])
    nmse_sig = np.mean((sig - truth) ** 2, axis=0) / np.var(truth, axis=0)
    X = np.random.default_rng(0).uniform(-3, 3, (100_000, len(names)))
    neg = int(np.sum(np.einsum('ij,ij->i', X, model.predict(X)) < 0))
    return {'published': cut, 'received': len(meas), 'answers': len(ans), 'paired': len(paired),
            'answered': len(paired) / cut,
            'lat_median': float(np.median(lat)) if len(lat) else None,
            'lat_p99': float(np.percentile(lat, 99)) if len(lat) else None,
            'play_s': t_play, 'est_rc': rc, 'diag': diag, 'nmse': nmse.tolist(),
            'nmse_sigmoid': nmse_sig.tolist(), 'negative_power': neg, 'names': names,
            'model': a.model or PARAMS['model'].default,
            'prior': a.prior or PARAMS['prior'].default,
            'friction_rms': np.sqrt(np.mean(truth ** 2, axis=0)).tolist()}


def robot_arms_noise() -> float:
    import robot_arms
    return robot_arms.NOISE_SD


def section(a, r: dict, wall: float) -> str:
    d = r['diag']
    lines = [C.header_lines('A 7-joint arm at 1 kHz, live (dgp-play -> estimator node)',
                            'bench/arm_live.py', a.quick, wall), '',
             f'Simulated Panda, {r["published"]} raw /joint_states messages (60 % of '
             f'{a.duration:g} s at 1 kHz, jittered stamps, a finger joint too) played at real '
             f'time by `dgp-play` into `estimator` (`model={r["model"]}`, `prior={r["prior"]}`, '
             f'`inverse_dynamics=urdf`, other parameters default), all on this '
             f'2-core machine with the listener. Latency: listener receives the measurement -> '
             f'listener receives the answer. Held out: the saved model on the last 40 % of the '
             f'trajectory at the true velocities against the true friction; sigmoid: '
             f'Makkar et al. per joint by least squares on the residual the estimator learned '
             f'from.',
             '']
    rows = [['answered (of published)', f'{100 * r["answered"]:.2f} %'],
            ['received by the listener', f'{r["received"]} of {r["published"]}'],
            ['end-to-end latency median / p99',
             f'{C.fmt(r["lat_median"])} / {C.fmt(r["lat_p99"])} ms'],
            ['estimator: messages received', d.get('messages_received', '-')],
            ['estimator: messages missing (from stamp gaps)', d.get('messages_missing', '-')],
            ['estimator: stamp -> answer median / p99 (s)',
             f'{d.get("stamp_to_answer_median_s", "-")} / {d.get("stamp_to_answer_p99_s", "-")}'],
            ['estimator: samples learned / refits ok / rejected',
             f'{d.get("samples_added", "-")} / {d.get("refits_ok", "-")} / '
             f'{d.get("refits_rejected", "-")}'],
            ['estimator: status at the end', d.get('message', '-')],
            ['estimator exit status after SIGINT (model saved)', r['est_rc']],
            ['negative power in 10^5 random velocities', r['negative_power']]]
    lines += [C.md_table(['quantity', 'value'], rows), '']
    lines.append(C.md_table(['joint', 'held-out NMSE (live model)', 'sigmoid model', 'ratio'],
                            [[j, C.fmt(x), C.fmt(y), C.fmt(x / y)] for j, x, y in
                             zip(r['names'], r['nmse'], r['nmse_sigmoid'])]))
    tgt = [['>= 99 % of messages answered', 'met' if r['answered'] >= 0.99 else '**missed**',
            f'{100 * r["answered"]:.2f} %'],
           ['end-to-end p99 <= 5 ms', 'met' if (r['lat_p99'] or 1e9) <= 5 else '**missed**',
            f'{C.fmt(r["lat_p99"])} ms'],
           ['held-out NMSE <= 0.5 x sigmoid on every joint whose friction exceeds the noise',
            'met' if all(x <= 0.5 * y for x, y, f in zip(r['nmse'], r['nmse_sigmoid'],
                                                         r['friction_rms'])
                         if f > robot_arms_noise())
            else '**missed**',
            ', '.join(C.fmt(x / y) for x, y in zip(r['nmse'], r['nmse_sigmoid']))]]
    lines += ['', C.md_table(['target', 'status', 'measured'], tgt)]
    return '\n'.join(lines)


def main(argv=None) -> int:
    a = C.parse_args(__doc__.split('\n\n')[0], argv, _extra)
    if a.quick:
        a.duration = min(a.duration, 6.0)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        r = run(a, work)
    wall = time.perf_counter() - t0
    C.write_section(a.out, SECTION, section(a, r, wall))
    C.log(f'arm_live: answered {100 * r["answered"]:.2f} %, p99 {r["lat_p99"]} ms, '
          f'NMSE {np.round(r["nmse"], 4).tolist()} vs sigmoid '
          f'{np.round(r["nmse_sigmoid"], 4).tolist()}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

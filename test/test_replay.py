"""
dgp-replay: offline replay through the same OnlineEstimator as the node.

- live run (publisher -> estimator node, recorded by the Recorder) == offline replay of the bag;
  bag played back (Player) into a fresh node == offline replay; to 1e-9, both storages;
- robot-like bags: /joint_states with extra joints in another order, --joints selects/orders;
- CLI outputs (csv, summary, plots) and clear errors.
"""
import csv
import json
import threading
import time

import numpy as np
import pytest

from dgp_ros.apps.replay import build_config, main as replay_main, replay, run
from dgp_ros.bags import write_joint_state_bag

JS = 'sensor_msgs/msg/JointState'

# small, fast, but exercising refits: first fit at 10 samples, refit every 0.5 s of stamp time
# (hyper-parameters optimized on the first fit only), projection for passivity
PARAMS = {'model': 'full', 'passivity': 'projected', 'buffer_size': 40, 'min_samples': 10,
          'refit_period_s': 0.5, 'optimize_every_n_refits': 0, 'selection': 'all'}


def write_js_bag(path, rows, storage='sqlite3', topic='/joint_states', extra_topics=()):
    """
    Write a JointState bag (rosbags only).

    rows: (t_s, names, velocity, effort).
    """
    return write_joint_state_bag(path, [(t, n, np.zeros(len(n)), v, e) for t, n, v, e in rows],
                                 topic=[topic, *extra_topics], storage=storage)


def passive_data(n, N=3, seed=0):
    """Velocities and a passive nonlinear damping force with a little noise."""
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-1.0, 1.0, (n, N))
    T = (1.0 + 0.5 * Q ** 2) * Q + 0.2 * np.roll(Q, 1, axis=1) * Q ** 2 * np.sign(Q) \
        + 0.01 * rng.standard_normal((n, N))
    return Q, T


# --------------------------------------------------------------------------- live vs offline
def _node_params(d):
    from rclpy.parameter import Parameter
    return [Parameter(k, value=v) for k, v in d.items()]


def _wait(cond, timeout):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def _key(stamp):
    return (int(stamp.sec), int(stamp.nanosec))


def _max_diff(node_out, offline):
    """Max |difference| of tau_hat and stddev between node outputs and offline estimates."""
    assert len(node_out) == len(offline)
    worst = 0.0
    for e in offline:
        sec = int(np.floor(e.stamp_s + 1e-12))
        key = (sec, int(round((e.stamp_s - sec) * 1e9)))
        force, std = node_out[key]
        assert np.array_equal(np.asarray(force.velocity), e.qd)
        for live, off in ((np.asarray(force.effort), e.tau_hat),
                          (np.asarray(std.effort), e.stddev)):
            assert np.array_equal(np.isnan(live), np.isnan(off))   # NaN would hide in max()
            ok = ~np.isnan(off)
            worst = max(worst, float(np.max(np.abs(live[ok] - off[ok]), initial=0.0)))
    return worst


@pytest.mark.ros
@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_live_and_played_bag_equal_offline_replay(tmp_path, storage):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState

    from dgp_ros.bags.ros import Player, Recorder
    from dgp_ros.nodes.estimator import EstimatorNode

    n = 44                   # <= the node's input queue depth (50): nothing can be dropped
    names = ['alpha', 'beta', 'airspeed']
    Q, T = passive_data(n)
    bag = tmp_path / 'live'
    params = dict(PARAMS, refit_mode='sync')
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    nodes, ex, stop, th, rec, player = [], None, None, None, None, None

    def spin():
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.01)

    def collector(sink, store):
        forces, stds = {}, {}

        def on_force(m):
            forces[_key(m.header.stamp)] = m
            if _key(m.header.stamp) in stds:
                store[_key(m.header.stamp)] = (m, stds[_key(m.header.stamp)])

        def on_std(m):
            stds[_key(m.header.stamp)] = m
            if _key(m.header.stamp) in forces:
                store[_key(m.header.stamp)] = (forces[_key(m.header.stamp)], m)
        q = QoSProfile(depth=1000)
        sink.create_subscription(JointState, '/dgp_estimator/damping_force', on_force, q)
        sink.create_subscription(JointState, '/dgp_estimator/damping_force_stddev', on_std, q)

    try:
        est_node = EstimatorNode(context=ctx, parameter_overrides=_node_params(params))
        src = Node('src', context=ctx)
        recn = Node('rec', context=ctx)
        sink = Node('sink', context=ctx)
        nodes += [est_node, src, recn, sink]
        pub = src.create_publisher(JointState, 'generalized_state', QoSProfile(depth=100))
        rec = Recorder(recn, bag, {'generalized_state': JS}, storage=storage,
                       log=lambda s: None)
        live = {}
        collector(sink, live)
        ex = SingleThreadedExecutor(context=ctx)
        for nd in nodes:
            ex.add_node(nd)
        stop = threading.Event()
        th = threading.Thread(target=spin, daemon=True)
        th.start()
        assert _wait(lambda: pub.get_subscription_count() >= 2 and
                     est_node.pub_force.get_subscription_count() >= 1 and
                     est_node.pub_std.get_subscription_count() >= 1, 20), 'no match'

        # live run, in lock step (one measurement, its answer) so no sample can be dropped
        for i in range(n):
            m = JointState()
            m.header.stamp.sec, m.header.stamp.nanosec = 50 + i // 20, (i % 20) * 50_000_000
            m.name = names
            m.velocity = Q[i].tolist()
            m.effort = T[i].tolist()
            pub.publish(m)
            assert _wait(lambda: len(live) == i + 1, 60), f'no estimate for message {i}'
        assert _wait(lambda: rec.count == n, 10)
        stop.set()                  # rclpy cannot destroy what a spinning executor waits on
        th.join(10)
        rec.close()
        ex.remove_node(est_node)
        est_node.destroy_node()
        nodes.remove(est_node)
        stop = threading.Event()
        th = threading.Thread(target=spin, daemon=True)
        th.start()

        # offline replay of the recorded bag (no DDS): same estimates
        offline, est, info = replay(bag, config=build_config(params))
        assert info['topic'] == '/generalized_state' and len(offline) == n
        assert est.diagnostics()['refits_ok'] >= 3   # several refits happened on the way
        assert {e.source for e in offline} == {'prior', 'model'}
        d_live = _max_diff(live, offline)
        assert d_live <= 1e-9, d_live

        # the bag played back into a fresh estimator node: same estimates again
        est2 = EstimatorNode(context=ctx, parameter_overrides=_node_params(params))
        nodes.append(est2)
        ex.add_node(est2)
        played = {}
        sink2 = Node('sink2', context=ctx)
        nodes.append(sink2)
        collector(sink2, played)
        ex.add_node(sink2)
        assert _wait(lambda: est2.pub_force.get_subscription_count() >= 1 and
                     est2.pub_std.get_subscription_count() >= 1, 20)
        player = Player(src, bag, rate=0.0, wait_for_subscribers=20, log=lambda s: None)
        assert player.run() == n
        assert _wait(lambda: len(played) == n, 120), f'{len(played)}/{n} estimates'
        d_play = _max_diff(played, offline)
        assert d_play <= 1e-9, d_play
        print(f'\nmax |live - offline| = {d_live:.3g}, max |played - offline| = {d_play:.3g}')
    finally:
        if stop is not None:
            stop.set()
            th.join(10)
        if player is not None:
            player.close()
        if rec is not None:
            rec.close()
        if ex is not None:
            ex.shutdown()
        for nd in nodes:
            nd.destroy_node()
        ctx.try_shutdown()


# -------------------------------------------------------------------------- robot-like bags
def test_robot_bag_extra_joints_other_order(tmp_path):
    """
    Check that a messy /joint_states replays like a clean bag.

    /joint_states with extra joints, a varying order and a message missing a joint replays
    exactly like a clean bag of the selected joints; the JointState topic is chosen by name.
    """
    n = 40
    Q, T = passive_data(n, N=2, seed=3)
    clean, robot = [], []
    for i in range(n):
        t = 5.0 + 0.02 * i
        clean.append((t, ['shoulder', 'elbow'], Q[i], T[i]))
        order = ['wrist', 'elbow', 'gripper', 'shoulder'] if i % 2 else \
            ['shoulder', 'gripper', 'elbow', 'wrist']
        vals = {'shoulder': (Q[i, 0], T[i, 0]), 'elbow': (Q[i, 1], T[i, 1]),
                'wrist': (0.3 * i, -1.0), 'gripper': (float(i), 99.0)}
        robot.append((t, order, [vals[j][0] for j in order], [vals[j][1] for j in order]))
        if i == 17:  # a message without the elbow: rejected (missing_joint), no estimate
            robot.append((t + 0.01, ['shoulder', 'wrist'], [0.1, 0.2], [0.1, 0.2]))
    b_clean = write_js_bag(tmp_path / 'clean', clean)
    b_robot = write_js_bag(tmp_path / 'robot', robot, storage='mcap',
                           extra_topics=['/other/joint_state_echo'])
    params = dict(PARAMS, min_samples=8, refit_period_s=0.2)
    ref, _, _ = replay(b_clean, config=build_config(params))
    got, est, info = replay(b_robot, config=build_config(params, joints=['shoulder', 'elbow']))
    assert info['topic'] == '/joint_states'
    assert est.health.rejected['missing_joint'] == 1
    assert len(got) == len(ref) == n
    for a, b in zip(ref, got):
        assert b.names == ['shoulder', 'elbow']
        assert a.stamp_s == b.stamp_s
        np.testing.assert_array_equal(a.qd, b.qd)
        np.testing.assert_array_equal(a.tau_hat, b.tau_hat)
        np.testing.assert_array_equal(a.stddev, b.stddev)

    # the CLI on the robot bag: outputs, joint order, mass scaling, rejected counts
    out = tmp_path / 'out'
    rc = replay_main([str(b_robot), '--out', str(out), '--joints', 'shoulder,elbow',
                      '--topic', 'joint_states', '--mass', '2.5', '--quiet']
                     + [f'--set={k}={v}' for k, v in params.items()])
    assert rc == 0
    with open(out / 'estimates.csv') as f:
        rows = list(csv.reader(f))
    assert rows[0] == ['t', 'q_shoulder', 'q_elbow', 'tau_shoulder', 'tau_elbow',
                       'tau_hat_shoulder', 'tau_hat_elbow', 'stddev_shoulder', 'stddev_elbow',
                       'P', 'P_hat', 'source', 'added']
    assert len(rows) == n + 1
    # csv round-trips the estimates exactly (repr floats)
    np.testing.assert_array_equal([float(r[5]) for r in rows[1:]], [e.tau_hat[0] for e in ref])
    s = json.loads((out / 'summary.json').read_text())
    assert s['joints'] == ['shoulder', 'elbow'] and s['estimates'] == n
    assert s['messages'] == n + 1 and s['rejected']['missing_joint'] == 1
    assert s['rejected_total'] == 1
    assert set(s['nmse']) == {'shoulder', 'elbow'} and all(v < 0.5 for v in s['nmse'].values())
    assert s['negative_power_fraction'] == 0.0
    assert s['refits']['ok'] >= 1
    assert s['outputs']['elbow']['rmse_per_mass'] == pytest.approx(
        s['outputs']['elbow']['rmse'] / 2.5)
    for key in ('wall_time_s', 'process_total_s', 'refit_count'):
        assert key in s['timings']
    for png in ('estimate_vs_measurement.png', 'error.png', 'power_hist.png'):
        assert (out / png).stat().st_size > 1000


def test_replay_cli_errors(tmp_path, capsys):
    Q, T = passive_data(5, N=2)
    rows = [(1.0 + 0.1 * i, ['a', 'b'], Q[i], T[i]) for i in range(5)]
    bag = write_js_bag(tmp_path / 'b', rows, topic='/arm/state', extra_topics=['/leg/state'])
    cases = [
        ([], 'several JointState topics'),
        (['--topic', '/nope'], 'not in bag'),
        (['--topic', 'arm/state', '--joints', 'a,zz', '--set', 'min_samples=2'], None),
        (['--topic', '/arm/state', '--set', 'buffer_size=1'], 'buffer_size'),
        (['--topic', '/arm/state', '--set', 'no_such_param=1'], 'no_such_param'),
        (['--topic', '/arm/state', '--model', 'ard', '--passivity', 'certified'], "'ard'"),
    ]
    for extra, expect in cases:
        rc = replay_main([str(bag), '--out', str(tmp_path / 'o'), '-q', '--no-plots'] + extra)
        err = capsys.readouterr().err
        if expect is None:
            # every message lacks joint zz: nothing to estimate -> exit 2 with the reason and
            # the bag's joints; the summary is still written
            assert rc == 2, err
            assert '5 missing_joint' in err and 'joints are a, b' in err, err
            s = json.loads((tmp_path / 'o' / 'summary.json').read_text())
            assert s['estimates'] == 0 and s['rejected']['missing_joint'] == 5
            continue
        assert rc == 2, (extra, err)
        assert expect in err and len(err.strip().splitlines()) == 1, (extra, err)


def test_replay_is_deterministic_and_writes_outputs(tmp_path):
    Q, T = passive_data(30, N=2, seed=7)
    rows = [(2.0 + 0.05 * i, ['x', 'y'], Q[i], T[i]) for i in range(30)]
    bag = write_js_bag(tmp_path / 'b', rows, storage='mcap')
    cfg = build_config(dict(PARAMS, min_samples=8))
    s1 = run(bag, tmp_path / 'o1', config=cfg, plots=False)
    s2 = run(bag, tmp_path / 'o2', config=cfg, plots=False)
    assert (tmp_path / 'o1' / 'estimates.csv').read_text() == \
        (tmp_path / 'o2' / 'estimates.csv').read_text()
    assert s1['nmse'] == s2['nmse'] and s1['config']['refit_mode'] == 'sync'


def test_replay_with_learning_off_serves_the_model_file_frozen(tmp_path):
    """--set learning=false --set model_path=M: the answers of the deployed node, M unchanged."""
    from dgp_ros.gp import load_model
    Q, T = passive_data(120, N=2, seed=3)
    rows = [(2.0 + 0.05 * i, ['x', 'y'], Q[i], T[i]) for i in range(120)]
    bag = write_js_bag(tmp_path / 'b', rows)
    model = tmp_path / 'm.npz'
    run(bag, tmp_path / 'o1', config=build_config(dict(PARAMS, min_samples=8)), plots=False,
        save_model=str(model))
    before = model.read_bytes()
    cfg = build_config(dict(PARAMS, min_samples=8, learning=False, model_path=str(model)))
    s = run(bag, tmp_path / 'o2', config=cfg, plots=False)
    assert model.read_bytes() == before                 # read, never written
    assert s['samples_added'] == 0 and 'learning off' in s['status']['message'], s['status']
    rows_out = (tmp_path / 'o2' / 'estimates.csv').read_text().splitlines()
    assert len(rows_out) == 121
    m = load_model(model)
    assert np.abs(m.predict(Q[:5])).max() > 0
    # a learning replay still never touches model_path
    assert build_config(dict(PARAMS, model_path=str(model))).model_path == ''

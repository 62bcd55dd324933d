"""
dgp_ros.bags.io and .joint_states (rosbags only).

Reading, writing, JointState streams, type checks, errors.

No rclpy here: ``import dgp_ros.bags`` must not load it (checked in a fresh interpreter).
"""
import ast
from contextlib import closing
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from dgp_ros import bags
from dgp_ros.bags import (bag_summary, BagError, BagWriter, check_message_type, iter_bag,
                          iter_joint_states, joint_state_topic, message_definition, normalize_type,
                          open_bag, playable_topics, typestore, write_joint_state_bag)
from dgp_ros.msgs.sample import JointStateSample

JS = 'sensor_msgs/msg/JointState'
PKG = Path(bags.__file__).resolve().parents[1]


# ------------------------------------------------------------------------- no rclpy, ever
@pytest.mark.parametrize('module', ['dgp_ros.bags', 'dgp_ros.bags.io', 'dgp_ros.bags.joint_states',
                                    'dgp_ros.msgs', 'dgp_ros.msgs.sample', 'dgp_ros.msgs.cdr',
                                    'dgp_ros.bags.cli', 'dgp_ros.apps.replay', 'dgp_ros.replay'])
def test_import_does_not_load_rclpy(module):
    code = (f'import sys, {module}\n'
            "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'rclpy')\n"
            'print(bad); sys.exit(1 if bad else 0)')
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr


@pytest.mark.parametrize('path', [PKG / 'bags' / 'io.py', PKG / 'bags' / 'joint_states.py',
                                  PKG / 'msgs' / 'sample.py', PKG / 'msgs' / 'cdr.py',
                                  PKG / 'msgs' / '__init__.py'])
def test_pure_modules_have_no_rclpy_import_even_lazily(path):
    tree = ast.parse(path.read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or '' for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in names if m.split('.')[0] == 'rclpy'], names


# ------------------------------------------------------------------------------ bad bags
def test_open_bag_errors_are_one_line(bad_bags):
    for name, path in bad_bags.items():
        with pytest.raises(BagError) as ei:
            for _ in iter_bag(path):
                pass
        msg = str(ei.value)
        assert '\n' not in msg and str(path.name) in msg, (name, msg)


def test_killed_recording_without_metadata_is_readable(tmp_path, make_samples):
    bag = write_joint_state_bag(tmp_path / 'b', make_samples(5))
    (bag / 'metadata.yaml').unlink()
    assert len(list(iter_bag(bag))) == 5


def test_replay_cli_bad_bag_exit_2_no_traceback(tmp_path, bad_bags, cli):
    for name, path in bad_bags.items():
        p = subprocess.run(cli('dgp-replay') + [str(path), '--out', str(tmp_path / f'o_{name}')],
                           capture_output=True, text=True, timeout=60)
        err = p.stderr.strip()
        assert p.returncode == 2, (name, p.returncode, err)
        assert 'Traceback' not in err and len(err.splitlines()) == 1, (name, err)
        assert err.startswith('dgp-replay: error:'), (name, err)


# ------------------------------------------------------------------ JointState round trip
@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_write_then_iter_joint_states(tmp_path, storage):
    rows = [JointStateSample(3.25, ['a', 'b'], np.array([0.5, -0.5]), np.array([1.0, 2.0]),
                             np.array([-3.0, 4.5])),
            (3.5 + 1e-9, ['a', 'b'], [], [0.1, 0.2], [0.3, 0.4]),         # tuple, no position
            (4.0 - 1e-10, ['a', 'b'], [], [0.0, 0.0], [0.0, 0.0])]        # rounds up to 4 s
    bag = write_joint_state_bag(tmp_path / 'b', rows, topic=['/joint_states', '/echo'],
                                storage=storage)
    assert bag_summary(bag)['topics'] == {'/joint_states': {'type': JS, 'count': 3},
                                          '/echo': {'type': JS, 'count': 3}}
    got = list(iter_joint_states(bag, topic='joint_states'))
    assert [s.stamp_s for s in got] == [3 + 1e-9 * 250_000_000, 3 + 1e-9 * 500_000_001, 4.0]
    assert all(s.names == ['a', 'b'] for s in got)
    np.testing.assert_array_equal(got[0].position, [0.5, -0.5])
    assert got[1].position.shape == (0,)
    np.testing.assert_array_equal(got[1].velocity, [0.1, 0.2])
    np.testing.assert_array_equal(got[0].effort, [-3.0, 4.5])
    # stamp='bag': the receive time recorded in the bag (equal to the header stamp here)
    by_bag = list(iter_joint_states(bag, topic='/echo', stamp='bag'))
    assert [s.stamp_s for s in by_bag] == [t * 1e-9 for _, t, _ in iter_bag(bag, ['/echo'])]
    with pytest.raises(ValueError):
        next(iter_joint_states(bag, stamp='wall'))


def test_iter_joint_states_yields_none_for_undecodable(tmp_path):
    from rosbags.rosbag2 import Writer
    ts = typestore()
    w = Writer(tmp_path / 'b', version=9, storage_plugin=bags.storage_plugin('sqlite3'))
    w.open()
    c = w.add_connection('/joint_states', JS, typestore=ts)
    good = JointStateSample(1.0, ['a'], np.zeros(0), np.ones(1), np.ones(1))
    write_joint_state_bag(tmp_path / 'ref', [good])
    raw = next(iter_bag(tmp_path / 'ref'))[2]
    w.write(c, 1, bytes(raw))
    w.write(c, 2, b'\x00\x01\x00\x00garbage')
    w.close()
    got = list(iter_joint_states(tmp_path / 'b'))
    assert got[0] is not None and got[0].names == ['a'] and got[1] is None


def test_joint_state_topic_choice(tmp_path, make_samples):
    def reader(name, topic):
        return closing(open_bag(write_joint_state_bag(tmp_path / name, make_samples(2),
                                                      topic=topic)))
    with reader('one', '/robot/state') as r:
        assert joint_state_topic(r) == '/robot/state'
    with reader('named', ['/a/joint_states', '/b/echo']) as r:
        assert joint_state_topic(r) == '/a/joint_states'
        assert joint_state_topic(r, 'b/echo') == '/b/echo'
        with pytest.raises(BagError, match='not in bag'):
            joint_state_topic(r, '/nope')
    with reader('two', ['/x', '/y']) as r:
        with pytest.raises(BagError, match='several JointState topics'):
            joint_state_topic(r)


# -------------------------------------------------------------------- types and writing
def test_normalize_type():
    assert normalize_type('sensor_msgs/JointState') == JS
    assert normalize_type(JS) == JS
    for bad in ('JointState', 'a/b/c/d', '../msg/X', 'pkg/msg/..', 'pkg/msg/9x', 'p-k/msg/X'):
        with pytest.raises(ValueError):
            normalize_type(bad)


def test_check_message_type_fixed_store_only():
    had_this = 'this' in sys.modules
    assert check_message_type('sensor_msgs/JointState') == JS
    assert check_message_type('rosgraph_msgs/msg/Clock') == 'rosgraph_msgs/msg/Clock'
    cases = {'this/msg/Zen': 'this/msg/Zen',                        # importable Python module
             'os/msg/path': 'os/msg/path',
             'sensor_msgs/msg/NoSuchType': 'NoSuchType',            # allowed package, no type
             'rmw_dds_common/msg/Gid': 'rmw_dds_common',             # Jazzy type, not allowed
             '../msg/X': 'invalid message type'}
    for t, named in cases.items():
        with pytest.raises(BagError) as ei:
            check_message_type(t)
        assert named in str(ei.value) and '\n' not in str(ei.value), (t, ei.value)
    assert had_this or 'this' not in sys.modules            # refused before any import


def test_check_message_type_installed_definitions(tmp_path, monkeypatch):
    share = tmp_path / 'share' / 'my_pkg' / 'msg'
    share.mkdir(parents=True)
    (share / 'Custom.msg').write_text('float64 x\n')
    with pytest.raises(BagError):
        check_message_type('my_pkg/msg/Custom', allow_installed=True)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    assert bags.installed_definition('my_pkg/Custom') == share / 'Custom.msg'
    assert check_message_type('my_pkg/Custom', allow_installed=True) == 'my_pkg/msg/Custom'
    with pytest.raises(BagError):           # playback never takes installed definitions
        check_message_type('my_pkg/Custom')
    msgdef, rihs = message_definition('my_pkg/msg/Custom')
    assert msgdef.strip() == 'float64 x' and rihs.startswith('RIHS01_')


def test_playable_topics(foreign_bag):
    with closing(open_bag(foreign_bag)) as r:
        with pytest.raises(BagError, match='this/msg/Zen'):
            playable_topics(r)
        plan = playable_topics(r, ['/joint_states'])
        assert list(plan) == ['/joint_states'] and plan['/joint_states'][0] == JS
        with pytest.raises(BagError, match='not in bag: /nope'):
            playable_topics(r, ['/joint_states', '/nope'])


def test_message_definition_from_the_jazzy_store():
    msgdef, rihs = message_definition('sensor_msgs/JointState')
    assert msgdef.startswith('std_msgs/Header header') and rihs == typestore().hash_rihs01(JS)
    assert message_definition('nobody/msg/Knows', 'RIHS01_ab') == ('', 'RIHS01_ab')


def test_bag_writer_thread(tmp_path):
    msgdef, rihs = message_definition(JS)
    raw = bytes(next(iter_bag(write_joint_state_bag(
        tmp_path / 'ref', [(1.0, ['a'], [], [1.0], [2.0])])))[2])
    w = BagWriter(tmp_path / 'b', 'mcap', {'recorded_by': 'test'})
    w.add_connection('/s', JS, msgdef, rihs)
    for t in (5, 6, 7):
        w.write('/s', t, raw)
    w.close()
    assert [(t, bytes(d)) for _, t, d in iter_bag(tmp_path / 'b')] == \
        [(5, raw), (6, raw), (7, raw)]
    with pytest.raises(BagError, match='cannot create bag'):
        BagWriter(tmp_path / 'b', 'sqlite3')                  # exists already
    with pytest.raises(BagError, match='unknown storage'):
        BagWriter(tmp_path / 'c', 'zip')

"""dgp_ros.msgs.sample: one JointState converter for rclpy and rosbags messages, bit for bit."""
import array
import math
import types

import numpy as np
import pytest

from dgp_ros.msgs.sample import joint_state_sample, JointStateSample, stamp_seconds

STAMPS = [(0, 0), (1, 1), (100, 999_999_999), (1_700_000_000, 123_456_789), (2**31 - 1, 5)]


def _rosbags_msg(sec, nanosec, names, pos, vel, eff):
    from dgp_ros.bags import JOINT_STATE, typestore
    ts = typestore()
    T = ts.types
    msg = T[JOINT_STATE](
        header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id='f'),
        name=list(names), position=np.asarray(pos, float), velocity=np.asarray(vel, float),
        effort=np.asarray(eff, float))
    return ts.deserialize_cdr(ts.serialize_cdr(msg, JOINT_STATE), JOINT_STATE)


def test_rclpy_and_rosbags_messages_give_identical_samples():
    from sensor_msgs.msg import JointState
    rng = np.random.default_rng(1)
    for sec, nsec in STAMPS:
        vel, eff = rng.standard_normal(3), rng.standard_normal(3) * 1e5
        m = JointState()
        m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
        m.name = ['a', 'b', 'c']
        m.velocity, m.effort = vel.tolist(), eff.tolist()
        a = joint_state_sample(m)
        b = joint_state_sample(_rosbags_msg(sec, nsec, m.name, [], vel, eff))
        # the node's historical expression, on the rclpy message's own fields
        assert a.stamp_s == m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
        assert a.stamp_s == b.stamp_s == sec + 1e-9 * nsec
        assert a.names == b.names == ['a', 'b', 'c']
        for x, y in ((a.velocity, b.velocity), (a.effort, b.effort), (a.position, b.position)):
            assert x.dtype == y.dtype == np.float64
            assert x.tobytes() == y.tobytes()
        assert a.velocity.tobytes() == vel.tobytes()


def test_sample_does_not_alias_the_message():
    msg = types.SimpleNamespace(header=types.SimpleNamespace(
        stamp=types.SimpleNamespace(sec=1, nanosec=2)), name=['a'],
        position=array.array('d', [1.0]), velocity=np.array([2.0]), effort=[3.0])
    s = joint_state_sample(msg)
    msg.velocity[0] = 99.0
    msg.position[0] = 99.0
    assert s.velocity[0] == 2.0 and s.position[0] == 1.0 and s.effort[0] == 3.0
    assert isinstance(s, JointStateSample)
    with pytest.raises(AttributeError):
        s.stamp_s = 0.0                                  # frozen


class _Raises:
    """Every message field access raises (dunder lookups behave normally)."""

    def __getattr__(self, name):
        if name.startswith('__'):
            raise AttributeError(name)
        raise RuntimeError(name)

    def __iter__(self):
        raise RuntimeError('iter')


@pytest.mark.parametrize('msg', [
    None, object(), _Raises(), types.SimpleNamespace(),
    types.SimpleNamespace(header=None, name='abc', velocity='x', effort=[[1.0], [2.0, 3.0]]),
    types.SimpleNamespace(header=types.SimpleNamespace(stamp=types.SimpleNamespace(
        sec='soon', nanosec=None)), name=5, position={'a': 1}, velocity=[1.0, 'x'],
        effort=_Raises()),
])
def test_odd_content_never_raises(msg):
    s = joint_state_sample(msg)
    assert math.isnan(s.stamp_s) and s.names == []
    for a in (s.position, s.velocity, s.effort):
        assert a.shape == (0,) and a.dtype == np.float64


def test_names_kept_as_given_for_the_estimator_to_judge():
    msg = types.SimpleNamespace(name=('a', 3), velocity=[1.0, 2.0], effort=[0.0, 0.0])
    s = joint_state_sample(msg)
    assert s.names == ['a', 3] and math.isnan(s.stamp_s)
    np.testing.assert_array_equal(s.velocity, [1.0, 2.0])


def test_stamp_seconds():
    assert stamp_seconds(types.SimpleNamespace(sec=np.int32(3), nanosec=np.uint32(5))) == \
        3 + 1e-9 * 5
    assert math.isnan(stamp_seconds(None))

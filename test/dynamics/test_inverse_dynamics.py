"""
Inverse dynamics front end.

URDF (pinocchio) reduction and ordering, continuous joints, the plugin spec, the parameter dispatch
and the import guards.
"""
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from dgp_ros.dynamics import (ARM_JOINTS, example_robot_urdf, make_inverse_dynamics,
                              PINOCCHIO_HINT, PluginInverseDynamics, UrdfInverseDynamics)

pin = pytest.importorskip('pinocchio')
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PANDA = ARM_JOINTS['panda']


@pytest.fixture(scope='module')
def panda_urdf():
    with open(example_robot_urdf('panda'), encoding='utf-8') as f:
        return f.read()


def _random_states(rng, k, n):
    return rng.uniform(-1.5, 1.5, (k, n)), rng.uniform(-2, 2, (k, n)), rng.uniform(-5, 5, (k, n))


def test_reduced_panda_equals_full_model_with_fingers_at_neutral(panda_urdf):
    full = pin.buildModelFromXML(panda_urdf)
    data = full.createData()
    assert full.nv == 9   # 7 arm joints + 2 fingers, locked by the reduction
    dyn = UrdfInverseDynamics(urdf=panda_urdf, joints=PANDA)
    q, qd, qdd = _random_states(np.random.default_rng(0), 5, 7)
    pad = np.zeros(2)
    want = np.array([pin.rnea(full, data, np.r_[q[i], pad], np.r_[qd[i], pad],
                              np.r_[qdd[i], pad])[:7] for i in range(5)])
    np.testing.assert_allclose(dyn(q, qd, qdd), want, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(dyn(q[2], qd[2], qdd[2]), want[2], rtol=1e-10, atol=1e-9)
    assert abs(want).max() > 10.0   # gravity and inertia are in it


def test_selected_order_is_the_callers(panda_urdf):
    perm = [6, 0, 3, 1, 5, 2, 4]
    ordered = UrdfInverseDynamics(urdf=panda_urdf, joints=PANDA)
    shuffled = UrdfInverseDynamics(urdf=panda_urdf, joints=[PANDA[i] for i in perm])
    q, qd, qdd = _random_states(np.random.default_rng(1), 3, 7)
    np.testing.assert_allclose(shuffled(q[:, perm], qd[:, perm], qdd[:, perm]),
                               ordered(q, qd, qdd)[:, perm], rtol=1e-12, atol=1e-10)
    np.testing.assert_array_equal(shuffled.lower, ordered.lower[perm])


def test_mass_matrix_from_the_callable_is_symmetric_positive_definite():
    """
    Check the joint mapping with the mass matrix.

    Column i of M(q) = tau(q, 0, e_i) - tau(q, 0, 0): symmetric and positive definite only if
    positions, accelerations and outputs are all mapped to the right joints (UR5, permuted).
    """
    names = list(ARM_JOINTS['ur5'])[::-1]
    dyn = UrdfInverseDynamics(urdf_file=example_robot_urdf('ur5'), joints=names)
    q = np.random.default_rng(2).uniform(-1, 1, 6)
    g = dyn(q, np.zeros(6), np.zeros(6))
    eye = np.eye(6)
    M = dyn(np.tile(q, (6, 1)), np.zeros((6, 6)), eye) - g
    np.testing.assert_allclose(M, M.T, atol=1e-9)
    assert np.linalg.eigvalsh(M).min() > 0.0
    assert abs(g[names.index('shoulder_lift_joint')]) > 5.0   # gravity on the shoulder


def _two_link_urdf(first_type: str) -> str:
    limit = '' if first_type == 'continuous' else \
        '<limit lower="-10" upper="10" effort="10" velocity="5"/>'
    link = ('<link name="{n}"><inertial><origin xyz="0.3 0 0.05"/><mass value="{m}"/>'
            '<inertia ixx="0.02" ixy="0.001" ixz="0" iyy="0.03" iyz="0" izz="0.04"/></inertial>'
            '<visual><geometry><mesh filename="package://nowhere/{n}.stl"/></geometry></visual>'
            '</link>')
    return ('<robot name="two">' + '<link name="base"/>' + link.format(n='l1', m=2.0)
            + link.format(n='l2', m=1.0)
            + f'<joint name="j1" type="{first_type}"><parent link="base"/><child link="l1"/>'
            + '<axis xyz="0 1 0"/>' + limit + '</joint>'
            + '<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>'
            + '<origin xyz="0.6 0 0"/><axis xyz="0 1 0"/>'
            + '<limit lower="-3" upper="3" effort="10" velocity="5"/></joint></robot>')


def test_continuous_joint_takes_the_angle_and_meshes_are_not_needed():
    cont = UrdfInverseDynamics(urdf=_two_link_urdf('continuous'), joints=['j2', 'j1'])
    rev = UrdfInverseDynamics(urdf=_two_link_urdf('revolute'), joints=['j2', 'j1'])
    assert cont.model.nq == 3 and rev.model.nq == 2   # (cos, sin) for the continuous joint
    q = np.array([[0.4, 0.3], [-1.0, 4.0], [2.5, -7.0]])   # angles beyond pi too
    qd, qdd = np.full((3, 2), 0.7), np.full((3, 2), -1.3)
    np.testing.assert_allclose(cont(q, qd, qdd), rev(q, qd, qdd), rtol=1e-10, atol=1e-10)
    assert cont.lower[1] == -np.inf and cont.upper[1] == np.inf and rev.upper[1] == 10.0


def test_all_movable_joints_when_none_selected():
    dyn = UrdfInverseDynamics(urdf=_two_link_urdf('revolute'))
    assert dyn.joint_names == ('j1', 'j2') and dyn.nv == 2


def test_unknown_joints_are_named_with_the_urdf_joints(panda_urdf):
    with pytest.raises(ValueError) as err:
        UrdfInverseDynamics(urdf=panda_urdf, joints=['panda_joint1', 'joint_a1', 'elbow'])
    msg = str(err.value)
    assert "'joint_a1'" in msg and "'elbow'" in msg
    assert 'panda_joint7' in msg and 'panda_finger_joint1' in msg
    with pytest.raises(ValueError, match='sequence of joint names'):
        UrdfInverseDynamics(urdf=panda_urdf, joints='panda_joint1')
    with pytest.raises(ValueError, match='repeated'):
        UrdfInverseDynamics(urdf=panda_urdf, joints=['panda_joint1', 'panda_joint1'])


@pytest.mark.parametrize('kwargs, reason', [
    ({'urdf': '<robot name="x"><link name="a"></robot>'}, 'not well-formed XML'),
    ({'urdf': '<sdf version="1.6"/>'}, 'root element is <sdf>'),
    ({'urdf_file': '/nonexistent/robot.urdf'}, 'cannot be read'),
    ({'urdf': '<robot name="x"><link name="a"/></robot>'}, 'no movable joints'),
    ({}, 'needs urdf'),
])
def test_parse_errors_are_one_line(kwargs, reason):
    with pytest.raises(ValueError, match=reason) as err:
        UrdfInverseDynamics(**kwargs)
    assert '\n' not in str(err.value)


def test_call_shapes_are_checked(panda_urdf):
    dyn = UrdfInverseDynamics(urdf=panda_urdf, joints=PANDA)
    with pytest.raises(ValueError, match='N = 7'):
        dyn(np.zeros(6), np.zeros(6), np.zeros(6))
    with pytest.raises(ValueError, match='one shape'):
        dyn(np.zeros(7), np.zeros((2, 7)), np.zeros(7))


def test_make_inverse_dynamics_dispatch(panda_urdf, tmp_path):
    assert make_inverse_dynamics('') is None and make_inverse_dynamics('  ') is None
    with pytest.raises(ValueError, match='robot_description .* urdf_file'):
        make_inverse_dynamics('urdf', joints=PANDA)
    with pytest.raises(ValueError, match=r"'rnea'.*'urdf'.*python:<module>:<function>"):
        make_inverse_dynamics('rnea')
    # robot_description wins over urdf_file (a broken file is then never read)
    dyn = make_inverse_dynamics('urdf', robot_description=panda_urdf,
                                urdf_file=str(tmp_path / 'missing.urdf'), joints=PANDA)
    assert isinstance(dyn, UrdfInverseDynamics) and dyn.joint_names == PANDA
    with pytest.raises(ValueError, match='robot_description is not a URDF'):
        make_inverse_dynamics('urdf', robot_description='<robot', urdf_file=example_robot_urdf(
            'panda'), joints=PANDA)
    assert make_inverse_dynamics('urdf', urdf_file=example_robot_urdf('ur5')).nv == 6


@pytest.fixture
def plugin_module(tmp_path, monkeypatch):
    (tmp_path / 'dgp_test_dyn_plugin.py').write_text(textwrap.dedent("""
        import numpy as np
        NOT_CALLABLE = 3
        def tau(q, qd, qdd):
            return 2.0 * qdd + 0.5 * qd
        def wrong(q, qd, qdd):
            return np.zeros(q.shape[-1] + 1)
        class ns:
            @staticmethod
            def tau(q, qd, qdd):
                return qdd
    """))
    (tmp_path / 'dgp_test_broken_plugin.py').write_text('raise RuntimeError("boom")\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    return 'dgp_test_dyn_plugin'


def test_plugin_calls_the_function_and_checks_shapes(plugin_module):
    f = make_inverse_dynamics(f'python:{plugin_module}:tau')
    assert isinstance(f, PluginInverseDynamics)
    np.testing.assert_allclose(f([0, 0], [1, 2], [3, 4]), [6.5, 9.0])
    assert f(np.zeros((4, 3)), np.ones((4, 3)), np.ones((4, 3))).shape == (4, 3)
    assert PluginInverseDynamics(f'python:{plugin_module}:ns.tau')([1.0], [2.0], [3.0]) == [3.0]
    bad = PluginInverseDynamics(f'python:{plugin_module}:wrong')
    with pytest.raises(ValueError, match=r'returned shape \(3,\) .* must return \(2,\)'):
        bad(np.zeros(2), np.zeros(2), np.zeros(2))


@pytest.mark.parametrize('spec, reason', [
    ('python:', 'expected "python:<module>:<function>"'),
    ('python:only_module', 'expected'),
    ('python:a:b:c', 'expected'),
    ('python:dgp_no_such_module_xyz:f', "cannot import 'dgp_no_such_module_xyz'.*ModuleNotFound"),
    ('python:dgp_test_broken_plugin:f', 'cannot import.*RuntimeError: boom'),
    ('python:dgp_test_dyn_plugin:missing', "has no attribute 'missing'"),
    ('python:dgp_test_dyn_plugin:NOT_CALLABLE', 'not callable'),
])
def test_plugin_spec_errors_are_clear(plugin_module, spec, reason):
    with pytest.raises(ValueError, match=reason):
        make_inverse_dynamics(spec)


def test_package_imports_without_rclpy_and_without_pinocchio():
    """
    Check that the package imports without rclpy and without pinocchio.

    In a fresh interpreter with pinocchio hidden: the package imports, never loads rclpy, and
    only "urdf" fails, with the install hint.
    """
    code = textwrap.dedent(f"""
        import sys
        sys.modules['pinocchio'] = None   # import pinocchio -> ImportError
        import dgp_ros.dynamics as d
        from dgp_ros.dynamics import arm_sim, filter, inverse, residual
        assert 'rclpy' not in sys.modules, 'rclpy imported'
        assert d.make_inverse_dynamics('') is None
        try:
            d.make_inverse_dynamics('urdf', robot_description='<robot name="x"/>')
        except ValueError as exc:
            assert {PINOCCHIO_HINT!r} in str(exc), str(exc)
        else:
            raise AssertionError('no ValueError')
        assert 'rclpy' not in sys.modules, 'rclpy imported'
        print('ok')
    """)
    run = subprocess.run([sys.executable, '-c', code], cwd=REPO, capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0 and run.stdout.strip() == 'ok', run.stderr

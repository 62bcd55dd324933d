"""Fixtures shared by the bag tests: sample data, broken bags, console-script command lines."""
from pathlib import Path
import re
import shutil
import sys

import numpy as np
import pytest

from dgp_ros.bags import write_joint_state_bag
from dgp_ros.msgs.sample import JointStateSample

SETUP_PY = Path(__file__).resolve().parents[2] / 'setup.py'


def console_scripts() -> dict:
    """
    Return the console scripts declared in setup.py.

    ``{name: (module, function)}`` as declared in setup.py (not the installed copies, which
    only change with a reinstall).
    """
    text = SETUP_PY.read_text()
    return {m[1]: (m[2], m[3]) for m in re.finditer(r"'([\w-]+) = ([\w.]+):(\w+)'", text)}


@pytest.fixture
def scripts():
    """Return the console scripts declared in setup.py: ``{name: (module, function)}``."""
    return console_scripts()


@pytest.fixture
def cli(scripts):
    """
    Return the command line running a console script's entry point.

    ``cli('dgp-play')`` -> command line running that console script's entry point.
    """
    def command(name):
        mod, fn = scripts[name]
        return [sys.executable, '-c', f'import sys; from {mod} import {fn} as m; sys.exit(m())']
    return command


def samples(n=20, N=2, seed=0, t0=10.0, dt=0.05):
    """``n`` JointState samples of ``N`` joints with a passive damping force as effort."""
    rng = np.random.default_rng(seed)
    names = [f'j{k}' for k in range(N)]
    out = []
    for i in range(n):
        qd = rng.uniform(-1, 1, N)
        out.append(JointStateSample(t0 + dt * i, names, np.zeros(0), qd, 2.0 * qd + 0.1 * qd ** 3))
    return out


@pytest.fixture
def bad_bags(tmp_path):
    """``{case: path}``: missing, not a bag, truncated (both storages), bad metadata, garbage."""
    good_db = write_joint_state_bag(tmp_path / 'good_db', samples(200))
    good_mc = write_joint_state_bag(tmp_path / 'good_mc', samples(200), storage='mcap')
    cases = {'missing': tmp_path / 'does_not_exist'}
    d = tmp_path / 'empty_dir'
    d.mkdir()
    cases['not_a_bag'] = d
    for name, src, fname in (('trunc_db3', good_db, 'good_db.db3'),
                             ('trunc_mcap', good_mc, 'good_mc.mcap')):
        dst = tmp_path / name
        shutil.copytree(src, dst)
        f = dst / fname
        data = f.read_bytes()
        f.write_bytes(data[:len(data) // 2])
        cases[name] = dst
    dst = tmp_path / 'bad_yaml'
    shutil.copytree(good_db, dst)
    (dst / 'metadata.yaml').write_text('rosbag2_bagfile_information: {version: [\n')
    cases['bad_metadata'] = dst
    dst = tmp_path / 'garbage_db3'
    shutil.copytree(good_db, dst)
    f = dst / 'good_db.db3'
    data = bytearray(f.read_bytes())
    for i in range(0, len(data), 61):
        data[i] ^= 0xA5
    f.write_bytes(bytes(data))
    cases['garbage_db3'] = dst
    return cases


@pytest.fixture
def make_samples():
    """Return the :func:`samples` factory."""
    return samples


@pytest.fixture
def foreign_bag(tmp_path):
    """
    Write a bag with a JointState topic and a topic ``/zen`` of type ``this/msg/Zen``.

    This is not a ROS type, and ``this`` is a Python module with an import side effect.
    """
    from rosbags.rosbag2 import Writer

    from dgp_ros.bags import JOINT_STATE, storage_plugin, typestore
    ts = typestore()
    T = ts.types
    msg = T[JOINT_STATE](
        header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=1, nanosec=0),
                                        frame_id=''),
        name=['a'], position=np.zeros(0), velocity=np.ones(1), effort=np.ones(1))
    path = tmp_path / 'foreign'
    w = Writer(path, version=9, storage_plugin=storage_plugin('sqlite3'))
    w.open()
    js = w.add_connection('/joint_states', JOINT_STATE, typestore=ts)
    w.write(js, 1_000_000_000, ts.serialize_cdr(msg, JOINT_STATE))
    zen = w.add_connection('/zen', 'this/msg/Zen', msgdef='string text',
                           rihs01='RIHS01_' + '0' * 64)
    w.write(zen, 1_000_000_001, bytes([0, 1, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]))
    w.close()
    return path

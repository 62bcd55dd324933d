"""
Class 4, bags naming message types that are not allowed (``bench/hostile.py``).

``dgp-play`` and ``dgp_ros.bags.ros.Player`` must refuse them before any import: each runs in a
subprocess that reports whether the named module was imported.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

from common import log, REPO

from .base import Sandbox


_BAG_PROBE = r"""
import io, json, sys, contextlib
mode, bags = sys.argv[1], json.loads(sys.argv[2])
before = set(sys.modules)
out = []
if mode == 'player':
    import rclpy
    from rclpy.node import Node
    from dgp_ros.bags import BagError
    from dgp_ros.bags.ros import Player
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node('hostile_bag_probe', context=ctx)
else:
    from dgp_ros.bags.cli import play_main
for path, mods in bags:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        if mode == 'player':
            try:
                p = Player(node, path, rate=0.0)
                p.close()
                rc = 0
            except BagError as exc:
                print(f'BagError: {exc}', file=sys.stderr)
                rc = 2
            except Exception as exc:
                print(f'{type(exc).__name__}: {exc}', file=sys.stderr)
                rc = 3
        else:
            try:
                rc = play_main([path, '--rate', '0', '-q'])
            except SystemExit as exc:
                rc = exc.code
            except Exception as exc:
                print(f'{type(exc).__name__}: {exc}', file=sys.stderr)
                rc = 3
    imported = [m for m in mods if m in sys.modules and m not in before]
    out.append(dict(path=path, rc=rc, stderr=err.getvalue().strip(), imported=imported))
if mode == 'player':
    node.destroy_node()
    ctx.try_shutdown()
sys.stdout.write(json.dumps(out))
"""


def build_bags(sb: Sandbox) -> list:
    """(label, bag dir, modules that must not be imported) of bags naming refused types."""
    from rosbags.rosbag2 import Writer

    from dgp_ros.bags import JOINT_STATE, storage_plugin, typestore
    ts = typestore()
    Tt = ts.types
    js = Tt[JOINT_STATE](
        header=Tt['std_msgs/msg/Header'](stamp=Tt['builtin_interfaces/msg/Time'](sec=1,
                                                                                 nanosec=0),
                                         frame_id=''),
        name=['a'], position=np.zeros(0), velocity=np.ones(1), effort=np.ones(1))
    out = []
    types = [('this/msg/Zen', ['this']), ('this/Zen (short form)', ['this']),
             ('tabnanny/msg/Check', ['tabnanny']), ('smtplib/msg/SMTP', ['smtplib']),
             ('turtle/msg/Turtle', ['turtle', 'tkinter']),
             ('rmw_dds_common/msg/Gid (in the store, package not allowed)',
              ['rmw_dds_common', 'rmw_dds_common.msg']),
             ('sensor_msgs/msg/Zen (allowed package, no such type)', []),
             ('this_1/msg/Zen__x', ['this_1'])]
    for i, (lab, mods) in enumerate(types):
        typ = lab.split(' ')[0]
        for mixed in (False, True):
            path = os.path.join(sb.bags, f'bag{i}{"m" if mixed else ""}')
            w = Writer(path, version=9, storage_plugin=storage_plugin('sqlite3'))
            w.open()
            if mixed:
                c = w.add_connection('/joint_states', JOINT_STATE, typestore=ts)
                w.write(c, 1_000_000_000, ts.serialize_cdr(js, JOINT_STATE))
            c = w.add_connection('/foreign', typ, msgdef='string text',
                                 rihs01='RIHS01_' + '0' * 64)
            w.write(c, 1_000_000_001, bytes([0, 1, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]))
            w.close()
            out.append((lab + (' + a JointState topic' if mixed else ''), path, mods, typ))
    return out


def run_bags(sb: Sandbox, bags: list) -> dict:
    arg = json.dumps([[p, m] for _l, p, m, _t in bags])
    rows = []
    for mode in ('dgp-play', 'player'):
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, '-c', _BAG_PROBE, mode, arg], capture_output=True,
                           text=True, timeout=300, cwd=REPO, env=dict(os.environ))
        dt = time.perf_counter() - t0
        try:
            res = json.loads(p.stdout)
        except ValueError:
            res = [{'path': b[1], 'rc': f'probe failed ({p.returncode})',
                    'stderr': p.stderr[-300:], 'imported': ['?']} for b in bags]
        for (lab, path, mods, typ), r in zip(bags, res):
            norm = typ if typ.count('/') == 2 else typ.replace('/', '/msg/')
            ok = (r['rc'] == 2 and not r['imported'] and norm in r['stderr'] and
                  'Traceback' not in r['stderr'] and 'Beautiful is better' not in
                  r['stderr'] + p.stdout)
            rows.append({'entry': mode, 'bag': lab, 'rc': r['rc'], 'imported': r['imported'],
                         'message': r['stderr'].splitlines()[0] if r['stderr'] else '',
                         'ok': ok})
        log(f'bags via {mode}: {len(res)} in {dt:.1f} s')
    return {'rows': rows}

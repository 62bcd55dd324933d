"""
The soak's memory tracing, its report's growth figure, the benchmarks' one entry point.

``online.memtrace``, ``bench/soak_live.py`` and ``python -m bench`` (bench/__main__.py).

Traced only where ``DGP_TRACEMALLOC`` asks: a process that grows a list writes lines whose top
grower is that list's line; without the variable nothing is started.
"""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                'bench'))

from dgp_ros.online import memtrace  # noqa: E402

import soak_live  # noqa: E402,I100

GROWER = """
import time
from dgp_ros.online.memtrace import start_from_env
start_from_env('probe')
keep = []
t0 = time.time()
while time.time() - t0 < 2.2:
    keep.append(bytearray(20000))      # the grower
    time.sleep(0.01)
"""


HEAP = """
import sys, threading
import numpy as np
from dgp_ros.online import memtrace
if sys.argv[1] == 'bound' and not memtrace.bound_heap():
    print('nan')
    sys.exit(0)
def anon():
    with open('/proc/self/smaps_rollup') as f:
        return next(int(x.split()[1]) for x in f if x.startswith('Anonymous:')) / 1024.0
before = anon()
np.ones(3 << 20).sum()              # a 24 MiB block freed: glibc's threshold follows it up
def work(seed):
    rng, keep = np.random.default_rng(seed), []
    for _ in range(80):
        a = np.ones(int(rng.integers(1 << 17, 1 << 21)))    # 1-16 MiB, in the thread's arena
        keep.append(np.ones(64))                             # a small survivor after each
        del a
threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
[t.start() for t in threads]
[t.join() for t in threads]
memtrace.trim()
print(anon() - before)
"""


@pytest.mark.skipif(not os.path.exists('/proc/self/smaps_rollup'), reason='no /proc smaps')
def test_a_bounded_heap_hands_back_what_threads_freed():
    # two threads allocate and free 160 blocks of 1-16 MiB, each leaving a small survivor:
    # in their arenas (glibc's default) the freed blocks stay resident, trimmed or not
    grew = {m: float(subprocess.run([sys.executable, '-c', HEAP, m], capture_output=True,
                                    text=True, check=True, timeout=60).stdout)
            for m in ('free', 'bound')}
    if np.isnan(grew['bound']):
        pytest.skip('not glibc: nothing to bound')
    assert grew['free'] > 20.0 and grew['bound'] < 5.0, grew       # MiB


def test_a_growing_process_names_its_grower(tmp_path):
    env = dict(os.environ, DGP_TRACEMALLOC=str(tmp_path / 'trace'), DGP_TRACEMALLOC_S='0.5')
    subprocess.run([sys.executable, '-c', GROWER], env=env, check=True, timeout=60)
    files = [p for p in os.listdir(tmp_path) if p.startswith('trace.probe.')]
    assert len(files) == 1, files
    lines = [json.loads(x) for x in (tmp_path / files[0]).read_text().splitlines()]
    assert len(lines) >= 2 and lines[-1]['role'] == 'probe'
    where, kib, count = lines[-1]['top'][0]
    assert where == '<string>:8' and kib > 500 and count > 20, lines[-1]
    assert lines[-1]['traced_mib'] > lines[0]['traced_mib']


def test_nothing_is_traced_without_the_variable(monkeypatch):
    monkeypatch.delenv(memtrace.ENV, raising=False)
    assert memtrace.start_from_env('x') is None


def test_the_growth_over_the_last_minutes():
    t = np.arange(0.0, 3600.0, 60.0)
    flat = [{'t': x, 'node': 200.0 + 0.1 * (i % 2)} for i, x in enumerate(t)]
    rng, slope = soak_live.growth(flat, 'node', 2400.0)
    assert abs(rng - 0.1) < 1e-9 and abs(slope) < 0.2
    rising = [{'t': x, 'node': 200.0 + x / 3600.0 * 12.0} for x in t]
    rng, slope = soak_live.growth(rising, 'node', 2400.0)
    assert 7.5 < rng < 8.5 and abs(slope - 12.0) < 1e-6


def test_one_entry_point_lists_and_runs_the_benchmarks():
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run([sys.executable, '-m', 'bench', '--list'], cwd=repo,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0
    names = [line.split()[0] for line in out.stdout.splitlines() if line.startswith('  ')]
    assert {'ledger', 'robot_family', 'soak_live', 'a320_family'} <= set(names)
    assert 'common' not in names and 'live_procs' not in names
    bad = subprocess.run([sys.executable, '-m', 'bench', 'nosuch'], cwd=repo,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and '--list' in bad.stderr


TRIM = """
import numpy as np
from dgp_ros.online import memtrace
def rss():
    for line in open('/proc/self/status'):
        if line.startswith('VmRSS'):
            return int(line.split()[1]) / 1024
big, small = [], []
for i in range(3000):                   # arrays freed between arrays kept: holes in the heap
    big.append(np.ones(12000))
    small.append(np.ones(100))
del big
before = rss()
ok = memtrace.trim()
print(ok, before, rss())
"""


def test_the_freed_heap_goes_back_to_the_system():
    out = subprocess.run([sys.executable, '-c', TRIM], capture_output=True, text=True,
                         timeout=60, check=True).stdout.split()
    ok, before, after = out[0] == 'True', float(out[1]), float(out[2])
    if not ok:
        import pytest
        pytest.skip('no glibc malloc_trim here')
    assert before > 250.0 and after < before - 150.0, (before, after)     # MB

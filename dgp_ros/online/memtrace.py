"""
Memory tracing for long runs: tracemalloc's top growers every period, where the environment asks.

A soak (``bench/soak_live.py``) starts the node with ``DGP_TRACEMALLOC=PREFIX``; the node's
process and its learner process (which inherits the environment) then each write one JSON line
every ``DGP_TRACEMALLOC_S`` seconds (60) to ``PREFIX.<role>.<pid>.jsonl``: the traced total
(MiB) and the ten source lines whose allocations grew most since the first period ended (the
warm-up: imports, the first model). Without the variable nothing is traced and nothing runs.
Tracing costs every allocation a few microseconds; the soak's RSS figures are taken without it.
Pure standard library (no rclpy).
"""
from __future__ import annotations

import json
import os
import threading
import time
import tracemalloc
from typing import Optional

__all__ = ['start_from_env', 'ENV', 'PERIOD_ENV']

ENV = 'DGP_TRACEMALLOC'
PERIOD_ENV = 'DGP_TRACEMALLOC_S'
#: source lines listed per period
TOP = 10


def start_from_env(role: str) -> Optional[threading.Thread]:
    """Start tracing in this process if ``DGP_TRACEMALLOC`` is set; the writer thread or None."""
    prefix = os.environ.get(ENV, '')
    if not prefix:
        return None
    try:
        period = max(float(os.environ.get(PERIOD_ENV, '60')), 0.5)
    except ValueError:
        period = 60.0
    path = f'{prefix}.{role}.{os.getpid()}.jsonl'
    tracemalloc.start(1)
    th = threading.Thread(target=_write, args=(path, role, period), name='dgp_memtrace',
                          daemon=True)
    th.start()
    return th


def _filtered(snap):
    return snap.filter_traces((tracemalloc.Filter(False, tracemalloc.__file__),
                               tracemalloc.Filter(False, '<frozen importlib._bootstrap>'),
                               tracemalloc.Filter(False, __file__)))


def _write(path: str, role: str, period: float) -> None:
    """Every ``period`` s, one line: the traced MiB and the top growers since the first."""
    t0 = time.time()
    time.sleep(period)
    base = _filtered(tracemalloc.take_snapshot())
    while True:
        time.sleep(period)
        snap = _filtered(tracemalloc.take_snapshot())
        top = snap.compare_to(base, 'lineno')[:TOP]
        line = {'t': round(time.time() - t0, 1), 'role': role,
                'traced_mib': round(tracemalloc.get_traced_memory()[0] / 2 ** 20, 3),
                'top': [[f'{s.traceback[0].filename}:{s.traceback[0].lineno}',
                         round(s.size_diff / 1024, 1), s.count_diff] for s in top]}
        with open(path, 'a') as f:
            f.write(json.dumps(line) + '\n')

"""
Memory over long runs: the heap handed back (``trim``), tracemalloc's top growers where asked.

``trim()`` asks glibc to return the freed heap to the system (``malloc_trim``): the learner
allocates and frees arrays of every size with each refit, proof and save, and glibc keeps what
it freed for reuse, so the resident memory of a learner process rose in steps over an hour
(251 -> 273 MB at 1 kHz) while the memory Python and numpy held stayed flat (26-31 MiB traced).
The learner process calls it every ``TRIM_PERIOD_S`` (``online.child``); where there is no glibc
it does nothing.

``bound_heap()`` keeps what trimming cannot return from piling up: glibc serves an allocation
below its mmap threshold from the calling thread's arena, and raises that threshold (up to
32 MiB) each time a larger block is freed, so after the first big free the Gram matrices and
copies of the learner's refit and rebase threads (0.1-30 MB each) come from their arenas,
which fragment and hold their high-water mark: the learner's anonymous memory rose in arenas of
those threads (two of 16 and 25 MiB after 25 minutes at 1 kHz) while its main heap stayed at
39 MiB. A fixed threshold of ``MMAP_THRESHOLD`` bytes sends every block as large as that to
its own mapping, returned when freed. The learner process sets it at its start.

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

__all__ = ['start_from_env', 'trim', 'bound_heap', 'ENV', 'PERIOD_ENV', 'TRIM_PERIOD_S',
           'MMAP_THRESHOLD']

ENV = 'DGP_TRACEMALLOC'
PERIOD_ENV = 'DGP_TRACEMALLOC_S'
#: source lines listed per period
TOP = 10
#: how often the learner process hands the freed heap back (s)
TRIM_PERIOD_S = 30.0
#: blocks of this many bytes or more get a mapping of their own (glibc's M_MMAP_THRESHOLD)
MMAP_THRESHOLD = 1 << 20
_M_MMAP_THRESHOLD = -3
_LIBC = {}


def _libc(name: str):
    """Return glibc's function ``name``, or None where there is none (another C library)."""
    if name not in _LIBC:
        try:
            import ctypes
            _LIBC[name] = getattr(ctypes.CDLL('libc.so.6'), name)
        except (OSError, AttributeError):
            _LIBC[name] = None
    return _LIBC[name]


def trim() -> bool:
    """Return the freed heap to the system (glibc malloc_trim); False where there is none."""
    fn = _libc('malloc_trim')
    return bool(fn is not None and fn(0) >= 0)


def bound_heap(threshold: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes (module docstring); False: not glibc."""
    fn = _libc('mallopt')
    return bool(fn is not None and fn(_M_MMAP_THRESHOLD, int(threshold)) == 1)


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

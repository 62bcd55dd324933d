"""
CPU accounting of process trees from /proc, for bench/arm_live.py.

``CpuWatch`` samples, while a run lasts, the CPU time of the benchmark's own process trees and
the machine's busy time (``/proc/stat``), so that a run's numbers come with the CPU the machine
spent elsewhere (other jobs on the shared cores).
"""
from __future__ import annotations

import os
import threading
import time
from typing import Dict, List


CLK = os.sysconf('SC_CLK_TCK')


def proc_stat(path: str):
    """(command name, ppid, user + system CPU seconds) of a /proc stat file; None once gone."""
    try:
        with open(path) as f:
            s = f.read()
    except OSError:
        return None
    rest = s[s.rfind(')') + 2:].split()
    return s[s.find('(') + 1:s.rfind(')')], int(rest[1]), (int(rest[11]) + int(rest[12])) / CLK


def proc_table():
    """{pid: (ppid, cpu seconds)} of every process now."""
    out = {}
    for d in os.listdir('/proc'):
        st = proc_stat(f'/proc/{d}/stat') if d.isdigit() else None
        if st:
            out[int(d)] = st[1:]
    return out


def machine_busy() -> float:
    with open('/proc/stat') as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return (sum(v) - v[3] - v[4]) / CLK


def descendants(table, root) -> List[int]:
    kids: Dict[int, list] = {}
    for pid, (ppid, _) in table.items():
        kids.setdefault(ppid, []).append(pid)
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        for k in kids.get(p, ()):
            out.append(k)
            todo.append(k)
    return out


def learner_pids(est_pid: int) -> List[int]:
    """Return the estimator's learner processes: the children of its fork server."""
    table = proc_table()
    out = []
    for pid in descendants(table, est_pid):
        try:
            cmd = open(f'/proc/{pid}/cmdline', 'rb').read()
        except OSError:
            continue
        if b'forkserver' in cmd:
            out.extend(descendants(table, pid))
    return out


class CpuWatch:
    """
    CPU of this benchmark's processes and of the machine over a window (sampled every 0.25 s).

    ``report()``: background cores (the machine's busy time minus ours, over the wall time), and
    per tracked process (``track``): its own CPU seconds (``cpu_NAME_s``) and its descendants'
    (``cpu_NAME_kids_s``) within the window. A process that ended between two samples loses at
    most its last 0.25 s.
    """

    def __init__(self):
        self.seen: Dict[int, float] = {}
        self.first: Dict[int, float] = {}
        self.roots: Dict[str, int] = {}
        self.kids: Dict[str, set] = {}
        self._stop = threading.Event()
        self._t = None

    def track(self, name: str, pid: int) -> None:
        self.roots[name] = pid
        self.kids.setdefault(name, set())

    def start(self) -> None:
        self.b0, self.w0 = machine_busy(), time.monotonic()
        self._sample(first=True)
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _sample(self, first: bool = False) -> None:
        table = proc_table()
        me = os.getpid()
        for name, root in self.roots.items():
            self.kids[name].update(descendants(table, root))
        for pid in set(descendants(table, me)) | {me}:
            cpu = table[pid][1]
            if pid not in self.first:
                self.first[pid] = cpu if first else 0.0     # born during the window: from 0
            self.seen[pid] = max(self.seen.get(pid, 0.0), cpu)

    def _run(self) -> None:
        while not self._stop.wait(0.25):
            self._sample()

    def report(self) -> dict:
        self._sample()
        self._stop.set()
        self._t.join()
        wall = time.monotonic() - self.w0
        busy = machine_busy() - self.b0

        def cpu(pids):
            return sum(self.seen.get(p, 0.0) - self.first.get(p, 0.0) for p in pids)
        ours = cpu(self.seen)
        out = {'wall_s': wall, 'bg_cores': max(0.0, (busy - ours) / wall),
               'machine_cores': busy / wall, 'ours_cores': ours / wall,
               'load': os.getloadavg()[0]}
        for name, root in self.roots.items():
            out[f'cpu_{name}_s'] = cpu([root])
            out[f'cpu_{name}_kids_s'] = cpu(self.kids[name])
        return out

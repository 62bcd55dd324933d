"""
One entry point for the benchmarks: ``python -m bench NAME [--quick] [options]``.

    python -m bench --list                 # every benchmark and its first docstring line
    python -m bench robot_family --quick   # one, with its own options (NAME --help)
    python -m bench --all --quick          # every one in turn, each in its own process

Each benchmark is a script of this folder with a ``main(argv)`` that writes its section of
docs/BENCHMARKS.md (and its plots in docs/bench/); the helper modules (``common``,
``cpu_watch``, ...) and the process roles of the live benchmarks are not listed. ``--all``
runs them in name order, prints each one's exit status and wall time, and exits 1 if any failed.
"""
from __future__ import annotations

import ast
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
#: scripts with a main that are parts of another benchmark, not benchmarks of their own
PARTS = ('live_procs',)


def benchmarks() -> dict:
    """Return {name: the first line of its docstring} of every benchmark script."""
    out = {}
    for f in sorted(os.listdir(HERE)):
        if not f.endswith('.py') or f.startswith('_') or f[:-3] in PARTS:
            continue
        tree = ast.parse(open(os.path.join(HERE, f)).read())
        if any(isinstance(n, ast.FunctionDef) and n.name == 'main' for n in tree.body):
            doc = (ast.get_docstring(tree) or '').strip().splitlines()
            out[f[:-3]] = doc[0] if doc else ''
    return out


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    known = benchmarks()
    if not argv or argv[0] in ('-h', '--help', '--list'):
        print(__doc__.strip().split('\n\n')[0] + '\n')
        for name, doc in known.items():
            print(f'  {name:22s} {doc}')
        return 0
    if argv[0] == '--all':
        failed = 0
        for name in known:
            t0 = time.perf_counter()
            rc = subprocess.call([sys.executable, os.path.join(HERE, name + '.py')] + argv[1:])
            failed += rc != 0
            print(f'[bench] {name}: exit {rc}, {time.perf_counter() - t0:.0f} s', flush=True)
        return 1 if failed else 0
    name = argv[0][:-3] if argv[0].endswith('.py') else argv[0]
    if name not in known:
        print(f'no benchmark {name!r}; python -m bench --list shows them', file=sys.stderr)
        return 2
    sys.argv = [os.path.join(HERE, name + '.py')] + argv[1:]
    sys.path.insert(0, HERE)
    import runpy
    try:
        runpy.run_path(sys.argv[0], run_name='__main__')
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


if __name__ == '__main__':
    sys.exit(main())

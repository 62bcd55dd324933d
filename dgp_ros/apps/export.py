"""
``dgp-export``: a frozen model as one header-only C++17 file for a real-time controller.

::

    dgp-export MODEL.npz --cpp OUT.hpp [--namespace NAME] [--joints a,b,c] [--no-correction]

``MODEL.npz`` is read as the frozen node reads its ``model_path`` (``learning:=false``): loaded,
its certificate proven again (never taken from the file), then written with every constant
baked in (``dgp_ros.export.export_cpp``; what each generated function equals:
docs/CONTRACTS.md, "dgp_ros.export"). Prints one line: the header, its size, the guarantee it
carries and how long the export took.

Exit status: 0 on success, 2 for a model that cannot be exported or a bad argument (one-line
message saying why and what to do, no traceback).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

__all__ = ['main']


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter, prog='dgp-export',
        description='Write a frozen dgp_ros model as one self-contained, header-only C++17 file '
                    '(no Python, no allocation, noexcept) that answers as the frozen node '
                    '(learning:=false model_path:=MODEL) would.')
    ap.add_argument('model', help='model file (.npz) saved by the estimator, dgp-replay '
                                  '--save-model or model.save()')
    ap.add_argument('--cpp', required=True, metavar='OUT.hpp', help='the header to write')
    ap.add_argument('--namespace', default='dgp_model',
                    help='C++ namespace of the generated functions (default dgp_model)')
    ap.add_argument('--joints', help="comma-separated joint names, in the model's order "
                                     '(default: the URDF joints of its correction, else '
                                     'joint_1..N)')
    ap.add_argument('--no-correction', action='store_true',
                    help='leave the correction and offsets out: friction() is the damping '
                         'force alone')
    a = ap.parse_args(argv)
    from dgp_ros.export import export_cpp, ExportError
    names = [s.strip() for s in a.joints.split(',')] if a.joints else None
    t0 = time.perf_counter()
    try:
        if not os.path.isfile(a.model):
            raise ExportError(f'{a.model}: no such model file')
        text = export_cpp(a.model, a.cpp, namespace=a.namespace, names=names,
                          correction=not a.no_correction)
    except (ExportError, OSError) as exc:
        print(f'dgp-export: {exc}', file=sys.stderr)
        return 2
    guarantee = next((ln for ln in text.splitlines() if ln.startswith('// Guarantee:')), '')
    print(f'dgp-export: wrote {a.cpp} ({len(text.encode()) / 1024:.0f} KiB) in '
          f'{time.perf_counter() - t0:.1f} s; {guarantee[3:]}')
    return 0


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())

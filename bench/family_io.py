"""
What the family scripts (``a320_family.py``, ``dgp_family.py``) share: options, tags, outputs.

They run the ``dgp_ros`` on ``PYTHONPATH`` (another checkout's, to compare commits), so this
module leaves ``sys.path`` alone (``common`` puts this checkout first: it is imported only to
write the section of docs/BENCHMARKS.md). Each writes ``OUT/<name>_<tag>.md`` and ``.json``
(tag: the short commit of the imported dgp_ros, and the ``--set`` parameters).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


def fmt(x, digits: int = 2) -> str:
    """Format a number for a table cell: '-' for None, 3 significant digits or scientific."""
    if x is None:
        return '-'
    x = float(x)
    if not math.isfinite(x):
        return str(x)
    if x == 0:
        return '0'
    if 1e-2 <= abs(x) < 1e3:
        return f'{x:.{digits + 1}g}'
    return f'{x:.{digits - 1}e}'


def per_out(v) -> str:
    """Format numbers per output as 'a / b / c' ('-' for None)."""
    return '-' if v is None else ' / '.join(fmt(x) for x in v)


def nmse(p, r):
    """Return the NMSE per output of predictions p against r, (k, N) each -> (N,)."""
    return ((p - r) ** 2).mean(axis=0) / r.var(axis=0)


def windows(P, T, t, var=None, first: int = 0, width_s: float = 1.0):
    """
    NMSE per output of every ``width_s`` window from window ``first`` on; (starts, (W, N)).

    Over ``var`` (default: the variance of all of ``T``); windows of fewer than 10 samples skipped.
    """
    var = T.var(axis=0) if var is None else var
    starts, out = [], []
    for w in range(first, int((t[-1] - t[0]) // width_s) + 1):
        s = (t >= t[0] + w * width_s) & (t < t[0] + (w + 1) * width_s)
        if s.sum() >= 10:
            starts.append(w * width_s)
            out.append(((P[s] - T[s]) ** 2).mean(axis=0) / var)
    return np.array(starts), np.array(out)


def course_point(est, t: float, course: list) -> None:
    """Append the estimator's elements and structure at ``t`` to ``course`` when they changed."""
    d = est.diagnostics()
    if not course or (d.get('elements'), d.get('structure')) != (course[-1]['elements'],
                                                                 course[-1]['structure']):
        course.append({'t': float(t), 'elements': d.get('elements'),
                       'structure': d.get('structure'),
                       'elements_scores': d.get('elements_scores'),
                       'refits_ok': d.get('refits_ok')})


def course_text(course: list) -> str:
    """Return a ``course`` (``course_point``'s list) as text: 't s: elements [structure]; ...'."""
    return '; '.join(f'{c["t"]:.0f} s: {c["elements"]} [{c["structure"]}]' for c in course)


def jsonable(x):
    """Return ``x`` with numpy values as plain ones, non-finite floats as None (json.dump)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def parser(doc: str, section: str, quick_help: str = 'a smoke run'):
    """Return an ArgumentParser with --quick, --out, --section, --tag and --set."""
    ap = argparse.ArgumentParser(description=doc.split('\n')[1])
    ap.add_argument('--quick', action='store_true', help=quick_help)
    ap.add_argument('--out', default=os.path.join(REPO, 'out', 'families'),
                    help='where the .md and .json go (default: out/families)')
    ap.add_argument('--section', action='store_true',
                    help=f"also write the report into docs/BENCHMARKS.md (section '{section}')")
    ap.add_argument('--tag', default='')
    ap.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                    help='an estimator parameter besides the defaults (diagnosis only; the '
                         'value is read as JSON, else as text), e.g. --set elements=all')
    return ap


def parse(ap, argv, params: dict):
    """Parse argv, put every ``--set NAME=VALUE`` into params; return (options, tag, where)."""
    a = ap.parse_args(argv)
    for kv in a.set:
        k, v = kv.split('=', 1)
        try:
            params[k] = json.loads(v)
        except ValueError:
            params[k] = v
    return (a,) + tag_and_where(a.tag, params)


def _commit_of(module_file: str) -> str:
    root = os.path.dirname(os.path.dirname(os.path.abspath(module_file)))
    try:
        return subprocess.run(['git', '-C', root, 'rev-parse', '--short', 'HEAD'],
                              capture_output=True, text=True, check=True).stdout.strip()
    except Exception:                                # noqa: BLE001
        return '?'


def tag_and_where(tag: str, params: dict):
    """
    Return (tag, where) of the imported ``dgp_ros``.

    tag: ``tag`` if given, else its short commit and the ``params`` besides the defaults;
    where: its directory (relative to this checkout when it is this checkout's).
    """
    import dgp_ros
    tag = tag or _commit_of(dgp_ros.__file__) + ''.join(
        f'_{k}-{v}' for k, v in sorted(params.items()))
    where = os.path.dirname(dgp_ros.__file__)
    if where.startswith(REPO + os.sep):
        where = os.path.relpath(where, REPO)      # this checkout's: no machine path
    return tag, where


def write(base: str, payload: dict, md: str, section, quick: bool, wall: float,
          script: str) -> None:
    """
    Write ``base.json`` (``payload``) and ``base.md`` (``md``), and print the report.

    ``section``: also write ``md`` (its title as the section's header) into docs/BENCHMARKS.md
    under that name; None: not. ``script``: the generating script's file name.
    """
    with open(base + '.json', 'w') as f:
        json.dump(jsonable(payload), f, indent=1)
    with open(base + '.md', 'w') as f:
        f.write(md)
    print(md)
    print(f'wrote {base}.md/.json')
    if section:
        sys.path.insert(0, HERE)
        import common as C
        title, rest = md.split('\n', 1)
        body = C.header_lines(title.lstrip('# '), f'bench/{os.path.basename(script)}',
                              quick, wall) + rest
        print('wrote', C.write_section(os.path.join(REPO, 'docs'), section, body))

"""
Smoke test of bench/certification.py --quick (into a tmp dir; speed is never asserted here).

It runs with the real Panda log where the shared folder has it and says so where it does not;
either way the A320 part runs, and every model it reports has 0 violations. Marked ``slow`` (a
benchmark run): ``bash scripts/run_tests.sh -m slow``.
"""
import os
import re
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BENCH = os.path.join(REPO, 'bench')


@pytest.mark.slow
def test_certification_quick(tmp_path):
    r = subprocess.run([sys.executable, os.path.join(BENCH, 'certification.py'), '--quick',
                        '--out', str(tmp_path)], cwd=REPO, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-4000:]
    assert r.stdout == ''
    text = (tmp_path / 'BENCHMARKS.md').read_text()
    i, j = text.find('<!-- BEGIN certification -->'), text.find('<!-- END certification -->')
    assert 0 <= i < j
    s = text[i:j]
    assert 'quick mode' in s and 'A320 envelope' in s
    sys.path.insert(0, BENCH)
    import certification
    real = certification.panda_dir() is not None
    if not real:
        assert 'Skipped: `panda_log_train.npz` not found' in s
    else:
        assert '| friction+stribeck, bias True | 100 | Full-D-GP |' in s
    row = [ln for ln in s.splitlines() if ln.startswith('| 0 violations')]
    assert len(row) == 1 and '| met |' in row[0], row
    n_models = int(re.search(r'(\d+) in (\d+) models', row[0]).group(2))
    assert n_models == (4 if real else 2)          # Full and Diag of each data set

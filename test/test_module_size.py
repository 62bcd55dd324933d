"""
No module of the package or of the benchmarks is longer than ``MAX_LINES``: a longer one is split.

Along a seam: ``dgp_ros/apps/replay.py`` and ``replay_report.py`` are the replay engine and CLI,
and the files it writes; ``bench/hostile.py`` is the command and ``bench/attacks/`` one module
per attack surface.
"""
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 500
PACKAGES = ('dgp_ros', 'sim_bridge', 'bench')


def long_modules(root: Path, packages=PACKAGES, limit: int = MAX_LINES) -> dict:
    """Return ``{path relative to root: lines}`` of the modules longer than ``limit`` lines."""
    out = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob('*.py')):
            n = len(f.read_text(encoding='utf-8').splitlines())
            if n > limit:
                out[str(f.relative_to(root))] = n
    return out


@pytest.mark.linter
def test_no_module_is_longer_than_the_limit():
    assert len(list((ROOT / 'dgp_ros').rglob('*.py'))) > 20
    assert len(list((ROOT / 'bench').rglob('*.py'))) > 10
    assert long_modules(ROOT) == {}


def test_the_check_finds_a_long_module(tmp_path):
    (tmp_path / 'pkg').mkdir()
    (tmp_path / 'pkg' / 'short.py').write_text('x = 1\n' * MAX_LINES)
    (tmp_path / 'pkg' / 'long.py').write_text('x = 1\n' * (MAX_LINES + 1))
    assert long_modules(tmp_path, ('pkg',)) == {'pkg/long.py': MAX_LINES + 1}

"""
The ament_python linter tests (flake8 and pep257), as a ROS 2 package template runs them.

Both linters check the package's Python sources with ament's defaults: ament_flake8 reads
its default configuration plus ``application-import-names`` from setup.cfg's ``[flake8]``
section (see the comment there), ament_pep257 uses the ``ament`` convention. There is no
copyright test: the sources carry no license headers.
"""
import configparser
import os

from ament_flake8.main import main_with_errors
from ament_pep257.main import main
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PATHS = ['dgp_ros', 'sim_bridge', 'bench', 'test', 'launch', 'setup.py']


# flake8-import-order 0.18.2 still imports pkg_resources
@pytest.mark.filterwarnings('ignore:pkg_resources is deprecated:DeprecationWarning')
@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch, tmp_path):
    """
    flake8 over every path with setup.cfg's ``[flake8]`` section, in one process.

    ``jobs = 1`` is the only addition: the suite's xdist workers already fill the cores, and
    flake8's own processes cost 6 CPU-s more over the same files (39 against 33).
    """
    monkeypatch.chdir(ROOT)
    cfg = configparser.RawConfigParser()
    cfg.read(os.path.join(ROOT, 'setup.cfg'))
    one = configparser.RawConfigParser()
    one['flake8'] = dict(cfg['flake8'], jobs='1')
    config = tmp_path / 'flake8.cfg'
    with open(config, 'w') as f:
        one.write(f)
    rc, errors = main_with_errors(argv=['--config', str(config)] + PATHS)
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + \
        '\n'.join(errors)


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257(monkeypatch):
    monkeypatch.chdir(ROOT)
    rc = main(argv=PATHS)
    assert rc == 0, 'Found code style errors / warnings'

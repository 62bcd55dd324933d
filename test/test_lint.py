"""
The ament_python linter tests (flake8 and pep257), as a ROS 2 package template runs them.

Both linters check the package's Python sources with ament's defaults: ament_flake8 reads
its default configuration plus ``application-import-names`` from setup.cfg's ``[flake8]``
section (see the comment there), ament_pep257 uses the ``ament`` convention. There is no
copyright test: the sources carry no license headers.
"""
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
def test_flake8(monkeypatch):
    monkeypatch.chdir(ROOT)
    rc, errors = main_with_errors(
        argv=['--config', os.path.join(ROOT, 'setup.cfg')] + PATHS)
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + \
        '\n'.join(errors)


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257(monkeypatch):
    monkeypatch.chdir(ROOT)
    rc = main(argv=PATHS)
    assert rc == 0, 'Found code style errors / warnings'

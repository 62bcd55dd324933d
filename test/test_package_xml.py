"""
package.xml declares what the code imports: ``rosdep install`` in a Jazzy workspace brings it.

Every third-party module imported by the installed packages (``dgp_ros``, ``sim_bridge``) and
the launch files maps to a dependency of package.xml, or is one of the PyPI-only modules the
README names (``PIP_ONLY``: no rosdep key). A new import without its dependency fails here, as
does the check on a bad example.
"""
import ast
from pathlib import Path
import sys
import xml.etree.ElementTree as ET

ROOT = Path(__file__).resolve().parents[1]
#: import name -> rosdep key, where they differ
KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'matplotlib': 'python3-matplotlib',
        'yaml': 'python3-yaml'}
#: from PyPI only (the README's workspace install says so)
PIP_ONLY = {'jsbsim', 'rosbags'}


def imports(paths) -> set:
    """Return the top-level names the Python files under ``paths`` import (absolute only)."""
    out = set()
    for base in paths:
        for f in Path(base).rglob('*.py'):
            for node in ast.walk(ast.parse(f.read_text(encoding='utf-8'))):
                if isinstance(node, ast.Import):
                    out |= {a.name.split('.')[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    out.add(node.module.split('.')[0])
    return out


def missing(names: set, deps: set, own=('dgp_ros', 'sim_bridge')) -> list:
    """Return the third-party ``names`` no dependency in ``deps`` covers."""
    third = {n for n in names if n not in sys.stdlib_module_names and n not in own}
    return sorted(n for n in third if KEYS.get(n, n) not in deps and n not in PIP_ONLY)


def declared(xml: Path) -> set:
    root = ET.parse(xml).getroot()
    return {e.text.strip() for e in root if e.tag.endswith('depend') and e.text}


def test_every_import_is_a_dependency_of_package_xml():
    names = imports([ROOT / 'dgp_ros', ROOT / 'sim_bridge', ROOT / 'launch'])
    assert {'numpy', 'rclpy', 'pinocchio'} <= names          # the walk found the code
    assert missing(names, declared(ROOT / 'package.xml')) == []


def test_the_pip_only_modules_are_named_in_the_readme():
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    assert f'pip install {" ".join(sorted(PIP_ONLY))}' in text


def test_the_check_finds_an_undeclared_import(tmp_path):
    (tmp_path / 'm.py').write_text('import os\nimport numpy as np\nfrom torch import nn\n'
                                   'from . import x\nimport jsbsim\n')
    assert missing(imports([tmp_path]), {'python3-numpy'}) == ['torch']

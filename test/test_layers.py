"""
The package's rooms keep their rules (docs/ARCHITECTURE.md, "Layers"), read from the sources.

Every ``import`` and ``from ... import`` of every module is read with ``ast`` (relative imports
resolved, imports inside functions included; an ``importlib`` call by a name computed at run
time is not an import and is not seen):

* the layers below the nodes import no ROS: no module of ``dgp_ros/gp``, ``dynamics``,
  ``online`` or ``bags`` (nor ``msgs``) imports rclpy or a ROS interface
  package (``rosidl*``, ``*_msgs``, ``*_srvs``, ...), except ``bags/ros.py`` and
  ``bags/cli.py`` (the rclpy player and recorder, and their command line);
* the GP numerics stand alone: ``dgp_ros/gp`` imports nothing from the rest of the package;
* no import circles among the modules of ``dgp_ros`` and ``sim_bridge``: no strongly connected
  component of the import graph has two modules or more;
* the online learner's rooms keep their order: a module of ``dgp_ros/online/<room>`` imports
  only its own room and the ones before it (``ONLINE_ROOMS``), a module at ``online/``'s top
  (``config``, ``memtrace``) no room; the package's ``__init__`` (the public names) may import
  any.

Each check is a function of a source tree and is also run on a planted violation, so that a
check that can no longer fail is noticed.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ('dgp_ros', 'sim_bridge')
#: the layers that must import no ROS (folders, or single modules: the message converter and
#: the CDR codec under the nodes), and the modules of them that may (rclpy on purpose)
NO_ROS = ('dgp_ros/gp', 'dgp_ros/dynamics', 'dgp_ros/online', 'dgp_ros/bags',
          'dgp_ros/msgs')
ROS_ALLOWED = ('dgp_ros/bags/ros.py', 'dgp_ros/bags/cli.py')
#: ROS packages by exact top-level name; and by prefix or suffix of it
ROS_NAMES = ('rclpy', 'launch_ros', 'ament_index_python', 'message_filters', 'tf2_ros')
ROS_PREFIXES = ('rclpy', 'rosidl', 'rmw')
ROS_SUFFIXES = ('_msgs', '_srvs', '_interfaces')
#: the online learner's rooms by who runs the code, in order (docs/ARCHITECTURE.md, "Layers"):
#: what replaces the served model, the learner's state, the learner process, the message path
ONLINE, ONLINE_ROOMS = 'dgp_ros.online', ('jobs', 'learner', 'process', 'path')


# ----------------------------------------------------------------------------- reading
def module_name(root: Path, path: Path) -> str:
    """Return the dotted name of the module at ``path`` (a package's ``__init__``: the package)."""
    parts = list(path.relative_to(root).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def imports(root: Path, path: Path) -> list:
    """
    Return every module name ``path`` imports, absolute, anywhere in the file.

    ``from X import Y`` gives ``X.Y`` as well as ``X`` (Y may be a module); relative imports are
    resolved against the module's own package.
    """
    name = module_name(root, path)
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'), str(path))):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[:len(base) - (node.level - 1)]
                mod = '.'.join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ''
            out.append(mod)
            out += [f'{mod}.{a.name}' for a in node.names if a.name != '*']
    return out


def sources(root: Path, packages=PACKAGES) -> dict:
    """Return ``{module name: path}`` of every module of ``packages`` under ``root``."""
    return {module_name(root, p): p
            for pkg in packages for p in sorted((root / pkg).rglob('*.py'))}


# ----------------------------------------------------------------------------- the checks
def is_ros(module: str) -> bool:
    """Tell whether ``module`` belongs to ROS (rclpy, an interface package, ...)."""
    top = module.split('.')[0]
    return top in ROS_NAMES or top.startswith(ROS_PREFIXES) or top.endswith(ROS_SUFFIXES)


def ros_imports(root: Path, layers=NO_ROS, allowed=ROS_ALLOWED) -> dict:
    """Return ``{path: [ROS modules]}`` of the modules under ``layers`` that import ROS."""
    bad = {}
    for layer in layers:
        where = root / layer
        for p in [where] if where.suffix == '.py' else sorted(where.rglob('*.py')):
            rel = p.relative_to(root).as_posix()
            if rel in allowed:
                continue
            found = sorted({m for m in imports(root, p) if is_ros(m)})
            if found:
                bad[rel] = found
    return bad


def outward_imports(root: Path, inner: str = 'dgp_ros.gp', top: str = 'dgp_ros') -> dict:
    """Return ``{module: [targets]}``: modules of ``inner`` that import ``top`` outside it."""
    bad = {}
    for name, p in sources(root, (inner.replace('.', '/'),)).items():
        out = sorted({m for m in imports(root, p)
                      if (m == top or m.startswith(top + '.')) and
                      not (m == inner or m.startswith(inner + '.'))})
        if out:
            bad[name] = out
    return bad


def room_violations(root: Path, package: str = ONLINE, rooms=ONLINE_ROOMS) -> dict:
    """Return ``{module: [targets]}``: modules of ``package`` importing a room after their own."""
    def rank(name: str) -> int:                   # -1: the package's top modules
        first = name[len(package) + 1:].split('.')[0]
        return rooms.index(first) if first in rooms else -1

    bad = {}
    for name, p in sources(root, (package.replace('.', '/'),)).items():
        if name == package:
            continue
        out = sorted({m for m in imports(root, p) if m.startswith(package + '.') and
                      rank(m) > rank(name)})
        if out:
            bad[name] = out
    return bad


def import_graph(root: Path, packages=PACKAGES) -> dict:
    """Return ``{module: {modules of the packages it imports}}`` (named targets only)."""
    mods = sources(root, packages)
    return {name: {m for m in imports(root, p) if m in mods and m != name}
            for name, p in mods.items()}


def circles(graph: dict) -> list:
    """Return the strongly connected components of ``graph`` with two nodes or more (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


# ----------------------------------------------------------------------------- the package
def test_the_layers_below_the_nodes_import_no_ros():
    assert len(list((ROOT / 'dgp_ros' / 'online').rglob('*.py'))) > 10
    assert ros_imports(ROOT) == {}
    # the two that may, do: the check sees an rclpy import where there is one
    assert set(ros_imports(ROOT, allowed=())) == set(ROS_ALLOWED)


def test_gp_imports_nothing_from_the_rest_of_the_package():
    assert outward_imports(ROOT) == {}


def test_the_online_rooms_import_only_the_rooms_before_them():
    online = ROOT / 'dgp_ros' / 'online'
    rooms = [d.name for d in online.iterdir() if (d / '__init__.py').exists()]
    assert sorted(rooms) == sorted(ONLINE_ROOMS)
    assert room_violations(ROOT) == {}


def test_no_import_circles():
    graph = import_graph(ROOT)
    assert len(graph) > 60 and sum(map(len, graph.values())) > 100, 'graph implausibly small'
    assert circles(graph) == []


# ------------------------------------------------------------------------- the checks can fail
#: a small package with one violation of each rule (and near misses that are not violations)
PLANTED = {
    'pkg/__init__.py': '',
    'pkg/gp/__init__.py': 'from .core import x\n',
    'pkg/gp/core.py': 'import numpy\nx = 1\n\n\ndef later():\n    from ..dyn import model  # noqa\n',
    'pkg/gp/clean.py': 'from . import core\nfrom pkg.gp.core import x\n',
    'pkg/dyn/__init__.py': '',
    'pkg/dyn/model.py': 'def f():\n    import rclpy.node  # noqa\n'
                        '    from sensor_msgs.msg import JointState  # noqa\n',
    'pkg/dyn/allowed.py': 'from std_srvs.srv import Trigger\n',
    'pkg/dyn/fine.py': 'import rosbags.typesys\nimport msgs_helper\n',
    'pkg/a.py': 'from .b import y\nx = 1\n',
    'pkg/b.py': 'y = 2\n\n\ndef f():\n    from pkg import a  # noqa\n',
    'pkg/c.py': 'from pkg.a import x\n',
    'pkg/on/__init__.py': 'from .top import t\nfrom .late.m import z\n',
    'pkg/on/top.py': 't = 1\n',
    'pkg/on/early/__init__.py': '',
    'pkg/on/early/e.py': 'from ..top import t\n\n\ndef f():\n    from ..late import n  # noqa\n',
    'pkg/on/late/__init__.py': '',
    'pkg/on/late/m.py': 'from ..early.e import f\nfrom . import n\nz = 1\n',
    'pkg/on/late/n.py': '',
}


def _planted(root: Path) -> Path:
    for rel, text in PLANTED.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


def test_imports_are_read_anywhere_and_resolved(tmp_path):
    root = _planted(tmp_path)
    assert imports(root, root / 'pkg/gp/core.py') == ['numpy', 'pkg.dyn', 'pkg.dyn.model']
    assert imports(root, root / 'pkg/gp/__init__.py') == ['pkg.gp.core', 'pkg.gp.core.x']


def test_the_ros_check_finds_a_planted_rclpy_import(tmp_path):
    root = _planted(tmp_path)
    assert ros_imports(root, ('pkg/dyn', 'pkg/gp'), ('pkg/dyn/allowed.py',)) == {
        'pkg/dyn/model.py': ['rclpy.node', 'sensor_msgs.msg', 'sensor_msgs.msg.JointState']}
    # a single module as a layer
    assert ros_imports(root, ('pkg/dyn/model.py', 'pkg/a.py'), ()) == {
        'pkg/dyn/model.py': ['rclpy.node', 'sensor_msgs.msg', 'sensor_msgs.msg.JointState']}
    assert is_ros('rosidl_runtime_py') and is_ros('std_srvs.srv') and not is_ros('rosbags')


def test_the_gp_check_finds_a_planted_outward_import(tmp_path):
    root = _planted(tmp_path)
    assert outward_imports(root, 'pkg.gp', 'pkg') == {'pkg.gp.core': ['pkg.dyn', 'pkg.dyn.model']}


def test_the_rooms_check_finds_a_planted_import_of_a_later_room(tmp_path):
    root = _planted(tmp_path)
    # early imports late inside a function: found; late importing early, its own room, the top,
    # and the package's __init__ importing a room are not violations
    assert room_violations(root, 'pkg.on', ('early', 'late')) == {
        'pkg.on.early.e': ['pkg.on.late', 'pkg.on.late.n']}
    (root / 'pkg/on/top.py').write_text('from .early import e  # noqa\n')
    assert set(room_violations(root, 'pkg.on', ('early', 'late'))) == {
        'pkg.on.early.e', 'pkg.on.top'}


def test_the_circle_check_finds_a_planted_circle(tmp_path):
    graph = import_graph(_planted(tmp_path), ('pkg',))
    assert graph['pkg.gp.core'] == {'pkg.dyn', 'pkg.dyn.model'}
    assert circles(graph) == [['pkg.a', 'pkg.b']]
    assert circles({'x': {'y'}, 'y': {'z'}, 'z': {'x'}, 'w': {'x'}}) == [['x', 'y', 'z']]
    assert circles({'x': {'y'}, 'y': set()}) == []

"""
The online learner and message path are parts that own their state (issue 47).

Read from the source with ``ast``: no class of ``dgp_ros/online`` uses a private attribute
(``self._x``) that it does not define itself (or inherit from a class of its own module: no
mixin reads its host's state), no code reads another object's private attribute
(``other._x``), and the learner and the estimator have no base classes. The checker is shown to
catch each kind on a small example, so that a clean result means something.
"""
import ast
import os

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ONLINE = os.path.join(ROOT, 'dgp_ros', 'online')


def _private(name: str) -> bool:
    return name.startswith('_') and not name.startswith('__')


def _defined(cls: ast.ClassDef) -> set:
    """Names a class defines: methods, class attributes, attributes assigned on self/cls."""
    own = set()
    for node in cls.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            own.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            own |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
    for node in ast.walk(cls):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and \
                isinstance(node.value, ast.Name) and node.value.id in ('self', 'cls'):
            own.add(node.attr)
    return own


def violations(source: str, path: str = '<source>') -> list:
    """Return every use of a private attribute its code does not own, as text."""
    tree = ast.parse(source, path)
    classes = {c.name: c for c in ast.walk(tree) if isinstance(c, ast.ClassDef)}
    out = []
    for name, cls in classes.items():
        own = _defined(cls)
        for base in cls.bases:              # a base class of this module: its names are known
            if isinstance(base, ast.Name) and base.id in classes:
                own |= _defined(classes[base.id])
        for node in ast.walk(cls):
            if not (isinstance(node, ast.Attribute) and _private(node.attr)):
                continue
            v = node.value
            if isinstance(v, ast.Name) and v.id in ('self', 'cls'):
                if node.attr not in own:
                    out.append(f'{path}:{node.lineno}: {name} uses self.{node.attr}, '
                               'which it does not define')
            else:
                out.append(f'{path}:{node.lineno}: {name} reads '
                           f'{ast.unparse(v)}.{node.attr}')
    for fn in (n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))):
        for node in ast.walk(fn):
            if isinstance(node, ast.Attribute) and _private(node.attr):
                out.append(f'{path}:{node.lineno}: {fn.name} reads '
                           f'{ast.unparse(node.value)}.{node.attr}')
    return out


def test_the_checker_catches_a_mixin_and_a_private_read():
    mixin = ('class Part:\n'
             '    def go(self):\n'
             '        return self._model\n')
    peek = ('class Part:\n'
            '    def __init__(self, other):\n'
            '        self._other = other\n'
            '    def go(self):\n'
            '        return self._other._lock\n')
    func = 'def f(est):\n    return est._learner\n'
    clean = ('class Base:\n'
             '    def __init__(self):\n'
             '        self._x = 1\n'
             'class Part(Base):\n'
             '    _y = 2\n'
             '    def go(self):\n'
             '        return self._x + self._y + self._z()\n'
             '    def _z(self):\n'
             '        return 0\n')
    assert len(violations(mixin)) == 1 and 'self._model' in violations(mixin)[0]
    assert len(violations(peek)) == 1 and 'self._other._lock' in violations(peek)[0]
    assert len(violations(func)) == 1 and 'est._learner' in violations(func)[0]
    assert violations(clean) == []


def test_no_part_touches_another_parts_private_state():
    found, read = [], 0
    for where, _, names in sorted(os.walk(ONLINE)):
        for name in sorted(n for n in names if n.endswith('.py')):
            path = os.path.join(where, name)
            with open(path) as fh:
                found += violations(fh.read(), os.path.relpath(path, ROOT))
            read += 1
    assert read > 25, f'only {read} modules read under {ONLINE}'
    assert not found, '\n'.join(found)


def test_the_learner_and_the_estimator_are_composed_not_mixed():
    for module, cls in (('learner/learner.py', 'Learner'),
                        ('path/estimator.py', 'OnlineEstimator')):
        with open(os.path.join(ONLINE, module)) as fh:
            tree = ast.parse(fh.read())
        node = next(c for c in ast.walk(tree) if isinstance(c, ast.ClassDef) and c.name == cls)
        assert node.bases == [], f'{cls} has base classes: ' + \
            ', '.join(ast.unparse(b) for b in node.bases)


def test_each_module_of_the_learner_says_which_part_it_is():
    # a file's first line names what it holds; a part's docstring says whose part it is
    parts = {'learner/window.py': 'Window', 'learner/prior.py': 'Structure',
             'learner/grounds.py': 'Grounds', 'learner/served.py': 'Served',
             'jobs/refits.py': 'Refits', 'jobs/rebase.py': 'Rebases', 'jobs/switch.py': 'Switch',
             'learner/sampling.py': 'Front',
             'learner/snapshot.py': 'Snapshots', 'path/intake.py': 'Intake',
             'path/clock.py': 'LearningClock'}
    for module, cls in parts.items():
        with open(os.path.join(ONLINE, module)) as fh:
            tree = ast.parse(fh.read())
        doc = ast.get_docstring(tree)
        assert doc and doc.splitlines()[0].strip(), module
        assert 'part of' in ' '.join(doc.split()).lower() or \
            'part of' in ' '.join((ast.get_docstring(next(
                c for c in tree.body if isinstance(c, ast.ClassDef) and c.name == cls))
                or '').split()).lower(), f'{module}: whose part is {cls}?'
    # a module of steps on the parts (passed in each call, not kept) says so
    with open(os.path.join(ONLINE, 'learner/files.py')) as fh:
        doc = ast.get_docstring(ast.parse(fh.read()))
    assert 'steps of' in ' '.join(doc.split()).lower() and 'parts.Parts' in doc


def test_the_jobs_keep_no_other_part():
    """
    ``Refits``, ``Rebases`` and ``Switch`` keep no part, lock or method of the learner (issue 65).

    Each step is passed the learner's parts (``parts.Parts``); a part's attributes hold none of
    them, no method bound to one and no function closing over one or over the learner.
    """
    import numpy as np
    from dgp_ros.online import EstimatorConfig
    from dgp_ros.online.learner.learner import Learner
    L = Learner(EstimatorConfig(refit_mode='sync', min_samples=10, buffer_size=40))
    rng = np.random.default_rng(0)
    for i in range(30):
        qd = rng.uniform(-1, 1, 2)
        L.learn(0.01 * i, qd, 0.5 * qd)
    parts = L.parts()
    held = {id(p) for p in parts} | {id(L)}

    def touches(value) -> bool:
        if id(value) in held or id(getattr(value, '__self__', None)) in held:
            return True
        cells = getattr(value, '__closure__', None) or ()
        return any(id(c.cell_contents) in held for c in cells)

    for name in ('refits', 'rebases', 'switch'):
        part = getattr(parts, name)
        kept = [k for k, v in vars(part).items() if touches(v)]
        assert not kept, f'{name} keeps {kept}'
    # the checker sees a kept peer, a bound method of one and a closure over the learner
    assert touches(parts.window) and touches(parts.settings) and touches(parts.last_t)

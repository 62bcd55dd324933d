"""
The module graph of dgp_ros.gp has no import circles.

Every ``from .x import`` (at the top or inside a function) is an edge; the graph must be acyclic,
so each layer only builds on the ones below it (issue 24: certified <-> passivity and
models <-> persistence were circles).
"""
import ast
import os

import dgp_ros.gp

GP = os.path.dirname(dgp_ros.gp.__file__)


def _graph():
    g = {}
    for f in sorted(os.listdir(GP)):
        if not f.endswith('.py') or f == '__init__.py':
            continue
        name = f[:-3]
        tree = ast.parse(open(os.path.join(GP, f)).read())
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                if node.level == 1 and node.module:
                    deps.add(node.module.split('.')[0])
                elif node.level == 1:
                    deps.update(a.name for a in node.names)
                elif node.module and node.module.startswith('dgp_ros.gp.'):
                    deps.add(node.module.split('.')[2])
        g[name] = deps - {name}
    return g


def _cycle(g):
    state = {}

    def visit(v, path):
        state[v] = 1
        for w in sorted(g.get(v, ())):
            if state.get(w) == 1:
                return path + [v, w]
            if w not in state:
                c = visit(w, path + [v])
                if c:
                    return c
        state[v] = 2
        return None

    for v in sorted(g):
        if v not in state:
            c = visit(v, [])
            if c:
                return c
    return None


def test_graph_is_read_from_the_sources():
    g = _graph()
    # the check must see real edges, including the lazy (function-level) ones
    assert 'posterior' in g['models'] and 'policy' in g['certified']
    assert _cycle({'a': {'b'}, 'b': {'a'}}) is not None      # the detector detects


def test_no_import_circles_in_gp():
    c = _cycle(_graph())
    assert c is None, ' -> '.join(c)

"""
Every console script's ``--help`` is complete: each option says what it does and its default.

The argparse tools (dgp-demo and its robot and closed-loop forms, dgp-replay, dgp-export,
dgp-record, dgp-play, sim_bridge.export) are asked for ``--help`` in this process with their
parser captured: every option has a help text, every option with a default shows it, the usage
names the installed command. The nodes (estimator, sim_bridge, dgp-arm-sim, dgp-arm-loop,
dgp-controller) print ``runtime.help_text``: each parameter with its type, default and range, in
plain brackets, under the installed name.
"""
import argparse
import contextlib
import io
import re

import pytest

from dgp_ros.nodes import runtime

TOOLS = [('dgp_ros.apps.demo', 'main', [], 'dgp-demo'),
         ('dgp_ros.apps.demo', 'main', ['--robot', 'panda'], 'dgp-demo'),
         ('dgp_ros.apps.demo', 'main', ['--robot', 'panda', '--closed-loop'], 'dgp-demo'),
         ('dgp_ros.apps.replay', 'main', [], 'dgp-replay'),
         ('dgp_ros.apps.export', 'main', [], 'dgp-export'),
         ('dgp_ros.bags.cli', 'record_main', [], 'dgp-record'),
         ('dgp_ros.bags.cli', 'play_main', [], 'dgp-play'),
         ('sim_bridge.export', 'main', [], 'python -m sim_bridge.export')]


@pytest.mark.parametrize('module,fn,args,name', TOOLS,
                         ids=[f'{t[3]} {" ".join(t[2])}'.strip() for t in TOOLS])
def test_every_option_of_a_tool_says_what_it_does_and_its_default(
        monkeypatch, module, fn, args, name):
    import importlib
    seen = []
    real = argparse.ArgumentParser.parse_args

    def capture(self, *a, **kw):
        seen.append(self)
        return real(self, *a, **kw)
    monkeypatch.setattr(argparse.ArgumentParser, 'parse_args', capture)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as ex:
        getattr(importlib.import_module(module), fn)(args + ['--help'])
    assert ex.value.code == 0
    ap = seen[-1]
    text = out.getvalue()
    assert text.startswith(f'usage: {name}') and f'{name} [-h] {name}' not in text, text[:200]
    for act in ap._actions:
        if isinstance(act, argparse._HelpAction):
            continue
        what = act.option_strings or [act.dest]
        assert act.help and act.help != argparse.SUPPRESS, f'{name}: {what} has no help'
        if act.option_strings and act.default not in (None, False, argparse.SUPPRESS) and \
                act.nargs != 0:
            assert '%(default)' in act.help or 'default' in act.help.lower() or \
                isinstance(ap.formatter_class, type) and \
                issubclass(ap.formatter_class, argparse.ArgumentDefaultsHelpFormatter), \
                f'{name}: {what} hides its default {act.default!r}'


NODES = [('dgp_ros.nodes.estimator', 'estimator'), ('sim_bridge.node', 'sim_bridge'),
         ('dgp_ros.nodes.arm_sim', 'dgp-arm-sim'), ('dgp_ros.nodes.arm_loop', 'dgp-arm-loop'),
         ('dgp_ros.nodes.controller', 'dgp-controller')]


@pytest.mark.parametrize('module,name', NODES, ids=[n for _, n in NODES])
def test_every_node_lists_its_parameters_with_plain_ranges(module, name):
    import importlib
    m = importlib.import_module(module)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert m.main([name, '--help']) == runtime.EXIT_OK
    text = out.getvalue()
    assert text.startswith(f'usage: {name} ')
    assert '[[' not in text and 'e+09' not in text, text
    params = re.findall(r'^  (\w+): (\S+) = ', text, re.M)
    assert len(params) >= 3, text
    for p, t in params:
        assert t in ('int', 'float', 'str', 'bool', 'str[]', 'float[]'), (p, t)

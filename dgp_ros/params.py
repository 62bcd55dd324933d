"""
A parameter table entry and its check: shared by the nodes, the CLIs and the YAML files.

Pure Python: the online estimator validates its configuration with it, the nodes declare their
ROS parameters (with ``ParameterDescriptor`` ranges) from it and print ``--help`` from it.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Optional, Tuple

import numpy as np

__all__ = ['ParamSpec', 'check_spec']


@dataclass(frozen=True)
class ParamSpec:
    """
    One parameter.

    Type ('int' | 'float' | 'str' | 'bool' | 'str[]' | 'float[]'), default, description (with
    units), allowed choices or closed range ``[low, high]``.
    """

    name: str
    type: str  # noqa: A003 (a dataclass field: it shadows nothing)
    default: Any
    description: str
    choices: Tuple[str, ...] = ()
    low: Optional[float] = None
    high: Optional[float] = None
    max_len: int = 0
    read_only: bool = False     # the node refuses changes at run time (start-up only)

    def range_text(self) -> str:
        """Return the choices ``a | b`` or the closed range ``[low, high]`` ('' for neither)."""
        if self.choices:
            return ' | '.join(self.choices)
        if self.low is not None:
            return f'[{_plain(self.low)}, {_plain(self.high)}]'
        return ''


def _plain(x: float) -> str:
    """Return ``x`` as a reader writes it: an integer as one (2147483647), else ``:g``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f'{x:g}'


def _is_number(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float, np.integer, np.floating))


def check_spec(spec: ParamSpec, v) -> None:
    """Raise ValueError naming the parameter when ``v`` does not fit ``spec``."""

    def fail(why):
        raise ValueError(f'{spec.name}={v!r}: {why}')

    t = spec.type
    if t == 'str':
        if not isinstance(v, str):
            fail('must be a string')
        if spec.choices and v not in spec.choices:
            fail(f'must be one of {", ".join(spec.choices)}')
        if spec.max_len and len(v) > spec.max_len:
            raise ValueError(f'{spec.name}: {len(v)} characters, at most {spec.max_len}')
        return
    if t == 'bool':
        if not isinstance(v, (bool, np.bool_)):
            fail('must be true or false')
        return
    if t in ('int', 'float'):
        if not _is_number(v) or (t == 'int' and not isinstance(v, (int, np.integer))):
            fail(f'must be {"an integer" if t == "int" else "a number"}')
        if not math.isfinite(v):
            fail('must be finite')
        if spec.low is not None and not spec.low <= v <= spec.high:
            fail(f'must lie in {spec.range_text()}')
        return
    if not isinstance(v, (list, tuple)):
        fail('must be a list')
    if spec.max_len and len(v) > spec.max_len:
        fail(f'at most {spec.max_len} entries')
    if t == 'str[]':
        if not all(isinstance(x, str) and x for x in v):
            fail('must be a list of non-empty names')
        return
    for x in v:
        if not _is_number(x) or not math.isfinite(x):
            fail('entries must be finite numbers')
        if spec.low is not None and not spec.low <= x <= spec.high:
            fail(f'entries must lie in {spec.range_text()}')

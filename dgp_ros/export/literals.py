"""
C++ literals of a model's numbers: every constant a generated header declares (``cpp``).

A double is written as the shortest decimal that reads back as exactly that double, so a header
carries the model's numbers bit for bit; a non-finite number is refused (a damaged file).
"""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np

from .errors import ExportError

__all__ = ['lit', 'arr', 'ints', 'dims', 'const']


def lit(x) -> str:
    """Return a C++ literal that reads back as exactly ``x`` (the shortest round trip)."""
    x = float(x)
    if not math.isfinite(x):
        raise ExportError(f'a model constant is not finite ({x!r}): the file is damaged')
    r = repr(x)
    return r if ('.' in r or 'e' in r) else r + '.0'


def arr(a, per_line: int = 4) -> str:
    """Brace-initializer of a float array of any rank (rows on lines of ``per_line`` numbers)."""
    a = np.asarray(a, float)
    if a.ndim == 1:
        items = [lit(v) for v in a]
        lines = [', '.join(items[i:i + per_line]) for i in range(0, len(items), per_line)]
        return '{' + ',\n    '.join(lines) + '}'
    return '{' + ',\n  '.join(arr(row, per_line) for row in a) + '}'


def ints(a: Iterable[int]) -> str:
    return '{' + ', '.join(str(int(v)) for v in a) + '}'


def dims(a) -> str:
    return ''.join(f'[{d}]' for d in np.shape(a))


def const(name: str, a, kind: str = 'double') -> str:
    """Declare ``name``: an ``inline constexpr`` array of doubles (any rank) or of ``kind``."""
    if kind == 'double':
        return f'inline constexpr double {name}{dims(a)} = {arr(a)};\n'
    return f'inline constexpr {kind} {name}[{len(a)}] = {ints(a)};\n'

"""
C++ literals of a model's numbers and text: every constant a generated header declares (``cpp``).

A double is written as the shortest decimal that reads back as exactly that double, so a header
carries the model's numbers bit for bit; a non-finite number is refused (a damaged file). Text
that comes from a user or a model file (joint names, paths, labels) never reaches the compiler
as code: a string literal escapes every byte outside printable ASCII (:func:`string`), a comment
keeps printable ASCII only (:func:`comment`), and an identifier must be one (:func:`identifier`).
"""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np

from .errors import ExportError

__all__ = ['lit', 'arr', 'ints', 'dims', 'const', 'string', 'comment', 'identifier']


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


def string(text: str) -> str:
    """
    Return a C++ string literal of ``text``.

    Its UTF-8 bytes, each outside printable ASCII (and the quote, the backslash and ``?``) as a
    three-digit octal escape, so no byte can end the literal, the line or the comment it is in.
    """
    out = []
    for b in str(text).encode('utf-8', 'surrogatepass'):
        c = chr(b)
        out.append(c if 0x20 <= b < 0x7f and c not in '"\\?' else f'\\{b:03o}')
    return '"' + ''.join(out) + '"'


def comment(text: str) -> str:
    """
    Return ``text`` fit for a ``//`` comment.

    Printable ASCII only (others as ``?``), and no backslash (one at the end of a line would
    splice the next line into the comment).
    """
    return ''.join(c if 0x20 <= ord(c) < 0x7f and c != '\\' else '?' for c in str(text))


def identifier(name: str, what: str = 'name') -> str:
    """Return ``name`` if it is an ASCII C++ identifier; ExportError otherwise."""
    ok = bool(name) and name.isascii() and (name[0].isalpha() or name[0] == '_') and \
        all(c.isalnum() or c == '_' for c in name)
    if not ok:
        raise ExportError(f'{what} {name!r} is not a C++ identifier (ASCII letters, digits and '
                          f'_, not starting with a digit)')
    return name

"""
Compile a generated header with the system C++ compiler and evaluate it from Python.

For the tests and the benchmark: :func:`find_compiler` (``CXX``, else ``g++``, ``clang++``,
``c++``), :func:`compile_program` (``-std=c++17 -Wall -Wextra -Werror`` plus the caller's
flags; :class:`CompileError` with the compiler's output), and :func:`evaluate`, which runs a
small driver (``DRIVER``) over poses and velocities in binary float64 and returns every public
function's answers. Nothing here is needed at run time by a controller.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from typing import Optional, Sequence

import numpy as np

__all__ = ['find_compiler', 'compile_program', 'evaluate', 'CompileError', 'WARNINGS',
           'DRIVER', 'OUTPUTS']

#: the flags every compile of the tests and the benchmark uses
WARNINGS = ('-std=c++17', '-Wall', '-Wextra', '-Werror')
#: what the driver writes per row, in this order, with its width in units of N
OUTPUTS = (('model_damping', 1), ('damping', 1), ('model_damping_matrix', 'NN'),
           ('damping_matrix', 'NN'), ('conservative', 1), ('correction', 1),
           ('friction', 1), ('model_residual', 1))

#: reads k rows of (q, qd) as float64 from argv[1], writes every answer to argv[2]
DRIVER = r"""
#include DGP_HEADER
#include <cstdio>
#include <vector>
int main(int argc, char** argv) {
  namespace m = DGP_NS;
  if (argc != 3) return 2;
  std::FILE* in = std::fopen(argv[1], "rb");
  std::FILE* out = std::fopen(argv[2], "wb");
  if (!in || !out) return 3;
  std::vector<double> q(m::N), qd(m::N), v(m::N), D(m::N * m::N);
  while (std::fread(q.data(), sizeof(double), m::N, in) == m::N &&
         std::fread(qd.data(), sizeof(double), m::N, in) == m::N) {
    m::model_damping(qd.data(), v.data());
    std::fwrite(v.data(), sizeof(double), m::N, out);
    m::damping(qd.data(), v.data());
    std::fwrite(v.data(), sizeof(double), m::N, out);
    m::model_damping_matrix(qd.data(), D.data());
    std::fwrite(D.data(), sizeof(double), m::N * m::N, out);
    m::damping_matrix(qd.data(), D.data());
    std::fwrite(D.data(), sizeof(double), m::N * m::N, out);
    m::conservative(q.data(), v.data());
    std::fwrite(v.data(), sizeof(double), m::N, out);
    m::correction(q.data(), v.data());
    std::fwrite(v.data(), sizeof(double), m::N, out);
    m::friction(q.data(), qd.data(), v.data());
    std::fwrite(v.data(), sizeof(double), m::N, out);
    m::model_residual(q.data(), qd.data(), v.data());
    std::fwrite(v.data(), sizeof(double), m::N, out);
  }
  std::fclose(in);
  return std::fclose(out) == 0 ? 0 : 4;
}
"""


class CompileError(RuntimeError):
    """The compiler refused a program: its command and output are in the message."""


def find_compiler(names: Sequence[str] = ('g++', 'clang++', 'c++')) -> Optional[str]:
    """Return the C++ compiler to use (``$CXX``, else the first of ``names`` on PATH) or None."""
    cxx = os.environ.get('CXX')
    if cxx and shutil.which(cxx):
        return shutil.which(cxx)
    for name in names:
        path = shutil.which(name)
        if path:
            return path
    return None


def compile_program(source: str, exe: str, compiler: str, flags: Sequence[str] = ('-O2',),
                    include: Sequence[str] = (), defines: Sequence[str] = (),
                    timeout_s: float = 300.0) -> str:
    """
    Compile one C++ source file (its text) to ``exe`` with ``WARNINGS`` and ``flags``.

    include : header folders (-I); defines : NAME=VALUE (-D). Returns ``exe``; CompileError
    with the command and the compiler's output when it fails.
    """
    src = exe + '.cpp'
    with open(src, 'w', encoding='utf-8') as f:
        f.write(source)
    cmd = [compiler, *WARNINGS, *flags, *(f'-I{d}' for d in include),
           *(f'-D{d}' for d in defines), src, '-o', exe]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if r.returncode != 0:
        raise CompileError(f'{" ".join(cmd)} failed ({r.returncode}):\n{r.stderr[-4000:]}')
    return exe


def driver(header: str, workdir: str, compiler: str, namespace: str = 'dgp_model',
           flags: Sequence[str] = ('-O2',)) -> str:
    """Compile ``DRIVER`` for the header file ``header``; returns the executable's path."""
    exe = os.path.join(workdir, 'dgp_driver')
    return compile_program(DRIVER, exe, compiler, flags,
                           defines=(f'DGP_HEADER="{os.path.abspath(header)}"',
                                    f'DGP_NS={namespace}'))


def evaluate(exe: str, Q: np.ndarray, Qd: np.ndarray, workdir: str) -> dict:
    """
    Run a compiled driver on poses Q and velocities Qd (k, N) each.

    Returns ``{name: (k, N) or (k, N, N)}`` for every name of ``OUTPUTS``.
    """
    Q, Qd = np.atleast_2d(np.asarray(Q, float)), np.atleast_2d(np.asarray(Qd, float))
    k, N = Qd.shape
    fin, fout = os.path.join(workdir, 'in.bin'), os.path.join(workdir, 'out.bin')
    np.ascontiguousarray(np.hstack([Q, Qd])).tofile(fin)
    subprocess.run([exe, fin, fout], check=True, timeout=600)
    widths = [N * N if w == 'NN' else N for _, w in OUTPUTS]
    raw = np.fromfile(fout, dtype=np.float64).reshape(k, sum(widths))
    out, c = {}, 0
    for (name, w), width in zip(OUTPUTS, widths):
        block = raw[:, c:c + width]
        out[name] = block.reshape(k, N, N) if w == 'NN' else block
        c += width
    return out

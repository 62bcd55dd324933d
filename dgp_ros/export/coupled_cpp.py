"""
The C++ of a coupled prior (``gp.coupled.CoupledMean``): its force, matrix, gains and gate.

A prior with coupled transmissions (``gp.transmission.TransmissionMean``) takes the same form,
with a motor per pair instead of the persistent columns (``_motor``): its force is passive
before the projection, which then changes nothing but rounding.

A coupled prior is a diagonal base ``diag(m_d(qd))`` (``prior_diag``, as for any prior) plus,
for each persistent column ``p``, the couplings ``tau_i += v_p^2 psi_p(x)^T W_p[i] / vref_p^2``
and ``D[i, p] += v_p psi_p(x)^T W_p[i] / vref_p^2`` (``x``: the other velocities clipped into
the prior's box). It is passive by its projection: the force is ``project_passive(qd, raw)``
(``gp.policy``, unit weights, with its few ulp steps) and the matrix ``M_raw + lam I`` with
``lam = max(0, -qd . M_raw qd) / |qd|^2``. Where a diagonal prior's ``m_d`` enters the answer,
its fallback and the gate, this prior's (force, matrix) enter instead, as in Python:

* ``model_answer`` (``gp.posterior``): D starts from ``mean.matrix(qd)``, tau from
  ``mean.force(qd)`` plus the correction;
* ``blend`` (``gp.blend.blend``, non-diagonal branch): joint by joint toward
  ``prior_answer(mean, qd, a)`` (the force times the gains, projected; its matrix row-scaled
  plus that projection's ``lam I``), then the blend projected onto ``qd . tau >= 0``; a
  transmission prior (``psd``: its diagonal plus a PSD part) takes the gains as the congruence
  ``R M R`` and, under a ``psd`` certificate, the blend ``S D S + R' Mp R'`` (no projection);
* the gate (``online/path/gate.py``): the fallback ``prior_answer(mean, qd, gain)``, and the
  prior's force at the query clipped into the learned box raising the limit.

Every function here mirrors the Python named beside it operation for operation where it decides
something (a sign, a clip); sums may differ in order (rounding only). Units: model units.
"""
from __future__ import annotations

from typing import List

import numpy as np

from .literals import const, lit
from .spec import Spec

__all__ = ['coupled_code', 'coupled_blend_code', 'coupled_answer', 'GATE_COUPLED']

#: the gate's prior of a coupled prior (``cpp_runtime.GATE``'s placeholders): the fallback
#: ``prior_answer(mean, q, GAIN, True)`` and the prior's force at the clipped query ``qb``
GATE_COUPLED = {
    'fallback': r"""    double fb[N], Mb[N * N];
    coupled_prior(q, Mb, fb);
    gain_prior(q, GAIN, Mb, fb);
    bool finite = true;
    for (std::size_t i = 0; i < N; ++i) finite = finite && std::isfinite(fb[i]);
    for (std::size_t i = 0; i < N; ++i) {
      tau[i] = finite ? fb[i] : 0.0;
      for (std::size_t j = 0; j < N; ++j) D[i * N + j] = finite ? Mb[i * N + j] : 0.0;
    }
""",
    'boxed_decl': 'pf[N]', 'boxed_prior': 'coupled_prior(qb, nullptr, pf);',
    'boxed_force': 'pf[i]'}

#: the projection with unit weights (gp/policy.py ``projection_lambda``, ``project_passive``)
#: and the gains of ``gp.blend.prior_answer`` on a prior's (M, f), in place
_UNIT = r"""
inline double lambda_unit(const double* q, const double* t) noexcept {
  const double p = power(q, t);
  double den = 0.0;
  for (std::size_t i = 0; i < N; ++i) den += q[i] * q[i];
  return (p < 0.0 && den > 0.0) ? -p / den : 0.0;
}
inline void project_unit(const double* q, double* t) noexcept {
  if (power(q, t) >= 0.0) return;
  const double lam = lambda_unit(q, t);
  for (std::size_t i = 0; i < N; ++i) t[i] += lam * q[i];
  for (int step = 0; step < 4; ++step) {  // rounding: a few ulps further where still < 0
    const double p = power(q, t);
    if (!(p < 0.0)) break;
    double den = 0.0, size = 0.0;
    for (std::size_t i = 0; i < N; ++i) {
      den += q[i] * q[i];
      size += std::fabs(q[i]) * std::fabs(t[i]);
    }
    const double k = (-p + 8.0 * 2.220446049250313e-16 * size) / den;
    for (std::size_t i = 0; i < N; ++i) t[i] += k * q[i];
  }
}
"""

#: ``prior_answer``'s gains on a coupled prior's (M, f): row by row, then projected
_GAIN_ROWS = r"""
inline void gain_prior(const double* q, const double* a, double* M, double* f) noexcept {
  for (std::size_t i = 0; i < N; ++i) f[i] = f[i] * a[i];
  const double lam = lambda_unit(q, f);
  project_unit(q, f);
  for (std::size_t i = 0; i < N; ++i) {
    for (std::size_t j = 0; j < N; ++j) M[i * N + j] *= a[i];
    M[i * N + i] += lam;
  }
}
"""

#: ... and on a transmission prior's (diagonal plus PSD): the congruence R M R, R = diag(sqrt a)
_GAIN_CONGRUENCE = r"""
inline void gain_prior(const double* q, const double* a, double* M, double* f) noexcept {
  double r[N];
  for (std::size_t i = 0; i < N; ++i) r[i] = std::sqrt(a[i]);
  for (std::size_t i = 0; i < N; ++i) {
    double t = 0.0;
    for (std::size_t j = 0; j < N; ++j) {
      M[i * N + j] *= r[i] * r[j];
      t += M[i * N + j] * q[j];
    }
    f[i] = t;
  }
}
"""

_TERM = {'x': 'x[{0}]', 'a': 'a[{0}]', 'x2': 'x[{0}] * x[{0}]', 'x3': 'x[{0}] * x[{0}] * x[{0}]',
         'xx': 'x[{0}] * x[{1}]', 'xa': 'x[{0}] * a[{1}]', 'ax': 'a[{0}] * x[{1}]'}


def _column(c: int, col: dict, boxed: bool) -> List[str]:
    """Return the lines adding column ``col`` (``spec._coupled``) to ``cp`` (force) and M."""
    o, terms, p = col['others'], col['terms'], col['p']
    clip = ('qd[{0}] < CP_LO[{0}] ? CP_LO[{0}] : (qd[{0}] > CP_HI[{0}] ? CP_HI[{0}] : qd[{0}])'
            if boxed else 'qd[{0}]')
    psi = ['1.0' if t[0] == 'one' else _TERM[t[0]].format(*t[1:]) for t in terms]
    vref = col['vref']
    out = [f'  {{  // column {p}: its features of the other velocities {o}']
    if o:
        out += [f'    double x[{len(o)}], a[{len(o)}];'] + [
            f'    x[{k}] = {clip.format(j)};\n    a[{k}] = std::fabs(x[{k}]);'
            for k, j in enumerate(o)]
    rows = [', '.join(psi[i:i + 4]) for i in range(0, len(psi), 4)]
    out += [f'    const double psi[{len(terms)}] = {{\n        ' + ',\n        '.join(rows) +
            '};',
            f'    const double r = qd[{p}] / {lit(vref)}, s = r * r, v = qd[{p}] / '
            f'{lit(np.float64(vref) ** 2)};',
            '    for (std::size_t i = 0; i < N; ++i) {',
            '      double c = 0.0, g = 0.0;',
            f'      for (std::size_t k = 0; k < {len(terms)}; ++k) {{',
            f'        c += (psi[k] * s) * CW{c}[i][k];',
            f'        g += psi[k] * CW{c}[i][k];',
            '      }',
            '      cp[i] += c;',
            f'      if (M != nullptr) M[i * N + {p}] += g * v;',
            '    }', '  }']
    return out


def _motor(motor: tuple, eps: float) -> List[str]:
    """
    Return the lines adding one coupled transmission (``gp.transmission``) to ``cp`` and M.

    ``motor``: (a, b, s, Coulomb, viscous); the motor turns at ``m = qd_a + s qd_b``, its force
    ``f = c tanh(m / eps) + v m`` goes to joint a and ``s f`` to joint b, and ``g = f / m``
    (``_tanh_over``'s ``1 / eps`` below ``1e-6 eps``) to ``M`` as ``g t t^T``.
    """
    a, b, s, cc, cv = motor
    op, sg = ('+', '') if s > 0 else ('-', '-')
    return [f'  {{  // the motor of joints {a} and {b}, turning at qd[{a}] {op} qd[{b}]',
            f'    const double m = qd[{a}] {op} qd[{b}], am = std::fabs(m);',
            f'    const double f = {lit(cc)} * std::tanh(m / {lit(eps)}) + {lit(cv)} * m;',
            f'    cp[{a}] += f;', f'    cp[{b}] += {sg}f;',
            '    if (M != nullptr) {',
            f'      const double g = {lit(cc)} * (am < {lit(1e-6 * eps)} ? {lit(1.0 / eps)} : '
            f'std::tanh(am / {lit(eps)}) / am) + {lit(cv)};',
            f'      M[{a} * N + {a}] += g;', f'      M[{b} * N + {b}] += g;',
            f'      M[{a} * N + {b}] += {sg}g;', f'      M[{b} * N + {a}] += {sg}g;',
            '    }', '  }']


def coupled_code(spec: Spec) -> str:
    """
    Return the coupled prior's constants and functions (module docstring).

    ``coupled_prior(qd, M, f)``: ``f`` (N) = ``mean.force(qd)`` and, unless ``M`` is null,
    ``M`` (N x N, row-major) = ``mean.matrix(qd)`` (gp/coupled.py); ``gain_prior(q, a, M, f)``:
    ``prior_answer``'s gains on them, in place; ``lambda_unit``, ``project_unit``: the
    projection of ``gp.policy`` with unit weights. Emitted after ``PROJECT`` (``power``).
    """
    cpl = spec.prior['coupled']
    boxed = cpl['box'] is not None
    out = ''
    if boxed:
        out += const('CP_LO', cpl['box'][0]) + const('CP_HI', cpl['box'][1])
    for c, col in enumerate(cpl['columns']):
        out += const(f'CW{c}', col['W'])
    lines = ['inline void coupled_prior(const double* qd, double* M, double* f) noexcept {',
             '  double md[N], cp[N];',
             '  prior_diag(qd, md);',
             '  for (std::size_t i = 0; i < N; ++i) cp[i] = 0.0;',
             '  if (M != nullptr)',
             '    for (std::size_t i = 0; i < N; ++i)',
             '      for (std::size_t j = 0; j < N; ++j) M[i * N + j] = i == j ? md[i] : 0.0;']
    for c, col in enumerate(cpl['columns']):
        lines += _column(c, col, boxed)
    for motor in cpl.get('motors', ()):
        lines += _motor(motor, cpl['eps'])
    lines += ['  if (M != nullptr) {',
              '    double mq[N];',
              '    for (std::size_t i = 0; i < N; ++i) {',
              '      double t = 0.0;',
              '      for (std::size_t j = 0; j < N; ++j) t += M[i * N + j] * qd[j];',
              '      mq[i] = t;', '    }',
              '    const double lam = lambda_unit(qd, mq);',
              '    if (lam > 0.0)',
              '      for (std::size_t i = 0; i < N; ++i) M[i * N + i] += lam;', '  }',
              '  for (std::size_t i = 0; i < N; ++i) f[i] = md[i] * qd[i] + cp[i];',
              '  project_unit(qd, f);', '}']
    gains = _GAIN_CONGRUENCE if cpl.get('psd') else _GAIN_ROWS
    return out + _UNIT + gains + '\n'.join(lines) + '\n'


def coupled_blend_code(spec: Spec) -> str:
    """
    Return ``blend(qd, Mp, fp, tau, D)``: the earned gains' blend toward a coupled prior.

    ``gp.blend.blend``'s non-diagonal branch: ``(fp, Mp)`` (the prior's force and matrix at
    qd) take the gains ``a`` (``gain_prior``, in place), then ``tb = w tau + (1 - w) fp`` and
    ``D = w D + (1 - w) Mp`` row by row, projected (``lam`` on D's diagonal).
    """
    w, a = spec.grounds
    if spec.prior['coupled'].get('psd') and spec.per_joint:
        # the congruence S D S + R Mp R (``blend``'s branch for a prior diagonal plus PSD)
        s, r = np.sqrt(w), np.sqrt((1.0 - w) * a)
        return (const('BS', s[:, None] * s[None, :]) + const('BR', r[:, None] * r[None, :]) +
                'inline void blend(const double* qd, double* Mp, double* fp, double* tau, '
                'double* D) noexcept {\n'
                '  (void)fp;\n'
                '  for (std::size_t i = 0; i < N; ++i)\n'
                '    for (std::size_t j = 0; j < N; ++j)\n'
                '      D[i * N + j] = D[i * N + j] * BS[i][j] + Mp[i * N + j] * BR[i][j];\n'
                '  for (std::size_t i = 0; i < N; ++i) {\n'
                '    double t = 0.0;\n'
                '    for (std::size_t j = 0; j < N; ++j) t += D[i * N + j] * qd[j];\n'
                '    tau[i] = t;\n  }\n}\n')
    return (const('BA', a) + const('BW', w) + const('BV', 1.0 - w) +
            'inline void blend(const double* qd, double* Mp, double* fp, double* tau, double* D)'
            ' noexcept {\n'
            '  gain_prior(qd, BA, Mp, fp);\n'
            '  double tb[N];\n'
            '  for (std::size_t i = 0; i < N; ++i) tb[i] = BW[i] * tau[i] + BV[i] * fp[i];\n'
            '  const double lam = lambda_unit(qd, tb);\n'
            '  project_unit(qd, tb);\n'
            '  for (std::size_t i = 0; i < N; ++i) {\n'
            '    for (std::size_t j = 0; j < N; ++j)\n'
            '      D[i * N + j] = BW[i] * D[i * N + j] + BV[i] * Mp[i * N + j];\n'
            '    D[i * N + i] += lam;\n'
            '    tau[i] = tb[i];\n  }\n}\n')


def coupled_answer(spec: Spec) -> dict:
    """
    Return the parts of ``model_answer`` that differ for a coupled prior (``cpp._answer_code``).

    ``decl``: the work arrays; ``prior``: D = ``mean.matrix(qd)``, ``fp`` = ``mean.force(qd)``
    (and their copy ``Mp`` for the blend); ``force``: the prior's force of joint ``i``;
    ``blend``: the call of :func:`coupled_blend_code`'s ``blend``.
    """
    gains = spec.grounds is not None
    prior = ['  coupled_prior(qd, D, fp);']
    if gains:
        prior.append('  for (std::size_t i = 0; i < N * N; ++i) Mp[i] = D[i];')
    prior.append('  for (std::size_t i = 0; i < N; ++i) corr[i] = 0.0;')
    return {'decl': '  double x[N], fp[N], ' + ('Mp[N * N], ' if gains else '') +
                    'acc[NE], corr[N];',
            'prior': prior, 'force': 'fp[i]', 'blend': '  blend(qd, Mp, fp, tau, D);'}

"""
A frozen model as one self-contained, header-only C++17 file (``render``).

The header holds the model's numbers (``spec.Spec``) as ``inline constexpr`` arrays and the
functions of ``cpp_runtime`` specialised to them, in ``namespace <ns>``; it includes only
``<cmath>``, ``<cstddef>``, ``<cstdint>`` and ``<cstring>``. Every function is ``noexcept``,
allocates nothing and keeps its work arrays on the stack (a few N x N blocks and one row of
``NE`` element sums). What each public function equals is in docs/CONTRACTS.md
("dgp_ros.export"); the banner of a header says which guarantee it carries and that the proof
was made at export.
"""
from __future__ import annotations

import numpy as np

from .coupled_cpp import coupled_answer, coupled_blend_code, coupled_code, GATE_COUPLED
from .cpp_runtime import (CHAIN, EXP, GATE, GATE_DIAGONAL, KERNEL, KERNEL_NONE, KERNEL_SCALAR,
                          PROJECT, PSD_FLOOR, TANH_OVER)
from .literals import const as _const, identifier as _identifier, lit as _lit, \
    string as _string
from .spec import Spec

__all__ = ['render', 'PAD']

#: elements are padded to a multiple of this (zero weights) so the element loops vectorize
PAD = 8


def _prior_code(spec: Spec) -> str:
    """``prior_diag`` for this prior (``gp.friction_means._friction_diag``, terms in its order)."""
    p = spec.prior
    coef, eps, vs = p['coef'], p['eps'], p['vs']
    K, S = int(p['K']), vs.shape[1]
    el = p.get('element')
    neg = p.get('coef_neg')
    out = _const('PC', coef)
    # an asymmetric prior: the coefficients of v < 0 are their own (gp/friction_means.py)
    pc = 'PC[i]'
    if neg is not None:
        out += _const('PCN', neg)
        pc = 'pc'
    body = [f'    double out = {pc}[0];']
    if neg is not None:
        body.insert(0, '    const double* pc = qd[i] < 0.0 ? PCN[i] : PC[i];')
    if K or S or el is not None:
        body.insert(0, '    const double a = std::fabs(qd[i]);')
    if K or S:
        out += _const('PE', eps)
        body += [f'    out += {pc}[{1 + k}] * tanh_over(a, PE[i][{k}]);' for k in range(K)]
    if S:
        out += _const('PV', vs)
        body.append(f'    const double t = tanh_over(a, PE[i][{K}]);')
        for s in range(S):
            body += [f'    {{ const double r = a / PV[i][{s}];',
                     f'      out += {pc}[{1 + K + s}] * t * std::exp(-(r * r)); }}']
    tail = '    md[i] = out;'
    if el is not None:
        out += _element_code(el, spec.N)
        tail = ('    const int e = ELEMENT_OF[i];\n'
                '    if (e >= 0) out = std::max(out + element_diag(e, qd[i], a), 0.0);\n'
                '    md[i] = out;')
    out += TANH_OVER.substitute() if (K or S or el is not None) else ''
    arg = 'qd' if K or S or el is not None or neg is not None else ''
    out += (f'inline void prior_diag(const double* {arg}, double* md) noexcept {{\n'
            '  for (std::size_t i = 0; i < N; ++i) {\n' + '\n'.join(body) + '\n' + tail +
            '\n  }\n}\n')
    return out


def _element_code(el: dict, N: int) -> str:
    """
    ``element_diag(e, v, |v|)``: element e's part of ``m_d`` (gp/joint_element.py).

    ``g(u) = sum_k w_k sin(k x)``, ``x = pi (u + 1) / 2``, ``u = w / sqrt(w^2 + vc^2)``, ``w`` the
    velocity clipped into the element's span, with
    ``sin(k x)`` by the recurrence ``s_(k+1) = 2 cos(x) s_k - s_(k-1)`` (one sin and one cos),
    times ``tanh(|v| / eps) / |v|``. The header declares ``tanh_over`` after this function's
    caller needs it: both are inline and defined before ``prior_diag``.
    """
    W = np.asarray(el['W'], float)
    n, M = W.shape
    of = np.full(N, -1, int)
    of[el['joints']] = np.arange(n)
    big = 1e300                     # no span known: nothing clipped
    lo = np.maximum(np.asarray(el.get('lo', np.full(n, -big)), float), -big)
    hi = np.minimum(np.asarray(el.get('hi', np.full(n, big)), float), big)
    return (_const('EW', W) + _const('EVC', el['vc']) + _const('EEPS', el['eps']) +
            _const('ELO', lo) + _const('EHI', hi) +
            _const('ELEMENT_OF', of, 'int') +
            'inline double tanh_over(double a, double eps) noexcept;\n'
            'inline double element_diag(int e, double v, double a) noexcept {\n'
            '  const double w = v < ELO[e] ? ELO[e] : (v > EHI[e] ? EHI[e] : v);\n'
            '  const double u = w / std::sqrt(w * w + EVC[e] * EVC[e]);\n'
            '  const double x = 1.5707963267948966 * (u + 1.0);\n'
            '  const double c2 = 2.0 * std::cos(x);\n'
            '  double s0 = 0.0, s1 = std::sin(x), g = 0.0;\n'
            f'  for (int k = 0; k < {M}; ++k) {{\n'
            '    g += EW[e][k] * s1;\n'
            '    const double s2 = c2 * s1 - s0;\n'
            '    s0 = s1;\n'
            '    s1 = s2;\n'
            '  }\n'
            '  return g * tanh_over(a, EEPS[e]);\n'
            '}\n')


def _weight_code(spec: Spec) -> str:
    """``weight(qd)``: the policy's correction weight (gp/certified.py ``_blend``)."""
    w = spec.weight
    if w[0] == 'one':
        return 'inline double weight(const double*) noexcept { return 1.0; }\n'
    if w[0] == 'scale':
        return f'inline double weight(const double*) noexcept {{ return {_lit(w[1])}; }}\n'
    _, scale, olo, dlo, ohi, dhi = w
    out = (_const('OLO', olo) + _const('DLO', dlo) + _const('OHI', ohi) + _const('DHI', dhi))
    return out + (
        'inline double weight(const double* qd) noexcept {\n'
        '  double w = 1.0;\n'
        '  for (std::size_t i = 0; i < N; ++i) {\n'
        '    double lo = (qd[i] - OLO[i]) / DLO[i], hi = (OHI[i] - qd[i]) / DHI[i];\n'
        '    lo = lo < 0.0 ? 0.0 : (lo > 1.0 ? 1.0 : lo);\n'
        '    hi = hi < 0.0 ? 0.0 : (hi > 1.0 ? 1.0 : hi);\n'
        '    const double t = lo < hi ? lo : hi;\n'
        '    w *= t * t * t * (t * (6.0 * t - 15.0) + 10.0);\n'
        '  }\n'
        f'  return {_lit(scale)} * w;\n}}\n')


def _blend_code(spec: Spec) -> str:
    """Return ``blend``: the earned gains' blend (gp/blend.py), on (tau, D) in place."""
    if spec.grounds is None:
        return ''
    if 'coupled' in spec.prior:
        return coupled_blend_code(spec)
    w, a = spec.grounds
    if spec.per_joint:
        s = np.sqrt(w)
        return (_const('BS', s[:, None] * s[None, :]) + _const('BF', (1.0 - w) * a) +
                'inline void blend(const double* qd, const double* md, double* tau, double* D)'
                ' noexcept {\n'
                '  for (std::size_t i = 0; i < N; ++i)\n'
                '    for (std::size_t j = 0; j < N; ++j) D[i * N + j] = D[i * N + j] * BS[i][j];\n'
                '  for (std::size_t i = 0; i < N; ++i) D[i * N + i] += md[i] * BF[i];\n'
                '  for (std::size_t i = 0; i < N; ++i) {\n'
                '    double t = 0.0;\n'
                '    for (std::size_t j = 0; j < N; ++j) t += D[i * N + j] * qd[j];\n'
                '    tau[i] = t;\n  }\n}\n')
    ws = float(np.min(w))
    return (_const('BF', (1.0 - ws) * a) +
            'inline void blend(const double* qd, const double* md, double* tau, double* D)'
            ' noexcept {\n'
            '  for (std::size_t i = 0; i < N; ++i) {\n'
            '    const double f = BF[i] * md[i];\n'
            f'    tau[i] = {_lit(ws)} * tau[i] + f * qd[i];\n'
            f'    for (std::size_t j = 0; j < N; ++j) D[i * N + j] = {_lit(ws)} * D[i * N + j];\n'
            '    D[i * N + i] += f;\n  }\n}\n')


def _answer_code(spec: Spec) -> str:
    """
    ``model_answer``: the model's predict and damping matrix (gp/models.py ``_answers``).

    D starts from the prior's matrix and tau from the prior's force (``gp.posterior``): a
    diagonal prior's ``diag(m_d)`` and ``m_d qd``, a coupled one's (``coupled_cpp``).
    """
    part = coupled_answer(spec) if 'coupled' in spec.prior else {
        'decl': '  double x[N], md[N], acc[NE], corr[N];',
        'prior': ['  prior_diag(qd, md);',
                  '  for (std::size_t i = 0; i < N * N; ++i) D[i] = 0.0;',
                  '  for (std::size_t i = 0; i < N; ++i) { D[i * N + i] = md[i]; '
                  'corr[i] = 0.0; }'],
        'force': 'md[i] * qd[i]', 'blend': '  blend(qd, md, tau, D);'}
    lines = ['inline void model_answer(const double* qd, double* tau, double* D) noexcept {',
             part['decl'],
             '  for (std::size_t i = 0; i < N; ++i) x[i] = qd[i] / SX[i];',
             '  element_sums(x, acc);',
             '  const double w = weight(qd);'] + part['prior'] + [
             '  for (std::size_t e = 0; e < E; ++e) {',
             '    corr[EM[e]] += acc[e] * x[EN[e]];',
             '    D[EM[e] * N + EN[e]] += w * (acc[e] * SYSX[e]);',
             '  }',
             '  for (std::size_t i = 0; i < N; ++i)',
             f'    tau[i] = {part["force"]} + (corr[i] * w) * SY[i];']
    if spec.clip_delta is not None:
        lines += ['  psd_floor(D);',
                  '  for (std::size_t i = 0; i < N; ++i) {',
                  '    double t = 0.0;',
                  '    for (std::size_t j = 0; j < N; ++j) t += D[i * N + j] * qd[j];',
                  '    tau[i] = t;', '  }',
                  '  project(qd, tau, D, tau);']
    elif spec.project:
        lines += ['  double dq[N];',
                  '  for (std::size_t i = 0; i < N; ++i) {',
                  '    double t = 0.0;',
                  '    for (std::size_t j = 0; j < N; ++j) t += D[i * N + j] * qd[j];',
                  '    dq[i] = t;', '  }',
                  '  project(qd, tau, D, dq);']
    if spec.grounds is not None:
        lines.append(part['blend'])
    return '\n'.join(lines) + '\n}\n'


def _correction_code(spec: Spec) -> str:
    """``conservative(q)`` and the offsets (dynamics/conservative.py ``Correction``)."""
    c = spec.correction
    N = spec.N
    off = np.zeros(N) if c is None else c['offsets']
    out = _const('OFFSETS', off)
    if c is None or c['basis'] is None:
        return out + ('inline void conservative_part(const double*, double* out) noexcept {\n'
                      '  for (std::size_t i = 0; i < N; ++i) out[i] = 0.0;\n}\n')
    if c['basis'] == 'potential':
        body = ['  double s[N], c[N];',
                '  for (std::size_t i = 0; i < N; ++i) {',
                '    s[i] = std::sin(q[i]); c[i] = std::cos(q[i]); out[i] = 0.0;', '  }']
        for k, (S, fs) in enumerate(c['terms']):
            th = float(c['theta'][k])
            if th == 0.0:
                continue
            val = [f's[{i}]' if f == 0 else f'c[{i}]' for i, f in zip(S, fs)]
            der = [f'c[{i}]' if f == 0 else f'(-s[{i}])' for i, f in zip(S, fs)]
            for a, i in enumerate(S):
                prod = ' * '.join([der[a]] + [v for b, v in enumerate(val) if b != a])
                body.append(f'  out[{i}] += {_lit(th)} * ({prod});')
        return out + ('inline void conservative_part(const double* q, double* out) noexcept {\n'
                      + '\n'.join(body) + '\n}\n')
    ch, th = c['chain'], np.asarray(c['theta'], float).reshape(-1, 10)
    J = ch.parent.size
    out += (f'constexpr std::size_t J = {J};\n' + _const('PARENT', ch.parent, 'int') +
            _const('COORD', ch.coord, 'std::size_t') + _const('R0', ch.R0) +
            _const('P0', ch.p0) + _const('AXIS', ch.axis) + _const('GRAVITY', ch.gravity) +
            _const('TH_M', th[:, 0]) + _const('TH_H', th[:, 1:4]))
    return out + CHAIN.substitute() + (
        'inline void conservative_part(const double* q, double* out) noexcept {\n'
        '  gravity_torque(q, out);\n}\n')


def render(spec: Spec, namespace: str = 'dgp_model', banner: str = '') -> str:
    """Return the header text of ``spec`` (module docstring); ``banner``: its comment lines."""
    _identifier(namespace, 'namespace')
    N, E = spec.N, len(spec.elements)
    vector = E >= PAD              # fewer elements than a vector's lanes: one at a time
    NE = -(-E // PAD) * PAD if vector else max(E, 1)
    IL2 = np.zeros((N, NE))
    V = np.zeros((spec.n, NE))
    for e, el in enumerate(spec.elements):
        IL2[:, e], V[:, e] = el.il2, el.v
    EM = [el.m for el in spec.elements] or [0]
    EN = [el.n for el in spec.elements] or [0]
    sysx = [spec.sy[el.m] / spec.sx[el.n] for el in spec.elements] or [0.0]
    guard = f'DGP_EXPORT_{namespace.upper()}_HPP'
    names = ', '.join(_string(s) for s in spec.names)
    c = spec.correction
    d = []
    d.append(f'constexpr std::size_t NE = {NE};\nconstexpr std::size_t E = {max(E, 1)};\n')
    d += [_const('SX', spec.sx), _const('SY', spec.sy), _const('X', spec.X),
          _const('IL2', IL2), _const('V', V), _const('EM', EM, 'std::size_t'),
          _const('EN', EN, 'std::size_t'), _const('SYSX', sysx), _const('W_INV', spec.w_inv),
          _const('LIMIT', spec.gate['limit']), _const('BOX_LO', spec.gate['box_lo']),
          _const('BOX_HI', spec.gate['box_hi']), _const('GAIN', spec.gate['gain']),
          f'constexpr bool GATE_PASSIVE = {"true" if spec.gate["passive"] else "false"};\n']
    if spec.clip_delta is not None:
        d.append(f'constexpr double PSD_DELTA = {_lit(spec.clip_delta)};\n')
    d.append(EXP.substitute())
    d.append((KERNEL if vector else KERNEL_SCALAR if E else KERNEL_NONE).substitute())
    d += [_prior_code(spec), _weight_code(spec)]
    if spec.clip_delta is not None:
        d.append(PSD_FLOOR.substitute())
    d.append(PROJECT.substitute())
    coupled = 'coupled' in spec.prior
    if coupled:
        d.append(coupled_code(spec))
    d += [_blend_code(spec), _answer_code(spec),
          GATE.substitute(GATE_COUPLED if coupled else GATE_DIAGONAL), _correction_code(spec)]
    detail = ''.join(d)
    return _HEADER.format(
        banner=banner, guard=guard, ns=namespace, N=N, n=spec.n, E=E,
        names=names, guarantee=_string(spec.guarantee), method=_string(spec.method),
        has_correction='true' if c is not None else 'false',
        conservative='true' if c is not None and c['basis'] is not None else 'false',
        detail=detail)


_HEADER = """\
{banner}
#ifndef {guard}
#define {guard}

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>

namespace {ns} {{

/// number of joints (generalized velocities), training samples and GP elements of D
constexpr std::size_t N = {N};
constexpr std::size_t n_train = {n};
constexpr std::size_t n_elements = {E};
/// the joint order of every array argument
inline constexpr const char* joint_names[N] = {{{names}}};
/// the passivity guarantee every answer carries, proven at export as the frozen node proves it
inline constexpr const char* guarantee = {guarantee};
inline constexpr const char* certificate_method = {method};
/// the model has a correction (offsets, and with has_conservative a dV/dq(q) term)
constexpr bool has_correction = {has_correction};
constexpr bool has_conservative = {conservative};

namespace detail {{
{detail}}}  // namespace detail

/// The model's damping force at qd[N]: load_model(M).predict(qd) after the export's proof.
inline void model_damping(const double* qd, double* tau) noexcept {{
  double D[N * N];
  detail::model_answer(qd, tau, D);
}}

/// The model's damping matrix D[N * N] (row-major) at qd: load_model(M).damping_matrix(qd).
inline void model_damping_matrix(const double* qd, double* D) noexcept {{
  double tau[N];
  detail::model_answer(qd, tau, D);
}}

/// The damping force the frozen node publishes (~/damping_force): the model's answer through
/// its output gate (a non-passive or non-finite answer replaced by the passive prior, an answer
/// beyond 1.5 x the largest learned force scaled down). qd . tau >= 0 under a passive mode.
inline void damping(const double* qd, double* tau) noexcept {{
  double D[N * N];
  detail::model_answer(qd, tau, D);
  detail::gate(qd, tau, D, false);
}}

/// The damping matrix the frozen node publishes with that force (D[N * N], row-major).
inline void damping_matrix(const double* qd, double* D) noexcept {{
  double tau[N];
  detail::model_answer(qd, tau, D);
  detail::gate(qd, tau, D, true);
}}

/// Both at once (one evaluation): tau[N] = damping(qd), D[N * N] = damping_matrix(qd).
inline void damping_with_matrix(const double* qd, double* tau, double* D) noexcept {{
  detail::model_answer(qd, tau, D);
  detail::gate(qd, tau, D, true);
}}

/// The learned conservative correction dV/dq at the pose q[N] (~/rigid_body_correction;
/// zeros without one), without the offsets.
inline void conservative(const double* q, double* tau) noexcept {{
  detail::conservative_part(q, tau);
}}

/// The whole correction at q: conservative part plus offsets (Correction.__call__).
inline void correction(const double* q, double* tau) noexcept {{
  detail::conservative_part(q, tau);
  for (std::size_t i = 0; i < N; ++i) tau[i] = tau[i] + detail::OFFSETS[i];
}}

/// The friction torque to compensate at (q, qd): damping(qd) + correction(q), the node's
/// published force plus the correction and offsets, as predict_residual adds them.
inline void friction(const double* q, const double* qd, double* tau) noexcept {{
  double c[N];
  damping(qd, tau);
  correction(q, c);
  for (std::size_t i = 0; i < N; ++i) tau[i] += c[i];
}}

/// load_model(M).predict_residual(q, qd): the model's damping force plus the correction.
inline void model_residual(const double* q, const double* qd, double* tau) noexcept {{
  double c[N];
  model_damping(qd, tau);
  correction(q, c);
  for (std::size_t i = 0; i < N; ++i) tau[i] += c[i];
}}

}}  // namespace {ns}

#endif  // {guard}
"""

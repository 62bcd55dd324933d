"""
The fixed C++ of a generated header: the functions every model shares (``cpp`` fills them in).

Each piece is a :class:`string.Template` (``$name`` placeholders, C++ uses no ``$``) in the
generated namespace's ``detail``; each mirrors one Python function, named beside it, operation
for operation where the order matters for rounding. Plain arithmetic only: no allocation, no
exceptions, no I/O; ``std::exp``, ``std::tanh``, ``std::sin``, ``std::cos`` of ``<cmath>``
where a kernel exponent does not need the fast one.
"""
from string import Template

__all__ = ['EXP', 'KERNEL', 'KERNEL_SCALAR', 'KERNEL_NONE', 'PSD_FLOOR', 'PROJECT', 'GATE',
           'GATE_DIAGONAL', 'CHAIN', 'TANH_OVER']

#: exp(x) in plain arithmetic, on one number or a vector of them (GCC/clang vector extensions,
#: so the element loop runs as SIMD where the target has it: SSE2, AVX, AVX-512, NEON):
#: Cody-Waite reduction by ln 2 and a degree-13 Taylor polynomial in Estrin's form, within a few
#: ulps of std::exp; exponents below -600 give 0 (online/learner/plan.py's EXP_FLOOR: the kernel
#: there is < 1e-260, nothing a float64 answer holds, and no subnormal number is ever made)
EXP = Template(r"""
#if defined(__GNUC__)
#define DGP_EXPORT_INLINE __attribute__((always_inline)) inline
#else
#define DGP_EXPORT_INLINE inline
#endif
template <class D, class U>
// in place (no vector argument ABI)
DGP_EXPORT_INLINE void exp_floor(D& x, const D& zero) noexcept {
  const D lo = zero - 600.0, shift = zero + 6755399441055744.0;  // 1.5 * 2^52: round to k
  const D xc = x < lo ? lo : x;
  D kd = xc * 1.4426950408889634 + shift;
  U ki;
  std::memcpy(&ki, &kd, sizeof ki);
  kd -= shift;
  const D r = (xc - kd * 6.93147180369123816490e-01) - kd * 1.90821492927058770002e-10;
  const D r2 = r * r, r4 = r2 * r2, r8 = r4 * r4;
  const D a0 = 1.0 + r, a1 = 0.5 + r * (1.0 / 6.0), a2 = (1.0 / 24.0) + r * (1.0 / 120.0),
          a3 = (1.0 / 720.0) + r * (1.0 / 5040.0), a4 = (1.0 / 40320.0) + r * (1.0 / 362880.0),
          a5 = (1.0 / 3628800.0) + r * (1.0 / 39916800.0),
          a6 = (1.0 / 479001600.0) + r * (1.0 / 6227020800.0);
  const D p = ((a0 + a1 * r2) + (a2 + a3 * r2) * r4) + ((a4 + a5 * r2) + a6 * r4) * r8;
  U pb;
  std::memcpy(&pb, &p, sizeof pb);
  pb += ki << 52;  // times 2^k, k >= -866: a normal number
  D out;
  std::memcpy(&out, &pb, sizeof out);
  x = x < lo ? zero : out;
}
""")

#: tanh(a / eps) / a, continuous at 0 (gp/friction_means.py ``_tanh_over``)
TANH_OVER = Template(r"""
inline double tanh_over(double a, double eps) noexcept {
  return a < 1e-6 * eps ? 1.0 / eps : std::tanh(a / eps) / a;
}
""")

#: the element corrections at one standardized query (gp/posterior.py ``_element_weights``):
#: acc[e] = sum_j exp(-0.5 sum_d (x_d - X_jd)^2 il2_ed) v_je, as many elements per vector as
#: the target's registers hold (2 with SSE2 or NEON, 4 with AVX, 8 with AVX-512: a wider
#: vector than the registers is split by the compiler, and ran 1.3x (-O2) to 5x (AVX2) slower).
#: On x86 built for less than AVX-512 (plain -O2), the 4- and 8-lane versions are compiled for
#: AVX2 and AVX-512 too and the processor's best is taken at run time (``__builtin_cpu_supports``,
#: as numpy and OpenBLAS do): the real Panda's 49-element Full-D 63 -> 17 us per call at -O2.
#: Each lane is one element summed over j in the same order at every width: the same answers
#: up to the contraction of a multiply-add. ``DGP_EXPORT_NO_DISPATCH``: the compile-time width.
KERNEL = Template(r"""
#if defined(__GNUC__) && !defined(DGP_EXPORT_SCALAR)
#if defined(__AVX512F__)
constexpr std::size_t LANES = 8;
#elif defined(__AVX__)
constexpr std::size_t LANES = 4;
#else
constexpr std::size_t LANES = 2;
#endif
static_assert(NE % 8 == 0, "NE is padded to a multiple of every vector width");
template <std::size_t W> struct lanes_of;  // the vector types of W doubles (not dependent)
template <> struct lanes_of<2> {
  typedef double d __attribute__((vector_size(16)));
  typedef std::uint64_t u __attribute__((vector_size(16)));
};
template <> struct lanes_of<4> {
  typedef double d __attribute__((vector_size(32)));
  typedef std::uint64_t u __attribute__((vector_size(32)));
};
template <> struct lanes_of<8> {
  typedef double d __attribute__((vector_size(64)));
  typedef std::uint64_t u __attribute__((vector_size(64)));
};
template <std::size_t W>
DGP_EXPORT_INLINE void element_sums_w(const double* x, double* acc) noexcept {
  typedef typename lanes_of<W>::d vecd;
  typedef typename lanes_of<W>::u vecu;
  vecd a[NE / W], s, il, v;
  const vecd zero = {};
  for (std::size_t b = 0; b < NE / W; ++b) a[b] = zero;
  for (std::size_t j = 0; j < n_train; ++j) {
    double d2[N];
    for (std::size_t d = 0; d < N; ++d) {
      const double t = x[d] - X[j][d];
      d2[d] = t * t;
    }
    for (std::size_t b = 0; b < NE / W; ++b) {
      std::memcpy(&il, &IL2[0][W * b], sizeof il);
      s = d2[0] * il;
      for (std::size_t d = 1; d < N; ++d) {
        std::memcpy(&il, &IL2[d][W * b], sizeof il);
        s += d2[d] * il;
      }
      std::memcpy(&v, &V[j][W * b], sizeof v);
      s *= -0.5;
      exp_floor<vecd, vecu>(s, zero);
      a[b] += s * v;
    }
  }
  std::memcpy(acc, a, sizeof a);
}
#if (defined(__x86_64__) || defined(__i386__)) && !defined(__AVX512F__) && \
    !defined(DGP_EXPORT_NO_DISPATCH)
#define DGP_EXPORT_DISPATCH 1
__attribute__((target("avx512f"))) inline void element_sums_avx512(const double* x,
                                                                    double* acc) noexcept {
  element_sums_w<8>(x, acc);
}
__attribute__((target("avx2,fma"))) inline void element_sums_avx2(const double* x,
                                                                   double* acc) noexcept {
  element_sums_w<4>(x, acc);
}
#endif
inline void element_sums(const double* x, double* acc) noexcept {
#if defined(DGP_EXPORT_DISPATCH)
  if (__builtin_cpu_supports("avx512f")) return element_sums_avx512(x, acc);
  if (LANES < 4 && __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
    return element_sums_avx2(x, acc);
#endif
  element_sums_w<LANES>(x, acc);
}
#else
inline void element_sums(const double* x, double* acc) noexcept {
  for (std::size_t e = 0; e < NE; ++e) acc[e] = 0.0;
  for (std::size_t j = 0; j < n_train; ++j) {
    double d2[N];
    for (std::size_t d = 0; d < N; ++d) {
      const double t = x[d] - X[j][d];
      d2[d] = t * t;
    }
    for (std::size_t e = 0; e < NE; ++e) {
      double s = d2[0] * IL2[0][e];
      for (std::size_t d = 1; d < N; ++d) s += d2[d] * IL2[d][e];
      s *= -0.5;
      exp_floor<double, std::uint64_t>(s, 0.0);
      acc[e] += s * V[j][e];
    }
  }
}
#endif
""")

#: the same, one element at a time: fewer elements than a vector holds (an arm whose joints keep
#: their own friction curve: up to N of the N x N), where eight padded lanes cost 8x the exps
KERNEL_SCALAR = Template(r"""
inline void element_sums(const double* x, double* acc) noexcept {
  for (std::size_t e = 0; e < NE; ++e) acc[e] = 0.0;
  for (std::size_t j = 0; j < n_train; ++j) {
    double d2[N];
    for (std::size_t d = 0; d < N; ++d) {
      const double t = x[d] - X[j][d];
      d2[d] = t * t;
    }
    for (std::size_t e = 0; e < NE; ++e) {
      double s = d2[0] * IL2[0][e];
      for (std::size_t d = 1; d < N; ++d) s += d2[d] * IL2[d][e];
      s *= -0.5;
      exp_floor<double, std::uint64_t>(s, 0.0);
      acc[e] += s * V[j][e];
    }
  }
}
""")

#: no element switched on (every output its prior alone): nothing to sum
KERNEL_NONE = Template(r"""
inline void element_sums(const double*, double* acc) noexcept {
  for (std::size_t e = 0; e < NE; ++e) acc[e] = 0.0;
}
""")

#: the eigenvalue floor of the symmetric part (gp/psd.py ``psd_clip``, ``smooth_floor``):
#: Gershgorin first, then a cyclic Jacobi eigen-decomposition of S = (D + D^T) / 2
PSD_FLOOR = Template(r"""
inline void psd_floor(double* D) noexcept {
  double S[N][N];
  for (std::size_t i = 0; i < N; ++i)
    for (std::size_t j = 0; j < N; ++j) S[i][j] = 0.5 * (D[i * N + j] + D[j * N + i]);
  double low = 0.0;
  for (std::size_t i = 0; i < N; ++i) {
    double off = 0.0;
    for (std::size_t j = 0; j < N; ++j) off += std::fabs(S[i][j]);
    const double g = S[i][i] + std::fabs(S[i][i]) - off;
    low = (i == 0 || g < low) ? g : low;
  }
  if (!(low < PSD_DELTA)) return;  // every eigenvalue >= delta: D as it is
  double Vec[N][N];
  for (std::size_t i = 0; i < N; ++i)
    for (std::size_t j = 0; j < N; ++j) Vec[i][j] = i == j ? 1.0 : 0.0;
  for (int sweep = 0; sweep < 60; ++sweep) {
    double off = 0.0, diag = 0.0;
    for (std::size_t i = 0; i < N; ++i) {
      diag += S[i][i] * S[i][i];
      for (std::size_t j = i + 1; j < N; ++j) off += S[i][j] * S[i][j];
    }
    if (!(off > 1e-36 * diag)) break;  // off-diagonal below (1e-18 |S|)^2: diagonal
    for (std::size_t p = 0; p + 1 < N; ++p) {
      for (std::size_t q = p + 1; q < N; ++q) {
        const double apq = S[p][q];
        if (apq == 0.0) continue;
        const double theta = (S[q][q] - S[p][p]) / (2.0 * apq);
        const double t = (theta >= 0.0 ? 1.0 : -1.0) /
                         (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
        const double c = 1.0 / std::sqrt(t * t + 1.0), sn = t * c;
        for (std::size_t k = 0; k < N; ++k) {
          const double akp = S[k][p], akq = S[k][q];
          S[k][p] = c * akp - sn * akq;
          S[k][q] = sn * akp + c * akq;
        }
        for (std::size_t k = 0; k < N; ++k) {
          const double apk = S[p][k], aqk = S[q][k];
          S[p][k] = c * apk - sn * aqk;
          S[q][k] = sn * apk + c * aqk;
        }
        S[p][q] = S[q][p] = 0.0;
        for (std::size_t k = 0; k < N; ++k) {
          const double vkp = Vec[k][p], vkq = Vec[k][q];
          Vec[k][p] = c * vkp - sn * vkq;
          Vec[k][q] = sn * vkp + c * vkq;
        }
      }
    }
  }
  double g[N];
  bool hit = false;
  for (std::size_t k = 0; k < N; ++k) {
    const double lam = S[k][k], y = lam / PSD_DELTA;
    g[k] = y >= 1.0 ? 0.0 : (y <= -1.0 ? -lam : 0.25 * PSD_DELTA * (y - 1.0) * (y - 1.0));
    hit = hit || g[k] > 0.0;
  }
  if (!hit) return;
  for (std::size_t i = 0; i < N; ++i)
    for (std::size_t j = 0; j < N; ++j) {
      double add = 0.0;
      for (std::size_t k = 0; k < N; ++k) add += Vec[i][k] * g[k] * Vec[j][k];
      D[i * N + j] += add;
    }
}
""")

#: the W-norm projection onto qd . tau >= 0 (gp/policy.py ``_project``, ``projection_lambda``,
#: ``project_passive``); ``dq``: D qd when the caller has computed it apart from tau
PROJECT = Template(r"""
inline double power(const double* q, const double* t) noexcept {
  double p = 0.0;
  for (std::size_t i = 0; i < N; ++i) p += q[i] * t[i];
  return p;
}
inline double tolerance(const double* q, const double* t) noexcept {
  double s = 0.0;
  for (std::size_t i = 0; i < N; ++i) s += std::fabs(q[i]) * std::fabs(t[i]);
  return 8.0 * 2.220446049250313e-16 * s;
}
inline double lambda(const double* q, const double* t) noexcept {
  const double p = power(q, t);
  double den = 0.0;
  for (std::size_t i = 0; i < N; ++i) den += q[i] * W_INV[i] * q[i];
  return (p < 0.0 && den > 0.0) ? -p / den : 0.0;
}
inline void project(const double* q, double* tau, double* D, const double* dq) noexcept {
  if (D != nullptr && dq != tau) {
    const double lam = lambda(q, dq);
    if (lam > 0.0)
      for (std::size_t i = 0; i < N; ++i) D[i * N + i] += lam * W_INV[i];
  }
  if (power(q, tau) >= 0.0) return;
  if (D != nullptr && dq == tau) {
    const double lam = lambda(q, tau);
    if (lam > 0.0)
      for (std::size_t i = 0; i < N; ++i) D[i * N + i] += lam * W_INV[i];
  }
  const double lam = lambda(q, tau);
  for (std::size_t i = 0; i < N; ++i) tau[i] += lam * (q[i] * W_INV[i]);
  for (int step = 0; step < 4; ++step) {  // rounding: a few ulps further where still < 0
    const double p = power(q, tau);
    if (!(p < 0.0)) break;
    double den = 0.0, size = 0.0;
    for (std::size_t i = 0; i < N; ++i) {
      den += q[i] * W_INV[i] * q[i];
      size += std::fabs(q[i]) * std::fabs(tau[i]);
    }
    const double k = (-p + 8.0 * 2.220446049250313e-16 * size) / den;
    for (std::size_t i = 0; i < N; ++i) tau[i] += k * (q[i] * W_INV[i]);
  }
}
""")

#: the frozen node's output gate (online/path/gate.py ``_gate``, ``_prior``, ``_bound``):
#: non-finite or non-passive answers replaced by the fallback (``gp.blend.prior_answer``: the
#: prior times its gains), answers beyond the learned force (or the prior's own force inside
#: the learned box) scaled down. ``$fallback`` sets (tau, D) to the fallback at q (zero where
#: it is not finite); ``$boxed_decl``, ``$boxed_prior``, ``$boxed_force``: the prior's force at
#: the query clipped into the box ``qb`` (its declaration, evaluation, and entry ``i``);
#: :data:`GATE_DIAGONAL` fills them for a diagonal prior, ``coupled_cpp`` for a coupled one
GATE = Template(r"""
inline void gate(const double* q, double* tau, double* D, bool check_d) noexcept {
  bool bad = false;
  for (std::size_t i = 0; i < N; ++i) bad = bad || !std::isfinite(tau[i]);
  if (check_d)
    for (std::size_t i = 0; i < N * N; ++i) bad = bad || !std::isfinite(D[i]);
  if (!bad && GATE_PASSIVE && power(q, tau) < -tolerance(q, tau)) bad = true;
  if (bad) {
$fallback  }
  double limit[N], worst = 0.0;
  for (std::size_t i = 0; i < N; ++i) {
    limit[i] = LIMIT[i];
    const double r = std::fabs(tau[i]) / limit[i];
    worst = r > worst ? r : worst;
  }
  if (!(worst > 1.0)) return;
  double qb[N], $boxed_decl;
  for (std::size_t i = 0; i < N; ++i)
    qb[i] = q[i] < BOX_LO[i] ? BOX_LO[i] : (q[i] > BOX_HI[i] ? BOX_HI[i] : q[i]);
  $boxed_prior
  worst = 0.0;
  for (std::size_t i = 0; i < N; ++i) {
    double pr = std::fabs($boxed_force);
    pr = std::isfinite(pr) ? pr : 0.0;
    limit[i] = limit[i] > pr ? limit[i] : pr;
    const double r = std::fabs(tau[i]) / limit[i];
    worst = r > worst ? r : worst;
  }
  if (!(worst > 1.0)) return;
  double s[N], tb[N];
  for (std::size_t i = 0; i < N; ++i) {
    const double a = std::fabs(tau[i]);
    const double r = limit[i] / (a > 1e-300 ? a : 1e-300);
    s[i] = r < 1.0 ? r : 1.0;
    tb[i] = tau[i] * s[i];
  }
  if (GATE_PASSIVE && power(q, tb) < tolerance(q, tb)) {  // uniformly, 2^-e <= 1 / worst: exact
    int e = 0;
    std::frexp(worst, &e);
    for (std::size_t i = 0; i < N; ++i) s[i] = std::ldexp(1.0, -e);
  }
  for (std::size_t i = 0; i < N; ++i) {
    tau[i] = tau[i] * s[i];
    for (std::size_t j = 0; j < N; ++j) D[i * N + j] *= s[i];
  }
}
""")

#: the gate's prior of a diagonal prior: ``diag(a m_d(q)) q`` and ``diag(a m_d(q))``
GATE_DIAGONAL = {
    'fallback': r"""    double md[N], fb[N];
    prior_diag(q, md);
    bool finite = true;
    for (std::size_t i = 0; i < N; ++i) {
      md[i] = md[i] * GAIN[i];
      fb[i] = md[i] * q[i];
      finite = finite && std::isfinite(fb[i]);
    }
    for (std::size_t i = 0; i < N; ++i) {
      tau[i] = finite ? fb[i] : 0.0;
      for (std::size_t j = 0; j < N; ++j) D[i * N + j] = (i == j && finite) ? md[i] : 0.0;
    }
""",
    'boxed_decl': 'md[N]', 'boxed_prior': 'prior_diag(qb, md);', 'boxed_force': 'md[i] * qb[i]'}

#: the gravity torque of a kinematic tree of revolute joints (export/kinematics.py)
CHAIN = Template(r"""
inline void gravity_torque(const double* q, double* out) noexcept {
  double R[J][3][3], p[J][3], mass[J], mom[J][3];
  for (std::size_t i = 0; i < J; ++i) {
    double Rp[3][3] = {{1.0, 0.0, 0.0}, {0.0, 1.0, 0.0}, {0.0, 0.0, 1.0}};
    double pp[3] = {0.0, 0.0, 0.0};
    if (PARENT[i] >= 0) {
      const std::size_t a = static_cast<std::size_t>(PARENT[i]);
      for (std::size_t r = 0; r < 3; ++r) {
        pp[r] = p[a][r];
        for (std::size_t c = 0; c < 3; ++c) Rp[r][c] = R[a][r][c];
      }
    }
    const double* ax = AXIS[i];
    const double ang = q[COORD[i]], c = std::cos(ang), sn = std::sin(ang), t = 1.0 - c;
    const double Rq[3][3] = {
        {t * ax[0] * ax[0] + c, t * ax[0] * ax[1] - sn * ax[2], t * ax[0] * ax[2] + sn * ax[1]},
        {t * ax[0] * ax[1] + sn * ax[2], t * ax[1] * ax[1] + c, t * ax[1] * ax[2] - sn * ax[0]},
        {t * ax[0] * ax[2] - sn * ax[1], t * ax[1] * ax[2] + sn * ax[0], t * ax[2] * ax[2] + c}};
    double Rj[3][3];
    for (std::size_t r = 0; r < 3; ++r) {
      p[i][r] = pp[r] + (Rp[r][0] * P0[i][0] + Rp[r][1] * P0[i][1] + Rp[r][2] * P0[i][2]);
      for (std::size_t k = 0; k < 3; ++k)
        Rj[r][k] = Rp[r][0] * R0[i][0][k] + Rp[r][1] * R0[i][1][k] + Rp[r][2] * R0[i][2][k];
    }
    for (std::size_t r = 0; r < 3; ++r)
      for (std::size_t k = 0; k < 3; ++k)
        R[i][r][k] = Rj[r][0] * Rq[0][k] + Rj[r][1] * Rq[1][k] + Rj[r][2] * Rq[2][k];
    mass[i] = TH_M[i];
    for (std::size_t r = 0; r < 3; ++r)
      mom[i][r] = TH_M[i] * p[i][r] +
                  (R[i][r][0] * TH_H[i][0] + R[i][r][1] * TH_H[i][1] + R[i][r][2] * TH_H[i][2]);
  }
  for (std::size_t k = J; k-- > 0;) {
    if (PARENT[k] < 0) continue;
    const std::size_t a = static_cast<std::size_t>(PARENT[k]);
    mass[a] += mass[k];
    for (std::size_t r = 0; r < 3; ++r) mom[a][r] += mom[k][r];
  }
  for (std::size_t i = 0; i < J; ++i) {
    double z[3], v[3];
    for (std::size_t r = 0; r < 3; ++r) {
      z[r] = R[i][r][0] * AXIS[i][0] + R[i][r][1] * AXIS[i][1] + R[i][r][2] * AXIS[i][2];
      v[r] = mom[i][r] - p[i][r] * mass[i];
    }
    const double gx = -GRAVITY[0], gy = -GRAVITY[1], gz = -GRAVITY[2];
    out[COORD[i]] = z[0] * (v[1] * gz - v[2] * gy) + z[1] * (v[2] * gx - v[0] * gz) +
                    z[2] * (v[0] * gy - v[1] * gx);
  }
}
""")

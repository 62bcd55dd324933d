"""
Rigorous branch-and-bound verification of ``q^T D(q) q >= 0`` on a box.

The structural certificate.

The posterior damping matrix of a D-GP is ``D(q) = diag(m_d) + C(q)`` with
``C_mn(q) = f_mn * sum_i a_{mn,i} * sf2_mn * exp(-0.5 |(x - x_i) / l_mn|^2)`` (``x = q / s_x``
standardized, ``f_mn = s_y,m / s_x,n`` the unit conversion, ``a_{mn,i} = x_{n,i} alpha_{m,i}``).
Over a box every exponential lies between its values at the farthest and nearest box point to
``x_i`` (per-dimension distance intervals), which gives rigorous interval bounds ``[Dlo, Dhi]`` of
every element over the box. A box is proven passive by either test:

(a) *matrix test*: the box lies in one closed orthant with signs ``s``; then for ``z = |q|``,
    ``q^T D q = z^T (S D S) z >= z^T A z`` with ``A_mn = min over [Dlo, Dhi] of s_m s_n D_mn``;
    ``A`` copositive (exact check, ``passivity.copositivity_margin``) proves it. Homogeneous in
    ``q``, so it also works in boxes that touch ``q = 0``.
(b) *power test*: interval arithmetic on ``sum_mn [q_m q_n] * [D_mn] >= 0``. Strong where one
    large dissipative term dominates (airspeed times lift).

Boxes that fail both are bisected along the side along which the power's enclosure widens most.
An exactly evaluated ``P(center) < 0`` ends the search with a counterexample. The search also ends,
uncertified, when ``max_boxes`` boxes have been examined. Cost per examined box: O(n * E * N).
"""
from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Callable, Optional

import numpy as np

from .copositive import copositivity_margin

__all__ = ['CorrectionTerms', 'verify_box', 'BoxResult']


@dataclass
class CorrectionTerms:
    """
    The GP correction of a D-GP in verifiable form (see module docstring).

    X: (n, N) standardized training inputs; elems: list of (m, n); sf2: (E,); ls: (E, N);
    coef: (E, n) = x_{n,i} * alpha_{m,i} * correction_scale; mean: the prior mean
    (``means.PriorMean``: ``diag_bounds`` gives the range of ``m_d`` over a box, ``diag_ref`` its
    typical size for normalized margins); sx, sy: (N,) standardization scales; D_fn: exact
    ``Q (k, N) -> D (k, N, N)`` of the same (unblended) model, used at box centres.
    """

    X: np.ndarray
    elems: list
    sf2: np.ndarray
    ls: np.ndarray
    coef: np.ndarray
    mean: object
    sx: np.ndarray
    sy: np.ndarray
    D_fn: Callable[[np.ndarray], np.ndarray]
    rkhs: Optional[np.ndarray] = None   # (E,) sqrt(a^T E_e a), E_e = exp(-|x_i - x_j|^2_l / 2)

    def __post_init__(self):
        if self.rkhs is None:
            from .kernels import se_ard
            r = np.zeros(len(self.elems))
            for e in range(len(self.elems)):
                a = self.coef[e]
                if self.sf2[e] > 0 and np.any(a):
                    r[e] = np.sqrt(max(float(a @ se_ard(self.X, self.X, self.ls[e], 1.0) @ a),
                                       0.0))
            self.rkhs = r


@dataclass
class BoxResult:
    """
    Result of ``verify_box``.

    ``ok``; ``margin`` (normalized, min over proven leaves); ``leaves`` (lo, hi) arrays of the
    proven partition (reused to re-verify after an update); ``boxes`` examined; ``seconds``;
    ``witness`` q with P(q) < 0 when one was found.
    """

    ok: bool
    margin: float
    leaves: Optional[tuple]
    boxes: int
    seconds: float
    witness: Optional[np.ndarray] = None
    reason: str = ''


def _split_at_zero(lo: np.ndarray, hi: np.ndarray):
    boxes = [(lo.copy(), hi.copy())]
    for d in range(lo.size):
        nxt = []
        for bl, bh in boxes:
            if bl[d] < 0.0 < bh[d]:
                a_hi = bh.copy()
                a_hi[d] = 0.0
                b_lo = bl.copy()
                b_lo[d] = 0.0
                nxt += [(bl, a_hi), (b_lo, bh)]
            else:
                nxt.append((bl, bh))
        boxes = nxt
    return np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes])


def _d_interval(T: CorrectionTerms, lo: np.ndarray, hi: np.ndarray):
    """
    Interval bounds of D over boxes, and which side of each box widens the power bound most.

    lo, hi: (B, N) model units. Returns Dlo, Dhi (B, N, N) and ``sens`` (B, N): per side ``d``,
    how much the power's enclosure widens along it (power units): the elements' centred slopes
    ``|dC_mn/dq_d| h_d`` times ``max|q_m q_n|``. It only chooses where ``verify_box`` bisects,
    so it need not be rigorous.

    Two rigorous enclosures per element, intersected:
    - natural: each exponential between its values at the farthest / nearest box point;
    - second-order centred: exact value and gradient at the box centre ``c`` plus a Hessian
      bound, using ``|d2 k / dx_d dx_e| <= sf2 (1 + r^2) exp(-r^2/2) / (l_d l_e)`` and that
      ``(1 + r^2) exp(-r^2/2)`` decreases for ``r >= 1`` (max ``2 e^-1/2`` at ``r = 1``), with
      ``r`` the scaled distance from the box to the training point, or, whichever is smaller, the
      RKHS bound ``|d2 g| <= sqrt(3) |g|_H sqrt(sf2) / (l_d l_e)`` with ``|g|_H^2 = a^T K_e a``,
      which sees the cancellation of alternating-sign GP weights. The remainder shrinks with the
      square of the box width.
    """
    B, N = lo.shape
    bl = lo / T.sx
    bh = hi / T.sx
    c = 0.5 * (bl + bh)
    h = 0.5 * (bh - bl)
    X = T.X
    # per-dim nearest / farthest squared distances, (B, n, N)
    below = bl[:, None, :] - X[None, :, :]
    above = X[None, :, :] - bh[:, None, :]
    dmin = np.maximum(np.maximum(below, above), 0.0)
    dmax = np.maximum(np.abs(below), np.abs(above))
    dmin *= dmin
    dmax *= dmax
    dc = c[:, None, :] - X[None, :, :]
    dc *= dc
    Dlo, Dhi = T.mean.matrix_bounds(lo, hi)          # the prior's (gp.coupled: its couplings)
    qmax = np.maximum(np.abs(lo), np.abs(hi))                       # (B, N)
    sens = np.zeros((B, N))
    for e, (m, n) in enumerate(T.elems):
        a = T.coef[e]
        if T.sf2[e] == 0.0 or not np.any(a):
            continue
        il2 = 1.0 / T.ls[e] ** 2
        smin = dmin @ il2
        e_hi = np.exp(-0.5 * smin)                # (B, n) largest kernel value in the box
        e_lo = np.exp(-0.5 * (dmax @ il2))        # smallest
        ap = np.maximum(a, 0.0)
        an = np.minimum(a, 0.0)
        f = T.sf2[e] * T.sy[m] / T.sx[n]
        nat_lo = f * (e_lo @ ap + e_hi @ an)
        nat_hi = f * (e_hi @ ap + e_lo @ an)
        # centred second-order enclosure
        d2c = dc @ il2                                              # (B, n)
        kc = np.exp(-0.5 * d2c) * a                                 # (B, n) weighted
        val = kc.sum(axis=1)
        grad = (kc @ X - c * val[:, None]) * il2                    # (B, N)
        phi = np.where(smin >= 1.0, (1.0 + smin) * e_hi, 2.0 * np.exp(-0.5))
        # Hessian bound: local sum of |a_i| or, exploiting cancellation, the RKHS norm
        # (|d2 g| <= |g|_H sqrt(d2 d2' k(x, x)) <= sqrt(3) |g|_H sqrt(sf2) / (l_d l_e))
        s_abs = np.minimum(phi @ np.abs(a), np.sqrt(3.0) * T.rkhs[e])   # (B,)
        hl = h / T.ls[e]                                            # (B, N) half-widths / l
        rem = 0.5 * s_abs * hl.sum(axis=1) ** 2
        lin = (np.abs(grad) * h).sum(axis=1)
        tay_lo = f * (val - lin - rem)
        tay_hi = f * (val + lin + rem)
        Dlo[:, m, n] += np.maximum(nat_lo, tay_lo)
        Dhi[:, m, n] += np.minimum(nat_hi, tay_hi)
        sens += np.abs(f * grad) * h * (qmax[:, m] * qmax[:, n])[:, None]
    return Dlo, Dhi, sens


def _matrix_test(lo, hi, Dlo, Dhi, scale):
    """Test (a). Returns normalized margin (B,), -inf where the box is not in one orthant."""
    B, N = lo.shape
    one = (lo >= 0) | (hi <= 0)
    in_orthant = np.all(one, axis=1)
    out = np.full(B, -np.inf)
    if not np.any(in_orthant):
        return out
    s = np.where(hi[in_orthant] <= 0, -1.0, 1.0)            # (b, N); [0,0] counts as +
    ss = s[:, :, None] * s[:, None, :]
    A = np.where(ss > 0, Dlo[in_orthant], -Dhi[in_orthant])
    out[in_orthant] = copositivity_margin(A) / scale
    return out


def _power_test(lo, hi, Dlo, Dhi, mean_diag):
    """
    Test (b).

    Lower bound of sum_mn q_m D_mn q_n over each box, normalized. (B,)
    """
    B, N = lo.shape
    # q_m q_n intervals
    p = np.stack([lo[:, :, None] * lo[:, None, :], lo[:, :, None] * hi[:, None, :],
                  hi[:, :, None] * lo[:, None, :], hi[:, :, None] * hi[:, None, :]])
    qlo = p.min(axis=0)
    qhi = p.max(axis=0)
    idx = np.arange(N)
    straddle = (lo < 0) & (hi > 0)
    diag_lo = np.where(straddle, 0.0, np.minimum(lo ** 2, hi ** 2))
    qlo[:, idx, idx] = diag_lo
    qhi[:, idx, idx] = np.maximum(lo ** 2, hi ** 2)
    prods = np.stack([qlo * Dlo, qlo * Dhi, qhi * Dlo, qhi * Dhi])
    lb = prods.min(axis=0).sum(axis=(1, 2))
    norm = (np.maximum(lo ** 2, hi ** 2) * np.maximum(mean_diag, 0.0)).sum(axis=1)
    norm = np.where(norm > 0, norm, 1.0)
    return lb / norm


#: weight of the widest side in lengthscales against the largest widening of the power bound
#: when ``_bisect`` chooses a side (each normalized to 1 per box)
WIDTH_WEIGHT = 1.0


def _bisect(fl, fh, centre, sens, scale):
    """
    Halve each failed box (fl, fh) at its ``centre`` across the side with the largest ``sens``.

    (The side along which the power's enclosure widens most, ``_d_interval``: the widest side
    in lengthscales is not it when one large element varies slowly along a long side, 15000
    boxes instead of 1100 on the A320 envelope.) The widest side in units of ``scale`` (the
    shortest lengthscales) breaks ties, and decides where the correction is flat. Returns the
    children (lo, hi), the first halves of all boxes, then the second halves.
    """
    w = (fh - fl) / scale
    s = sens / np.maximum(sens.max(axis=1, keepdims=True), 1e-300)
    d = np.argmax(s + WIDTH_WEIGHT * w / np.maximum(w.max(axis=1, keepdims=True), 1e-300), axis=1)
    r = np.arange(len(fl))
    mid = centre[r, d]
    a_hi = fh.copy()
    a_hi[r, d] = mid
    b_lo = fl.copy()
    b_lo[r, d] = mid
    return np.concatenate([fl, b_lo]), np.concatenate([a_hi, fh])


def verify_box(T: CorrectionTerms, lo: np.ndarray, hi: np.ndarray, *, max_boxes: int = 20000,
               batch: int = 512, leaves: Optional[tuple] = None, tol: float = 0.0) -> BoxResult:
    """
    Prove ``q^T D(q) q >= 0`` for all q in the box ``[lo, hi]`` (model units, (N,) each).

    leaves: a previous partition of the same box (from ``BoxResult.leaves``) to start from.
    Returns a ``BoxResult``; ``ok`` is rigorous (up to floating-point rounding of the bounds).
    Worst first: each batch takes the queued boxes whose parent had the lowest margin, so a
    counterexample (a box centre with ``P < 0``) is found after few boxes; a proof examines
    the same boxes in any order.
    """
    t0 = time.perf_counter()
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    if leaves is not None and len(leaves[0]):
        qlo, qhi = np.array(leaves[0], float), np.array(leaves[1], float)
    else:
        qlo, qhi = _split_at_zero(lo, hi)
    key = np.zeros(len(qlo))
    mref = np.maximum(np.asarray(T.mean.diag_ref(), float), 0.0)
    scale = max(float(np.max(mref)), 1e-300)
    lmin = np.min(T.ls, axis=0) * T.sx if len(T.elems) else np.ones(lo.size)
    done_lo, done_hi = [], []
    margin = np.inf
    examined = 0
    while len(qlo):
        if examined >= max_boxes:
            return BoxResult(False, -np.inf, None, examined, time.perf_counter() - t0,
                             reason=f'box budget {max_boxes} exhausted before a proof')
        if len(qlo) > batch:
            take = np.argpartition(key, batch - 1)[:batch]
            rest = np.ones(len(qlo), dtype=bool)
            rest[take] = False
            bl, bh = qlo[take], qhi[take]
            qlo, qhi, key = qlo[rest], qhi[rest], key[rest]
        else:
            bl, bh = qlo, qhi
            qlo, qhi, key = qlo[:0], qhi[:0], key[:0]
        examined += len(bl)
        Dlo, Dhi, sens = _d_interval(T, bl, bh)
        ma = _matrix_test(bl, bh, Dlo, Dhi, scale)
        mb = _power_test(bl, bh, Dlo, Dhi, mref)
        m = np.maximum(ma, mb)
        ok = m >= tol
        if np.any(ok):
            margin = min(margin, float(m[ok].min()))
            done_lo.append(bl[ok])
            done_hi.append(bh[ok])
        if np.all(ok):
            continue
        fl, fh = bl[~ok], bh[~ok]
        centre = 0.5 * (fl + fh)
        Dc = T.D_fn(centre)
        Pc = np.einsum('bi,bij,bj->b', centre, Dc, centre)
        normc = (centre ** 2 * mref).sum(axis=1) + 1e-300
        neg = Pc < -1e-10 * normc
        if np.any(neg):
            k = int(np.argmin(Pc / normc))
            return BoxResult(False, float(Pc[k] / normc[k]), None, examined,
                             time.perf_counter() - t0, witness=centre[k],
                             reason='counterexample: q^T D(q) q < 0 inside the domain')
        clo, chi = _bisect(fl, fh, centre, sens[~ok], lmin)
        qlo, qhi = np.concatenate([qlo, clo]), np.concatenate([qhi, chi])
        mf = m[~ok]
        mf = np.where(np.isnan(mf), -1e300, np.maximum(mf, -1e300))
        key = np.concatenate([key, np.tile(mf, 2)])
    leaves_out = (np.concatenate(done_lo) if done_lo else np.zeros((0, lo.size)),
                  np.concatenate(done_hi) if done_hi else np.zeros((0, lo.size)))
    if margin == np.inf:
        margin = 0.0
    return BoxResult(True, float(margin), leaves_out, examined, time.perf_counter() - t0)

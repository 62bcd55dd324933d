"""
Coupled transmissions: one motor's friction shared by two joints, as a passive prior part.

Many industrial wrists drive two joints from one motor (or two motors through a differential):
that motor turns at ``m = qd_a + s qd_b`` (``s = +1`` or ``-1``) and its friction ``f(m)``
reaches both joints, ``tau_a += f(m)``, ``tau_b += s f(m)``. Neither joint's share is a function
of its own velocity, so no per-joint friction curve can carry it. This part adds, per pair,

    f(m) = c_c tanh(m / EPS) + c_v m,   c_c, c_v >= 0      (:func:`motor_columns`)

to the damping force, i.e. ``g(m) t t^T`` to the damping matrix with ``t = e_a + s e_b`` and
``g(m) = f(m) / m >= 0`` (even, non-increasing in ``|m|``; ``c_c / EPS + c_v`` at 0).

**Passivity.** ``qd^T g(m) t t^T qd = g(m) m^2 >= 0``: each pair adds a positive semi-definite
matrix, so the prior stays passive at every velocity, inside and outside the data, without a
projection. Its matrix is not diagonal (``is_diagonal`` False) but the base's diagonal plus a
positive semi-definite part (``psd_over_diagonal``): ``qd^T M qd >= sum_i m_inf,i qd_i^2`` with
the base's infimum, so the global certificate (``diag(m_inf) - B`` copositive) proves the
posterior's symmetric part PSD as it does over a diagonal prior, and the earned-gain blend is the
congruence ``S D S + R M R`` (``gp.blend``).

Velocities ``Qd`` (k, N) [rad/s on an arm], forces (k, N) [N m]. Pure numpy; no rclpy.
"""
from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np

from .friction_means import _tanh_over
from .means import mean_from_dict, PriorMean, register_mean
from .prior_mean import OverDiagonalMean

__all__ = ['TransmissionMean', 'motor_columns', 'EPS', 'FEATURES']

#: the motor's Coulomb smoothing velocity (rad/s of the motor speed ``m``)
EPS = 0.01
#: features per motor: its Coulomb and viscous columns
FEATURES = 2


def motor_columns(m: np.ndarray) -> np.ndarray:
    """Return a motor's friction columns at motor speeds m (...,): [tanh(m / EPS), m], (..., 2)."""
    m = np.asarray(m, float)
    return np.stack([np.tanh(m / EPS), m], axis=-1)


def _gain(a: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """``g = f(m) / m`` at motor speeds ``a = |m|`` (...,); coef (2,) [Coulomb, viscous]."""
    return coef[0] * _tanh_over(a, np.float64(EPS)) + coef[1]


@register_mean
class TransmissionMean(OverDiagonalMean):
    """
    A diagonal passive prior plus coupled transmissions (module docstring).

    base : a fitted diagonal prior (``is_diagonal``); pairs : ((a, b, s), ...) distinct joints
    a, b and s = +1 or -1; coef : (len(pairs), 2) each motor's [Coulomb N m, viscous N m s/rad],
    non-negative.
    """

    name = 'transmission'
    psd_over_diagonal = True

    def __init__(self, base: PriorMean, pairs: Sequence[Tuple[int, int, int]], coef):
        super().__init__(base, 'transmission prior')
        self.pairs = tuple((int(a), int(b), int(s)) for a, b, s in pairs)
        self.coef = np.asarray(coef, float).reshape(len(self.pairs), FEATURES)
        if not self.pairs:
            raise ValueError('transmission prior: no pair')
        if not (np.all(np.isfinite(self.coef)) and np.all(self.coef >= 0.0)):
            raise ValueError('transmission prior: motor coefficients must be finite and >= 0')
        for a, b, s in self.pairs:
            if a == b or min(a, b) < 0 or s not in (1, -1):
                raise ValueError(f'transmission prior: pair {(a, b, s)} is not two distinct '
                                 'joints and a sign +1 or -1')
        # every motor at once (the message path answers one velocity at a time): its joints,
        # sign, the direction t = e_a + s e_b as a row of T (P, N) and t t^T's entries
        self._a = np.array([a for a, _, _ in self.pairs], dtype=np.intp)
        self._b = np.array([b for _, b, _ in self.pairs], dtype=np.intp)
        self._s = np.array([s for _, _, s in self.pairs], dtype=float)
        self._top = int(max(max(a, b) for a, b, _ in self.pairs))
        self._T = {}                # N -> (T (P, N), T * T (P, N), t t^T (P, N, N))

    def _check(self, N: int) -> None:
        if self._top >= N:
            raise ValueError(f'transmission prior: a pair names a joint beyond the {N} given')

    def _directions(self, N: int):
        """Return (T (P, N), T**2 (P, N), t t^T (P, N, N)) of the motors for N joints (cached)."""
        out = self._T.get(N)
        if out is None:
            self._check(N)
            T = np.zeros((len(self.pairs), N))
            T[np.arange(len(self.pairs)), self._a] = 1.0
            T[np.arange(len(self.pairs)), self._b] = self._s
            out = self._T[N] = (T, T * T, T[:, :, None] * T[:, None, :])
        return out

    def _speeds(self, Qd: np.ndarray) -> np.ndarray:
        """Return the motor speeds ``m = qd_a + s qd_b`` (k, P)."""
        return Qd[:, self._a] + self._s * Qd[:, self._b]

    # ------------------------------------------------------------------ values
    def force(self, Qd) -> np.ndarray:
        """Return ``diag(m_d) qd`` plus each motor's ``f(m) t`` (k, N)."""
        Qd = np.atleast_2d(np.asarray(Qd, float))
        T = self._directions(Qd.shape[1])[0]
        m = self._speeds(Qd)
        f = self.coef[:, 0] * np.tanh(m / EPS) + self.coef[:, 1] * m        # (k, P)
        return np.asarray(self.base.force(Qd), float) + f @ T

    def _gains(self, Qd: np.ndarray) -> np.ndarray:
        """``g(m) = f(m) / m`` of every motor (k, P)."""
        return self.coef[:, 0] * _tanh_over(self._speeds(Qd), np.float64(EPS)) + self.coef[:, 1]

    def matrix(self, Qd) -> np.ndarray:
        """Return ``diag(m_d(qd)) + sum g(m) t t^T`` (k, N, N); ``force = matrix @ qd``."""
        Qd = np.atleast_2d(np.asarray(Qd, float))
        tt = self._directions(Qd.shape[1])[2]
        M = np.array(self.base.matrix(Qd), float)
        return M + np.einsum('kp,pij->kij', self._gains(Qd), tt)

    def diag(self, Qd) -> np.ndarray:
        """Return the diagonal of :meth:`matrix` (k, N); the force is not ``diag * qd`` here."""
        Qd = np.atleast_2d(np.asarray(Qd, float))
        T2 = self._directions(Qd.shape[1])[1]
        return np.asarray(self.base.diag(Qd), float) + self._gains(Qd) @ T2

    # ------------------------------------------------------------------ bounds
    def _gain_bounds(self, lo, hi, pair, c):
        """Range of ``g(m)`` over boxes [lo, hi] (B, N): (glo, ghi) (B,) each."""
        a, b, s = pair
        mlo = lo[:, a] + np.minimum(s * lo[:, b], s * hi[:, b])
        mhi = hi[:, a] + np.maximum(s * lo[:, b], s * hi[:, b])
        amax = np.maximum(np.abs(mlo), np.abs(mhi))
        amin = np.where((mlo <= 0.0) & (mhi >= 0.0), 0.0,
                        np.minimum(np.abs(mlo), np.abs(mhi)))
        return _gain(amax, c), _gain(amin, c)        # g is non-increasing in |m|

    def matrix_bounds(self, lo, hi):
        """Rigorous range of :meth:`matrix` over boxes [lo, hi] (B, N): (B, N, N) each."""
        lo, hi = np.atleast_2d(np.asarray(lo, float)), np.atleast_2d(np.asarray(hi, float))
        self._check(lo.shape[1])
        Mlo, Mhi = self.base.matrix_bounds(lo, hi)
        Mlo, Mhi = np.array(Mlo, float), np.array(Mhi, float)
        for pair, c in zip(self.pairs, self.coef):
            a, b, s = pair
            glo, ghi = self._gain_bounds(lo, hi, pair, c)
            for i, j in ((a, a), (b, b)):
                Mlo[:, i, j] += glo
                Mhi[:, i, j] += ghi
            olo, ohi = (glo, ghi) if s > 0 else (-ghi, -glo)
            for i, j in ((a, b), (b, a)):
                Mlo[:, i, j] += olo
                Mhi[:, i, j] += ohi
        return Mlo, Mhi

    def diag_ref(self):
        """Return the base's typical ``m_d`` per joint (N,): the proofs' scale of the power."""
        return np.asarray(self.base.diag_ref(), float)

    # ------------------------------------------------------------------ persistence
    def _params(self):
        return {'base': self.base.to_dict(), 'pairs': [list(p) for p in self.pairs],
                'coef': self.coef.tolist()}

    @classmethod
    def _from(cls, d):
        return cls(mean_from_dict(d['base']), [tuple(p) for p in d['pairs']],
                   np.asarray(d['coef'], float))

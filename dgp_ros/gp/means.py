"""
Prior means of the damping force: passive by construction (the paper's Assumption 2).

A D-GP prior mean is ``m_tau(qd) = diag(m_d(qd)) qd`` with ``m_d(qd) >= 0`` element-wise, so it
dissipates ``sum_n m_d,n(qd) qd_n^2 >= 0`` for every ``qd``. Optionally a per-joint constant
``bias`` ``b`` (sensor offset, model error) is learned with it; it is *not* dissipative, so it is
kept apart from the damping force: the data are modelled as ``tau = D(qd) qd + b``, the published
damping force is ``D(qd) qd``, and ``b`` is reported separately.

* :class:`ViscousMean` -- ``m_d`` constant per joint (least squares, clamped at 0): the paper's
  prior.
* :class:`FrictionMean`, :class:`BasisFrictionMean` -- Coulomb + viscous (+ Stribeck) per
  joint, in :mod:`~.friction_means`.
* :class:`ConstantMean` -- a constant force per output (the ARD baseline; no damping structure).

Every mean takes and returns model units: ``Qd`` (k, N) velocities, forces (k, N).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

# the friction priors live in their own module; re-exported so ``gp.means`` names every prior
from .friction_means import _nnls_with_bias, _tanh_over  # noqa: F401
from .friction_means import BasisFrictionMean, FrictionMean
from .prior_mean import PriorMean

__all__ = ['PriorMean', 'ViscousMean', 'FrictionMean', 'BasisFrictionMean', 'ConstantMean',
           'make_mean', 'register_mean',
           'mean_from_dict', 'prior_mean_diag', 'PRIORS']

PRIORS = ('viscous', 'friction', 'friction+stribeck')


def prior_mean_diag(Qd, Tau) -> np.ndarray:
    """
    Least-squares diagonal prior damping ``m_dn = <qd_n, tau_n> / <qd_n, qd_n>``, clamped at 0.

    Qd, Tau: (n, N) (n may be 0). Returns (N,), in units of tau per unit qd. A dimension with
    no excitation (``<qd_n, qd_n> = 0``) gets 0.
    """
    from ._validation import as_matrix
    Qd = as_matrix(Qd, 'Qd', allow_empty=True)
    Tau = as_matrix(Tau, 'Tau', Qd.shape[1], allow_empty=True)
    if Qd.shape[0] != Tau.shape[0]:
        raise ValueError(f'Qd has {Qd.shape[0]} samples but Tau has {Tau.shape[0]}')
    num = np.einsum('ij,ij->j', Qd, Tau)
    den = np.einsum('ij,ij->j', Qd, Qd)
    out = np.zeros(Qd.shape[1])
    ok = den > 0
    out[ok] = num[ok] / den[ok]
    return np.maximum(out, 0.0)


class ViscousMean(PriorMean):
    """
    ``m_d`` constant per joint; see the module docstring.

    Without bias ``m_d`` is :func:`prior_mean_diag`; with bias, ``m_d >= 0`` and ``b`` come from
    one bounded least-squares problem per joint.
    """

    name = 'viscous'

    def __init__(self, bias: bool = False):
        super().__init__(bias)
        self.m_d = None

    def fit(self, Qd, Tau) -> 'ViscousMean':
        N = Qd.shape[1]
        if not self.bias_enabled:
            self.m_d = prior_mean_diag(Qd, Tau)
            self.bias = np.zeros(N)
            return self
        coef, b = _nnls_with_bias([Qd[:, [n]] for n in range(N)], Tau)
        self.m_d = np.array([c[0] for c in coef])
        self.bias = b
        return self

    def diag(self, Qd):
        return np.broadcast_to(self.m_d, Qd.shape)

    def force(self, Qd):
        return Qd * self.m_d

    def diag_bounds(self, lo, hi):
        d = np.broadcast_to(self.m_d, lo.shape)
        return d, d

    def diag_inf(self):
        return self.m_d.copy()

    def _params(self):
        return {'m_d': self.m_d.tolist()}

    @classmethod
    def _from(cls, d):
        m = cls(bias=d.get('bias_enabled', False))
        m.m_d = np.asarray(d['m_d'], float)
        return m


class ConstantMean(PriorMean):
    """A constant force per output: the ARD baseline's prior (the mean of the data)."""

    name = 'constant'
    has_damping = False

    def __init__(self, bias: bool = False):
        super().__init__(bias)
        self.value = None

    def fit(self, Qd, Tau) -> 'ConstantMean':
        self.value = Tau.mean(axis=0)
        self.bias = np.zeros(Tau.shape[1])
        return self

    def force(self, Qd):
        return np.broadcast_to(self.value, Qd.shape)

    def _params(self):
        return {'value': self.value.tolist()}

    @classmethod
    def _from(cls, d):
        m = cls()
        m.value = np.asarray(d['value'], float)
        return m


_BY_NAME = {'viscous': ViscousMean, 'friction': FrictionMean, 'constant': ConstantMean,
            'friction_basis': BasisFrictionMean}


def register_mean(cls) -> type:
    """Make a :class:`PriorMean` subclass readable by :func:`mean_from_dict` (its ``name``)."""
    _BY_NAME[cls.name] = cls
    return cls


def make_mean(prior: str, kind: str, bias: bool = False) -> PriorMean:
    """
    Make the prior mean for a model kind: 'ard' always gets :class:`ConstantMean`.

    prior : 'viscous' | 'friction' | 'friction+stribeck', or a fitted :class:`PriorMean` (a
    frozen prior such as :class:`BasisFrictionMean`; copied, its own bias setting kept).
    """
    if kind == 'ard':
        return ConstantMean()
    if isinstance(prior, PriorMean):
        import copy
        return copy.deepcopy(prior)
    if prior == 'viscous':
        return ViscousMean(bias=bias)
    if prior in ('friction', 'friction+stribeck'):
        return FrictionMean(stribeck=prior.endswith('stribeck'), bias=bias)
    raise ValueError(f"prior must be one of {', '.join(PRIORS)}, got {prior!r}")


def mean_from_dict(d: dict, N: Optional[int] = None) -> PriorMean:
    """Inverse of ``PriorMean.to_dict``; ValueError for anything malformed."""
    try:
        cls = _BY_NAME[d['name']]
        m = cls._from(d)
        m.bias = np.asarray(d.get('bias', []), float)
        if N is not None and m.bias.size != N:
            raise ValueError(f'bias has {m.bias.size} entries, expected {N}')
    except (KeyError, TypeError) as exc:
        raise ValueError(f'malformed prior mean record ({type(exc).__name__}: {exc})') from None
    for k, v in m.to_dict().items():
        if isinstance(v, list) and not np.all(np.isfinite(np.asarray(v, float))):
            raise ValueError(f'prior mean field {k!r} is not finite')
    return m

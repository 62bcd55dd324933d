"""
The base of every prior mean of the damping force: ``m_tau(qd) = diag(m_d(qd)) qd``.

:class:`PriorMean` says what a prior gives the GP and the proofs (its force, its diagonal, their
bounds over boxes, its infimum) and how it is saved; :mod:`~.means` holds the simple priors and
the registry, :mod:`~.friction_means` the friction families. Velocities ``Qd`` (k, N), forces
(k, N), in model units.
"""
from __future__ import annotations

import numpy as np

__all__ = ['PriorMean', 'OverDiagonalMean']


class PriorMean:
    """Base class. Subclasses set ``name`` and implement ``fit``, ``force``, ``diag``."""

    name = ''
    has_damping = True
    #: the damping matrix is ``diag(m_d(qd))`` (every mean here; not ``gp.coupled``'s): what
    #: the global certificates (``diag(m_inf) - B`` copositive) need
    is_diagonal = True
    #: the symmetric part of ``M(qd) - diag(base m_d(qd))`` is positive semi-definite for every
    #: qd (a diagonal prior: nothing beyond it; ``gp.transmission``: its motors), so
    #: ``qd^T M qd >= sum_i diag_inf()_i qd_i^2``: the global certificates hold with
    #: ``diag_inf`` and the earned-gain blend may be the congruence ``S D S + R M R``
    psd_over_diagonal = True

    def __init__(self, bias: bool = False):
        self.bias_enabled = bool(bias)
        self.bias = None          # (N,) after fit: zeros unless ``bias_enabled``

    @property
    def N(self) -> int:
        return self.bias.size

    def __call__(self, Qd: np.ndarray) -> np.ndarray:
        """Return the prior of the measured force, damping part plus bias, (k, N)."""
        return self.force(Qd) + self.bias

    def force(self, Qd: np.ndarray) -> np.ndarray:
        """Return the damping part ``diag(m_d(qd)) qd``, (k, N)."""
        return self.diag(Qd) * Qd

    def raw_force(self, Qd: np.ndarray) -> np.ndarray:
        """Return the force the proofs bound (``matrix_bounds``); the force itself here."""
        return self.force(Qd)

    def diag(self, Qd: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def matrix(self, Qd: np.ndarray) -> np.ndarray:
        """Return the prior's damping matrix ``M(qd)`` (k, N, N), ``force = M qd``."""
        d = np.asarray(self.diag(Qd), float)
        M = np.zeros(d.shape + (d.shape[-1],))
        idx = np.arange(d.shape[-1])
        M[..., idx, idx] = d
        return M

    def diag_bounds(self, lo: np.ndarray, hi: np.ndarray):
        """Range ``(dlo, dhi)`` of ``m_d`` over boxes ``[lo, hi]`` (B, N) each; (B, N) each."""
        raise NotImplementedError  # pragma: no cover

    def matrix_bounds(self, lo: np.ndarray, hi: np.ndarray):
        """Range of ``M(qd)`` over boxes ``[lo, hi]`` (B, N): (B, N, N) each (a proof's input)."""
        dlo, dhi = self.diag_bounds(lo, hi)
        idx = np.arange(dlo.shape[-1])
        Mlo, Mhi = np.zeros(dlo.shape + (dlo.shape[-1],)), np.zeros(dhi.shape + (dhi.shape[-1],))
        Mlo[..., idx, idx], Mhi[..., idx, idx] = dlo, dhi
        return Mlo, Mhi

    def diag_inf(self) -> np.ndarray:
        """``inf_qd m_d(qd)`` per joint, (N,): the margin a global certificate may use."""
        raise NotImplementedError  # pragma: no cover

    def diag_ref(self) -> np.ndarray:
        """Return a typical ``m_d`` per joint, (N,), to normalize certificate margins."""
        return self.diag_inf()

    # persistence: plain numbers and arrays only
    def to_dict(self) -> dict:
        return {'name': self.name, 'bias_enabled': self.bias_enabled,
                'bias': np.asarray(self.bias, float).tolist(), **self._params()}

    def _params(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


class OverDiagonalMean(PriorMean):
    """
    A prior that adds a non-diagonal part to a fitted diagonal ``base``.

    ``gp.coupled`` and ``gp.transmission``: frozen with its base, its diagonal's bounds read off
    its ``matrix_bounds``, its infimum the base's. ``what`` names the prior in errors.
    """

    is_diagonal = False
    psd_over_diagonal = False       # a subclass whose addition is PSD says so

    def __init__(self, base: PriorMean, what: str):
        super().__init__(base.bias_enabled)
        if not getattr(base, 'is_diagonal', True):
            raise ValueError(f'{what}: its base must be a diagonal prior')
        self.base = base
        self.bias = base.bias

    def fit(self, Qd, Tau) -> 'OverDiagonalMean':
        """Keep everything (a frozen prior: the D-GP learns what it leaves); returns self."""
        self.base.fit(Qd, Tau)
        self.bias = self.base.bias
        return self

    def diag_bounds(self, lo, hi):
        Mlo, Mhi = self.matrix_bounds(lo, hi)
        N = Mlo.shape[1]
        return Mlo[:, np.arange(N), np.arange(N)], Mhi[:, np.arange(N), np.arange(N)]

    def diag_inf(self):
        """Return the base's infimum (a global certificate needs ``psd_over_diagonal``)."""
        return np.asarray(self.base.diag_inf(), float)

"""
The fitted attributes of an estimator, read off its posterior (scikit-learn's trailing ``_``).

A mixin of ``models._DGP``: every attribute reads ``posterior_`` (the exact posterior,
``posterior.Posterior``) and raises RuntimeError before ``fit``. Units are the model's:
``X_train_`` (n, N) velocities, ``Y_train_`` (n, N) forces.
"""
from __future__ import annotations

import numpy as np

from .posterior import Posterior

__all__ = ['Fitted']


class Fitted:
    """Read-only views of ``posterior_`` (module docstring)."""

    def _check_fitted(self) -> Posterior:
        p = getattr(self, 'posterior_', None)
        if p is None:
            raise RuntimeError(f'{type(self).__name__} is not fitted: call fit() first')
        return p

    @property
    def N(self) -> int:
        return self._check_fitted().N

    @property
    def n_samples_(self) -> int:
        p = getattr(self, 'posterior_', None)
        return 0 if p is None else p.n

    @property
    def X_train_(self) -> np.ndarray:
        return self._check_fitted().Qd

    @property
    def Y_train_(self) -> np.ndarray:
        return self._check_fitted().Tau

    @property
    def mean_(self):
        """Get the fitted prior mean (``means.PriorMean``)."""
        return self._check_fitted().mean

    @property
    def mean_diag_(self) -> np.ndarray:
        """Lower bound of the prior damping ``m_d(qd)`` per joint (viscous: ``m_d``), (N,)."""
        p = self._check_fitted()
        if not p.structure.has_damping:
            raise AttributeError('ArdGP has a constant prior mean, see mean_')
        return p.mean.diag_inf()

    @property
    def bias_(self) -> np.ndarray:
        """Per-joint constant bias (N,), force units: zeros unless ``bias=True``."""
        return np.array(self._check_fitted().mean.bias, dtype=float)

    @property
    def hyperparams_(self) -> dict:
        """Hyper-parameters, scales and prior mean as lists (``hyperparams=`` to warm start)."""
        p = self._check_fitted()
        return dict(p.hyper.to_dict(), mean=p.mean.to_dict())

    @property
    def jitter_(self) -> float:
        return float(self._check_fitted().jitter.max())

    def log_marginal_likelihood(self) -> float:
        """Sum over outputs of the log marginal likelihood of the training data (standardized)."""
        return self._check_fitted().log_marginal_likelihood()

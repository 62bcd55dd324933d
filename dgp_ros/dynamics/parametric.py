"""
The parametric part's vocabulary: its friction columns, its families and a fitted structure.

What the long history (:mod:`~dgp_ros.dynamics.history`) fits and the learner serves: per joint
``j`` friction ``f_j(v) . c_j`` with ``c_j >= 0`` (viscous ``v``, Coulomb ``tanh(v / eps_k)`` at
:data:`FRICTION_EPS`, Stribeck ``tanh(v / EPS_S) exp(-(v / vs)^2)`` at :data:`STRIBECK_VS`: every
column odd, its coefficient non-negative, so passive; an asymmetric family has a level per
direction of motion, each non-negative: the Coulomb and viscous friction of a geared joint
differ between its directions), an offset, a conservative correction of
the rigid-body model, on an arm the motors of coupled transmissions (``gp.transmission``), and
on a system that is not an arm the couplings of a persistent column
(``gp.coupled``); :class:`ParametricFit` holds one fitted structure and turns it into the D-GP's
prior mean (``friction_mean``) and the correction a saved model carries. No rclpy.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from dgp_ros.gp.joint_element import ElementFit

__all__ = ['ParametricFit', 'friction_columns', 'FRICTION_EPS', 'STRIBECK_VS', 'EPS_S', 'F',
           'FAMILIES']

#: Coulomb smoothing velocities (velocity units: rad/s on an arm)
FRICTION_EPS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2)
#: Stribeck velocities and the smoothing of their sign
STRIBECK_VS = (0.05, 0.2)
EPS_S = 0.01
F = 1 + len(FRICTION_EPS) + len(STRIBECK_VS)
#: friction families -> their (odd) columns among the F per joint; an asymmetric joint adds
#: each one's even twin ``|col|``, F further on (``layout.Unknowns``)
FAMILIES = {'none': [], 'viscous': [0], 'friction': list(range(1 + len(FRICTION_EPS))),
            'friction+stribeck': list(range(F))}


def friction_columns(v: np.ndarray) -> np.ndarray:
    """Friction columns of velocities v (k,) -> (k, 2F): the odd ones, then ``|col|``."""
    v = np.asarray(v, float)
    cols = [v] + [np.tanh(v / e) for e in FRICTION_EPS]
    t = np.tanh(v / EPS_S)
    cols += [t * np.exp(-(v / vs) ** 2) for vs in STRIBECK_VS]
    odd = np.stack(cols, axis=-1)
    return np.concatenate([odd, np.abs(odd)], axis=-1)


@dataclass
class ParametricFit:
    """
    A fitted structure: ``family``, ``offsets``, ``conservative`` and the coefficients.

    ``offsets``: per joint, whether it has one ((N,) bools; a bool for all joints alike).

    coef : (N, F) friction (>= 0) for v >= 0, coef_neg : the same for v < 0 (None: symmetric);
    bias : (N,) offsets; theta : (C,) correction; scores :
    cross-validation score of every candidate ``(family, offsets, conservative) -> score``
    (empty before there are blocks to score); basis : the correction's basis or None.
    """

    family: str
    offsets: bool
    conservative: bool
    coef: np.ndarray
    bias: np.ndarray
    theta: np.ndarray
    basis: object = None
    scores: dict = field(default_factory=dict)
    samples: int = 0
    memory: str = 'all'
    element: Optional[ElementFit] = None
    #: the couplings of the persistent columns: (``gp.coupled.CouplingBasis``, W (N, K)) or None
    coupling: Optional[tuple] = None
    #: friction (>= 0) for v < 0 where a joint is asymmetric (None: every joint symmetric)
    coef_neg: Optional[np.ndarray] = None
    #: per joint, whether its friction has a level per direction of motion ((N,) bools)
    asymmetric: Optional[np.ndarray] = None
    #: coupled transmissions (``gp.transmission``): (pairs ((a, a + 1, s), ...), coef (P, 2)
    #: each motor's [Coulomb, viscous] >= 0), or None
    transmission: Optional[tuple] = None

    def motors(self) -> tuple:
        """Return the motors that serve as the history's structure names them, ((a, s), ...)."""
        return () if self.transmission is None else \
            tuple((a, s) for a, _, s in self.transmission[0])

    def label(self, names=None) -> str:
        """Name the structure (/diagnostics ``structure``); ``names``: the velocities'."""
        on = np.flatnonzero(np.broadcast_to(np.asarray(self.offsets, bool), self.bias.shape))
        parts = [self.family, 'no offsets' if not on.size else 'offsets' if
                 on.size == self.bias.size else 'offsets on ' + ' '.join(str(j) for j in on)]
        asym = np.flatnonzero(np.asarray(self.asymmetric, bool)) if \
            self.asymmetric is not None else np.zeros(0, int)
        if asym.size:
            parts.append('asymmetric' if asym.size == self.bias.size else
                         'asymmetric on ' + ' '.join(str(j) for j in asym))
        if self.basis is not None:
            parts.append('correction' if self.conservative else 'no correction')
        if self.coupling is not None:
            cols = self.coupling[0].cols
            parts.append('couplings through ' + ' '.join(
                str(names[p]) if names is not None and p < len(names) else str(p)
                for p in cols))
        if self.transmission is not None:
            def name(p):
                return str(names[p]) if names is not None and p < len(names) else str(p)
            parts.append('transmission on ' + ' '.join(
                f'{name(a)}{"+" if s > 0 else "-"}{name(b)}' for a, b, s in self.transmission[0]))
        if self.memory != 'all':
            parts.append(f'{self.memory} memory')
        if self.element is not None and self.element.label():
            parts.append(self.element.label())
        return ', '.join(parts)

    def friction_mean(self):
        """Return the friction as a frozen passive prior mean of the D-GP."""
        from dgp_ros.gp.means import BasisFrictionMean
        base = BasisFrictionMean(self.coef, FRICTION_EPS, EPS_S, STRIBECK_VS,
                                 coef_neg=self.coef_neg)
        if self.coupling is not None:
            from dgp_ros.gp.coupled import CoupledMean
            return CoupledMean(base, *self.coupling)
        mean = base if self.element is None else self.element.mean(base)
        if self.transmission is not None:
            from dgp_ros.gp.transmission import TransmissionMean
            mean = TransmissionMean(mean, *self.transmission)
        return mean

    def train_correction(self, Yt: Optional[np.ndarray]) -> np.ndarray:
        """Return what the non-damping parts explain of samples with columns Yt (k, N, C)."""
        if Yt is None or not self.conservative or self.theta.size == 0:
            return np.broadcast_to(self.bias, (1 if Yt is None else Yt.shape[0],
                                               self.bias.size))
        return np.einsum('knc,c->kn', Yt, self.theta) + self.bias

    def correction(self):
        """Return the applied non-damping part as a :class:`~.conservative.Correction`."""
        from .conservative import Correction
        use = self.conservative and self.basis is not None
        return Correction(self.basis if use else None, self.theta if use else np.zeros(0),
                          self.bias)

"""
The stream part: the couplings of a persistent column, learned on the message path (no rclpy).

A part of :class:`~dgp_ros.online.estimator.OnlineEstimator` on a system that is not an arm (no
rigid-body model: an aircraft, the paper's damping systems). Where a velocity never nears zero
(``dynamics.coupling_track``), the forces ride on its column of ``D`` (``gp.coupled``: dynamic
pressure times a coefficient polynomial in alpha and beta, for an aircraft). The learner learns
that part from its long history and the D-GP beside it, but the learner may be late: a fit
takes its time, a busy computer starves it for seconds, and a prior refitted at a rebase
extrapolates half a second of a polynomial fitted on one second of flight (-250 kN of lift).
This part is learned where every accepted message passes, at every message, in microseconds:

* **recursive least squares** of each output on the persistent column's features (shared by
  every output: one Gram matrix), with forgetting (a sample's weight halves after
  :data:`HALF_LIFE_S` of stamp time: the air's density grows by 3 % over an approach) and the
  long history's ridge (``dynamics.coupling_track.COUPLING_RIDGE``), solved every
  :data:`SOLVE_EVERY_S` of stamps;
* **its one-step skill beside the model's**: every message is answered by both before either
  learns it; the exponentially weighted squared errors over :data:`SKILL_HALF_LIFE_S` weigh the
  two answers per output, ``u = e_model / (e_model + e_part)`` to this part: a starved learner
  whose snapshot lags, a first fit that oscillates, a first visit the window has not seen, and
  the part answers; where the D-GP knows better, it does;
* **passive**: its own answer is projected onto ``qd^T tau >= 0``, and so is the weighed one
  (per-output weights are no convex combination of the two vectors).

Before a column has shown itself persistent (and on an arm, or where every velocity reverses)
the part is silent: the answers are the model's, exactly.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.linalg import cho_factor, cho_solve, LinAlgError

from dgp_ros.dynamics.coupling_track import COUPLING_RIDGE, CouplingTrack
from dgp_ros.gp.policy import projection_lambda

__all__ = ['StreamPart', 'HALF_LIFE_S', 'SKILL_HALF_LIFE_S', 'SOLVE_EVERY_S']

#: a learned sample's weight halves after this much stamp time (s)
HALF_LIFE_S = 10.0
#: the one-step errors that weigh the part against the model: half-life in stamp time (s) ...
SKILL_HALF_LIFE_S = 0.5
#: ... and at least this many samples (a slow stream)
SKILL_HALF_LIFE_SAMPLES = 10
#: the weights are solved for at most this often (stamp time, s)
SOLVE_EVERY_S = 0.005


class StreamPart:
    """
    The couplings learned on the message path and their one-step skill (module docstring).

    N : velocities. ``learn`` takes accepted messages with the answers the model gave them;
    ``weigh`` combines the model's answers with this part's.
    """

    def __init__(self, N: int):
        self.N = int(N)
        self.track = CouplingTrack(self.N)
        K = self.track.K
        self.G = np.zeros((K, K))
        self.B = np.zeros((K, self.N))
        self.n = 0.0                        # effective samples (decayed)
        self.W: Optional[np.ndarray] = None     # (N, K): weights of the serving column only
        self._col = None                    # the serving column's index among track.cols
        self._t = None                      # stamp of the last sample learned
        self._solved_t = -np.inf
        z = np.zeros(self.N)
        self.e_model, self.e_part, self.e_zero = z.copy(), z.copy(), z.copy()
        self.scored = 0.0
        self.samples = 0

    # ------------------------------------------------------------------ answers
    @property
    def active(self) -> bool:
        """Whether the part answers (a persistent column and its weights)."""
        return self.W is not None

    def answer(self, Q: np.ndarray):
        """Return (tau (k, N), D (k, N, N)) of the part at Q (k, N), passive; None if silent."""
        if self.W is None:
            return None
        tr, c = self.track, self._col
        basis = tr.fitted_basis()
        p = basis.cols[c]
        psi = basis.psi(Q, c)                                     # (k, Kc)
        g = psi @ self.W.T                                        # (k, N): D[:, :, p] * vref^2/v
        v = Q[:, p] / basis.vref[c] ** 2
        tau = g * (v * Q[:, p])[:, None]
        lam = projection_lambda(Q, tau)
        D = np.zeros((Q.shape[0], self.N, self.N))
        D[:, :, p] = g * v[:, None]
        idx = np.arange(self.N)
        D[:, idx, idx] += lam[:, None]
        return tau + lam[:, None] * Q, D

    def shares(self) -> np.ndarray:
        """Return the part's weight per output ``u`` (N,), 0 while silent or before any score."""
        if self.W is None or self.scored <= 0.0:
            return np.zeros(self.N)
        den = self.e_model + self.e_part
        return np.where(den > 0.0, self.e_model / np.where(den > 0.0, den, 1.0), 0.0)

    def weigh(self, Q: np.ndarray, tau: np.ndarray, D: Optional[np.ndarray],
              conf: Optional[np.ndarray] = None):
        """
        Weigh the model's answers ``tau`` (k, N) (and ``D``, ``conf``) with the part's.

        Returns (tau', D', conf', the part's answers or None). Where the part is silent or has
        no share, the model's answers come back unchanged (the same arrays).
        """
        part = self.answer(Q)
        u = self.shares()
        if part is None or not np.any(u > 0.0):
            return tau, D, conf, part
        tp, Dp = part
        out = (1.0 - u) * tau + u * tp
        lam = projection_lambda(Q, out)
        out = out + lam[:, None] * Q
        if D is not None:
            D = (1.0 - u)[:, None] * D + u[:, None] * Dp
            idx = np.arange(self.N)
            D[:, idx, idx] += lam[:, None]
        if conf is not None:
            conf = (1.0 - u) * conf + u * self.confidence()
        return out, D, conf, part

    def confidence(self) -> np.ndarray:
        """How much of the part's answer a controller may use, (N,): 1 - its NMSE, in [0, 1]."""
        ok = self.e_zero > 0.0
        r = np.where(ok, self.e_part / np.where(ok, self.e_zero, 1.0), 1.0)
        return np.clip(1.0 - r, 0.0, 1.0)

    # ------------------------------------------------------------------ learning
    def learn(self, stamps: np.ndarray, Q: np.ndarray, T: np.ndarray,
              model: np.ndarray, part: Optional[np.ndarray]) -> None:
        """
        Learn accepted messages: stamps (k,) s, velocities Q and forces T (k, N), in order.

        ``model``, ``part`` (k, N): what the model and this part answered them before either
        learned them (``part`` None: the part was silent); they move the skill first.
        """
        stamps = np.asarray(stamps, float)
        if not stamps.size:
            return
        self._score(stamps, T, model, part)
        dead = self.track.observe(Q)
        if dead:
            keep = np.setdiff1d(np.arange(self.track.K), self.track.drop_slices(dead))
            self.G, self.B = self.G[np.ix_(keep, keep)], self.B[keep]
            self.W = None
        if not self.track.cols:
            return
        t_last = float(stamps[-1])
        age = np.maximum(t_last - stamps, 0.0)
        w = 0.5 ** (age / HALF_LIFE_S)
        if self._t is not None:
            g = 0.5 ** (max(t_last - self._t, 0.0) / HALF_LIFE_S)
            self.G *= g
            self.B *= g
            self.n *= g
        Phi = self.track.columns(Q)                               # (k, K)
        Pw = Phi * w[:, None]
        self.G += Pw.T @ Phi
        self.B += Pw.T @ T
        self.n += float(w.sum())
        self._t = t_last
        self.samples += stamps.size
        if t_last - self._solved_t >= SOLVE_EVERY_S or self.W is None:
            self._solve()
            self._solved_t = t_last

    def _solve(self) -> None:
        """Solve for the serving column's weights (ridge as the long history's)."""
        c = self.track.serving()
        if c is None:
            self.W = None
            return
        size = self.track.K // len(self.track.cols)
        sl = slice(c * size, (c + 1) * size)
        G = self.G[sl, sl].copy()
        d = np.diag(G).copy()
        ridge = COUPLING_RIDGE * d / max(self.n, 1.0)
        ridge[0] = 0.0                      # the constant feature: none
        G[np.diag_indices_from(G)] += ridge + 1e-9 * d + 1e-300
        try:
            W = cho_solve(cho_factor(G), self.B[sl]).T
        except (LinAlgError, ValueError):
            return                          # keep the last weights
        if np.all(np.isfinite(W)):
            self.W, self._col = W, c

    def _score(self, stamps, T, model, part) -> None:
        """Move the one-step errors of the model, the part and no answer (module docstring)."""
        for i in range(stamps.size):
            dt = 0.0 if self._t is None else max(float(stamps[i]) - (
                self._t if i == 0 else float(stamps[i - 1])), 0.0)
            g = 0.5 ** min(dt / SKILL_HALF_LIFE_S, 1.0 / SKILL_HALF_LIFE_SAMPLES)
            t = T[i]
            self.e_zero = g * self.e_zero + (1.0 - g) * t * t
            self.e_model = g * self.e_model + (1.0 - g) * (model[i] - t) ** 2
            ep = (t * t) if part is None else (part[i] - t) ** 2
            self.e_part = g * self.e_part + (1.0 - g) * ep
            self.scored = g * self.scored + (1.0 - g)

    # ------------------------------------------------------------------ report
    def status(self) -> dict:
        """Return what /diagnostics says of the part."""
        tr = self.track
        c = None if self.W is None else self._col
        return {'stream_part': 'silent' if c is None else f'column {tr.cols[c]}',
                'stream_part_share': [round(float(x), 3) for x in self.shares()],
                'stream_part_samples': int(self.samples)}

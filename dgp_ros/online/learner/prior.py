"""
The parametric part of the learner: the prior the D-GP learns beside (no rclpy).

A part of :class:`~dgp_ros.online.learner.Learner`; it owns its state and is called under the
learner's lock. With ``prior='auto'`` every learned sample also goes into a
:class:`~dgp_ros.dynamics.history.LongHistory` (sufficient statistics of the whole run). At each
hyper-parameter refit the structure (friction family, offsets, the conservative correction of
the rigid-body model) is re-selected by cross-validation on that history and fitted on all of
it; then

* the D-GP's prior mean is the fitted friction, frozen (passive: non-negative coefficients of
  odd columns; the GP learns what it leaves, and the projection acts on both together);
* the window's targets become ``residual - correction`` (the offsets and ``dV/dq`` are not
  damping and must not be learned as such): ``Window.retarget``;
* a saved model carries the correction (``predict_residual``), and /diagnostics names the
  structure.

With a fixed ``prior`` the part is the passive prior of that family fitted to the window, which
answers before the first model and is the output gate's fallback. Either way it keeps the
largest |residual| learned per joint, which bounds what a correction may make of a target.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from dgp_ros.dynamics.conservative import correction_basis
from dgp_ros.dynamics.history import LongHistory
from dgp_ros.dynamics.parametric import ParametricFit
from dgp_ros.gp.means import make_mean

__all__ = ['Structure']


class Structure:
    """
    The parametric part (module docstring).

    config : the learner's ``EstimatorConfig`` (its model, prior and bias: structural, so fixed
    for this part's life); inverse : the rigid-body model (None without one). The learner's
    ``LearnerHealth`` is passed to the steps that record what this part chose and refused
    (``push``, ``reselect``, ``target``, ``prior``): it holds no peer.
    """

    #: a correction may make no learned target larger than this times the largest residual
    CORRECTION_INFLATION = 1.5
    #: the structure is re-selected when the history has grown by this factor since the last
    RESELECT_GROWTH = 1.25
    #: a persistent column's couplings are refitted for the served model at most this often
    #: (s of learning time): every 50 samples one step ahead 0.042 of an approach's drag
    #: variance, every 10: 9.6e-3, every sample: 7.4e-3 (seed 777, flight 21, prior alone)
    FOLLOW_S = 0.02

    def __init__(self, config, inverse):
        self.auto = config.prior == 'auto' and config.model != 'ard'
        self._family = 'viscous' if config.model == 'ard' or config.prior == 'auto' else \
            config.prior
        self._bias = bool(config.bias)
        self._elements = bool(config.history_elements)
        # the couplings of a persistent column (gp.coupled): not for the paper's Theorem 1,
        # which needs a diagonal prior
        self._couplings = config.passivity != 'paper'
        self._inverse = inverse
        self._history: Optional[LongHistory] = None
        self._param: Optional[ParametricFit] = None
        #: the auto prior of the last snapshot: (fit, mean, std, window seq, buffer rows)
        self._auto_cache: Optional[tuple] = None
        #: the fixed prior fitted to the window: (mean, std, window seq), refitted per tenth
        self._fixed: Optional[tuple] = None
        self._rmax: Optional[np.ndarray] = None    # largest |residual| learned per joint
        self._reselect_now = False    # re-select at the next occasion (a model to be saved)
        self._names: Optional[List[str]] = None     # the velocities' names (the label)
        self._followed: Optional[float] = None      # when the couplings were last refitted

    # ------------------------------------------------------------------ the history
    def push(self, stamp: float, q, qd, qdd, r, N: int, names: List[str],
             health) -> Optional[np.ndarray]:
        """
        Add a learned sample to the long history; its correction columns (N, C) or None.

        stamp [s]; q, qd, qdd, r : (N,) position, velocity, acceleration (None where not
        known) and residual; ``health`` (``LearnerHealth``) records the basis and the errors.
        """
        if not self.auto:
            return None
        h = health
        self._names = list(names) if names else None
        if self._history is None:
            basis = None
            if self._inverse is not None and q is not None:
                try:
                    basis = correction_basis(self._inverse, names)
                except Exception as exc:        # noqa: BLE001 - offsets and friction still
                    h.last_refit_error = f'no conservative correction: {exc}'
            default = 'friction' if self._inverse is not None else 'viscous'
            # the elements from every sample serve arms (a rigid-body model given); on the
            # A320 an element toggling at a re-selection left 1 s windows of 0.16-0.24 in two
            # random flights and the default flight's beta 4x worse (docs/BENCHMARKS.md)
            arm = self._inverse is not None
            self._history = LongHistory(N, basis, default, offsets=arm,
                                        elements=self._elements and arm,
                                        couplings=self._couplings and not arm, asymmetric=arm,
                                        transmissions=arm)
            h.correction_basis = '' if basis is None else basis.source
        try:
            return self._history.push(stamp, q, qd, qdd, r)
        except Exception as exc:                # noqa: BLE001 - e.g. a pose pinocchio rejects
            h.last_refit_error = f'long history: {type(exc).__name__}: {exc}'
            return None

    def push_thinned(self, samples, window, config, N: int, names: List[str], health) -> None:
        """
        Add samples a learner behind its stream thinned out to the long history only.

        samples : (stamp, qd, residual, q, qdd) each. The history's statistics cost
        microseconds a sample, so it learns every one but the outliers the window refuses: a
        starved learner (4x real time beside two busy loops) that fed it one sample in nine
        saved an approach's prior at 0.096 / 0.31 of drag / lift held out; fed every sample,
        0.0089 / 0.0047. Only where no rigid-body model is evaluated per sample.
        """
        for stamp, qd, r, q, qdd in samples:
            if window.buffer is not None and not window.outlier(config, qd, r):
                self.push(stamp, q, qd, qdd, r, N, names, health)

    @property
    def history_samples(self) -> int:
        """Return how many samples the long history holds (0 without one)."""
        return 0 if self._history is None else self._history.samples

    def reselect(self, window, health) -> None:
        """
        Re-select and refit the parametric part on the history; retarget the window.

        ``health`` (``LearnerHealth``) records the structure, its scores and a refused
        correction.
        """
        if not self.auto or self._history is None or self._history.samples == 0:
            return
        self._reselect_now = False
        fit = self._history.select(None if self._param is None else self._param.family)
        h = health
        if fit.conservative and self._inflates(fit, window):
            # a pose-dependent correction fitted to a short or narrow history can be larger
            # than the residual it corrects (targets of 13 N m where the residual spans 2.6 on
            # a Panda 3 s into a stream): the D-GP would learn it as damping; not that one
            fit = self._history.fit(fit.family, fit.offsets, False, fit.asymmetric, fit.motors())
            h.corrections_refused += 1
        self._param = fit
        h.structure = fit.label(self._names)
        h.structure_scores = {', '.join(map(str, k)): round(v, 4)
                              for k, v in sorted(fit.scores.items(), key=lambda kv: kv[1])[:6]}
        h.joint_elements = {} if fit.element is None else fit.element.summary()
        window.retarget(fit.train_correction)

    def _inflates(self, fit, window) -> bool:
        """Tell whether ``fit``'s correction inflates the buffered targets (see reselect)."""
        if window.buffer is None:
            return False
        r, y = window.residuals_unordered()
        if not len(r):
            return False
        rmax = np.abs(r).max(axis=0)
        if self._rmax is not None:
            rmax = np.maximum(rmax, self._rmax)
        return self._inflated(r - fit.train_correction(y), rmax)

    def _inflated(self, t: np.ndarray, rmax: np.ndarray) -> bool:
        """Tell whether any target in t (..., N) exceeds the inflation limit of rmax (N,)."""
        return bool(np.any(np.abs(t) > self.CORRECTION_INFLATION * rmax + 1e-12))

    def follow(self, t: Optional[float]) -> bool:
        """
        Refresh the couplings at learning time ``t`` (s), at most every ``FOLLOW_S``.

        Returns whether the prior changed (the served model then takes ``frozen_prior``).
        """
        if t is None or self._param is None or self._param.coupling is None or (
                self._followed is not None and 0.0 <= t - self._followed < self.FOLLOW_S):
            return False
        self._followed = t
        return self.refresh()

    def carried_by(self, model) -> bool:
        """
        Tell whether ``model``'s prior is the parametric part selected last (True without one).

        A re-selection for the answers before a model (``_auto_prior``) or between rebases
        names a structure on /diagnostics that the served model takes only at its next rebase:
        a save in between must not write the older one.
        """
        if not self.auto or self._param is None or model is None:
            return True
        return model.mean_.to_dict() == self.frozen_prior().to_dict()

    def frozen_prior(self):
        """Return the parametric part as the D-GP's frozen prior mean (``friction_mean``)."""
        return self._param.friction_mean().fit(None, None)

    def refresh(self) -> bool:
        """
        Refit the chosen structure on the history as it is now, where it carries couplings.

        Returns whether the prior changed. Each rebase calls it: couplings carry whole forces
        (an aircraft's lift and drag), and a prior held from one selection to the next (a
        quarter more history) answered the last seconds of an approach from data 10 s old.
        """
        p = self._param
        if not self.auto or p is None or p.coupling is None or not self.history_grew():
            return False
        fit = self._history.refit(p)
        fit.samples = p.samples
        self._param = fit
        return True

    def reselect_due(self) -> bool:
        """Tell whether the history grew enough (or a save asks) for a re-selection."""
        h, p = self._history, self._param
        return self.auto and h is not None and h.samples > 0 and (
            p is None or h.samples >= self.RESELECT_GROWTH * max(p.samples, 1) or
            (self._reselect_now and h.samples > p.samples))

    def reselect_soon(self) -> None:
        """Re-select at the next occasion whatever the growth (a model about to be saved)."""
        self._reselect_now = True

    def history_grew(self) -> bool:
        """Tell whether samples came into the long history since the last selection."""
        h, p = self._history, self._param
        return self.auto and h is not None and p is not None and h.samples > p.samples

    # ------------------------------------------------------------------ targets
    def target(self, r: np.ndarray, yt: Optional[np.ndarray], health) -> np.ndarray:
        """
        Return the damping target of a residual r (N,) with correction columns yt.

        A correction fitted on the poses seen so far may extrapolate to a new pose: where it
        would make the target larger than ``CORRECTION_INFLATION`` x the largest residual
        learned on that joint, this sample is learned uncorrected (counted) until the next
        re-selection refits the correction with it (``health.corrections_refused``).
        """
        a = np.abs(r)
        self._rmax = a if self._rmax is None else np.maximum(self._rmax, a)
        if self._param is None:
            return r
        t = r - self._param.train_correction(None if yt is None else yt[None])[0]
        if self._inflated(t, self._rmax):
            health.corrections_refused += 1
            return r
        return t

    @property
    def residual_bound(self) -> Optional[np.ndarray]:
        """Return a copy of the largest |residual| learned per joint, (N,), or None."""
        return None if self._rmax is None else self._rmax.copy()

    def restore_residual_bound(self, bound) -> None:
        """Take the largest |residual| per joint a previous learner saw (a restart), (N,)."""
        b = np.abs(np.asarray(bound, float))
        self._rmax = b if self._rmax is None else np.maximum(self._rmax, b)

    # ------------------------------------------------------------------ the model's parts
    def with_prior(self, hyper: Optional[dict]) -> Optional[dict]:
        """Return warm-start hyper-parameters carrying the current frozen prior."""
        if hyper is None or not self.auto or self._param is None:
            return hyper
        return dict(hyper, mean=self._param.friction_mean().fit(None, None).to_dict())

    def model_kw(self, cfg) -> dict:
        """Return the GP's constructor arguments: ``cfg``'s, with the frozen prior."""
        kw = cfg.model_kwargs()
        if self.auto and self._param is not None:
            kw['prior'] = self._param.friction_mean()
            kw['bias'] = False
        return kw

    def correction(self):
        """
        Return the correction that belongs to the window's current targets (None if none).

        A model fitted on the window carries it (``correction_``, saved with it,
        ``predict_residual``): targets and correction must come from the same parametric fit.
        """
        return self._param.correction() if self.auto and self._param is not None else None

    def offsets(self) -> Optional[list]:
        """Return the fitted offsets per joint (N m) for /diagnostics, None without any."""
        p = self._param
        if p is None or not np.any(p.offsets):
            return None
        return [round(float(b), 6) for b in p.bias]

    # ------------------------------------------------------------------ the prior
    def prior(self, window, N: int, health):
        """
        Return (mean, std): the passive prior the answers come from before the first model.

        ``prior='auto'``: the parametric part itself; else the configured family fitted to the
        window, refitted per tenth of it (a 7-joint friction prior costs ~15 ms: refitted on
        every learned sample it held the answers while the first fit ran). std (N,) is the RMS
        of what the prior leaves of the buffered targets. ``health``: where a re-selection
        records (``reselect``).
        """
        auto = self._auto_prior(window, N, health)
        if auto is not None:
            return auto
        seq = window.seq
        if self._fixed is None or seq >= self._fixed[2] + max(1, self._fixed[2] // 10):
            Q, T = window.arrays() if window.size else (np.zeros((0, N)), np.zeros((0, N)))
            try:
                mean = make_mean(self._family, 'full', self._bias).fit(Q, T)
                resid = T - mean(Q) if Q.shape[0] else T
                std = np.sqrt(np.mean(resid ** 2, axis=0)) if Q.shape[0] else np.zeros(N)
            except Exception:           # degenerate buffer: no prior damping at all
                mean, std = make_mean('viscous', 'full').fit(Q[:0], T[:0]), np.zeros(N)
            self._fixed = (mean, std, seq)
        return self._fixed[0], self._fixed[1]

    def answering(self, window, N: int, model, health):
        """
        Return the prior the answers come from now (the fallback beside ``model``), or None.

        The served ``model``'s own prior mean where it has one, else ``prior``; None while
        nothing was fitted (the answer was zero, not a prior's) or the buffer is degenerate.
        """
        if model is None and not window.size and not self.history_samples:
            return None
        try:
            if model is not None and model.posterior_.structure.has_damping:
                return model.mean_
            return self.prior(window, N, health)[0]
        except Exception:           # noqa: BLE001 - no prior yet (degenerate buffer)
            return None

    def _auto_prior(self, window, N: int, health):
        """(mean, std) of the parametric part for answers before the first model, or None."""
        if not self.auto or self._history is None or self._history.samples < 1:
            return None
        h = self._history
        if h.samples < 2:
            # the very first sample: the default family of it alone answers the second message
            # (a re-selection would start the doubling schedule one sample early)
            fit = h.fit(h.default_family, False, False)
        else:
            if self._param is None or self._param.samples * 2 < h.samples:
                self.reselect(window, health)
            fit = self._param
            # every snapshot asks (tens a second): the mean is the fit's own, its stddev over
            # the buffer is refreshed per tenth of the buffer learned (the friction basis at
            # every buffered sample cost 3 to 5 ms a snapshot, the largest part of the learner's
            # own thread on a 7-joint stream)
            c = self._auto_cache
            if c is not None and c[0] is fit and window.seq < c[3] + max(1, c[4] // 10):
                return c[1], c[2]
        mean = fit.friction_mean().fit(None, None)
        Q, T = window.rows_unordered() if window.size else (np.zeros((0, N)), np.zeros((0, N)))
        std = np.sqrt(np.mean((T - mean(Q)) ** 2, axis=0)) if Q.shape[0] else np.zeros(N)
        self._auto_cache = (fit, mean, std, window.seq, Q.shape[0])
        return mean, std

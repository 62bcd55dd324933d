"""
The learner's parametric part (``prior='auto'``): long history, structure, correction.

Every learned sample also goes into a :class:`~dgp_ros.dynamics.history.LongHistory` (sufficient
statistics of the whole run). At each hyper-parameter refit the structure (friction family,
offsets, the conservative correction of the rigid-body model) is re-selected by
cross-validation on that history and fitted on all of it; then

* the D-GP's prior mean is the fitted friction, frozen (passive: non-negative coefficients of
  odd columns; the GP learns what it leaves, and the projection acts on both together);
* the buffered samples' targets become ``residual - correction`` (the offsets and ``dV/dq``
  are not damping and must not be learned as such);
* a saved model carries the correction (``predict_residual``), and /diagnostics names the
  structure.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from dgp_ros.dynamics.conservative import correction_basis
from dgp_ros.dynamics.history import LongHistory, ParametricFit

__all__ = ['StructureMixin']


class StructureMixin:
    """
    Mixin of :class:`~dgp_ros.online.learner.Learner` (module docstring).

    Uses the learner's ``config``, ``_lock``, ``_N``, ``_inverse``, ``_buf``, ``health``.
    """

    _history: Optional[LongHistory] = None
    _param: Optional[ParametricFit] = None
    #: the auto prior of the last snapshot: (fit, mean, std, _seq, buffer rows)
    _auto_cache: Optional[tuple] = None
    _names_hint: Optional[List[str]] = None
    _rmax: Optional[np.ndarray] = None

    @property
    def auto(self) -> bool:
        """Tell whether the structure is chosen from the data (``prior='auto'``)."""
        return self.config.prior == 'auto' and self.config.model != 'ard'

    def set_joint_names(self, names) -> None:
        """Take the stream's joint names (they may name a known robot: its URDF kinematics)."""
        with self._lock:
            if not self._names_hint and names:
                self._names_hint = [str(n) for n in names]

    def _structure_names(self) -> List[str]:
        return list(self.config.joints) or list(getattr(self._inverse, 'joint_names', [])) \
            or list(self._names_hint or [])

    def _history_push(self, stamp: float, q, qd, qdd, r) -> Optional[np.ndarray]:
        """Add a learned sample to the long history; its correction columns (N, C) or None."""
        if not self.auto:
            return None
        if self._history is None:
            names = self._structure_names()
            basis = None
            if self._inverse is not None and q is not None:
                try:
                    basis = correction_basis(self._inverse, names)
                except Exception as exc:        # noqa: BLE001 - offsets and friction still
                    self.health.last_refit_error = f'no conservative correction: {exc}'
            default = 'friction' if self._inverse is not None else 'viscous'
            self._history = LongHistory(self._N, basis, default, offsets=self._inverse is not None)
            self.health.correction_basis = '' if basis is None else basis.source
        try:
            return self._history.push(stamp, q, qd, qdd, r)
        except Exception as exc:                # noqa: BLE001 - e.g. a pose pinocchio rejects
            self.health.last_refit_error = f'long history: {type(exc).__name__}: {exc}'
            return None

    def _reselect(self) -> None:
        """Re-select and refit the parametric part; retarget the buffer (under the lock)."""
        if not self.auto or self._history is None or self._history.samples == 0:
            return
        self._reselect_now = False
        fit = self._history.select()
        if fit.conservative and self._inflates(fit):
            # a pose-dependent correction fitted to a short or narrow history can be larger
            # than the residual it corrects (targets of 13 N m where the residual spans 2.6 on
            # a Panda 3 s into a stream): the D-GP would learn it as damping; not that one
            fit = self._history.fit(fit.family, fit.offsets, False)
            self.health.corrections_refused += 1
        self._param = fit
        self.health.structure = fit.label()
        self.health.structure_scores = {', '.join(map(str, k)): round(v, 4)
                                        for k, v in sorted(fit.scores.items(),
                                                           key=lambda kv: kv[1])[:6]}
        if self._buf is not None:
            self._buf.retarget(fit.train_correction)
            self._target_gen += 1       # what the model holds is not appended to any more

    #: a correction may make no learned target larger than this times the largest residual
    CORRECTION_INFLATION = 1.5

    def _inflates(self, fit) -> bool:
        """Tell whether ``fit``'s correction inflates the buffered targets (see _reselect)."""
        if self._buf is None:
            return False
        r, y = self._buf.residuals_unordered()
        if not len(r):
            return False
        rmax = np.abs(r).max(axis=0)
        if self._rmax is not None:
            rmax = np.maximum(rmax, self._rmax)
        return self._inflated(r - fit.train_correction(y), rmax)

    def _inflated(self, t: np.ndarray, rmax: np.ndarray) -> bool:
        """Tell whether any target in t (..., N) exceeds the inflation limit of rmax (N,)."""
        return bool(np.any(np.abs(t) > self.CORRECTION_INFLATION * rmax + 1e-12))

    #: the structure is re-selected when the history has grown by this factor since the last
    RESELECT_GROWTH = 1.25

    #: set to re-select at the next occasion whatever the growth (a model about to be saved)
    _reselect_now = False

    def _reselect_due(self) -> bool:
        h, p = self._history, self._param
        return self.auto and h is not None and h.samples > 0 and (
            p is None or h.samples >= self.RESELECT_GROWTH * max(p.samples, 1) or
            (self._reselect_now and h.samples > p.samples))

    def _history_grew(self) -> bool:
        """Tell whether samples came into the long history since the last selection."""
        h, p = self._history, self._param
        return self.auto and h is not None and p is not None and h.samples > p.samples

    def _with_prior(self, hyper: Optional[dict]) -> Optional[dict]:
        """Return warm-start hyper-parameters carrying the current frozen prior."""
        if hyper is None or not self.auto or self._param is None:
            return hyper
        return dict(hyper, mean=self._param.friction_mean().fit(None, None).to_dict())

    def restore_residual_bound(self, bound) -> None:
        """Take the largest |residual| per joint a previous learner saw (a restart), (N,)."""
        with self._lock:
            b = np.abs(np.asarray(bound, float))
            self._rmax = b if self._rmax is None else np.maximum(self._rmax, b)
            self._snap = None           # the next snapshot carries it

    def _target(self, r: np.ndarray, yt: Optional[np.ndarray]) -> np.ndarray:
        """
        Return the damping target of a residual r (N,) with correction columns yt.

        A correction fitted on the poses seen so far may extrapolate to a new pose: where it
        would make the target larger than ``CORRECTION_INFLATION`` x the largest residual
        learned on that joint, this sample is learned uncorrected (counted) until the next
        re-selection refits the correction with it.
        """
        a = np.abs(r)
        self._rmax = a if self._rmax is None else np.maximum(self._rmax, a)
        if self._param is None:
            return r
        t = r - self._param.train_correction(None if yt is None else yt[None])[0]
        if self._inflated(t, self._rmax):
            self.health.corrections_refused += 1
            return r
        return t

    def _model_kw(self, cfg=None) -> dict:
        """Return the GP's constructor arguments: the configuration's, with the frozen prior."""
        cfg = cfg or self.config
        kw = cfg.model_kwargs()
        if self.auto and self._param is not None:
            kw['prior'] = self._param.friction_mean()
            kw['bias'] = False
        return kw

    def _auto_prior(self):
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
                self._reselect()
            fit = self._param
            # every snapshot asks (tens a second): the mean is the fit's own, its stddev over
            # the buffer is refreshed per tenth of the buffer learned (the friction basis at
            # every buffered sample cost 3 to 5 ms a snapshot, the largest part of the learner's
            # own thread on a 7-joint stream)
            c = self._auto_cache
            if c is not None and c[0] is fit and self._seq < c[3] + max(1, c[4] // 10):
                return c[1], c[2]
        mean = fit.friction_mean().fit(None, None)
        Q, T = self._buf.rows_unordered() if self._buf is not None and self._buf.size else \
            (np.zeros((0, self._N)), np.zeros((0, self._N)))
        std = np.sqrt(np.mean((T - mean(Q)) ** 2, axis=0)) if Q.shape[0] else np.zeros(self._N)
        self._auto_cache = (fit, mean, std, self._seq, Q.shape[0])
        return mean, std

    def _correction(self):
        """
        Return the correction that belongs to the buffer's current targets (None if none).

        A model fitted on the buffer carries it (``correction_``, saved with it,
        ``predict_residual``): targets and correction must come from the same parametric fit.
        """
        return self._param.correction() if self.auto and self._param is not None else None

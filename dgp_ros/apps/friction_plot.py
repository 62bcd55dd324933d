"""
``friction_curves.png``: per joint, what was learned against velocity, beside the learned model.

The picture a robot user asks for first: for each joint, the friction residual the estimator
learned (``effort - tau_rb``, less the learned conservative correction ``dV/dq(q)`` of the
rigid-body model, so that what is left is friction plus the joint's offset) against the joint's
velocity; the learned model's curve there (its damping force with the other joints at rest,
plus the offset, as the saved model answers: with its earned gains), its +-2 sigma band; its
parametric part alone, and with the element learned from every sample where the joint carries
one (``gp.joint_element``); a Coulomb + viscous + offset least-squares refit of the same samples
(``baselines.fit_cv``); and in each title which elements of D the joint kept (``gp.select``),
the element from every sample with its error held out on the newest blocks over the parametric
part's, and the confidence it earned. numpy and matplotlib (Agg) only.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ['friction_curves']


def _curves(model, qd: np.ndarray, j: int, k: int = 200):
    """
    Return (v (k,), model, -+2 sigma (2, k), prior (k,), parametric part (k,)) along joint j.

    The prior is the model's prior mean: its parametric part, with the element learned from
    every sample where the joint carries one (``gp.joint_element``).
    """
    lo, hi = float(np.min(qd[:, j])), float(np.max(qd[:, j]))
    pad = 0.1 * max(hi - lo, 1e-6)
    v = np.linspace(lo - pad, hi + pad, k)
    V = np.zeros((k, qd.shape[1]))
    V[:, j] = v
    tau, var = model.predict(V, return_var=True)
    corr = getattr(model, 'correction_', None)
    off = float(np.asarray(getattr(corr, 'offsets', np.zeros(qd.shape[1])))[j]) \
        if corr is not None else 0.0
    sd = np.sqrt(np.maximum(np.nan_to_num(var[:, j]), 0.0))
    band = np.vstack([tau[:, j] - 2.0 * sd, tau[:, j] + 2.0 * sd]) + off
    mean = model.mean_
    base = getattr(mean, 'base', mean)
    return v, tau[:, j] + off, band, mean.force(V)[:, j] + off, base.force(V)[:, j] + off


def _less_correction(model, residual: np.ndarray, q) -> np.ndarray:
    """Return ``residual`` (n, N) less the model's learned conservative correction at ``q``."""
    y = np.atleast_2d(residual).copy()
    corr = getattr(model, 'correction_', None)
    if corr is not None and q is not None and getattr(corr, 'needs_position', False):
        y = y - corr.conservative(np.atleast_2d(q))
    return y


def friction_curves(path, model, qd: np.ndarray, residual: np.ndarray,
                    q: Optional[np.ndarray] = None, names: Optional[Sequence[str]] = None,
                    confidence: Optional[Sequence[float]] = None,
                    element_scores: Optional[Sequence[Optional[float]]] = None,
                    points: str = 'learned residual', title: Optional[str] = None,
                    refit_on: Optional[tuple] = None) -> Path:
    """
    Write ``friction_curves.png`` (module docstring) to ``path``; return it.

    Parameters
    ----------
    path : path-like
        The PNG file to write.
    model : fitted D-GP
        The model to draw (a saved model answers with its earned gains).
    qd, residual : (n, N)
        The learned samples: velocities [rad/s] and residuals [N m].
    q : (n, N) or None
        Their poses [rad]: the learned conservative correction is taken off the residuals.
    names : N str, optional
        Joint names (default q0, q1, ...).
    confidence : N floats, optional
        The confidence each joint earned (shown in its title).
    element_scores : N floats or None, optional
        Per joint the error of its element from every sample on the history's newest blocks
        over the parametric part's alone (``joint_elements`` of /diagnostics; in its title).
    points : str
        The legend of the samples drawn (held-out samples: say so).
    title : str or None
        The figure's title (default: what the curves are).
    refit_on : (qd (m, N), residual (m, N), q (m, N) or None) or None
        The samples the Coulomb-viscous refit learns (default: those drawn; their correction is
        taken off as the drawn ones'); held-out samples drawn: pass the learned ones.

    """
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt
    from dgp_ros.dynamics.baselines import fit_cv, predict_cv
    from dgp_ros.gp.joint_element import element_joints
    from dgp_ros.gp.select import row_choices

    qd, residual = np.atleast_2d(qd), np.atleast_2d(residual)
    N = qd.shape[1]
    names = list(names) if names else [f'q{j}' for j in range(N)]
    y = _less_correction(model, residual, q)
    rq, ry = (qd, y) if refit_on is None else (np.atleast_2d(refit_on[0]),
                                               _less_correction(model, *refit_on[1:]))
    post = model.posterior_
    choice = row_choices(post.structure, post.hyper)
    cols = 1 if N <= 2 else 2
    rows = math.ceil(N / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.0 * cols, 2.9 * rows), squeeze=False)
    for j in range(N):
        ax = axes[j // cols, j % cols]
        ax.plot(qd[:, j], y[:, j], '.', ms=2, color='0.6', alpha=0.5, label=points)
        v, tau, band, prior, param = _curves(model, qd, j)
        ax.fill_between(v, band[0], band[1], color='C0', alpha=0.15, lw=0, label='model ±2σ')
        ax.plot(v, tau, color='C0', lw=1.6, label='learned model')
        ax.plot(v, param, color='C2', lw=1.0, ls='--', label='its parametric part')
        has_element = j in element_joints(model.mean_)
        if has_element:
            ax.plot(v, prior, color='C1', lw=1.2, ls='-.',
                    label='parametric + element from every sample')
        if len(rq) >= 3:
            cv = fit_cv(rq[:, j], ry[:, j])
            ax.plot(v, predict_cv(cv, v) + cv['b'], color='C3', lw=1.0, ls=':',
                    label='Coulomb + viscous + offset refit' +
                          ('' if refit_on is None else ' (of the learned samples)'))
        c = '' if confidence is None or confidence[j] is None else \
            f', confidence {float(confidence[j]):.2f}'
        e = ''
        if has_element:
            sc = None if element_scores is None else element_scores[j]
            e = ', element from every sample' + ('' if sc is None else
                                                 f' ({float(sc):.2f}x held out)')
        ax.set_title(f'{names[j]}: elements {choice[j]}{e}{c}', fontsize=9)
        ax.set_xlabel('velocity [rad/s]', fontsize=8)
        ax.set_ylabel('[N m]', fontsize=8)
        ax.grid(alpha=0.3)
    for j in range(N, rows * cols):
        axes[j // cols, j % cols].set_visible(False)
    axes[0, 0].legend(loc='upper left', fontsize=7)
    fig.suptitle(title or 'friction learned against velocity (the other joints at rest; '
                 'residuals less the learned rigid-body correction)', fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

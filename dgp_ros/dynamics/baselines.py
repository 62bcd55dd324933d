"""
Parametric friction baselines, fitted per joint by least squares (robot demo, bench/robot_arms).

- :func:`fit_cv`: Coulomb-viscous ``Fc tanh(v / eps) + Fv v + b`` (eps from a grid);
- :func:`fit_sigmoid`: the sigmoid model of Makkar et al.
  ``a1 (tanh(b1 v) - tanh(b2 v)) + a2 tanh(b3 v) + a3 v + b`` (multi-start, bounded);
- :func:`residual_stream`: the samples these are fitted on, the estimator's own front end
  (``FrictionResidual`` with the URDF's RNEA and the same ``AccelFilter``, one sample per
  ``min_sample_interval_s`` of stamp time).

The bias ``b`` is fitted and left out of the prediction ``f`` (as the D-GP's). Pure numpy and
scipy; no ROS.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ['fit_cv', 'fit_sigmoid', 'residual_stream', 'predict_cv', 'predict_sigmoid']


def fit_cv(v, y) -> dict:
    """
    Fit Coulomb-viscous + bias to one joint: ``Fc tanh(v / eps) + Fv v + b``.

    Parameters
    ----------
    v, y : numpy.ndarray, (n,)
        Velocities [rad/s] and residual torques [N m].

    Returns
    -------
    dict
        ``eps`` [rad/s] (from the grid 0.001..0.1), ``Fc`` [N m], ``Fv`` [N m s/rad], ``b``
        [N m] and ``f``: the friction ``v -> Fc tanh(v / eps) + Fv v`` (no bias), (k,) -> (k,).

    """
    best = None
    for eps in (0.001, 0.003, 0.01, 0.03, 0.1):
        A = np.column_stack([np.tanh(v / eps), v, np.ones_like(v)])
        c, *_ = np.linalg.lstsq(A, y, rcond=None)
        r = float(np.sum((A @ c - y) ** 2))
        if best is None or r < best[0]:
            best = (r, eps, c)
    _, eps, c = best
    return {'eps': eps, 'Fc': c[0], 'Fv': c[1], 'b': c[2],
            'f': lambda x, eps=eps, c=c: c[0] * np.tanh(x / eps) + c[1] * x}


def predict_cv(fit: dict, v) -> np.ndarray:
    """Coulomb-viscous friction (no bias) of a :func:`fit_cv` result at ``v`` (k,) [N m]."""
    return fit['Fc'] * np.tanh(np.asarray(v) / fit['eps']) + fit['Fv'] * np.asarray(v)


def predict_sigmoid(fit: dict, v) -> np.ndarray:
    """Makkar friction (no bias) of a :func:`fit_sigmoid` result at ``v`` (k,) [N m]."""
    return _makkar(fit['params'], np.asarray(v))


def _makkar(p, v):
    a1, a2, a3, _, l1, l2, l3 = p
    return (a1 * (np.tanh(np.exp(l1) * v) - np.tanh(np.exp(l2) * v))
            + a2 * np.tanh(np.exp(l3) * v) + a3 * v)


#: evaluations of each start of the sigmoid fit (the best one is then polished up to 2000): the
#: starts that converge do so in 20-130; a third of them crawl along a degenerate valley (b1 ~
#: b2) and took nine tenths of the time
START_NFEV = 200


def fit_sigmoid(v, y, cv: dict) -> dict:
    """
    Fit the Makkar friction model to one joint.

    ``a1 (tanh(b1 v) - tanh(b2 v)) + a2 tanh(b3 v) + a3 v + b`` by ``scipy.optimize.least_squares``
    from 8 starts around the Coulomb-viscous fit ``cv`` (b_i = exp(l_i) > 0).

    Parameters
    ----------
    v, y : numpy.ndarray, (n,)
        Velocities [rad/s] and residual torques [N m].
    cv : dict
        :func:`fit_cv` of the same data (the starts).

    Returns
    -------
    dict
        ``params`` (7,) ``[a1, a2, a3, b, log b1, log b2, log b3]``, ``b`` [N m] and ``f``: the
        friction without the bias, (k,) -> (k,) [N m].

    """
    from scipy.optimize import least_squares

    def res(p):
        return _makkar(p, v) + p[3] - y

    def jac(p):
        # analytic: a finite-difference Jacobian cost 8 evaluations per step (27 s for 6 joints)
        a1, a2, _, _, l1, l2, l3 = p
        b1, b2, b3 = np.exp(l1), np.exp(l2), np.exp(l3)
        t1, t2, t3 = np.tanh(b1 * v), np.tanh(b2 * v), np.tanh(b3 * v)
        J = np.empty((v.size, 7))
        J[:, 0], J[:, 1], J[:, 2], J[:, 3] = t1 - t2, t3, v, 1.0
        J[:, 4] = a1 * (1.0 - t1 * t1) * b1 * v
        J[:, 5] = -a1 * (1.0 - t2 * t2) * b2 * v
        J[:, 6] = a2 * (1.0 - t3 * t3) * b3 * v
        return J

    # bounds keep the fit inside physical magnitudes: without them a1 -> inf with b1 -> b2
    # (a derivative-like term) fits the noise and explodes between the samples
    ymax = max(float(np.max(np.abs(y))), 1e-6)
    vmax = max(float(np.max(np.abs(v))), 1e-6)
    lb = np.array([-5 * ymax, -5 * ymax, -5 * ymax / vmax, -5 * ymax,
                   np.log(0.1), np.log(0.1), np.log(0.1)])
    ub = -lb
    ub[4:] = np.log(1e4)
    best = None
    for a1f in (0.0, 0.5):
        for s1 in (0.005, 0.02):
            for s2 in (0.05, 0.2):
                p0 = np.array([a1f * max(cv['Fc'], 0.05), cv['Fc'], cv['Fv'], cv['b'],
                               np.log(1 / s1), np.log(1 / s2), np.log(1 / cv['eps'])])
                p0 = np.clip(p0, lb + 1e-9, ub - 1e-9)
                try:
                    r = least_squares(res, p0, jac=jac, bounds=(lb, ub), method='trf',
                                      x_scale='jac', max_nfev=START_NFEV)
                except Exception:   # pragma: no cover - a bad start
                    continue
                if best is None or r.cost < best.cost:
                    best = r
    if best.status == 0:            # the best start ran out of evaluations: polish it
        best = least_squares(res, best.x, jac=jac, bounds=(lb, ub), method='trf',
                             x_scale='jac', max_nfev=2000)
    p = best.x
    return {'params': p, 'b': p[3], 'f': lambda x, p=p: _makkar(p, x)}


def residual_stream(t, q, qd, effort, urdf_file: str, joints: Sequence[str],
                    accel_half_window_s: float, min_sample_interval_s: float,
                    with_position: bool = False):
    """
    Return the residual samples the estimator's front end makes of a recording: (Qd, R).

    Parameters
    ----------
    t : numpy.ndarray, (k,)
        Stamps [s], increasing.
    q, qd, effort : numpy.ndarray, (k, N)
        Measured positions [rad], velocities [rad/s], efforts [N m] in ``joints`` order.
    urdf_file : str
        URDF of the rigid body subtracted (``inverse_dynamics=urdf``).
    joints : sequence of str
        The N joints.
    accel_half_window_s, min_sample_interval_s : float
        The estimator's parameters of the same names [s].
    with_position : bool
        Return the samples' positions too.

    Returns
    -------
    Qd, R : numpy.ndarray, (n, N)
        Velocities [rad/s] and residuals ``effort - tau_rb`` [N m] of the wanted samples (and
        their positions P [rad], (n, N), with ``with_position``).

    """
    from .filter import AccelFilter
    from .inverse import make_inverse_dynamics
    from .residual import FrictionResidual
    inv = make_inverse_dynamics('urdf', urdf_file=urdf_file, joints=list(joints))
    front = FrictionResidual(inv, AccelFilter(accel_half_window_s))
    dt = min_sample_interval_s
    last = None
    Q, R, P = [], [], []
    for i in range(len(t)):
        ti = float(t[i])
        want = not (dt > 0 and last is not None and last <= ti < last + dt * (1.0 - 1e-9))
        if want:
            last = ti
        for r in front.push(ti, q[i], qd[i], effort[i], want=want):
            Q.append(r.qd)
            R.append(r.residual)
            P.append(r.q)
    n = len(joints)
    out = np.array(Q).reshape(-1, n), np.array(R).reshape(-1, n)
    return out + (np.array(P).reshape(-1, n),) if with_position else out

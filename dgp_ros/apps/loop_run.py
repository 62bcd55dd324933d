"""
One closed-loop run in one process: the arm, the example controller and the estimator, lock-step.

The faithful in-process mode of ``dgp-demo --robot R --closed-loop`` and of
``bench/closed_loop.py`` (no ROS): every 1 ms step is

1. the arm's measurement at ``t`` (``ClosedLoopArm.measure``: q, noisy qd, measured torque);
2. with ``dgp``: the estimator (``OnlineEstimator``, the node's defaults except
   ``refit_mode='sync'``: the learner in line, so that the run is reproducible) answers it, and
   the answer ``tau_hat`` (and, where the model has one, its conservative correction at q), each
   times the answer's confidence (the controller's gain ``k`` scaled by it, as
   ``nodes.controller`` does with ``~/damping_force_confidence``), goes to the controller's
   zero-order holds (``HeldEstimate``) stamped ``t``;
3. the controller's command for ``t`` (``TrackingController``: PD + the URDF's feed-forward +
   ``k *`` the held compensation, dropped when older than ``timeout_s``);
4. the arm integrates the command over one step.

This is what the DDS nodes do in lock-step (``nodes.arm_loop``, ``nodes.controller``, the
estimator node): the arm publishes ``/joint_states`` at ``t`` and steps once the command for ``t``
is in; the controller commands ``t`` once the estimator's answer stamped ``t`` is in (or after its
wait). Compensations (:data:`COMPENSATIONS`): ``none``; ``sigmoid``: none while learning, then a
Makkar sigmoid per joint fitted by least squares on the learning period's residual stream (the
estimator's own front end: URDF RNEA, the same acceleration filter) at the measured velocity;
``dgp``: the live estimator's damping force plus its correction; ``dgp_damping_only``: its damping
force alone. ``kill_at_s``: from then on the estimator answers nothing (as after a SIGKILL);
``restart_at_s``: the estimator is killed then and a new one, without the model, answers from
``restart_at_s + RESTART_GAP_S`` on (a node restarted without ``model_path``).
"""
from __future__ import annotations

import time
from typing import Callable, Optional

import numpy as np

from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf
from dgp_ros.dynamics.baselines import _makkar, fit_cv, fit_sigmoid, residual_stream
from dgp_ros.dynamics.closed_loop import (ClosedLoopArm, DT, HeldEstimate, reference_path,
                                          TrackingController)

__all__ = ['COMPENSATIONS', 'estimator_config', 'SigmoidCompensation', 'run_loop', 'score',
           'windows']

COMPENSATIONS = ('none', 'sigmoid', 'dgp', 'dgp_damping_only')
#: answers older than this [s of simulated time] are not used by the controller
TIMEOUT_S = 0.05
#: simulated time without answers between a kill and the restarted estimator's first answer [s]
RESTART_GAP_S = 0.5


def estimator_config(robot: str, **overrides):
    """Return the node's defaults with the robot's URDF and joints, learner in line."""
    from dgp_ros.online import EstimatorConfig
    cfg = {'inverse_dynamics': 'urdf', 'urdf_file': example_robot_urdf(robot),
           'joints': list(ARM_JOINTS[robot]), 'refit_mode': 'sync'}
    cfg.update(overrides)
    return EstimatorConfig(**cfg).validate()


class SigmoidCompensation:
    """
    The parametric baseline: a Makkar sigmoid per joint (``baselines.fit_sigmoid``).

    ``fit(t, q, qd, effort)`` on a recording (k,), (k, N) x 3 in ``ARM_JOINTS`` order, through the
    estimator's front end (``residual_stream``); then ``self(qd)`` (N,) -> friction (N,) [N m]
    (the fitted bias is left out).
    """

    def __init__(self, robot: str):
        self.robot = robot
        self.fits = None

    def fit(self, t, q, qd, effort) -> 'SigmoidCompensation':
        from dgp_ros.online.config import PARAMS
        Qd, R = residual_stream(np.asarray(t), np.asarray(q), np.asarray(qd),
                                np.asarray(effort), example_robot_urdf(self.robot),
                                ARM_JOINTS[self.robot], PARAMS['accel_half_window_s'].default,
                                PARAMS['min_sample_interval_s'].default)
        self.fits = [fit_sigmoid(Qd[:, j], R[:, j], fit_cv(Qd[:, j], R[:, j]))
                     for j in range(Qd.shape[1])]
        self._params = np.array([f['params'] for f in self.fits]).T
        return self

    def __call__(self, qd) -> np.ndarray:
        # every joint's parameters at once: (7, N) unpack into per-joint rows
        return _makkar(self._params, np.asarray(qd, dtype=float))


def run_loop(robot: str = 'panda', compensation: str = 'dgp', duration_s: float = 30.0,
             learn_s: float = 20.0, seed: int = 0, k: float = 1.0, timeout_s: float = TIMEOUT_S,
             kill_at_s: Optional[float] = None, estimator=None, cycle_s: float = 10.0,
             progress: Optional[Callable[[float], None]] = None,
             restart_at_s: Optional[float] = None, use_confidence: bool = True) -> dict:
    """
    Run the arm in closed loop for ``duration_s`` with one compensation (module docstring).

    Parameters
    ----------
    robot : str
        ``'panda'`` or ``'ur5'``.
    compensation : str
        One of :data:`COMPENSATIONS`.
    duration_s, learn_s : float
        The run and its learning part [s of simulated time] (the sigmoid is fitted at
        ``learn_s``; the estimator learns all along).
    seed : int
        Reference path and sensor noise (the same for every compensation).
    k : float
        Feed-forward gain of the compensation.
    timeout_s : float
        Staleness limit of the controller's held answers [s].
    kill_at_s : float, optional
        From this time on the estimator answers nothing.
    restart_at_s : float, optional
        The estimator is killed at this time; a new one without the model answers from
        ``restart_at_s + RESTART_GAP_S`` on.
    use_confidence : bool
        Scale the compensation by the answers' confidence (the example controller does).
    estimator : OnlineEstimator, optional
        The estimator (default: :func:`estimator_config`'s); closed at the end either way.
    cycle_s : float
        Period of the reference path [s].
    progress : callable, optional
        Called with the simulated time every simulated second.

    Returns
    -------
    dict
        ``t`` (k,) [s]; ``error`` (k, N) ``q_ref - q`` [rad]; ``comp`` (k, N) the compensation
        added [N m]; ``confidence`` (k, N) the held answer's confidence (zeros without one);
        ``injected_j`` energy it injected [J]; ``answers``, ``nonpassive_answers``
        (answers with ``qd . tau_hat < 0``), ``stale`` (steps whose held answer was too old),
        ``clipped`` (commands at an effort limit); ``names``; ``wall_s``; ``estimator``
        (its diagnostics, or None).

    """
    if compensation not in COMPENSATIONS:
        raise ValueError(f'compensation must be one of {COMPENSATIONS}, got {compensation!r}')
    names = ARM_JOINTS[robot]
    steps = int(round(duration_s / DT))
    ref = reference_path(robot, seed=seed, cycle_s=cycle_s)
    rq, rqd, rqdd = ref(np.arange(steps) * DT)
    arm = ClosedLoopArm(robot, rq[0], rqd[0], seed=seed)
    ctl = TrackingController(robot, k=k)
    held_d, held_c = HeldEstimate(names, timeout_s), HeldEstimate(names, timeout_s)
    live = compensation.startswith('dgp')
    est = estimator if estimator is not None or not live else _estimator(robot)
    sigmoid = SigmoidCompensation(robot) if compensation == 'sigmoid' else None
    learn_steps = int(round(learn_s / DT))
    rec = {key: np.zeros((steps, len(names)))
           for key in ('q', 'qd', 'effort', 'error', 'comp', 'confidence')}
    held_k = HeldEstimate(names, timeout_s)
    t_arr = np.zeros(steps)
    answers = nonpassive = 0
    t0 = time.perf_counter()
    try:
        for n in range(steps):
            t, q, qd, effort = arm.measure()
            t_arr[n], rec['q'][n], rec['qd'][n], rec['effort'][n] = t, q, qd, effort
            comp = None
            if live:
                if restart_at_s is not None and est is not None and t >= restart_at_s:
                    est.close(timeout=5.0)
                    est = None
                if est is None and restart_at_s is not None and \
                        t >= restart_at_s + RESTART_GAP_S:
                    est, restart_at_s = _estimator(robot), None
                if est is not None and (kill_at_s is None or t < kill_at_s):
                    e = est.process(t, names, qd, effort, q)
                    if e is not None:
                        answers += 1
                        nonpassive += int(float(e.qd @ e.tau_hat) < 0.0)
                        held_d.update(t, e.names, e.tau_hat)
                        conf = e.confidence if use_confidence and e.confidence is not None \
                            else np.ones(len(e.names))
                        held_k.update(t, e.names, conf)
                        c = est.rigid_body_correction(q) if compensation == 'dgp' else None
                        if c is not None:
                            held_c.update(t, e.names, c)
                rec['confidence'][n] = held_k.value(t)
                comp = rec['confidence'][n] * (held_d.value(t) + held_c.value(t))
            elif sigmoid is not None and n >= learn_steps:
                if sigmoid.fits is None:
                    sigmoid.fit(t_arr[:n], rec['q'][:n], rec['qd'][:n], rec['effort'][:n])
                comp = sigmoid(qd)
            tau = ctl.command(q, qd, (rq[n], rqd[n], rqdd[n]), comp)
            rec['comp'][n] = 0.0 if comp is None else k * comp
            rec['error'][n] = rq[n] - arm.q
            arm.step(tau)
            if progress is not None and n % 1000 == 0:
                progress(t)
        diag = est.diagnostics() if est is not None else None
    finally:
        if est is not None:
            est.close(timeout=5.0)
    return {'robot': robot, 'compensation': compensation, 'names': names, 't': t_arr,
            'error': rec['error'], 'comp': rec['comp'], 'confidence': rec['confidence'],
            'injected_j': ctl.injected_j,
            'answers': answers, 'nonpassive_answers': nonpassive,
            'stale': held_d.stale + held_c.stale, 'clipped': ctl.clipped,
            'wall_s': time.perf_counter() - t0, 'estimator': diag,
            'sigmoid': None if sigmoid is None or sigmoid.fits is None else
            [f['params'].tolist() for f in sigmoid.fits]}


def _estimator(robot: str):
    from dgp_ros.online import OnlineEstimator
    est = OnlineEstimator(estimator_config(robot))
    # the controller takes the force only (the node likewise computes the rest for subscribers)
    est.set_outputs(stddev=False, damping=False, residuals=False)
    return est


def score(run: dict, start_s: float, end_s: Optional[float] = None):
    """RMS and largest |error| per joint (N,) [rad] over ``start_s <= t < end_s``."""
    t = run['t']
    sel = (t >= start_s) & (t < (np.inf if end_s is None else end_s))
    e = run['error'][sel]
    return np.sqrt(np.mean(e ** 2, axis=0)), np.max(np.abs(e), axis=0)


def windows(run: dict, width_s: float = 1.0) -> np.ndarray:
    """Tracking RMS per joint over consecutive windows from t = 0: (w, N) [rad]."""
    t = run['t']
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0        # the last step's window ends at t+dt
    k = int(np.floor((t[-1] + dt) / width_s + 1e-9))
    return np.array([score(run, i * width_s, (i + 1) * width_s)[0] for i in range(k)])

"""
The robot demo's numbers and plots (``dgp_ros.apps.robot_demo``): pure numpy/scipy/matplotlib.

:func:`evaluate` scores the estimator's saved model on the held-out part of the run: NMSE per
joint of ``model.predict`` at the true velocities against the true friction, of
``model.predict_residual`` (where the model has it) against the true friction + payload gravity
torque + sensor bias (what a model of the residual from ``q`` and ``qd`` can know), and of the
Makkar sigmoid and Coulomb-viscous models fitted per joint by least squares on the residual
stream of the learned part (the estimator's own front end); the listener's answered fraction and
end-to-end latency; the dissipated power of the answers and of ``predict`` at 10^5 random
velocities. :func:`plot` writes the five figures (``friction_curves.png``: ``friction_plot``),
:func:`print_summary` the table.
"""
from __future__ import annotations

import os
from typing import List

import numpy as np

__all__ = ['evaluate', 'plot', 'print_summary', 'jsonable', 'save_stream']

HELD_STRIDE = 10          # held-out samples evaluated: every 10th (100 Hz)
N_RANDOM = 100_000        # random velocities for the passivity count
ROUNDOFF = 1e-12          # qd . tau < -ROUNDOFF |qd| |tau|: negative beyond rounding


def _negative(qd, tau) -> tuple:
    """Rows with ``qd . tau < 0``, and below ``-ROUNDOFF |qd| |tau|`` (counts), (k, N) each."""
    p = np.einsum('ij,ij->i', qd, tau)
    scale = np.linalg.norm(qd, axis=1) * np.linalg.norm(tau, axis=1)
    return int(np.sum(p < 0)), int(np.sum(p < -ROUNDOFF * scale))


def _nmse(pred, truth) -> np.ndarray:
    """NMSE per column: mean squared error / variance of the truth, (k, N) -> (N,)."""
    var = np.var(truth, axis=0)
    return np.mean((pred - truth) ** 2, axis=0) / np.where(var > 0, var, 1.0)


def _answers(lis, n: int):
    """Velocities and estimates (k, n) of the answers, their stamps (k,) [ns]."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    stamps = sorted(lis.ans)
    qd, tau = np.zeros((len(stamps), n)), np.zeros((len(stamps), n))
    for i, s in enumerate(stamps):
        m = deserialize_message(lis.ans[s][1], JointState)
        qd[i], tau[i] = m.velocity, m.effort
    return qd, tau, np.array(stamps, dtype=np.int64)


def _fit_joints(Qs: np.ndarray, Rs: np.ndarray) -> list:
    """Coulomb-viscous and sigmoid fits of each column (a worker process): picklable dicts."""
    from dgp_ros.dynamics.baselines import fit_cv, fit_sigmoid
    out = []
    for j in range(Qs.shape[1]):
        cv = fit_cv(Qs[:, j], Rs[:, j])
        sg = fit_sigmoid(Qs[:, j], Rs[:, j], cv)
        out.append(({k: v for k, v in cv.items() if k != 'f'},
                    {k: v for k, v in sg.items() if k != 'f'}))
    return out


def _power_at_random(model_path: str, vlim: np.ndarray, k: int, seed: int) -> tuple:
    """
    Passivity of ``predict`` at ``k`` uniform velocities in ``+-vlim`` (a worker process).

    Returns ``qd . predict(qd)`` (k,) [W] and the two counts of :func:`_negative`.
    """
    from dgp_ros.gp import load_model
    X = np.random.default_rng(seed).uniform(-vlim, vlim, (k, vlim.size))
    tau = load_model(model_path).predict(X)
    return np.einsum('ij,ij->i', X, tau), _negative(X, tau)


def evaluate(truth: dict, learn_s: float, model_path: str, lis, published: int,
             urdf: str, workers: int = 2) -> dict:
    """
    Every number of the summary (module docstring).

    Parameters
    ----------
    truth : dict
        ``demo_arm`` output of the run (the same simulation the publisher streamed).
    learn_s : float
        End of the learned (streamed) part [s]; the rest is held out.
    model_path : str
        The model the estimator saved on SIGINT.
    lis : robot_demo.Listener
        Arrival times [s] of the measurements and answers by stamp [ns], raw answers.
    published : int
        Measurements published.
    urdf : str
        The URDF the estimator was given (the baselines' front end uses it too).
    workers : int
        Processes for the baseline fits and the random-velocity check (spawned: this process
        has DDS threads).

    Returns
    -------
    dict
        Scalars and per-joint dicts (``summary.json``) and numpy arrays under ``_arrays``.

    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from dgp_ros.dynamics import UrdfInverseDynamics
    from dgp_ros.dynamics.baselines import predict_cv, predict_sigmoid, residual_stream
    from dgp_ros.gp import load_model
    from dgp_ros.online.config import PARAMS
    names = list(truth['names'])
    n = len(names)
    t = truth['t']
    k = int(np.searchsorted(t, learn_s))
    held = np.arange(k, t.size, HELD_STRIDE)
    Qh, Fh = truth['qd_true'][held], truth['friction'][held]
    out = {'robot': truth['robot'], 'names': names, 'duration_s': float(t[-1] - t[0]),
           'learned_s': float(learn_s), 'friction_model': truth['friction_model'],
           'payload_kg': truth['payload_kg'], 'heldout_samples': int(held.size),
           'cycle_s': 1.0 / truth['base_hz'] if truth.get('base_hz') else None}
    t0 = _clock()
    vlim = UrdfInverseDynamics(urdf_file=urdf, joints=names).velocity_limit
    pool = ProcessPoolExecutor(max_workers=workers,
                               mp_context=multiprocessing.get_context('spawn'))
    try:
        # passivity of the saved model at random velocities in the URDF's velocity box
        chunks = [N_RANDOM // 2, N_RANDOM - N_RANDOM // 2]
        f_rand = [pool.submit(_power_at_random, model_path, vlim, c, i)
                  for i, c in enumerate(chunks)]
        # parametric baselines on the residual stream of the learned part
        Qs, Rs, Ps = residual_stream(t[:k], truth['q'][:k], truth['qd'][:k],
                                     truth['effort'][:k], urdf, names,
                                     PARAMS['accel_half_window_s'].default,
                                     PARAMS['min_sample_interval_s'].default, with_position=True)
        parts = [np.arange(i, n, workers) for i in range(workers)]
        f_fit = [pool.submit(_fit_joints, Qs[:, J], Rs[:, J]) for J in parts]
        model = load_model(model_path)
        pred = model.predict(Qh)
        out['model'] = type(model).__name__
        out['nmse'] = dict(zip(names, _nmse(pred, Fh).tolist()))
        out['has_predict_residual'] = hasattr(model, 'predict_residual')
        rtruth = Fh + truth['payload_gravity'][held] + truth['bias']
        arrays = {'t_h': t[held], 'Qh': Qh, 'Fh': Fh, 'pred': pred, 'rtruth': rtruth}
        if out['has_predict_residual']:
            pr = np.asarray(model.predict_residual(q=truth['q'][held], qd=Qh))
            arrays['pred_residual'] = pr
            out['nmse_residual'] = dict(zip(names, _nmse(pr, rtruth).tolist()))
        out.update(_stream_numbers(lis, n, published))
        fits = [None] * n
        for J, f in zip(parts, f_fit):
            for j, r in zip(J, f.result()):
                fits[j] = r
        rand = [f.result() for f in f_rand]
        p_rand = np.concatenate([r[0] for r in rand])
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    cv, sg = [f[0] for f in fits], [f[1] for f in fits]
    arrays['pred_cv'] = np.column_stack([predict_cv(cv[j], Qh[:, j]) for j in range(n)])
    arrays['pred_sigmoid'] = np.column_stack([predict_sigmoid(sg[j], Qh[:, j])
                                              for j in range(n)])
    arrays['fits'] = {'cv': cv, 'sigmoid': sg}
    out['nmse_sigmoid'] = dict(zip(names, _nmse(arrays['pred_sigmoid'], Fh).tolist()))
    out['nmse_coulomb_viscous'] = dict(zip(names, _nmse(arrays['pred_cv'], Fh).tolist()))
    out['baseline_samples'] = int(Qs.shape[0])
    out['friction_rms'] = dict(zip(names, np.sqrt(np.mean(Fh ** 2, axis=0)).tolist()))
    out['payload_gravity_rms'] = dict(zip(names, np.sqrt(np.mean(
        truth['payload_gravity'][held] ** 2, axis=0)).tolist()))
    lo, hi = truth['qd_true'][:k].min(axis=0), truth['qd_true'][:k].max(axis=0)
    out['heldout_inside_learned_box'] = float(np.mean(np.all((Qh >= lo) & (Qh <= hi), axis=1)))
    out.update(random_velocities=int(p_rand.size), random_box=vlim.tolist(),
               random_negative_power=sum(r[1][0] for r in rand),
               random_negative_power_beyond_roundoff=sum(r[1][1] for r in rand),
               random_negative_power_fraction=float(np.mean(p_rand < 0)),
               evaluation_seconds=_clock() - t0)
    arrays.update(latency_ms=out.pop('_latency_ms'), p_answers=out.pop('_p_answers'),
                  answers=out.pop('_answers'), p_random=p_rand, model=model,
                  learned_box=(lo, hi), learned=(Qs, Rs, Ps))
    out['_arrays'] = arrays
    return out


def _stream_numbers(lis, n: int, published: int) -> dict:
    """Answered fraction, latency, dissipated power of the answers (the listener's record)."""
    paired = sorted(set(lis.meas) & set(lis.ans))
    lat = np.array([lis.ans[s][0] - lis.meas[s] for s in paired]) * 1e3
    qd_a, tau_a, st = _answers(lis, n)
    p_ans = np.einsum('ij,ij->i', qd_a, tau_a)
    neg = p_ans < 0
    scale = np.linalg.norm(qd_a, axis=1) * np.linalg.norm(tau_a, axis=1)
    some = p_ans.size > 0
    beyond = _negative(qd_a, tau_a)[1] if some else 0
    return {
        'published': int(published), 'measurements_received': len(lis.meas),
        'answers': len(lis.ans), 'paired': len(paired),
        'answered_fraction': len(lis.ans) / max(published, 1),
        'latency_ms': {'median': float(np.median(lat)) if lat.size else None,
                       'p99': float(np.percentile(lat, 99)) if lat.size else None},
        'answers_negative_power': int(np.sum(neg)),
        'answers_negative_power_beyond_roundoff': beyond,
        'answers_negative_power_fraction': float(np.mean(neg)) if some else None,
        'answers_most_negative_power': float(p_ans.min()) if some else None,
        'answers_most_negative_cosine': float(np.min(p_ans / np.where(scale > 0, scale, 1.0)))
        if some else None,
        '_latency_ms': lat, '_p_answers': p_ans,
        '_answers': {'stamp_ns': st, 'qd': qd_a, 'tau': tau_a}}


def _clock() -> float:
    import time
    return time.perf_counter()


def jsonable(res: dict) -> dict:
    """Return the summary without the arrays (``summary.json``)."""
    return {k: v for k, v in res.items() if not k.startswith('_')}


def save_stream(res: dict, path: str) -> None:
    """
    Write the listener's record of the answers to ``path`` (npz).

    ``stamp_ns`` (k,), ``qd``, ``tau_hat`` (k, N) of every answer [rad/s, N m], ``power`` (k,)
    [W], ``latency_ms`` (m,) of the paired ones, ``names``.
    """
    A = res['_arrays']
    np.savez_compressed(path, stamp_ns=A['answers']['stamp_ns'], qd=A['answers']['qd'],
                        tau_hat=A['answers']['tau'], power=A['p_answers'],
                        latency_ms=A['latency_ms'], names=np.array(res['names']))


def _short(name: str) -> str:
    return name.replace('panda_', '').replace('_joint', '')


def plot(res: dict, truth: dict, out_dir: str) -> List[str]:
    """Write the five figures into ``out_dir``; return their paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from dgp_ros.apps.friction_plot import friction_curves
    from dgp_ros.dynamics.baselines import predict_sigmoid
    A, names = res['_arrays'], res['names']
    n = len(names)
    files = []

    def save(fig, name):
        p = os.path.join(out_dir, name)
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        plt.close(fig)
        files.append(p)

    # 1. friction estimate vs truth over the held-out time
    fig, axes = plt.subplots(n, 1, figsize=(11, 1.9 * n), sharex=True)
    for j, ax in enumerate(axes):
        ax.plot(A['t_h'], A['Fh'][:, j], 'k', lw=1.2, label='true friction')
        ax.plot(A['t_h'], A['pred'][:, j], 'C0', lw=1.0, label='D-GP (saved model)')
        ax.plot(A['t_h'], A['pred_sigmoid'][:, j], 'C1--', lw=0.9, label='sigmoid LS')
        if 'pred_residual' in A:
            ax.plot(A['t_h'], A['pred_residual'][:, j], 'C2:', lw=0.9,
                    label='D-GP residual model')
        nm = names[j]
        ax.set_ylabel(f'{_short(nm)} [N m]', fontsize=8)
        ax.set_title(f'{nm}: NMSE D-GP {res["nmse"][nm]:.3g}, sigmoid '
                     f'{res["nmse_sigmoid"][nm]:.3g}', fontsize=8)
    axes[0].legend(loc='upper right', fontsize=7, ncol=4)
    axes[-1].set_xlabel('time [s] (held-out part of the run)')
    save(fig, 'friction_vs_time.png')

    # 2. friction-velocity curves: truth (every pose) and the learned D(qd) qd
    cols = 2 if n > 4 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.6 * rows), squeeze=False)
    model = A['model']
    for j in range(n):
        ax = axes.flat[j]
        v = A['Qh'][:, j]
        ax.plot(v, A['Fh'][:, j], '.', color='0.6', ms=1.5, label='true friction (held out)')
        ax.plot(v, A['pred'][:, j], '.', color='C0', ms=1.5, alpha=0.5,
                label='D-GP at the held-out velocities')
        vmax = max(np.abs(v).max(), 1e-3) * 1.1
        grid = np.linspace(-vmax, vmax, 301)
        Q = np.zeros((grid.size, n))
        Q[:, j] = grid
        ax.plot(grid, model.predict(Q)[:, j], 'C0', lw=1.3, label='D-GP, this joint alone')
        ax.plot(grid, predict_sigmoid(A['fits']['sigmoid'][j], grid), 'C1--', lw=1.1,
                label='sigmoid LS')
        lo, hi = A['learned_box'][0][j], A['learned_box'][1][j]
        ax.axvspan(lo, hi, color='C2', alpha=0.06, lw=0)
        ax.axhline(0, color='k', lw=0.5)
        ax.set_title(f'{names[j]}', fontsize=8)
        ax.set_xlabel('qd [rad/s]', fontsize=8)
        ax.set_ylabel('friction [N m]', fontsize=8)
    for ax in list(axes.flat)[n:]:
        ax.axis('off')
    axes.flat[0].legend(loc='upper left', fontsize=6)
    fig.suptitle('friction vs velocity (shaded: the velocities learned)', fontsize=9)
    save(fig, 'friction_velocity.png')
    Qs, Rs, Ps = A['learned']
    if len(Qs):
        conf = (getattr(model, 'grounds_', None) or {}).get('confidence')
        files.append(str(friction_curves(os.path.join(out_dir, 'friction_curves.png'), model,
                                         Qs, Rs, Ps, names, conf)))

    # 3. dissipated power of the answers and of predict at random velocities
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    for ax, p, what in ((axes[0], A['p_answers'], 'answers over DDS'),
                        (axes[1], A['p_random'], f'predict, {p_count(A["p_random"])} random qd')):
        if p.size:
            ax.hist(p, bins=80, color='C0')
        ax.axvline(0, color='k', lw=0.8)
        ax.set_xlabel('qd . tau_hat [W]')
        ax.set_title(f'{what}: {int(np.sum(p < 0))} of {p.size} negative', fontsize=9)
    save(fig, 'dissipated_power_histogram.png')

    # 4. latency
    fig, ax = plt.subplots(figsize=(7, 3.6))
    lat = A['latency_ms']
    if lat.size:
        ax.hist(lat, bins=np.linspace(0, max(np.percentile(lat, 99.5), 1e-3), 80), color='C0')
    ax.set_xlabel('measurement received -> answer received [ms]')
    ax.set_ylabel('answers')
    L = res['latency_ms']
    ax.set_title(f'end-to-end latency (listener): median {L["median"] or float("nan"):.2f} '
                 f'ms, p99 {L["p99"] or float("nan"):.2f} ms', fontsize=9)
    save(fig, 'latency_histogram.png')
    return files


def p_count(p) -> str:
    """``10^5`` for 100000 (plot titles)."""
    e = int(round(np.log10(max(p.size, 1))))
    return f'10^{e}' if 10 ** e == p.size else str(p.size)


def print_summary(res: dict) -> None:
    """Print the summary table and the stream's numbers."""
    names = res['names']
    has_r = 'nmse_residual' in res
    print('\n=== dgp_ros robot demo: ' + res['robot'] + ' ' + '=' * 52)
    cyc = res.get('cycle_s')
    print(f'{res["friction_model"]} friction, payload {res["payload_kg"]:g} kg not in the URDF, '
          + (f'task cycle {cyc:g} s; ' if cyc and cyc < res['duration_s'] else
             'a path that never repeats; ') +
          f'learned {res["learned_s"]:g} s of {res["duration_s"]:.0f} s, held out the rest '
          f'({res["heldout_samples"]} samples, {100 * res["heldout_inside_learned_box"]:.0f} % '
          'inside the learned velocity box)')
    hdr = f'{"joint":<20}{"friction rms":>13}{"D-GP":>10}'
    hdr += f'{"D-GP res.":>11}' if has_r else ''
    print('held-out NMSE against the true friction (predict at the true velocities):')
    print(hdr + f'{"sigmoid LS":>12}{"Coul-visc LS":>14}')
    for nm in names:
        row = f'{nm:<20}{res["friction_rms"][nm]:>10.2f} Nm{res["nmse"][nm]:>10.4f}'
        row += f'{res["nmse_residual"][nm]:>11.4f}' if has_r else ''
        print(row + f'{res["nmse_sigmoid"][nm]:>12.4f}{res["nmse_coulomb_viscous"][nm]:>14.4f}')
    gm = {k: float(np.exp(np.mean(np.log(np.maximum(list(res[k].values()), 1e-300)))))
          for k in ('nmse', 'nmse_sigmoid', 'nmse_coulomb_viscous') + (
              ('nmse_residual',) if has_r else ())}
    print(f'{"geometric mean":<33}{gm["nmse"]:>10.4f}' +
          (f'{gm["nmse_residual"]:>11.4f}' if has_r else '') +
          f'{gm["nmse_sigmoid"]:>12.4f}{gm["nmse_coulomb_viscous"]:>14.4f}')
    if has_r:
        print('(D-GP res.: predict_residual against friction + payload gravity + sensor bias)')
    else:
        print('(this model has no predict_residual: the residual model is not scored)')
    L = res['latency_ms']
    print(f'stream: {res["published"]} measurements published, {res["measurements_received"]} '
          f'received by the listener, {res["answers"]} answers: answered '
          f'{100 * res["answered_fraction"]:.2f} %')
    if L['median'] is not None:
        print(f'end-to-end latency (listener: measurement -> answer): median {L["median"]:.2f} '
              f'ms, p99 {L["p99"]:.2f} ms')
    neg = res['answers_negative_power']
    print(f'negative dissipated power qd . tau_hat < 0: answers {neg} of {res["answers"]}' + (
        f' ({res["answers_negative_power_beyond_roundoff"]} below -1e-12 |qd| |tau_hat|; most '
        f'negative {res["answers_most_negative_power"]:.3g} W, cosine '
        f'{res["answers_most_negative_cosine"]:.2g})' if neg else '') +
        f'; predict at {res["random_velocities"]} random velocities '
        f'{res["random_negative_power"]} ({res["random_negative_power_beyond_roundoff"]} below '
        '-1e-12 |qd| |tau_hat|)')
    d = res.get('diagnostics') or {}
    if d:
        print(f'estimator: received {d.get("messages_received")}, refits {d.get("refits_ok")}, '
              f'buffer {d.get("buffer_fill")}/{d.get("buffer_size")}, bias {d.get("bias")}; '
              f'status: {d.get("message")}')
    print(f'wall time {res["wall_time_s"]:.1f} s (of which evaluation: baselines and the random '
          f'velocities in {res["evaluation_seconds"]:.1f} s)')
    print('=' * 76, flush=True)

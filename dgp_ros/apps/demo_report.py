"""
The A320 demo's numbers and plots (``dgp_ros.apps.demo``): pure numpy and matplotlib, no rclpy.

:func:`analyse` pairs the recorded measurements and answers by stamp: NMSE per output one step
ahead over the run, from 1 s, over its second half and its worst 1 s window, dissipated power,
latency; :func:`held_out` scores the model saved mid-flight on the rest; :func:`plot` writes the
two figures, :func:`print_summary` the table and the estimator's last status. Outputs are named
as the forces they are (:func:`force_label`).
"""
from __future__ import annotations

import os
from typing import List, Optional

import numpy as np

from dgp_ros.gp import load_model
from sim_bridge.config import FORCE_NAMES

__all__ = ['analyse', 'held_out', 'plot', 'print_summary', 'force_label', 'certified_share',
           'OUT_NAMES']

OUT_NAMES = ['alpha', 'beta', 'airspeed']


def held_out(model_path: str, split_s: float, res: dict) -> Optional[dict]:
    """
    Score the model saved at ``split_s`` [s of stamps] on the measurements after it.

    Returns ``{'after_s', 'samples', 'nmse': {name: NMSE}}``, or None without a model or later
    measurements.
    """
    if not os.path.exists(model_path) or 't' not in res:
        return None
    later = res['t'] > split_s
    if not later.any():
        return None
    pred = load_model(model_path).predict(res['qd'][later])
    tau = res['tau'][later]
    var = np.where(tau.var(axis=0) > 0, tau.var(axis=0), 1.0)
    nmse = ((pred - tau) ** 2).mean(axis=0) / var
    return {'after_s': split_s, 'samples': int(later.sum()),
            'nmse': dict(zip(res['names'], nmse.tolist()))}


def analyse(rec) -> dict:
    """Pair the measurements and answers of a ``demo._Recorder`` by stamp: NMSE, power, latency."""
    stamps = sorted(set(rec.meas) & set(rec.est))
    out = {'measurements': len(rec.meas), 'answers': len(rec.est), 'paired': len(stamps),
           'matrices': rec.n_matrix}
    if not stamps:
        return out
    names = rec.meas[stamps[0]][1] or OUT_NAMES
    tau = np.array([rec.meas[s][3] for s in stamps])
    qd = np.array([rec.meas[s][2] for s in stamps])
    tau_hat = np.array([rec.est[s][2] for s in stamps])
    lat = np.array([rec.est[s][0] - rec.meas[s][0] for s in stamps])
    var = tau.var(axis=0)
    var[var == 0] = 1.0
    nmse = ((tau_hat - tau) ** 2).mean(axis=0) / var
    half = len(stamps) // 2
    nmse2 = ((tau_hat[half:] - tau[half:]) ** 2).mean(axis=0) / np.where(
        tau[half:].var(axis=0) > 0, tau[half:].var(axis=0), 1.0)
    # from 1 s of stamps on (the first answers have learned nothing) and the worst 1 s window
    ts = np.array(stamps)
    on = ts >= ts[0] + 1.0
    nmse1 = ((tau_hat[on] - tau[on]) ** 2).mean(axis=0) / var if on.any() else nmse
    wins = [((tau_hat[w] - tau[w]) ** 2).mean(axis=0) / var
            for w in ((ts >= ts[0] + k) & (ts < ts[0] + k + 1)
                      for k in range(1, int(ts[-1] - ts[0]) + 1)) if w.sum() >= 10]
    worst = np.max(wins, axis=0) if wins else np.full(len(names), np.nan)
    worst_at = (1 + np.argmax(wins, axis=0)) if wins else np.zeros(len(names), int)
    p_est = np.einsum('ij,ij->i', qd, tau_hat)
    p_meas = np.einsum('ij,ij->i', qd, tau)
    powers = np.array(rec.power) if rec.power else p_est
    out.update(
        names=list(names), t=np.array(stamps), qd=qd, tau=tau, tau_hat=tau_hat,
        p_est=p_est, p_meas=p_meas,
        nmse=dict(zip(names, nmse.tolist())), nmse_second_half=dict(zip(names, nmse2.tolist())),
        nmse_from_1s=dict(zip(names, nmse1.tolist())),
        worst_window=dict(zip(names, worst.tolist())),
        worst_window_at_s=dict(zip(names, [float(x) for x in worst_at])),
        negative_power_fraction=float(np.mean(powers < 0)),
        negative_power_count=int(np.sum(powers < 0)), power_messages=int(powers.size),
        measured_negative_power_fraction=float(np.mean(p_meas < 0)),
        latency_end_to_end_ms={'median': float(np.median(lat) * 1e3),
                               'p99': float(np.percentile(lat, 99) * 1e3)},
        # of the measurements this process saw, the fraction the estimator answered (answers
        # to measurements published before our subscription matched are not counted)
        answered_fraction=len(stamps) / max(len(rec.meas), 1),
        answers_to_unseen=len(set(rec.est) - set(rec.meas)),
    )
    return out


def force_label(name: str) -> str:
    """Name the effort that pairs with velocity ``name``: 'lift (N) at airspeed'."""
    f = FORCE_NAMES.get(name)
    return f'{f} at {name}' if f else f'tau[{name}]'


def plot(res: dict, out_dir: str) -> List[str]:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    files = []
    t, tau, tau_hat, names = res['t'], res['tau'], res['tau_hat'], res['names']
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 2.6 * len(names)), sharex=True)
    for i, ax in enumerate(np.atleast_1d(axes)):
        ax.plot(t, tau[:, i], lw=1.0, label='measured')
        ax.plot(t, tau_hat[:, i], lw=1.0, ls='--', label='D-GP answer (one step ahead)')
        ax.set_ylabel(FORCE_NAMES.get(names[i], f'tau[{names[i]}]'))
        ax.set_title(f'{force_label(names[i])}: NMSE one step ahead '
                     f'{res["nmse"][names[i]]:.3g}', fontsize=9)
        ax.legend(loc='upper right', fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel('simulation time (s)')
    fig.tight_layout()
    p = os.path.join(out_dir, 'estimate_vs_measurement.png')
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p)
    fig, ax = plt.subplots(figsize=(7, 4))
    lo = min(res['p_meas'].min(), res['p_est'].min())
    hi = max(res['p_meas'].max(), res['p_est'].max())
    bins = np.linspace(lo, hi, 60) if hi > lo else 10
    ax.hist(res['p_meas'], bins=bins, alpha=0.55, label='measured  qd^T tau')
    ax.hist(res['p_est'], bins=bins, alpha=0.55, label='estimated qd^T tau_hat')
    ax.axvline(0.0, color='k', lw=0.8)
    ax.set_xlabel('dissipated power (W)')
    ax.set_ylabel('samples')
    ax.set_title(f'negative estimated power: {100 * res["negative_power_fraction"]:.2f} % '
                 f'(measured: {100 * res["measured_negative_power_fraction"]:.2f} %)', fontsize=9)
    ax.legend(loc='upper right')
    fig.tight_layout()
    p = os.path.join(out_dir, 'dissipated_power_histogram.png')
    fig.savefig(p, dpi=110)
    plt.close(fig)
    files.append(p)
    return files


def certified_share(diag: Optional[dict]) -> Optional[float]:
    """Return the estimator's ``certified_share`` from its last /diagnostics (None if absent)."""
    try:
        v = float((diag or {}).get('certified_share', 'nan'))
    except (TypeError, ValueError):
        return None
    return None if v != v else v


def _share_text(diag: dict) -> str:
    share = certified_share(diag)
    return ('-' if share is None else f'{100 * share:.1f} % '
            f'(by guarantee: {diag.get("answers_by_guarantee", "")})')


def print_summary(res: dict, diag: Optional[dict], wall_s: float) -> None:
    print('\n=== dgp_ros demo summary ' + '=' * 50)
    print(f'wall time {wall_s:.1f} s; measurements {res["measurements"]}, answers '
          f'{res["answers"]}, measurements answered {res["paired"]} '
          f'({100 * res.get("answered_fraction", 0):.2f} %; {res.get("answers_to_unseen", 0)} '
          f'answers to measurements sent before this listener connected), damping matrices '
          f'{res["matrices"]}')
    if 'nmse' in res:
        ho = res.get('held_out')
        w = max(len(force_label(n)) for n in res['names']) + 2
        print(f'{"output":<{w}}{"NMSE (run)":>12}{"from 1 s":>11}{"2nd half":>11}'
              f'{"worst 1 s (at)":>20}' + (f'{"held out":>11}' if ho else ''))
        for n in res['names']:
            print(f'{force_label(n):<{w}}{res["nmse"][n]:>12.4g}{res["nmse_from_1s"][n]:>11.4g}'
                  f'{res["nmse_second_half"][n]:>11.4g}'
                  f'{res["worst_window"][n]:>13.4g} ({res["worst_window_at_s"][n]:.0f} s)' +
                  (f'{ho["nmse"][n]:>11.4g}' if ho else ''))
        print('(run, from 1 s, 2nd half: one step ahead, each message answered before the '
              'estimator learned it (the very first answer knows nothing: zero); worst 1 s: over '
              "the run's variance;" + (f' held out: the model saved after {ho["after_s"]:.0f} s '
                                       f'of flight, on the {ho["samples"]} measurements after '
                                       'it)' if ho else ' no held-out model was saved)'))
        print(f'negative estimated dissipated power: {res["negative_power_count"]} of '
              f'{res["power_messages"]} ({100 * res["negative_power_fraction"]:.3f} %); measured: '
              f'{100 * res["measured_negative_power_fraction"]:.2f} %')
        lat = res['latency_end_to_end_ms']
        print(f'end-to-end latency (measurement -> answer, via DDS): median {lat["median"]:.2f} '
              f'ms, p99 {lat["p99"]:.2f} ms')
    if diag:
        def g(k, scale=1.0, unit=''):
            """Format the number under ``k`` times ``scale`` (2 decimals), else 'none yet'."""
            try:
                return f'{scale * float(diag.get(k, "")):.2f}{unit}'
            except (TypeError, ValueError):
                return 'none yet'      # (no refit finished: 'None' on /diagnostics)
        print(f'estimator processing latency: median {g("latency_median_s", 1e3, " ms")}, '
              f'p99 {g("latency_p99_s", 1e3, " ms")}')
        print(f'refits ok {diag.get("refits_ok")}, failed {diag.get("refits_failed")}, last '
              f'duration {g("last_refit_duration_s", 1.0, " s")}; certified '
              f'{diag.get("certified")} ({diag.get("method")}, margin {diag.get("margin")}); '
              f'buffer {diag.get("buffer_fill")}/{diag.get("buffer_size")}, skipped '
              f'(near-duplicates) {diag.get("samples_skipped")}, rate-limited '
              f'{diag.get("samples_rate_limited")}, rejected '
              f'{diag.get("rejected_total")}, passivity fallbacks '
              f'{diag.get("passivity_fallbacks")}')
        print(f'answers under a proven certificate (psd or passive-on-domain): '
              f'{_share_text(diag)}; guarantee now {diag.get("guarantee")}')
        if diag.get('stream_part') is not None:
            ratio = diag.get('stream_part_vs_answers')
            print(f'parametric part learned on the message path: {diag["stream_part"]}, its '
                  f'share of the answers now {diag.get("stream_part_share")}; the answers of '
                  'the last seconds against it alone (NMSE ratio): '
                  f'{"-" if ratio is None else ratio}')
        print(f'status: {["OK", "WARN", "ERROR", "STALE"][min(int(diag["level"]), 3)]}: '
              f'{diag.get("message")}')
    print('=' * 76, flush=True)

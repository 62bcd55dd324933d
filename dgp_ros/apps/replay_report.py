"""
What ``dgp-replay`` writes: the estimates as CSV, the summary, the plots (no rclpy, no DDS).

The replay itself (bag in, estimates out) is :mod:`dgp_ros.apps.replay`; this module turns its
estimates (a list of :class:`dgp_ros.online.Estimate`) and the estimator into files.

The files ``dgp-replay --out DIR`` writes to ``DIR``:

- ``estimates.csv``: ``t`` (header stamp, s), then per joint ``q_<j>`` (velocity), ``tau_<j>``
  (measured effort), ``tau_hat_<j>``, ``stddev_<j>``; then ``P`` (measured power ``qd.tau``),
  ``P_hat`` (``qd.tau_hat``), ``source`` (model/prior/fallback) and ``added`` (0/1). Rejected
  messages have no row (they are counted in the summary).
- ``summary.json``: NMSE per output one step ahead (``nmse``: each message predicted before the
  estimator learned it, the headline; with inverse dynamics each learned residual sample,
  predicted by the model's damping plus its rigid-body correction) and after learning it
  (``nmse_after_learning``: a tracking error, not an accuracy, sampled; see ``OneStep``),
  RMSE (and RMSE / mass with ``--mass``), median absolute error, count of huge/non-finite
  estimates, negative-power fractions (estimate and measurement), refits, timings,
  rejected-message counts by reason, certificate at the end, the configuration used, the
  structure of the parametric part (``structure``) and which elements of D each joint keeps
  with what they add over the parametric part, held out (``elements``, :func:`elements_report`).
- ``estimate_vs_measurement.png``, ``error.png`` (divided by the mass when given: m/s^2),
  ``power_hist.png`` (matplotlib, Agg backend); with inverse dynamics ``friction_curves.png``
  (``friction_plot``: per joint the learned residual against velocity, the saved model's curve,
  its parametric part and a Coulomb + viscous + offset refit).
"""
from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path
import time

import numpy as np

__all__ = ['arrays_of', 'CsvWriter', 'CSV_FIXED', 'elements_report', 'make_plots', 'OneStep',
           'summarize', 'write_csv', 'write_summary']


def _after_nmse(after, y) -> float:
    """Return the NMSE of the sampled tracking estimates ``after`` (NaN: not sampled)."""
    fin = np.isfinite(after)
    return _nmse(after[fin] - y[fin], y[fin])[0] if fin.any() else float('nan')


def _nmse(err, y):
    """
    Compute the NMSE and MSE.

    (NMSE, MSE); inf if an estimate is non-finite or overflows (JSON writes it as null,
    ``huge_or_nonfinite`` in the summary says why).
    """
    var = float(np.var(y)) if y.size else float('nan')
    with np.errstate(over='ignore', invalid='ignore'):
        mse = float(np.mean(np.square(err))) if err.size else float('nan')
    if math.isnan(mse) and err.size:
        mse = float('inf')
    return mse / var if var > 0 else float('nan'), mse


def _clean(x):
    """JSON-safe (NaN/inf -> None)."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def arrays_of(estimates):
    """Stack estimates into arrays: t (k,), qd/tau/tau_hat/stddev (k, N), P/P_hat (k,)."""
    if not estimates:
        return None
    return {
        't': np.array([e.stamp_s for e in estimates]),
        'qd': np.array([e.qd for e in estimates]),
        'tau': np.array([e.tau for e in estimates]),
        'tau_hat': np.array([e.tau_hat for e in estimates]),
        'stddev': np.array([e.stddev for e in estimates]),
        'P': np.array([e.measured_power for e in estimates]),
        'P_hat': np.array([e.power for e in estimates]),
        'source': np.array([e.source for e in estimates]),
        'added': np.array([bool(e.added) for e in estimates]),
        'proc': np.array([e.processing_time_s for e in estimates]),
    }


CSV_FIXED = ('P', 'P_hat', 'source', 'added')


class OneStep:
    """
    What the estimator learns, predicted before and after it learned it (the replay's NMSE).

    Without inverse dynamics the target is the measured force: ``ahead`` is the answer to the
    message (the model before it learned the message) and ``after`` the estimator's estimate
    at the same velocity once it has. With inverse dynamics the target is the friction residual
    the estimator learns (``effort - tau_rb``, complete ``accel_half_window_s`` later): ``ahead``
    is what the node published for the message (its damping force, blended by the grounds)
    plus the model's correction of the rigid-body model and offsets, ``after`` the model's
    ``predict_residual(q, qd)`` once the residual was learned; only the messages the rate limit
    lets through count. ``qd``, ``q``: the learned samples' velocities and poses (the friction
    curves). Call :meth:`add` with each Estimate (and the
    message's positions) right after ``OnlineEstimator.process`` returned it.
    """

    #: stamps of learned messages whose residual is not complete yet are kept this long (s)
    KEEP_S = 5.0
    #: the tracking error (``after``, not an accuracy) is sampled at one message in this many
    #: (NaN between): a second answer per message took a fifth of an A320 replay's wall time
    AFTER_EVERY = 4

    def __init__(self, est):
        self.est = est
        self.residual = bool(est.config.inverse_dynamics)
        self.truth, self.ahead, self.after, self.t = [], [], [], []
        self.qd, self.q = [], []
        self._waiting = {}              # stamp -> prediction before learning (residual case)

    @property
    def target(self) -> str:
        return 'friction residual' if self.residual else 'measured effort'

    def _residual_prediction(self, q, qd, fallback):
        m = self.est.model
        if m is None:
            return fallback
        return np.asarray(m.predict_residual(q=q[None, :], qd=qd[None, :]))[0]

    def _published(self, q, tau_hat):
        """Return the published force plus the model's correction and offsets at q (N,)."""
        corr = getattr(self.est.model, 'correction_', None)
        return tau_hat if corr is None else tau_hat + np.asarray(corr(q[None, :]))[0]

    def add(self, e, names=None, position=None) -> None:
        """Take the Estimate ``e`` of a message with joint ``names`` and ``position`` (M,)."""
        if not self.residual:
            self.t.append(e.stamp_s)
            self.truth.append(e.tau)
            self.ahead.append(e.tau_hat)
            self.after.append(self.est.predict(e.qd)[0] if len(self.t) % self.AFTER_EVERY == 1
                              else np.full(e.qd.shape, np.nan))
            return
        for r in e.residuals:
            before = self._waiting.pop(r.stamp_s, None)
            if before is not None and np.all(np.isfinite(r.residual)):
                self.t.append(r.stamp_s)
                self.truth.append(r.residual)
                self.ahead.append(before)
                self.after.append(self._residual_prediction(r.q, r.qd, before))
                self.qd.append(r.qd)
                self.q.append(r.q)
        if e.added and position is not None:
            q = np.asarray(position, float)
            if e.names and names is not None:      # the message's order -> the estimator's
                at = {n: i for i, n in enumerate(names)}
                q = q[[at[n] for n in e.names]]
            if q.shape == e.qd.shape:
                self._waiting[e.stamp_s] = self._published(q, e.tau_hat)
            old = [s for s in self._waiting if s < e.stamp_s - self.KEEP_S]
            for s in old:
                del self._waiting[s]

    def arrays(self):
        """(t (k,), truth, ahead, after (k, N) each), or None before any pair."""
        if not self.truth:
            return None
        return (np.array(self.t), np.array(self.truth), np.array(self.ahead),
                np.array(self.after))


class CsvWriter:
    """
    Write ``estimates.csv`` as the estimates come.

    ``estimates.csv`` written row by row as estimates come (flushed about once a second), so
    that an interrupted or killed replay leaves what it had.
    """

    def __init__(self, path):
        self.path = path
        self._f = None
        self._w = None
        self._flushed = time.monotonic()

    def __call__(self, e) -> None:
        if self._w is None:
            names = e.names or [f'q{i}' for i in range(e.qd.size)]
            self._f = open(self.path, 'w', newline='')
            self._w = csv.writer(self._f)
            self._w.writerow(['t'] + [f'{k}_{j}' for k in ('q', 'tau', 'tau_hat', 'stddev')
                                      for j in names] + list(CSV_FIXED))
        r = repr
        self._w.writerow([r(float(e.stamp_s))] + [r(float(x)) for x in e.qd]
                         + [r(float(x)) for x in e.tau] + [r(float(x)) for x in e.tau_hat]
                         + [r(float(x)) for x in e.stddev]
                         + [r(float(e.measured_power)), r(float(e.power)), e.source,
                            int(bool(e.added))])
        now = time.monotonic()
        if now - self._flushed >= 1.0:
            self._flushed = now
            self._f.flush()

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
        elif not os.path.exists(self.path):
            Path(self.path).write_text('')


def write_csv(path, estimates, names=None):
    """Write ``estimates`` (a list of Estimate) to ``path`` (see the module docstring)."""
    w = CsvWriter(path)
    for e in estimates:
        w(e)
    w.close()


def _final_certificate(est) -> dict:
    """
    Return the certificate of the final model.

    It is re-proven first if updates left it stale (offline, so the branch-and-bound may take its
    time here).
    """
    model = est.model
    if model is None:
        return {'certified': False, 'margin': None, 'method': '', 'domain': None, 'stale': False}
    cert = model.certificate()
    if cert.stale:
        cert = model.recertify()
    return {'certified': bool(cert.certified), 'margin': float(cert.margin), 'method': cert.method,
            'domain': None if cert.domain is None else [np.asarray(v).tolist()
                                                        for v in cert.domain],
            'stale': bool(cert.stale), 'correction_scale': float(cert.correction_scale)}


def elements_report(diag: dict, names) -> dict:
    """
    Return which elements of D each joint keeps and, held out, what they add over the prior.

    From the last hyper-parameter refit's choice (``gp.select``: blocked cross-validation over
    the buffer, standardized MSE per joint and choice): ``chosen`` ('own: 0 1, none: 2'),
    ``heldout_error`` (choice -> per joint) and ``over_parametric`` (choice -> joint -> that
    choice's held-out error over the parametric part's alone, ``none``: below 1 the GP helps).
    Empty before any such refit (``elements`` not 'auto', or a short run).
    """
    scores = diag.get('elements_scores') or {}
    none = scores.get('none')
    over = {}
    if none:
        for c, e in scores.items():
            if c != 'none':
                over[c] = {j: (e[i] / none[i] if none[i] > 0 else None)
                           for i, j in enumerate(names) if i < min(len(e), len(none))}
    return {'chosen': diag.get('elements') or '', 'heldout_error': dict(scores),
            'over_parametric': over}


def summarize(bag, estimates, est, info, names, mass=None) -> dict:
    """
    Return the content of ``summary.json`` (module docstring) as a JSON-safe dict.

    ``estimates``: the replay's Estimates (N joints each), ``est``: its OnlineEstimator after the
    stream, ``info``: what ``replay.replay`` returned about the stream, ``names``: the N joint
    names, ``mass``: kg or None (adds the RMSE per mass, m/s^2).
    """
    diag = est.diagnostics()
    A = arrays_of(estimates)
    one = info.get('one_step')
    S = one.arrays() if one is not None else None
    if S is None and A is not None:                 # a caller without the replay's pairs
        S = (A['t'], A['tau'], A['tau_hat'], None)
    per = {}
    if S is not None:
        _, truth, ahead, after = S
        err = ahead - truth
        for i, j in enumerate(names):
            nmse, mse = _nmse(err[:, i], truth[:, i])
            th = ahead[:, i]
            scale = 1e6 * max(float(np.max(np.abs(truth[:, i]))), 1.0)
            d = {'nmse': nmse,
                 'nmse_after_learning': (_after_nmse(after[:, i], truth[:, i])
                                         if after is not None else float('nan')),
                 'rmse': math.sqrt(mse),
                 'median_abs_error': float(np.median(np.abs(err[:, i]))),
                 # estimates that are non-finite or > 1e6 x the largest measurement
                 'huge_or_nonfinite': int(np.sum(~np.isfinite(th) | (np.abs(th) > scale)))}
            if A is not None:
                d['mean_stddev'] = float(np.mean(A['stddev'][:, i]))
            if mass:
                d['rmse_per_mass'] = math.sqrt(mse) / mass
            per[j] = d
    k = 0 if A is None else len(A['t'])
    durs = est.refit_durations()
    s = {
        'bag': str(bag), 'topic': info['topic'], 'joints': list(names),
        'messages': info['messages'], 'estimates': k,
        'duration_s': float(A['t'][-1] - A['t'][0]) if k else 0.0,
        # the headline: each message (residual sample) predicted before it was learned
        'nmse': {j: per[j]['nmse'] for j in per},
        'nmse_mean': float(np.mean([per[j]['nmse'] for j in per])) if per else float('nan'),
        'nmse_after_learning': {j: per[j]['nmse_after_learning'] for j in per},
        'nmse_target': one.target if one is not None else 'measured effort',
        'nmse_samples': 0 if S is None else int(len(S[0])),
        'outputs': per,
        'negative_power_fraction': float(np.mean(A['P_hat'] < 0)) if k else float('nan'),
        'min_power_estimate': float(np.min(A['P_hat'])) if k else float('nan'),
        'measured_negative_power_fraction': float(np.mean(A['P'] < 0)) if k else float('nan'),
        'sources': {src: int(np.sum(A['source'] == src)) for src in ('model', 'prior', 'fallback')}
        if k else {},
        'samples_added': diag['samples_added'], 'samples_skipped': diag['samples_skipped'],
        'samples_rate_limited': diag['samples_rate_limited'],
        'refits': {'started': diag['refits_started'], 'ok': diag['refits_ok'],
                   'failed': diag['refits_failed'], 'last_error': diag['last_refit_error']},
        'rejected': dict(diag['rejected'], undecodable=info['undecodable']),
        'rejected_total': diag['rejected_total'] + info['undecodable'],
        'time_jumps_back': diag['time_jumps_back'],
        'passivity_fallbacks': diag['passivity_fallbacks'],
        'structure': diag.get('structure') or '',
        'joint_elements': diag.get('joint_elements') or {},
        'elements': elements_report(diag, names),
        'certificate': _final_certificate(est),
        'status': {'level': diag['level'], 'message': diag['message']},
        'learned_negative_power_fraction': diag['negative_power_fraction'],
        'interrupted': info.get('interrupted', False),
        'timings': {
            'wall_time_s': info['wall_time_s'],
            'wall_per_data_second': (info['wall_time_s'] / float(A['t'][-1] - A['t'][0])
                                     if k > 1 and A['t'][-1] > A['t'][0] else float('nan')),
            'process_total_s': info['process_time_s'],
            'process_per_msg_median_s': float(np.median(A['proc'])) if k else float('nan'),
            'process_per_msg_p99_s': float(np.percentile(A['proc'], 99)) if k else float('nan'),
            'process_per_msg_max_s': float(np.max(A['proc'])) if k else float('nan'),
            'refit_count': len(durs), 'refit_total_s': float(np.sum(durs)) if durs else 0.0,
            'refit_mean_s': float(np.mean(durs)) if durs else float('nan'),
            'refit_max_s': float(np.max(durs)) if durs else float('nan'),
        },
        'mass_kg': mass,
        'config': est.config.to_dict(),
    }
    return _clean(s)


def make_plots(out: Path, estimates, names, mass=None, one_step=None) -> list:
    """
    Write the three plots (module docstring) into ``out``; return their paths ([] if no estimate).

    ``names``: the N joint names; ``mass`` (kg): the error plot is divided by it when given;
    ``one_step``: the replay's :class:`OneStep` (what was learned, predicted before and after it
    was): the estimate and error plots show it, one step ahead (else the answers against the
    measured effort).
    """
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt

    A = arrays_of(estimates)
    if A is None:
        return []
    S = one_step.arrays() if one_step is not None else None
    target = one_step.target if S is not None else 'measured effort'
    ts, truth, ahead, after = S if S is not None else (A['t'], A['tau'], A['tau_hat'], None)
    t0 = A['t'][0]
    t, tp = A['t'] - t0, ts - t0
    N = len(names)
    files = []

    fig, axes = plt.subplots(N, 1, figsize=(10, 2.6 * N), sharex=True, squeeze=False)
    for i, j in enumerate(names):
        ax = axes[i, 0]
        ax.plot(tp, truth[:, i], lw=0.8, color='0.4', label=target)
        ax.plot(tp, ahead[:, i], lw=1.0, color='C0', label='one step ahead')
        if after is not None:
            ax.plot(tp, after[:, i], lw=0.6, color='C1', alpha=0.6,
                    label='after learning it (tracking)')
        if S is None or not one_step.residual:
            sd = A['stddev'][:, i]
            ok = np.isfinite(sd)
            lo, hi = (A['tau_hat'][:, i] - 2 * sd)[ok], (A['tau_hat'][:, i] + 2 * sd)[ok]
            ax.fill_between(t[ok], lo, hi, color='C0', alpha=0.2, lw=0, label='±2σ')
        ax.set_ylabel(f'{j}')
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc='upper right', fontsize=8)
    axes[0, 0].set_title(f'{target}: each predicted before it was learned')
    axes[-1, 0].set_xlabel('time [s]')
    fig.tight_layout()
    files.append(out / 'estimate_vs_measurement.png')
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    err = ahead - truth
    unit = 'N'
    if mass:
        err = err / mass
        unit = 'N/kg = m/s²'
    fig, axes = plt.subplots(N, 1, figsize=(10, 2.2 * N), sharex=True, squeeze=False)
    for i, j in enumerate(names):
        ax = axes[i, 0]
        ax.plot(tp, err[:, i], lw=0.8, color='C3')
        ax.axhline(0, color='k', lw=0.5)
        ax.set_ylabel(f'{j} [{unit}]' if mass else j)
        ax.grid(alpha=0.3)
    axes[0, 0].set_title('error one step ahead' + (f' / mass ({mass:g} kg)' if mass else ''))
    axes[-1, 0].set_xlabel('time [s]')
    fig.tight_layout()
    files.append(out / 'error.png')
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    both = np.concatenate([A['P_hat'], A['P']])
    both = both[np.isfinite(both)]
    bins = np.linspace(both.min(), both.max(), 60) if both.size and both.min() < both.max() else 30
    ax.hist(A['P'], bins=bins, alpha=0.5, color='0.4', label='measured qd·tau')
    ax.hist(A['P_hat'], bins=bins, alpha=0.6, color='C0', label='estimate qd·tau_hat')
    ax.axvline(0, color='k', lw=0.8)
    ax.set_xlabel('dissipated power')
    ax.set_ylabel('count')
    neg = float(np.mean(A['P_hat'] < 0))
    ax.set_title(f'dissipated power (estimate < 0: {100 * neg:.2f} %)')
    ax.legend(fontsize=8)
    fig.tight_layout()
    files.append(out / 'power_hist.png')
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)
    return files


def write_summary(out: Path, summary: dict) -> None:
    """Write ``summary`` to ``out/summary.json`` atomically (a temporary file, then a rename)."""
    tmp = out / 'summary.json.tmp'
    tmp.write_text(json.dumps(summary, indent=2, sort_keys=False) + '\n')
    os.replace(tmp, out / 'summary.json')

"""
``dgp-replay``: offline evaluation of a rosbag2 bag, without DDS.

::

    dgp-replay BAG --out DIR [--topic T] [--joints a,b,c] [--model full|diag|ard]
               [--passivity none|paper|certified|projected] [--mass KG]
               [--params estimator.yaml] [--set name=value ...] [--no-plots] [--quiet]

The bag's ``sensor_msgs/JointState`` messages are streamed, in bag order, through
:class:`dgp_ros.online.OnlineEstimator`: the same code path as the estimator node (one
implementation), with ``refit_mode='sync'`` so that the result is deterministic. Messages are
converted by :func:`dgp_ros.messages.joint_state_sample`, the node's converter, so the stamp
given to the estimator is ``header.stamp`` computed exactly as the node does and replaying the
bag a node saw gives the node's estimates (the tests check this to 1e-9).

Messages are decoded with the rosbags typestore (pure Python; no rclpy, no DDS) by
:func:`dgp_ros.bags.iter_joint_states`, which also picks the topic. Any JointState
topic works: robot bags (``/joint_states`` with velocity and effort, extra joints, another order)
too; ``--joints`` selects and orders the joints. Without ``--topic`` the topic is picked
automatically if the choice is clear (a single JointState topic, else one named
``generalized_state`` or ``joint_states``).

Estimator parameters: the defaults of :class:`EstimatorConfig`, then a ROS parameter file
(``--params``, the node's ``ros__parameters``), then ``--model/--passivity/--joints`` and
``--set name=value`` (YAML values, e.g. ``--set buffer_size=100 --set selection_scale=[1,1]``).

Writes to ``DIR``:

- ``estimates.csv``: ``t`` (header stamp, s), then per joint ``q_<j>`` (velocity), ``tau_<j>``
  (measured effort), ``tau_hat_<j>``, ``stddev_<j>``; then ``P`` (measured power ``qd.tau``),
  ``P_hat`` (``qd.tau_hat``), ``source`` (model/prior/fallback) and ``added`` (0/1). Rejected
  messages have no row (they are counted in the summary).
- ``summary.json``: NMSE per output (all estimates, and model-only estimates), RMSE (and RMSE /
  mass with ``--mass``), median absolute error, count of huge/non-finite estimates,
  negative-power fractions (estimate and measurement), refits, timings,
  rejected-message counts by reason, certificate at the end, the configuration used.
- ``estimate_vs_measurement.png``, ``error.png`` (divided by the mass when given: m/s^2),
  ``power_hist.png`` (matplotlib, Agg backend).

Exit status: 0 on success, 2 for a bad bag / topic / argument (one-line message, no traceback).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
from pathlib import Path
import signal
import sys
import threading
import time
from typing import Optional

import numpy as np

from dgp_ros.bags import BagError, iter_joint_states, joint_state_topic, open_bag
from dgp_ros.gp import KINDS, PASSIVITY_MODES
from dgp_ros.gp.passivity import describe_modes

EXIT_OK, EXIT_ERROR = 0, 2


class ReplayError(Exception):
    """
    Bad joints / parameters.

    A one-line message for the user (bag and topic problems are :class:`~dgp_ros.bags.BagError`).
    """


# ----------------------------------------------------------------------------------- progress
class Progress:
    """
    A plain-stderr progress bar (no dependency).

    Redraws at most every ``period`` s on a terminal; on a pipe/file, prints a line every 10 %.
    """

    def __init__(self, total: int, enabled: bool = True, stream=None, period: float = 0.2,
                 width: int = 30):
        self.total = max(int(total), 0)
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = enabled and hasattr(self.stream, 'isatty') and self.stream.isatty()
        self.period, self.width = period, width
        self.t0 = time.monotonic()
        self._last = 0.0
        self._last_decile = -1
        self.n = 0

    def _line(self):
        frac = self.n / self.total if self.total else 0.0
        fill = int(round(frac * self.width))
        el = time.monotonic() - self.t0
        # the first refits are slower than the rest: no estimate before 5 % or 5 s
        eta = (el / frac - el) if frac >= 0.05 or (frac > 0 and el >= 5.0) else float('nan')
        eta_s = f'eta {eta:5.1f} s' if math.isfinite(eta) else 'eta ...'
        return (f'replay [{"#" * fill}{"." * (self.width - fill)}] {100 * frac:5.1f}% '
                f'{self.n}/{self.total} msgs {el:6.1f} s {eta_s}')

    def update(self, n: int):
        self.n = n
        if not self.enabled:
            return
        now = time.monotonic()
        if self.tty:
            if now - self._last >= self.period:
                self._last = now
                self.stream.write('\r' + self._line())
                self.stream.flush()
        else:
            dec = int(10 * n / self.total) if self.total else 0
            if dec > self._last_decile:
                self._last_decile = dec
                self.stream.write(self._line() + '\n')
                self.stream.flush()

    def close(self):
        if not self.enabled:
            return
        if self.tty:
            self.stream.write('\r' + self._line() + '\n')
        elif self._last_decile < 10:
            self.stream.write(self._line() + '\n')
        self.stream.flush()


# ------------------------------------------------------------------------------------ config
def load_params_file(path) -> dict:
    """Estimator parameters from a ROS 2 parameter file (``node: ros__parameters: {...}``)."""
    import yaml
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ReplayError(f'cannot read parameter file {path}: {" ".join(str(exc).split())}')
    if not isinstance(data, dict):
        raise ReplayError(f'parameter file {path}: not a mapping')
    for key in ('dgp_estimator', '/dgp_estimator', '/**'):
        if isinstance(data.get(key), dict) and 'ros__parameters' in data[key]:
            return dict(data[key]['ros__parameters'] or {})
    for v in data.values():
        if isinstance(v, dict) and 'ros__parameters' in v:
            return dict(v['ros__parameters'] or {})
    return dict(data)


def build_config(params: Optional[dict] = None, **overrides):
    """
    Build EstimatorConfig from parameters + overrides, with ``refit_mode='sync'`` (deterministic).

    ``params`` (e.g. a node parameter file) may hold node-only names, which are ignored;
    an unknown name in ``overrides`` is an error.
    """
    from dgp_ros.online import EstimatorConfig
    d = {}
    names = set(EstimatorConfig.__dataclass_fields__)
    for k, v in (params or {}).items():
        if k in names:  # node-only parameters (diagnostics_period_s, use_sim_time) are ignored
            d[k] = v
    d.update({k: v for k, v in overrides.items() if v is not None})
    d['refit_mode'] = 'sync'
    d['model_path'] = ''  # replay never reads or overwrites a model file
    try:
        cfg = EstimatorConfig.from_dict(d).validate()
    except (TypeError, ValueError) as exc:
        raise ReplayError(f'invalid estimator parameters: {exc}') from None
    if cfg.awaits_urdf:
        raise ReplayError('inverse_dynamics=urdf needs the URDF offline: --set urdf_file=PATH '
                          '(or robot_description=TEXT); a bag replay has no /robot_description '
                          'topic')
    return cfg


# ------------------------------------------------------------------------------------ replay
def replay(bag, topic: Optional[str] = None, config=None, progress: bool = False,
           stamp: str = 'header', on_estimate=None):
    """
    Stream a bag through an OnlineEstimator; returns ``(estimates, estimator, info)``.

    ``estimates`` is the list of :class:`dgp_ros.online.Estimate` (rejected messages have none);
    ``on_estimate(e)`` is called with each as it comes (partial outputs); ``info`` has the
    topic, message counts, undecodable count, timings, the joint names of the first message
    and ``interrupted`` (a KeyboardInterrupt, i.e. SIGINT, ends the stream early: what was
    estimated so far is returned).
    """
    from dgp_ros.online import OnlineEstimator
    config = config if config is not None else build_config()
    if config.refit_mode != 'sync':
        raise ReplayError("replay needs refit_mode='sync' (deterministic)")
    try:
        est = OnlineEstimator(config)
    except ValueError as exc:
        raise ReplayError(f'invalid estimator parameters: {exc}') from None
    est.set_source('bag')
    reader = open_bag(bag)
    t0 = time.perf_counter()
    out, n, undecodable = [], 0, 0
    t_proc = 0.0
    seen_names, interrupted = None, False
    try:
        topic = joint_state_topic(reader, topic)
        bar = Progress(reader.topics[topic].msgcount, enabled=progress)
        try:
            for sample in iter_joint_states(bag, topic, stamp=stamp, reader=reader):
                n += 1
                if sample is None:
                    undecodable += 1
                else:
                    if seen_names is None:
                        seen_names = list(sample.names)
                    tp = time.perf_counter()
                    r = est.process(sample.stamp_s, sample.names, sample.velocity,
                                    sample.effort, sample.position)
                    t_proc += time.perf_counter() - tp
                    if r is not None:
                        out.append(r)
                        if on_estimate is not None:
                            on_estimate(r)
                bar.update(n)
        except KeyboardInterrupt:
            interrupted = True
        bar.close()
    finally:
        reader.close()
        est.close()
    info = {'topic': topic, 'messages': n, 'undecodable': undecodable,
            'wall_time_s': time.perf_counter() - t0, 'process_time_s': t_proc,
            'bag_joints': seen_names or [], 'interrupted': interrupted}
    return out, est, info


# ----------------------------------------------------------------------------------- outputs
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


def summarize(bag, estimates, est, info, names, mass=None) -> dict:
    diag = est.diagnostics()
    A = arrays_of(estimates)
    per = {}
    if A is not None:
        err = A['tau_hat'] - A['tau']
        model = A['source'] == 'model'
        for i, j in enumerate(names):
            nmse, mse = _nmse(err[:, i], A['tau'][:, i])
            nmse_m, _ = _nmse(err[model, i], A['tau'][model, i])
            th = A['tau_hat'][:, i]
            scale = 1e6 * max(float(np.max(np.abs(A['tau'][:, i]))), 1.0)
            d = {'nmse': nmse, 'nmse_model_only': nmse_m, 'rmse': math.sqrt(mse),
                 'median_abs_error': float(np.median(np.abs(err[:, i]))),
                 # estimates that are non-finite or > 1e6 x the largest measurement
                 'huge_or_nonfinite': int(np.sum(~np.isfinite(th) | (np.abs(th) > scale))),
                 'mean_stddev': float(np.mean(A['stddev'][:, i]))}
            if mass:
                d['rmse_per_mass'] = math.sqrt(mse) / mass
            per[j] = d
    k = 0 if A is None else len(A['t'])
    durs = est.refit_durations()
    s = {
        'bag': str(bag), 'topic': info['topic'], 'joints': list(names),
        'messages': info['messages'], 'estimates': k,
        'duration_s': float(A['t'][-1] - A['t'][0]) if k else 0.0,
        'nmse': {j: per[j]['nmse'] for j in per},
        'nmse_mean': float(np.mean([per[j]['nmse'] for j in per])) if per else float('nan'),
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


def make_plots(out: Path, estimates, names, mass=None) -> list:
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt

    A = arrays_of(estimates)
    if A is None:
        return []
    t = A['t'] - A['t'][0]
    N = len(names)
    files = []

    fig, axes = plt.subplots(N, 1, figsize=(10, 2.6 * N), sharex=True, squeeze=False)
    for i, j in enumerate(names):
        ax = axes[i, 0]
        ax.plot(t, A['tau'][:, i], lw=0.8, color='0.4', label='measured')
        ax.plot(t, A['tau_hat'][:, i], lw=1.0, color='C0', label='estimate')
        sd = A['stddev'][:, i]
        ok = np.isfinite(sd)
        lo, hi = (A['tau_hat'][:, i] - 2 * sd)[ok], (A['tau_hat'][:, i] + 2 * sd)[ok]
        ax.fill_between(t[ok], lo, hi, color='C0', alpha=0.2, lw=0, label='±2σ')
        ax.set_ylabel(f'{j}')
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc='upper right', fontsize=8)
    axes[0, 0].set_title('damping force: estimate vs measurement')
    axes[-1, 0].set_xlabel('time [s]')
    fig.tight_layout()
    files.append(out / 'estimate_vs_measurement.png')
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    err = A['tau_hat'] - A['tau']
    unit = 'N'
    if mass:
        err = err / mass
        unit = 'N/kg = m/s²'
    fig, axes = plt.subplots(N, 1, figsize=(10, 2.2 * N), sharex=True, squeeze=False)
    for i, j in enumerate(names):
        ax = axes[i, 0]
        ax.plot(t, err[:, i], lw=0.8, color='C3')
        ax.axhline(0, color='k', lw=0.5)
        ax.set_ylabel(f'{j} [{unit}]' if mass else j)
        ax.grid(alpha=0.3)
    axes[0, 0].set_title('estimation error' + (f' / mass ({mass:g} kg)' if mass else ''))
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


def _write_summary(out: Path, summary: dict) -> None:
    tmp = out / 'summary.json.tmp'
    tmp.write_text(json.dumps(summary, indent=2, sort_keys=False) + '\n')
    os.replace(tmp, out / 'summary.json')


def run(bag, out, topic=None, config=None, mass=None, plots=True, progress=False,
        stamp='header', save_model: Optional[str] = None) -> dict:
    """
    Replay ``bag`` and write the outputs to ``out``; returns the summary dict.

    ``estimates.csv`` grows as the replay runs; ``summary.json`` (and the plots) are written at
    the end, also after a SIGINT (``summary['interrupted']``). ``save_model``: write the final
    model there (loadable with ``dgp_ros.gp.load_model``). ReplayError when no message could be
    estimated, with the reason.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    writer = CsvWriter(out / 'estimates.csv')
    try:
        estimates, est, info = replay(bag, topic=topic, config=config, progress=progress,
                                      stamp=stamp, on_estimate=writer)
    finally:
        writer.close()
    names = (estimates[0].names if estimates and estimates[0].names else
             est.names or [f'q{i}' for i in range(estimates[0].qd.size if estimates else 0)])
    summary = summarize(bag, estimates, est, info, names, mass=mass)
    if plots and estimates:
        summary['plots'] = [p.name for p in make_plots(out, estimates, names, mass=mass)]
    if save_model and est.trained and not info['interrupted']:
        summary['model_file'] = est.save(save_model)
    _write_summary(out, summary)
    if not estimates:
        raise ReplayError(_nothing_estimated(info, summary))
    if save_model and not est.trained:
        raise ReplayError(f'no model to save to {save_model}: the estimator was never trained '
                          f'({summary["status"]["message"]})')
    return summary


def _nothing_estimated(info, summary) -> str:
    rej = {k: v for k, v in summary['rejected'].items() if v}
    why = ', '.join(f'{v} {k}' for k, v in sorted(rej.items(), key=lambda kv: -kv[1]))
    msg = f'no message of the {info["messages"]} on {info["topic"]} could be estimated'
    if why:
        msg += f' (rejected: {why})'
    if rej.get('missing_joint') and info.get('bag_joints'):
        msg += f'; the bag\'s joints are {", ".join(map(str, info["bag_joints"]))}'
    return msg


# --------------------------------------------------------------------------------------- CLI
def _parse_set(specs) -> dict:
    import yaml
    d = {}
    for spec in specs:
        k, sep, v = spec.partition('=')
        if not sep or not k:
            raise ReplayError(f'invalid --set {spec!r} (expected name=value)')
        try:
            d[k.strip()] = yaml.safe_load(v)
        except yaml.YAMLError:
            raise ReplayError(f'invalid value in --set {spec!r}') from None
    return d


def _interrupt(*_):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    prog = 'dgp-replay'
    ap = argparse.ArgumentParser(
        prog=prog, description='Replay a bag through the online D-GP estimator (offline, no DDS) '
                               'and write estimates.csv, summary.json and plots.')
    ap.add_argument('bag', help='rosbag2 directory (or .db3/.mcap file)')
    ap.add_argument('--out', '-o', required=True, help='output directory (created)')
    ap.add_argument('--topic', '-t', help='JointState topic (default: automatic)')
    ap.add_argument('--joints', '-j', help='comma-separated joint names to select and order')
    ap.add_argument('--model', choices=KINDS)
    ap.add_argument('--passivity', choices=PASSIVITY_MODES,
                    help=describe_modes())
    ap.add_argument('--save-model', metavar='PATH',
                    help='write the final model here (.npz; load with dgp_ros.gp.load_model, '
                         'or give it to the node as model_path)')
    ap.add_argument('--mass', type=float, help='mass in kg: errors are also shown divided by it')
    ap.add_argument('--params', help='ROS 2 parameter file for the estimator (ros__parameters)')
    ap.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                    help='estimator parameter override (YAML value), the same names as the '
                         "node's (estimator --help); repeatable")
    ap.add_argument('--stamp', choices=('header', 'bag'), default='header',
                    help='time given to the estimator: header.stamp (as the node) or bag time')
    ap.add_argument('--no-plots', action='store_true')
    ap.add_argument('--quiet', '-q', action='store_true', help='no progress bar or summary line')
    a = ap.parse_args(argv)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _interrupt)     # SIGTERM ends the replay like SIGINT
    if a.mass is not None and not (math.isfinite(a.mass) and a.mass > 0):
        ap.error('--mass must be a positive number')
    try:
        params = load_params_file(a.params) if a.params else {}
        overrides = _parse_set(a.set)   # unlike the file, unknown names here are an error
        joints = None
        if a.joints is not None:
            joints = [j.strip() for j in a.joints.split(',') if j.strip()]
            if not joints:
                raise ReplayError('--joints is empty')
        for k, v in (('model', a.model), ('passivity', a.passivity), ('joints', joints)):
            if v is not None:
                overrides[k] = v
        config = build_config(params, **overrides)
        t0 = time.perf_counter()
        if a.save_model:
            from dgp_ros.online.config import check_model_path
            try:
                check_model_path(a.save_model)
            except ValueError as exc:
                raise ReplayError(f'--save-model: {exc}') from None
        s = run(a.bag, a.out, topic=a.topic, config=config, mass=a.mass,
                plots=not a.no_plots, progress=not a.quiet, stamp=a.stamp,
                save_model=a.save_model)
        wall = time.perf_counter() - t0
    except (BagError, ReplayError) as exc:
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return 130
    if s.get('interrupted'):
        print(f'{prog}: interrupted; partial results ({s["estimates"]} estimates) in {a.out}',
              file=sys.stderr)
        return 130
    if s['status']['level'] > 0:
        print(f'{prog}: warning: {s["status"]["message"]}', file=sys.stderr)
    if not a.quiet:
        nm = ', '.join(f'{j} {v:.4g}' if v is not None else
                       f'{j} inf/n.a. ({s["outputs"][j]["huge_or_nonfinite"]} huge estimates)'
                       for j, v in s['nmse'].items())
        print(f'{prog}: {s["estimates"]}/{s["messages"]} messages on {s["topic"]}; NMSE {nm}; '
              f'P_hat<0 fraction {s["negative_power_fraction"]}; refits ok {s["refits"]["ok"]} '
              f'failed {s["refits"]["failed"]}; rejected {s["rejected_total"]}; '
              f'wall {wall:.2f} s -> {a.out}', file=sys.stderr)
    return EXIT_OK


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())

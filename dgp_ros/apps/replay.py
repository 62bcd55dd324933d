"""
``dgp-replay``: offline evaluation of a rosbag2 bag, without DDS.

::

    dgp-replay BAG --out DIR [--topic T] [--joints a,b,c] [--model full|diag|ard]
               [--passivity none|paper|certified|projected] [--mass KG]
               [--params estimator.yaml] [--set name=value ...] [--no-plots] [--quiet]

The bag's ``sensor_msgs/JointState`` messages are streamed, in bag order, through
:class:`dgp_ros.online.OnlineEstimator`: the same code path as the estimator node (one
implementation: ``process`` checks each message as the node checks what its array path does not
cover, and every accepted message is answered by the node's step, ``OnlineEstimator._respond``),
with ``refit_mode='sync'`` so that the result is deterministic. Messages are
converted by :func:`dgp_ros.msgs.sample.joint_state_sample`, the node's converter, so the stamp
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

Writes to ``DIR``: ``estimates.csv`` (as the estimates come), ``summary.json`` and plots; their
contents are described in :mod:`dgp_ros.apps.replay_report`.

Exit status: 0 on success, 2 for a bad bag / topic / argument (one-line message, no traceback).
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
import signal
import sys
import threading
import time
from typing import Optional

import numpy as np

from dgp_ros.apps.replay_report import (arrays_of, CsvWriter, make_plots, OneStep, summarize,
                                        write_csv, write_summary)
from dgp_ros.bags import BagError, iter_joint_states, joint_state_topic, open_bag
from dgp_ros.gp import KINDS, PASSIVITY_MODES
from dgp_ros.gp.passivity import describe_modes

__all__ = ['build_config', 'load_params_file', 'main', 'replay', 'ReplayError', 'run',
           # the outputs (replay_report), here too: one import for a replay and its files
           'arrays_of', 'CsvWriter', 'make_plots', 'summarize', 'write_csv', 'write_summary']

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
    if d.get('learning', True) is not False:
        # learning, the estimator would overwrite model_path at every refit: replay never writes
        # a model file but with --save-model; with learning=false it reads model_path and
        # serves it frozen (what the deployed node answers; nothing is written)
        d['model_path'] = ''
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
    topic, message counts, undecodable count, timings, the joint names of the first message,
    ``one_step`` (a :class:`~dgp_ros.apps.replay_report.OneStep`: what was learned, predicted
    before and after it was) and ``interrupted`` (a KeyboardInterrupt, i.e. SIGINT, ends the
    stream early: what was estimated so far is returned).
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
    scores = OneStep(est)
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
                        scores.add(r, sample.names, sample.position)
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
            'bag_joints': seen_names or [], 'interrupted': interrupted, 'one_step': scores}
    return out, est, info


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
        summary['plots'] = [p.name for p in make_plots(out, estimates, names, mass=mass,
                                                       one_step=info.get('one_step'))]
    if save_model and est.trained and not info['interrupted']:
        summary['model_file'] = est.save(save_model)
    if plots and est.trained and not info['interrupted']:
        curves = _friction_curves(out, est, info.get('one_step'), summary.get('model_file'))
        if curves is not None:
            summary.setdefault('plots', []).append(curves.name)
    write_summary(out, summary)
    if not estimates:
        raise ReplayError(_nothing_estimated(info, summary))
    if save_model and not est.trained:
        raise ReplayError(f'no model to save to {save_model}: the estimator was never trained '
                          f'({summary["status"]["message"]})')
    return summary


def _friction_curves(out: Path, est, one_step, model_file: Optional[str]):
    """
    Write ``friction_curves.png`` of the model as saved (with its earned gains); None if none.

    Only with inverse dynamics (an arm: what was learned is a friction residual).
    """
    import tempfile
    from dgp_ros.apps.friction_plot import friction_curves
    from dgp_ros.gp import load_model
    if one_step is None or not one_step.residual or not one_step.qd:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        model = load_model(model_file or est.save(str(Path(tmp) / 'model.npz')))
    conf = (getattr(model, 'grounds_', None) or {}).get('confidence')
    scores = (est.diagnostics().get('joint_elements') or {}).get('newest_blocks')
    return friction_curves(out / 'friction_curves.png', model, np.array(one_step.qd),
                           np.array(one_step.truth), np.array(one_step.q), est.names, conf,
                           scores)


def _structure_line(s: dict) -> str:
    """
    Return 'structure ...; elements ... (own over the parametric part, held out: j 0.93x); '.

    With the joints that carry an element from every sample and its held-out error ratio;
    '' when there is nothing to say.
    """
    out = f'structure {s["structure"]}; ' if s.get('structure') else ''
    je = s.get('joint_elements') or {}
    if je.get('on'):
        nb = je.get('newest_blocks') or []
        out += 'elements from every sample on ' + ', '.join(
            f'{j} ({nb[j]:.2f}x)' if j < len(nb) and nb[j] is not None else str(j)
            for j in je['on']) + ' (held out on the newest blocks, over the parametric part); '
    el = s.get('elements') or {}
    if el.get('chosen'):
        gains = '; '.join(f'{c} over the parametric part, held out: ' + ', '.join(
            f'{j} {v:.2f}x' for j, v in per.items() if v is not None)
            for c, per in el.get('over_parametric', {}).items())
        out += f'elements {el["chosen"]}' + (f' ({gains})' if gains else '') + '; '
    return out


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
        prog=prog, formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description='Replay a bag through the online D-GP estimator (offline, no DDS) '
                    'and write estimates.csv, summary.json and plots.')
    ap.add_argument('bag', help='rosbag2 directory (or .db3/.mcap file)')
    ap.add_argument('--out', '-o', required=True, help='output directory (created)')
    ap.add_argument('--topic', '-t', help='JointState topic (default: automatic)')
    ap.add_argument('--joints', '-j', help='comma-separated joint names to select and order')
    ap.add_argument('--model', choices=KINDS, help="damping model (default: the node's)")
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
    ap.add_argument('--no-plots', action='store_true',
                    help='write no PNG plots (CSV and JSON only)')
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
        after = ', '.join(f'{j} {v:.3g}' if v is not None else f'{j} n.a.'
                          for j, v in s['nmse_after_learning'].items())
        what = 'residual sample' if 'residual' in s['nmse_target'] else 'message'
        print(f'{prog}: {s["estimates"]}/{s["messages"]} messages on {s["topic"]}; NMSE one '
              f'step ahead (each {what} predicted before it was learned, against the '
              f'{s["nmse_target"]}): {nm}; after learning it (tracking, not accuracy): {after}; '
              f'{_structure_line(s)}'
              f'P_hat<0 fraction {s["negative_power_fraction"]}; refits ok {s["refits"]["ok"]} '
              f'failed {s["refits"]["failed"]}; rejected {s["rejected_total"]}; '
              f'wall {wall:.2f} s -> {a.out}', file=sys.stderr)
    return EXIT_OK


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())

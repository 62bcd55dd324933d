"""
The learner's part of the diagnostics: what its parts say, and the warnings they imply.

``learner_status(learner)`` reads the learner's parts through their public methods (under the
learner's lock, which ``Learner.status`` holds) and returns the dict the message path merges
into /diagnostics: the certificate in force, the counters of ``LearnerHealth``, the structure
and elements chosen, the gains (``grounds``), and ``warnings``: each condition on the data a
user should act on, with its reason and what to change (``health.Health.status`` makes them
WARN).
"""
from __future__ import annotations

from typing import List

from .skill import FLOOR_S

__all__ = ['learner_status', 'STALL_WARN_S']

#: stamp time without a learned sample (while moving) after which learning is said to stall
STALL_WARN_S = 30.0


def learner_status(L) -> dict:
    """Return the learner's part of the diagnostics (module docstring)."""
    cfg, h, model = L.config, L.health, L.served.model
    cert = model.certificate() if model is not None else None
    d = {
        'trained': model is not None,
        'certified': bool(cert.certified) if cert is not None else False,
        'certificate_stale': bool(cert.stale) if cert is not None else False,
        'margin': float(cert.margin) if cert is not None else float('nan'),
        'method': str(cert.method) if cert is not None else '',
        'domain': str(cert.domain) if cert is not None else '',
        # which guarantee holds now (gp.policy.GUARANTEES); before the first fit the answer is
        # the prior mean diag(m_d) qd with m_d >= 0: PSD by construction
        'guarantee': (str(cert.guarantee) if cert is not None else
                      'none' if cfg.passivity == 'none' else 'psd'),
        'learning': L.learning_state,
        'buffer_fill': L.window.size,
        'refit_running': L.refits.running(),
        'load_error': L.load_error, 'hyper_samples': L.refits.hyper_samples,
        # learned while a refit runs (a sample may land just as one ends: not one)
        'pending_samples': L.refits.pending(),
        'negative_power_fraction': L.window.negative_power_fraction(),
        'residual_delay_s': L.front.residual.delay_s,
        'accel_filter_restarts': L.front.residual.restarts,
        'accel_filter_dropped': L.front.residual.dropped,
        'bias': (None if model is None or not cfg.bias else
                 [round(float(b), 6) for b in model.bias_]),
        'version': L.version,
        'last_fit_wall_s': _num(h.last_fit_wall_s),
        'last_fit_cpu_s': _num(h.last_fit_cpu_s),
        'structure': h.structure,
        'structure_scores': dict(h.structure_scores),
        'joint_elements': dict(h.joint_elements),
        'elements': h.elements,
        'elements_scores': dict(h.elements_scores),
        'correction_basis': h.correction_basis,
        'corrections_refused': h.corrections_refused,
        'offsets': L.structure.offsets(),
        # each joint's effort against the rigid-body torque (1: torque in N m; None: not judged)
        'effort_gain': _gains(L.front.effort),
        'warnings': warnings(L),
    }
    d.update(h.counters())
    d.update(L.grounds.summary())
    return d


def _gains(check):
    """Return the effort's gain on ``tau_rb`` per judged joint (None elsewhere), or None."""
    if check is None or check.n == 0:
        return None
    gain, judged = check.gains()[0], check.judged()
    return [round(float(g), 3) if ok else None for g, ok in zip(gain, judged)]


def _num(x):
    """Return a finite number rounded for /diagnostics, None for NaN (nothing measured)."""
    return None if x != x else round(float(x), 3)


#: a learner whose last fit took this many times its computing time, and at least this much
#: wall time (s), is short of CPU (``_starved``)
STARVED_RATIO, STARVED_MIN_S = 5.0, 2.0


def warnings(L) -> List[str]:
    """Conditions on the data the user should act on (WARN with the reason)."""
    cfg, out = L.config, []
    inverse = L.inverse
    if cfg.awaits_urdf:
        out.append('waiting for the robot model: inverse_dynamics=urdf and neither '
                   'robot_description nor urdf_file is set; nothing is learned until a URDF '
                   'arrives on /robot_description (robot_state_publisher publishes it)')
    stalled = L.window.stalled_for(cfg, L.last_t, STALL_WARN_S)
    if stalled is not None:
        out.append(f'learning stalled: no sample learned for {stalled:.0f} s while the '
                   f'velocities moved (check selection_min_distance / selection_scale)')
    if L.front.effort is not None:
        said = L.front.effort.warning(L.structure_names() or [], cfg.effort_scale)
        if said:
            out.append(said)
    frac = L.window.negative_power_fraction()
    if frac is not None and frac > cfg.negative_power_warn_fraction:
        what = 'effort - inverse dynamics' if inverse is not None else 'effort'
        hint = ('check the URDF, the joint order and the torque sign convention'
                if inverse is not None else
                'raw joint torques hold gravity and inertia: set inverse_dynamics (urdf and '
                'robot_description, or a python plugin) so the rigid-body torque is '
                'subtracted')
        out.append(f'data are not damping: qd . ({what}) < 0 on {100 * frac:.0f}% of the '
                   f'recent samples (friction dissipates); {hint}')
    out += _front_warnings(L.front.residual, L.health)
    starved = _starved(L.health)
    if starved:
        out.append(starved)
    if L.served.model is not None:
        names = L.structure_names() or [str(j) for j in range(L.N or 0)]
        bad = L.grounds.worse_than_nothing(names)
        if bad:
            out.append(f'the model answered worse than no answer on {", ".join(bad)} (one-step, '
                       f'the last {FLOOR_S:g} s): those answers fall back to the parametric '
                       'part, or to zero where it did worse too')
        worse = L.grounds.trailing(names)
        if worse:
            out.append(f'the model answers worse than its parametric part on '
                       f'{", ".join(worse)} (one-step, the last seconds): the answers fall back '
                       'to it there')
    return out


def _starved(h) -> str:
    """
    Say that the learner is short of CPU; '' when it is not.

    Short: its last fit's wall time over its own computing time is at least ``STARVED_RATIO``
    (and the wall at least ``STARVED_MIN_S``). Quiet, a fit's thread shares the learner process
    with its own loop (2-3x its computing time); beside two busy processes a learner at nice 10
    took 4.4 s of wall for 0.24 s of work (18x).
    The model then learns more slowly: the answers lean on the parametric part and on the
    model they have, and a controller should know.
    """
    wall, cpu = h.last_fit_wall_s, h.last_fit_cpu_s
    if not (wall >= STARVED_MIN_S and cpu > 0 and wall >= STARVED_RATIO * cpu):
        return ''
    return (f'the learner is short of CPU: its last refit took {wall:.1f} s for {cpu:.2f} s '
            f'of computing ({wall / cpu:.0f}x): the model learns more slowly and the answers '
            'lean on the parametric part meanwhile (other processes take the CPU, and the '
            'learner runs niced: learner_sched)')


def _front_warnings(front, h) -> List[str]:
    """Warn of the residual front end: a stream too slow, dropped samples, a failing plugin."""
    out, f = [], front.filter
    if f is not None and f.too_slow:
        out.append(f'the stream is too slow for the acceleration filter: one sample every '
                   f'{1e3 * f.sample_interval_s:.0f} ms, its longest window (0.2 s each '
                   'side) holds fewer than 2 per side; nothing is learned: publish '
                   'joint_states at 10 Hz or more')
    elif f is not None and f.samples_out < f.dropped and f.dropped >= 20:
        out.append(f'the acceleration filter dropped {f.dropped} of the residual samples '
                   f'(gaps of over {1e3 * max(f.max_gap_s, 4 * f.sample_interval_s):.0f} ms '
                   'or stamps that go back restart it): few samples are learned; a longer '
                   'accel_half_window_s bridges short gaps')
    if h.inverse_dynamics_errors and h.inverse_dynamics_errors >= 0.01 * max(
            h.samples_added + h.samples_rate_limited, 1):
        out.append(f'inverse dynamics failed on {h.inverse_dynamics_errors} samples (not '
                   'learned; check the plugin, the joints and their order)')
    return out

"""
dgp-replay on robot bags.

Raw /joint_states of a simulated Panda (gravity and inertia in the effort), with and without
inverse dynamics; --save-model; partial outputs on SIGINT.
"""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dgp_ros.apps.replay import main as replay_main
from dgp_ros.bags import write_joint_state_bag
from dgp_ros.dynamics import ARM_JOINTS, example_robot_urdf, friction_truth, simulate_arm
from dgp_ros.gp import load_model

NAMES = list(ARM_JOINTS['panda'])


def _bag(tmp_path_factory, seconds):
    d = simulate_arm('panda', seconds, seed=3)
    bag = tmp_path_factory.mktemp('bag') / 'panda'
    samples = [(t, NAMES + ['panda_finger_joint1'], np.r_[q, 0.02], np.r_[v, 0.0],
                np.r_[e, 0.1]) for t, q, v, e in zip(d['t'], d['q'], d['qd'], d['effort'])]
    write_joint_state_bag(bag, samples, topic='/joint_states')
    return bag, d


@pytest.fixture(scope='module')
def panda_bag(tmp_path_factory):
    """Return 10 s of the simulated Panda: one period of its excitation (held-out scores)."""
    return _bag(tmp_path_factory, 10.0)


@pytest.fixture(scope='module')
def short_bag(tmp_path_factory):
    """Return its first 3 s: what the checks of warnings and errors need (300 learned samples)."""
    return _bag(tmp_path_factory, 3.0)


COMMON = ['--model', 'diag', '--joints', ','.join(NAMES), '--no-plots', '-q',
          '--set', 'prior=friction', '--set', 'bias=true', '--set', 'buffer_size=150',
          '--set', 'min_samples=60', '--set', 'refit_period_s=1.0']


def test_urdf_replay_learns_friction_and_saves_a_loadable_model(panda_bag, tmp_path, capsys):
    bag, d = panda_bag
    out, model = tmp_path / 'o', tmp_path / 'm.npz'
    rc = replay_main([str(bag), '--out', str(out), '--save-model', str(model),
                      '--set', 'inverse_dynamics=urdf',
                      '--set', f'urdf_file={example_robot_urdf("panda")}'] + COMMON)
    err = capsys.readouterr().err
    assert rc == 0, err
    s = json.loads((out / 'summary.json').read_text())
    assert s['status']['level'] == 0, s['status']
    assert s['learned_negative_power_fraction'] < 0.1
    assert s['estimates'] == len(d['t']) and s['model_file'] == str(model)
    m = load_model(model)
    later = simulate_arm('panda', 16.0, seed=3)
    Qs = later['qd_true'][10000::20]
    truth = friction_truth('panda', Qs)
    nmse = np.mean((m.predict(Qs) - truth) ** 2, axis=0) / np.var(truth, axis=0)
    assert np.median(nmse) < 0.5, nmse              # held out: the next 6 s of the trajectory
    assert np.einsum('ij,ij->i', Qs, m.predict(Qs)).min() >= 0


def test_replay_with_the_default_prior_prints_no_python_warning(short_bag, tmp_path, recwarn):
    """
    Replay prints no RuntimeWarning.

    The Stribeck prior fitted to an empty buffer (the first answers) warned 'Mean of empty
    slice' on every replay with inverse dynamics. With the plots, the friction curves too.
    """
    bag, _ = short_bag
    out = tmp_path / 'o'
    rc = replay_main([str(bag), '--out', str(out), '--joints', ','.join(NAMES),
                      '--model', 'diag', '-q', '--set', 'inverse_dynamics=urdf',
                      '--set', f'urdf_file={example_robot_urdf("panda")}',
                      '--set', 'refit_period_s=1.0', '--set', 'min_samples=150'])
    assert rc == 0
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)], \
        [str(w.message) for w in recwarn]
    s = json.loads((out / 'summary.json').read_text())
    assert 'friction_curves.png' in s['plots'] and (out / 'friction_curves.png').stat().st_size
    # the summary says what the prior is and which elements of D each joint keeps
    assert s['structure'].split(',')[0] in ('none', 'viscous', 'friction', 'friction+stribeck')
    el = s['elements']
    assert set(el) == {'chosen', 'heldout_error', 'over_parametric'}
    for per in el['over_parametric'].values():
        assert set(per) <= set(NAMES) and all(v is None or v > 0 for v in per.values())


def test_the_elements_report_gives_each_choice_over_the_parametric_part():
    from dgp_ros.apps.replay_report import elements_report
    diag = {'elements': 'own: 0, none: 1',
            'elements_scores': {'none': [0.2, 0.5], 'own': [0.1, 0.6], 'all': [0.3, 0.0]}}
    r = elements_report(diag, ['a', 'b'])
    assert r['chosen'] == 'own: 0, none: 1'
    assert r['over_parametric'] == {'own': {'a': pytest.approx(0.5), 'b': pytest.approx(1.2)},
                                    'all': {'a': pytest.approx(1.5), 'b': 0.0}}
    assert elements_report({'elements': '', 'elements_scores': {}}, ['a'])['over_parametric'] == {}
    assert elements_report({'elements_scores': {'none': [0.0], 'own': [0.1]}},
                           ['a'])['over_parametric'] == {'own': {'a': None}}


def test_urdf_without_a_urdf_is_refused_offline(short_bag, tmp_path, capsys):
    """The node waits for /robot_description; a bag replay has no such topic: exit 2, why."""
    bag, _ = short_bag
    rc = replay_main([str(bag), '--out', str(tmp_path / 'o'), '--set', 'inverse_dynamics=urdf'])
    err = capsys.readouterr().err
    assert rc == 2 and 'urdf_file' in err and '/robot_description' in err, err


def test_raw_effort_replay_warns_with_the_reason(short_bag, tmp_path, capsys):
    bag, _ = short_bag
    rc = replay_main([str(bag), '--out', str(tmp_path / 'o')] + COMMON)
    err = capsys.readouterr().err
    assert rc == 0
    s = json.loads((tmp_path / 'o' / 'summary.json').read_text())
    assert s['status']['level'] >= 1 and 'inverse_dynamics' in s['status']['message']
    assert s['learned_negative_power_fraction'] > 0.2
    assert 'warning: ' in err and 'data are not damping' in err


# an inverse-dynamics plugin (zero rigid-body torque) that holds the replay at its 1000th call
# until a signal comes (bounded): the SIGINT then lands mid-stream whatever the replay's speed
GATE_PLUGIN = """
import os, time
import numpy as np
calls = 0
def tau_rb(q, qd, qdd):
    global calls
    calls += 1
    if calls == 1000:
        open(os.environ['DGP_TEST_GATE'], 'w').close()
        end = time.monotonic() + 120
        while time.monotonic() < end:
            time.sleep(0.01)
    return np.zeros_like(q)
"""


def test_sigint_leaves_partial_csv_and_summary(panda_bag, tmp_path):
    bag, _ = panda_bag
    out = tmp_path / 'o'
    (tmp_path / 'gate_plugin.py').write_text(GATE_PLUGIN)
    gate = tmp_path / 'held'
    env = dict(os.environ, DGP_TEST_GATE=str(gate),
               PYTHONPATH=os.pathsep.join([str(tmp_path)] + [
                   p for p in [os.environ.get('PYTHONPATH')] if p]))
    # the interruption is the point, not the model: Diag-D-GP with a fixed prior learns fast
    cmd = [sys.executable, '-m', 'dgp_ros.apps.replay', str(bag), '--out', str(out), '--model',
           'diag', '--joints', ','.join(NAMES), '--set', 'min_sample_interval_s=0.0', '--no-plots',
           '--set', 'prior=friction', '--set', 'inverse_dynamics=python:gate_plugin:tau_rb']
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    csv_file = out / 'estimates.csv'
    try:
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end and not gate.exists() and p.poll() is None:
            time.sleep(0.05)
        assert gate.exists(), 'the replay never reached the 1000th sample'
        assert csv_file.stat().st_size > 0              # written as it goes
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 130, err
    assert 'Traceback' not in err and 'partial results' in err
    s = json.loads((out / 'summary.json').read_text())
    rows = csv_file.read_text().splitlines()
    assert s['interrupted'] and 0 < s['estimates'] < 10000
    assert len(rows) - 1 >= s['estimates'] - 1                  # flushed rows, header + data
    assert not os.path.exists(out / 'summary.json.tmp')


#: the one-liner a user's controller runs on a saved robot model (only dgp_ros.gp imported)
ONE_LINER = ('import json, numpy as np; from dgp_ros.gp import load_model; '
             'm = load_model("friction.npz"); d = np.load("poses.npz"); '
             'r = m.predict_residual(q=d["q"], qd=d["qd"]); '
             'print(json.dumps({"r": r.tolist(), "kept": type(m.correction_).__name__}))')


def test_a_saved_robot_model_evaluates_with_one_import(tmp_path):
    """
    ``dgp-replay --save-model`` with the default prior (auto): the model carries a correction.

    A fresh interpreter that imports ``dgp_ros.gp`` alone evaluates ``predict_residual`` on it
    (the correction's owner is found through dgp_ros's entry point), equal to the answer of the
    process that has the robot front end imported.
    """
    d = simulate_arm('panda', 3.0, seed=3)
    bag = tmp_path / 'bag'
    write_joint_state_bag(bag, list(zip(d['t'], [NAMES] * len(d['t']), d['q'], d['qd'],
                                        d['effort'])), topic='/joint_states')
    rc = replay_main([str(bag), '--out', str(tmp_path / 'o'), '--save-model',
                      str(tmp_path / 'friction.npz'), '--model', 'diag', '--joints',
                      ','.join(NAMES), '--no-plots', '-q', '--set', 'buffer_size=60',
                      '--set', 'min_samples=40', '--set', 'refit_period_s=1.0',
                      '--set', 'inverse_dynamics=urdf',
                      '--set', f'urdf_file={example_robot_urdf("panda")}'])
    assert rc == 0
    q, qd = d['q'][::250], d['qd'][::250]
    np.savez(tmp_path / 'poses.npz', q=q, qd=qd)
    p = subprocess.run([sys.executable, '-c', ONE_LINER], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert out['kept'] == 'SavedCorrection'         # loaded without the robot front end
    here = load_model(tmp_path / 'friction.npz')
    assert here.correction_ is not None
    ref = here.predict_residual(q=q, qd=qd)
    np.testing.assert_array_equal(np.array(out['r']), ref)
    assert np.abs(ref - here.predict(qd)).max() > 1e-6      # the correction is in it

"""
sim_bridge offline.

Trim, envelope of the approach, lift balance, sign conventions, body coords.
"""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from sim_bridge import ApproachSimulator, FrozenAero, SimConfig, simulate_approach
from sim_bridge.simulator import LBF_TO_N


@pytest.fixture(scope='session')
def approach():
    """Return the default approach, simulated once per session (angle coordinates)."""
    return simulate_approach(SimConfig())


@pytest.fixture(scope='session')
def approach_body():
    return simulate_approach(SimConfig(coordinates='body'))


def test_trim_succeeds_on_glide_path_in_landing_configuration():
    cfg = SimConfig()
    sim = ApproachSimulator(cfg)
    sim.reset()                                    # loads the aircraft and trims it
    fdm = sim.fdm
    assert sim.trim_speed_kts == cfg.approach_speed_kts
    assert fdm['fcs/flap-pos-deg'] == pytest.approx(40.0)
    assert fdm['gear/gear-pos-norm'] == pytest.approx(1.0)
    assert math.degrees(fdm['flight-path/gamma-rad']) == pytest.approx(-3.0, abs=0.05)
    assert fdm['position/h-agl-ft'] == pytest.approx(1000.0, abs=1.0)
    # trimmed: no residual accelerations, controls inside their ranges
    assert abs(fdm['accelerations/udot-ft_sec2']) < 0.1
    assert abs(fdm['accelerations/wdot-ft_sec2']) < 0.1
    assert 0.0 < fdm['fcs/throttle-cmd-norm[0]'] < 1.0
    assert -1.0 < fdm['fcs/pitch-trim-cmd-norm'] < 0.0


def test_trim_fails_cleanly_far_below_the_full_flap_speed():
    from sim_bridge import TrimError
    sim = ApproachSimulator(SimConfig(approach_speed_kts=100.0))
    with pytest.raises(TrimError):
        # 100..135 kt: the model runs out of nose-up elevator; all fallbacks fail too
        sim.reset()


def test_approach_reaches_touchdown_inside_envelope(approach):
    d = approach
    assert d['touched_down']
    alpha = np.degrees(d['alpha'])
    assert np.all(np.abs(alpha) < 20.0), (alpha.min(), alpha.max())
    v_rel = d['airspeed'] / d['trim_airspeed_mps']
    assert np.all(np.abs(v_rel - 1.0) < 0.30), (v_rel.min(), v_rel.max())
    # no ground contact (gear or structure) before the runway threshold, i.e. where the
    # glide path reaches the runway
    before = d['along_track_m'] < d['threshold_m']
    assert not np.any(d['ground_contact'][before])
    assert d['touchdown_along_track_m'] >= d['threshold_m']
    assert d['ground_contact'][-1]
    assert np.all(d['load_factor'] > 0.0) and np.all(d['load_factor'] < 2.5)
    # wind really blew: sideslip and alpha vary
    assert np.ptp(d['beta']) > math.radians(5) and np.ptp(d['alpha']) > math.radians(5)


def test_mean_lift_balances_weight(approach):
    d = approach
    lift = d['tau'][:, 2]
    expected = d['weight_n'] * math.cos(math.radians(3.0))
    assert lift.mean() == pytest.approx(expected, rel=0.10)


def test_jsbsim_wind_force_signs_and_tau_convention():
    """
    Check the JSBSim 1.3.3 wind force signs and the tau convention.

    JSBSim 1.3.3: fwx = +drag, fwz = +lift (magnitudes), fwy = side force opposing beta.
    """
    sim = ApproachSimulator(SimConfig(wind_amplitude=(0.0, 10.0, 0.0), wind_ramp_s=0.0))
    sim.reset()
    fdm = sim.fdm
    assert fdm['forces/fwx-aero-lbs'] > 0          # drag, positive
    assert fdm['forces/fwz-aero-lbs'] > 0          # lift, positive (NOT -lift)
    assert fdm['forces/fbz-aero-lbs'] < 0          # body z is down: lift points up
    states = [sim.step() for _ in range(60)]
    s = states[-1]                                 # fdm holds this state
    assert abs(s.beta) > math.radians(1)
    assert np.sign(fdm['forces/fwy-aero-lbs']) == -np.sign(fdm['aero/beta-rad'])
    # published: force_wind = [-drag, side, -lift], tau = -force_wind = [drag, -side, lift]
    assert s.force_wind[0] < 0 and s.force_wind[2] < 0
    np.testing.assert_allclose(s.tau, -s.force_wind)
    assert s.tau[0] > 0 and s.tau[2] > 0
    assert s.beta * s.tau[1] > 0                   # beta * (-side) is dissipative
    # consistency with JSBSim's body-axis force: F_body = T_w2b(alpha, beta) F_wind
    a, b = s.alpha, s.beta
    tw2b = np.array([[math.cos(a) * math.cos(b), -math.cos(a) * math.sin(b), -math.sin(a)],
                     [math.sin(b), math.cos(b), 0.0],
                     [math.sin(a) * math.cos(b), -math.sin(a) * math.sin(b), math.cos(a)]])
    np.testing.assert_allclose(tw2b @ s.force_wind, s.force_body, rtol=1e-6, atol=1.0)
    assert abs(s.tau[2] - fdm['forces/fwz-aero-lbs'] * LBF_TO_N) < 1e-6 * s.tau[2]


def test_angle_coordinates_layout(approach):
    d = approach
    assert d['joint_names'] == ['alpha', 'beta', 'airspeed']
    np.testing.assert_allclose(d['q'][:, 0], d['alpha'])
    np.testing.assert_allclose(d['q'][:, 1], d['beta'])
    np.testing.assert_allclose(d['q'][:, 2], d['airspeed'])
    assert d['q'].shape == d['tau'].shape == d['force_wind'].shape == (len(d['t']), 3)
    np.testing.assert_allclose(np.diff(d['t']), 1 / 60.0, atol=1e-9)
    # in normal flight every dissipated-power term except alpha*drag at alpha<0 is >= 0
    assert np.all(d['q'][:, 2] * d['tau'][:, 2] > 0)
    assert np.all(d['q'][:, 1] * d['tau'][:, 1] >= -1e-6)


def test_body_coordinates_are_passive(approach_body):
    d = approach_body
    assert d['joint_names'] == ['u', 'v', 'w']
    power = np.einsum('ij,ij->i', d['q'], d['tau'])
    assert np.all(power >= 0.0)
    # q^T tau = drag * V (lift does no work)
    drag = -d['force_wind'][:, 0]
    np.testing.assert_allclose(power, drag * d['airspeed'], rtol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(d['q'], axis=1), d['airspeed'], rtol=1e-6)


def test_deterministic():
    cfg = SimConfig(max_time_s=3.0)
    a, b = simulate_approach(cfg), simulate_approach(cfg)
    np.testing.assert_array_equal(a['q'], b['q'])
    np.testing.assert_array_equal(a['tau'], b['tau'])


def test_frozen_aero_matches_simulation(approach):
    d = approach
    idx = np.arange(0, len(d['t']), 400)
    tau = FrozenAero(SimConfig()).tau(d['q'][idx])
    assert tau.shape == (len(idx), 3)
    # the flown states add angular rates and elevator motion: agree within a few percent
    np.testing.assert_allclose(tau[:, 2], d['tau'][idx, 2], rtol=0.08)
    np.testing.assert_allclose(tau[:, 0], d['tau'][idx, 0], rtol=0.15)
    # exactly at trim, it is the trimmed force
    np.testing.assert_allclose(tau[0], d['tau'][0], rtol=1e-4, atol=1.0)


def test_frozen_aero_body_and_zero_speed():
    fa = FrozenAero(SimConfig(coordinates='body'))
    Q = np.array([[90.0, 3.0, 8.0], [0.0, 0.0, 0.0], [80.0, -5.0, -2.0]])
    tau = fa.tau(Q)
    np.testing.assert_array_equal(tau[1], 0.0)
    assert np.all(np.einsum('ij,ij->i', Q, tau) >= 0)
    with pytest.raises(ValueError):
        fa.tau(np.zeros((2, 2)))


@pytest.mark.parametrize('kw, match', [
    ({'coordinates': 'polar'}, 'coordinates'),
    ({'rate_hz': 0.0}, 'rate_hz'),
    ({'wind_amplitude': (0.0, 30.0, 0.0)}, r'\+-25'),
    ({'wind_amplitude': (1.0, 2.0)}, 'exactly 3'),
    ({'wind_frequency': (0.1, -0.2, 0.3)}, 'wind_frequency'),
    ({'wind_phase': (0.0, float('nan'), 0.0)}, 'finite'),
    ({'aircraft': 'B999'}, 'not found'),
])
def test_config_validation_messages(kw, match):
    with pytest.raises(ValueError, match=match):
        SimConfig(**kw).validate()


def test_export_cli(tmp_path):
    out = tmp_path / 'a.npz'
    r = subprocess.run([sys.executable, '-m', 'sim_bridge.export', '--out', str(out),
                        '--coordinates', 'body', '--wind-amplitude', '0,5,0'],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    d = np.load(out)
    assert d['q'].shape == d['tau'].shape and d['q'].shape[1] == 3
    assert d['t'].shape == (d['q'].shape[0],)
    assert float(d['mass_kg']) > 50000
    cfg = json.loads(str(d['config']))
    assert cfg['coordinates'] == 'body' and cfg['wind_amplitude'] == [0.0, 5.0, 0.0]
    r = subprocess.run([sys.executable, '-m', 'sim_bridge.export', '--out', str(out),
                        '--wind-amplitude', '0,40,0'], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and '+-25' in r.stderr

"""
The accuracy ledger (issue 30): both worlds with the node's defaults, against the best reached.

Each case is ``bench/ledger.py``'s (the same code writes the ledger's section of
docs/BENCHMARKS.md): the A320 approach of sim_bridge one step ahead, the shared real Panda log
held out (skipped with the reason where the shared data are absent, as in a user's clone), the
simulated Panda with friction outside the prior's family held out. The thresholds are
``ledger.LIMITS``: about 1.4x the best value reached, so a 1.5x loss of any figure fails here.
"""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                'bench'))

import ledger  # noqa: E402


@pytest.fixture
def a320(session_once):
    # the flight and its answers once per session, whichever worker asks first (conftest)
    return session_once('ledger_a320', lambda _: ledger.a320_case(ledger.a320_flight()))


def test_a320_first_20_s_one_step_ahead(a320):
    assert ledger.check('a320_early', a320['early']) == [], a320
    assert a320['early'].max() <= 0.02                      # the bar


def test_a320_whole_flight_one_step_ahead(a320):
    assert a320['flight_s'] > 55.0                          # the whole approach, to touch-down
    assert ledger.check('a320_whole', a320['whole']) == [], a320
    assert a320['whole'].max() <= 5e-3                      # the bar
    # passive data never stop the learning
    assert a320['absorbs_rejected'] == 0 and a320['refits_failed'] == 0, a320


# the real Panda split is the robot family's first case (test/test_robot_family.py)


@pytest.mark.timeout(1200)
@pytest.mark.parametrize('robot', ['panda', pytest.param('ur5', marks=pytest.mark.slow)])
def test_simulated_arm_held_out(robot):
    """
    The simulated arm held out within its ledger limits.

    The default suite holds the Panda; the UR5 (the same case on the demo's other arm, 16 CPU-s)
    is in the slow suite (``-m slow``), which keeps the default run within 6 minutes on 2 cores.
    """
    # friction outside the prior's family (direction asymmetry, |v|^0.6 viscous, growing with
    # the gravity load), a payload the URDF lacks, sensor noise and bias
    r = ledger.panda_sim_case(robot=robot)
    assert ledger.check(f'{robot}_sim_geo', r['geo']) == [], r
    assert ledger.check(f'{robot}_sim_worst', r['worst']) == [], r


def test_the_check_fails_beyond_a_limit():
    lim = np.array(ledger.LIMITS['a320_whole'])
    assert ledger.check('a320_whole', lim) == []
    assert len(ledger.check('a320_whole', lim * [1.0, 1.5, 1.0])) == 1
    assert ledger.check('panda_real_mean', 1.5 * ledger.LIMITS['panda_real_mean']) != []


#: the default suite flies the first of the ledger's test family (the latest regression,
#: dd2123c); the others (3 and 6, 22-29 CPU-s each, the same check on other winds) fly in the
#: slow suite (``-m slow``), which keeps the default run within 6 minutes on 2 cores
FAMILY_CASES = [i if i == ledger.A320_TEST_FAMILY[0] else pytest.param(i, marks=pytest.mark.slow)
                for i in ledger.A320_TEST_FAMILY]


@pytest.mark.parametrize('index', FAMILY_CASES)
def test_a320_family_flight_one_step_ahead(index):
    """One flight of the ledger's A320 family within the family limits (``FAMILY_CASES``)."""
    # one flight is not the aircraft: stronger wind along the runway, other phases (each of these
    # failed on 0623bec: drag answers off by a standard deviation the first time the aircraft
    # reached negative angles of attack)
    r = ledger.family_case(index)
    assert r['flight_s'] > 45.0, r
    assert ledger.family_check(r) == [], r
    assert r['refits_failed'] == 0, r


def test_the_family_check_fails_beyond_a_limit():
    ok = {'label': 'x', 'whole': np.full(3, 1e-3), 'early': np.full(3, 1e-3),
          'window_max': np.full(3, 1e-2)}
    assert ledger.family_check(ok) == []
    for key, bad in (('whole', 6e-3), ('early', 0.03), ('window_max', 0.11)):
        r = dict(ok, **{key: np.array([1e-3, bad, 1e-3])})
        assert len(ledger.family_check(r)) == 1, key


def test_closed_loop_learning_transient_does_no_harm():
    # the first seconds of the closed-loop arm with the estimator's compensation (times its
    # confidence) are no worse than no compensation: per 1 s window and per joint's peak
    r = ledger.loop_transient_case()
    assert len(r['window_ratios']) == int(ledger.LOOP_S), r
    assert ledger.check('loop_window', r['window_ratios'],
                        [ledger.LIMITS['loop_window']] * len(r['window_ratios'])) == [], r
    assert ledger.check('loop_peak', r['peak_ratios'],
                        [ledger.LIMITS['loop_peak']] * len(r['peak_ratios'])) == [], r
    assert r['nonpassive_answers'] == 0, r

"""
The robot family (issue 42): the node's defaults on real arms at their rates and resampled.

Each case is ``bench/robot_family.py``'s (the same code writes its section of
docs/BENCHMARKS.md): learn the first part of a shared real log, hold the saved model out on the
rest, beside Coulomb-viscous and sigmoid refits of the same samples; the published answers one
step ahead beat answering zero on every joint; no negative power. The limits are
``robot_family.LIMITS``; each case failed on 1b13a8e (the UR10 held out at 262x the refit,
the Panda at 30 Hz never trained). Skipped with the reason where the shared logs are absent
(a user's clone).
"""
import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                'bench'))

import robot_family  # noqa: E402


#: the suite's cases: every rate but 500 Hz, which lies between the ~1 kHz log and its 125 Hz
#: decimation and costs 20 s (bench/robot_family.py runs it). The Panda at 125 Hz (15 CPU-s) runs
#: in the slow suite (``-m slow``): the same log as the ~1 kHz case, at the UR10's rate, between
#: the 1 kHz and 30 Hz cases the default run keeps (within 6 minutes on 2 cores)
SUITE = [c[0] if c[0] != 'real Panda at 125 Hz' else pytest.param(c[0], marks=pytest.mark.slow)
         for c in robot_family.CASES if c[2] != 500.0]


@pytest.mark.timeout(600)       # 10-40 s alone: the suite's 300 s guard is for hangs
@pytest.mark.parametrize('label', SUITE)
def test_a_real_arm_held_out_beside_its_parametric_refits(label):
    """One case of the robot family within its limits (``SUITE``: the 125 Hz Panda is slow)."""
    log = robot_family.family_log(label)
    if log is None:
        pytest.skip(f'the shared log of {label!r} (../shared/data) is not here')
    r = robot_family.arm_case(log)
    assert robot_family.check(label, r) == [], r


def test_the_check_fails_beyond_a_limit():
    import numpy as np
    ok = {'trained': True, 'mean': 0.02, 'held': np.full(6, 0.02), 'cv': np.full(6, 0.021),
          'sigmoid': np.full(6, 0.03), 'live': np.full(6, 0.1), 'zero': np.ones(6),
          'negative_power': 0, 'saved_negative_power': 0, 'status': (0, 'ok')}
    label = 'real UR10, 125 Hz'
    assert robot_family.check(label, ok) == []
    held = ok['held'].copy()
    held[2] = 0.04
    for bad in ({'mean': 0.03}, {'held': held}, {'live': np.r_[np.full(5, 0.1), 1.5]},
                {'saved_negative_power': 1}, {'trained': False},
                {'status': (1, 'the effort does not behave as joint torque on j2: ...')}):
        assert robot_family.check(label, dict(ok, **bad)), bad
    assert robot_family.check('real Panda at 30 Hz', dict(ok, mean=0.031))

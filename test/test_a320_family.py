"""
Random A320 approaches the defaults were not chosen on (issue 48), small: one of the family.

``bench/a320_family.py`` draws wind on all three axes (up to 25 m/s each, 0.05-0.4 Hz) and
approach speeds of 170-200 kt from fixed seeds; the suite flies one of its 24 flights (not one
of the ledger's) with the node's defaults in line and holds them to the ledger's bars:
one step ahead, whole flight <= 5e-3, first 20 s <= 0.02, no 1 s window above 0.1, per output,
and no refit fails. The whole family is in docs/BENCHMARKS.md ("A320 random family"), with the
flights that fail it today.
"""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                'bench'))

import a320_family  # noqa: E402,I100

#: flights of the family the suite flies (one: the ledger's tests fly two more approaches, and two
#: more in the slow suite)
SUITE_FLIGHTS = (12,)


@pytest.mark.parametrize('index', SUITE_FLIGHTS)
def test_a_random_approach_is_learned_one_step_ahead_within_the_ledger_bars(index, tmp_path):
    fl = a320_family.flight(index, str(tmp_path))
    assert fl['t'][-1] - fl['t'][0] > 40.0            # flown to touch-down
    r = a320_family.score(fl)
    for key, bar in a320_family.BARS.items():
        assert np.max(r[key]) <= bar, (key, r[key], r['elements'])
    assert r['refits_failed'] == 0, r

"""The long history's couplings of a persistent column (dynamics/coupling_track.py, history.py)."""
import os
import sys

import numpy as np

from dgp_ros.dynamics.coupling_track import CouplingTrack
from dgp_ros.dynamics.history import LongHistory
from dgp_ros.gp.coupled import CoupledMean

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'gp'))
from test_coupled import aircraft  # noqa: E402,I100,I201


def _feed(h, t, Q, T):
    for i in range(len(t)):
        h.push(float(t[i]), None, Q[i], None, T[i])


def test_the_history_learns_an_aircrafts_forces_through_its_airspeed():
    t = np.arange(0.0, 30.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    h = LongHistory(3, None, 'viscous', offsets=False, elements=False, couplings=True)
    _feed(h, t, Q, T)
    fit = h.select()
    assert fit.coupling is not None and fit.coupling[0].cols == (2,)
    assert 'couplings through airspeed' in fit.label(['alpha', 'beta', 'airspeed'])
    mean = fit.friction_mean().fit(None, None)
    assert isinstance(mean, CoupledMean)
    # held out: the next seconds of the stream, alpha and beta within what was seen
    Qh, Th = aircraft(np.arange(30.0, 36.0, 1.0 / 60.0))
    err = ((mean.force(Qh) - Th) ** 2).mean(axis=0) / Th.var(axis=0)
    assert np.all(err < 1e-3), err
    # a refit of the chosen structure keeps it and its memory
    again = h.refit(fit)
    assert again.family == fit.family and again.memory == fit.memory
    assert again.coupling is not None


def test_a_diagonal_prior_cannot_carry_the_drag_at_zero_angle_of_attack():
    """Why the couplings exist: the same history without them answers zero drag at alpha 0."""
    t = np.arange(0.0, 20.0, 1.0 / 60.0)
    Q, T = aircraft(t)
    h = LongHistory(3, None, 'viscous', offsets=False, elements=False, couplings=False)
    _feed(h, t, Q, T)
    mean = h.select().friction_mean().fit(None, None)
    q0 = np.array([[0.0, 0.0, 90.0]])
    assert abs(mean.force(q0)[0, 0]) < 1e-9
    hc = LongHistory(3, None, 'viscous', offsets=False, elements=False, couplings=True)
    _feed(hc, t, Q, T)
    drag = hc.select().friction_mean().fit(None, None).force(q0)[0, 0]
    assert np.isfinite(drag)
    truth = 0.5 * 1.225 * 90.0 ** 2 * 122.6 * 0.03
    assert abs(drag - truth) < 0.05 * truth


def test_velocities_that_reverse_drop_their_columns_and_leave_the_statistics_exact():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 12.0, 0.01)
    Q = np.stack([np.sin(1.3 * t + 0.2), 0.5 * np.cos(0.9 * t), np.sin(2.1 * t + 1)], 1)
    T = 2.0 * Q + 0.3 * np.tanh(Q / 0.05) + 0.01 * rng.standard_normal(Q.shape)
    hc = LongHistory(3, None, 'viscous', offsets=False, elements=False, couplings=True)
    h = LongHistory(3, None, 'viscous', offsets=False, elements=False, couplings=False)
    _feed(hc, t, Q, T)
    _feed(h, t, Q, T)
    assert hc.K == 0 and hc.coupling.cols == []
    a, b = hc.select(), h.select()
    assert a.coupling is None and a.family == b.family
    assert np.allclose(a.coef, b.coef, rtol=1e-9, atol=1e-12)
    Qr = rng.standard_normal((200, 3))
    fa, fb = a.friction_mean().fit(None, None), b.friction_mean().fit(None, None)
    assert np.allclose(fa.force(Qr), fb.force(Qr), rtol=1e-9, atol=1e-12)


def test_the_track_serves_the_least_spread_column_and_drops_what_nears_zero():
    tr = CouplingTrack(3)
    V = np.array([[0.06, 0.001, 90.0], [0.065, -0.002, 90.5], [0.07, 0.003, 91.0]])
    dead = tr.observe(V)
    assert dead == [1]                  # beta changed sign
    tr.drop_slices(dead)
    assert tr.cols == [0, 2]
    assert tr.cols[tr.serving()] == 2   # the airspeed: 0.5 % spread against alpha's 6 %
    dead = tr.observe(np.array([[0.001, 0.0, 92.0]]))    # alpha near zero
    assert dead == [0]

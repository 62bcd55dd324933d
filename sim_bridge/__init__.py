"""
sim_bridge: JSBSim A320 approach in periodic wind, as generalized velocities and forces.

Pure Python (JSBSim + numpy); the only ROS code is ``sim_bridge.node``.

Public API::

    from sim_bridge import SimConfig, ApproachSimulator, FrozenAero, simulate_approach
    sim = ApproachSimulator(SimConfig(coordinates='angle')); sim.reset(); s = sim.step()
    data = simulate_approach(SimConfig())      # dict of arrays t, q, tau, force_wind, ...
    FrozenAero(SimConfig()).tau(Q)             # force at frozen states (k, 3) -> (k, 3)

The approach: the A320 shipped with the jsbsim wheel, full flaps (40 deg), gear down, trimmed
(JSBSim full trim) on a -3 deg glide path with the CG at 1000 ft above the runway, flown to
touch-down by ``Autopilot``: pitch-attitude hold with the elevator whose attitude command tracks
the glide path (main-wheel height and sink rate), a linear flare below 60 ft, PI airspeed hold on
the throttle, wings level with the ailerons (the model's yaw damper does the rest).  The runway
threshold is where the glide path (flown by the main wheels) reaches the runway.

Trim speed: the model trims with full flaps from 160 kt CAS up (at 160 kt the trim already uses
84 % of the nose-up elevator; below it the trim fails).  The default approach speed is 180 kt
(~94 m/s TAS, elevator trim at 52 %), which leaves enough elevator for the gusts.

Wind (paper: 3-D periodic, within +-25 m/s, f = [0.1, 0.2, 0.3] Hz, phases [0, 2, 3] rad) in the
runway frame [north = along the runway, east, down], ramped in over 5 s.  Default amplitudes
[5, 25, 10] m/s, the largest found flyable by a sweep at 180 kt (flyable: |alpha| < 15 deg with
the full-flap stall at ~16 deg, load factor in (0, 2) g, the flaps-extended limit, airspeed within
+-30 % of trim, touch-down beyond the threshold):

- vertical 25 m/s at 0.3 Hz changes alpha by up to ~15 deg within 1.7 s: the aircraft stalls and
  leaves the envelope (alpha -45..46 deg, 4 g).  10 m/s gives alpha -4.8..12.5 deg and
  0.28..1.76 g; 12.5 m/s reaches 14.6 deg (1.4 deg from stall) and 1.93 g; 15 m/s exceeds 2 g.
- along the runway 25 m/s at 0.1 Hz swings the airspeed by -40..+35 % (the wind changes faster,
  up to 1.6 g, than any airliner can accelerate) and the aircraft stalls; 7.5 m/s already lands
  short of the threshold, 5 m/s is flown.
- cross-wind 25 m/s is flown (sideslip within +-9 deg), so it keeps the paper's value.
"""
from .config import FORCE_NAMES, JOINT_NAMES, MAX_WIND_MPS, SimConfig
from .simulator import (ApproachSimulator, Autopilot, FrozenAero, PeriodicWind, SimState,
                        simulate_approach, TrimError)

__all__ = ['SimConfig', 'ApproachSimulator', 'FrozenAero', 'simulate_approach', 'SimState',
           'PeriodicWind', 'Autopilot', 'TrimError', 'JOINT_NAMES', 'FORCE_NAMES',
           'MAX_WIND_MPS']

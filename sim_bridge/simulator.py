"""
JSBSim A320 approach: trim, autopilot, periodic wind and aerodynamic read-out (no ROS).

Sign conventions (checked in test/test_sim_physics.py against the installed JSBSim 1.3.3):
JSBSim's ``forces/fw[xyz]-aero-lbs`` are the *magnitudes* ``[drag, side, lift]`` (drag > 0 and
lift > 0 in normal flight; the side force is positive to the right and opposes sideslip), not a
vector in a right-handed frame.  ``SimState.force_wind`` is the physical force vector in wind
axes (x along the relative wind, y right, z down): ``F_wind = [-drag, side, -lift]``, so that
``F_body = T_w2b(alpha, beta) F_wind`` equals ``forces/fb[xyz]-aero-lbs``.  The published
resistive force is ``tau = -F_wind = [drag, -side, lift]`` (docs/CONTRACTS.md), and in body
coordinates ``tau = -F_body`` with ``q = [u, v, w]`` the air-relative body velocity.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np

from .config import SimConfig

LBF_TO_N = 4.4482216152605
FT_TO_M = 0.3048
KT_TO_MPS = 0.514444
LB_TO_KG = 0.45359237
G0 = 9.80665

#: Speeds tried after ``approach_speed_kts`` when the full trim throws (kt).
TRIM_FALLBACK_STEP_KTS = 5.0
TRIM_MAX_TRIES = 8
#: Main landing gear contact units of the A320 model (1 = LEFT_MLG, 2 = RIGHT_MLG).
MAIN_GEAR_UNITS = (1, 2)


class TrimError(RuntimeError):
    """JSBSim could not trim the aircraft in the requested approach configuration."""


@dataclass
class SimState:
    """One output sample of the approach."""

    t: float                  # simulation time (s)
    q: np.ndarray             # (3,) generalized velocity in the configured coordinates
    tau: np.ndarray           # (3,) resistive aerodynamic force (N) in the same coordinates
    force_wind: np.ndarray    # (3,) aero force in wind axes [-drag, side, -lift] (N)
    force_body: np.ndarray    # (3,) raw JSBSim body-axis aero force [fbx, fby, fbz] (N)
    alpha: float              # rad
    beta: float               # rad
    airspeed: float           # true airspeed relative to the air (m/s)
    altitude_agl_m: float     # CG height above the runway (m)
    wheel_height_m: float     # main-gear height above the runway (m)
    along_track_m: float      # distance flown along the runway axis since the start (m)
    glide_path_error_m: float  # wheel height minus glide-path height (m)
    load_factor: float        # lift / weight (JSBSim forces/load-factor)
    nz: float                 # normal load factor at the CG (g), accelerations/Nz
    theta: float              # pitch attitude (rad)
    phi: float                # bank angle (rad)
    gamma: float              # flight-path angle (rad)
    wind_ned: np.ndarray      # (3,) wind [north, east, down] (m/s)
    throttle: float
    elevator: float
    touched_down: bool
    ground_contact: bool      # any contact point (gear or structure) on the ground


def _cos_ramp(t, ramp):
    if ramp <= 0 or t >= ramp:
        return 1.0
    return 0.5 - 0.5 * math.cos(math.pi * t / ramp)


class PeriodicWind:
    """3-D periodic wind ``r(t) A_i sin(2 pi f_i t + phi_i)`` in [north, east, down] (m/s)."""

    def __init__(self, amplitude, frequency, phase, ramp_s=0.0):
        self.amplitude = np.asarray(amplitude, float)
        self.frequency = np.asarray(frequency, float)
        self.phase = np.asarray(phase, float)
        self.ramp_s = float(ramp_s)

    def __call__(self, t: float) -> np.ndarray:
        return _cos_ramp(t, self.ramp_s) * self.amplitude * np.sin(
            2 * math.pi * self.frequency * t + self.phase)


def _new_exec(cfg: SimConfig):
    import jsbsim
    jsbsim.FGJSBBase().debug_lvl = 0   # silence the banner of the next FGFDMExec
    fdm = jsbsim.FGFDMExec(cfg.jsbsim_root())
    fdm.set_debug_level(0)
    if not fdm.load_model(cfg.aircraft):
        raise ValueError(f'JSBSim could not load aircraft {cfg.aircraft!r}')
    fdm.set_dt(cfg.dt)
    return fdm


def _set_approach_ic(fdm, cfg: SimConfig, speed_kts: float):
    fdm['ic/terrain-elevation-ft'] = 0.0
    fdm['ic/lat-geod-deg'] = 0.0
    fdm['ic/long-gc-deg'] = 0.0
    fdm['ic/h-agl-ft'] = cfg.start_height_ft
    fdm['ic/psi-true-deg'] = 0.0
    fdm['ic/phi-deg'] = 0.0
    fdm['ic/vc-kts'] = speed_kts
    fdm['ic/gamma-deg'] = -cfg.glide_slope_deg
    for prop in ('atmosphere/wind-north-fps', 'atmosphere/wind-east-fps',
                 'atmosphere/wind-down-fps'):
        fdm[prop] = 0.0
    # Landing configuration: full flaps, gear down (set positions too: no transition at t=0).
    fdm['fcs/flap-cmd-norm'] = 1.0
    fdm['fcs/flap-pos-deg'] = 40.0
    fdm['gear/gear-cmd-norm'] = 1.0
    fdm['gear/gear-pos-norm'] = 1.0
    fdm['fcs/speedbrake-cmd-norm'] = 0.0
    fdm['propulsion/set-running'] = -1
    fdm.run_ic()
    fdm['fcs/flap-pos-deg'] = 40.0
    fdm['gear/gear-pos-norm'] = 1.0


def trim_approach(fdm, cfg: SimConfig):
    """Full trim on the glide path; returns the speed (kt) that trimmed. Raises TrimError."""
    import jsbsim
    errors = []
    for k in range(TRIM_MAX_TRIES):
        speed = cfg.approach_speed_kts + k * TRIM_FALLBACK_STEP_KTS
        _set_approach_ic(fdm, cfg, speed)
        try:
            fdm['simulation/do_simple_trim'] = 1  # tFull
        except jsbsim.TrimFailureError as exc:
            errors.append(f'{speed:.0f} kt: {exc}')
            continue
        return speed
    raise TrimError(f'{cfg.aircraft} does not trim on a -{cfg.glide_slope_deg} deg glide path '
                    f'with full flaps and gear down ({"; ".join(errors)})')


class Autopilot:
    """
    Glide-path tracking by pitch attitude (elevator), PI airspeed hold (throttle), wings level.

    All gains are in JSBSim normalised command units per rad, rad/s, m or m/s.
    """

    # pitch attitude hold (elevator); positive elevator = nose down in this model
    K_THETA = 4.0
    K_Q = 3.0
    K_THETA_I = 1.0
    # glide path -> pitch attitude command
    K_H = 0.006       # rad per m of height error
    K_HDOT = 0.025    # rad per m/s of sink-rate error
    THETA_AUTH = math.radians(10.0)
    # airspeed hold (throttle)
    K_V = 0.08
    K_V_I = 0.02
    # wings level (aileron); positive aileron = roll right
    K_PHI = 2.0
    K_P = 1.5
    # flare: commanded sink rate proportional to wheel height
    FLARE_MIN_SINK = 0.4
    K_FLARE = 0.06    # rad per m/s of sink-rate error in the flare

    def __init__(self, cfg: SimConfig, trim: dict):
        self.cfg = cfg
        self.trim = trim
        self.tan_gs = math.tan(math.radians(cfg.glide_slope_deg))
        self.h_flare = cfg.flare_height_ft * FT_TO_M
        self.int_theta = 0.0
        self.int_v = 0.0

    def glide_path_height(self, x):
        return self.trim['wheel_height_m'] - x * self.tan_gs

    def __call__(self, fdm, x, wheel_h, dt):
        tr = self.trim
        theta = fdm['attitude/theta-rad']
        q = fdm['velocities/q-rad_sec']
        phi = fdm['attitude/phi-rad']
        p = fdm['velocities/p-rad_sec']
        hdot = -fdm['velocities/v-down-fps'] * FT_TO_M
        vg = fdm['velocities/vg-fps'] * FT_TO_M
        vt = fdm['velocities/vt-fps'] * FT_TO_M

        if self.h_flare > 0 and wheel_h < self.h_flare:
            # commanded sink decays linearly with height from the glide-path sink at flare entry
            hdot_ref = -vg * self.tan_gs * max(wheel_h, 0.0) / self.h_flare - self.FLARE_MIN_SINK
            dtheta = self.K_FLARE * (hdot_ref - hdot)
        else:
            h_ref = self.glide_path_height(x)
            hdot_ref = -vg * self.tan_gs
            dtheta = self.K_H * (h_ref - wheel_h) + self.K_HDOT * (hdot_ref - hdot)
        theta_cmd = tr['theta'] + min(max(dtheta, -self.THETA_AUTH), self.THETA_AUTH)

        e_theta = theta_cmd - theta
        self.int_theta = min(max(self.int_theta + e_theta * dt, -0.5), 0.5)
        elev = tr['elevator'] - (self.K_THETA * e_theta + self.K_THETA_I * self.int_theta
                                 - self.K_Q * q)
        fdm['fcs/elevator-cmd-norm'] = min(max(elev - tr['pitch_trim'], -1.0), 1.0)

        e_v = tr['airspeed'] - vt
        self.int_v = min(max(self.int_v + e_v * dt, -10.0), 10.0)
        thr = tr['throttle'] + self.K_V * e_v + self.K_V_I * self.int_v
        thr = min(max(thr, 0.0), 1.0)
        fdm['fcs/throttle-cmd-norm[0]'] = thr
        fdm['fcs/throttle-cmd-norm[1]'] = thr

        ail = -(self.K_PHI * phi + self.K_P * p)
        fdm['fcs/aileron-cmd-norm'] = min(max(ail, -1.0), 1.0)
        return thr, elev


class ApproachSimulator:
    """
    Trimmed A320 on a -3 deg glide path in periodic wind, flown to touch-down.

    >>> sim = ApproachSimulator(SimConfig()); sim.reset()
    >>> s = sim.step()        # SimState: s.t, s.q, s.tau, s.force_wind, s.touched_down, ...
    """

    def __init__(self, cfg: Optional[SimConfig] = None):
        self.cfg = (cfg or SimConfig()).validate()
        self.wind = PeriodicWind(self.cfg.wind_amplitude, self.cfg.wind_frequency,
                                 self.cfg.wind_phase, self.cfg.wind_ramp_s)
        self.fdm = None
        self.trim = None
        self.autopilot = None
        self.mass_kg = float('nan')
        self.trim_airspeed_mps = float('nan')
        self.trim_speed_kts = float('nan')
        self.threshold_m = float('nan')
        self.t = 0.0
        self.x = 0.0
        self.touched_down = False
        self._k = 0

    # ------------------------------------------------------------------ setup
    def reset(self) -> SimState:
        """(Re)load the aircraft, trim it on the glide path and return the state at t = 0."""
        cfg = self.cfg
        fdm = _new_exec(cfg)
        speed = trim_approach(fdm, cfg)
        self.fdm = fdm
        wheel_h = self._wheel_height()
        self.trim = {
            'speed_kts': speed,
            'airspeed': fdm['velocities/vt-fps'] * FT_TO_M,
            'theta': fdm['attitude/theta-rad'],
            'alpha': fdm['aero/alpha-rad'],
            'throttle': fdm['fcs/throttle-cmd-norm[0]'],
            'pitch_trim': fdm['fcs/pitch-trim-cmd-norm'],
            'elevator': fdm['fcs/elevator-cmd-norm'] + fdm['fcs/pitch-trim-cmd-norm'],
            'wheel_height_m': wheel_h,
        }
        self.trim_speed_kts = speed
        self.trim_airspeed_mps = self.trim['airspeed']
        self.mass_kg = fdm['inertia/weight-lbs'] * LB_TO_KG
        self.threshold_m = wheel_h / math.tan(math.radians(cfg.glide_slope_deg))
        self.autopilot = Autopilot(cfg, self.trim)
        self.t = 0.0
        self.x = 0.0
        self._k = 0
        self.touched_down = False
        self._apply_wind(0.0)
        return self._state()

    @property
    def weight_n(self) -> float:
        return self.mass_kg * G0

    # ------------------------------------------------------------------ stepping
    def step(self) -> SimState:
        """Advance one output period (1/rate_hz) and return the new sample."""
        if self.fdm is None:
            self.reset()
        if self.touched_down:
            return self._state()
        fdm, dt = self.fdm, self.cfg.dt
        for _ in range(self.cfg.substeps):
            self.autopilot(fdm, self.x, self._wheel_height(), dt)
            self._apply_wind(self.t)
            fdm.run()
            self._k += 1
            self.t = self._k * dt
            self.x += fdm['velocities/v-north-fps'] * FT_TO_M * dt
            if self._wheels_on_ground() or self._structure_contact():
                self.touched_down = True
                break
        return self._state()

    def run(self, max_time_s: Optional[float] = None):
        """Yield samples until touch-down (inclusive) or max_time_s."""
        limit = self.cfg.max_time_s if max_time_s is None else max_time_s
        while not self.touched_down and self.t < limit - 1e-9:
            yield self.step()

    # ------------------------------------------------------------------ internals
    def _apply_wind(self, t):
        w = self.wind(t) / FT_TO_M
        self.fdm['atmosphere/wind-north-fps'] = w[0]
        self.fdm['atmosphere/wind-east-fps'] = w[1]
        self.fdm['atmosphere/wind-down-fps'] = w[2]

    def _wheel_height(self):
        return min(self.fdm[f'gear/unit[{i}]/AGL-ft'] for i in MAIN_GEAR_UNITS) * FT_TO_M

    def _wheels_on_ground(self):
        return any(self.fdm[f'gear/unit[{i}]/WOW'] > 0.5 for i in range(3))

    def _structure_contact(self):
        n = int(self.fdm['gear/num-units'])
        return any(self.fdm[f'gear/unit[{i}]/WOW'] > 0.5 for i in range(3, n))

    def _state(self) -> SimState:
        fdm = self.fdm
        # JSBSim gives [drag, side, lift]; make it a vector in wind axes (z down).
        fw = np.array([-fdm['forces/fwx-aero-lbs'], fdm['forces/fwy-aero-lbs'],
                       -fdm['forces/fwz-aero-lbs']]) * LBF_TO_N
        fb = np.array([fdm['forces/fbx-aero-lbs'], fdm['forces/fby-aero-lbs'],
                       fdm['forces/fbz-aero-lbs']]) * LBF_TO_N
        alpha, beta = fdm['aero/alpha-rad'], fdm['aero/beta-rad']
        vt = fdm['velocities/vt-fps'] * FT_TO_M
        if self.cfg.coordinates == 'body':
            q = np.array([fdm['velocities/u-aero-fps'], fdm['velocities/v-aero-fps'],
                          fdm['velocities/w-aero-fps']]) * FT_TO_M
            tau = -fb
        else:
            q = np.array([alpha, beta, vt])
            tau = -fw
        wheel_h = self._wheel_height()
        return SimState(
            t=self.t, q=q, tau=tau, force_wind=fw, force_body=fb,
            alpha=alpha, beta=beta, airspeed=vt,
            altitude_agl_m=fdm['position/h-agl-ft'] * FT_TO_M,
            wheel_height_m=wheel_h, along_track_m=self.x,
            glide_path_error_m=wheel_h - self.autopilot.glide_path_height(self.x),
            load_factor=fdm['forces/load-factor'], nz=fdm['accelerations/Nz'],
            theta=fdm['attitude/theta-rad'], phi=fdm['attitude/phi-rad'],
            gamma=fdm['flight-path/gamma-rad'],
            wind_ned=np.array([fdm['atmosphere/total-wind-north-fps'],
                               fdm['atmosphere/total-wind-east-fps'],
                               fdm['atmosphere/total-wind-down-fps']]) * FT_TO_M,
            throttle=fdm['fcs/throttle-cmd-norm[0]'], elevator=fdm['fcs/elevator-pos-norm'],
            touched_down=self.touched_down, ground_contact=self._structure_contact()
            or self._wheels_on_ground())


def simulate_approach(cfg: Optional[SimConfig] = None, max_time_s: Optional[float] = None) -> dict:
    """
    Fly one approach offline; return numpy arrays and metadata.

    Keys: ``t`` (k,), ``q`` (k, 3), ``tau`` (k, 3), ``force_wind`` (k, 3), ``force_body`` (k, 3),
    telemetry arrays ``alpha, beta, airspeed, altitude_agl_m, wheel_height_m, along_track_m,
    glide_path_error_m, load_factor, nz, theta, phi, gamma, throttle, elevator`` (k,),
    ``wind_ned`` (k, 3), ``ground_contact`` (k,) bool; scalars ``mass_kg, weight_n,
    trim_airspeed_mps, trim_speed_kts, threshold_m, touched_down, touchdown_along_track_m``;
    ``joint_names`` and ``config`` (dict).  Sample 0 is the trimmed state at t = 0.
    """
    sim = ApproachSimulator(cfg)
    states = [sim.reset()]
    states.extend(sim.run(max_time_s))
    out = {}
    for name in SimState.__dataclass_fields__:
        vals = [getattr(s, name) for s in states]
        out[name] = np.array(vals, dtype=bool if isinstance(vals[0], (bool, np.bool_)) else float)
    out.update(
        mass_kg=sim.mass_kg, weight_n=sim.weight_n, trim_airspeed_mps=sim.trim_airspeed_mps,
        trim_speed_kts=sim.trim_speed_kts, threshold_m=sim.threshold_m,
        touched_down=bool(sim.touched_down),
        touchdown_along_track_m=float(sim.x) if sim.touched_down else float('nan'),
        joint_names=list(sim.cfg.joint_names), config=sim.cfg.to_dict(),
    )
    return out


class FrozenAero:
    """
    Aerodynamic force of the trimmed approach configuration at frozen states.

    Flaps 40 deg, gear down, elevator at its glide-path trim, zero angular rates and alpha-dot;
    JSBSim evaluates its own aerodynamic tables (``run_ic`` at the trim altitude) for every query
    point.  ``tau(Q)`` takes ``Q`` (k, 3) in the configured coordinates ([alpha, beta, V] or
    body [u, v, w]) and returns the resistive force (k, 3) with the same convention as
    ``ApproachSimulator`` (``[drag, -side, lift]`` or ``-F_body``).  Zero airspeed gives zero
    force.
    """

    def __init__(self, cfg: Optional[SimConfig] = None):
        self.cfg = (cfg or SimConfig()).validate()
        fdm = _new_exec(self.cfg)
        self.trim_speed_kts = trim_approach(fdm, self.cfg)
        self.trim_airspeed_mps = fdm['velocities/vt-fps'] * FT_TO_M
        self.trim_alpha = fdm['aero/alpha-rad']
        self.mass_kg = fdm['inertia/weight-lbs'] * LB_TO_KG
        self._elevator = fdm['fcs/elevator-cmd-norm']
        self._pitch_trim = fdm['fcs/pitch-trim-cmd-norm']
        self._h_ft = fdm['position/h-agl-ft']
        self.fdm = fdm

    def _force(self, alpha, beta, v_mps):
        """Return (F_wind, F_body) in N at one frozen state."""
        fdm = self.fdm
        fdm['ic/h-agl-ft'] = self._h_ft
        fdm['ic/vt-fps'] = v_mps / FT_TO_M
        fdm['ic/alpha-rad'] = alpha
        fdm['ic/beta-rad'] = beta
        fdm['ic/gamma-deg'] = 0.0
        fdm['ic/phi-deg'] = 0.0
        fdm['ic/p-rad_sec'] = 0.0
        fdm['ic/q-rad_sec'] = 0.0
        fdm['ic/r-rad_sec'] = 0.0
        for prop in ('atmosphere/wind-north-fps', 'atmosphere/wind-east-fps',
                     'atmosphere/wind-down-fps'):
            fdm[prop] = 0.0
        fdm['fcs/elevator-cmd-norm'] = self._elevator
        fdm['fcs/pitch-trim-cmd-norm'] = self._pitch_trim
        fdm['fcs/aileron-cmd-norm'] = 0.0
        fdm['fcs/rudder-cmd-norm'] = 0.0
        fdm.run_ic()
        fw = np.array([-fdm['forces/fwx-aero-lbs'], fdm['forces/fwy-aero-lbs'],
                       -fdm['forces/fwz-aero-lbs']]) * LBF_TO_N
        fb = np.array([fdm['forces/fbx-aero-lbs'], fdm['forces/fby-aero-lbs'],
                       fdm['forces/fbz-aero-lbs']]) * LBF_TO_N
        return fw, fb

    def tau(self, Q) -> np.ndarray:
        Q = np.atleast_2d(np.asarray(Q, float))
        if Q.ndim != 2 or Q.shape[1] != 3:
            raise ValueError(f'Q must have shape (k, 3), got {np.shape(Q)}')
        out = np.zeros_like(Q)
        body = self.cfg.coordinates == 'body'
        for i, qi in enumerate(Q):
            if body:
                u, v, w = qi
                V = math.sqrt(u * u + v * v + w * w)
                if V < 1e-6:
                    continue
                alpha, beta = math.atan2(w, u), math.asin(max(-1.0, min(1.0, v / V)))
            else:
                alpha, beta, V = qi
                if abs(V) < 1e-6:
                    continue
            fw, fb = self._force(alpha, beta, V)
            out[i] = -fb if body else -fw
        return out

    __call__ = tau

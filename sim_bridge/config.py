"""Configuration of the approach simulation (pure Python, no ROS)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
import os
from typing import Optional, Tuple

COORDINATES = ('angle', 'body')
#: Joint names published for each coordinate choice (order of q and tau).
JOINT_NAMES = {
    'angle': ('alpha', 'beta', 'airspeed'),
    'body': ('u', 'v', 'w'),
}
#: What each published effort is, per velocity name: the force that pairs with it (its unit).
#: The effort is the resistive force, so ``qd . tau`` is the dissipated power.
FORCE_NAMES = {
    'alpha': 'drag (N)', 'beta': 'side force, -Y (N)', 'airspeed': 'lift (N)',
    'u': 'force -X body (N)', 'v': 'force -Y body (N)', 'w': 'force -Z body (N)',
}
#: The paper's bound on the wind magnitude per axis (m/s).
MAX_WIND_MPS = 25.0

#: Default wind amplitudes [north (along the runway), east (cross), down] in m/s: the largest
#: that keep the A320 flyable at 180 kt (see the sim_bridge package docstring for the sweep).
#: Cross-wind keeps the paper's 25 m/s; 25 m/s along the runway at 0.1 Hz swings the airspeed by
#: +-30 % (stall at the low end) and 25 m/s vertical at 0.3 Hz swings alpha by +-9 deg around trim
#: (stall, > 2 g), so those axes are reduced to 5 and 10 m/s.
DEFAULT_WIND_AMPLITUDE = (5.0, 25.0, 10.0)
DEFAULT_WIND_FREQUENCY = (0.1, 0.2, 0.3)
DEFAULT_WIND_PHASE = (0.0, 2.0, 3.0)


def _triple(name, value):
    try:
        vals = tuple(float(v) for v in value)
    except TypeError:
        raise ValueError(f'{name} must be a sequence of 3 numbers, got {value!r}') from None
    except ValueError:
        raise ValueError(f'{name} must contain numbers only, got {value!r}') from None
    if len(vals) != 3:
        raise ValueError(f'{name} must have exactly 3 entries (north, east, down), '
                         f'got {len(vals)}')
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f'{name} must be finite, got {vals}')
    return vals


@dataclass
class SimConfig:
    """
    Everything that defines one approach; two equal configs give bit-identical runs.

    Wind (m/s) per axis i of the local runway frame (north = along the runway, the aircraft flies
    heading 0; east = cross-wind; down): ``w_i(t) = r(t) * A_i * sin(2 pi f_i t + phi_i)`` with a
    smooth cosine ramp ``r`` from 0 to 1 over ``wind_ramp_s`` (0 disables the ramp), so the trimmed
    aircraft is not hit by a step gust at t = 0.
    """

    coordinates: str = 'angle'
    rate_hz: float = 60.0
    wind_amplitude: Tuple[float, float, float] = DEFAULT_WIND_AMPLITUDE
    wind_frequency: Tuple[float, float, float] = DEFAULT_WIND_FREQUENCY
    wind_phase: Tuple[float, float, float] = DEFAULT_WIND_PHASE
    wind_ramp_s: float = 5.0
    aircraft: str = 'A320'
    #: Calibrated airspeed the approach is trimmed and flown at (kt).  The A320 model trims with
    #: full flaps from 160 kt up (it runs out of nose-up elevator below); 180 kt leaves ~half the
    #: elevator authority for gusts.  If the trim fails, faster speeds are tried (+5 kt steps).
    approach_speed_kts: float = 180.0
    glide_slope_deg: float = 3.0
    start_height_ft: float = 1000.0
    #: Main-wheel height (ft) where the flare starts; 0 disables the flare.
    flare_height_ft: float = 60.0
    #: Internal JSBSim rate (Hz); each output sample integrates ceil(integration_hz/rate_hz) steps.
    integration_hz: float = 120.0
    #: Safety stop (simulated s) if no touch-down happens.
    max_time_s: float = 200.0
    #: JSBSim root (aircraft/, engine/, systems/); None = the data shipped in the jsbsim wheel.
    root_dir: Optional[str] = None

    def __post_init__(self):
        # Normalise sequences to tuples so configs compare and serialise cleanly.
        for name in ('wind_amplitude', 'wind_frequency', 'wind_phase'):
            val = getattr(self, name)
            try:
                setattr(self, name, tuple(float(v) for v in val))
            except (TypeError, ValueError):
                pass  # validate() reports it

    # ------------------------------------------------------------------ validation
    def validate(self) -> 'SimConfig':
        """Raise ValueError with a clear message on the first invalid field; return self."""
        if self.coordinates not in COORDINATES:
            raise ValueError(f'coordinates must be one of {COORDINATES}, got {self.coordinates!r}')
        for name in ('rate_hz', 'integration_hz'):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 < v <= 1000:
                raise ValueError(f'{name} must be a number in (0, 1000] Hz, got {v!r}')
        amp = _triple('wind_amplitude', self.wind_amplitude)
        if any(abs(a) > MAX_WIND_MPS for a in amp):
            raise ValueError(f'wind_amplitude must be within +-{MAX_WIND_MPS} m/s per axis, '
                             f'got {amp}')
        freq = _triple('wind_frequency', self.wind_frequency)
        if any(f < 0 or f > 10 for f in freq):
            raise ValueError(f'wind_frequency must be in [0, 10] Hz per axis, got {freq}')
        _triple('wind_phase', self.wind_phase)
        if not math.isfinite(self.wind_ramp_s) or self.wind_ramp_s < 0:
            raise ValueError(f'wind_ramp_s must be >= 0 s, got {self.wind_ramp_s!r}')
        if not isinstance(self.aircraft, str) or not self.aircraft.strip():
            raise ValueError(f'aircraft must be a non-empty model name, got {self.aircraft!r}')
        model = os.path.join(self.jsbsim_root(), 'aircraft', self.aircraft, self.aircraft + '.xml')
        if not os.path.isfile(model):
            raise ValueError(f'aircraft {self.aircraft!r} not found: no JSBSim model at {model}')
        if not 100 <= self.approach_speed_kts <= 300:
            raise ValueError(f'approach_speed_kts must be in [100, 300] kt, '
                             f'got {self.approach_speed_kts!r}')
        if not 1 <= self.glide_slope_deg <= 6:
            raise ValueError(f'glide_slope_deg must be in [1, 6] deg, '
                             f'got {self.glide_slope_deg!r}')
        if not 200 <= self.start_height_ft <= 5000:
            raise ValueError(f'start_height_ft must be in [200, 5000] ft, '
                             f'got {self.start_height_ft!r}')
        if not 0 <= self.flare_height_ft < self.start_height_ft / 2:
            raise ValueError('flare_height_ft must be in [0, start_height_ft/2), '
                             f'got {self.flare_height_ft!r}')
        if not math.isfinite(self.max_time_s) or self.max_time_s <= 0:
            raise ValueError(f'max_time_s must be > 0 s, got {self.max_time_s!r}')
        return self

    # ------------------------------------------------------------------ helpers
    def jsbsim_root(self) -> str:
        if self.root_dir:
            return self.root_dir
        import jsbsim
        return jsbsim.get_default_root_dir()

    @property
    def joint_names(self) -> Tuple[str, str, str]:
        return JOINT_NAMES.get(self.coordinates, JOINT_NAMES['angle'])

    @property
    def substeps(self) -> int:
        return max(1, math.ceil(self.integration_hz / self.rate_hz - 1e-9))

    @property
    def dt(self) -> float:
        """Get the JSBSim integration step (s)."""
        return 1.0 / (self.rate_hz * self.substeps)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    def replace(self, **changes) -> 'SimConfig':
        return dataclasses.replace(self, **changes)

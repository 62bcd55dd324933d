"""
Export one simulated approach to .npz: ``python -m sim_bridge.export --out FILE.npz``.

Arrays: t (k,), q (k, 3), tau (k, 3), force_wind (k, 3) plus telemetry; metadata: mass_kg,
trim_airspeed_mps, joint_names, config (JSON string of SimConfig).
"""
import argparse
import json
import sys

import numpy as np

from .config import SimConfig
from .simulator import simulate_approach


def _triple(text):
    vals = [float(v) for v in text.split(',')]
    if len(vals) != 3:
        raise argparse.ArgumentTypeError('expected three comma-separated numbers')
    return tuple(vals)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m sim_bridge.export',
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                 description=__doc__.split('\n')[0])
    ap.add_argument('--out', required=True, help='output .npz file')
    ap.add_argument('--coordinates', choices=['angle', 'body'], default='angle',
                    help='velocities as [alpha, beta, airspeed] or body-axis [u, v, w]')
    ap.add_argument('--rate-hz', type=float, default=60.0, help='samples a second written')
    ap.add_argument('--wind-amplitude', type=_triple, default=None, metavar='AN,AE,AD',
                    help='wind amplitudes north,east,down (m/s)')
    args = ap.parse_args(argv)
    kw = {'coordinates': args.coordinates, 'rate_hz': args.rate_hz}
    if args.wind_amplitude is not None:
        kw['wind_amplitude'] = args.wind_amplitude
    try:
        cfg = SimConfig(**kw).validate()
    except ValueError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    data = simulate_approach(cfg)
    arrays = {k: v for k, v in data.items() if isinstance(v, np.ndarray)}
    np.savez(args.out, **arrays,
             mass_kg=np.float64(data['mass_kg']),
             trim_airspeed_mps=np.float64(data['trim_airspeed_mps']),
             threshold_m=np.float64(data['threshold_m']),
             joint_names=np.array(data['joint_names']),
             config=np.array(json.dumps(data['config'])))
    print(f"wrote {args.out}: {len(data['t'])} samples, {data['t'][-1]:.1f} s, "
          f"touched_down={data['touched_down']}")
    return 0


if __name__ == '__main__':
    sys.exit(main())

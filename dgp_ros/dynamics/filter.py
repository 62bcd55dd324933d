"""
Joint acceleration from the measured velocity, centred on the sample it is paired with.

The friction residual ``effort - tau_rb(q, qd, qdd)`` needs ``qdd`` at the *same* instant as the
effort and velocity of the sample. A causal differentiator (finite difference plus low-pass) is
late by its group delay, and on a 1 kHz stream with inertias of a few kg m^2 even a few ms of lag
turn into large torque errors during fast reversals. So :class:`AccelFilter` fits a local
polynomial (Savitzky-Golay-like, but on the actual, jittered stamps) to the velocity samples in
``[t_c - h, t_c + h]`` by weighted least squares and takes its derivative at ``t_c``: no lag; the
price is that the answer for ``t_c`` exists once the stream has reached ``t_c + h``, i.e. the
output trails the input by the half window ``h`` (at most :data:`MAX_DELAY_S`).

Cost: appending a sample is a few array writes; the fit (about ``2 h`` times the rate samples) is
done only for the samples pushed with ``want=True`` (the estimator learns at most one sample per
10 ms, so the other 9 of 10 cost nearly nothing).

Default half window :data:`DEFAULT_HALF_WINDOW_S` = 20 ms, by measurement on the simulated Panda
(``arm_sim.simulate_arm``: 1 kHz, velocity noise 0.003 rad/s, torque noise 0.3 N m; order 2,
uniform weights, one wanted sample in 10). RMS error of ``qdd_hat`` [rad/s^2] / of the residual
against the true friction + bias [N m]; 0.3 N m, the torque noise, is the floor:

=================================  ===========  ===========  ===========  ===========  ===========
h [s]                              0.005        0.01         0.02         0.04         0.08
=================================  ===========  ===========  ===========  ===========  ===========
slow (0.1 Hz base, <= 4.6 rad/s^2)  0.35 / 0.59  0.12 / 0.34  0.04 / 0.31  0.01 / 0.30  0.01 / 0.30
fast (0.4 Hz base, <= 19 rad/s^2)   0.35 / 0.67  0.12 / 0.36  0.05 / 0.31  0.13 / 0.38  0.49 / 0.94
=================================  ===========  ===========  ===========  ===========  ===========

Short windows pass the velocity noise (variance ~ 1 / h^3), long ones bend fast motion (bias
~ h^2 times the third derivative of qd); 20 ms stays within 5 % of the floor in both cases (the
fast one is about the Panda's acceleration limits) with a 20 ms delay. Uniform weights beat
Epanechnikov and tricube here (noise-limited). Order 3 with h = 40 ms does as well on both and
better with noisier velocities, at twice the delay and fit cost.

**Sized from the stream's rate.** A window in seconds holds few samples of a slow stream: the
estimator's 50 ms hold 3 samples of a 30 Hz ``/joint_states`` stream, fewer than the fit needs,
so every sample was dropped and nothing was ever learned. The filter measures the stream's
sample interval (the median of the last :data:`RATE_SAMPLES` intervals, ``sample_interval_s``)
and uses ``max(half_window_s, MIN_SIDE_SAMPLES x interval)`` (at most :data:`MAX_DELAY_S`;
``effective_half_window_s``); a gap restarts it only beyond ``max(max_gap_s, 4 x interval)``.
Below ``MIN_SIDE_SAMPLES / MAX_DELAY_S`` (15 Hz) the window holds fewer samples than that, and
below 2 per side (10 Hz) the estimate is no better than a difference quotient of its neighbours
(``too_slow`` says so: the residual's acceleration term is then noise).
"""
from __future__ import annotations

from collections import deque
import math
from typing import Any, NamedTuple

import numpy as np

__all__ = ['AccelFilter', 'AccelSample', 'DEFAULT_HALF_WINDOW_S', 'MAX_DELAY_S', 'KERNELS',
           'MIN_SIDE_SAMPLES']

DEFAULT_HALF_WINDOW_S = 0.02
MAX_DELAY_S = 0.2
#: samples on each side of the centre the window holds at least (at the measured rate)
MIN_SIDE_SAMPLES = 3
#: sample intervals the rate is measured over (their median)
RATE_SAMPLES = 64

# weight of a sample at normalized offset u = (t - t_c) / h, |u| <= 1
KERNELS = {
    'uniform': None,   # all ones (Savitzky-Golay); None skips the multiplication
    'epanechnikov': lambda u: 1.0 - u * u,
    'tricube': lambda u: (1.0 - np.abs(u) ** 3) ** 3,
}


class AccelSample(NamedTuple):
    """One output of :class:`AccelFilter` (all arrays (N,))."""

    t: float
    """Stamp of the centre sample [s]."""
    qd: np.ndarray
    """Measured velocity at ``t`` (as pushed) [rad/s]."""
    qdd: np.ndarray
    """Acceleration estimate at ``t`` [rad/s^2]: derivative of the local fit."""
    qd_smooth: np.ndarray
    """Velocity of the local fit at ``t`` [rad/s]."""
    payload: Any
    """What was pushed with the sample (e.g. its position and effort)."""


class AccelFilter:
    """
    Streaming centred local-polynomial differentiator of joint velocities.

    Parameters
    ----------
    half_window_s : float
        Least half window ``h`` [s], in (0, :data:`MAX_DELAY_S`]. The output for a sample comes
        when the first sample at or after ``t_c + h`` arrives. It is widened to hold
        :data:`MIN_SIDE_SAMPLES` samples per side at the measured rate (module docstring).
    order : int
        Degree of the local polynomial in t, 1 to 4. On a symmetric window the derivative of
        degrees 1 and 2 (or 3 and 4) coincide; 2 keeps it so on jittered stamps.
    max_gap_s : float
        A stamp more than this (or 4 measured sample intervals, if more) after the previous one
        restarts the filter [s]; so does a stamp before the previous one.
    kernel : str
        Weights over the window, a key of :data:`KERNELS` (``'uniform'`` is Savitzky-Golay's).

    Notes
    -----
    Counters: ``samples_in`` (pushed), ``samples_out`` (returned), ``restarts`` (backwards stamps
    and gaps), ``rejected`` (non-finite or repeated stamps, ignored), ``dropped`` (wanted samples
    that got no estimate: within ``h`` of a (re)start, pending at a restart, a window with a side
    empty or fewer than ``order + 2`` samples, or a non-finite result).

    """

    def __init__(self, half_window_s: float = DEFAULT_HALF_WINDOW_S, order: int = 2,
                 max_gap_s: float = 0.1, kernel: str = 'uniform'):
        if not 0.0 < half_window_s <= MAX_DELAY_S:
            raise ValueError(f'half_window_s must be in (0, {MAX_DELAY_S}] s (it is the delay), '
                             f'got {half_window_s}')
        if int(order) != order or not 1 <= order <= 4:
            raise ValueError(f'order must be an integer in 1..4, got {order}')
        if not max_gap_s > 0.0:
            raise ValueError(f'max_gap_s must be > 0, got {max_gap_s}')
        if kernel not in KERNELS:
            raise ValueError(f'kernel must be one of {sorted(KERNELS)}, got {kernel!r}')
        self.half_window_s = float(half_window_s)
        self.order = int(order)
        self.max_gap_s = float(max_gap_s)
        self.kernel = kernel
        self._weight = KERNELS[kernel]
        self._rhs = np.eye(self.order + 1)[:, :2]
        self.samples_in = self.samples_out = self.restarts = self.rejected = self.dropped = 0
        self._nj: int | None = None
        self._t = np.empty(0)
        self._v = np.empty((0, 0))
        self._dts: deque = deque(maxlen=RATE_SAMPLES)
        self._dt = 0.0
        self._n_dt = 0
        self.reset()

    @property
    def sample_interval_s(self) -> float:
        """Return the stream's measured sample interval [s] (median of the last; 0 before two)."""
        return self._dt

    @property
    def effective_half_window_s(self) -> float:
        """Return the half window in use [s]: ``half_window_s`` widened to the measured rate."""
        return min(MAX_DELAY_S, max(self.half_window_s, MIN_SIDE_SAMPLES * self._dt))

    @property
    def too_slow(self) -> bool:
        """Tell whether the longest window holds fewer than 2 samples per side (module doc)."""
        return 2.0 * self._dt > MAX_DELAY_S * (1.0 + 1e-9)

    @property
    def delay_s(self) -> float:
        """How long the output trails the input [s] (the effective half window)."""
        return self.effective_half_window_s

    @property
    def pending(self) -> int:
        """Wanted samples waiting for the end of their window."""
        return len(self._pending)

    def reset(self) -> None:
        """Forget the stream (pending samples are lost; counters are kept, nothing is counted)."""
        self._n = 0
        self._start = -math.inf   # first stamp of the current segment
        self._pending: deque = deque()

    def _restart(self) -> None:
        self.restarts += 1
        self.dropped += len(self._pending)
        self.reset()

    def _append(self, t: float, qd: np.ndarray) -> None:
        """Store one sample, dropping samples no pending window needs when the buffer is full."""
        n = self._n
        if n == self._t.size:
            oldest = self._pending[0][0] if self._pending else t
            lo = int(np.searchsorted(self._t[:n], oldest - self.effective_half_window_s, 'left'))
            keep = n - lo
            cap = self._t.size if keep < self._t.size // 2 else 2 * max(self._t.size, 32)
            t_buf, v_buf = np.empty(cap), np.empty((cap, self._nj))
            t_buf[:keep] = self._t[lo:n]
            v_buf[:keep] = self._v[lo:n]
            self._t, self._v, n = t_buf, v_buf, keep
        self._t[n] = t
        self._v[n] = qd
        self._n = n + 1

    def push(self, t: float, qd, want: bool = True, payload: Any = None) -> list[AccelSample]:
        """
        Add one velocity sample; return the wanted samples whose window is now complete.

        Parameters
        ----------
        t : float
            Stamp [s]; increasing (see ``max_gap_s`` for what restarts the filter).
        qd : array_like, (N,)
            Measured joint velocities [rad/s]. N is fixed by the first push.
        want : bool
            Whether this sample needs an estimate. Unwanted samples only join the windows of the
            others (a few array writes, no fit).
        payload : object
            Returned with this sample's estimate (e.g. its position and effort).

        Returns
        -------
        list of AccelSample
            In stamp order; usually zero or one, each ``delay_s`` or a little more behind ``t``.

        Raises
        ------
        ValueError
            ``qd`` not of shape (N,).

        """
        self.samples_in += 1
        qd = np.asarray(qd, dtype=float)
        if self._nj is None:
            if qd.ndim != 1:
                raise ValueError(f'qd must have shape (N,), got {qd.shape}')
            self._nj = qd.shape[0]
            self._v = np.empty((0, self._nj))
        elif qd.shape != (self._nj,):
            raise ValueError(f'qd must have shape ({self._nj},), got {qd.shape}')
        t = float(t)
        if not math.isfinite(t):
            self.rejected += 1
            return []
        if self._n:
            last = self._t[self._n - 1]
            if t == last:
                self.rejected += 1
                return []
            if last < t:
                self._note_interval(t - last)
            if t < last or t - last > max(self.max_gap_s, 4.0 * self._dt):
                self._restart()
        if not self._n:
            self._start = t
        self._append(t, qd)
        if want:
            self._pending.append((t, qd.copy(), payload))
        out: list[AccelSample] = []
        h = self.effective_half_window_s
        while self._pending and self._pending[0][0] + h <= t:
            tc, qd_c, pl = self._pending.popleft()
            fit = self._fit(tc)
            if fit is None:
                self.dropped += 1
                continue
            out.append(AccelSample(tc, qd_c, fit[1], fit[0], pl))
        self.samples_out += len(out)
        return out

    def _note_interval(self, dt: float) -> None:
        """Take one sample interval into the measured rate (median, refreshed every 8)."""
        self._dts.append(dt)
        self._n_dt += 1
        if self._n_dt <= 8 or self._n_dt % 8 == 0:
            self._dt = float(np.median(self._dts))

    def _fit(self, tc: float) -> np.ndarray | None:
        """(fitted velocity, derivative) at ``tc``, (2, N), or None if the window is unusable."""
        h = self.effective_half_window_s
        if tc - h < self._start:
            return None
        t = self._t[:self._n]
        lo = int(np.searchsorted(t, tc - h, 'left'))
        hi = int(np.searchsorted(t, tc + h, 'right'))
        u = (t[lo:hi] - tc) / h
        if hi - lo < self.order + 2 or u[0] >= 0.0 or u[-1] <= 0.0:
            return None
        V = np.empty((u.size, self.order + 1))          # Vandermonde in u, (n, p)
        V[:, 0] = 1.0
        for k in range(1, self.order + 1):
            np.multiply(V[:, k - 1], u, out=V[:, k])
        Vw = V if self._weight is None else V * self._weight(u)[:, None]
        # first two columns of (V^T W V)^-1 (symmetric), then rows 0, 1 of the fit operator
        G = (Vw @ np.linalg.solve(Vw.T @ V, self._rhs)).T   # (2, n)
        coef = G @ self._v[lo:hi]                           # (2, N): value, d/du
        coef[1] /= h
        if not np.isfinite(coef).all():
            return None
        return coef
